"""PX4: the ULog reader, the PX4 model (names, slots by device id, units, rotations, mapping), the
pipeline on a simulated PX4 recording, and PX4's conventions checked on PX4's own logs.

The public ULogs in ../shared/data/px4/ (pyulog's test logs) are read from there, never copied."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from mavcal.autopilot import is_px4, model_for
from mavcal.cli import main
from mavcal.pipeline import Options, calibrate_source
from mavcal.px4 import params as pn
from mavcal.px4.firmware import Px4MagCal, accel_cal_from_params, mag_cal_from_params
from mavcal.px4.rotations import ROT_LOOKUP_DEG, nearest_rotation, rotation_matrix, sensor_rotation
from mavcal.testing.px4_sim import random_truth, simulate_px4, truth_errors

PX4_LOGS = Path(__file__).resolve().parents[2] / "shared" / "data" / "px4"
#: every log, and what mavcal says of it: exit code of calibrate, and of segments
EXPECTED = {"sample.ulg": 3, "sample_appended_multiple.ulg": 3, "sample_log_small.ulg": 4,
            "sample_logging_tagged_and_default_params.ulg": 4, "sample_px4_events.ulg": 4}
WITH_RAW = ("sample_log_small.ulg", "sample_logging_tagged_and_default_params.ulg", "sample_px4_events.ulg")
FAST = Options(uncertainty_draws=50, holdout=False)


@pytest.fixture(scope="module")
def px4_logs() -> Path:
    if not PX4_LOGS.is_dir():
        pytest.skip(f"PX4 logs not found at {PX4_LOGS} (shared/ must sit beside the repo)")
    return PX4_LOGS


# --------------------------------------------------------------------------- names, slots, rotations

def test_names_and_int32():
    a, m = pn.accel_names(2), pn.mag_names(3)
    assert a["id"] == "CAL_ACC2_ID" and a["ofs"][1] == "CAL_ACC2_YOFF" and a["scale"][2] == "CAL_ACC2_ZSCALE"
    assert m["odiag"] == ("CAL_MAG3_XODIAG", "CAL_MAG3_YODIAG", "CAL_MAG3_ZODIAG")
    assert m["custom"][1] == "CAL_MAG3_PITCH"
    assert all(pn.is_int32(n) for n in (a["id"], a["rot"], a["prio"], "SENS_BOARD_ROT"))
    assert not any(pn.is_int32(n) for n in (*a["ofs"], *m["scale"], "SENS_BOARD_X_OFF"))
    with pytest.raises(ValueError):
        pn.accel_names(4)


def test_slot_is_found_by_device_id_not_instance():
    p = {"CAL_MAG0_ID": 0, "CAL_MAG1_ID": 197388, "CAL_MAG2_ID": 197644, "CAL_MAG3_ID": 0,
         "CAL_MAG2_XOFF": 0.25, "CAL_MAG2_ROT": -1}
    assert pn.find_slot(p, "mag", 197644) == 2 and pn.find_slot(p, "mag", 1) is None
    assert pn.free_slot(p, "mag") == 0
    cal = mag_cal_from_params(p, 197644)
    assert cal.slot == 2 and cal.ofs_gauss[0] == pytest.approx(0.25) and not cal.external
    assert mag_cal_from_params(p, 12345).slot is None  # no slot: uncalibrated


def test_rotation_table_matches_ardupilot_where_px4_agrees():
    from mavcal.autopilot.rotations import rotation_matrix as ap_matrix

    for v in range(0, 38):  # PX4 and ArduPilot share 0..37; 38 differs (whole degrees in PX4)
        assert np.allclose(rotation_matrix(v), ap_matrix(v), atol=1e-12), v
    assert len(ROT_LOOKUP_DEG) == 48
    assert nearest_rotation(rotation_matrix(6)) == (6, pytest.approx(0.0, abs=1e-6))
    # the level adjustment comes first: L @ R(value)
    level = (1.0, -2.0, 0.5)
    assert nearest_rotation(sensor_rotation(4, level), level)[0] == 4


def test_px4_correction_forward_inverse_and_ardupilot_form():
    rng = np.random.default_rng(3)
    cal = Px4MagCal(1, 0, (0.1, -0.2, 0.05), (1.05, 0.95, 1.02), (0.02, -0.01, 0.03),
                    sensor_rotation(10, (0.5, -1.0, 0.0)), 10, True)
    raw = rng.normal(0, 400, (50, 3))
    m = cal.correct(raw)
    assert np.allclose(cal.undo(m), raw, atol=1e-9)
    # PX4: R S (s - OFF); by hand, offsets in gauss subtracted in the sensor frame before S, then R
    by_hand = (cal.rotation @ cal.matrix @ (raw - 1000 * np.array(cal.ofs_gauss)).T).T
    assert np.allclose(m, by_hand, atol=1e-9)
    from mavcal.ardupilot.firmware import apply_compass

    assert np.allclose(apply_compass(cal.ardupilot_form(), raw, sensor_frame=True), m, atol=1e-9)


# --------------------------------------------------------------------------- the pipeline on a simulated PX4

@pytest.mark.parametrize("seed, board_rot, mag_rot", [(1, 0, None), (2, 4, None), (3, 0, 2), (4, 2, 6)])
def test_simulated_px4_calibration_is_exact(seed, board_rot, mag_rot):
    """Internal and external magnetometers, a board rotation, a calibration in force in every slot:
    the written CAL_* values, applied with PX4's equations to the raw sensors, give the truth."""
    truth = random_truth(seed, board_rot=board_rot, mag_rot=mag_rot)
    log_ = simulate_px4(truth, seed=seed)
    assert is_px4(log_) and model_for(log_).name == "PX4"
    run = calibrate_source(log_, FAST)
    assert run.accepted, run.gates.failures()
    new = run.mapping.new
    assert set(new) == {*pn.accel_names(0)["ofs"], *pn.accel_names(0)["scale"], *pn.mag_names(0)["ofs"],
                        *pn.mag_names(0)["scale"], *pn.mag_names(0)["odiag"]}
    err = truth_errors(truth, new)
    assert err["heading_deg"] <= 0.1 and err["tilt_deg"] <= 0.02, err
    assert err["mag_offset_gauss"] <= 0.001 and err["accel_mag_mps2"] <= 0.005, err


