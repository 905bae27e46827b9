"""mavcal calibrate SOURCE --write against the loopback test vehicle (ArduPilot's protocol)."""
import numpy as np
import pytest

from mavcal.autopilot.paramfile import read_param_file
from mavcal.cli import main


@pytest.fixture
def vehicle(start_vehicle):
    return start_vehicle("udpout", heartbeat_hz=20)


def test_calibrate_log_and_write_to_vehicle(vehicle, sitl_dir, tmp_path, capsys):
    backup = tmp_path / "backup.param"
    rc = main(["calibrate", str(sitl_dir / "sitl02.tlog"), "--write", "--yes", "--connect", vehicle.gcs_device,
               "--backup", str(backup), "--param-timeout", "0.5", "--param-out", str(tmp_path / "new.param")])
    out = capsys.readouterr().out
    assert rc == 0, out
    new = read_param_file(tmp_path / "new.param")
    for name, value in new.items():
        assert np.float32(vehicle.get_param(name)) == np.float32(value), name
    assert vehicle.get_param("COMPASS_ORIENT") == 4.0
    assert set(vehicle.force_saves) >= {"compass", "accel"}
    old = read_param_file(backup)
    assert set(old) >= {"COMPASS_OFS_X", "INS_ACCSCAL_Z"}
    assert "backup of the old values" in out


def test_dry_run_writes_nothing(vehicle, sitl_dir, capsys):
    before = dict(vehicle.params)
    rc = main(["calibrate", str(sitl_dir / "sitl01.tlog"), "--dry-run", "--connect", vehicle.gcs_device])
    out = capsys.readouterr().out
    assert rc == 0
    assert "dry run" in out and "COMPASS_OFS_X" in out
    assert vehicle.params == before and not vehicle.force_saves
