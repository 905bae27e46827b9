"""Does each piece of memory machinery earn its place? ``mavcal calibrate`` on long logs with
and without each of them.

The pieces, each switched off alone in a variant (and all together in the last):

* ``trim``: ``mavcal.memory.release_free_memory`` (glibc ``malloc_trim`` between the stages and
  before the fit workers fork), made a no-op;
* ``mallopt``: ``mavcal.memory.return_large_blocks`` (``mallopt(M_MMAP_THRESHOLD)`` in each fit
  worker), made a no-op;
* ``freeze``: ``gc.freeze()`` before the workers fork (``mavcal.workers``), made a no-op;
* ``hugepage``: the CLI's ``NUMPY_MADVISE_HUGEPAGE=0``, replaced by numpy's default (1).

Each run is ``mavcal calibrate LOG --json OUT`` as a user types it, in a fresh process (through
a ``python -c`` driver that switches the piece off before mavcal is imported), under
``/usr/bin/time`` (wall s, CPU s = user + system of the process and its fit workers, peak RSS =
the largest process). The variants are interleaved ``--repeat`` times (the machine's load falls
on all alike): the table gives the medians and the largest peak RSS. ``--pss-repeat`` more runs
per variant (interleaved too, untimed) sample the summed PSS of the process tree every 25 ms
(``bench_long_logs.TreeMemory``: the physical memory of the parent and its workers, shared
pages counted once): its median and range.

    python benchmarks/bench_memory_machinery.py LOG [LOG ...] [--repeat 3] [--pss-repeat 1] [--without PIECE ...] [--save | --out DIR]

Measured for issue 29 (``benchmarks/results/memory_machinery.md``): mallopt, freeze and hugepage
did not earn their place and were removed after commit 8740813; their variants now switch off
nothing (equal to "all on"): check that commit out to run them again.

Logs: e.g. ``python benchmarks/biglogs.py tlog /tmp/t100.tlog 100e6`` (time-shifted copies of
the bundled log) and ``python benchmarks/biglogs.py intervals /tmp/n20000.tlog 20000``.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

from bench_long_logs import TreeMemory  # noqa: E402  (benchmarks/ is this script's directory)

OUT = REPO / "benchmarks" / "out"

DRIVER = r"""
import os, sys
off = set(sys.argv.pop(1).split(",")) - {""}
if "hugepage" in off:
    os.environ["NUMPY_MADVISE_HUGEPAGE"] = "1"  # numpy's default (the CLI sets 0 only when unset)
if "trim" in off or "mallopt" in off:
    import mavcal.memory as m
    if "trim" in off:
        m.release_free_memory = lambda: False
    if "mallopt" in off:
        m.return_large_blocks = lambda *a, **k: False
if "freeze" in off:
    import gc
    gc.freeze = lambda: None
