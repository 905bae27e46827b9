"""The safe writer against the loopback test vehicle."""
from __future__ import annotations

import numpy as np
import pytest
from pymavlink import mavutil

from mavcal.autopilot.paramfile import read_param_file
from mavcal.errors import LinkError, ParamWriteError, RestoreFailedError, UnknownParameterError, UsageError
from mavcal.link.connection import as_link, open_link
from mavcal.link.params import fetch_all_params
from mavcal.link.writer import write_params

FAST = dict(timeout_s=0.2, restore_wait_s=1.0)


@pytest.fixture
def vehicle(start_vehicle):
    return start_vehicle("udpout", heartbeat_hz=20, seed=1)


@pytest.fixture
def link(vehicle):
    lk = open_link(vehicle.gcs_device, timeout_s=5)
    yield lk
    lk.close()


def test_unknown_name_is_refused_before_any_write(vehicle, link, tmp_path):
    backup = tmp_path / "b.param"
    with pytest.raises(UnknownParameterError) as exc:
        write_params(link, {"COMPASS_OFS_X": 5.0, "COMPASS_OFS9_X": 1.0}, backup_path=backup, **FAST)
    assert exc.value.names == ["COMPASS_OFS9_X"] and exc.value.exit_code == 2
    assert vehicle.param_sets == [] and not backup.exists()


@pytest.mark.parametrize("changes", [{"COMPASS_OFS_X": float("nan")}, {"COMPASS_ORIENT": 300},
                                     {"COMPASS_ORIENT": 2.5}, {"COMPASS_OFS_X": 1e39},
                                     {"COMPASS_OFS_X": 1.0, "bad name": 1.0}])
def test_values_the_vehicle_would_not_store_are_refused(vehicle, link, tmp_path, changes):
    with pytest.raises(UsageError):
        write_params(link, changes, backup_path=tmp_path / "b.param", **FAST)
    assert vehicle.param_sets == [] and not (tmp_path / "b.param").exists()


def test_write_is_confirmed_by_echo_and_read_back(vehicle, link, tmp_path):
    changes = {"COMPASS_OFS_X": 123.456, "COMPASS_SCALE": 1.01, "COMPASS_ORIENT": 6,
               "INS_ACC2SCAL_Y": 0.9876543, "COMPASS_OFFS_MAX": 2000}
    report = write_params(link, changes, backup_path=tmp_path / "b.param", **FAST)
    assert report.complete and not report.restored and report.in_doubt == ()
    for r in report.results:
        assert r.ok and r.attempts == 1
        assert r.echoed == float(np.float32(changes[r.name]))
        assert vehicle.get_param(r.name) == float(np.float32(changes[r.name]))
    # plain REAL32 on the wire, never the byte-wise PX4 encoding
    assert [(n, v) for n, v, _ in vehicle.param_sets] == [(n, float(np.float32(v))) for n, v in changes.items()]


def test_vector_echo_of_siblings_does_not_confuse_the_writer(vehicle, link, tmp_path):
    vehicle.set_param_local("COMPASS_OFS2_Z", 9.0)
    changes = {"COMPASS_OFS2_X": 1.5, "COMPASS_OFS2_Y": -2.5, "COMPASS_OFS2_Z": 3.5}
    report = write_params(link, changes, backup_path=tmp_path / "b.param", **FAST)
    assert report.complete
    assert [r.attempts for r in report.results] == [1, 1, 1]
    assert [vehicle.get_param(n) for n in changes] == [1.5, -2.5, 3.5]


def test_unchanged_values_are_not_written(vehicle, link, tmp_path):
    report = write_params(link, {"COMPASS_DIA_X": 1.0, "COMPASS_OFS_X": 2.0}, backup_path=tmp_path / "b.param",
                          **FAST)
    assert [n for n, _, _ in vehicle.param_sets] == ["COMPASS_OFS_X"]
    assert read_param_file(tmp_path / "b.param") == {"COMPASS_OFS_X": 0.0}
    assert [r.attempts for r in report.results] == [0, 1]


def test_backup_is_on_disk_before_the_first_param_set(vehicle, link, tmp_path):
    backup = tmp_path / "b.param"
    vehicle.set_param_local("COMPASS_OFS_Y", 1e-7)
    seen = []
    send = link.mav.param_set_send

    def spy(*a, **k):
        seen.append(backup.exists() and read_param_file(backup))
        return send(*a, **k)

    link.mav.param_set_send = spy
    try:
        write_params(link, {"COMPASS_OFS_Y": 4.0, "COMPASS_OFS_Z": 5.0}, backup_path=backup, **FAST)
    finally:
        link.mav.param_set_send = send
    assert seen and {k: np.float32(v) for k, v in seen[0].items()} == {"COMPASS_OFS_Y": np.float32(1e-7),
                                                                     "COMPASS_OFS_Z": 0.0}


def test_existing_backup_is_never_overwritten(vehicle, link, tmp_path):
    backup = tmp_path / "b.param"
    backup.write_text("COMPASS_OFS_X,42\n")
    with pytest.raises(UsageError):
        write_params(link, {"COMPASS_OFS_X": 4.0}, backup_path=backup, **FAST)
    assert vehicle.param_sets == [] and backup.read_text() == "COMPASS_OFS_X,42\n"