def test_misrotated_external_magnetometer_gets_its_rotation():
    """PX4 told ROT 0 for an external magnetometer mounted yaw 90: CAL_MAG0_ROT 2 is written."""
    truth = dataclasses.replace(random_truth(5, mag_rot=0), mag_rotation=rotation_matrix(2))
    run = calibrate_source(simulate_px4(truth, seed=5), FAST)
    assert run.accepted and run.mapping.new["CAL_MAG0_ROT"] == 2
    assert truth_errors(truth, run.mapping.new)["heading_deg"] <= 0.1


def test_external_magnetometer_off_by_degrees_gets_custom_euler_angles():
    """7 deg off any standard rotation: ROT 100 with CAL_MAG0_ROLL/PITCH/YAW (PX4's custom Euler angles)."""
    from mavcal.autopilot.rotations import euler_to_matrix

    truth = dataclasses.replace(random_truth(6, mag_rot=0), mag_rotation=euler_to_matrix(*np.radians([4.0, -3.0, 5.0])))
    run = calibrate_source(simulate_px4(truth, seed=6), FAST)
    new = run.mapping.new
    assert run.accepted and new["CAL_MAG0_ROT"] == pn.ROT_CUSTOM
    assert (new["CAL_MAG0_ROLL"], new["CAL_MAG0_PITCH"], new["CAL_MAG0_YAW"]) == pytest.approx((4, -3, 5), abs=0.1)
    assert truth_errors(truth, new)["heading_deg"] <= 0.1


def test_gates_speak_of_px4s_limits_not_ardupilots():
    """A PX4 recording is judged against PX4's own compass limits (offsets: its 1.3 gauss saturation
    warning; field: its 0.2-0.7 gauss sphere radius) and the reasons never name an ArduPilot
    parameter: a compass 1.5 gauss off is refused in PX4's words."""
    truth = dataclasses.replace(random_truth(8), o_mgauss=np.array([1500.0, 100.0, -50.0]))
    run = calibrate_source(simulate_px4(truth, seed=8), FAST)
    gates = {(g.sensor, g.name): g for g in run.gates.gates}
    off = gates["compass0", "offsets"]
    assert not off.ok and "1300 mGauss" in off.limit and "PX4's saturation warning" in off.reason, off
    assert [v.accepted for v in run.verdicts if v.sensor == "compass0"] == [False]
    texts = " ".join(g.limit + " " + g.reason for g in run.gates.gates)
    assert "ArduPilot" not in texts and "COMPASS_" not in texts and "INS_" not in texts, texts
    ok = calibrate_source(simulate_px4(random_truth(8), seed=8), FAST)
    field = {(g.sensor, g.name): g for g in ok.gates.gates}["compass0", "field"]
    assert ok.accepted and field.ok, ok.gates.failures()
    assert "COMPASS_OFFS_MAX" not in {(g.sensor, g.name): g for g in ok.gates.gates}["compass0", "offsets"].limit


