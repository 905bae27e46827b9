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

from mavcal.autopilot.gates import Gate, GateReport  # noqa: E402
from mavcal.errors import UsageError  # noqa: E402
from mavcal.pipeline import calibrate_source  # noqa: E402
from mavcal.report import FIGURE_NAMES, interval_numbers, summary_text, write_html  # noqa: E402

USED_RGB = (0x2E, 0x7D, 0x32)  # report.figures.USED_COLOUR: the opaque interval strip of the timeline
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


def test_interval_numbers_before_and_after(run):
    st = interval_numbers(run)
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
    # the verdict first, its reasons under it (said once: no second list at the end)
    lines = s.splitlines()
    k = lines.index("compass0: REJECTED")
    assert lines[k + 1].strip().startswith("offsets: compass offset length too big for the test")
    assert s.count("compass offset length too big for the test") == 1
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


# --------------------------------------------------------------------------- JSON both ways

def _same(a, b) -> bool:
    return np.array_equal(np.asarray(a, float), np.asarray(b, float), equal_nan=True)


def test_json_round_trip_loads_the_same_objects(run):
    from mavcal.report.json import FORMAT_VERSION, from_json, to_json

    doc = json.loads(json.dumps(to_json(run)))  # through text, as on disk
    assert doc["format"] == "mavcal report v1" and doc["format_version"] == FORMAT_VERSION
    saved = from_json(doc)
    cal, sc = run.calibration, saved.calibration
    assert sc == cal  # gains, biases, noise covariances, field, orientations, cost, model
    for name in ("param_cov", "n_accel", "n_mag"):
        assert _same(getattr(sc, name), getattr(cal, name)), name
    assert sc.param_names == cal.param_names and sc.dof == cal.dof and sc.iterations == cal.iterations
    assert sc.method == cal.method and sc.model_reason == cal.model_reason and sc.converged == cal.converged
    assert dict(saved.mapping.new) == {n: float(v) for n, v in run.mapping.new.items()}
    assert dict(saved.mapping.old) == dict(run.mapping.old)
    assert saved.mapping.notes == tuple(run.mapping.notes)
    assert saved.mapping.reboot_required == run.mapping.reboot_required
    assert saved.mapping.changed() == run.mapping.changed()
    for k, v in run.quality.__dict__.items():
        assert _same(getattr(saved.quality, k), v), k
    assert len(saved.gates.gates) == len(run.gates.gates) and saved.gates.passed == run.gates.passed
    for g, h in zip(saved.gates.gates, run.gates.gates):
        assert (g.sensor, g.name, g.ok, g.limit, g.reason) == (h.sensor, h.name, h.ok, h.limit, h.reason)
        assert _same(g.value, h.value)
    assert saved.accepted == run.accepted and saved.source == run.source
    assert [(i.start_s, i.end_s, i.used) for i in saved.intervals] == \
        [(iv.start_s, iv.end_s, k in run.intervals_used) for k, iv in enumerate(run.segmentation.intervals)]
    assert [dict(i.samples_accel) for i in saved.intervals] == [iv.n_accel for iv in run.segmentation.intervals]
    # and back again: the loaded objects give the same document
    assert to_json(run)["parameters"] == doc["parameters"]


def test_json_file_round_trip_and_bad_documents(run, tmp_path):
    from mavcal.errors import SourceError
    from mavcal.report.json import read_json, to_json, write_json

    p = write_json(run, tmp_path / "cal.json")
    saved = read_json(p)
    assert saved.calibration == run.calibration and saved.format_version == 2
    with pytest.raises(SourceError):
        read_json(tmp_path / "missing.json")
    (tmp_path / "other.json").write_text('{"format": "something else"}')
    with pytest.raises(SourceError, match="not a mavcal JSON report"):
        read_json(tmp_path / "other.json")
    doc = to_json(run)
    doc["format_version"] = 99
    with pytest.raises(SourceError, match="newer"):
        from mavcal.report.json import from_json
        from_json(doc)


def test_json_format_1_loads_with_diagonal_noise(run):
    from mavcal.report.json import from_json, to_json

    doc = json.loads(json.dumps(to_json(run)))
    del doc["format_version"]
    for k in ("accel_noise_cov", "mag_noise_cov", "gravity", "orientations", "iterations", "block_iterations",
              "refine_iterations", "param_names", "param_cov", "n_accel", "n_mag"):
        del doc["calibration"][k]
    saved = from_json(doc)
    assert saved.format_version == 1
    np.testing.assert_allclose(saved.calibration.accel.gain, run.calibration.accel.gain)
    np.testing.assert_allclose(np.diag(saved.calibration.mag.noise_cov), np.diag(run.calibration.mag.noise_cov))
    assert saved.calibration.orientations.shape == (0, 3, 3) and saved.calibration.param_cov is None


def test_run_to_json_method_is_the_report(run):
    from mavcal.report.json import to_json

    assert run.to_json()["parameters"] == to_json(run)["parameters"]


# --------------------------------------------------------------------------- write texts

class _R:  # a ParamResult stand-in
    def __init__(self, name, old, expected, changed=True, ok=True, attempts=1, restored=None):
        self.name, self.old, self.expected, self.changed = name, old, expected, changed
        self.ok, self.attempts, self.restored = ok, attempts, restored


def test_write_texts():
    from mavcal.errors import ParamWriteError, RestoreFailedError
    from mavcal.report.text import param_table, plan_text, write_done_text, write_failed_text

    rows = [_R("COMPASS_OFS_X", 1.0, 12.5), _R("COMPASS_OFS_Y", 2.0, 2.0, changed=False, attempts=0)]
    t = param_table(rows)
    assert t.splitlines()[0].startswith("PARAMETER") and "-> 12.5" in t and "unchanged" in t and "ok" in t
    assert param_table([]) == ""

    class Plan:
        results = rows
        changed = rows[:1]

    assert "dry run: 1 of 2 parameters would change" in plan_text(Plan, dry_run=True)
    assert plan_text(Plan, confirm_hint="type 'x'", prefix="mavcal: ").endswith(
        "mavcal: 1 parameter(s) would change; type 'x'\n")

    class Report:
        changed = rows[:1]
        results = rows
        message = "1 parameters written and verified"
        backup_path = "b.param"
        force_saved = ("compass",)
        force_save_failed = ()
        reboot_required = ("COMPASS_ORIENT",)

    done = write_done_text(Report, prefix="mavcal: ")
    assert "mavcal: 1 parameters written and verified; backup of the old values in b.param" in done
    assert "calibration marked saved (compass)" in done and "reboot the vehicle for COMPASS_ORIENT" in done
    failed = write_failed_text(ParamWriteError("x"), "write", "b.param")
    assert failed == "write failed; every value written was restored (backup kept in b.param)\n"
    exc = RestoreFailedError("y", in_doubt=("COMPASS_OFS_Y",))
    doubt = write_failed_text(exc, "write", "b.param", "tcp:x:1")
    assert "parameters in doubt" in doubt and "  COMPASS_OFS_Y\n" in doubt
    assert "mavcal restore b.param --connect tcp:x:1" in doubt


def test_summary_says_each_verdict_once_and_can_leave_the_table_to_the_write_plan(run):
    s = summary_text(run)
    assert s.splitlines()[0].startswith("ACCEPTED: ")
    assert sum(line.startswith("accel0:") for line in s.splitlines()) == 1  # the verdict is not repeated
    short = summary_text(run, param_table=False)
    assert "PARAMETER" in s and "PARAMETER" not in short
    assert short.splitlines()[:3] == s.splitlines()[:3]
