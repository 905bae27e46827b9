"""Damaged records are skipped and counted where they are read (issue 10, item 5); a refused
log still gets per-sensor verdicts in the JSON; a log whose accelerometer calibration has no
IMU data is refused with that reason."""
from __future__ import annotations

import json

import numpy as np
import pytest

from mavcal.ardupilot import firmware as fw
from mavcal.ardupilot.recover import accel_cal_without_imu, recover_raw
from mavcal.cli import EXIT_INTERNAL, main
from mavcal.errors import SourceError
from mavcal.report.json import from_json
from mavcal.sources.reader import read_log
from mavcal.sources.types import ImuLog, ParamTimeline, SensorSeries
from mavcal.testing.logwriters import DataFlashWriter, TlogWriter
from mavcal.testing.simlog import SimConfig, simulate_session

G = 9.80665


def _still_bin(path, *, bad_instance: int | None = None, orient: float | None = None):
    """A short DataFlash log, level and still; optionally IMU records with instance
    ``bad_instance`` and an AHRS_ORIENTATION PARM record of value ``orient``."""
    with DataFlashWriter(path) as w:
        w.parm(0, "INS_ACCOFFS_X", 0.1)
        if orient is not None:
            w.parm(0, "AHRS_ORIENTATION", orient)
        for k in range(200):
            t = 1000 + k * 20000
            w.imu(t, 0, (0, 0, 0), (0.0, 0.0, -G))
            if bad_instance is not None and k % 10 == 0:
                w.imu(t, bad_instance, (0, 0, 0), (1e6, 0.0, -G))
            w.mag(t, 0, (200, 10, 400))
    return path


def test_corrupt_instance_byte_is_skipped_and_counted(tmp_path):
    lg = read_log(_still_bin(tmp_path / "a.bin", bad_instance=109))
    assert lg.instances("accel") == [0] and len(lg.get("accel", 0)) == 200  # the good part is used
    assert any("skipped 20 IMU records with an impossible instance number (109" in w for w in lg.warnings)
    raw = recover_raw(lg)  # used to raise "accel instance must be 0..4"
    assert raw.accel_instances() == [0]


def test_impossible_rotation_parameter_is_skipped(tmp_path):
    lg = read_log(_still_bin(tmp_path / "b.bin", orient=109))
    assert "AHRS_ORIENTATION" not in lg.params and "INS_ACCOFFS_X" in lg.params
    assert any("AHRS_ORIENTATION=109" in w and "corrupt" in w for w in lg.warnings)
    assert fw.param_value_plausible("AHRS_ORIENTATION", 109) is False
    assert fw.param_value_plausible("COMPASS_ORIENT2", 6) is True
    assert fw.param_value_plausible("COMPASS_OFS_X", float("nan")) is False


def _log_with(params: dict[str, float]) -> ImuLog:
    t = np.arange(0, 10, 0.1)
    acc = SensorSeries("accel", 0, "IMU", t, np.tile([0.0, 0.0, -G], (len(t), 1)))
    mag = SensorSeries("mag", 0, "MAG", t, np.tile([200.0, 10.0, 400.0], (len(t), 1)))
    tl = ParamTimeline({n: (np.array([0.0]), np.array([v])) for n, v in params.items()})
    return ImuLog(source="mem", kind="dataflash", series=(acc, mag), params=tl)


def test_parameters_that_cannot_be_undone_leave_readings_out_with_a_warning():
    # a singular soft-iron matrix (DIA 0 with ODI making it rank-deficient) and an unknown rotation
    names = fw.compass_param_names(0)
    p = {n: 1.0 for n in names["dia"]} | {n: 1.0 for n in names["odi"]} | {names["scale"]: 1.0}
    raw = recover_raw(_log_with(p))
    mag = raw.get("mag", 0)
    assert np.isnan(mag.values).all()
    assert any("cannot be undone" in w and "mag 0" in w for w in raw.warnings)
    raw = recover_raw(_log_with({"INS_ACCOFFS_X": 0.0, fw.board_param_names()["orientation"]: 109}))
    assert np.isnan(raw.get("accel", 0).values).all()
    assert any("cannot be undone" in w and "accel 0" in w for w in raw.warnings)


