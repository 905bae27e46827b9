"""How fast ``mavcal flight`` reads a flight: end to end, beside pymavlink's DFReader and MAGFit (issue 39).

The issue's bars: ``mavcal flight`` at least 10 times faster end to end than MAVProxy's MAGFit
on the same log, and on a 100 MB flight ``.bin`` at least 20 times faster than pymavlink's
DFReader merely reading the ``MAG``, ``BAT``, ``ATT`` and ``XKQ`` messages of the same file.

The logs: an ArduPilot SITL ``quad`` flight (``benchmarks/flight.py --keep DIR`` leaves them in
DIR; else one is flown here, root and SITL needed) and longer ones made from it by looping its
messages: the format records (``FMT``, ``FMTU``, ``UNIT``, ``MULT``) once, then every other record
of the flight again and again with its ``TimeUS`` shifted past the previous copy's end (a series
of flights, one after another, as a long log of many flights is). They are made in a cache
directory (``--cache``, default ``~/.cache/mavcal-bench/flight``), never in the repository.

Each command runs as a fresh process (what a user types), timed from its start to its exit
(the interpreter's start and every import included), with its peak RSS (``/usr/bin/time -f %M``):

* ``mavcal flight LOG --json F`` (the whole stage: read, fit, verdict, report);
* **DFReader** reading the four messages as a program that wants them does::

      from pymavlink import DFReader
      r = DFReader.DFReader_binary(LOG, zero_time_base=False)
      while (m := r.recv_match(type=["MAG", "BAT", "ATT", "XKQ"])) is not None:
          n += 1          # each message built as a DFMessage object, nothing else done with it

  with pymavlink's default indexer (its compiled ``dfindexer`` when installed, as pip installs
  it) and with its pure-Python one (``PYMAVLINK_FAST_INDEX=0``);
* **MAGFit** (``MAVProxy/modules/lib/magfit.py``'s headless ``main()`` with a stand-in ``wx``;
  ``--cmot``) on the logs up to ``--magfit-max-mb``.

The median of ``--runs`` runs (MAGFit: one).

    python benchmarks/flight_speed.py [--source LOG.bin] [--sizes 9 20 100] [--runs 5] [--save | --out DIR]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "out"  # rebound by --save / --out (bench_output)
CACHE = Path.home() / ".cache" / "mavcal-bench" / "flight"
FORMAT_NAMES = {"FMT", "FMTU", "UNIT", "MULT"}
MAGFIT_BAR, DFREADER_BAR = 10.0, 20.0

DFREADER_RUN = """
import sys
from pymavlink import DFReader
r = DFReader.DFReader_binary(sys.argv[1], zero_time_base=False)
n = 0
while True:
    m = r.recv_match(type=["MAG", "BAT", "ATT", "XKQ"])
    if m is None:
        break
    n += 1
print(n)
"""

INPROCESS_RUN = """
import json, sys, time
from pymavlink import DFReader
from mavcal.flight.stage import analyse
from mavcal.sources.fast_dataflash import decode_dataflash
from mavcal.sources.flight_series import read_flight_series

def best(f, runs):
    ts = []
    for _ in range(runs):
        t = time.perf_counter()
        f()
        ts.append(time.perf_counter() - t)
    return min(ts)

def dfreader():
    r = DFReader.DFReader_binary(sys.argv[1], zero_time_base=False)
    while r.recv_match(type=["MAG", "BAT", "ATT", "XKQ"]) is not None:
        pass

runs = int(sys.argv[2])
s = read_flight_series(sys.argv[1])
print(json.dumps({"dfreader_s": best(dfreader, runs),
                  "decode4_s": best(lambda: decode_dataflash(sys.argv[1], ("MAG", "BAT", "ATT", "XKQ")), runs),
                  "read_series_s": best(lambda: read_flight_series(sys.argv[1]), runs),
                  "analyse_s": best(lambda: analyse(s), runs)}))
