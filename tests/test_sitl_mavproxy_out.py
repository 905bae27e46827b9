"""mavcal beside a ground station that holds the cable: MAVProxy on ArduPilot SITL's serial line (a pty,
:class:`mavcal.testing.serial_cable.SerialCable`) forwards to mavcal with ``--out udp:127.0.0.1:PORT``
(docs/live-link.md, "Beside a ground station"); ``mavcal apply --connect udpin:127.0.0.1:PORT`` writes
through it and reads back (a free port here, 14551 in the docs, so that parallel tests never share one)."""
from __future__ import annotations

import importlib.util
import os
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from mavcal.testing.serial_cable import SerialCable

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(300),
              pytest.mark.skipif(importlib.util.find_spec("MAVProxy") is None,
                                 reason="MAVProxy is not installed (pip install --no-deps MAVProxy)")]

NAMES = ("COMPASS_OFS_X", "COMPASS_OFS_Y", "COMPASS_OFS_Z")


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_apply_behind_mavproxy_out_on_the_serial_line(start_sitl, tmp_path):
    cable = SerialCable(baud=115200)
    mavproxy = None
    try:
        sitl = start_sitl(serial2=f"uart:{cable.vehicle_tty}:115200", measure_field=False)
        cable.start()
        port = _free_udp_port()
        mavproxy = subprocess.Popen([sys.executable, "-m", "MAVProxy.mavproxy", "--master", cable.path,
                                     "--baudrate", "115200", "--out", f"udp:127.0.0.1:{port}", "--no-state",
                                     "--default-modules=link", "--daemon"],
                                    stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                    cwd=tmp_path)
        before = sitl.get_params(NAMES)
        values = {n: round(before[n] + 11.0 + k, 1) for k, n in enumerate(NAMES)}
        pfile = tmp_path / "cal.param"
        pfile.write_text("".join(f"{n} {v}\n" for n, v in values.items()))
        time.sleep(1.0)  # MAVProxy opens the port and starts forwarding
        proc = subprocess.run([sys.executable, "-m", "mavcal", "apply", str(pfile), "--connect",
                               f"udpin:127.0.0.1:{port}", "--yes", "--backup", str(tmp_path / "b.param")],
                              capture_output=True, text=True, timeout=180, env=dict(os.environ, CI="", MAVCAL_TEST="1"))
        assert mavproxy.poll() is None, "MAVProxy died"
        assert proc.returncode == 0, f"rc {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
        assert "written and verified" in proc.stdout
        assert sitl.get_params(NAMES) == pytest.approx({n: float(np.float32(v)) for n, v in values.items()}, abs=1e-6)
    finally:
        if mavproxy is not None:
            mavproxy.terminate()
            try:
                mavproxy.wait(timeout=10)
            except subprocess.TimeoutExpired:
                mavproxy.kill()
        cable.stop()
