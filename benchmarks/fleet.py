"""A fleet's logs per second and memory: the fork pool, a Dask LocalCluster, a Dask cluster of
separately started `dask scheduler` / `dask worker` processes; from local disk and from an S3
API served locally (moto's server); and a run killed with SIGKILL at about half and resumed.

The fleet: ``--n`` logs made from the bundled SITL logs (``sitl_logs/``) and the real logs of
``../shared/data/real`` (varied vehicles, lengths, calibrations in force; most real ones are
refused quickly for too few still poses, as they are in practice), each copy with other trailing
bytes (another content hash), plus ``--corrupt`` corrupt ones. The real log
``2024-04-05 09-36-27.tlog`` (6 s alone) is left out to keep a run short.

Fair on a shared machine: the logs are cut into ``--rounds`` chunks and the configurations
take turns on each chunk (round 1: fork, LocalCluster, separate; round 2 in another order, ...),
so background load falls on all of them alike; each round's logs/s is reported beside the fork
pool's of the same round, and overall. Each chunk is one ``mavcal -q calibrate @CHUNK --table
T.csv`` (``--jobs 2``, or ``--scheduler-address`` of a cluster started once, before the
rounds) in a fresh process (``--one``), with two workers (this machine has 2 CPUs): wall time,
and the CPU time the configuration spent (the mavcal process and its forked workers; for Dask
also every process of the cluster, scheduler, nannies and workers, from ``/proc``), which
background load distorts much less than the wall time. The load average is noted per round.
The largest RSS of any worker (``ru_maxrss``) and of the parent; Dask's per-task overhead
with a no-op task.

    python benchmarks/fleet.py [--n 60] [--corrupt 3] [--rounds 5] [--configs ...] [--save | --out DIR]

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


def _noop(x):
    return x


def _warm() -> int:
    """Import what a log's job imports (a cluster's workers are started once and kept)."""
    import mavcal.batch  # noqa: F401
    import mavcal.fleet.run  # noqa: F401
    import mavcal.pipeline  # noqa: F401
    return os.getpid()


def run_one(config: str, listfile: str, table: str, address: str) -> dict:
    """One chunk of one configuration in this (fresh) process: the CLI, two workers."""
    from mavcal.cli import main

    extra = ["--jobs", "2"] if config.startswith("fork") else ["--scheduler-address", address]
    t0, c0 = time.perf_counter(), time.process_time()
    code = main(["-q", "calibrate", f"@{listfile}", "--table", table, *extra])
    wall, own = time.perf_counter() - t0, time.process_time() - c0
    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    return {"exit": code, "wall_s": wall, "parent_cpu_s": own, "children_cpu_s": ch.ru_utime + ch.ru_stime,
            "children_max_rss_mb": ch.ru_maxrss / 1024.0,
            "parent_max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}


def _tree_cpu_s(root_pids: list[int]) -> float:
    """CPU seconds (user + system) so far of the processes ``root_pids`` and all their descendants."""
    tick = os.sysconf("SC_CLK_TCK")
    stat: dict[int, tuple[int, float]] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                f = (d / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            stat[int(d.name)] = (int(f[1]), (int(f[11]) + int(f[12])) / tick)
    keep, total, grew = set(root_pids), 0.0, True
    while grew:
        grew = False
        for pid, (ppid, _) in stat.items():
            if ppid in keep and pid not in keep:
                keep.add(pid)
                grew = True
    for pid in keep:
        total += stat.get(pid, (0, 0.0))[1]
    return total


def _serve_localcluster() -> int:
    """A Dask LocalCluster of 2 workers in this process (its nanny sets the workers' environment
    here, not in the benchmark's): prints the scheduler address, runs until stdin closes."""
    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as lc:
        print(lc.scheduler_address, flush=True)
        sys.stdin.read()
    return 0


def _localcluster(env: dict):
    from contextlib import contextmanager

    @contextmanager
    def cm():
        proc = subprocess.Popen([sys.executable, __file__, "--serve-localcluster"], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env,
                                preexec_fn=os.setpgrp)  # same session: same CPU share (autogroup)
        try:
            assert proc.stdout is not None
            yield proc.stdout.readline().strip(), [proc.pid]
        finally:
            try:
                assert proc.stdin is not None
                proc.stdin.close()
                proc.wait(timeout=30)
            except (subprocess.TimeoutExpired, OSError):
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
    return cm()


def _separate(env: dict):
    from contextlib import contextmanager

    from mavcal.testing.fleet import dask_cluster

    @contextmanager
    def cm():
        before = set(_children(os.getpid()))
        with dask_cluster(workers=2) as address:
            yield address, [p for p in _children(os.getpid()) if p not in before]
    return cm()


def _children(pid: int) -> list[int]:
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if int((d / "stat").read_text().rsplit(")", 1)[1].split()[1]) == pid:
                    out.append(int(d.name))
            except OSError:
                continue
    return out


def run_rounds(configs: list[str], chunks: list[list[str]], root: Path, tmp: Path, env: dict,
               on_round=None) -> dict:
    """Every configuration on every chunk (paths under ``root``), taking turns (the order rotated
    each round); a ``-s3`` configuration reads the same logs from ``s3://fleet/``."""
    from contextlib import ExitStack

    from distributed import Client

    clusters: dict[str, tuple[str, list[int]]] = {}
    per: dict[str, list[dict]] = {c: [] for c in configs}
    extra: dict[str, dict] = {c: {} for c in configs}
    rounds = []
    with ExitStack() as stack:
        for c in configs:
            if c.startswith("localcluster"):
                clusters[c] = stack.enter_context(_localcluster(env))
            elif c.startswith("separate"):
                clusters[c] = stack.enter_context(_separate(env))
        for address, _ in clusters.values():  # a long-lived cluster's workers have mavcal imported already
            with Client(address) as cl:
                cl.run(_warm)
        for r, chunk in enumerate(chunks):
            order = configs[r % len(configs):] + configs[:r % len(configs)]
            this = {"round": r + 1, "logs": len(chunk), "load_before": os.getloadavg()[0], "order": order}
            for c in order:
                address, pids = clusters.get(c, ("", []))
                listfile = tmp / f"chunk{r}-{c}.txt"
                listfile.write_text("".join((f"s3://fleet/{rel}" if c.endswith("-s3") else str(root / rel)) + "\n"
                                            for rel in chunk))
                cpu0 = _tree_cpu_s(pids) if pids else 0.0
                out = subprocess.run([sys.executable, __file__, "--one", c, str(listfile), str(tmp / f"{c}.csv"),
                                      address], env=env, capture_output=True, text=True, timeout=3000, check=False)
                if out.returncode != 0:
                    raise RuntimeError(f"{c}, round {r + 1}: {out.stderr[-3000:]}")
                res = json.loads(out.stdout.strip().splitlines()[-1])
                res["cluster_cpu_s"] = (_tree_cpu_s(pids) - cpu0) if pids else 0.0
                res["logs"] = len(chunk)
                res["logs_per_s"] = len(chunk) / res["wall_s"]
                res["cpu_s_per_log"] = (res["parent_cpu_s"] + res["children_cpu_s"] + res["cluster_cpu_s"]) / len(chunk)
                per[c].append(res)
                this[c] = {"logs_per_s": res["logs_per_s"], "cpu_s_per_log": res["cpu_s_per_log"]}
                print(f"round {r + 1} {c}: {res['logs_per_s']:.2f} logs/s, {res['cpu_s_per_log']:.3f} CPU s/log, "
                      f"load {os.getloadavg()[0]:.2f}", file=sys.stderr, flush=True)
            this["load_after"] = os.getloadavg()[0]
            rounds.append(this)
            for c, (address, _) in clusters.items():
                with Client(address) as cl:
                    extra[c]["worker_max_rss_mb"] = max(cl.run(_worker_rss_mb).values())
            if on_round is not None:  # the rounds so far (a run stopped early keeps them)
                on_round(_summary(configs, per, extra, rounds, len(chunks)))
        for c, (address, _) in clusters.items():
            with Client(address) as cl:
                n = 2000
                t0 = time.perf_counter()
                cl.gather(cl.map(_noop, range(n), pure=False))
                extra[c]["dask_noop_task_ms"] = (time.perf_counter() - t0) / n * 1000 * 2  # per worker
    return _summary(configs, per, extra, rounds, len(chunks))


def _summary(configs: list[str], per: dict, extra: dict, rounds: list, planned: int) -> dict:
    results = []
    for c in configs:
        rs = per[c]
        n = sum(r["logs"] for r in rs)
        wall = sum(r["wall_s"] for r in rs)
        cpu = sum(r["parent_cpu_s"] + r["children_cpu_s"] + r["cluster_cpu_s"] for r in rs)
        results.append({"config": c, "logs": n, "wall_s": wall, "logs_per_s": n / wall, "cpu_s_per_log": cpu / n,
                        "parent_cpu_s_per_log": sum(r["parent_cpu_s"] for r in rs) / n,
                        "worker_max_rss_mb": extra[c].get("worker_max_rss_mb",
                                                          max(r["children_max_rss_mb"] for r in rs)),
                        "parent_max_rss_mb": max(r["parent_max_rss_mb"] for r in rs),
                        **{k: v for k, v in extra[c].items() if k != "worker_max_rss_mb"}})
    return {"results": results, "rounds": list(rounds), "rounds_planned": planned}


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
    configs = [r["config"] for r in doc["results"]]
    lines = ["# Fleet: logs per second and memory (benchmarks/fleet.py)", "",
             f"`{doc['command']}`", "",
             f"{doc['n_logs']} logs ({doc['size_mb']:.0f} MB), 2 workers, {doc['machine']['cpus']} CPUs, "
             f"{doc['date']}; `uptime` at the start: `{doc['uptime_before']}`, at the end: `{doc['uptime_after']}`. "
             f"The logs are cut into {doc['rounds_planned']} chunks and the configurations take turns on each "
             "(the order rotated every round), so background load falls on all alike"
             + (f"; {len(doc['rounds'])} of the {doc['rounds_planned']} rounds were run "
                f"({doc['results'][0]['logs']} logs per configuration)" if len(doc['rounds']) < doc['rounds_planned']
                else "") + ".", "",
             "| configuration | wall s | logs/s | vs fork | CPU s/log (all its processes) | of it the mavcal process "
             "| max worker RSS MB | parent RSS MB |", "|---|---|---|---|---|---|---|---|"]
    fork = next((r for r in doc["results"] if r["config"] == "fork"), None)
    for r in doc["results"]:
        vs = f"{r['logs_per_s'] / fork['logs_per_s']:.2f}" if fork else "-"
        lines.append(f"| {r['config']} | {r['wall_s']:.1f} | {r['logs_per_s']:.2f} | {vs} | {r['cpu_s_per_log']:.3f} | "
                     f"{r['parent_cpu_s_per_log']:.3f} | {r['worker_max_rss_mb']:.0f} | {r['parent_max_rss_mb']:.0f} |")
    lines += ["", "Per round (logs/s, and in brackets the ratio to the fork pool's of the same round; load average "
              "before the round):", "",
              "| round | logs | load | " + " | ".join(configs) + " |", "|---" * (3 + len(configs)) + "|"]
    for rd in doc["rounds"]:
        cells = []
        for c in configs:
            v = rd[c]["logs_per_s"]
            ratio = f" ({v / rd['fork']['logs_per_s']:.2f})" if "fork" in rd and c != "fork" else ""
            cells.append(f"{v:.2f}{ratio}")
        lines.append(f"| {rd['round']} | {rd['logs']} | {rd['load_before']:.2f} | " + " | ".join(cells) + " |")
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


# --------------------------------------------------------------------------- --why: a log's cost, where it runs

def _timed(source: str, heap: bool = False) -> tuple[float, float, float, int, float]:
    """One log's job (mavcal's per-log function, the CLI's options) timed where it runs: wall,
    this thread's CPU, the whole process's CPU, minor page faults, system CPU."""
    from contextlib import nullcontext

    import mavcal
    from mavcal.fleet.run import FleetJob, calibrate_entry, roomy_heap
    from mavcal.pipeline import Options

    job = FleetJob(Options(), None, mavcal.__version__, frozenset())
    ru0 = resource.getrusage(resource.RUSAGE_SELF)
    t0, c0, p0 = time.perf_counter(), time.thread_time(), time.process_time()
    with roomy_heap() if heap else nullcontext():
        calibrate_entry(job, source)
    ru1 = resource.getrusage(resource.RUSAGE_SELF)
    return (time.perf_counter() - t0, time.thread_time() - c0, time.process_time() - p0,
            ru1.ru_minflt - ru0.ru_minflt, ru1.ru_stime - ru0.ru_stime)


def _timed_heap(source: str):
    return _timed(source, heap=True)


WHY = {  # name: (how it runs, Dask config or environment)
    "plain process": ("plain", {}),
    "plain process, MALLOC_TRIM_THRESHOLD_=65536": ("plain", {"MALLOC_TRIM_THRESHOLD_": "65536"}),
    "forked child (the fork pool)": ("fork", {}),
    "Dask worker, as Dask starts it": ("dask", {}),
    "Dask worker, profiler off": ("dask", {"distributed.worker.profile.enabled": False}),
    "Dask worker, without MALLOC_TRIM_THRESHOLD_": ("dask", {"distributed.nanny.pre-spawn-environ": {
        "OMP_NUM_THREADS": 1, "MKL_NUM_THREADS": 1, "OPENBLAS_NUM_THREADS": 1}}),
    "Dask worker, mavcal's job (roomy_heap)": ("dask-mavcal", {}),
}


def why_one(name: str, logs: list[str]) -> list:
    how, cfg = WHY[name]
    _warm()
    _timed(logs[0])
    if how == "plain":
        return [_timed(s) for s in logs]
    if how == "fork":
        import multiprocessing as mp

        with mp.get_context("fork").Pool(1) as p:
            return p.map(_timed, logs, chunksize=1)
    import dask
    from distributed import Client, LocalCluster

    fn = _timed_heap if how == "dask-mavcal" else _timed
    with dask.config.set(cfg), LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                            dashboard_address=None) as lc, Client(lc) as c:
        c.run(_warm)
        c.submit(fn, logs[0], pure=False).result()
        return [c.submit(fn, s, pure=False).result() for s in logs]


