"""A vehicle that cannot be turned over: a log of poses within reach (any heading, small tilts)
calibrates the compass with the accelerometer's scales held and its offsets fitted, writes only what
the poses identify and says per sensor what was kept, why, and what pose would identify it (issues 27, 37)."""
import json

import numpy as np
import pytest

from mavcal.ardupilot import firmware as fw
from mavcal.autopilot.evaluate import attitude_errors, attitude_grid
from mavcal.cli import main
from mavcal.coverage import REACH_FLOWN_TILT_DEG
from mavcal.errors import InsufficientDataError
from mavcal.pipeline import Options, calibrate_source
from mavcal.report.text import summary_text
from mavcal.sources.wmm import field_ned
from mavcal.testing.simlog import AccelErrorTruth, MagTruth, SimConfig, poses_within_reach, simulate_session

SOFT = ((1.04, 0.02, -0.01), (0.02, 0.97, 0.015), (-0.01, 0.015, 1.01))
HARD = (120.0, -80.0, 45.0)
BIAS = (0.15, -0.1, 0.25)
GAIN = (1.02, 0.98, 1.01)
LOCATION = (47.0, 8.0, 400.0)
FIELD = tuple(float(v) for v in field_ned(*LOCATION))
# the accelerometer's calibration in force: close to its truth (an earlier calibration), 0.02 m/s^2 off
ACCEL_CAL = fw.AccelCal(ofs_mps2=(0.17, -0.11, 0.23), scale=tuple(1.0 / np.array(GAIN)))


def _log(path, tilt_deg: float, headings: int | None = None, seed: int = 3):
    cfg = SimConfig(accels=(AccelErrorTruth(bias_mps2=BIAS, gain=GAIN, noise_mps2=0.03),),
                    mags=(MagTruth(hard_iron_mgauss=HARD, soft_iron=SOFT, noise_mgauss=1.5),),
                    accel_cals=(ACCEL_CAL,), compass_cals=(fw.CompassCal(ofs_mgauss=(10.0, 0.0, -5.0), external=True),),
                    earth_field_ned_mgauss=FIELD, poses_deg=poses_within_reach(tilt_deg, 12, seed, headings),
                    hold_s=3.0, move_s=1.5, seed=seed)
    simulate_session(cfg, tlog=path)
    return path


def _errors(cm, max_tilt_deg: float, accel: fw.AccelCal = ACCEL_CAL):
    K = np.array(SOFT)
    return attitude_errors(lambda f: f * np.array(GAIN) + BIAS, lambda B: B @ K.T + HARD, accel, cm.new,
                           np.array(FIELD), attitude_grid(max_tilt_deg=max_tilt_deg))


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    return _log(tmp_path_factory.mktemp("reach") / "s.tlog", 12.0)


@pytest.fixture(scope="module")
def run(small):
    return calibrate_source(str(small), Options(uncertainty_draws=60, location=LOCATION))


def test_small_tilts_calibrate_the_compass_and_keep_the_accelerometer(run):
    assert run.exit_code == 0 and [v.sensor for v in run.verdicts] == ["accel0", "compass0"]
    assert all(v.accepted for v in run.verdicts)
    cal = run.calibration
    assert cal.converged and cal.certificate.certified
    # the 12 deg tilts determine the dip better than the World Magnetic Model knows it: fitted
    assert set(cal.held) == {"K_a[11]", "K_a[22]", "K_a[33]"}
    assert "closer than the World Magnetic Model's" in cal.model_reason
    write = run.params_to_write()
    # the offsets fitted and written (the truth 0.15, -0.1, 0.25; in force 0.02 m/s^2 off), the scales kept
    ofs = np.array([write[f"INS_ACCOFFS_{c}"] for c in "XYZ"])
    assert np.abs(ofs[:2] - BIAS[:2]).max() <= 0.01, ofs
    assert not any(n.startswith("INS_ACCSCAL") and write[n] != pytest.approx(ACCEL_CAL.scale["XYZ".index(n[-1])],
                                                                              rel=1e-6) for n in write)
    assert {"COMPASS_OFS_X", "COMPASS_OFS_Y", "COMPASS_OFS_Z", "COMPASS_DIA_Z", "COMPASS_ODI_Y"} <= set(write)
    # what is kept, why, and what would identify it
    kept = {(k.sensor, k.what): k for k in run.kept}
    assert ("accel0", "Z scale") in kept and ("compass0", "orientation") in kept
    assert "tilts up to 12 deg cannot separate it from the Z offset" in kept["accel0", "Z scale"].why
    assert "on its side" in kept["accel0", "Z scale"].pose


def test_heading_error_small_and_within_the_bound(run):
    cm, am = run.mapping.compass[0], run.mapping.accel[0].new  # as written: the offsets fitted, the scales kept
    level = _errors(cm, 0.0, am)
    flown = _errors(cm, REACH_FLOWN_TILT_DEG, am)
    assert level.max_heading_deg <= 0.5
    assert flown.max_heading_deg <= run.quality.heading_95_deg
    assert run.quality.heading_95_deg <= 2.0


