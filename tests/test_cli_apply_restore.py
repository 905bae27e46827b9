"""``mavcal apply`` / ``mavcal restore`` through ``main([...])`` against the test vehicle."""
from __future__ import annotations

import math
import socket
import time

import pytest
from pymavlink import mavutil

from mavcal.autopilot.paramfile import read_param_file
from mavcal.cli import main
from mavcal.testing.relay import LossRelay

FAST = ["--param-timeout", "0.2", "--timeout", "3"]


@pytest.fixture
def vehicle(start_vehicle):
    return start_vehicle("udpout", heartbeat_hz=20, seed=2)


@pytest.fixture
def calfile(tmp_path):
    p = tmp_path / "cal.param"
    p.write_text("# new calibration\nCOMPASS_OFS_X,12.5\nCOMPASS_OFS_Y -3.25\nINS_ACCSCAL_Z\t1.0123\nCOMPASS_DIA_X,1\n")
    return p


def test_apply_writes_backs_up_and_prints_a_table(vehicle, calfile, tmp_path, capsys):
    backup = tmp_path / "backup.param"
    assert main(["apply", str(calfile), "--connect", vehicle.gcs_device, "--yes", "--backup", str(backup)] + FAST) == 0
    out = capsys.readouterr().out
    assert "COMPASS_OFS_X" in out and "-> 12.5" in out and "written and verified" in out
    assert vehicle.get_param("COMPASS_OFS_X") == 12.5 and vehicle.force_saves == ["compass", "accel"]
    assert read_param_file(backup) == {"COMPASS_OFS_X": 0.0, "COMPASS_OFS_Y": 0.0, "INS_ACCSCAL_Z": 1.0}


def test_dry_run_writes_nothing(vehicle, calfile, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["apply", str(calfile), "--connect", vehicle.gcs_device, "--dry-run"] + FAST) == 0
    out = capsys.readouterr().out
    assert "dry run: 3 of 4 parameters would change" in out and "unchanged" in out
    assert vehicle.param_sets == [] and sorted(p.name for p in tmp_path.iterdir()) == ["cal.param"]


def test_without_yes_and_no_terminal_nothing_is_written(vehicle, calfile, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("sys.stdin.isatty", lambda: False, raising=False)
    assert main(["apply", str(calfile), "--connect", vehicle.gcs_device] + FAST) == 2
    assert vehicle.param_sets == []


@pytest.mark.timeout(30)  # "quickly": bounded by --timeout, no hang
def test_device_that_does_not_answer_exits_3_quickly_with_one_line(calfile, capsys):
    rc = main(["apply", str(calfile), "--connect", "udpin:127.0.0.1:0", "--yes", "--timeout", "0.3"])
    err = capsys.readouterr().err
    assert rc == 3 and err.count("\n") == 1 and "no heartbeat" in err


@pytest.mark.parametrize("text,code", [("COMPASS_OFS_X\n", 3), ("COMPASS_OFS_X 1 2\n", 3), ("", 3)])
def test_bad_files(tmp_path, capsys, text, code):
    p = tmp_path / "bad.param"
    p.write_text(text)
    assert main(["apply", str(p), "--connect", "udpin:127.0.0.1:0", "--timeout", "0.2"]) == code
    assert capsys.readouterr().err.count("\n") == 1


def test_unknown_parameter_exits_2_before_any_write(vehicle, tmp_path, capsys):
    p = tmp_path / "x.param"
    p.write_text("COMPASS_OFS_X 1\nNOT_A_PARAM 2\n")
    assert main(["apply", str(p), "--connect", vehicle.gcs_device, "--yes"] + FAST) == 2
    assert "NOT_A_PARAM" in capsys.readouterr().err and vehicle.param_sets == []


def test_rejected_write_is_restored_exit_5(vehicle, tmp_path, capsys):
    p = tmp_path / "x.param"
    p.write_text("COMPASS_OFS_X 1\nMIS_TOTAL 5\n")  # internal-use-only: write-denied (BRD_OPTIONS 0)
    before = vehicle.params
    assert main(["apply", str(p), "--connect", vehicle.gcs_device, "--yes",
                 "--backup", str(tmp_path / "b.param")] + FAST) == 5
    assert vehicle.params == before and "restored" in capsys.readouterr().out


def test_killed_mid_write_exit_6_then_restore_recovers(vehicle, calfile, tmp_path, capsys):
    before = vehicle.params
    backup = tmp_path / "b.param"
    vehicle.die_after_n_sets = 2
    assert main(["apply", str(calfile), "--connect", vehicle.gcs_device, "--yes", "--backup", str(backup),
                 "--write-budget", "1"] + FAST) == 6
    cap = capsys.readouterr()
    assert "parameters in doubt" in cap.out and "COMPASS_OFS_Y" in cap.out and "mavcal restore" in cap.out
    assert backup.exists() and vehicle.get_param("COMPASS_OFS_Y") == -3.25
    vehicle.revive()
    assert main(["restore", str(backup), "--connect", vehicle.gcs_device, "--yes"] + FAST) == 0
    assert vehicle.params == before
    undo = list(tmp_path.glob("b-before-restore-*.param"))
    assert len(undo) == 1 and read_param_file(undo[0])["COMPASS_OFS_Y"] == -3.25


@pytest.mark.timeout(60)
def test_a_vehicle_gone_for_good_is_waited_for_then_exit_6_says_how_long(start_vehicle, calfile, tmp_path, capsys):
    """The link goes dark for good right after the second PARAM_SET: the write waits the write
    budget (1 s) for the vehicle, the restore its own budget (4 x 1 s) before its first PARAM_SET;
    then exit 6, the parameters in doubt listed, the error saying how long the vehicle was unheard."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with LossRelay(port, loss=0.0, dup=0.0) as relay:
        v = start_vehicle("udpout", port=relay.vehicle_port, heartbeat_hz=1)
        before = v.params
        relay.blackout_at(mavutil.mavlink.MAVLINK_MSG_ID_PARAM_SET, 2, math.inf)
        t0 = time.monotonic()
        rc = main(["apply", str(calfile), "--connect", relay.tool_device, "--yes", "--backup",
                   str(tmp_path / "b.param"), "--write-budget", "1"] + FAST)
        waited = time.monotonic() - relay.blackouts[0]
        took = time.monotonic() - t0
    cap = capsys.readouterr()
    print(f"\ngone for good: exit {rc} {waited:.1f} s after the blackout ({took:.1f} s in all); {cap.err.strip()}")
    assert rc == 6
    assert waited >= 1.0 + 4.0  # the write's budget, then the restore's
    assert "parameters in doubt" in cap.out and "COMPASS_OFS_X" in cap.out
    assert "vehicle unheard for" in cap.err and "the restore waited 4." in cap.err and "its budget 4 s" in cap.err
    assert v.params != before and v.get_param("COMPASS_OFS_X") == 12.5  # the first value was written: in doubt