def why(n: int, out_dir: Path) -> None:
    """The same logs, one at a time, in each place of :data:`WHY`, each in a fresh process (a
    LocalCluster's nanny sets its workers' environment in the process that starts it)."""
    with tempfile.TemporaryDirectory(prefix="mavcal-fleet-why-") as tmp:
        root = Path(tmp) / "fleet"
        logs = [str(p) for p in make_fleet(root, n, 0)]
        (Path(tmp) / "logs.txt").write_text("\n".join(logs))
        rows = []
        for name, (how, cfg) in WHY.items():
            env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", **{k: str(v) for k, v in cfg.items() if how == "plain"}}
            out = subprocess.run([sys.executable, __file__, "--why-one", name, str(Path(tmp) / "logs.txt")], env=env,
                                 capture_output=True, text=True, timeout=3000, check=True)
            res = json.loads(out.stdout.strip().splitlines()[-1])
            m = [sum(r[i] for r in res) / len(res) for i in range(5)]
            rows.append({"where": name, "wall_s": m[0], "thread_cpu_s": m[1], "process_cpu_s": m[2],
                         "minor_faults": m[3], "system_cpu_s": m[4], "load": os.getloadavg()[0]})
            print(rows[-1], file=sys.stderr, flush=True)
    lines = ["# A log's cost where it runs (benchmarks/fleet.py --why)", "",
             f"`python benchmarks/fleet.py --why {n}`, {datetime_utc()}; `uptime` at the end: `{_uptime()}`. "
             f"The same {n} logs one at a time; means per log. CPU times are what load distorts least.", "",
             "| where the log's job runs | wall s | CPU s, its thread | CPU s, its process | system CPU s "
             "| minor page faults | load |", "|---|---|---|---|---|---|---|"]
    lines += [f"| {r['where']} | {r['wall_s']:.3f} | {r['thread_cpu_s']:.3f} | {r['process_cpu_s']:.3f} | "
              f"{r['system_cpu_s']:.3f} | {r['minor_faults']:.0f} | {r['load']:.1f} |" for r in rows]
    (out_dir / "fleet.why.md").write_text("\n".join(lines) + "\n")
    (out_dir / "fleet.why.json").write_text(json.dumps(rows, indent=1) + "\n")