def test_sensor_without_a_slot_gets_a_free_one_with_its_device_id():
    truth = random_truth(7)
    p = dict(truth.params)
    p["CAL_ACC0_ID"], p["CAL_ACC1_ID"] = 999, 0
    truth = dataclasses.replace(truth, params=p)
    run = calibrate_source(simulate_px4(truth, seed=7), FAST)
    assert run.mapping.new["CAL_ACC1_ID"] == truth.accel_id and "CAL_ACC1_XOFF" in run.mapping.new
    assert any("no calibration slot" in n for n in run.mapping.notes)
    assert truth_errors(truth, run.mapping.new)["tilt_deg"] <= 0.02


def test_ardupilot_logs_keep_the_ardupilot_model(sitl_dir):
    from mavcal.sources.reader import read_log

    log_ = read_log(sitl_dir / "sitl02.tlog")
    assert not is_px4(log_) and model_for(log_).name == "ArduPilot"


# --------------------------------------------------------------------------- PX4's own logs

@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_every_px4_log_gives_a_verdict_or_a_one_line_refusal(px4_logs, name, capsys):
    code = EXPECTED[name]
    assert main(["calibrate", str(px4_logs / name)]) == code
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.strip().splitlines()[-1].startswith("mavcal: error: ")
    if code == 3:
        assert "no raw sensor_accel/sensor_mag topics" in err and "SDLOG_PROFILE" in err
    assert main(["segments", str(px4_logs / name)]) == code
    assert "Traceback" not in capsys.readouterr().err


def test_ulog_reader(px4_logs):
    from mavcal.sources.reader import read_log

    log_ = read_log(px4_logs / "sample_logging_tagged_and_default_params.ulg")
    assert log_.kind == "ulog" and log_.vehicle["autopilot"] == 12
    assert log_.instances("accel") == [0, 1, 2] and log_.instances("mag") == [0, 1]
    mag0 = log_.get("mag", 0)
    assert mag0 is not None and int(mag0.extra["device_id"][0]) == 197388
    assert 200 < np.linalg.norm(mag0.values, axis=1).mean() < 700  # gauss -> mGauss
    assert log_.params.initial("CAL_ACC0_ID") == 1310988 and log_.params.initial("CAL_MAG0_ROT") == -1
    lat, lon, _ = log_.position
    assert lat == pytest.approx(47.398, abs=0.01) and lon == pytest.approx(8.546, abs=0.01)


def _nearest(t_cal: np.ndarray, t: np.ndarray) -> np.ndarray:
    i = np.clip(np.searchsorted(t_cal, t), 1, len(t_cal) - 1)
    return np.where(np.abs(t_cal[i - 1] - t) < np.abs(t_cal[i] - t), i - 1, i)


def _residuals(path: Path, sensor: str, rotation=None) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """Per series: (device, PX4's calibrated output - mavcal's model applied to the raw topic, the same
    with the raw topic only rotated) at the calibrated sample nearest to each raw one."""
    from mavcal.px4.recover import cal_of
    from mavcal.sources.ulog import calibrated_topics, read_ulog

    log_, cal = read_ulog(str(path)), calibrated_topics(str(path))
    params = log_.params.snapshot()
    out = []
    for s in log_.series:
        if s.sensor != sensor:
            continue
        dev = int(s.extra["device_id"][-1])
        topic = "vehicle_imu" if sensor == "accel" else "vehicle_magnetometer"
        c = next((c for c in cal if c.topic == topic and (c.device_id == dev).any()), None)
        if c is None:
            continue
        m = cal_of(s, params)
        if rotation is not None:
            m = dataclasses.replace(m, rotation=rotation(params))
        sel = c.device_id == dev
        j = _nearest(c.time_s[sel], s.time_s)
        px4 = c.values[sel][j]
        out.append((dev, m.correct(s.values) - px4, s.values @ m.rotation.T - px4))
    return out


