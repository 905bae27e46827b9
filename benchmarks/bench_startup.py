"""How long a command takes to start: `mavcal --help` and `mavcal <cmd> --help`, end to end.

Each command runs as a fresh process (what a user types), N times; the table gives the median
and the worst wall time, next to `python -c pass` (the interpreter's own start) in the same run.
Bar (issue 14): `mavcal --help` starts in <= 0.5 s.

    python benchmarks/bench_startup.py [--runs 15] [--save | --out DIR]
"""
from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

OUT = Path(__file__).resolve().parent / "out"
BAR_S = 0.5


def _commands() -> list[tuple[str, list[str]]]:
    mavcal = shutil.which("mavcal")
    base = [mavcal] if mavcal else [sys.executable, "-m", "mavcal"]
    return [("python -c pass", [sys.executable, "-c", "pass"]),
            ("mavcal --help", base + ["--help"]),
            ("mavcal calibrate --help", base + ["calibrate", "--help"]),
            ("mavcal segments --help", base + ["segments", "--help"]),
            ("mavcal apply --help", base + ["apply", "--help"])]


def _time(cmd: list[str], runs: int) -> list[float]:
    out = []
    for _ in range(runs):
        t0 = time.perf_counter()
        subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
        out.append(time.perf_counter() - t0)
    return out


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=15)
    args = p.parse_args(argv)
    rows = []
    for name, cmd in _commands():
        ts = _time(cmd, args.runs)
        rows.append({"command": name, "median_s": statistics.median(ts), "max_s": max(ts), "runs": len(ts)})
    lines = ["# Command start-up time", "", f"Produced by `python benchmarks/bench_startup.py --runs {args.runs}`; "
             f"bar: `mavcal --help` <= {BAR_S} s (median).", "",
             "| command | median s | worst s |", "|---|---|---|"]
    lines += [f"| `{r['command']}` | {r['median_s']:.3f} | {r['max_s']:.3f} |" for r in rows]
    help_row = next(r for r in rows if r["command"] == "mavcal --help")
    verdict = "meets" if help_row["median_s"] <= BAR_S else "MISSES"
    lines += ["", f"`mavcal --help`: {help_row['median_s']:.3f} s median, {verdict} the {BAR_S} s bar."]
    text = "\n".join(lines) + "\n"
    print(text)
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "startup.md").write_text(text)
    (OUT / "startup.json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    from bench_output import output_dir  # --save / --out: where the results go (benchmarks/README.md)

    OUT, _argv = output_dir(sys.argv[1:])
    sys.exit(main(_argv))