def datetime_utc() -> str:
    from datetime import datetime, timezone

    return datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")


def _uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True, check=False).stdout.strip()
    except OSError:
        return "load average: " + ", ".join(f"{x:.2f}" for x in os.getloadavg())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=60)
    ap.add_argument("--corrupt", type=int, default=3)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--configs", nargs="*", default=list(CONFIGS))
    ap.add_argument("--no-kill", action="store_true", help="leave out the killed-and-resumed run")
    ap.add_argument("--one", nargs=4, metavar=("CONFIG", "LIST", "TABLE", "ADDRESS"), help=argparse.SUPPRESS)
    ap.add_argument("--serve-localcluster", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--why", type=int, metavar="N", help="instead: N logs' cost per log in a plain process, a forked "
                    "child and a Dask worker with its settings switched one at a time (fleet.why.md)")
    ap.add_argument("--why-one", nargs=2, help=argparse.SUPPRESS)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_output import add_output_arguments, resolve  # --save / --out (benchmarks/README.md)

    add_output_arguments(ap)
    args = ap.parse_args()
    if args.serve_localcluster:
        return _serve_localcluster()
    if args.why_one:
        print(json.dumps(why_one(args.why_one[0], Path(args.why_one[1]).read_text().split("\n"))))
        return 0
    if args.why:
        why(args.why, resolve(args.save, args.out))
        return 0
    if args.one:
        print(json.dumps(run_one(*args.one)))
        return 0
    from contextlib import ExitStack
    from datetime import datetime, timezone

    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    up0 = _uptime()
    with tempfile.TemporaryDirectory(prefix="mavcal-fleet-bench-") as tmp, ExitStack() as stack:
        root = Path(tmp) / "fleet"
        logs = make_fleet(root, args.n, args.corrupt)
        size = sum(p.stat().st_size for p in logs) / 1e6
        print(f"{len(logs)} logs, {size:.0f} MB", file=sys.stderr)
        rel = [str(p.relative_to(root)) for p in logs]
        if any(c.endswith("-s3") for c in args.configs):
            from mavcal.testing.fleet import moto_s3

            s3env = stack.enter_context(moto_s3("fleet"))
            os.environ.update(s3env)  # this process's uploads, and every child (the dask workers too)
            env.update(s3env)
            import fsspec

            fs = fsspec.filesystem("s3")
            for r in rel:
                fs.put_file(str(root / r), f"fleet/{r}")
        k = max(1, min(args.rounds, len(rel)))
        chunks = [rel[i::k] for i in range(k)]  # every chunk a mix of the fleet's kinds of log
        def document(done: dict, kill: dict | None = None) -> dict:
            return {"machine": {"cpus": os.cpu_count(), "python": platform.python_version()}, "n_logs": len(logs),
                    "size_mb": size, "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
                    "command": "python benchmarks/fleet.py " + " ".join(sys.argv[1:]),
                    "uptime_before": up0, "uptime_after": _uptime(), **done, "killed_and_resumed": kill}

        out_dir = resolve(args.save, args.out)
        done = run_rounds(list(args.configs), chunks, root, Path(tmp), env,
                          on_round=lambda d: write_results(document(d), out_dir))
        kill = killed_and_resumed(str(root), str(Path(tmp) / "killed.csv"), str(Path(tmp) / "fork.csv")) \
            if "fork" in args.configs and not args.no_kill else None
        doc = document(done, kill)
    print(json.dumps(doc, indent=1))
    write_results(doc, out_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
