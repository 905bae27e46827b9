"""Long logs end to end: ``mavcal calibrate`` / ``mavcal segments`` vs pymavlink at 10 MB, 100 MB (1 GB).

For each size and kind, builds a log of time-shifted copies (``benchmarks/biglogs.py``:
``sitl_logs/sitl02.tlog`` and ``00000124.BIN``, every sample of every copy kept) under /tmp and
runs, each as its own subprocess with this tree first on ``PYTHONPATH``:

* ``mavcal calibrate LOG --json OUT`` (end to end: read, recover, segment, fit, gates, outputs),
* ``mavcal segments LOG --json``,
* pymavlink reading the same IMU messages: tlog ``recv_match`` loop over RAW_IMU and
  SCALED_IMU2; .bin ``DFReader`` (via ``mavlink_connection``) ``recv_match`` over IMU and MAG,
  collecting the values.

Each run's wall time is measured here (the median of ``--repeat`` runs), its peak resident
memory by ``/usr/bin/time -f %M`` (interpreter start included for all three); ``mavcal
calibrate`` runs once more with its process tree's PSS sampled (its fit workers), untimed. Prints a table with the ratios to
pymavlink, peak memory / file size and the 10 MB -> 100 MB (-> 1 GB) time scaling.

The interval-count case (``--intervals 2000 20000``, kind ``sim``): simulated sessions of that
many random poses (``biglogs.build_intervals_tlog``), ``mavcal calibrate`` and the pymavlink
reader on each; ``time x`` is then the cost against the interval count.

Results go to ``benchmarks/out/long_logs.md`` / ``.json``, to ``benchmarks/results/`` with
``--save`` (tracked), or ``--out DIR`` (benchmarks/README.md).

    python benchmarks/bench_long_logs.py [--save] [--full] [--repeat 3] [--sizes-mb 10 100] [--intervals 2000 20000]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

import biglogs  # noqa: E402  (benchmarks/ is this script's directory)

OUT = REPO / "benchmarks" / "out"  # rebound by --save / --out (bench_output)
TLOG_TYPES = ["RAW_IMU", "SCALED_IMU2"]
DF_TYPES = ["IMU", "MAG"]
TOOLS = ("mavcal calibrate", "mavcal segments", "pymavlink read")

# the reference reader, run as ``python -c PYMAVLINK_READER LOG``
PYMAVLINK_READER = rf"""
import sys
from pymavlink import mavutil
path = sys.argv[1]
tlog = path.endswith(".tlog")
types = {TLOG_TYPES!r} if tlog else {DF_TYPES!r}
m = mavutil.mavlink_connection(path)
rows = []
while True:
    msg = m.recv_match(type=types)
    if msg is None:
        break
    if tlog:
        rows.append((msg._timestamp, msg.xacc, msg.yacc, msg.zacc, msg.xgyro, msg.ygyro, msg.zgyro,
                     msg.xmag, msg.ymag, msg.zmag))
    elif msg.get_type() == "IMU":
        rows.append((msg.TimeUS, msg.AccX, msg.AccY, msg.AccZ, msg.GyrX, msg.GyrY, msg.GyrZ))
    else:
        rows.append((msg.TimeUS, msg.MagX, msg.MagY, msg.MagZ))