@pytest.mark.parametrize("name", WITH_RAW)
def test_px4_calibration_applied_to_raw_topics_gives_px4s_output(px4_logs, name):
    """Convention check on PX4's own logs: mavcal's model of the CAL_* in force applied to the raw
    sensor_accel reproduces PX4's calibrated vehicle_imu (Delta v / dt, the sample nearest in time,
    <= 32 ms apart) and, where the log holds it per device, sensor_mag reproduces vehicle_magnetometer.
    The raw topics are logged at ~1 Hz while the calibrated ones average or filter, so single samples
    differ by the vehicle's motion and noise (rms 0.05-0.1 m/s^2); the tolerance is on the mean over
    the log: within 3 standard errors + 0.01 m/s^2 (accel) / + 2 mGauss (mag) per axis."""
    checked = 0
    for sensor, floor in (("accel", 0.01), ("mag", 2.0)):
        for dev, d, _ in _residuals(px4_logs / name, sensor):
            if sensor == "mag" and name == "sample_log_small.ulg":
                continue  # PX4 < 1.12 calibrated magnetometers in the driver: sensor_mag is not raw there
            se = d.std(axis=0, ddof=1) / np.sqrt(len(d))
            assert np.all(np.abs(d.mean(axis=0)) <= 3 * se + floor), (sensor, dev, d.mean(axis=0), se)
            checked += 1
    assert checked >= (3 if name == "sample_log_small.ulg" else 2)  # every accel, and the mag when raw


def test_hardware_log_proves_the_rotation_order(px4_logs):
    """sample_log_small.ulg (CubeOrange): SENS_BOARD_ROT 4 (yaw 180) with SENS_BOARD_X/Y_OFF 0.76/-2.94 deg
    and accel offsets up to 0.16 m/s^2. mavcal's ``L @ R(rot)`` with OFF/SCALE reproduces PX4's output;
    the rotation without the level adjustment, or applied in the other order, and the uncalibrated
    readings do not."""
    from mavcal.autopilot.rotations import euler_to_matrix

    def wrong_order(p):
        return rotation_matrix(int(p["SENS_BOARD_ROT"])) @ euler_to_matrix(*np.radians(
            [p["SENS_BOARD_X_OFF"], p["SENS_BOARD_Y_OFF"], p["SENS_BOARD_Z_OFF"]]))

    path = px4_logs / "sample_log_small.ulg"
    for (dev, d, d_uncal), (_, d_wrong, _), (_, d_nolevel, _) in zip(
            _residuals(path, "accel"), _residuals(path, "accel", wrong_order),
            _residuals(path, "accel", lambda p: rotation_matrix(int(p["SENS_BOARD_ROT"])))):
        right = np.linalg.norm(d.mean(axis=0))
        assert right < 0.03, (dev, d.mean(axis=0))
        assert min(np.linalg.norm(d_wrong.mean(axis=0)), np.linalg.norm(d_nolevel.mean(axis=0)),
                   np.linalg.norm(d_uncal.mean(axis=0))) > 5 * right


def test_accel_cal_from_ulog_params_uses_board_rotation(px4_logs):
    from mavcal.sources.reader import read_log

    p = read_log(px4_logs / "sample_log_small.ulg").params.snapshot()
    cal = accel_cal_from_params(p, 2424842)
    assert cal.slot == 0 and cal.ofs_mps2[0] == pytest.approx(0.158, abs=1e-3)
    assert np.allclose(cal.rotation, sensor_rotation(4, (p["SENS_BOARD_X_OFF"], p["SENS_BOARD_Y_OFF"], 0.0)))


