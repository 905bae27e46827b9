"""End to end against PX4's own flight code: PX4 SITL in external-simulator mode (none_iris), posed by
mavcal's poser (mavcal/testing/px4_poser.py) with random sensor errors and a wrong calibration in force.
A guided ``mavcal capture --connect --write`` (a scripted hand follows its advice), and a plain
``mavcal calibrate DEVICE --write``, record live, calibrate, write CAL_* through the safe writer; the values
are read back from PX4, the INT32 device ids are intact, the written calibration is scored against the
truth, and PX4's own calibrated output after the write (SCALED_IMU accelerometer, HIGHRES_IMU
magnetometer) agrees with the poser's truth.

The MAVProxy module in a real MAVProxy does the same guided capture and write (seed 3): PX4's INT32
device ids decoded through MAVProxy's feed, SCALED_IMU filed (PX4 refuses RAW_IMU).

In CI: guided captures on seeds 4 and 5 (~40 s each: the poses are held in real time) and one through
MAVProxy (seed 3, ~40 s); ``MAVCAL_PX4_SEEDS=1,2`` runs other guided captures (see SEEDS), and
``MAVCAL_PX4_CALIBRATE=1`` adds the plain live calibration (``mavcal calibrate DEVICE --write``, ~65 s)."""
from __future__ import annotations

import json
import os
import threading
import time

import numpy as np
import pytest

from mavcal.testing.px4_sim import truth_errors
from mavcal.testing.simlog import DEFAULT_POSES_DEG

pytestmark = [pytest.mark.sitl, pytest.mark.slow, pytest.mark.xdist_group("heavy")]  # see test_px4_sitl.py

#: the CLI's guided captures in CI. Seed 1 passes but holds twice as many poses (~90 s). Seed 2 once read
#: 0.31 deg off in PX4's HIGHRES_IMU after the write (2 of 4 full-suite runs): PX4 had left its last small
#: CAL_MAG0_ZODIAG change out of use, as it does with any change of a CAL_* vector up to a threshold
#: (test_a_small_change_is_taken_into_use_through_the_detour below); the writer's detours now put every
#: vector into use (seed 2 since: 0.004-0.056 deg). MAVCAL_PX4_SEEDS=2 runs seed 2.
SEEDS = [int(s) for s in os.environ.get("MAVCAL_PX4_SEEDS", "4,5").split(",")]
HOLD_S, MOVE_S = 2.5, 1.0


def _pose_forever(poser, stop: threading.Event) -> None:
    while not stop.is_set():
        for p in DEFAULT_POSES_DEG:
            if stop.is_set():
                return
            poser.turn_to(*p, MOVE_S)
            stop.wait(HOLD_S)


def _px4_output(link, poser, poses) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """(SCALED_IMU accel m/s^2, HIGHRES_IMU mag mGauss, true f_body, true B_body) per pose: medians of
    the readings PX4 stamped 1.0-2.5 s (of its own clock) after the first one received once the pose
    was reached. PX4's clock is the poser's HIL_SENSOR time (lockstep): under CI load it runs slower
    than the wall clock, so a window of wall time may hold readings from before the pose, or none."""
    from mavcal.link.streams import PX4_STREAM_MESSAGES, start_streams

    start_streams(link, 50.0, message_ids=tuple(PX4_STREAM_MESSAGES.values()))
    out = []
    for p in poses:
        poser.turn_to(*p, MOVE_S)
        acc: list = []
        mag: list = []
        tokens = [link.add_handler("SCALED_IMU", lambda m, acc=acc: acc.append((m.time_boot_ms * 1e3,
                                                                                m.xacc, m.yacc, m.zacc))),
                  link.add_handler("HIGHRES_IMU", lambda m, mag=mag: mag.append((m.time_usec, m.xmag, m.ymag,
                                                                                 m.zmag)))]
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline and not (acc and mag and min(acc[-1][0], mag[-1][0])
                                                   >= min(acc[0][0], mag[0][0]) + 2.5e6):
            link.pump(0.05)
        for t in tokens:
            link.remove_handler(t)
        f, B = poser.truth_body()
        t0 = min(acc[0][0], mag[0][0]) + 1.0e6
        a = np.array([r[1:] for r in acc if r[0] >= t0])
        m = np.array([r[1:] for r in mag if r[0] >= t0])
        assert len(a) >= 10 and len(m) >= 10, (len(acc), len(mag))  # PX4's clock reached the window
        out.append((np.median(a, axis=0) * 9.80665 / 1000, np.median(m, axis=0) * 1000, f, B))
    return out


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def _calibrate_device(px4, poser, tmp_path) -> tuple[int, dict]:
    """``mavcal calibrate DEVICE --write`` (in-process, in the namespace) while a hand turns the vehicle
    through the poses again and again."""
    from mavcal.cli import main

    stop = threading.Event()
    hand = threading.Thread(target=_pose_forever, args=(poser, stop), daemon=True)
    hand.start()
    report = tmp_path / "run.json"
    try:
        with px4.netns():
            rc = main(["calibrate", px4.device, "--duration", "46", "--write", "--yes",
                       "--backup", str(tmp_path / "backup.param"), "--json", str(report)])
    finally:
        stop.set()
        hand.join(timeout=10)
    return rc, json.loads(report.read_text()) if report.exists() else {}