"""

def records(data: bytes) -> list[tuple[int, int, int]]:
    """(start, end, type) of every record of a DataFlash log, as DFReader frames them (a record
    of a known type, else one byte skipped). Set-up only: a plain loop."""
    lengths = {0x80: 89}
    out = []
    p, n = 0, len(data)
    while p + 3 <= n:
        if data[p] != 0xA3 or data[p + 1] != 0x95 or data[p + 2] not in lengths:
            p += 1
            continue
        t = data[p + 2]
        end = p + lengths[t]
        if end > n:
            break
        if t == 0x80:
            lengths.setdefault(data[p + 3], data[p + 4])
        out.append((p, end, t))
        p = end
    return out


def _formats(data: bytes, recs: list[tuple[int, int, int]]) -> dict[int, tuple[str, str, str]]:
    fm = {}
    for p, _, t in recs:
        if t == 0x80:
            ty = data[p + 3]
            name, fmt, cols = (data[a:b].split(b"\0", 1)[0].decode("ascii", "replace")
                               for a, b in ((p + 5, p + 9), (p + 9, p + 25), (p + 25, p + 89)))
            fm.setdefault(ty, (name, fmt, cols))
    return fm


def loop_log(src: Path, dest: Path, target_mb: float) -> Path:
    """``src``'s flight repeated until ``dest`` is at least ``target_mb`` MB (see the module doc)."""
    if dest.exists() and dest.stat().st_size >= target_mb * 1e6 and dest.stat().st_mtime >= src.stat().st_mtime:
        return dest
    data = src.read_bytes()
    recs = records(data)
    fm = _formats(data, recs)
    timed = {t for t, (_, fmt, cols) in fm.items() if fmt[:1] == "Q" and cols.split(",")[0] == "TimeUS"}
    head = [(p, e) for p, e, t in recs if fm.get(t, ("",))[0] in FORMAT_NAMES or t == 0x80]
    body = [(p, e, t) for p, e, t in recs if not (fm.get(t, ("",))[0] in FORMAT_NAMES or t == 0x80)]
    times = [struct.unpack_from("<Q", data, p + 3)[0] for p, _, t in body if t in timed]
    span = max(times) - min(times) + 1_000_000  # one copy's length, and a second between copies
    tmp = dest.with_suffix(".part")
    with open(tmp, "wb") as fh:
        size = 0
        for p, e in head:
            size += fh.write(data[p:e])
        k = 0
        while size < target_mb * 1e6:
            shift = k * span
            out = bytearray()
            for p, e, t in body:
                r = bytearray(data[p:e])
                if t in timed:
                    struct.pack_into("<Q", r, 3, struct.unpack_from("<Q", r, 3)[0] + shift)
                out += r
            size += fh.write(out)
            k += 1
    os.replace(tmp, dest)
    return dest


def timed(cmd: list[str], env: dict | None = None, timeout_s: float = 1800) -> dict:
    """Wall time from the process's start to its exit, its peak RSS, exit code and stdout."""
    with tempfile.NamedTemporaryFile("r", prefix="mavcal-time-") as tf:
        t0 = time.perf_counter()
        out = subprocess.run(["/usr/bin/time", "-f", "%M", "-o", tf.name] + cmd, capture_output=True, text=True,
                             env=env, timeout=timeout_s)
        wall = time.perf_counter() - t0
        kb = tf.read().split()
    return {"wall_s": wall, "peak_rss_mb": int(kb[-1]) / 1024 if kb else None, "rc": out.returncode,
            "stdout": out.stdout[-300:], "stderr": out.stderr[-300:]}


def median_run(cmd: list[str], runs: int, env: dict | None = None) -> dict:
    rs = [timed(cmd, env) for _ in range(runs)]
    return {"wall_s": statistics.median(r["wall_s"] for r in rs), "wall_min_s": min(r["wall_s"] for r in rs),
            "peak_rss_mb": max(r["peak_rss_mb"] or 0 for r in rs), "rc": rs[-1]["rc"], "runs": runs,
            "stdout": rs[-1]["stdout"], "stderr": rs[-1]["stderr"]}


