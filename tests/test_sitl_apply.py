"""``mavcal apply`` / ``restore`` and the refusals before any write, against the real ArduPilot SITL.

One SITL for the module (tests/conftest's start_sitl for one per test); the ``mavcal`` CLI
runs as a subprocess in the vehicle's network namespace on SERIAL1 (``sitl.tool_device``),
the fixture watches on SERIAL0: ArduPilot echoes every accepted PARAM_SET on every channel,
so ``sitl.writes_since(mark)`` lists what a command wrote.
"""
from __future__ import annotations

import sys

import pytest

from mavcal.autopilot.paramfile import read_param_file
from mavcal.testing.sitl import CALIBRATION_NAMES, SitlVehicle, require_sitl

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(240)]

NAMES = ["COMPASS_OFS_X", "COMPASS_OFS_Y", "INS_ACCSCAL_Z", "COMPASS_DIA_X"]


# compass 1 is not the one of the bundled SITL logs (device id 97539: SITL bus, address 0x7d);
# this one sits at address 0x7e, so a log of sitl_logs/ is "a log from another compass"
OTHER_COMPASS_DEVID = 97795


@pytest.fixture(scope="module")
def sitl():
    require_sitl()
    with SitlVehicle(params={"SIM_MAG1_DEVID": OTHER_COMPASS_DEVID}) as v:
        yield v


def mavcal(sitl: SitlVehicle, *args: str, timeout: float = 120.0):
    return sitl.run([sys.executable, "-m", "mavcal", *args], timeout=timeout)


def test_apply_read_back_restore_round_trip(sitl, tmp_path):
    before = sitl.get_params(NAMES)
    assert set(before) == set(NAMES)
    cal = tmp_path / "cal.param"
    cal.write_text("COMPASS_OFS_X 12.5\nCOMPASS_OFS_Y,-3.25\nINS_ACCSCAL_Z 1.0123\nCOMPASS_DIA_X 1.015\n")
    backup = tmp_path / "backup.param"
    mark = len(sitl.param_values)
    r = mavcal(sitl, "apply", str(cal), "--connect", sitl.tool_device, "--yes", "--backup", str(backup))
    assert r.returncode == 0, r.stderr + r.stdout
    assert "written and verified" in r.stdout
    written = {n for n, _ in sitl.writes_since(mark, NAMES)}
    assert written >= set(NAMES), written
    after = sitl.get_params(NAMES)
    want = read_param_file(cal)
    for n in NAMES:
        assert after[n] == pytest.approx(want[n], rel=1e-6), n
    assert read_param_file(backup) == pytest.approx(before, rel=1e-6)

    r = mavcal(sitl, "restore", str(backup), "--connect", sitl.tool_device, "--yes")
    assert r.returncode == 0, r.stderr + r.stdout
    assert sitl.get_params(NAMES) == pytest.approx(before, rel=1e-6)


def test_unknown_name_refused_before_any_write(sitl, tmp_path):
    p = tmp_path / "x.param"
    p.write_text("COMPASS_OFS_X 1\nNOT_A_PARAM 2\n")
    before = sitl.get_params(["COMPASS_OFS_X"])
    mark = len(sitl.param_values)
    # ArduPilot does not answer a read of a name it does not have: the read gives up after its
    # retries; a short --param-timeout keeps that wait (about 30 s with the defaults) out of CI
    r = mavcal(sitl, "apply", str(p), "--connect", sitl.tool_device, "--yes", "--backup", str(tmp_path / "b.param"),
               "--param-timeout", "0.5")
    assert r.returncode == 2, r.stderr + r.stdout
    assert "NOT_A_PARAM" in r.stderr and r.stderr.count("\n") == 1
    assert sitl.writes_since(mark, CALIBRATION_NAMES + ("NOT_A_PARAM",)) == []
    assert sitl.get_params(["COMPASS_OFS_X"]) == before
    assert not (tmp_path / "b.param").exists()


@pytest.mark.parametrize("line", ["INS_ACCSCAL_X 1.5", "COMPASS_OFS_Y 2500", "COMPASS_DIA_Z 0.05"])
def test_out_of_range_refused_before_any_write(sitl, tmp_path, line):
    p = tmp_path / "x.param"
    p.write_text(f"COMPASS_OFS_X 1\n{line}\n")
    name = line.split()[0]
    before = sitl.get_params(["COMPASS_OFS_X", name])
    mark = len(sitl.param_values)
    r = mavcal(sitl, "apply", str(p), "--connect", sitl.tool_device, "--yes", "--backup", str(tmp_path / "b.param"))
    assert r.returncode == 2, r.stderr + r.stdout
    assert name in r.stderr
    assert sitl.writes_since(mark) == []
    assert sitl.get_params(["COMPASS_OFS_X", name]) == before
    assert not (tmp_path / "b.param").exists()


def test_log_from_another_compass_refused_before_any_write(sitl, sitl_dir, tmp_path):
    assert sitl.get_param("COMPASS_DEV_ID") == OTHER_COMPASS_DEVID
    names = ["COMPASS_OFS_X", "COMPASS_OFS_Y", "COMPASS_OFS_Z", "INS_ACCOFFS_X"]
    before = sitl.get_params(names)
    mark = len(sitl.param_values)
    r = mavcal(sitl, "calibrate", str(sitl_dir / "sitl01.tlog"), "--write", "--connect", sitl.tool_device, "--yes",
               "--backup", str(tmp_path / "b.param"))
    assert r.returncode == 2, r.stderr + r.stdout
    assert "97539" in r.stderr and str(OTHER_COMPASS_DEVID) in r.stderr, r.stderr
    assert sitl.writes_since(mark) == []
    assert sitl.get_params(names) == before
    assert not (tmp_path / "b.param").exists()