def _guided_capture(px4, poser, tmp_path, seed: int) -> tuple[int, dict]:
    """``mavcal capture --connect DEVICE --write --yes`` with a scripted hand following its advice."""
    from mavcal.testing.px4_poser import PosedPx4
    from mavcal.testing.sitl_hand import run_guided_capture

    g = run_guided_capture(PosedPx4(px4, poser), tmp_path, return_prob=0.0, seed=seed, timeout_s=150)
    report = tmp_path / "run.json"
    return g.rc, json.loads(report.read_text()) if report.exists() else {}


def _mavproxy_capture(px4, poser, tmp_path, seed: int) -> tuple[int, dict]:
    """The MAVProxy module in a real MAVProxy against PX4: load, ``mavcal start``, a hand following the
    module's advice, ``mavcal write yes``; the verdicts and written rows parsed from its output in the
    shape of the JSON report (``sensors``, ``parameters``). PX4's INT32 device ids must be decoded
    through MAVProxy's feed (the module tells the worker the HEARTBEAT's autopilot)."""
    import importlib.util
    import re

    if importlib.util.find_spec("MAVProxy") is None:
        pytest.fail("MAVProxy is not installed (pip install --no-deps MAVProxy, as README.md says)")
    from test_sitl_mavproxy import SitlMAVProxy, changed_rows

    from mavcal.testing.px4_poser import PosedPx4
    from mavcal.testing.sitl_hand import AdviceHand

    posed = PosedPx4(px4, poser)
    mp = SitlMAVProxy(posed, tmp_path)
    hand = AdviceHand(posed, mp.advice, return_prob=0.0, seed=seed)
    try:
        mp.expect(r"Detected vehicle 1:1", timeout=30)
        mp.expect(r"Loaded module mavcal\.mavproxy_mavcal", after=mp.send("module load mavcal.mavproxy_mavcal"))
        mp.send(f"mavcal set backup_dir {tmp_path / 'backups'}")
        _, at = mp.expect(r"mavcal: capture started", timeout=60, after=mp.send("mavcal start"))
        hand.start()
        m, at = mp.expect(r"capture (finished|aborted)", timeout=150, after=at)
        hand.stop()
        assert m.group(1) == "finished" and hand.error is None, "\n".join(mp.lines[-30:])
        mp.expect(r"mavcal: fit done", timeout=60, after=at)
        sensors = []
        for line in mp.lines[at:]:
            v = re.match(r"^(accel\d|compass\d): (accepted|rejected.*)$", line)
            if v:
                sensors.append({"sensor": v.group(1), "accepted": v.group(2) == "accepted"})
        mark = mp.send("mavcal write yes")
        mp.expect(r"mavcal: \d+ parameters written and verified", timeout=60, after=mark)
        rows = changed_rows(mp.lines, mark)
        mp.expect(r"mavcal: unloaded; worker stopped; mavcal threads left: none",
                  after=mp.send("module unload mavcal"))
        # the recovery's warnings: logged once, then in the summary; not at every one of ~40 updates
        assert sum("device id not in the data" in line for line in mp.lines) <= 4
        assert sum("SET_MESSAGE_INTERVAL" in line for line in mp.lines) <= 8  # asked once, not again and again
    finally:
        hand.stop()
        mp.close()
        (tmp_path / "mavproxy.txt").write_text("\n".join(mp.lines))
    return 0, {"sensors": sensors, "parameters": {n: {"new": v, "written": True, "changed": True}
                                                  for n, v in rows.items()}}