def test_summary_json_and_html_say_what_was_kept(run, tmp_path):
    text = summary_text(run)
    assert "accel0: written: INS_ACCOFFS_X" in text and "accel0: kept:" in text
    assert "Z scale kept: tilts up to 12 deg cannot separate it from the Z offset" in text
    assert "compass0: written: COMPASS_DIA_X" in text
    assert "tilts up to 15 deg; the kept values' uncertainty counted" in text
    doc = run.to_json()
    assert {"sensor": "accel0", "parameter": "Z scale"}.items() <= doc["kept"][1].items()
    assert doc["parameters"]["INS_ACCOFFS_X"]["written"]
    pytest.importorskip("matplotlib")
    from mavcal.report.html import write_html

    html = write_html(run, tmp_path / "r.html").read_text()
    assert "<div id='kept'>" in html and "Z scale kept (not written)" in html


def test_without_a_position_the_dip_is_fitted(small):
    r = calibrate_source(str(small), Options(uncertainty_draws=30))
    assert r.exit_code == 0 and "h_z" not in r.calibration.held
    assert "the field dip estimated from the tilts" in r.calibration.model_reason
    assert _errors(r.mapping.compass[0], 0.0).max_heading_deg <= 0.5


def test_dip_held_at_the_world_magnetic_model_when_the_tilts_see_it_less_well(tmp_path, monkeypatch):
    """When the tilts determine the dip less well than the model knows it (here: a model trusted to
    0.05 deg, 4 deg tilts), the dip is held at the model's inclination, and the compass is still
    written with a small level heading error within its bound."""
    import mavcal.coverage
    import mavcal.fits

    monkeypatch.setattr(mavcal.fits, "WMM_INCLINATION_SD_DEG", 0.05)
    monkeypatch.setattr(mavcal.coverage, "WMM_INCLINATION_SD_DEG", 0.05)
    r = calibrate_source(str(_log(tmp_path / "tiny.tlog", 4.0)), Options(uncertainty_draws=60, location=LOCATION))
    cal = r.calibration
    assert "h_z" in cal.held and "World Magnetic Model's inclination" in cal.model_reason
    assert cal.inclination_deg == pytest.approx(np.degrees(np.arctan2(FIELD[2], np.hypot(*FIELD[:2]))), abs=0.01)
    assert cal.converged and r.exit_code == 0
    assert _errors(r.mapping.compass[0], 0.0).max_heading_deg <= 0.5
    assert _errors(r.mapping.compass[0], REACH_FLOWN_TILT_DEG).max_heading_deg <= r.quality.heading_95_deg


def test_a_fit_within_reach_not_certified_says_which_poses_to_add(small, monkeypatch):
    """When the fit of poses within reach is not certified (forced here: the weak-fit rule asks
    for more degrees of freedom than any capture has), the compass is not written and its
    reason names poses the vehicle can take (headings, tilts), not the full capture's advice."""
    import mavcal.core.held

    monkeypatch.setattr(mavcal.core.held, "WEAK_DOF", 10 ** 6)
    r = calibrate_source(str(small), Options(uncertainty_draws=10, location=LOCATION))
    assert not r.calibration.converged and r.exit_code != 0
    (v,) = [v for v in r.verdicts if v.sensor == "compass0"]
    assert not v.accepted
    why = " ".join(v.reasons)
    assert "not certified" in why and "turn the vehicle to headings between the" in why, why
    assert "tilt it in new directions, as far as it can go (the largest tilt so far is 12 deg)" in why, why
    assert "record more, better spread poses" not in why
    assert not any(n.startswith("COMPASS_") for n in r.params_to_write())


def test_too_few_headings_are_refused_with_what_to_add(tmp_path):
    with pytest.raises(InsufficientDataError, match="too few headings.*turn the vehicle to more headings"):
        calibrate_source(str(_log(tmp_path / "few.tlog", 12.0, headings=3)), Options(uncertainty_draws=10))


def test_segments_says_per_parameter_what_the_poses_identify(small, capsys):
    assert main(["segments", str(small), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    reach = d["reach"]
    assert reach["compass_identified"] and reach["max_tilt_deg"] <= 12.0
    assert {k["parameter"] for k in reach["kept"] if k["sensor"] == "accel0"} == {
        "Z scale", "X and Y scales"}
    assert [s["identifiable"] for s in d["sensors"]] == [False, True]  # accel0 not, compass0 within reach


def test_headings_counted_on_a_sitl_capture_at_5_deg():
    """The 8 poses of a --max-tilt 5 capture on ArduPilot's SITL (its steep field, -65 deg): the
    relaxation alone counted 3 headings there and the capture stalled; 6 headings of the 8 are
    distinct at 40 deg (two pairs are 30 deg apart)."""
    from mavcal.coverage import reach_coverage

    g = [[-0.0344, 0.0157, 0.9993], [-0.124, 0.0152, 0.9922], [-0.035, 0.1059, 0.9938], [-0.0345, 0.0158, 0.9993],
         [0.055, 0.0157, 0.9984], [-0.0344, -0.0752, 0.9966], [-0.0986, 0.0798, 0.9919], [0.0293, -0.0495, 0.9983]]
    m = [[324.2, 11.9, -702.1], [255.8, -202.9, -693.3], [-18.2, -249.3, -677.9], [-135.8, 11.8, -686.4],
         [-67.9, 227.8, -669.7], [206.3, 274.4, -670.3], [325.8, -146.3, -684.0], [-137.7, 172.6, -659.0]]
    r = reach_coverage(np.array(g), np.array(m))
    assert r.applies and r.compass_identified and r.n_field_directions == 6, r
