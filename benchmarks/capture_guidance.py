"""Guided capture vs random poses: how many poses until every sensor reaches its target.

A simulated hand holds an ArduPilot-like vehicle (the loopback test vehicle's sensor model,
:class:`mavcal.testing.vehicle.TestVehicle`: 3 IMUs and 3 compasses with random true sensor
errors, its own calibration parameters applied and int16 truncation as in RAW_IMU /
SCALED_IMU2 / SCALED_IMU3) still in one pose after another, turning between them at a
realistic rate (the gyro sees the motion). Telemetry at 10 Hz, 2 s per hold. The hand either
follows :class:`mavcal.capture.CaptureSession`'s advice (with 5 deg roll/pitch and 10 deg
heading error, as a person would) or picks uniformly random orientations. Both stop by the
session's own rule with the product's default settings (``CaptureConfig()``), and the final
fit (``session.result()``, every sensor's verdict) is what the person would get.

    python benchmarks/capture_guidance.py [--seeds 20] [--save]
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
from mavcal.errors import MavcalError
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
    """Moves the simulated vehicle and produces RAW_IMU-like readings at ``rate_hz`` of the
    IMU/compass ``instances`` (0: RAW_IMU, 1: SCALED_IMU2, 2: SCALED_IMU3)."""

    MESSAGES = ("RAW_IMU", "SCALED_IMU2", "SCALED_IMU3")

    def __init__(self, vehicle: TestVehicle, rate_hz: float = 10.0, hold_s: float = 2.0, turn_dps: float = 90.0,
                 instances: tuple[int, ...] = (0,)):
        self.v, self.rate, self.hold_s, self.turn = vehicle, rate_hz, hold_s, np.radians(turn_dps)
        self.instances = instances
        self.t = 0.0

    def _sample(self, gyro=None):
        s = self.v.corrected_sensors()
        g = s["gyro_rads"] if gyro is None else gyro[None] + s["gyro_rads"]
        return s["accel_mps2"], s["mag_mgauss"], g

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
        out = []
        for i in self.instances:
            acc = np.trunc(np.array([r[1][i] for r in rows]) / MG) * MG  # int16 milli-g, truncated
            mag = np.trunc(np.array([r[2][i] for r in rows]))
            gyr = np.trunc(np.array([r[3][i] for r in rows]) * 1000) / 1000
            m = self.MESSAGES[i]
            out += [SensorSeries("accel", i, m, t, acc), SensorSeries("mag", i, m, t, mag),
                    SensorSeries("gyro", i, m, t, gyr)]
        return out


    def follow(self, sess, max_poses: int = 30, on_status=None):
        """Hold each pose the capture ``sess`` advises (its heading from magnetic north: the declination of
        the vehicle's field added) until the capture is done, ``on_status(status)`` returns True, or
        ``max_poses`` poses were held; returns the last status."""
        B = np.array(self.v.truth.earth_field_ned_mgauss)
        decl = np.degrees(np.arctan2(B[1], B[0]))
        st = sess.update()
        for _ in range(max_poses):
            if st.done:
                break
            a = st.next_pose
            sess.add(self.go(euler_matrix(a.roll_deg, a.pitch_deg, a.yaw_deg + decl)))
            st = sess.update()
            if on_status is not None and on_status(st):
                break
        return st


def _bounds(run) -> dict[str, float]:
    """Every sensor's 95 % bound from its gates: tilt (accelerometers), heading (compasses)."""
    return {g.sensor: g.value for g in run.gates.gates if g.name in ("tilt uncertainty", "heading uncertainty")}


def run(seed: int, guided: bool, max_poses: int = 40, instances: tuple[int, ...] = (0, 1, 2),
        rate_hz: float = 10.0, hold_s: float = 2.0) -> dict:
    """One capture with the product's default settings, then its final fit: poses, time, verdicts."""
    rng = np.random.default_rng(10_000 + seed)
    v = TestVehicle(truth=VehicleTruth.random(seed), seed=seed)
    hand = Hand(v, rate_hz=rate_hz, hold_s=hold_s, instances=instances)
    t0 = time.perf_counter()
    sess = CaptureSession(v.params, CaptureConfig(max_intervals=max_poses))
    B = np.array(v.truth.earth_field_ned_mgauss)
    decl = np.degrees(np.arctan2(B[1], B[0]))
    st = sess.update()
    poses = max_poses
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
            poses = k + 1
            break
    t_capture = time.perf_counter() - t0
    try:
        res = sess.result()
    except MavcalError as exc:  # nothing to fit (e.g. holds too short for a still interval)
        return {"poses": poses, "intervals": st.n_intervals, "reason": f"{st.reason}; {exc}",
                "heading": st.heading_95_deg, "capture_s": t_capture, "total_s": time.perf_counter() - t0,
                "verdicts": {}, "bounds": {}, "all_accepted": False, "rejected": {"all": [str(exc)]}}
    verdicts = {x.sensor: x.accepted for x in res.gates.verdicts()}
    return {"poses": poses, "intervals": st.n_intervals, "reason": st.reason, "heading": st.heading_95_deg,
            "capture_s": t_capture, "total_s": time.perf_counter() - t0, "verdicts": verdicts,
            "bounds": _bounds(res), "all_accepted": bool(verdicts) and all(verdicts.values()),
            "rejected": {x.sensor: list(x.reasons) for x in res.gates.verdicts() if not x.accepted}}


def _summary(rows: list[dict], mode: str) -> str:
    p = np.array([x[mode]["poses"] for x in rows])
    ok = sum(x[mode]["all_accepted"] for x in rows)
    t = np.median([x[mode]["total_s"] for x in rows])
    return f"{np.median(p):.1f} | {p.mean():.1f} | {p.min()}-{p.max()} | {ok}/{len(rows)} | {t:.1f} s"


def _worst(res: dict, kind: str) -> str:
    b = {k: v for k, v in res["bounds"].items() if k.startswith(kind)}
    if not b:
        return "-"
    k = max(b, key=lambda s: b[s])
    return f"{b[k]:.3g} ({k})"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--modes", nargs="+", default=["guided", "random"], choices=["guided", "random"])
    ap.add_argument("--baseline", metavar="JSON", help="a previous run's capture_guidance.json (e.g. of the code "
                                                       "before a change) to compare with, seed by seed")
    ap.add_argument("--label", default="", help="what code this run measures (written into the result)")
    ap.add_argument("--rate-hz", type=float, default=10.0, help="telemetry rate (default 10)")
    ap.add_argument("--hold-s", type=float, default=2.0, help="how long the hand holds each pose (default 2)")
    ap.add_argument("--name", default="capture_guidance", help="result file stem (default capture_guidance)")
    args = ap.parse_args(argv)
    rows = []
    t0 = time.perf_counter()
    for seed in range(args.seeds):
        row: dict = {"seed": seed}
        for mode in args.modes:
            row[mode] = run(seed, mode == "guided", rate_hz=args.rate_hz, hold_s=args.hold_s)
            x = row[mode]
            print(f"seed {seed}: {mode} {x['poses']} poses, {x['total_s']:.1f} s, every sensor accepted: "
                  f"{x['all_accepted']} {x['rejected'] or ''} ({x['reason']})", file=sys.stderr, flush=True)
        rows.append(row)
    cmd = " ".join(["python benchmarks/capture_guidance.py", f"--seeds {args.seeds}"]
                   + (["--modes", *args.modes] if args.modes != ["guided", "random"] else [])
                   + ([f"--rate-hz {args.rate_hz:g}"] if args.rate_hz != 10.0 else [])
                   + ([f"--hold-s {args.hold_s:g}"] if args.hold_s != 2.0 else [])
                   + ([f"--name {args.name}"] if args.name != "capture_guidance" else [])
                   + ([f"--baseline {args.baseline}"] if args.baseline else []))
    L = ["# Guided capture vs random poses: every sensor to its target\n",
         f"Produced by `{cmd}` ({time.perf_counter() - t0:.0f} s){' on ' + args.label if args.label else ''}. "
         f"Simulated hand, 3 IMUs and 3 compasses, {args.rate_hz:g} Hz telemetry, {args.hold_s:g} s holds, int16 "
         "truncation; the capture "
         "stops by its own rule with the product's default settings, then the final fit judges every sensor.\n",
         "| | median poses | mean | range | every sensor accepted | median time (capture + final fit) |",
         "|---|---|---|---|---|---|"]
    L += [f"| {mode} | {_summary(rows, mode)} |" for mode in args.modes]
    base = None
    if args.baseline:
        base = {r["seed"]: r for r in json.loads(Path(args.baseline).read_text())["rows"]}
        label = json.loads(Path(args.baseline).read_text()).get("label") or args.baseline
        L += [f"| baseline {mode} ({label}) | {_summary([base[r['seed']] for r in rows], mode)} |"
              for mode in args.modes if all(mode in base.get(r["seed"], {}) for r in rows)]
    if "guided" in args.modes and "random" in args.modes:
        g = np.median([x["guided"]["poses"] for x in rows])
        r = np.median([x["random"]["poses"] for x in rows])
        L += ["", f"**median guided / median random = {g / r:.2f}** (bar: <= 0.70)"]
    L += ["", "| seed | mode | poses | every sensor accepted | worst tilt bound (deg) | worst heading bound (deg) |"
          + (" baseline poses | baseline accepted |" if base else ""),
          "|---|---|---|---|---|---|" + ("---|---|" if base else "")]
    for x in rows:
        for mode in args.modes:
            res = x[mode]
            rej = ", ".join(res["rejected"]) or "-"
            cells = [str(x["seed"]), mode, str(res["poses"]), "yes" if res["all_accepted"] else f"no ({rej})",
                     _worst(res, "accel"), _worst(res, "compass")]
            if base:
                b = base.get(x["seed"], {}).get(mode)
                brej = ", ".join(b["rejected"]) if b else ""
                cells += ([str(b["poses"]), "yes" if b["all_accepted"] else f"no ({brej})"] if b else ["-", "-"])
            L.append("| " + " | ".join(cells) + " |")
    OUT.mkdir(exist_ok=True)
    (OUT / f"{args.name}.md").write_text("\n".join(L) + "\n")
    (OUT / f"{args.name}.json").write_text(json.dumps({"label": args.label, "rows": rows}, default=float, indent=1))
    print("\n".join(L))
    return 0


if __name__ == "__main__":
    from bench_output import output_dir  # --save / --out: where the results go (benchmarks/README.md)

    OUT, _argv = output_dir(sys.argv[1:])
    sys.exit(main(_argv))
