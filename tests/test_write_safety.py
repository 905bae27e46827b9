"""Issue 13: range-checked writes, compasses matched by device id, writes that survive loss,
the vehicle's own words when it refuses, and ``calibrate DEVICE --timeout``."""
from __future__ import annotations

import time

import numpy as np
import pytest
from pymavlink import mavutil

from mavcal.ardupilot import limits as L
from mavcal.autopilot import gates
from mavcal.cli import main
from mavcal.errors import ParamWriteError, RestoreFailedError, UnknownParameterError
from mavcal.link.connection import open_link
from mavcal.link.params import fetch_all_params
from mavcal.link.writer import fetch_for_write, write_params

A = mavutil.mavlink
FAST = ["--param-timeout", "0.2", "--timeout", "3"]


def _f32(x: float) -> float:
    return float(np.float32(x))


# ------------------------------------------------------------------ 1. limits
def test_limits_table_is_the_gates_table():
    c = gates.GateConfig()
    assert (c.accel_offset_max_mps2, c.accel_scale_range, c.dia_range, c.odi_max, c.field_range_mgauss) == (
        L.ACCEL_OFFSET_MAX_MPS2, L.ACCEL_SCALE_RANGE, L.DIA_RANGE, L.ODI_MAX, L.FIELD_RANGE_MGAUSS)
    assert L.compass_offset_max({}) == 1800 and L.compass_offset_max({"COMPASS_OFFS_MAX": 900}) == 900


def test_limit_messages_name_parameter_value_and_limit():
    bad = L.check_limits({"COMPASS_OFS_X": 1e30, "INS_ACCSCAL_X": 1e30, "COMPASS_DIA_X": -5.0, "COMPASS_ODI2_Y": 0.5,
                          "INS_ACC2OFFS_Z": -3.6, "COMPASS_ORIENT": 45, "COMPASS_SCALE": 2.0},
                         {"COMPASS_OFFS_MAX": 1800})
    msgs = [v.message for v in bad]
    assert [v.name for v in bad] == ["COMPASS_OFS_X", "INS_ACCSCAL_X", "COMPASS_DIA_X", "INS_ACC2OFFS_Z",
                                     "COMPASS_ORIENT", "COMPASS_SCALE"]
    assert msgs[0].startswith("COMPASS_OFS_X = 1e+30") and "COMPASS_OFFS_MAX 1800" in msgs[0]
    assert "0.8..1.2" in msgs[1] and "0.2 < DIA < 5" in msgs[2] and all("\n" not in m for m in msgs)
    # the offset length counts the vehicle's other axes; an all-zero DIA switches the matrix off
    assert L.check_limits({"COMPASS_OFS_X": 1200.0}, {"COMPASS_OFS_Y": 1200.0, "COMPASS_OFS_Z": 1200.0})
    assert not L.check_limits({"COMPASS_DIA_X": 0.0}, {"COMPASS_DIA_Y": 0.0, "COMPASS_DIA_Z": 0.0})
    assert L.failing_kinds({"COMPASS_OFS_X": 1.0}, {"COMPASS_DIA_X": 9.0}) == {"compass"}


@pytest.fixture
def vehicle(start_vehicle):
    return start_vehicle("udpout", heartbeat_hz=20, seed=3)


@pytest.mark.parametrize("line", ["COMPASS_OFS_X 1e30", "INS_ACCSCAL_X 1e30", "COMPASS_DIA_X -5"])
@pytest.mark.parametrize("command", ["apply", "restore"])
def test_out_of_range_apply_and_restore_are_refused_before_any_param_set(vehicle, tmp_path, capsys, line, command):
    p = tmp_path / "x.param"
    p.write_text(f"COMPASS_OFS_Y 10\n{line}\n")
    assert main([command, str(p), "--connect", vehicle.gcs_device, "--yes"] + FAST) == 2
    err = capsys.readouterr().err
    name, value = line.split()
    assert err.count("\n") == 1 and name in err and f"{float(value):g}" in err and "limit" in err
    assert vehicle.param_sets == [] and vehicle.force_saves == []
    assert not list(tmp_path.glob("*before-restore*")) and not list(tmp_path.glob("mavcal-backup*"))


def test_force_writes_loudly_and_does_not_mark_the_failing_sensor_calibrated(vehicle, tmp_path, capsys):
    p = tmp_path / "x.param"
    p.write_text("COMPASS_DIA_X -5\nINS_ACCOFFS_X 0.25\n")
    rc = main(["apply", str(p), "--connect", vehicle.gcs_device, "--yes", "--force",
               "--backup", str(tmp_path / "b.param")] + FAST)
    cap = capsys.readouterr()
    assert rc == 0 and vehicle.get_param("COMPASS_DIA_X") == -5.0
    assert "WARNING" in cap.err and "COMPASS_DIA_X = -5" in cap.err and "compass will NOT be marked" in cap.err
    assert vehicle.force_saves == ["accel"] and "not marked calibrated" in cap.out