def one_log(log: Path, runs: int, magfit: bool, work: Path) -> dict:
    res: dict = {"log": log.name, "size_mb": log.stat().st_size / 1e6, "load": os.getloadavg()[0]}
    js = work / "flight.json"
    res["mavcal"] = median_run([sys.executable, "-m", "mavcal", "flight", str(log), "--json", str(js)], runs)
    env = dict(os.environ)
    res["dfreader"] = median_run([sys.executable, "-c", DFREADER_RUN, str(log)], runs, env)
    res["dfreader_pure"] = median_run([sys.executable, "-c", DFREADER_RUN, str(log)], max(1, runs // 3),
                                      dict(env, PYMAVLINK_FAST_INDEX="0"))
    res["messages"] = int(res["dfreader"]["stdout"].split()[-1]) if res["dfreader"]["rc"] == 0 else None
    # the same records as DFReader's: mavcal's decoder counts the four messages alike
    from mavcal.sources.fast_dataflash import decode_dataflash

    cols, _, _ = decode_dataflash(str(log), ("MAG", "BAT", "ATT", "XKQ"))
    res["mavcal_messages"] = sum(len(c["_index"]) for c in cols.values())
    inproc = subprocess.run([sys.executable, "-c", INPROCESS_RUN, str(log), str(runs)], capture_output=True, text=True,
                            env=dict(env, OPENBLAS_NUM_THREADS="1"), timeout=1800)
    res["in_process"] = json.loads(inproc.stdout.strip().splitlines()[-1]) if inproc.returncode == 0 else None
    if magfit:
        from flight import MAGFIT_RUN, WX_STANDIN  # the flight benchmark's MAGFit run, headless (its stand-in wx)

        standin = work / "standin"
        (standin / "wx").mkdir(parents=True, exist_ok=True)
        (standin / "wx" / "__init__.py").write_text(WX_STANDIN)
        menv = dict(env, PYTHONPATH=str(standin) + os.pathsep + env.get("PYTHONPATH", ""), MPLBACKEND="Agg")
        res["magfit"] = timed([sys.executable, "-c", MAGFIT_RUN, str(log), "--cmot", "--save-plot",
                               str(work / "magfit.png")], menv)
    return res


def same_as_dfreader(log: Path) -> dict:
    """mavcal's decoder against DFReader on ``log``: MAG, BAT, ATT and XKQ record by record, every
    numeric field; the number of values compared and the largest relative difference."""
    import numpy as np
    from pymavlink import DFReader

    from mavcal.sources.fast_dataflash import decode_dataflash

    names = ("MAG", "BAT", "ATT", "XKQ")
    cols, _, _ = decode_dataflash(str(log), names)
    r = DFReader.DFReader_binary(str(log), zero_time_base=False)
    msgs: dict[str, list] = {n: [] for n in names}
    while (m := r.recv_match(type=list(names))) is not None:
        msgs[m.get_type()].append(m)
    n, worst = 0, 0.0
    for name in names:
        got = cols.get(name, {})
        if len(got.get("_index", ())) != len(msgs[name]):
            return {"values": n, "max_rel_diff": float("inf"), "count_mismatch": name}
        for k in msgs[name][0].get_fieldnames() if msgs[name] else ():
            want = [getattr(m, k) for m in msgs[name]]
            if k not in got or not all(isinstance(v, (int, float)) for v in want):
                continue
            a, b = np.asarray(got[k], float), np.asarray(want, float)
            worst = max(worst, float(np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-300), initial=0.0)))
            n += len(b)
    return {"values": n, "max_rel_diff": worst}


def source_log(arg: Path | None) -> Path:
    if arg is not None:
        return arg
    kept = sorted(CACHE.glob("flight_[0-9].bin"))
    if kept:
        return kept[0]
    from mavcal.testing.sitl import SitlVehicle, require_sitl
    from mavcal.testing.sitl_flight import flight_params, fly

    require_sitl()
    CACHE.mkdir(parents=True, exist_ok=True)
    with SitlVehicle(wrong_calibration=False, params=flight_params((3.0, -2.0, 4.0)), model="quad", speedup=8,
                     measure_field=False) as sitl:
        return fly(sitl, CACHE / "flight_0.bin")


