"""The real ArduPilot on a real serial line: SITL's own UART driver on a pseudo-terminal
(``--serial2 uart:/dev/pts/K:57600``), relayed at a telemetry radio's rate (57600 baud, 5.76 kB/s
each way, :class:`mavcal.testing.serial_cable.SerialCable`) to the pty mavcal opens by a udev-like
symlink. No network between mavcal and the vehicle: the serial driver, pyserial and the rate are real.

* a guided capture (the scripted hand of tests/test_sitl_capture.py), its write and read-back:
  written and verified, heading within 0.2 deg of the truth (the UDP capture's bar);
* a cable pulled for 3 s right after the 4th PARAM_SET of a 15-parameter ``mavcal apply`` and
  plugged back at the same path: the write resumes (exit 0, every value held) or is undone
  (exit 5, every old value held), never exit 6 with parameters in doubt while the vehicle is back.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from pymavlink import mavutil

from mavcal.testing.serial_cable import SerialCable
from mavcal.testing.sitl import InjectedErrors
from mavcal.testing.sitl_hand import run_guided_capture

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(420)]

BAUD = 57600
PARAM_SET_ID = mavutil.mavlink.MAVLINK_MSG_ID_PARAM_SET


@pytest.fixture()
def cable():
    c = SerialCable(baud=BAUD)  # the vehicle's end is a pty SITL opens itself
    try:
        yield c
    finally:
        c.stop()


def test_capture_write_and_read_back_over_a_57600_baud_serial_line(start_sitl, cable, tmp_path):
    sitl = start_sitl(InjectedErrors.random(11, mag_orient=6), serial2=f"uart:{cable.vehicle_tty}:{BAUD}")
    cable.start()
    g = run_guided_capture(sitl, tmp_path, return_prob=0.0, seed=11, timeout_s=300,
                           args=("--connect", cable.path, "--baud", str(BAUD)))
    print(f"capture over serial at {BAUD}: {len(g.hand.poses)} poses, {g.took_s:.0f} s, rc {g.rc}, "
          f"cable {cable.stats}")
    assert g.hand.error is None, g.hand.error
    report = json.loads((tmp_path / "run.json").read_text())
    rejected = {s["sensor"]: s["reasons"] for s in report["sensors"] if not s["accepted"]}
    assert g.rc == 0 and not rejected, f"rc {g.rc}, rejected {rejected}\n{g.status.text()[-3000:]}\n{g.stdout[-3000:]}"
    assert "written and verified" in g.stdout  # mavcal's own read-back, over the serial line
    assert cable.stats["to_tool"] > 0 and cable.stats["to_vehicle"] > 0
    s = sitl.score()  # read back again over the fixture's own channel
    print(f"SITL score: {s.line()}")
    assert s.max_heading_deg <= 0.2, s.line()  # the UDP capture's bar (test_sitl_capture.py); measured 0.148
    assert s.compass_ofs_error_mgauss <= 1.0 and s.orient_right, s.line()


NAMES = tuple(f"COMPASS_OFS{s}_{a}" for s in ("", "2", "3") for a in "XYZ") + tuple(
    f"INS_ACC{s}OFFS_{a}" for s in ("", "2") for a in "XYZ")


def test_a_cable_pulled_mid_write_and_plugged_back_never_leaves_parameters_in_doubt(start_sitl, cable, tmp_path):
    sitl = start_sitl(serial2=f"uart:{cable.vehicle_tty}:{BAUD}", measure_field=False)
    cable.start()
    before = sitl.get_params(NAMES)
    values = {n: (round(before[n] + 7.0 + k, 1) if n.startswith("COMPASS") else round(0.05 * (k - 9), 2))
              for k, n in enumerate(NAMES)}
    pfile = tmp_path / "cal.param"
    pfile.write_text("".join(f"{n} {v}\n" for n, v in values.items()))
    cable.pull_at(PARAM_SET_ID, 4, 3.0)
    proc = subprocess.run([sys.executable, "-m", "mavcal", "apply", str(pfile), "--connect", cable.path,
                           "--baud", str(BAUD), "--yes", "--backup", str(tmp_path / "b.param")],
                          capture_output=True, text=True, timeout=300, env=dict(os.environ, CI="", MAVCAL_TEST="1"))
    after = sitl.get_params(NAMES)
    print(f"pulled cable: rc {proc.returncode}, pulls {cable.pulls}, stderr {proc.stderr.strip()[-500:]}")
    assert len(cable.pulls) == 1 and cable.pulls[0][1] is not None, f"{cable.pulls}\n{proc.stderr}"
    assert cable.sent(PARAM_SET_ID) > 4  # the write went on after the cable came back
    assert proc.returncode in (0, 5), f"rc {proc.returncode}\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}"
    expect = ({n: float(np.float32(v)) for n, v in values.items()} if proc.returncode == 0 else before)
    assert after == pytest.approx(expect, abs=1e-6), proc.stdout
    assert "went away" in proc.stderr and "is back" in proc.stderr
