"""A fleet's logs per second and memory: the fork pool, a Dask LocalCluster, a Dask cluster of
separately started `dask scheduler` / `dask worker` processes; from local disk and from an S3
API served locally (moto's server); and a run killed with SIGKILL at about half and resumed.

The fleet: ``--n`` logs made from the bundled SITL logs (``sitl_logs/``) and the real logs of
``../shared/data/real`` (varied vehicles, lengths, calibrations in force; most real ones are
refused quickly for too few still poses, as they are in practice), each copy with other trailing
bytes (another content hash), plus ``--corrupt`` corrupt ones. The real log
``2024-04-05 09-36-27.tlog`` (6 s alone) is left out to keep a run short.

Each configuration runs in a fresh process (``--one``) with two workers (this machine has 2
CPUs) and the CLI's options (``mavcal calibrate DIR --table T.csv``): wall time, logs/s, the
largest RSS of any worker (``ru_maxrss``: of the fork pool's children, or of each Dask worker
process) and of the parent. Dask's own per-task overhead is measured with a no-op task.

    python benchmarks/fleet.py [--n 60] [--corrupt 3] [--save | --out DIR]

Results go to ``benchmarks/out/`` (``--save``: ``benchmarks/results/fleet.json`` and ``fleet.md``;
``--out DIR``: there).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
REAL = REPO.parent / "shared" / "data" / "real"
SLOW = {"2024-04-05 09-36-27.tlog"}
CONFIGS = ("fork", "localcluster", "separate", "fork-s3", "separate-s3")


def make_fleet(root: Path, n: int, corrupt: int) -> list[Path]:
    bases = [REPO / "sitl_logs" / "sitl01.tlog", REPO / "sitl_logs" / "sitl02.tlog"]
    if REAL.is_dir():
        bases += sorted(p for p in REAL.iterdir() if p.suffix.lower() in (".tlog", ".bin", ".csv")
                        and p.name not in SLOW)
    out = []
    for k in range(n):
        b = bases[k % len(bases)]
        p = root / f"v{k % 7}" / f"{k:05d}-{b.name.replace(' ', '_')}"
        p.parent.mkdir(parents=True, exist_ok=True)
        pad = b"" if b.suffix.lower() == ".csv" else b"\x00" * (k // len(bases))  # another content, same log
        p.write_bytes(b.read_bytes() + pad)
        out.append(p)
    for k in range(corrupt):
        p = root / "broken" / f"corrupt{k}.tlog"
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(bytes((i * 37 + 11 + k) % 251 for i in range(4000)).replace(b"\xfd", b"\x00").replace(b"\xfe", b"\x00"))
        out.append(p)
    return sorted(out)


def _worker_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_one(config: str, root: str, table: str) -> dict:
    """One configuration in this (fresh) process: the CLI's options, two workers."""
    from mavcal.cli import main
    from mavcal.testing.fleet import dask_cluster, moto_s3

    def cli(source: str, extra: list[str]) -> tuple[int, float]:
        t0 = time.perf_counter()
        code = main(["-q", "calibrate", source, "--table", table, *extra])
        return code, time.perf_counter() - t0

    res: dict = {"config": config}
    if config == "fork":
        res["exit"], res["wall_s"] = cli(root, ["--jobs", "2"])
        res["worker_max_rss_mb"] = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
    elif config == "localcluster":
        from distributed import Client, LocalCluster

        with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as lc:
            t0 = time.perf_counter()
            res["exit"], res["wall_s"] = cli(root, ["--scheduler-address", lc.scheduler_address])
            res["startup_s"] = 0.0
            with Client(lc) as c:
                res["worker_max_rss_mb"] = max(c.run(_worker_rss_mb).values())
    elif config.startswith("separate") or config == "fork-s3":
        s3 = config.endswith("-s3")
        from contextlib import ExitStack

        with ExitStack() as stack:
            source = root
            if s3:
                env = stack.enter_context(moto_s3("fleet"))
                os.environ.update(env)
                import fsspec

                fs = fsspec.filesystem("s3")
                for p in Path(root).rglob("*"):
                    if p.is_file():
                        fs.put_file(str(p), f"fleet/{p.relative_to(root)}")
                source = "s3://fleet/"
            if config.startswith("separate"):
                t0 = time.perf_counter()
                address = stack.enter_context(dask_cluster(workers=2))
                res["startup_s"] = time.perf_counter() - t0
                res["exit"], res["wall_s"] = cli(source, ["--scheduler-address", address])
                from distributed import Client

                with Client(address) as c:
                    res["worker_max_rss_mb"] = max(c.run(_worker_rss_mb).values())
                    n = 2000
                    t0 = time.perf_counter()
                    c.gather(c.map(_noop, range(n), pure=False))
                    res["dask_noop_task_ms"] = (time.perf_counter() - t0) / n * 1000 * 2  # per worker
            else:
                res["exit"], res["wall_s"] = cli(source, ["--jobs", "2"])
                res["worker_max_rss_mb"] = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
    res["parent_max_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    from mavcal.fleet.table import read_table

    rows = read_table(table)
    res["logs"] = len(rows)
    res["logs_per_s"] = len(rows) / res["wall_s"]
    res["cpu_s_per_log"] = sum(r["elapsed_s"] or 0.0 for r in rows) / max(len(rows), 1)
    return res


def _noop(x):
    return x


def killed_and_resumed(root: str, table: str, reference: str) -> dict:
    """The fork pool run killed with SIGKILL at about half, resumed; its rows vs ``reference``'s."""
    from mavcal.fleet.table import read_table
    from mavcal.testing.fleet import comparable, row_differences

    total = len(read_table(reference))
    proc = subprocess.Popen([sys.executable, "-m", "mavcal", "-q", "calibrate", root, "--table", table, "--jobs", "2"],
                            start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    while proc.poll() is None and len(read_table(table)) < total // 2:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    kept = len(read_table(table))
    subprocess.run([sys.executable, "-m", "mavcal", "-q", "calibrate", root, "--table", table, "--jobs", "2"],
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=False)
    rows = read_table(table)
    diffs = row_differences(comparable(rows, root), comparable(read_table(reference), root))
    return {"rows_at_kill": kept, "rows_after_resume": len(rows), "reference_rows": total,
            "distinct_sources": len({r["source"] for r in rows}), "differences": diffs[:5], "equal": not diffs}


def write_results(doc: dict, out_dir: Path) -> None:
    """``fleet.json`` and ``fleet.md`` in ``out_dir``."""
    (out_dir / "fleet.json").write_text(json.dumps(doc, indent=1) + "\n")
    lines = ["# Fleet: logs per second and memory (benchmarks/fleet.py)", "",
             f"{doc['n_logs']} logs, 2 workers, {doc['machine']['cpus']} CPUs: the "
             "worker s/log column (a log's wall time in its worker) shows how loaded the machine was.", "",
             "| configuration | wall s | logs/s | worker s/log | start-up s | max worker RSS MB | parent RSS MB |",
             "|---|---|---|---|---|---|---|"]
    for r in doc["results"]:
        lines.append(f"| {r['config']} | {r['wall_s']:.1f} | {r['logs_per_s']:.2f} | {r['cpu_s_per_log']:.2f} | "
                     f"{r.get('startup_s', 0):.1f} | {r['worker_max_rss_mb']:.0f} | {r['parent_max_rss_mb']:.0f} |")
    noop = [r["dask_noop_task_ms"] for r in doc["results"] if "dask_noop_task_ms" in r]
    if noop:
        lines += ["", f"Dask's cost of a no-op task (2,000 of them on the 2 workers, per worker): "
                      f"{min(noop):.1f}-{max(noop):.1f} ms."]
    kill = doc.get("killed_and_resumed")
    if kill:
        lines += ["", f"Killed with SIGKILL at {kill['rows_at_kill']} of {kill['reference_rows']} rows and resumed: "
                      f"{kill['rows_after_resume']} rows, {kill['distinct_sources']} distinct logs, "
                      f"equal to the uninterrupted run: {kill['equal']}."]
    (out_dir / "fleet.md").write_text("\n".join(lines) + "\n")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=60)
    ap.add_argument("--corrupt", type=int, default=3)
    ap.add_argument("--configs", nargs="*", default=list(CONFIGS))
    ap.add_argument("--one", nargs=3, metavar=("CONFIG", "ROOT", "TABLE"), help=argparse.SUPPRESS)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_output import add_output_arguments, resolve  # --save / --out (benchmarks/README.md)

    add_output_arguments(ap)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(run_one(*args.one)))
        return 0
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    results = []
    with tempfile.TemporaryDirectory(prefix="mavcal-fleet-bench-") as tmp:
        root = Path(tmp) / "fleet"
        logs = make_fleet(root, args.n, args.corrupt)
        print(f"{len(logs)} logs, {sum(p.stat().st_size for p in logs) / 1e6:.0f} MB", file=sys.stderr)
        for config in args.configs:
            table = str(Path(tmp) / f"{config}.csv")
            out = subprocess.run([sys.executable, __file__, "--one", config, str(root), table], env=env,
                                 capture_output=True, text=True, timeout=3000, check=False)
            if out.returncode != 0:
                print(out.stderr[-3000:], file=sys.stderr)
                continue
            res = json.loads(out.stdout.strip().splitlines()[-1])
            print(json.dumps(res), file=sys.stderr)
            results.append(res)
        kill = killed_and_resumed(str(root), str(Path(tmp) / "killed.csv"), str(Path(tmp) / "fork.csv")) \
            if "fork" in args.configs else None
    doc = {"machine": {"cpus": os.cpu_count(), "python": platform.python_version()}, "n_logs": args.n + args.corrupt,
           "results": results, "killed_and_resumed": kill}
    print(json.dumps(doc, indent=1))
    write_results(doc, resolve(args.save, args.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
