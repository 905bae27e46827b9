"""A vehicle that cannot be turned over, on the real ArduPilot SITL (issue 27): ``mavcal capture
--max-tilt 15 --write --yes`` with a hand that holds each advised pose; the compass is accepted
and written, the heading error in level flight is at most 0.5 deg against the injected truth
(:mod:`mavcal.testing.sitl_truth`), the primary accelerometer's offsets are written closer to their
truth (issue 37), and every parameter the poses cannot identify (the accelerometers' scales, the
other accelerometer, the compasses' orientations) reads back unchanged."""
from __future__ import annotations

import json

import numpy as np
import pytest

from mavcal.ardupilot import firmware as fw
from mavcal.autopilot.evaluate import attitude_errors, attitude_grid
from mavcal.testing.sitl import CALIBRATION_NAMES, WRONG_CALIBRATION, InjectedErrors
from mavcal.testing.sitl_hand import run_guided_capture

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(240)]

ACCEL_NAMES = {n for i in range(2) for key in ("ofs", "scale") for n in fw.accel_param_names(i)[key]}  # type: ignore[literal-required]
ORIENT_NAMES = {fw.compass_param_names(i)["orient"] for i in range(3)}


def boot_calibration(errors: InjectedErrors) -> dict[str, float]:
    """A wrong compass calibration in force, and the accelerometer calibrated before (its ideal
    values, 0.02 m/s^2 off): what a large vehicle's owner has when the compass needs redoing."""
    ideal = errors.ideal_params()
    acc = {n: v + (0.02 if n in fw.accel_param_names(0)["ofs"] else 0.0) for n, v in ideal.items() if n in ACCEL_NAMES}
    return {**WRONG_CALIBRATION, **acc}


def test_capture_within_reach_writes_the_compass_and_the_accel_offsets_and_keeps_the_rest(start_sitl, tmp_path):
    errors = InjectedErrors.random(21)
    sitl = start_sitl(errors, wrong_calibration=boot_calibration(errors))
    before = sitl.get_params(CALIBRATION_NAMES)
    g = run_guided_capture(sitl, tmp_path, return_prob=0.0, seed=21, timeout_s=180, args=["--max-tilt", "15"])
    print(f"capture within reach: {len(g.hand.poses)} poses held, {g.took_s:.0f} s, rc {g.rc}")
    assert g.hand.error is None, g.hand.error
    tilts = [float(np.degrees(np.arccos(np.cos(np.radians(r)) * np.cos(np.radians(p))))) for r, p, _ in g.hand.poses]
    assert max(tilts) <= 15.1, g.hand.poses  # every pose advised within the limit
    assert (tmp_path / "run.json").exists(), f"rc {g.rc}\n{g.status.text()[-3000:]}\n{g.stdout[-2000:]}"
    report = json.loads((tmp_path / "run.json").read_text())
    verdicts = {s["sensor"]: s for s in report["sensors"]}
    assert g.rc == 0 and verdicts["compass0"]["accepted"], f"{verdicts}\n{g.status.text()[-2000:]}\n{g.stdout[-2000:]}"
    assert {k["sensor"] for k in report["kept"]} >= {"accel0", "compass0"}
    written = {n for n, _ in sitl.writes_since(g.mark)}
    assert {"COMPASS_OFS_X", "COMPASS_DIA_X", "COMPASS_ODI_X"} <= written, written
    offsets = fw.accel_param_names(0)["ofs"]
    # (the accelerometers' force-save makes ArduPilot announce its other values too: they read back unchanged)
    assert set(offsets) <= written and not written & ORIENT_NAMES, written
    after = sitl.get_params(CALIBRATION_NAMES)
    for n in sorted((ACCEL_NAMES - set(offsets) | ORIENT_NAMES) & set(before)):
        assert after[n] == pytest.approx(before[n], rel=1e-6, abs=1e-9), n  # read back unchanged
    ideal = errors.ideal_params()  # the offsets in force were 0.02 m/s^2 off: X and Y now closer
    assert max(abs(after[n] - ideal[n]) for n in offsets[:2]) < 0.02, {n: (after[n], ideal[n]) for n in offsets}
    cal_c, cal_a = fw.compass_cal_from_params(after, 0), fw.accel_cal_from_params(after, 0)
    level = attitude_errors(errors.raw_accel, errors.raw_mag_sensor, cal_a, cal_c, sitl.field_ned_mgauss,
                            attitude_grid(max_tilt_deg=0.0))
    print(f"level flight: max heading error {level.max_heading_deg:.3f} deg; bound "
          f"{report['quality']['heading_95_deg']:.3f} deg (95 %, tilts up to 15 deg)")
    assert level.max_heading_deg <= 0.5


#: issue 37: compass errors 395 mGauss from the calibration in force (WRONG_CALIBRATION's offsets) at
#: CMAC's -66 deg dip, for which the heading count from the raw means (the relaxation and the circle)
#: gave 4 headings for the plan's 6, so no fit came and the plan was advised again and again
FAR_ERRORS = InjectedErrors(mag_ofs_mgauss=(-254.6, -120.0, -245.6), mag_dia=(0.9298, 1.0397, 0.9897),
                            mag_odi=(0.0299, -0.0264, -0.018), mag_noise_mgauss=3.0,
                            acc_bias_mps2=(-0.021, 0.005, -0.431), acc_scale=(0.9716, 0.9736, 1.0294))


def test_capture_within_reach_ends_accepted_with_offsets_far_from_those_in_force(start_sitl, tmp_path):
    """Issue 37: with offsets 300+ mGauss from those in force the headings are counted from a
    provisional fit, and the capture ends within 25 poses with the compass accepted."""
    errors = FAR_ERRORS
    far = np.array(errors.mag_ofs_mgauss) - np.array([WRONG_CALIBRATION[f"COMPASS_OFS_{a}"] for a in "XYZ"])
    assert np.linalg.norm(far) >= 300.0
    sitl = start_sitl(errors, wrong_calibration=boot_calibration(errors))
    g = run_guided_capture(sitl, tmp_path, return_prob=0.0, seed=37, timeout_s=200, args=["--max-tilt", "15"])
    print(f"capture within reach, offsets {np.linalg.norm(far):.0f} mGauss from those in force: "
          f"{len(g.hand.poses)} poses held, {g.took_s:.0f} s, rc {g.rc}")
    assert g.hand.error is None, g.hand.error
    assert len(g.hand.poses) <= 26, g.hand.poses  # the cap (25 intervals), and the last pose held as it ends
    assert (tmp_path / "run.json").exists(), f"rc {g.rc}\n{g.status.text()[-3000:]}\n{g.stdout[-2000:]}"
    report = json.loads((tmp_path / "run.json").read_text())
    verdicts = {s["sensor"]: s for s in report["sensors"]}
    assert g.rc == 0 and verdicts["compass0"]["accepted"], f"{verdicts}\n{g.status.text()[-2000:]}\n{g.stdout[-2000:]}"
    after = sitl.get_params(CALIBRATION_NAMES)
    cal_c, cal_a = fw.compass_cal_from_params(after, 0), fw.accel_cal_from_params(after, 0)
    level = attitude_errors(errors.raw_accel, errors.raw_mag_sensor, cal_a, cal_c, sitl.field_ned_mgauss,
                            attitude_grid(max_tilt_deg=0.0))
    print(f"level flight: max heading error {level.max_heading_deg:.3f} deg; offsets "
          f"{np.max(np.abs(np.array(cal_c.ofs_mgauss) - errors.mag_ofs_mgauss)):.1f} mGauss off")
    assert level.max_heading_deg <= 0.5