def report(rows: list[dict], cmd: str, src: Path) -> str:
    lines = ["# `mavcal flight`: how fast, end to end, beside DFReader and MAGFit (issue 39)", "",
             f"Made by `{cmd}` ({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}), on a machine of 2 cores "
             f"shared with other jobs (load average {rows[0].get('load', float('nan')):.1f} at the start, "
             f"{rows[-1].get('load', float('nan')):.1f} at the end). The flight: an ArduPilot SITL `quad` flight (`{src.name}`, "
             f"{src.stat().st_size / 1e6:.1f} MB); the longer logs loop its records (the format records once, "
             "every other record again with `TimeUS` shifted past the previous copy: a series of flights). "
             "Every time is a fresh process from its start to its exit (interpreter start and imports included), "
             "the median of the runs; peak RSS from `/usr/bin/time -f %M`. DFReader: `DFReader_binary(LOG)` then "
             "`recv_match(type=[MAG, BAT, ATT, XKQ])` until None (each message built, nothing else done), with "
             "pymavlink's default indexer (its compiled `dfindexer`, as pip installs it) and its pure-Python one "
             "(`PYMAVLINK_FAST_INDEX=0`). MAGFit: `magfit.py LOG --cmot` (headless, one run).", "",
             "| log MB | messages read by DFReader (by mavcal's decoder) | mavcal flight s | mavcal peak MB | DFReader s (dfindexer) "
             "| DFReader MB | DFReader s (pure Python) | MAGFit s | MAGFit MB | DFReader / mavcal | "
             "DFReader pure / mavcal | MAGFit / mavcal |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        m, d, dp, mf = r["mavcal"], r["dfreader"], r["dfreader_pure"], r.get("magfit")
        mf_s = "-" if mf is None else f"{mf['wall_s']:.1f}"
        mf_mb = "-" if mf is None else f"{mf['peak_rss_mb']:.0f}"
        mf_q = "-" if mf is None else f"{mf['wall_s'] / m['wall_s']:.0f}"
        lines.append(
            f"| {r['size_mb']:.1f} | {r['messages']} ({r['mavcal_messages']}) | {m['wall_s']:.2f} | {m['peak_rss_mb']:.0f} | {d['wall_s']:.2f} | "
            f"{d['peak_rss_mb']:.0f} | {dp['wall_s']:.2f} | {mf_s} | {mf_mb} | {d['wall_s'] / m['wall_s']:.1f} | "
            f"{dp['wall_s'] / m['wall_s']:.1f} | {mf_q} |")
    lines += ["", "Inside one process (the best of the runs; no interpreter start, no imports; `OPENBLAS_NUM_THREADS=1` "
              "as the CLI sets it): DFReader reading the four messages; mavcal's decoder reading the same four; "
              "mavcal reading every series the stage needs (`read_flight_series`: MAG, BAT, ATT, XKY0, GPS, CTUN, "
              "PARM, ARM, EV, MSG, FMTU); the stage's fit and verdicts (`analyse`).", "",
              "| log MB | DFReader s | mavcal decoder, same 4 messages, s | DFReader / decoder | mavcal read_flight_series s "
              "| DFReader / read_flight_series | analyse s |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        p = r.get("in_process")
        if p:
            lines.append(f"| {r['size_mb']:.1f} | {p['dfreader_s']:.3f} | {p['decode4_s']:.3f} | "
                         f"{p['dfreader_s'] / p['decode4_s']:.1f} | {p['read_series_s']:.3f} | "
                         f"{p['dfreader_s'] / p['read_series_s']:.1f} | {p['analyse_s']:.3f} |")
    big = max(rows, key=lambda r: r["size_mb"])
    withmf = [r for r in rows if r.get("magfit")]
    lines += ["", "Bars:", ""]
    if withmf:
        worst = min(r["magfit"]["wall_s"] / r["mavcal"]["wall_s"] for r in withmf)
        lines.append(f"- {MAGFIT_BAR:.0f} times faster than MAGFit on the same log: at least **{worst:.0f} times** "
                     f"({'met' if worst >= MAGFIT_BAR else 'NOT met'})")
    q, qp = (big["dfreader"]["wall_s"] / big["mavcal"]["wall_s"],
             big["dfreader_pure"]["wall_s"] / big["mavcal"]["wall_s"])
    lines.append(f"- {DFREADER_BAR:.0f} times faster than DFReader reading MAG, BAT, ATT and XKQ on the "
                 f"{big['size_mb']:.0f} MB log: **{q:.1f} times** against DFReader with its compiled indexer "
                 f"({'met' if q >= DFREADER_BAR else 'NOT met'}), **{qp:.1f} times** against its pure-Python "
                 f"indexer ({'met' if qp >= DFREADER_BAR else 'NOT met'})")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--source", type=Path, help="the SITL flight .bin (default: one kept by benchmarks/flight.py)")
    ap.add_argument("--cache", type=Path, default=CACHE, help="where the looped logs are made")
    ap.add_argument("--sizes", type=float, nargs="+", default=[0.0, 20.0, 100.0],
                    help="log sizes in MB (0: the flight itself)")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--magfit-max-mb", type=float, default=30.0)
    args = ap.parse_args(argv)
    src = source_log(args.source)
    check = same_as_dfreader(src)
    args.cache.mkdir(parents=True, exist_ok=True)
    rows = []
    with tempfile.TemporaryDirectory(prefix="mavcal-flight-speed-") as tmp:
        for mb in args.sizes:
            log = src if mb <= 0 else loop_log(src, args.cache / f"{src.stem}_x{mb:g}MB.bin", mb)
            r = one_log(log, args.runs, log.stat().st_size / 1e6 <= args.magfit_max_mb, Path(tmp))
            print(json.dumps(r), flush=True)
            rows.append(r)
    saved = " --save" if OUT.resolve() == (REPO / "benchmarks" / "results").resolve() else ""
    cmd = ("python benchmarks/flight_speed.py" + saved + " " + " ".join(sys.argv[1:] if argv is None else argv)).strip()
    text = report(rows, cmd, src) + (
        f"\nThe records are DFReader's: on `{src.name}` mavcal's decoder gives the same MAG, BAT, ATT and XKQ "
        f"records, {check['values']} values, the largest relative difference {check['max_rel_diff']:.1e}.\n")
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "flight_speed.md").write_text(text)
    (OUT / "flight_speed.json").write_text(json.dumps(rows, indent=1) + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    from bench_output import output_dir  # --save / --out: where the results go (benchmarks/README.md)

    OUT, _argv = output_dir(sys.argv[1:])
    sys.exit(main(_argv))