def test_refused_log_still_writes_json_verdicts(tmp_path, capsys):
    path = _still_bin(tmp_path / "c.bin")  # one pose: too little data
    out = tmp_path / "r.json"
    assert main(["-q", "calibrate", str(path), "--json", str(out)]) == 4
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("mavcal: error:")
    doc = json.loads(out.read_text())
    assert doc["exit_code"] == 4 and doc["accepted"] is False and doc["error"]
    assert [s["sensor"] for s in doc["sensors"]] == ["accel0", "compass0"]
    for s in doc["sensors"]:
        assert set(s) == {"sensor", "accepted", "reasons"} and s["accepted"] is False
        assert s["reasons"][0].startswith("not calibrated: 1 still interval(s)")
    with pytest.raises(SourceError, match="refused"):
        from_json(doc)
    # --json - : the JSON alone on stdout
    assert main(["-q", "calibrate", str(path), "--json", "-"]) == 4
    assert json.loads(capsys.readouterr().out)["sensors"][0]["sensor"] == "accel0"
    # unreadable: exit 3, still a JSON with the error and no sensors
    bad = tmp_path / "x.tlog"
    bad.write_bytes(b"\x00" * 100)
    assert main(["-q", "calibrate", str(bad), "--json", str(out)]) == 3
    doc = json.loads(out.read_text())
    assert doc["exit_code"] == 3 and doc["sensors"] == []


def _blind_tlog(path, lost: bool):
    """A simulated 6-pose session with ArduPilot's accel calibration; with ``lost`` the ground
    station streams RAW_IMU only before the first prompt."""
    cfg = SimConfig(accel_cal_period_s=(6.0, 60.0), mags=())
    sim = simulate_session(cfg)
    t0, a = 1.7e9, 6.0
    recs = [(tt, "hb") for tt in np.arange(0, cfg.duration_s, 1.0)]
    recs += [(0.001 * j, ("param", n, v)) for j, (n, v) in enumerate(sorted(sim.params_initial.items()))]
    prompts = ["level", "on its LEFT side", "on its RIGHT side", "nose DOWN", "nose UP", "on its BACK"]
    recs += [(a + j * 9.0 + 0.01, ("text", f"Place vehicle {p} and press any key.")) for j, p in enumerate(prompts)]
    recs += [(60.0, ("text", "Calibration successful"))]
    ta = sim.accel_time_s[0]
    for j, tt in enumerate(ta):
        if lost and tt >= a - 1.0:
            break
        recs.append((float(tt), ("imu", j)))
    recs.sort(key=lambda r: r[0])
    acc, gyr = sim.accel_logged_mps2[0], sim.gyro_rad_s[0]
    with TlogWriter(path) as w:
        for tt, r in recs:
            if r == "hb":
                w.heartbeat(t0 + tt)
            elif r[0] == "param":
                w.param_value(t0 + tt, r[1], r[2])
            elif r[0] == "text":
                w.statustext(t0 + tt, r[1])
            else:
                j = r[1]
                w.raw_imu(t0 + tt, int((30 + tt) * 1e6), acc[j] * 1000 / G, gyr[j] * 1000, (0, 0, 0))
    return path


def test_calibration_prompts_without_imu_data_are_refused_with_that_reason(tmp_path, capsys):
    path = _blind_tlog(tmp_path / "blind.tlog", lost=True)
    lg = read_log(path)
    (a, b), = accel_cal_without_imu(lg)
    t0 = lg.get("accel", 0).time_s[0]  # the session's start on the log's time base (boot time)
    assert a - t0 == pytest.approx(6.01, abs=0.05) and b - t0 == pytest.approx(60.0, abs=0.05)
    out = tmp_path / "r.json"
    assert main(["-q", "calibrate", str(path), "--json", str(out)]) == 4
    err = capsys.readouterr().err
    assert "accelerometer calibration" in err and "no IMU data during it" in err
    doc = json.loads(out.read_text())
    assert any("no IMU data during it" in r for r in doc["sensors"][0]["reasons"])
    # the same session with the IMU stream kept: no such reason
    full = read_log(_blind_tlog(tmp_path / "full.tlog", lost=False))
    assert accel_cal_without_imu(full) == []


def test_cli_last_resort_is_one_line_with_its_own_exit_code(monkeypatch, capsys):
    import mavcal.commands.segments as seg

    def boom(args):
        raise ZeroDivisionError("bug")

    monkeypatch.setattr(seg, "run", boom)
    assert main(["-q", "segments", "x.tlog"]) == EXIT_INTERNAL == 70
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["mavcal: internal error: ZeroDivisionError: bug (a bug in mavcal; -vv shows where)"]