from mavcal.cli import main
sys.exit(main(sys.argv[1:]))
"""
PIECES = ["trim", "mallopt", "freeze", "hugepage"]
VARIANTS = [("all on (as shipped)", "")] + [(f"without {p}", p) for p in PIECES] + [("all off", ",".join(PIECES))]


def run_once(cmd: list[str], tree: bool) -> dict:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO)] + [p for p in [os.environ.get("PYTHONPATH")] if p]))
    with tempfile.NamedTemporaryFile("r", prefix="mavcal-time-") as tf:
        proc = subprocess.Popen(["/usr/bin/time", "-f", "%e %U %S %M", "-o", tf.name] + cmd,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env, cwd="/tmp")
        mem = TreeMemory(proc.pid) if tree else None
        if mem is not None:
            mem.start()
        _, err = proc.communicate()
        pss = mem.stop() if mem is not None else None
        wall, user, sys_, rss_kb = tf.read().split()[-4:]
    if proc.returncode not in (0, 4, 7):
        raise SystemExit(f"{' '.join(cmd)}: exit {proc.returncode}: {err.decode(errors='replace')[-500:]}")
    return dict(wall_s=float(wall), cpu_s=float(user) + float(sys_), peak_rss_mb=int(rss_kb) * 1024 / 1e6,
                peak_pss_mb=pss, rc=proc.returncode)


def bench(log: Path, repeat: int, tmp: Path, variants: list[tuple[str, str]], pss_repeat: int = 1) -> list[dict]:
    runs: dict[str, list[dict]] = {name: [] for name, _ in variants}
    def cmd(off: str) -> list[str]:
        return [sys.executable, "-c", DRIVER, off, "-q", "calibrate", str(log), "--json", str(tmp / "cal.json")]
    for _ in range(repeat):
        for name, off in variants:
            runs[name].append(run_once(cmd(off), tree=False))
    psss: dict[str, list[float]] = {name: [] for name, _ in variants}
    for _ in range(pss_repeat):
        for name, off in variants:
            psss[name].append(run_once(cmd(off), tree=True)["peak_pss_mb"])
    rows = []
    for name, _ in variants:
        pss = statistics.median(psss[name])
        rs = runs[name]
        rows.append(dict(log=log.name, size_mb=round(log.stat().st_size / 1e6, 1), variant=name,
                         wall_s=statistics.median(r["wall_s"] for r in rs), cpu_s=statistics.median(r["cpu_s"] for r in rs),
                         walls_s=[r["wall_s"] for r in rs], cpus_s=[r["cpu_s"] for r in rs],
                         peak_rss_mb=round(max(r["peak_rss_mb"] for r in rs), 1), peak_pss_mb=pss,
                         peak_pss_range_mb=[min(psss[name]), max(psss[name])], rc=rs[-1]["rc"]))
        print(json.dumps(rows[-1]), flush=True)
    return rows


def table(rows: list[dict]) -> list[str]:
    lines = ["| log | MB | variant | wall s | CPU s | peak RSS MB | peak PSS MB (tree) | PSS range MB | rc |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lo, hi = r["peak_pss_range_mb"]
        lines.append(f"| {r['log']} | {r['size_mb']} | {r['variant']} | {r['wall_s']:.2f} | {r['cpu_s']:.2f} | "
                     f"{r['peak_rss_mb']:.1f} | {r['peak_pss_mb']:.1f} | {lo:.1f}-{hi:.1f} | {r['rc']} |")
    return lines


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("logs", type=Path, nargs="+")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--pss-repeat", type=int, default=1, metavar="N",
                   help="sampled (untimed) runs per variant for the tree's peak PSS: the median and range")
    p.add_argument("--without", nargs="+", choices=PIECES + ["all"], metavar="PIECE",
                   help=f"only these variants besides 'all on' ({', '.join(PIECES)}, all; default: every one)")
    args = p.parse_args(argv)
    variants = VARIANTS if not args.without else [VARIANTS[0]] + [
        v for v in VARIANTS[1:] if v[1] in args.without or (v[1] == ",".join(PIECES) and "all" in args.without)]
    rows: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="mavcal-memory-") as tmp:
        for log in args.logs:
            rows += bench(log, args.repeat, Path(tmp), variants, args.pss_repeat)
    env = f"python {platform.python_version()}, {platform.machine()}, {os.cpu_count()} CPUs"
    thp = Path("/sys/kernel/mm/transparent_hugepage/enabled")
    thp_s = thp.read_text().strip() if thp.exists() else "n/a"
    text = "\n".join(["# Memory machinery: `mavcal calibrate` with and without each piece", "",
                      f"Produced by `python benchmarks/bench_memory_machinery.py {' '.join(a.name for a in args.logs)} "
                      f"--repeat {args.repeat} --pss-repeat {args.pss_repeat}{' --without ' + ' '.join(args.without) if args.without else ''}`; {env}; transparent huge pages: `{thp_s}`.", ""] + table(rows)) + "\n"
    print(text)
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "memory_machinery.md").write_text(text)
    (OUT / "memory_machinery.json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    from bench_output import output_dir  # --save / --out: where the results go (benchmarks/README.md)

    OUT, _argv = output_dir(sys.argv[1:])
    sys.exit(main(_argv))
