"""The mavcal MAVProxy module in a real MAVProxy process against the real ArduPilot SITL.

MAVProxy runs in the vehicle's network namespace on SERIAL1 (``sitl.tool_device``), driven
through its stdin (tests/test_mavproxy_module's :class:`MAVProxy` driver); the scripted hand
follows the advice the module prints, with the module's default settings. load -> capture ->
fit -> write -> unload; the written calibration is scored against the injected truth.
"""
from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
import threading
import time

import pytest
from test_mavproxy_module import MAVProxy

from mavcal.testing.sitl import InjectedErrors, SitlVehicle
from mavcal.testing.sitl_hand import AdviceHand

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(420),
              pytest.mark.skipif(importlib.util.find_spec("MAVProxy") is None,
                                 reason="MAVProxy is not installed (pip install mavcal[test])")]


def changed_rows(lines: list[str], start: int) -> dict[str, float]:
    """(name, new value) of the safe writer's table rows marked ok after output line ``start``."""
    rows = {}
    for line in lines[start:]:
        m = re.search(r"(\w+)\s+\S+\s+->\s+(\S+)\s+ok$", line)
        if m:
            rows[m.group(1)] = float(m.group(2))
    return rows


class SitlMAVProxy(MAVProxy):
    """:class:`MAVProxy` started in the SITL's network namespace."""

    def __init__(self, sitl: SitlVehicle, cwd) -> None:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.started = time.monotonic()
        self.p = sitl.popen([sys.executable, "-m", "MAVProxy.mavproxy", "--master", sitl.tool_device, "--no-state",
                             "--default-modules=link,param"], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, cwd=str(cwd), env=env)
        self.lines = []
        self.cond = threading.Condition()
        self.reader = threading.Thread(target=self._read, name="mavproxy-reader", daemon=True)
        self.reader.start()


def test_mavproxy_module_load_capture_write_unload(start_sitl, tmp_path):
    sitl = start_sitl(InjectedErrors.random(13, mag_orient=6))
    mp = SitlMAVProxy(sitl, tmp_path)
    hand = AdviceHand(sitl, mp.advice, return_prob=0.5, seed=13)
    t0 = time.monotonic()
    try:
        mp.expect(r"Detected vehicle 1:1", timeout=30)
        loaded = mp.send("module load mavcal.mavproxy_mavcal")
        mp.expect(r"Loaded module mavcal\.mavproxy_mavcal", after=loaded)
        mp.send(f"mavcal set backup_dir {tmp_path / 'backups'}")
        _, at = mp.expect(r"mavcal: capture started", after=mp.send("mavcal start"))
        mp.expect(r"next: level, nose towards magnetic north", after=at)
        hand.start()
        m, at = mp.expect(r"capture (finished|aborted)", timeout=240, after=at)
        assert m.group(1) == "finished", "\n".join(mp.lines[-30:])
        hand.stop()
        assert hand.error is None, hand.error
        mp.expect(r"mavcal: fit done", timeout=60, after=at)
        verdicts = {}
        for sensor in ("accel0", "accel1", "compass0", "compass1", "compass2"):
            v, _ = mp.expect(rf"^{sensor}: (accepted|rejected.*)$", after=at)
            verdicts[sensor] = v.group(1)
        assert all(v == "accepted" for v in verdicts.values()), verdicts
        mark = mp.send("mavcal write yes")
        mp.expect(r"mavcal: \d+ parameters written and verified", timeout=60, after=mark)
        mp.expect(r"calibration marked saved \(compass, accel\)", after=mark)
        rows = changed_rows(mp.lines, mark)
        assert rows and {"COMPASS_OFS_X", "COMPASS_ORIENT", "INS_ACCOFFS_X"} <= set(rows)
        got = sitl.get_params(rows)
        assert all(got[n] == pytest.approx(x, rel=1e-5, abs=1e-5) for n, x in rows.items())
        mark = mp.send("module unload mavcal")
        mp.expect(r"mavcal: unloaded; worker stopped; mavcal threads left: none", after=mark)
        mp.expect(r"Unloaded module mavcal", after=mark)
    finally:
        hand.stop()
        mp.close()
    print(f"MAVProxy capture: {len(hand.poses)} poses held, {hand.returns} quick returns, "
          f"{time.monotonic() - t0:.0f} s")
    s = sitl.score()
    print(f"SITL score: {s.line()}")
    assert s.max_heading_deg <= 0.2 and s.max_tilt_deg <= 0.05, s.line()
    assert s.compass_ofs_error_mgauss <= 1.0 and s.orient_right, s.line()