#: (how, seed): guided captures (the CLI's advice followed by a hand) and the MAVProxy module's guided
#: capture, three seeds in all; a plain live calibration with MAVCAL_PX4_CALIBRATE=1
CASES = ([("capture", s) for s in SEEDS] + [("mavproxy", 3)]
         + ([("calibrate", 6)] if os.environ.get("MAVCAL_PX4_CALIBRATE") == "1" else []))


@pytest.mark.parametrize("how, seed", CASES)
def test_live_calibration_of_px4_is_written_and_px4_agrees_with_the_truth(how, seed, tmp_path):
    from mavcal.link.connection import open_link
    from mavcal.link.params import fetch_all_params
    from mavcal.px4.params import accel_names, mag_names
    from mavcal.testing.px4_poser import posed_px4
    from mavcal.testing.px4_sitl import require_px4

    require_px4()
    with posed_px4(seed) as (posed, truth):
        px4, poser = posed.px4, posed.poser
        rc, run = {"capture": _guided_capture, "mavproxy": _mavproxy_capture,
                   "calibrate": lambda *a: _calibrate_device(*a[:3])}[how](px4, poser, tmp_path, seed)
        assert rc == 0, (rc, run.get("sensors"), run.get("warnings"), px4.log_tail(400))
        assert {s["sensor"] for s in run["sensors"] if s["accepted"]} == {"accel0", "compass0"}
        written = {n: v["new"] for n, v in run["parameters"].items()}
        assert all(v["written"] for v in run["parameters"].values() if v["changed"])
        err = truth_errors(truth, written)
        assert err["heading_deg"] <= 0.2 and err["tilt_deg"] <= 0.05, err
        assert err["mag_offset_gauss"] <= 0.001, err
        with px4.netns():
            link = open_link(px4.device)
        try:
            table = fetch_all_params(link, timeout_s=20)
            for n, v in written.items():  # read back from the vehicle (float32 on the wire)
                assert table[n][0] == pytest.approx(v, rel=1e-6, abs=1e-7), n
            assert table[accel_names(0)["id"]] == (truth.accel_id, 6)  # INT32 device ids intact
            assert table[mag_names(0)["id"]] == (truth.mag_id, 6)
            # PX4's own calibrated output after the write, against the poser's truth
            outputs = _px4_output(link, poser, [(0, 0, 0), (30, -20, 120), (-60, 40, 250)])
            for acc, mag, f, B in outputs:
                print(f"{how} seed {seed}: PX4 after the write: accel {_angle_deg(acc, f):.4f} deg, "
                      f"{np.linalg.norm(acc) - np.linalg.norm(f):+.4f} m/s^2; mag {_angle_deg(mag, B):.4f} deg "
                      f"(PX4 {np.round(mag, 2)}, truth {np.round(B, 2)} mGauss); written: {err}")
            for acc, mag, f, B in outputs:
                assert _angle_deg(acc, f) <= 0.05 and abs(np.linalg.norm(acc) - np.linalg.norm(f)) <= 0.02
                assert _angle_deg(mag, B) <= 0.2, (mag, B)
        finally:
            link.close()


