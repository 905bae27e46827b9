"""The HTML report and the terminal summary on the SITL demo log."""
from __future__ import annotations

import base64
import json
import re
import shutil
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

pytest.importorskip("matplotlib")

from mavcal.ardupilot.gates import Gate, GateReport  # noqa: E402
from mavcal.errors import UsageError  # noqa: E402
from mavcal.pipeline import calibrate_source  # noqa: E402
from mavcal.report import FIGURE_NAMES, interval_stats, summary_text, write_html  # noqa: E402

USED_RGB = (0x2E, 0x7D, 0x32)  # report._USED: the opaque interval strip of the timeline
UNUSED_RGB = (0xEF, 0x6C, 0x00)


@pytest.fixture(scope="module")
def run(sitl_dir):
    return calibrate_source(str(sitl_dir / "sitl01.tlog"))


@pytest.fixture(scope="module")
def report(run, tmp_path_factory):
    d = tmp_path_factory.mktemp("report")
    path = write_html(run, d / "sitl01.html", png_dir=d / "png")
    return path, d / "png", path.read_text(encoding="utf-8")


def _attr(text: str, name: str) -> int:
    m = re.search(name + r"=['\"](\d+)['\"]", text)
    assert m, f"{name} missing"
    return int(m.group(1))


def test_report_is_self_contained(report):
    path, _, text = report
    assert path.name == "sitl01.html"
    assert text.startswith("<!DOCTYPE html>")
    low = re.sub(r"base64,[A-Za-z0-9+/=]+", "base64,", text).lower()
    assert "http" not in low and "file:" not in low
    assert "<script" not in low and "<link" not in low and "@import" not in low and "url(" not in low
    srcs = re.findall(r"src=['\"]([^'\"]{0,40})", text)
    assert len(srcs) == len(FIGURE_NAMES)
    assert all(s.startswith("data:image/png;base64,") for s in srcs), srcs
    assert text.count("data:image/png;base64,") == len(FIGURE_NAMES)


def test_report_content(run, report):
    _, _, text = report
    n = len(run.segmentation.intervals)
    assert n == 21  # the SITL demo log: 20 dance poses + the final rest
    assert _attr(text, "data-intervals") == n
    assert _attr(text, "data-intervals-used") == len(run.intervals_used)
    assert _attr(text, "data-shaded-spans") == n
    assert f"{n} still intervals found" in text
    for name in run.mapping.new:
        assert name in text
    # every changed parameter is highlighted: one 'changed' row per changed value
    changed = sum(1 for k, v in run.mapping.new.items()
                  if run.mapping.old.get(k) is None or np.float32(v) != np.float32(run.mapping.old[k]))
    assert changed > 0
    assert text.count("<tr class='changed'>") == changed
    assert "ACCEPTED" in text and "REJECTED" not in text
    assert f"{run.quality.heading_95_deg:.3f}" in text
    assert run.calibration.model in text
    assert "dropped terms" in text
    for w in run.warnings:
        assert w in text


def test_pngs_match_embedded_images(report):
    _, png_dir, text = report
    embedded = [base64.b64decode(b) for b in re.findall(r"data:image/png;base64,([A-Za-z0-9+/=]+)", text)]
    for name, data in zip(FIGURE_NAMES, embedded):
        f = png_dir / f"{name}.png"
        assert f.is_file()
        raw = f.read_bytes()
        assert raw[:8] == b"\x89PNG\r\n\x1a\n"
        assert raw == data


def _runs_of_colour(img: np.ndarray, rgb) -> int:
    """Most runs of ``rgb`` along any pixel row of an RGB(A) float image."""
    target = np.array(rgb) / 255.0
    hit = np.all(np.abs(img[:, :, :3] - target) < 1.5 / 255, axis=2)
    edges = np.diff(hit.astype(np.int8), axis=1, prepend=0)
    return int((edges == 1).sum(axis=1).max())


def test_timeline_figure_shows_the_intervals(run, report, tmp_path):
    import matplotlib.image as mpimg

    img = mpimg.imread(report[1] / "timeline.png")
    assert _runs_of_colour(img, USED_RGB) == len(run.intervals_used) == 21
    assert _runs_of_colour(img, UNUSED_RGB) == 0
    # the last three intervals left out of the fit are drawn apart
    part = replace(run, intervals_used=run.intervals_used[:-3])
    text = write_html(part, tmp_path / "part.html", png_dir=tmp_path).read_text()
    img = mpimg.imread(tmp_path / "timeline.png")
    assert _runs_of_colour(img, USED_RGB) == 18
    assert _runs_of_colour(img, UNUSED_RGB) == 3
    assert _attr(text, "data-intervals") == 21 and _attr(text, "data-intervals-used") == 18
    assert _attr(text, "data-shaded-spans") == 21


