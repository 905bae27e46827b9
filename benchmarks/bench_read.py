"""Reading speed: vectorised decoders vs pymavlink on ~50 MB logs.

Builds, in a temporary directory under /tmp, a ~50 MB tlog and a ~50 MB .bin of time-shifted
copies of ``sitl_logs/sitl02.tlog`` and ``00000124.BIN`` (``benchmarks/biglogs.py``: every
time field shifted so the copies follow each other, whole records only), and times

* pymavlink: ``mavutil.mavlink_connection`` + ``recv_match(type=[IMU messages...])`` loop
  (DFReader for the .bin), collecting the IMU values, and
* mavcal: ``fast_tlog.decode_tlog`` / ``fast_dataflash.decode_dataflash`` of the same
  messages (IMU only; plus full ``read_log``),

checks that the decoded values are identical and that ``read_log`` keeps every IMU sample of
every copy, counts the lines pymavlink printed (e.g. "bad header"; 0 on these clean inputs,
the count goes to the results instead of the terminal) and writes
``read_speed.md`` and ``.json`` into benchmarks/out/ (benchmarks/results/ with ``--save``; ``--name`` changes the file name, never
the directory).

    python benchmarks/bench_read.py [--size-mb 50] [--name read_speed]
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

import biglogs  # noqa: E402  (benchmarks/ is this script's directory)
from pymavlink import mavutil  # noqa: E402

from mavcal.sources import read_log  # noqa: E402
from mavcal.sources.fast_dataflash import decode_dataflash  # noqa: E402
from mavcal.sources.fast_tlog import decode_tlog  # noqa: E402

OUT = REPO / "benchmarks" / "out"  # --save: benchmarks/results/ (benchmarks/README.md)
TLOG_IMU = ["RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3"]
DF_IMU = ["IMU", "MAG"]


def ref_tlog(path: Path):
    m = mavutil.mavlink_connection(str(path))
    out: dict[str, list] = {n: [] for n in TLOG_IMU}
    while True:
        msg = m.recv_match(type=TLOG_IMU)
        if msg is None:
            break
        out[msg.get_type()].append((msg._timestamp, msg.time_boot_ms if hasattr(msg, "time_boot_ms") else msg.time_usec,
                                    msg.xacc, msg.yacc, msg.zacc, msg.xgyro, msg.ygyro, msg.zgyro,
                                    msg.xmag, msg.ymag, msg.zmag))
    return {k: np.array(v, dtype=float) for k, v in out.items()}


def fast_tlog(path: Path):
    cols, _ = decode_tlog(str(path), TLOG_IMU)
    out = {}
    for k, c in cols.items():
        t = c["time_boot_ms"] if "time_boot_ms" in c else c["time_usec"]
        fields = ("xacc", "yacc", "zacc", "xgyro", "ygyro", "zgyro", "xmag", "ymag", "zmag")
        out[k] = np.column_stack([c["_log_time_s"], t] + [c[f] for f in fields]).astype(float)
    return out


def ref_bin(path: Path):
    m = mavutil.mavlink_connection(str(path))
    out: dict[str, list] = {n: [] for n in DF_IMU}
    while True:
        msg = m.recv_match(type=DF_IMU)
        if msg is None:
            break
        if msg.get_type() == "IMU":
            out["IMU"].append((msg.TimeUS, msg.I, msg.AccX, msg.AccY, msg.AccZ, msg.GyrX, msg.GyrY, msg.GyrZ))
        else:
            out["MAG"].append((msg.TimeUS, msg.I, msg.MagX, msg.MagY, msg.MagZ, msg.OfsX, msg.OfsY, msg.OfsZ))
    return {k: np.array(v, dtype=float) for k, v in out.items()}


def fast_bin(path: Path):
    cols, _, _ = decode_dataflash(str(path), DF_IMU)
    f = {"IMU": ("TimeUS", "I", "AccX", "AccY", "AccZ", "GyrX", "GyrY", "GyrZ"),
         "MAG": ("TimeUS", "I", "MagX", "MagY", "MagZ", "OfsX", "OfsY", "OfsZ")}
    return {k: np.column_stack([cols[k][c] for c in f[k]]).astype(float) for k in DF_IMU}


def timed(fn, *a, repeat=1):
    best = None
    for _ in range(repeat):
        t = time.perf_counter()
        r = fn(*a)
        dt = time.perf_counter() - t
        best = dt if best is None else min(best, dt)
    return r, best


def quiet(fn, *a):
    """Run ``fn(*a)`` with its stdout captured; returns (result, number of lines printed)."""
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        r = fn(*a)
    return r, len(buf.getvalue().splitlines())


def accel_samples(path: Path) -> int:
    lg = read_log(path)
    return sum(len(s) for s in lg.series if s.sensor == "accel")


def bench_one(label: str, path: Path, copies: int, source: Path, ref, fast) -> dict:
    (r, printed), t_ref = timed(quiet, ref, path)
    f, t_fast = timed(fast, path, repeat=3)
    _, t_full = timed(read_log, path, repeat=3)
    same = set(r) == set(f) and all(np.array_equal(r[k].reshape(-1, f[k].shape[1]) if r[k].size else
                                                   np.zeros((0, f[k].shape[1])), f[k]) for k in r)
    kept, per_copy = accel_samples(path), accel_samples(source)
    n = sum(len(v) for v in f.values())
    return dict(file=label, size_mb=round(path.stat().st_size / 1e6, 1), copies=copies, imu_messages=n,
                pymavlink_s=round(t_ref, 2), fast_s=round(t_fast, 3), read_log_s=round(t_full, 3),
                speedup=round(t_ref / t_fast, 1), speedup_read_log=round(t_ref / t_full, 1),
                identical=bool(same), accel_samples_kept=kept, accel_samples_expected=copies * per_copy,
                pymavlink_lines_printed=printed)


def write_results(rows: list, name: str) -> str:
    md = ["| file | size MB | copies | IMU msgs | pymavlink s | fast decode s | read_log s | speed-up (decode) |"
          " speed-up (read_log) | identical | accel samples kept / expected | pymavlink printed |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        md.append(f"| {r['file']} | {r['size_mb']} | {r['copies']} | {r['imu_messages']} | {r['pymavlink_s']} | "
                  f"{r['fast_s']} | {r['read_log_s']} | {r['speedup']}x | {r['speedup_read_log']}x | "
                  f"{r['identical']} | {r['accel_samples_kept']} / {r['accel_samples_expected']} | "
                  f"{r['pymavlink_lines_printed']} lines |")
    env = f"python {platform.python_version()}, numpy {np.__version__}, {platform.machine()}, {os.cpu_count()} CPUs"
    text = ("# Reading speed (benchmarks/bench_read.py)\n\n" + "\n".join(md) +
            "\n\nInputs: time-shifted copies of sitl_logs/sitl02.tlog and 00000124.BIN (benchmarks/biglogs.py),"
            " so every copy's samples are kept. pymavlink = `recv_match(type=IMU messages)` loop (DFReader for .bin),"
            " collecting the values; fast decode = `decode_tlog`/`decode_dataflash` of the same messages;"
            " read_log = full ImuLog (also params, events, position; tlog CRCs checked for the decoded message"
            " types, as `read_log` does by default). Best of 3 for the fast paths, pymavlink once."
            f" Machine shared with other jobs: timings vary between runs. {env}.\n")
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / f"{name}.md").write_text(text)
    (OUT / f"{name}.json").write_text(json.dumps({"environment": env, "rows": rows}, indent=1))
    return text


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size-mb", type=float, default=50.0)
    ap.add_argument("--tlog", type=Path, default=biglogs.DEFAULT_TLOG)
    ap.add_argument("--bin", type=Path, default=biglogs.DEFAULT_BIN)
    ap.add_argument("--name", default="read_speed", help="results file name (in benchmarks/out/, or benchmarks/results/ with --save)")
    args = ap.parse_args(argv)
    if Path(args.name).name != args.name:
        ap.error("--name is a file name, not a path: results go to benchmarks/results/")
    rows = []
    with tempfile.TemporaryDirectory(prefix="mavcal-bench-", dir="/tmp") as tmp:
        tl = Path(tmp) / "big.tlog"
        bn = Path(tmp) / "big.bin"
        nt = biglogs.build_tlog(tl, args.size_mb * 1e6, args.tlog)
        nb = biglogs.build_bin(bn, args.size_mb * 1e6, args.bin)
        for label, path, copies, src, ref, fast in (("tlog", tl, nt, args.tlog, ref_tlog, fast_tlog),
                                                    ("bin", bn, nb, args.bin, ref_bin, fast_bin)):
            rows.append(bench_one(label, path, copies, src, ref, fast))
            print(rows[-1], file=sys.stderr)
    print(write_results(rows, args.name))
    ok = all(r["identical"] and r["accel_samples_kept"] == r["accel_samples_expected"] for r in rows)
    return 0 if ok else 1


if __name__ == "__main__":
    from bench_output import output_dir  # --save / --out: where the results go (benchmarks/README.md)

    OUT, _argv = output_dir(sys.argv[1:])
    sys.exit(main(_argv))
