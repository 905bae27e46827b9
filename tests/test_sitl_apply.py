"""``mavcal apply`` / ``restore`` and the refusals before any write, against the real ArduPilot SITL.

One SITL for the module (tests/conftest's start_sitl for one per test); the ``mavcal`` CLI
runs as a subprocess in the vehicle's network namespace on SERIAL1 (``sitl.tool_device``),
the fixture watches on SERIAL0: ArduPilot echoes every accepted PARAM_SET on every channel,
so ``sitl.writes_since(mark)`` lists what a command wrote.
"""
from __future__ import annotations

import sys

import pytest

from mavcal.ardupilot.paramfile import read_param_file
from mavcal.testing.sitl import SitlVehicle, require_sitl

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(240)]

NAMES = ["COMPASS_OFS_X", "COMPASS_OFS_Y", "INS_ACCSCAL_Z", "COMPASS_DIA_X"]


@pytest.fixture(scope="module")
def sitl():
    require_sitl()
    with SitlVehicle() as v:
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
    written = {n for n, _ in sitl.writes_since(mark)}
    assert written >= set(NAMES), written
    after = sitl.get_params(NAMES)
    want = read_param_file(cal)
    for n in NAMES:
        assert after[n] == pytest.approx(want[n], rel=1e-6), n
    assert read_param_file(backup) == pytest.approx(before, rel=1e-6)

    r = mavcal(sitl, "restore", str(backup), "--connect", sitl.tool_device, "--yes")
    assert r.returncode == 0, r.stderr + r.stdout
    assert sitl.get_params(NAMES) == pytest.approx(before, rel=1e-6)
