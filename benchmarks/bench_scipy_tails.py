"""What scipy's chi-square and F tails would cost a user's command: ``mavcal calibrate`` on the
bundled log, as now (``mavcal.core.stats.chi2_sf`` / ``f_sf``, pure Python) and with the import
that calling scipy's would add (``scipy.special`` for ``chdtrc``/``fdtrc``, or ``scipy.stats``).

``mavcal calibrate`` imports no scipy module today (numpy does the linear algebra), so scipy's
tails would add their whole import to every calibration; the calls themselves take microseconds
either way (a few dozen per run). Each variant runs as a fresh process (what a user types)
``--runs`` times, interleaved so that the machine's load falls on all alike; the table gives the
median and the spread (quartiles) of the CPU time (user + system, of the process and its fit
workers: ``os.wait4``'s rusage; on a machine shared with other jobs the wall time mostly
measures the others) and the median wall time, and each variant's difference to the first.
``python -X importtime`` of the two imports alone is given too (cumulative microseconds, one run).

Measured for issue 29 at commit 235d87a (``benchmarks/results/scipy_tails.md``); since 8740813
``core.stats`` calls scipy.special's tails itself, so the first variant includes that import and
the second equals it: check out 235d87a to compare with the hand-written tails again.

    python benchmarks/bench_scipy_tails.py [--runs 15] [--log sitl_logs/sitl02.tlog] [--save | --out DIR]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
OUT = Path(__file__).resolve().parent / "out"
LOG = REPO / "sitl_logs" / "sitl02.tlog"

# the CLI, with an import first: exactly what calling scipy's tail functions would add to the run
DRIVER = "import sys\n{pre}from mavcal.cli import main\nsys.exit(main(sys.argv[1:]))\n"
VARIANTS = [("mavcal calibrate (now: core.stats tails)", ""),
            ("+ import scipy.special (chdtrc, fdtrc)", "import scipy.special\n"),
            ("+ import scipy.stats (chi2.sf, f.sf)", "import scipy.stats\n")]


def _import_us(module: str) -> int:
    """Cumulative -X importtime of ``module`` in a fresh interpreter (after numpy, which the run has)."""
    err = subprocess.run([sys.executable, "-X", "importtime", "-c", f"import numpy; import {module}"],
                         capture_output=True, text=True, check=True).stderr
    rows = [ln.split("|") for ln in err.splitlines() if ln.startswith("import time:")]
    return next(int(r[1]) for r in rows if r[2].strip() == module)


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=15)
    p.add_argument("--log", type=Path, default=LOG)
    args = p.parse_args(argv)
    times: dict[str, list[float]] = {name: [] for name, _ in VARIANTS}  # CPU s
    walls: dict[str, list[float]] = {name: [] for name, _ in VARIANTS}
    with tempfile.TemporaryDirectory(prefix="mavcal-scipy-") as tmp:
        for _ in range(args.runs):
            for name, pre in VARIANTS:
                cmd = [sys.executable, "-c", DRIVER.format(pre=pre), "-q", "calibrate", str(args.log),
                       "--json", os.path.join(tmp, "cal.json")]
                t0 = time.perf_counter()
                proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                _, status, ru = os.wait4(proc.pid, 0)
                proc.returncode = os.waitstatus_to_exitcode(status)
                if proc.returncode != 0:
                    raise SystemExit(f"{name}: exit {proc.returncode}")
                walls[name].append(time.perf_counter() - t0)
                times[name].append(ru.ru_utime + ru.ru_stime)
    imports = {m: _import_us(m) for m in ("scipy.special", "scipy.stats")}
    base = statistics.median(times[VARIANTS[0][0]])
    rows = []
    for name, ts in times.items():
        q = statistics.quantiles(ts, n=4)
        rows.append({"variant": name, "cpu_median_s": statistics.median(ts), "cpu_q1_s": q[0], "cpu_q3_s": q[2],
                     "cpu_extra_s": statistics.median(ts) - base, "wall_median_s": statistics.median(walls[name]),
                     "runs": len(ts)})
    lines = ["# scipy's chi-square/F tails: the import cost on `mavcal calibrate`", "",
             f"Produced by `python benchmarks/bench_scipy_tails.py --runs {args.runs}` on "
             f"`{args.log.relative_to(REPO) if args.log.is_relative_to(REPO) else args.log}` "
             f"({os.cpu_count()} CPUs, machine shared with other jobs).", "",
             "| variant | CPU s (median) | CPU quartiles s | extra CPU s | wall s (median) |", "|---|---|---|---|---|"]
    lines += [f"| {r['variant']} | {r['cpu_median_s']:.3f} | {r['cpu_q1_s']:.3f}-{r['cpu_q3_s']:.3f} | "
              f"{r['cpu_extra_s']:+.3f} | {r['wall_median_s']:.2f} |" for r in rows]
    lines += ["", "Import alone (`python -X importtime -c 'import numpy; import M'`, cumulative): "
              + ", ".join(f"`{m}` {us / 1000:.0f} ms" for m, us in imports.items()) + "."]
    text = "\n".join(lines) + "\n"
    print(text)
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "scipy_tails.md").write_text(text)
    (OUT / "scipy_tails.json").write_text(json.dumps({"rows": rows, "import_us": imports}, indent=1))
    return 0


if __name__ == "__main__":
    from bench_output import output_dir  # --save / --out: where the results go (benchmarks/README.md)

    OUT, _argv = output_dir(sys.argv[1:])
    sys.exit(main(_argv))
