"""The SITL fixture itself (mavcal.testing.sitl): isolation, truth, clean-up, skip rules.

Also where the real ArduPilot and the loopback vehicle (mavcal.testing.vehicle) differ, on
this build: a PARAM_SET of an unknown name gets no answer at all (no PARAM_ERROR, no
STATUSTEXT), and device ids (COMPASS_DEV_ID, INS_ACC_ID) are *accepted* over MAVLink, where
the loopback vehicle denies them ("Param write denied").
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time

import numpy as np
import pytest

from mavcal.ardupilot import firmware as fw
from mavcal.autopilot.rotations import euler_to_matrix
from mavcal.testing import sitl as sitl_mod
from mavcal.testing.sitl import WRONG_CALIBRATION, InjectedErrors, SitlVehicle, require_sitl

SITL = pytest.mark.sitl


@pytest.fixture(scope="module")
def sitl():
    require_sitl()
    with SitlVehicle(InjectedErrors.random(5, mag_orient=6), relay=True) as v:
        yield v


def gone(pid: int, within_s: float = 10.0) -> bool:
    deadline = time.monotonic() + within_s
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.1)
    return False


@SITL
def test_namespace_is_private_with_loopback_only(sitl):
    assert os.readlink(f"/proc/{sitl.pid}/ns/net") != os.readlink("/proc/self/ns/net")
    assert os.readlink(f"/proc/{sitl.pid}/ns/net") == os.readlink(sitl.netns_path)
    devs = [line.split(":")[0].strip() for line in open(f"/proc/{sitl.pid}/net/dev").read().splitlines()[2:]]
    assert devs == ["lo"]
    # the RC input port SITL binds on every address at boot is inside the namespace only
    rc_port = f"{5501 + 10 * sitl.instance:04X}"
    inside = open(f"/proc/{sitl.pid}/net/udp").read()
    assert f"00000000:{rc_port}" in inside
    mine = f"/proc/self/task/{threading.get_native_id()}/ns/net"
    with sitl.netns():  # this thread, for a moment, in the vehicle's namespace
        assert os.readlink(mine) == os.readlink(sitl.netns_path)
    assert os.readlink(mine) != os.readlink(sitl.netns_path)
    r = sitl.run(["cat", "/proc/self/net/dev"])
    assert r.returncode == 0 and [line.split(":")[0].strip() for line in r.stdout.splitlines()[2:]] == ["lo"]


@SITL
def test_in_process_links_on_the_tool_and_relay_ports(sitl):
    """A socket opened in ``with sitl.netns():`` stays in the vehicle's namespace: in-process
    code talks to SITL on SERIAL1 and SERIAL2 from this thread after the block."""
    from mavcal.link.connection import open_link

    with sitl.netns():
        tool = open_link(sitl.tool_device, timeout_s=15)
        relay = open_link(sitl.relay_device, timeout_s=15)
    try:
        for link in (tool, relay):
            assert (link.target_system, link.target_component) == (1, 1)
            t = link.last_rx_s
            assert link.wait(lambda lk=link, t0=t: lk.last_rx_s > t0, 5.0)  # heartbeats keep coming
    finally:
        tool.close()
        relay.close()


@SITL
def test_truth_is_what_sitl_reads(sitl):
    """With the ideal calibration in force, SITL's corrected readings are the true specific
    force and the measured field, rotated by SIMSTATE's attitude: the truth, the error model,
    COMPASS_ORIENT 6 and the field measurement agree with the firmware."""
    assert sitl.score(sitl.truth).max_heading_deg < 1e-3
    wrong = sitl.score()
    assert wrong.max_heading_deg > 5 and not wrong.orient_right
    B = sitl.field_ned_mgauss
    assert 540 < np.linalg.norm(B) < 620 and -70 < np.degrees(np.arcsin(B[2] / np.linalg.norm(B))) < -60
    sitl.set_params(sitl.truth)
    try:
        st = sitl.set_pose(30, -20, 100)
        acc, mag = sitl.read_imu(50)
        C = euler_to_matrix(*np.radians([st.roll_deg, st.pitch_deg, st.yaw_deg]))
        np.testing.assert_allclose(acc, C.T @ [0, 0, -fw.GRAVITY_MSS], atol=0.03)
        np.testing.assert_allclose(mag, C.T @ B, atol=2.5)
    finally:
        sitl.set_params({n: WRONG_CALIBRATION.get(n, v) for n, v in sitl.truth.items()})
        sitl.set_pose(0, 0, 0)


@SITL
def test_unknown_name_gets_no_answer_and_device_ids_are_writable(sitl):
    n_values, n_texts = len(sitl.param_values), len(sitl.statustexts)
    sitl.send_param_set("NOT_A_PARAM", 2.0)
    time.sleep(2.0)
    assert sitl.param_values[n_values:] == [] or all(n != "NOT_A_PARAM" for n, _ in sitl.param_values[n_values:])
    assert not any("NOT_A_PARAM" in t or "denied" in t.lower() for t in sitl.statustexts[n_texts:])
    dev = sitl.get_param("COMPASS_DEV_ID")
    try:
        sitl.set_params({"COMPASS_DEV_ID": 5})  # accepted and echoed (the loopback vehicle denies it)
        assert sitl.get_param("COMPASS_DEV_ID") == 5
    finally:
        sitl.set_params({"COMPASS_DEV_ID": dev})


@SITL
def test_stop_leaves_nothing_running(start_sitl):
    v = start_sitl(measure_field=False)
    child = v.popen(["sleep", "300"])
    pids = [v.pid, v._keeper.pid, child.pid]
    workdir = v.workdir
    assert workdir.is_dir() and all(not gone(p, 0.1) for p in pids)
    v.stop()
    assert all(gone(p) for p in pids) and not workdir.exists()


_STARTER = """
import sys, time
from mavcal.testing.sitl import SitlVehicle
v = SitlVehicle(measure_field=False).start()
print(v.pid, v._keeper.pid, v.popen(["sleep", "300"]).pid, v.workdir, flush=True)
time.sleep(300)
"""


@SITL
def test_a_killed_test_process_takes_its_sitl_with_it():
    require_sitl()
    p = subprocess.Popen([sys.executable, "-c", _STARTER], stdout=subprocess.PIPE, text=True)
    try:
        *pids_text, workdir = p.stdout.readline().split()
        pids = [int(x) for x in pids_text]
        assert len(pids) == 3 and all(not gone(x, 0.1) for x in pids)
    finally:
        p.send_signal(signal.SIGKILL)  # no finaliser, no atexit: only the parent-death signal
        p.wait()
    assert all(gone(x) for x in pids)
    # its working directory is left behind; the next vehicle started sweeps it away
    assert os.path.isdir(workdir)
    SitlVehicle(measure_field=False).start().stop()
    assert not os.path.exists(workdir)


@SITL
@pytest.mark.timeout(120)
def test_a_timed_out_test_stops_its_sitl(tmp_path):
    require_sitl()
    (tmp_path / "test_hang.py").write_text(textwrap.dedent("""
        import time
        import pytest
        from mavcal.testing.sitl import SitlVehicle

        @pytest.fixture
        def v():
            with SitlVehicle(measure_field=False) as v:
                yield v

        def test_hangs(v):
            print("PIDS", v.pid, v._keeper.pid, flush=True)
            time.sleep(300)
    """))
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-s", "-p", "no:cacheprovider", "--timeout", "12",
                        "-o", "addopts=", str(tmp_path / "test_hang.py")], cwd=tmp_path, capture_output=True,
                       text=True, timeout=100)
    assert r.returncode == 1 and "Timeout" in r.stdout, r.stdout[-2000:]
    pids = [int(x) for x in r.stdout.split("PIDS", 1)[1].split()[:2]]
    assert all(gone(x, 1.0) for x in pids)


def test_no_sitl_skips_with_the_reason_and_fails_under_ci(monkeypatch, tmp_path):
    monkeypatch.setenv(sitl_mod.ENV_BINARY, str(tmp_path / "nowhere" / "arducopter"))
    monkeypatch.delenv("CI", raising=False)
    with pytest.raises(pytest.skip.Exception, match="no SITL binary at .*nowhere"):
        require_sitl()
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match="CI=true but SITL cannot run: no SITL binary"):
        require_sitl()


def test_injected_errors_from_a_seed():
    a, b = InjectedErrors.random(3), InjectedErrors.random(3, mag_orient=6)
    assert a.mag_ofs_mgauss == b.mag_ofs_mgauss and b.mag_orient == 6 and a != InjectedErrors.random(4)
    assert all(abs(x) <= 250 for x in a.mag_ofs_mgauss) and all(0.97 <= x <= 1.03 for x in a.acc_scale)
    p = b.sim_params()
    assert p["SIM_MAG1_ORIENT"] == 6 and p["SIM_ACC1_BIAS_X"] == b.acc_bias_mps2[0]
    t = b.ideal_params()
    assert t["COMPASS_ORIENT"] == 6 and t["COMPASS_OFS_Y"] == b.mag_ofs_mgauss[1]
    assert t["INS_ACCSCAL_Z"] == b.acc_scale[2]
    B = np.array([[232.0, 52.0, -528.0], [-10.0, 400.0, 100.0]])
    np.testing.assert_allclose(b.body_field(b.raw_mag_sensor(B)), B, atol=1e-9)
