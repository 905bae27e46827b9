"""Whole `mavcal apply` sessions through a 30 %-loss relay against the real ArduPilot SITL (issue 31).

Each session is the CLI with its default options (``mavcal apply FILE --connect DEVICE --yes
--backup B``, a subprocess in the vehicle's network namespace) through
:class:`mavcal.testing.relay.LossRelay` dropping 30 % of the datagrams each way and duplicating
5 %: the heartbeat, the reads, the write, the force-save and the read-back all cross it. Two SITL
vehicles with two relayed channels each (SERIAL1, SERIAL2; each channel writes its own compass's
three offsets) run four sessions at a time. After each session the fixture reads the three
parameters back over its own lossless control channel (SERIAL0) and compares them with what the
exit code says: exit 0 -> every new value held (complete and verified, start included), exit 5
-> every old value held (restored), any other exit -> nothing changed; anything else is a silent
mismatch. Exit 6 is a session that left parameters in doubt.

Target: >= 39 of 40 complete, the rest restored, 0 in doubt, 0 silent mismatches.

    python benchmarks/apply_loss.py [--sessions 40] [--seed 31] [--save]
"""
from __future__ import annotations

import argparse
import contextlib
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mavcal.testing.sitl import SitlVehicle, unavailable_reason
from mavcal.testing.sitl_sessions import relayed_channels, run_sessions

OUT = Path(__file__).resolve().parent / "results"
#: each channel's parameters: a session writes its channel's three
CHANNEL_NAMES = (("COMPASS_OFS_X", "COMPASS_OFS_Y", "COMPASS_OFS_Z"),
                 ("COMPASS_OFS2_X", "COMPASS_OFS2_Y", "COMPASS_OFS2_Z"))
TOOL_PORTS = (14571, 14572)  # where the tool listens, behind each relay
LOSS, DUP = 0.3, 0.05


def run(n_sessions: int, seed: int) -> tuple[list[dict], list[dict], float]:
    """``n_sessions`` sessions over four relayed channels of two vehicles; (outcomes, relay stats, wall s)."""
    with contextlib.ExitStack() as stack, tempfile.TemporaryDirectory(prefix="apply-loss-") as tmpdir:
        vehicles = [stack.enter_context(SitlVehicle(wrong_calibration=False, relay=True, measure_field=False))
                    for _ in range(2)]
        channels = relayed_channels(stack, vehicles, CHANNEL_NAMES, TOOL_PORTS, seed=seed, loss=LOSS, dup=DUP)
        outcomes, wall = run_sessions(channels, n_sessions, Path(tmpdir), on_outcome=lambda o: print(
            f"session {o['i']}: exit {o['rc']} {'ok' if o['ok'] else 'MISMATCH'} {o['s']:.1f} s {o['err']}", flush=True))
        stats = [dict(relay.stats) for _, relay, _ in channels]
    for o in outcomes:
        o["names"] = next(iter(o["meant"]))[:-2]  # COMPASS_OFS or COMPASS_OFS2
    return outcomes, stats, wall


def summary(outcomes: list[dict], stats: list[dict], wall: float) -> dict:
    times = [o["s"] for o in outcomes]
    dropped = sum(st["dropped_out"] + st["dropped_in"] for st in stats)
    sent = sum(st["out"] + st["in"] for st in stats)
    return {"sessions": len(outcomes),
            "complete": sum(o["rc"] == 0 and o["ok"] for o in outcomes),
            "restored": sum(o["rc"] == 5 and o["ok"] for o in outcomes),
            "in_doubt": sum(o["rc"] == 6 for o in outcomes),
            "silent_mismatches": sum(not o["ok"] for o in outcomes),
            "other_exits": sorted({o["rc"] for o in outcomes} - {0, 5, 6}),
            "median_s": float(np.median(times)), "max_s": float(np.max(times)), "wall_s": round(wall, 1),
            "datagrams_dropped": round(dropped / max(sent, 1), 4),
            "datagrams_duplicated": round(sum(st["dup_out"] + st["dup_in"] for st in stats) / max(sent - dropped, 1), 4)}


def passes(s: dict) -> bool:
    return (s["complete"] >= s["sessions"] - 1 and s["complete"] + s["restored"] == s["sessions"]
            and s["in_doubt"] == 0 and s["silent_mismatches"] == 0)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sessions", type=int, default=40)
    ap.add_argument("--seed", type=int, default=31, help="the relays' seeds are SEED..SEED+3")
    args = ap.parse_args(argv)
    reason = unavailable_reason()
    if reason is not None:
        print(f"apply_loss: {reason}", file=sys.stderr)
        return 2
    outcomes, stats, wall = run(args.sessions, args.seed)
    s = summary(outcomes, stats, wall)
    cmd = "python benchmarks/apply_loss.py " + " ".join(sys.argv[1:])
    rows = "\n".join(f"| {o['i']} | {o['names']} | {o['rc']} | {'yes' if o['ok'] else 'NO'} | {o['s']:.1f} "
                     f"| {' '.join(o['err']) if o['rc'] else ''} |" for o in outcomes)
    md = (f"# `mavcal apply` through a 30 % loss relay against ArduPilot SITL (issue 31)\n\n"
          f"Produced by `{cmd.strip()}` ({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}). "
          f"CLI defaults; relay loss {LOSS:.0%} each way, {DUP:.0%} duplicated; 2 SITL vehicles x 2 channels, "
          f"4 sessions at a time. Values checked over the fixture's lossless control channel.\n\n"
          f"| sessions | complete and verified (start included) | restored (exit 5) | in doubt (exit 6) "
          f"| silent mismatches | other exits | session median / max (s) | wall (s) | datagrams dropped |\n"
          f"|---|---|---|---|---|---|---|---|---|\n"
          f"| {s['sessions']} | {s['complete']} | {s['restored']} | {s['in_doubt']} | {s['silent_mismatches']} "
          f"| {s['other_exits'] or '-'} | {s['median_s']:.1f} / {s['max_s']:.1f} | {s['wall_s']:.0f} "
          f"| {s['datagrams_dropped']:.1%} |\n\n"
          f"Target: >= {s['sessions'] - 1} complete, the rest restored, 0 in doubt, 0 silent mismatches: "
          f"**{'met' if passes(s) else 'NOT met'}**.\n\n"
          f"| session | parameters | exit | state as the exit says | time (s) | last stderr line |\n"
          f"|---|---|---|---|---|---|\n{rows}\n")
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "apply_loss.md").write_text(md)
    (OUT / "apply_loss.json").write_text(json.dumps({"summary": s, "relays": stats, "sessions": outcomes},
                                                    indent=1, default=float) + "\n")
    print(md)
    return 0 if passes(s) else 1


if __name__ == "__main__":
    from bench_output import output_dir  # --save / --out: where the results go (benchmarks/README.md)

    OUT, _argv = output_dir(sys.argv[1:])
    sys.exit(main(_argv))