def _highres_mag_mgauss(link, seconds: float) -> np.ndarray:
    """Median HIGHRES_IMU magnetometer (mGauss) over ``seconds`` of PX4's own clock, the first 0.5 s left out."""
    rows: list = []
    token = link.add_handler("HIGHRES_IMU", lambda m: rows.append((m.time_usec, m.xmag, m.ymag, m.zmag)))
    deadline = time.monotonic() + 30.0
    try:
        while time.monotonic() < deadline and not (rows and rows[-1][0] >= rows[0][0] + seconds * 1e6):
            link.pump(0.05)
    finally:
        link.remove_handler(token)
    t0 = rows[0][0] + 0.5e6
    return np.median(np.array([r[1:] for r in rows if r[0] >= t0]), axis=0) * 1000


def test_a_small_change_is_taken_into_use_through_the_detour(tmp_path, monkeypatch):
    """PX4 takes a changed CAL_* vector into use only when it differs from the one in use by more than a
    threshold (0.01 for an off-diagonal; see mavcal.px4.params.DETOUR_STEP): a plain PARAM_SET of
    CAL_MAG0_YODIAG 0.009 away reads back new while PX4's calibrated field (HIGHRES_IMU, the poser's
    exact raw field) stays as the old value gives it (seen: within 0.25 mGauss; the new value would move
    it by ~4). mavcal's writer sends the vector's pivot a detour first (detoured_order): as small a
    change the other way is then in use at once (seen: within 0.12 mGauss of mavcal's model of PX4)."""
    from scipy.spatial.transform import Rotation

    import mavcal.link.writer as writer
    from mavcal.autopilot.rotations import euler_to_matrix
    from mavcal.link.connection import open_link
    from mavcal.link.params import fetch_all_params
    from mavcal.link.streams import PX4_STREAM_MESSAGES, start_streams
    from mavcal.px4.firmware import mag_cal_from_params
    from mavcal.testing.px4_poser import posed_px4
    from mavcal.testing.px4_sim import raw_at
    from mavcal.testing.px4_sitl import require_px4

    require_px4()
    with posed_px4(2) as (posed, truth):
        px4, poser = posed.px4, posed.poser
        poser.turn_to(0, 0, 120, MOVE_S)
        raw = raw_at(truth, Rotation.from_matrix(euler_to_matrix(*np.radians([0, 0, 120]))[None]))[1][0]
        with px4.netns():
            link = open_link(px4.device)
        try:
            start_streams(link, 50.0, message_ids=tuple(PX4_STREAM_MESSAGES.values()))

            def write(value: float, name: str) -> np.ndarray:
                report = writer.write_params(link, {"CAL_MAG0_YODIAG": value}, force_save=(),
                                             backup_path=str(tmp_path / f"{name}.param"))
                assert report.complete, report.message
                link.pump(0.5)
                table = fetch_all_params(link, timeout_s=20)
                assert table["CAL_MAG0_YODIAG"][0] == pytest.approx(value, abs=1e-6)
                return mag_cal_from_params({k: v for k, (v, _) in table.items()}, truth.mag_id).correct(raw)

            old = mag_cal_from_params(truth.params, truth.mag_id).correct(raw)
            assert np.abs(_highres_mag_mgauss(link, 2.0) - old).max() < 0.6
            y0 = truth.params["CAL_MAG0_YODIAG"]
            with monkeypatch.context() as m:
                m.setattr(writer, "detoured_order", lambda changes: (dict(changes), {}))
                new = write(y0 + 0.009, "plain")
            seen = _highres_mag_mgauss(link, 2.0)
            print(f"plain: PX4 - old {np.abs(seen - old).max():.2f}, PX4 - new {np.abs(seen - new).max():.2f}")
            assert np.abs(new - old).max() > 2.5  # what the change would do
            assert np.abs(seen - old).max() < 0.6  # PX4 left it out of use
            new = write(y0 - 0.009, "detoured")
            seen = _highres_mag_mgauss(link, 2.0)
            print(f"detoured: PX4 - old {np.abs(seen - old).max():.2f}, PX4 - new {np.abs(seen - new).max():.2f}")
            assert np.abs(new - old).max() > 2.5
            assert np.abs(seen - new).max() < 0.6  # in use
        finally:
            link.close()