def test_batch_rows_of_px4_name_device_ids_and_the_change_in_px4s_calibration(px4_logs, monkeypatch):
    """``mavcal batch`` on PX4: the device ids come from the recording (CAL_*_ID by slot), and the
    drift columns compare the calibration in force (CAL_* in the mapping's form) with the new one."""
    import mavcal.sources.reader
    from mavcal.batch import calibrate_many

    (row,) = calibrate_many([str(px4_logs / "sample_log_small.ulg")], FAST)
    assert row.exit_code == 4 and row.accel_id and row.compass_dev_id  # refused, but the vehicle is named
    truth = random_truth(9)
    sim = simulate_px4(truth, seed=9)
    run = calibrate_source(sim, FAST)
    monkeypatch.setattr(mavcal.sources.reader, "read_log", lambda source, **kw: sim)  # the batch reads as calibrate
    (row,) = calibrate_many(["simulated.ulg"], FAST)
    assert row.ok and row.accepted, row
    assert (row.accel_id, row.compass_dev_id) == (truth.accel_id, truth.mag_id)
    cm, am = run.mapping.compass[0], run.mapping.accel[0]
    assert row.compass_ofs_old == pytest.approx(tuple(cm.old.ofs_mgauss), abs=1e-9)
    assert row.compass_ofs_new == pytest.approx(tuple(cm.new.ofs_mgauss), rel=1e-6, abs=1e-6)
    assert row.accel_scale_old == pytest.approx(tuple(am.old.scale), abs=1e-12)
    assert row.compass_ofs_change_mgauss > 1.0 and row.drift is not None


def test_a_live_capture_recovering_again_and_again_logs_each_warning_once(caplog):
    """A live capture undoes the readings at every update: the recovery's warnings reach the log at
    WARNING once per process, at DEBUG after that (they stay in every result's warnings)."""
    from mavcal.px4.recover import recover_raw

    truth = random_truth(10)
    truth = dataclasses.replace(truth, params={**truth.params, pn.THERMAL_ACCEL: 1.0})
    log_ = simulate_px4(truth, seed=10)
    caplog.set_level("DEBUG")
    first = recover_raw(log_)
    assert any("thermal compensation" in w for w in first.warnings)
    n = sum(r.levelname == "WARNING" for r in caplog.records)
    assert n <= 1
    again = [recover_raw(log_) for _ in range(3)]
    assert sum(r.levelname == "WARNING" for r in caplog.records) == n
    assert all(r.warnings == first.warnings for r in again)


def test_custom_rotation_is_px4s_dcm_of_euler_angles():
    """CAL_MAG<n>_ROT 100: PX4 builds the rotation as matrix::Dcmf(Eulerf(roll, pitch, yaw))
    (Magnetometer::ParametersUpdate, set_custom_rotation), the 3-2-1 intrinsic Tait-Bryan matrix
    written out here from PX4's matrix library (Dcm.hpp, the constructor from Euler angles)."""
    def px4_dcm(phi, the, psi):
        cf, sf, ct, st, cp, sp = np.cos(phi), np.sin(phi), np.cos(the), np.sin(the), np.cos(psi), np.sin(psi)
        return np.array([[ct * cp, -cf * sp + sf * st * cp, sf * sp + cf * st * cp],
                         [ct * sp, cf * cp + sf * st * sp, -sf * cp + cf * st * sp],
                         [-st, sf * ct, cf * ct]])

    for deg in [(4.0, -3.0, 5.0), (30.0, 20.0, -120.0), (-170.0, 80.0, 45.0)]:
        np.testing.assert_allclose(rotation_matrix(pn.ROT_CUSTOM, deg), px4_dcm(*np.radians(deg)), atol=1e-12)


def test_a_px4_calibration_is_in_use_without_a_reboot():
    """The writer's detours put every CAL_* vector into use at once (tests/test_px4_sitl_capture.py proves it
    against PX4): a PX4 calibration asks for no reboot."""
    from mavcal.report.text import summary_text

    run = calibrate_source(simulate_px4(random_truth(1), seed=1), FAST)
    assert not run.mapping.reboot_required and "reboot needed" not in summary_text(run)


def _in_use(held: dict, params: dict, thresholds: dict) -> dict:
    """PX4's parameter update as its calibration library does it (set_offset / set_scale /
    set_offdiagonal): each vector taken whole when it differs from the one in use by more than its threshold."""
    from mavcal.px4.params import calibration_vector

    out = dict(held)
    for g in {calibration_vector(n) for n in params} - {None}:
        d = np.array([params[n] - held[n] for n in g])
        if np.linalg.norm(d) > thresholds[g[0][-3:]]:
            out.update({n: params[n] for n in g})
    return out


