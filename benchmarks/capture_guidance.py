"""Guided capture vs random poses: how many poses until the heading-error target.

A simulated hand holds an ArduPilot-like vehicle (the loopback test vehicle's sensor model,
:class:`mavcal.testing.vehicle.TestVehicle`, with random true sensor errors, its own
calibration parameters applied and int16 truncation as in RAW_IMU) still in one pose after
another, turning between them at a realistic rate (the gyro sees the motion). Telemetry at
10 Hz, 2 s per hold. The hand either follows :class:`mavcal.capture.CaptureSession`'s
advice (with 5 deg roll/pitch and 10 deg heading error, as a person would) or picks
uniformly random orientations. Both stop by the same rule: the 95 % heading error bound
<= 0.5 deg with >= 8 intervals.

    python benchmarks/capture_guidance.py [--seeds 20]   # writes benchmarks/results/capture_guidance.md
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from mavcal.capture import CaptureConfig, CaptureSession, euler_matrix
from mavcal.core.rotations import exp_so3, random_rotations
from mavcal.sources.types import SensorSeries
from mavcal.testing.vehicle import TestVehicle, VehicleTruth

OUT = Path(__file__).resolve().parent / "results"
MG = 9.80665e-3


def _log_so3(R: np.ndarray) -> np.ndarray:
    c = np.clip((np.trace(R) - 1) / 2, -1, 1)
    th = np.arccos(c)
    if th < 1e-9:
        return np.zeros(3)
    if np.pi - th < 1e-6:  # 180 deg: axis from the symmetric part
        w, V = np.linalg.eigh((R + np.eye(3)) / 2)
        return V[:, -1] * th
    return th / (2 * np.sin(th)) * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])


class Hand:
    """Moves the simulated vehicle and produces RAW_IMU-like readings at ``rate_hz``."""

    def __init__(self, vehicle: TestVehicle, rate_hz: float = 10.0, hold_s: float = 2.0, turn_dps: float = 90.0):
        self.v, self.rate, self.hold_s, self.turn = vehicle, rate_hz, hold_s, np.radians(turn_dps)
        self.t = 0.0

    def _sample(self, gyro=None):
        s = self.v.corrected_sensors()
        g = s["gyro_rads"][0] if gyro is None else gyro + s["gyro_rads"][0]
        return s["accel_mps2"][0], s["mag_mgauss"][0], g

    def go(self, C: np.ndarray) -> list:
        R0 = self.v.attitude
        w = _log_so3(R0.T @ C)  # body-frame rotation vector from R0 to C
        ang = float(np.linalg.norm(w))
        n_move = max(2, int(np.ceil(ang / self.turn * self.rate)))
        rows = []
        for k in range(1, n_move + 1):
            self.v.set_attitude(R0 @ exp_so3(w * k / n_move))
            rows.append((self.t,) + self._sample(gyro=w / (n_move / self.rate)))
            self.t += 1 / self.rate
        self.v.set_attitude(C)
        for _ in range(int(self.hold_s * self.rate)):
            rows.append((self.t,) + self._sample())
            self.t += 1 / self.rate
        t = np.array([r[0] for r in rows])
        acc = np.trunc(np.array([r[1] for r in rows]) / MG) * MG  # int16 milli-g, truncated
        mag = np.trunc(np.array([r[2] for r in rows]))
        gyr = np.trunc(np.array([r[3] for r in rows]) * 1000) / 1000
        return [SensorSeries("accel", 0, "RAW_IMU", t, acc), SensorSeries("mag", 0, "RAW_IMU", t, mag),
                SensorSeries("gyro", 0, "RAW_IMU", t, gyr)]


def run(seed: int, guided: bool, target: float = 0.5, max_poses: int = 40):
    rng = np.random.default_rng(10_000 + seed)
    v = TestVehicle(truth=VehicleTruth.random(seed), seed=seed)
    hand = Hand(v)
    sess = CaptureSession(v.params, CaptureConfig(target_heading_deg=target, max_intervals=max_poses))
    B = np.array(v.truth.earth_field_ned_mgauss)
    decl = np.degrees(np.arctan2(B[1], B[0]))
    st = sess.update()
    for k in range(max_poses):
        if guided:
            a = st.next_pose
            C = euler_matrix(a.roll_deg + rng.normal(0, 5), a.pitch_deg + rng.normal(0, 5),
                             a.yaw_deg + decl + rng.normal(0, 10))
        else:
            C = random_rotations(1, rng)[0]
        sess.add(hand.go(C))
        st = sess.update()
        if st.done:
            return k + 1, st
    return max_poses, st


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    args = ap.parse_args(argv)
    rows = []
    t0 = time.perf_counter()
    for seed in range(args.seeds):
        g, sg = run(seed, True)
        r, sr = run(seed, False)
        rows.append({"seed": seed, "guided": g, "random": r, "guided_heading": sg.heading_95_deg,
                     "random_heading": sr.heading_95_deg, "guided_reason": sg.reason, "random_reason": sr.reason,
                     "guided_ok": bool(sg.done and not sg.aborted and sg.heading_95_deg is not None
                                       and sg.heading_95_deg <= 0.5)})
        print(f"seed {seed}: guided {g} poses ({sg.reason}); random {r} poses ({sr.reason})", file=sys.stderr)
    g = np.array([x["guided"] for x in rows])
    r = np.array([x["random"] for x in rows])
    ratio = np.median(g) / np.median(r)
    L = ["# Guided capture vs random poses\n",
         f"Produced by `python benchmarks/capture_guidance.py --seeds {args.seeds}` ({time.perf_counter() - t0:.0f} s). "
         "Poses until the 95 % heading-error bound is <= 0.5 deg (at least 8 intervals), simulated hand, "
         "10 Hz telemetry, 2 s holds, int16 truncation.\n",
         "| | median poses | mean | max | reached the target |", "|---|---|---|---|---|",
         f"| guided (heading criterion) | {np.median(g):.1f} | {g.mean():.1f} | {g.max()} | "
         f"{sum(x['guided_ok'] for x in rows)}/{len(rows)} |",
         f"| random orientations | {np.median(r):.1f} | {r.mean():.1f} | {r.max()} | "
         f"{sum((x['random_heading'] or 99) <= 0.5 for x in rows)}/{len(rows)} |",
         "", f"**median guided / median random = {ratio:.2f}** (bar: <= 0.70)", "",
         "| seed | guided | random |", "|---|---|---|"]
    L += [f"| {x['seed']} | {x['guided']} | {x['random']} |" for x in rows]
    OUT.mkdir(exist_ok=True)
    (OUT / "capture_guidance.md").write_text("\n".join(L) + "\n")
    (OUT / "capture_guidance.json").write_text(json.dumps(rows, default=float, indent=1))
    print("\n".join(L))
    return 0


if __name__ == "__main__":
    from bench_output import output_dir  # --save / --out: where the results go (benchmarks/README.md)

    OUT, _argv = output_dir(sys.argv[1:])
    sys.exit(main(_argv))
