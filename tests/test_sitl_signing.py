"""MAVLink 2 signing against the real ArduPilot SITL.

Signing is set up on the vehicle with SETUP_SIGNING (MAVProxy's key of the passphrase); from then
on ArduPilot drops unsigned messages on every channel but the first (SERIAL0, the fixture's own
control link, which therefore keeps working). The ``mavcal`` CLI talks on SERIAL1
(``sitl.tool_device``): with the right key it writes and verifies; with none or a wrong one it
says in one line that the vehicle requires signing (exit 8), not that the link is lossy, and
nothing is written (the fixture sees every accepted PARAM_SET as an echo on its channel).

SETUP_SIGNING is sent on SERIAL1 before the tool uses it (ArduPilot takes it on any channel
while no key is set): the fixture has no public call to send it on its control link.
"""
from __future__ import annotations

import json
import sys
import time

import pytest
from pymavlink import mavutil

from mavcal.link.signing import is_signed, key_from_passphrase
from mavcal.testing.sitl import SitlVehicle, require_sitl

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(240)]

PASSPHRASE = "mavcal sitl signing test"
KEY = key_from_passphrase(PASSPHRASE)
NAMES = ["COMPASS_OFS_X", "COMPASS_OFS_Y"]


def setup_signing(sitl: SitlVehicle, key: bytes, timeout_s: float = 20.0) -> None:
    """SETUP_SIGNING on SERIAL1 until the vehicle's heartbeats arrive signed (as MAVProxy's
    ``signing setup``: the key and the current time since 2015 in 10 us units)."""
    with sitl.netns():
        conn = mavutil.mavlink_connection(sitl.tool_device, source_system=255, source_component=190,
                                          dialect="ardupilotmega")
    try:
        hb = conn.wait_heartbeat(timeout=timeout_s)
        assert hb is not None, "no heartbeat on SERIAL1"
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            stamp = int((time.time() - 1420070400) * 1e5)
            conn.mav.setup_signing_send(conn.target_system, conn.target_component, list(key), stamp)
            m = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=1.5)
            if m is not None and is_signed(m):
                return
        raise AssertionError("the vehicle does not sign after SETUP_SIGNING")
    finally:
        conn.close()


@pytest.fixture(scope="module")
def sitl():
    require_sitl()
    with SitlVehicle(wrong_calibration=False) as v:
        setup_signing(v, KEY.secret)
        yield v


def apply(sitl: SitlVehicle, tmp_path, values: dict[str, float], *args: str, verbose: bool = False):
    cal = tmp_path / "cal.param"
    cal.write_text("".join(f"{n} {v}\n" for n, v in values.items()))
    t0 = time.monotonic()
    r = sitl.run([sys.executable, "-m", "mavcal", *(["-vv"] if verbose else []), "apply", str(cal), "--connect",
                  sitl.tool_device, "--yes", "--backup", str(tmp_path / "backup.param"), *args], timeout=120)
    return r, time.monotonic() - t0


@pytest.mark.parametrize("key_args,words", [((), "requires MAVLink 2 signing"),
                                            (("--signing-key", "not the passphrase"), "signed with a different key")])
def test_no_key_or_a_wrong_key_is_one_clear_line_and_nothing_written(sitl, tmp_path, key_args, words):
    before = sitl.get_params(NAMES)
    mark = len(sitl.param_values)
    r, took = apply(sitl, tmp_path, {"COMPASS_OFS_X": before["COMPASS_OFS_X"] + 7.5}, *key_args)
    print(f"{key_args or 'no key'}: exit {r.returncode} after {took:.1f} s: {r.stderr.strip()}")
    assert r.returncode == 8, r.stderr + r.stdout
    assert r.stderr.count("\n") == 1 and words in r.stderr, r.stderr
    assert "no heartbeat" not in r.stderr and "incomplete" not in r.stderr
    assert sitl.writes_since(mark, NAMES) == []
    assert sitl.get_params(NAMES) == before


def test_right_key_writes_and_verifies_and_never_shows_the_key(sitl, tmp_path):
    before = sitl.get_params(NAMES)
    want = {"COMPASS_OFS_X": before["COMPASS_OFS_X"] + 4.25, "COMPASS_OFS_Y": before["COMPASS_OFS_Y"] - 2.5}
    keyfile = tmp_path / "signing.key"
    keyfile.write_text(PASSPHRASE + "\n")
    r, took = apply(sitl, tmp_path, want, "--signing-key-file", str(keyfile), verbose=True)
    print(f"right key: exit {r.returncode} after {took:.1f} s")
    assert r.returncode == 0, r.stderr + r.stdout
    assert "written and verified" in r.stdout and "(signed)" in r.stderr
    assert sitl.get_params(NAMES) == pytest.approx(want, rel=1e-6)
    for secret in (PASSPHRASE, KEY.secret.hex()):
        assert secret not in r.stdout + r.stderr
    # and back, with the passphrase on the command line
    restore = sitl.run([sys.executable, "-m", "mavcal", "restore", str(tmp_path / "backup.param"), "--connect",
                        sitl.tool_device, "--yes", "--signing-key", PASSPHRASE], timeout=120)
    assert restore.returncode == 0, restore.stderr
    assert sitl.get_params(NAMES) == pytest.approx(before, rel=1e-6)


def test_a_signed_live_recording_never_puts_the_key_in_its_report(sitl, tmp_path):
    """A 3 s live recording is too short to calibrate (exit 4), but it was read over the
    signed link and its JSON report is written: the key is not in it, nor in -vv's output."""
    out = tmp_path / "run.json"
    r = sitl.run([sys.executable, "-m", "mavcal", "-vv", "calibrate", sitl.tool_device, "--duration", "3",
                  "--json", str(out), "--signing-key", PASSPHRASE], timeout=120)
    assert r.returncode == 4, r.stderr[-2000:]
    text = out.read_text()
    report = json.loads(text)
    assert report["exit_code"] == 4
    for secret in (PASSPHRASE, KEY.secret.hex()):
        assert secret not in text and secret not in r.stdout + r.stderr