# ------------------------------------------------------------------ 2. device ids
def test_calibration_for_another_compass_is_refused_before_any_param_set(start_vehicle, sitl_dir, tmp_path, capsys):
    v = start_vehicle("udpout", heartbeat_hz=20, params={"COMPASS_DEV_ID": 12345, "COMPASS_PRIO1_ID": 12345})
    args = ["calibrate", str(sitl_dir / "sitl02.tlog"), "--write", "--yes", "--connect", v.gcs_device,
            "--backup", str(tmp_path / "b.param"), "--param-timeout", "0.3"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "97539" in err and "12345" in err and "--map-compass 1:1" in err and err.count("\n") == 1
    assert v.param_sets == [] and not (tmp_path / "b.param").exists()
    # the user says it is the same compass: written, and the device id is stored by the force-save
    assert main(args + ["--map-compass", "1:1"]) == 0
    assert v.param_sets and "compass" in v.force_saves


def test_a_pending_priority_swap_is_refused(start_vehicle, sitl_dir, tmp_path, capsys):
    v = start_vehicle("udpout", heartbeat_hz=20)
    v.set_param_local("COMPASS_PRIO1_ID", 131874)  # swapped by a user, not yet rebooted
    v.set_param_local("COMPASS_PRIO2_ID", 97539)
    assert main(["calibrate", str(sitl_dir / "sitl02.tlog"), "--write", "--yes", "--connect", v.gcs_device,
                 "--backup", str(tmp_path / "b.param"), "--param-timeout", "0.3"]) == 2
    assert "reboot the vehicle first" in capsys.readouterr().err and v.param_sets == []


# ------------------------------------------------------------------ 3. the vehicle's own words
def test_param_error_and_denial_are_reported_in_the_vehicles_words(start_vehicle, tmp_path):
    v = start_vehicle("udpout", heartbeat_hz=20, param_errors=True, deny_params=("COMPASS_OFS2_X",))
    link = open_link(v.gcs_device, timeout_s=5)
    try:
        t0 = time.monotonic()
        with pytest.raises(UnknownParameterError) as exc:  # PARAM_ERROR: no full download, no long wait
            fetch_for_write(link, ["COMPASS_OFS_X", "COMPASS_OFS9_X"], timeout_s=0.2)
        assert exc.value.names == ["COMPASS_OFS9_X"] and time.monotonic() - t0 < 2.0
        with pytest.raises(ParamWriteError) as werr:
            write_params(link, {"COMPASS_OFS_X": 2.0, "COMPASS_OFS2_X": 3.0}, backup_path=tmp_path / "b.param",
                         timeout_s=0.2)
        msg = str(werr.value)
        assert "COMPASS_OFS2_X: the vehicle refused 3" in msg and "no echo" not in msg
        assert "Param write denied (COMPASS_OFS2_X)" in msg or "PERMISSION_DENIED" in msg
        assert werr.value.report.restored and v.get_param("COMPASS_OFS_X") == 0.0
    finally:
        link.close()


def test_a_refused_force_save_is_reported_with_the_ack_result(vehicle, tmp_path):
    vehicle.force_save_result = A.MAV_RESULT_DENIED
    link = open_link(vehicle.gcs_device, timeout_s=5)
    try:
        rep = write_params(link, {"COMPASS_OFS_X": 2.0}, backup_path=tmp_path / "b.param", force_save=("compass",),
                           timeout_s=0.2)
    finally:
        link.close()
    assert rep.complete and rep.force_save_failed == ("compass",) and "MAV_RESULT_DENIED" in rep.message


def test_only_what_the_write_needs_is_read_when_the_names_answer(vehicle):
    link = open_link(vehicle.gcs_device, timeout_s=5)
    try:
        table = fetch_for_write(link, ["COMPASS_OFS_X"], context=L.related_names(["COMPASS_OFS_X"]), timeout_s=0.2)
    finally:
        link.close()
    assert "COMPASS_OFS_X" in table and "COMPASS_DEV_ID" in table and "COMPASS_OFFS_MAX" in table
    assert len(table) < 30 < len(vehicle.params)


# ------------------------------------------------------------------ 3/4. loss
@pytest.mark.slow
def test_at_30_percent_loss_95_percent_of_writes_complete(tmp_path, start_vehicle):
    rng = np.random.default_rng(13)
    n_writes, complete = 30, 0
    with start_vehicle("udpout", heartbeat_hz=20, seed=13) as v:
        link = open_link(v.gcs_device, timeout_s=5)
        try:
            v.set_faults(drop_in=0.3, drop_out=0.3, dup_in=0.05, dup_out=0.05, seed=13)
            t0 = time.monotonic()
            table = fetch_all_params(link, 5, retry_s=0.1)  # complete despite the loss
            assert len(table) == len(v.params) and time.monotonic() - t0 < 30
            for i in range(n_writes):
                changes = {n: float(rng.normal(0, 50)) for n in ("COMPASS_OFS_X", "COMPASS_OFS_Y", "COMPASS_MOT_Z")}
                before = v.params
                try:
                    write_params(link, changes, backup_path=tmp_path / f"b{i}.param", params=table,
                                 force_save=("compass",), timeout_s=0.05)
                except RestoreFailedError:
                    raise
                except ParamWriteError:
                    assert v.params == before  # fully restored
                    continue
                complete += 1
                assert all(v.get_param(n) == _f32(x) for n, x in changes.items())
        finally:
            link.close()
    assert complete >= 0.95 * n_writes, complete


# ------------------------------------------------------------------ 5. --timeout
@pytest.mark.timeout(30)
def test_calibrate_device_honours_timeout(capsys):
    t0 = time.monotonic()
    rc = main(["calibrate", "udpin:127.0.0.1:0", "--timeout", "0.4", "--duration", "1"])
    err = capsys.readouterr().err
    assert rc == 3 and "within 0.4 s" in err and time.monotonic() - t0 < 3