print(len(rows))
"""


def _descendants(root: int) -> list[int]:
    """``root`` and every process below it (from the parent ids in /proc/*/stat)."""
    children: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as f:
                    ppid = int(f.read().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue
            children.setdefault(ppid, []).append(int(d))
    out, todo = [], [root]
    while todo:
        p = todo.pop()
        out.append(p)
        todo += children.get(p, [])
    return out


def _pss_mb(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/smaps_rollup") as f:
            for line in f:
                if line.startswith("Pss:"):
                    return int(line.split()[1]) * 1024 / 1e6
    except OSError:
        pass
    return 0.0


class TreeMemory(threading.Thread):
    """Samples, every ``period_s``, the summed PSS of a process and its descendants (the fit
    worker processes of ``mavcal calibrate``): the physical memory of the whole tree, each
    shared page counted once, which the max-RSS of ``/usr/bin/time`` (the largest single
    process, shared pages counted in each) does not give when there are workers."""

    def __init__(self, pid: int, period_s: float = 0.025) -> None:
        super().__init__(daemon=True)
        self.pid, self.period_s, self.peak_mb = pid, period_s, 0.0
        self._stop_event = threading.Event()

    def run(self) -> None:
        while not self._stop_event.is_set():
            self.peak_mb = max(self.peak_mb, sum(_pss_mb(p) for p in _descendants(self.pid)))
            self._stop_event.wait(self.period_s)

    def stop(self) -> float:
        self._stop_event.set()
        self.join()
        return round(self.peak_mb, 1)


def run(cmd: list, timeout_s: float, stdout=subprocess.DEVNULL, tree_memory: bool = True) -> dict:
    """Run ``cmd`` under ``/usr/bin/time``: wall time, the child's peak RSS and exit code.

    The peak RSS comes from ``/usr/bin/time -f %M`` (its child's ``wait4`` rusage, the
    largest process of the tree): asking ``os.wait4`` for a child forked from this process
    would report at least this process's own resident size, which a fork copies into the
    child's high-water mark. ``peak_pss_mb`` is the tree's summed PSS (:class:`TreeMemory`),
    sampled only with ``tree_memory`` (None otherwise): the sampler reads /proc every 25 ms
    and takes CPU from the run it measures (about 0.06 s on a 1 s run with two busy workers
    on 2 cores), so the timed runs go without it.
    """
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO)] + [p for p in [os.environ.get("PYTHONPATH")] if p]))
    with tempfile.NamedTemporaryFile("r", prefix="mavcal-time-", dir="/tmp") as tf:
        t0 = time.perf_counter()
        proc = subprocess.Popen(["/usr/bin/time", "-f", "%M", "-o", tf.name] + cmd, stdout=stdout,
                                stderr=subprocess.PIPE, env=env, cwd="/tmp")
        mem = TreeMemory(proc.pid) if tree_memory else None
        if mem is not None:
            mem.start()
        try:
            _, err = proc.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
            if mem is not None:
                mem.stop()
            return dict(wall_s=None, peak_rss_mb=None, rc="timeout")
        wall = time.perf_counter() - t0
        pss = mem.stop() if mem is not None else None
        lines = tf.read().split()
    out: dict = dict(wall_s=round(wall, 2), peak_rss_mb=round(int(lines[-1]) * 1024 / 1e6, 1) if lines else None,
                     peak_pss_mb=pss, rc=proc.returncode)
    if proc.returncode not in (0, 4):  # 4 = calibration rejected by a gate: still a complete run
        out["stderr_tail"] = err.decode(errors="replace").strip().splitlines()[-3:]
    return out


def _n_intervals(cal_json: Path) -> int | None:
    try:
        return len(json.loads(cal_json.read_text())["intervals"])
    except (OSError, ValueError, KeyError):
        return None


def measure(cmd: list, timeout_s: float, repeat: int, tree: bool) -> dict:
    """``repeat`` timed runs of ``cmd`` (the median wall time; peak RSS the largest) and, for a
    command that forks workers (``tree``), one more run with the tree's PSS sampled."""
    runs = [run(cmd, timeout_s, tree_memory=False) for _ in range(max(1, repeat))]
    walls = sorted(r["wall_s"] for r in runs if r["wall_s"] is not None)
    out = dict(runs[-1], wall_s=walls[(len(walls) - 1) // 2] if len(walls) == len(runs) else None,
               walls_s=[r["wall_s"] for r in runs],
               peak_rss_mb=max((r["peak_rss_mb"] or 0.0) for r in runs) or None, peak_pss_mb=None)
    if tree and out["wall_s"] is not None:
        mem = run(cmd, timeout_s, tree_memory=True)
        out["peak_rss_mb"] = max(out["peak_rss_mb"] or 0.0, mem["peak_rss_mb"] or 0.0) or None
        out["peak_pss_mb"] = mem["peak_pss_mb"]
    return out


def bench_log(kind: str, path: Path, copies: int, tmp: Path, timeout_s: float, tools, repeat: int = 1) -> list:
    py = sys.executable
    size_mb = path.stat().st_size / 1e6
    cmds = {
        "mavcal calibrate": [py, "-m", "mavcal", "-q", "calibrate", str(path), "--json", str(tmp / "cal.json")],
        "mavcal segments": [py, "-m", "mavcal", "-q", "segments", str(path), "--json"],
        "pymavlink read": [py, "-c", PYMAVLINK_READER, str(path)],
    }
    rows = []
    for tool, cmd in cmds.items():
        if tool not in tools:
            continue
        (tmp / "cal.json").unlink(missing_ok=True)
        r = measure(cmd, timeout_s, repeat, tree=tool == "mavcal calibrate")
        r.update(kind=kind, size_mb=round(size_mb, 1), copies=copies, tool=tool,
                 rss_per_file=round(max(r["peak_rss_mb"], r["peak_pss_mb"] or 0.0) / size_mb, 2)
                 if r["peak_rss_mb"] else None,
                 intervals=_n_intervals(tmp / "cal.json") if tool == "mavcal calibrate" else None)
        rows.append(r)
        print(r, file=sys.stderr, flush=True)
    ref = rows[-1]["wall_s"] if rows and rows[-1]["tool"] == "pymavlink read" else None
    for r in rows:
        r["time_vs_pymavlink"] = round(r["wall_s"] / ref, 3) if r["wall_s"] and ref else None
    return rows


def add_scaling(rows: list) -> None:
    """time(size) / time(smallest size) and the size ratio, per kind and tool."""
    for r in rows:
        same = [q for q in rows if q["kind"] == r["kind"] and q["tool"] == r["tool"]]
        base = min(same, key=lambda q: (q["copies"], q["size_mb"]))
        r["size_x"] = round(r["size_mb"] / base["size_mb"], 1) if r["kind"] != "sim" else \
            round(r["copies"] / base["copies"], 1)
        r["time_x"] = round(r["wall_s"] / base["wall_s"], 1) if r["wall_s"] and base["wall_s"] else None


def bar_lines(rows: list) -> list[str]:
    """Issue 11's bars, per log: speed-up of ``mavcal calibrate`` over the pymavlink reader of
    the same file in the same run (>= 20), its peak RSS / file (<= 2), and the time scaling
    to the next size (<= 12 for 10x the size or the intervals)."""
    out = ["| log | size MB | calibrate s | pymavlink s | speed-up (bar >= 20) | peak / file (bar <= 2) "
           "| time x / size x (bar <= 12 for 10) |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        if r["tool"] != "mavcal calibrate" or not r["wall_s"]:
            continue
        ref = next((q for q in rows if q["kind"] == r["kind"] and q["size_mb"] == r["size_mb"]
                    and q["copies"] == r["copies"] and q["tool"] == "pymavlink read"), None)
        speed = round(ref["wall_s"] / r["wall_s"], 1) if ref and ref["wall_s"] else None
        out.append(f"| {r['kind']} | {r['size_mb']} | {r['wall_s']} | {ref['wall_s'] if ref else ''} | {speed} "
                   f"| {r['rss_per_file'] if r['kind'] != 'sim' else ''} | {r['time_x']} / {r['size_x']} |")
    return out


def write_results(rows: list, env: str, command: str = "") -> str:
    md = ["| log | size MB | copies / poses | intervals | tool | wall s | peak RSS MB | peak PSS MB (tree) "
          "| peak / file | time / pymavlink | size x | time x | rc |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        md.append(f"| {r['kind']} | {r['size_mb']} | {r['copies']} | {r.get('intervals') or ''} | {r['tool']} | "
                  f"{r['wall_s']} | {r['peak_rss_mb']} | {r.get('peak_pss_mb')} | {r['rss_per_file']} | "
                  f"{r['time_vs_pymavlink']} | "
                  f"{r['size_x']} | {r['time_x']} | {r['rc']} |")
    text = ("# Long logs end to end (benchmarks/bench_long_logs.py)\n\n" + "\n".join(md) + "\n\n"
            + "\n".join(bar_lines(rows)) +
            "\n\nLogs: time-shifted copies of sitl_logs/sitl02.tlog and 00000124.BIN (benchmarks/biglogs.py). "
            "Each row is one subprocess: `mavcal calibrate LOG --json OUT`, `mavcal segments LOG --json`, or "
            "pymavlink reading the IMU messages (tlog: recv_match over RAW_IMU, SCALED_IMU2; .bin: DFReader over "
            "IMU, MAG) and collecting the values. wall s = the median of `--repeat` timed runs (one on 1 GB), "
            "each with nothing else sampling it. Peak RSS = `/usr/bin/time -f %M` of the runs, interpreter "
            "included (MB = 1e6 bytes): the largest process of the run; peak PSS (tree) = the largest sum of "
            "the proportional set sizes of the processes of one more mavcal calibrate run (it forks fit "
            "workers), sampled every 25 ms (the sampler costs the run CPU, so this run is not timed); "
            "peak / file = the larger of the two over the file size. size x / time x: ratio to "
            "the smallest size of the same log kind and tool (linear = equal); for kind sim, the ratio of "
            "the pose counts (simulated sessions, biglogs.build_intervals_tlog) and its time, i.e. the cost "
            "against the interval count. intervals: still intervals of the calibrate run. rc 4 = calibration "
            "rejected by a quality gate (the copies of one session are a valid but repetitive log). "
            f"Machine shared with other jobs: timings vary between runs. {env}.\n"
            + (f"\nProduced by `{command}`.\n" if command else ""))
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "long_logs.md").write_text(text)
    (OUT / "long_logs.json").write_text(json.dumps({"environment": env, "command": command, "rows": rows},
                                                   indent=1))
    return text


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes-mb", type=float, nargs="+", default=[10.0, 100.0])
    ap.add_argument("--full", action="store_true", help="also 1 GB (1000 MB)")
    ap.add_argument("--kinds", nargs="+", default=["tlog", "bin", "sim"], choices=["tlog", "bin", "sim"])
    ap.add_argument("--intervals", type=int, nargs="+", default=[2000, 20000],
                    help="pose counts of the simulated sessions (kind sim)")
    ap.add_argument("--timeout", type=float, default=3600.0, help="seconds per run")
    ap.add_argument("--tools", nargs="+", default=list(TOOLS), choices=list(TOOLS))
    ap.add_argument("--repeat", type=int, default=1,
                    help="timed runs of every command on logs up to 100 MB (the median is reported)")
    args = ap.parse_args(argv)
    sizes = list(args.sizes_mb) + ([1000.0] if args.full else [])
    import numpy as np

    env = f"python {platform.python_version()}, numpy {np.__version__}, {platform.machine()}, {os.cpu_count()} CPUs"
    rows: list = []
    tmp = Path(tempfile.mkdtemp(prefix="mavcal-long-logs-", dir="/tmp"))
    command = "python benchmarks/bench_long_logs.py " + " ".join(sys.argv[1:])
    try:
        for kind in args.kinds:
            for size in (args.intervals if kind == "sim" else sizes):
                path = tmp / f"big_{int(size)}{'poses' if kind == 'sim' else 'MB'}.{'bin' if kind == 'bin' else 'tlog'}"
                if kind == "sim":
                    copies = biglogs.build_intervals_tlog(path, int(size))
                    tools = [t for t in args.tools if t != "mavcal segments"]
                else:
                    build = biglogs.build_tlog if kind == "tlog" else biglogs.build_bin
                    copies, tools = build(path, size * 1e6), args.tools
                rows += bench_log(kind, path, copies, tmp, args.timeout, tools,
                                  args.repeat if kind == "sim" or size <= 100.0 else 1)
                path.unlink()
                add_scaling(rows)
                write_results(rows, env, command)  # after every log: a long run interrupted keeps what it measured
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    add_scaling(rows)
    print(write_results(rows, env, command))
    return 0


if __name__ == "__main__":
    from bench_output import output_dir  # --save / --out: where the results go (benchmarks/README.md)

    OUT, _argv = output_dir(sys.argv[1:])  # the other arguments go on to main's own parser
    sys.exit(main(_argv))
