"""Reading speed: vectorised decoders vs pymavlink on ~50 MB logs.

Builds a ~50 MB tlog by concatenating ``sitl_logs/sitl01.tlog`` with shifted timestamps,
and a ~50 MB .bin by concatenating the body of a real DataFlash log (the FMT records of the
first copy define all types), in a temporary directory. Times

* pymavlink: ``mavutil.mavlink_connection`` + ``recv_match(type=[IMU messages...])`` loop
  (DFReader for the .bin), collecting the IMU values, and
* mavcal: ``fast_tlog.decode_tlog`` / ``fast_dataflash.decode_dataflash`` of the same
  messages (IMU only; plus full ``read_log``),

checks that the decoded values are identical and writes ``benchmarks/results/read_speed.md``
and ``.json``.

    python benchmarks/bench_read.py [--size-mb 50] [--bin PATH]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import struct
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from pymavlink import mavutil  # noqa: E402

from mavcal.sources import read_log  # noqa: E402
from mavcal.sources.fast_dataflash import decode_dataflash  # noqa: E402
from mavcal.sources.fast_tlog import decode_tlog  # noqa: E402

TLOG_IMU = ["RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3"]
DF_IMU = ["IMU", "MAG"]


def build_tlog(src: Path, dst: Path, size_mb: float) -> None:
    data = src.read_bytes()
    # split into (ts, frame) records by walking the file (sitl01 is clean)
    recs = []
    p = 0
    while p + 10 <= len(data):
        stx = data[p + 8]
        plen = data[p + 9]
        flen = (6 if stx == 0xFE else 10) + plen + 2 + (13 if stx == 0xFD and data[p + 10] & 1 else 0)
        recs.append((struct.unpack(">Q", data[p:p + 8])[0], data[p + 8:p + 8 + flen]))
        p += 8 + flen
    span = recs[-1][0] - recs[0][0] + 1_000_000
    with open(dst, "wb") as fh:
        k = 0
        while fh.tell() < size_mb * 1e6:
            off = k * span
            fh.write(b"".join(struct.pack(">Q", t + off) + f for t, f in recs))
            k += 1


def build_bin(src: Path, dst: Path, size_mb: float) -> None:
    data = src.read_bytes()
    with open(dst, "wb") as fh:
        fh.write(data)
        while fh.tell() < size_mb * 1e6:
            fh.write(data)


def ref_tlog(path: Path):
    m = mavutil.mavlink_connection(str(path))
    out = {n: [] for n in TLOG_IMU}
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
        out[k] = np.column_stack([c["_log_time_s"], t] + [c[f] for f in
                                 ("xacc", "yacc", "zacc", "xgyro", "ygyro", "zgyro", "xmag", "ymag", "zmag")]).astype(float)
    return out


def ref_bin(path: Path):
    m = mavutil.mavlink_connection(str(path))
    out = {n: [] for n in DF_IMU}
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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size-mb", type=float, default=50.0)
    ap.add_argument("--tlog", type=Path, default=REPO / "sitl_logs" / "sitl01.tlog")
    ap.add_argument("--bin", type=Path, default=REPO.parent / "shared" / "data" / "real" / "00000124.BIN")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "read_speed")
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory(prefix="mavcal-bench-") as tmp:
        tl = Path(tmp) / "big.tlog"
        bn = Path(tmp) / "big.bin"
        build_tlog(args.tlog, tl, args.size_mb)
        build_bin(args.bin, bn, args.size_mb)
        for label, path, ref, fast in (("tlog", tl, ref_tlog, fast_tlog), ("bin", bn, ref_bin, fast_bin)):
            r, t_ref = timed(ref, path)
            f, t_fast = timed(fast, path, repeat=3)
            _, t_full = timed(read_log, path, repeat=3)
            same = set(r) == set(f) and all(np.array_equal(r[k].reshape(-1, f[k].shape[1]) if r[k].size else
                                                           np.zeros((0, f[k].shape[1])), f[k]) for k in r)
            n = sum(len(v) for v in f.values())
            rows.append(dict(file=label, size_mb=round(path.stat().st_size / 1e6, 1), imu_messages=n,
                             pymavlink_s=round(t_ref, 2), fast_s=round(t_fast, 3), read_log_s=round(t_full, 3),
                             speedup=round(t_ref / t_fast, 1), speedup_read_log=round(t_ref / t_full, 1),
                             identical=bool(same)))
            print(rows[-1], file=sys.stderr)
    md = ["| file | size MB | IMU msgs | pymavlink s | fast decode s | read_log s | speed-up (decode) | speed-up (read_log) | identical |",
          "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        md.append(f"| {r['file']} | {r['size_mb']} | {r['imu_messages']} | {r['pymavlink_s']} | {r['fast_s']} | "
                  f"{r['read_log_s']} | {r['speedup']}x | {r['speedup_read_log']}x | {r['identical']} |")
    env = f"python {platform.python_version()}, numpy {np.__version__}, {platform.machine()}, {os.cpu_count()} CPUs"
    text = ("# Reading speed (benchmarks/bench_read.py)\n\n" + "\n".join(md) +
            f"\n\npymavlink = `recv_match(type=IMU messages)` loop (DFReader for .bin), collecting the values;"
            f" fast decode = `decode_tlog`/`decode_dataflash` of the same messages; read_log = full ImuLog"
            f" (also params, events, position; tlog CRCs checked for the decoded message types, as"
            f" `read_log` does by default). Best of 3 for the fast paths, pymavlink once."
            f" Machine shared with other jobs: timings vary by ~20% between runs. {env}.\n")
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".md").write_text(text)
    args.out.with_suffix(".json").write_text(json.dumps({"environment": env, "rows": rows}, indent=1))
    return 0 if all(r["identical"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
