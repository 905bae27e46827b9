"""``mavcal flight LOG --html FILE``: the self-contained page with one figure per compass (issue 39, item 4).

A synthetic flight (:mod:`mavcal.testing.flight_synth`) written as a DataFlash ``.bin``
(``tests/test_flight_real.py``'s writer), one of two compasses with a constant offset its
calibration lacks.
"""
from __future__ import annotations

import base64
import re
import subprocess
import sys

import numpy as np
import pytest

from mavcal.flight.stage import analyse
from mavcal.report.flight_html import compass_curves
from mavcal.testing.flight_synth import SynthCompass, synth_flight, write_flight_bin

pytest.importorskip("matplotlib")

@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    mot = (4.0, -3.0, 6.0)
    s = synth_flight([SynthCompass(interference=mot), SynthCompass(interference=mot, ofs_true=(85.0, 13.0, -18.0))],
                     seed=3)
    return s, write_flight_bin(tmp_path_factory.mktemp("fl") / "flight.bin", s)


def test_html_page_has_a_figure_per_compass_and_no_external_asset(flight, tmp_path):
    _, log = flight
    page = tmp_path / "flight.html"
    out = subprocess.run([sys.executable, "-m", "mavcal", "flight", str(log), "--html", str(page)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode in (0, 7), out.stdout + out.stderr
    assert f"HTML report written to {page}" in out.stdout
    text = page.read_text()
    assert "data-compasses='2' data-figures='2'" in text
    imgs = re.findall(r"<img [^>]*src='data:image/png;base64,([A-Za-z0-9+/=]+)'", text)
    assert len(imgs) == 2
    for b in imgs:
        assert base64.b64decode(b)[:8] == b"\x89PNG\r\n\x1a\n"
    # self-contained: nothing fetched from elsewhere
    assert not re.search(r"(src|href)\s*=\s*['\"](?!data:)", text)
    assert "http://" not in text and "https://" not in text and "<script" not in text and "<link" not in text
    for k in (0, 1):
        assert f"<figure data-compass='{k}'>" in text
    assert "field magnitude" in text and "heading against the GSF yaw" in text
    assert "WRONG in flight" in text  # compass1, its offset lacking, in the verdict table


def test_the_figures_draw_what_the_fit_found(flight):
    s, _ = flight
    r = analyse(s)
    for c in r.compasses:
        cv = compass_curves(s, r, c)
        assert c.fit is not None
        # the fitted slope drawn is the interference, -COMPASS_MOT
        assert np.allclose(cv.slope_per_unit, -c.fit.mot_per_unit)
        # the field error without the motor term follows the fitted slope (a least-squares line through it)
        for j in range(3):
            got = np.polyfit(cv.driver, cv.error_mgauss[:, j], 1)[0]
            assert abs(got - cv.slope_per_unit[j]) < 0.1 * max(1.0, abs(cv.slope_per_unit[j])), (c.instance, j, got)
        # as fitted the magnitude sits on the field's length, as logged it does not
        assert np.median(np.abs(cv.norm_after_mgauss - cv.field_norm_mgauss)) < 0.5 * np.median(
            np.abs(cv.norm_before_mgauss - cv.field_norm_mgauss))
        assert len(cv.heading_time_s) > 30  # the synthetic flight has a converged GSF yaw


def test_html_refuses_to_overwrite_the_log_and_needs_a_file(flight):
    _, log = flight
    for bad in (str(log), "-"):
        out = subprocess.run([sys.executable, "-m", "mavcal", "flight", str(log), "--html", bad],
                             capture_output=True, text=True, timeout=60)
        assert out.returncode == 2 and out.stderr.startswith("mavcal: error:"), out.stderr
        assert "Traceback" not in out.stderr


def test_without_a_gsf_yaw_the_heading_panel_says_so_and_a_throttle_driver_is_drawn(flight, tmp_path):
    from dataclasses import replace

    from mavcal.report.flight_html import write_flight_html

    s, _ = flight
    e = np.zeros(0)
    s = replace(s, gsf_time_s=e, gsf_yaw_deg=e, gsf_yaw_sigma_deg=e)
    r = analyse(s, driver="throttle")
    assert r.driver_kind == "throttle"
    for c in r.compasses:
        cv = compass_curves(s, r, c)
        assert len(cv.heading_time_s) == 0
        assert 0.0 <= cv.driver.min() and cv.driver.max() <= 1.0  # the throttle, 0..1
    page = write_flight_html(s, r, tmp_path / "nogsf.html").read_text()
    assert page.count("<img ") == len(r.compasses)
    assert "rotation judged against: nothing" in page and "field error against the throttle" in page


def test_a_px4_ulog_gets_its_page_too(tmp_path):
    """The figures come from the autopilot's own in-flight model (PX4's sensor-frame compensation),
    not ArduPilot's: the fitted field's magnitude stays near the Earth field's after the fit."""
    from mavcal.sources.flight_logs import read_flight_log
    from mavcal.testing.px4_flight import Px4SynthCompass, write_px4_flight

    log = write_px4_flight(tmp_path / "p.ulg", [Px4SynthCompass(comp_true=np.array([3.0, -2.0, 1.5]))], seed=3)
    page = tmp_path / "p.html"
    out = subprocess.run([sys.executable, "-m", "mavcal", "flight", str(log), "--html", str(page)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
    text = page.read_text()
    assert "data-compasses='1' data-figures='1'" in text
    assert len(re.findall(r"<img [^>]*src='data:image/png;base64,", text)) == 1
    s = read_flight_log(log)
    r = analyse(s)
    cv = compass_curves(s, r, r.compasses[0])
    before = np.sqrt(np.mean((cv.norm_before_mgauss - cv.field_norm_mgauss) ** 2))
    after = np.sqrt(np.mean((cv.norm_after_mgauss - cv.field_norm_mgauss) ** 2))
    assert after < before / 3, (before, after)