def test_dry_run_writes_nothing(vehicle, link, tmp_path):
    report = write_params(link, {"COMPASS_OFS_X": 4.0, "COMPASS_DIA_X": 1.0}, backup_path=None, dry_run=True,
                          **FAST)
    assert report.dry_run and not report.complete and report.backup_path is None
    assert [(r.name, r.old, r.expected, r.changed) for r in report.results] == [
        ("COMPASS_OFS_X", 0.0, 4.0, True), ("COMPASS_DIA_X", 1.0, 1.0, False)]
    assert vehicle.param_sets == [] and vehicle.force_saves == [] and list(tmp_path.iterdir()) == []


def test_force_save_is_sent_after_the_writes(vehicle, link, tmp_path):
    report = write_params(link, {"COMPASS_OFS_X": 4.0}, backup_path=tmp_path / "a.param", **FAST)
    assert report.force_saved == ("compass", "accel") and vehicle.force_saves == ["compass", "accel"]
    cmds = [c for c, p in vehicle.commands if c == mavutil.mavlink.MAV_CMD_PREFLIGHT_CALIBRATION]
    assert len(cmds) == 2
    write_params(link, {"COMPASS_OFS_X": 5.0}, backup_path=tmp_path / "b.param", force_save=(), **FAST)
    assert vehicle.force_saves == ["compass", "accel"]


def test_reboot_needs_are_reported(vehicle, link, tmp_path):
    report = write_params(link, {"CUST_ROT1_YAW": 45.0, "COMPASS_ORIENT": 101, "COMPASS_OFS_X": 1.0},
                          backup_path=tmp_path / "b.param", force_save=(), **FAST)
    assert report.reboot_required == ("CUST_ROT1_YAW", "COMPASS_ORIENT") and report.needs_reboot


def test_a_rejected_value_restores_what_was_written(vehicle, link, tmp_path):
    # MIS_TOTAL is internal-use-only (denied with BRD_OPTIONS 0): the echo carries the old value
    vehicle.set_param_local("COMPASS_OFS_X", 10.0)
    before = vehicle.params
    with pytest.raises(ParamWriteError) as exc:
        write_params(link, {"COMPASS_OFS_X": 20.0, "MIS_TOTAL": 12}, backup_path=tmp_path / "b.param",
                     **FAST)
    assert not isinstance(exc.value, RestoreFailedError) and exc.value.exit_code == 5
    rep = exc.value.report
    assert rep.restored and not rep.complete and rep.in_doubt == ()
    assert {r.name: (r.ok, r.restored) for r in rep.results} == {
        "COMPASS_OFS_X": (True, True), "MIS_TOTAL": (False, True)}
    assert vehicle.params == before
    assert (tmp_path / "b.param").exists()


def test_link_killed_mid_write_leaves_backup_and_lists_params_in_doubt(vehicle, link, tmp_path):
    vehicle.die_after_n_sets = 2
    before = vehicle.params
    changes = {"COMPASS_OFS_X": 1.0, "COMPASS_OFS_Y": 2.0, "COMPASS_OFS_Z": 3.0}
    with pytest.raises(RestoreFailedError) as exc:
        write_params(link, changes, backup_path=tmp_path / "b.param", budget_s=1.0, **FAST)
    assert exc.value.exit_code == 6
    assert set(exc.value.in_doubt) == {"COMPASS_OFS_X", "COMPASS_OFS_Y"}
    assert vehicle.get_param("COMPASS_OFS_Y") == 2.0  # applied, never echoed
    assert read_param_file(tmp_path / "b.param") == {n: before[n] for n in changes}
    vehicle.revive()
    rep = write_params(link, read_param_file(tmp_path / "b.param"), backup_path=tmp_path / "c.param", **FAST)
    assert rep.complete and vehicle.params == before


def test_retries_recover_from_a_lossy_link(vehicle, link, tmp_path):
    table = fetch_all_params(link, 5, retry_s=0.2)
    vehicle.set_faults(drop_in=0.5, seed=11)
    changes = {f"COMPASS_OFS{s}_{a}": float(i) + 0.5 for i, (s, a) in enumerate(
        (s, a) for s in ("", "2", "3") for a in "XYZ")}
    rep = write_params(link, changes, backup_path=tmp_path / "b.param", params=table, retries=10,
                       force_save=(), **FAST)
    assert rep.complete and rep.total_attempts > len(changes)
    assert all(vehicle.get_param(n) == v for n, v in changes.items())


def test_a_bare_pymavlink_connection_can_be_used(vehicle, tmp_path):
    conn = mavutil.mavlink_connection(vehicle.gcs_device, source_system=255, dialect="ardupilotmega")
    try:
        assert conn.wait_heartbeat(timeout=5)
        rep = write_params(conn, {"COMPASS_OFS3_Z": -7.25}, backup_path=tmp_path / "b.param", **FAST)
        assert rep.complete and vehicle.get_param("COMPASS_OFS3_Z") == -7.25
        assert as_link(conn).target_system == 1
    finally:
        conn.close()


def test_no_vehicle_gives_a_link_error_quickly():
    with pytest.raises(LinkError) as exc:
        open_link("udpin:127.0.0.1:0", timeout_s=0.3)
    assert "no heartbeat" in str(exc.value) and "\n" not in str(exc.value)