def test_interval_stats_before_and_after(run):
    st = interval_stats(run)
    n = len(run.segmentation.intervals)
    assert len(st) == n and st.used.sum() == len(run.intervals_used)
    # the SITL log was recorded with a deliberately wrong calibration: |a| and |B| as
    # logged vary from pose to pose; through the new parameters they are constant
    dev_a_before = np.sqrt(np.nanmean((st.accel_before - 9.80665) ** 2))
    dev_a_after = np.sqrt(np.nanmean((st.accel_after - 9.80665) ** 2))
    dev_m_before = np.sqrt(np.nanmean((st.mag_before - st.field_target_mgauss) ** 2))
    dev_m_after = np.sqrt(np.nanmean((st.mag_after - st.field_target_mgauss) ** 2))
    assert dev_a_before > 0.2 and dev_a_after < 0.01
    assert dev_m_before > 50 and dev_m_after < 1.0
    assert 500 < st.field_target_mgauss < 650  # WMM at CMAC
    # residuals: finite for used intervals, of the order of the noise of the means
    used = st.used
    assert np.isfinite(st.accel_resid_sigma[used]).all() and np.isfinite(st.mag_resid_sigma[used]).all()
    assert 0.3 < np.median(st.accel_resid_norm[used]) < 10
    assert 0.3 < np.median(st.mag_resid_norm[used]) < 10


def test_summary_text(run):
    s = summary_text(run)
    assert "21 of 21 still intervals used" in s
    assert "heading error <=" in s and "95 % confidence" in s
    for name in run.mapping.new:  # vectors are shown together as NAME_XYZ
        assert name in s or (name[:-2] + "_XYZ") in s
    assert "ACCEPTED" in s
    assert len(s.splitlines()) < 40


def test_failed_gate_reasons_shown(run, tmp_path):
    bad = Gate("compass0", "offsets", False, 2500.0, "<= 1800 mGauss", "compass offset length too big for the test")
    rejected = replace(run, gates=GateReport(run.gates.gates + (bad,)))
    text = write_html(rejected, tmp_path / "r.html").read_text()
    assert "REJECTED" in text and "compass offset length too big for the test" in text
    assert "<tr class='fail'>" in text
    s = summary_text(rejected)
    assert "REJECTED" in s and "compass0 offsets: compass offset length too big for the test" in s
    assert not list(tmp_path.glob("*.png"))  # no png_dir, no PNG files


def test_unwritable_path_is_a_usage_error(run, tmp_path):
    with pytest.raises(UsageError, match="cannot write the report"):
        write_html(run, tmp_path / "no" / "such" / "dir" / "r.html")


def test_without_matplotlib_a_usage_error(run, tmp_path, monkeypatch):
    for mod in ("matplotlib", "matplotlib.figure", "matplotlib.backends.backend_agg"):
        monkeypatch.setitem(sys.modules, mod, None)
    with pytest.raises(UsageError, match=r"pip install 'mavcal\[plots\]'") as ei:
        write_html(run, tmp_path / "r.html")
    assert ei.value.exit_code == 2
    assert not (tmp_path / "r.html").exists()


# --------------------------------------------------------------------------- browser

_PROBE = """<script>
window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.querySelectorAll('figure img'));
  document.body.setAttribute('data-probe', JSON.stringify(imgs.map(function (i) {
    return [i.complete, i.naturalWidth, i.naturalHeight, i.getBoundingClientRect().width];
  })));
});
</script>"""


def _chromium(args, tmp_path, timeout=60):
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        pytest.skip("chromium not installed (apt-get install chromium)")
    base = [exe, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
            "--disable-component-update", "--disable-sync", "--no-first-run", "--enable-logging=stderr", "--v=0",
            f"--user-data-dir={tmp_path / 'chromium-profile'}"]
    return subprocess.run(base + args, capture_output=True, text=True, timeout=timeout)


def _page_errors(stderr: str):
    """Console messages and failed loads of the page (not chromium's own dbus/GPU chatter)."""
    return [ln for ln in stderr.splitlines()
            if "CONSOLE" in ln or "net::ERR" in ln or "Not allowed to load" in ln or "Failed to load" in ln]


def test_report_opens_in_headless_chromium(report, tmp_path):
    path, png_dir, text = report
    probe = tmp_path / "probe.html"
    probe.write_text(text.replace("</body>", _PROBE + "</body>"), encoding="utf-8")
    p = _chromium(["--window-size=1400,3000", "--virtual-time-budget=5000", "--dump-dom", probe.as_uri()], tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    assert _page_errors(p.stderr) == []
    dom = p.stdout
    for name in FIGURE_NAMES:
        assert f'id="fig-{name}"' in dom
    m = re.search(r'data-probe="([^"]*)"', dom)
    assert m, "the page's load event did not run"
    imgs = json.loads(m.group(1).replace("&quot;", '"'))
    assert len(imgs) == len(FIGURE_NAMES)
    for complete, w, h, shown in imgs:
        assert complete and w > 500 and h > 300 and shown > 300  # decoded and laid out

    shot = tmp_path / "shot.png"
    p = _chromium(["--window-size=1400,3000", "--hide-scrollbars", f"--screenshot={shot}", path.as_uri()], tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    assert _page_errors(p.stderr) == []
    import matplotlib.image as mpimg

    img = mpimg.imread(shot)
    assert img.shape[0] == 3000 and img.shape[1] == 1400
    # the timeline's interval strip is on screen (green of the used intervals)
    target = np.array(USED_RGB) / 255.0
    assert np.all(np.abs(img[:, :, :3] - target) < 3 / 255, axis=2).sum() > 5000
