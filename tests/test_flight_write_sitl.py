"""``mavcal flight LOG --connect DEV --write`` against the real ArduPilot SITL (issue 39).

One SITL boot: a synthetic flight ``.bin`` carrying this vehicle's system id and compass device
ids is fitted and its accepted compensation written through the safe writer (backup, read-back);
the parameters read back from the vehicle are the ones the JSON report lists. The same flight with
another system id is refused first, in one line with exit 11, before anything is written. The
CLI runs in the vehicle's network namespace on SERIAL1 (``sitl.tool_device``), as in
``tests/test_sitl_apply.py``.
"""
from __future__ import annotations

import json
import sys

import pytest

from mavcal.autopilot.paramfile import read_param_file
from mavcal.testing.flight_synth import SynthCompass, synth_flight, write_flight_bin
from mavcal.testing.sitl import SitlVehicle, require_sitl

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(240)]

MOT = (3.0, -2.0, 4.0)
WRITTEN = ["COMPASS_MOTCT", *(f"COMPASS_MOT{s}_{a}" for s in ("", "2") for a in "XYZ")]


def test_flight_write_reads_back_and_refuses_another_vehicle(tmp_path):
    require_sitl()
    with SitlVehicle(wrong_calibration=False, measure_field=False) as sitl:
        ident = sitl.get_params(["MAV_SYSID", "COMPASS_DEV_ID", "COMPASS_DEV_ID2"])  # MAV_SYSID: 4.7's name
        assert set(ident) == {"MAV_SYSID", "COMPASS_DEV_ID", "COMPASS_DEV_ID2"}
        compasses = [SynthCompass(interference=MOT), SynthCompass(interference=MOT)]
        log = write_flight_bin(tmp_path / "flight.bin", synth_flight(compasses, seed=3, params=ident))
        other = write_flight_bin(tmp_path / "other.bin", synth_flight(
            compasses, seed=3, params={**ident, "MAV_SYSID": ident["MAV_SYSID"] + 6}))
        before = sitl.get_params(WRITTEN)

        def flight(path, *more: str):
            return sitl.run([sys.executable, "-m", "mavcal", "flight", str(path), "--connect", sitl.tool_device,
                             "--write", "--yes", *more], timeout=120)

        mark = len(sitl.param_values)
        r = flight(other, "--backup", str(tmp_path / "b0.param"))
        assert r.returncode == 11, r.stdout + r.stderr
        assert r.stderr.count("\n") == 1 and "not the one the log comes from" in r.stderr and "system id" in r.stderr
        assert sitl.writes_since(mark, WRITTEN) == [] and not (tmp_path / "b0.param").exists()

        js, backup = tmp_path / "r.json", tmp_path / "backup.param"
        r = flight(log, "--json", str(js), "--backup", str(backup))
        assert r.returncode == 0, r.stdout + r.stderr
        assert "written and verified" in r.stdout
        want = json.loads(js.read_text())["parameters"]
        assert set(want) == set(WRITTEN)
        got = sitl.get_params(WRITTEN)
        for n in WRITTEN:
            assert got[n] == pytest.approx(want[n], rel=1e-5, abs=1e-4), n
        assert got["COMPASS_MOT_Z"] == pytest.approx(-MOT[2], abs=0.3)
        assert read_param_file(backup) == pytest.approx({n: before[n] for n in read_param_file(backup)}, rel=1e-6)