def _send(order, detours, params: dict, held: dict, rng, p_update: float, thresholds: dict) -> dict:
    """PX4's state in use after the writes, a parameter update after each write with probability
    ``p_update`` (several writes may fall into one), one after the detours (the writer's dwell) and one at the end."""
    for n, v in detours.items():
        params[n] = v
        if rng.random() < p_update:
            held = _in_use(held, params, thresholds)
    held = _in_use(held, params, thresholds) if detours else held
    for n, v in order.items():
        params[n] = v
        if rng.random() < p_update:
            held = _in_use(held, params, thresholds)
    return _in_use(held, params, thresholds)


def test_detoured_order_puts_each_pivot_last_and_detours_it_towards_the_default():
    from mavcal.px4.params import DETOUR_STEP, detoured_order

    changes = {"CAL_MAG0_XOFF": 0.1, "CAL_MAG0_YOFF": -0.2, "CAL_MAG0_ZOFF": 0.3, "CAL_MAG0_XSCALE": 0.97,
               "CAL_MAG0_ZODIAG": 0.004, "CAL_MAG0_PRIO": 50.0, "CAL_ACC0_YSCALE": 1.02, "CAL_ACC0_ZSCALE": 1.01}
    order, detours = detoured_order(changes)
    assert list(order) == ["CAL_MAG0_YOFF", "CAL_MAG0_ZOFF", "CAL_MAG0_XOFF", "CAL_MAG0_XSCALE", "CAL_MAG0_ZODIAG",
                           "CAL_MAG0_PRIO", "CAL_ACC0_ZSCALE", "CAL_ACC0_YSCALE"]
    assert order == changes  # the same values
    assert detours == pytest.approx({"CAL_MAG0_XOFF": 0.1 - DETOUR_STEP, "CAL_MAG0_XSCALE": 0.97 + DETOUR_STEP,
                                     "CAL_MAG0_ZODIAG": 0.004 - DETOUR_STEP, "CAL_ACC0_YSCALE": 1.02 - DETOUR_STEP})
    assert detoured_order({"COMPASS_OFS_X": 1.0, "COMPASS_OFS_Y": 2.0}) == ({"COMPASS_OFS_X": 1.0,
                                                                            "COMPASS_OFS_Y": 2.0}, {})


@pytest.mark.parametrize("p_update", [1.0, 0.5, 0.1])
def test_detours_leave_px4_using_every_written_vector_whatever_it_held(p_update):
    """On a model of PX4's update rule (thresholds 0.005 gauss for offsets, 0.01 otherwise, as seen on the
    PX4 SITL; and 0.01 / 0.02 for margin), random small changes from a random state in use (which may
    differ from the parameters by up to a threshold, as earlier writes leave it), updates falling between
    any writes: sent plainly, some vectors stay out of use; sent with their detours, none ever does."""
    from mavcal.px4.params import calibration_vector, detoured_order, mag_names

    n = mag_names(0)
    names = [*n["ofs"], *n["scale"], *n["odiag"]]
    rng = np.random.default_rng(7)
    plain_wrong = 0
    for trial in range(300):
        thr = {"OFF": [0.005, 0.01, 0.02][trial % 3], "ALE": 0.01 + 0.01 * (trial % 2), "IAG": 0.01}
        params = {k: (1.0 if "SCALE" in k else 0.0) + rng.uniform(-0.1, 0.1) for k in names}
        held = {k: v + rng.uniform(-0.4, 0.4) * 0.01 for k, v in params.items()}
        changes = {k: params[k] + rng.choice([0.0, rng.uniform(-0.03, 0.03)]) for k in names}
        changes = {k: v for k, v in changes.items() if v != params[k]}
        written = {k for k in names if calibration_vector(k) in {calibration_vector(c) for c in changes}}
        target = {k: changes.get(k, params[k]) for k in written}  # the vectors written
        order, detours = detoured_order(changes)
        got = _send(order, detours, dict(params), held, rng, p_update, thr)
        assert {k: got[k] for k in written} == pytest.approx(target, abs=1e-12), trial
        plain = _send(dict(changes), {}, dict(params), held, rng, p_update, thr)
        plain_wrong += {k: plain[k] for k in written} != pytest.approx(target, abs=1e-12)
    assert plain_wrong > 30  # the model does show PX4's problem
