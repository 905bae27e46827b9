"""Fuzz every bundled and shared log through ``mavcal segments`` and ``mavcal calibrate``.

Each mutant (bit flips, truncation, splice, zeroed run, inserted bytes; see :func:`mutate`) of
every log in ``sitl_logs/``, ``../shared/data/real/`` and the PX4 ULogs of ``../shared/data/px4/``
(``--set`` picks one group) is written to a scratch file and run,
in a forked child with a time limit, through ``mavcal.cli.main(["-q", "segments", F])`` and
``mavcal.cli.main(["-q", "calibrate", F, "--json", J])``. A run is

- a **traceback** when an exception escapes ``main``, or ``main`` returns the last-resort
  "internal error" exit code (:data:`mavcal.cli.EXIT_INTERNAL`), or an exit code outside the
  documented ones, or an error exit prints anything but one ``mavcal: error:`` line, or that
  line names a Python exception (``KeyError``...: :func:`mavcal.testing.damaged.error_line_problem`);
- a **hang** when the child outlives ``--timeout`` seconds (it is killed).

Prints a table of tracebacks and hangs per log and mutation kind, writes ``fuzz_logs.md`` and
``fuzz_logs.json`` (``fuzz_logs_px4.*`` / ``fuzz_logs_ardupilot.*`` for ``--set``; benchmarks/README.md: ``benchmarks/out/`` by default, ``--save`` for
``benchmarks/results/``) and keeps every failing mutant under ``<out>/fuzz_failures/`` to replay
with ``mavcal -vv``.

    python benchmarks/fuzz_logs.py --mutants 10000 --workers 2          # the issue's bar
    python benchmarks/fuzz_logs.py --set px4 --mutants 5000 --timeout 60   # issue 35: PX4 ULogs
    python benchmarks/fuzz_logs.py --set ardupilot --mutants 5000 --timeout 60
    python benchmarks/fuzz_logs.py --mutants 200 --workers 1            # smoke run

The mutants are spread over the logs in inverse proportion to each log's own run time (a log
that takes 20 s to calibrate gets fewer mutants than one refused in 50 ms), every log at least
``--min-per-log``; the seed makes a run repeatable.
"""
from __future__ import annotations

import argparse
import collections
import io
import json
import os
import random
import select
import signal
import sys
import tempfile
import time
import traceback
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(REPO))
OUT = HERE / "out"

KINDS = ("bitflip", "truncate", "splice", "zero", "insert")
DOCUMENTED = {0, 2, 3, 4, 5, 6, 7}  # mavcal.errors / cli --help
LOG_SUFFIXES = {".tlog", ".bin", ".log", ".csv", ".ulg"}
SETS = ("all", "ardupilot", "px4")


def default_logs(which: str = "all") -> list[Path]:
    """The logs of ``which`` set: ``ardupilot`` (the bundled sitl_logs/*.tlog and every log in
    ../shared/data/real/), ``px4`` (every ULog in ../shared/data/px4/) or ``all``."""
    shared = REPO.parent / "shared" / "data"
    if not shared.is_dir():
        shared = Path("/work/shared/data")
    logs: list[Path] = []
    if which in ("all", "ardupilot"):
        logs += sorted((REPO / "sitl_logs").glob("*.tlog"))
        logs += sorted(p for p in (shared / "real").glob("*") if p.suffix.lower() in LOG_SUFFIXES)
    if which in ("all", "px4"):
        logs += sorted(p for p in (shared / "px4").glob("*.ulg"))
    return logs


def mutate(data: bytes, kind: str, rng: random.Random) -> bytes:
    """One damaged copy of ``data``: the damage an SD card, a radio link or a cut-off write does."""
    n = len(data)
    if n == 0:
        return data
    if kind == "bitflip":  # 1..16 single-bit errors
        b = bytearray(data)
        for _ in range(rng.randint(1, 16)):
            i = rng.randrange(n)
            b[i] ^= 1 << rng.randrange(8)
        return bytes(b)
    if kind == "truncate":  # the write stopped (power loss)
        return data[:rng.randrange(n)]
    if kind == "splice":  # a block from elsewhere in the file, or a block lost
        i, j = sorted(rng.randrange(n) for _ in range(2))
        if rng.random() < 0.5:
            return data[:i] + data[j:]
        k = rng.randrange(n)
        ln = rng.randint(1, 4096)
        return data[:i] + data[k:k + ln] + data[i:]
    if kind == "zero":  # an erased flash page
        i = rng.randrange(n)
        ln = rng.choice((1, 16, 256, 512, 4096, 65536))
        return data[:i] + bytes(min(ln, n - i)) + data[i + ln:]
    if kind == "insert":  # garbage bytes
        i = rng.randrange(n)
        return data[:i] + bytes(rng.randrange(256) for _ in range(rng.randint(1, 64))) + data[i:]
    raise ValueError(kind)


def _cli_run(argv: list[str]) -> dict:
    """``mavcal.cli.main(argv)`` in this (child) process: exit code, stderr, escaped exception."""
    from mavcal import cli

    err, out = io.StringIO(), io.StringIO()
    res: dict = {"argv": argv[1:2]}
    try:
        with redirect_stderr(err), redirect_stdout(out):
            code = cli.main(argv)
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    except BaseException as exc:  # noqa: BLE001 - what the fuzzer looks for
        res.update(code=None, error=f"{type(exc).__name__}: {exc}"[:300],
                   where=traceback.format_exc().strip().splitlines()[-3].strip()[:200])
        return res
    from mavcal.testing.damaged import error_line_problem

    res["code"] = code
    lines = [x for x in err.getvalue().splitlines() if x.strip()]
    res["stderr"] = lines[-3:]
    if code not in DOCUMENTED:
        res["error"] = (lines[-1] if lines else f"exit code {code}")[:300]
    else:
        problem = error_line_problem(code, err.getvalue())
        if problem:
            res["error"] = problem
    return res


def _child(path: Path, json_path: Path) -> list[dict]:
    return [_cli_run(["-q", "segments", str(path)]),
            _cli_run(["-q", "calibrate", str(path), "--json", str(json_path)])]


def _warm_up() -> None:
    """Import everything a run needs once, in the parent, so that every forked child starts warm."""
    import mavcal.cli  # noqa: F401
    import mavcal.commands.calibrate  # noqa: F401
    import mavcal.commands.segments  # noqa: F401
    import mavcal.pipeline  # noqa: F401
    import mavcal.report.json  # noqa: F401
    import mavcal.report.text  # noqa: F401
    import mavcal.sources.fast_dataflash  # noqa: F401
    import mavcal.sources.fast_tlog  # noqa: F401
    import mavcal.sources.ulog  # noqa: F401
    import mavcal.testing.damaged  # noqa: F401
    try:
        import pymavlink.mavutil  # noqa: F401
        import pyulog  # noqa: F401
    except ImportError:  # pragma: no cover
        pass


class Runner:
    """At most ``workers`` forked children at a time, each killed after ``timeout`` seconds."""

    def __init__(self, workers: int, timeout: float, scratch: Path) -> None:
        self.workers, self.timeout, self.scratch = workers, timeout, scratch
        self.running: dict[int, tuple] = {}  # pid -> (task, read fd, start, chunks)

    def start(self, task: tuple, data: bytes) -> None:
        log_path, kind, idx = task
        f = self.scratch / f"m{idx}{log_path.suffix}"
        f.write_bytes(data)
        r, w = os.pipe()
        pid = os.fork()
        if pid == 0:  # child
            os.close(r)
            try:
                res = _child(f, self.scratch / f"m{idx}.json")
                payload = json.dumps(res).encode()
            except BaseException as exc:  # noqa: BLE001
                payload = json.dumps([{"code": None, "error": f"harness: {type(exc).__name__}: {exc}"}]).encode()
            os.write(w, payload)
            os.close(w)
            os._exit(0)
        os.close(w)
        self.running[pid] = (task, r, time.monotonic(), [], f)

    def wait_one(self) -> list[tuple[tuple, list[dict] | None, float]]:
        """Block until at least one child is done or overdue; (task, results or None for a hang, s)."""
        done = []
        while not done:
            fds = {v[1]: pid for pid, v in self.running.items()}
            ready, _, _ = select.select(list(fds), [], [], 0.2)
            for fd in ready:
                chunk = os.read(fd, 65536)
                pid = fds[fd]
                if chunk:
                    self.running[pid][3].append(chunk)
                    continue
                task, r, t0, chunks, f = self.running.pop(pid)
                os.close(r)
                os.waitpid(pid, 0)
                try:
                    res = json.loads(b"".join(chunks).decode())
                except ValueError:
                    res = [{"code": None, "error": "child died without a result (signal or os._exit)"}]
                done.append((task, res, time.monotonic() - t0, f))
            now = time.monotonic()
            for pid, (task, r, t0, _chunks, f) in list(self.running.items()):
                if now - t0 > self.timeout:
                    os.kill(pid, signal.SIGKILL)
                    os.waitpid(pid, 0)
                    os.close(r)
                    self.running.pop(pid)
                    done.append((task, None, now - t0, f))
        return done


def _baseline_cost(logs: list[Path], runner: Runner) -> dict[Path, float]:
    cost = {}
    for p in logs:
        runner.start((p, "none", -1), p.read_bytes())
        (_task, _res, dt, f), = runner.wait_one()
        f.unlink(missing_ok=True)
        cost[p] = max(dt, 0.05)
    return cost


def allocate(cost: dict[Path, float], total: int, min_per_log: int) -> dict[Path, int]:
    """Mutants per log: ``total`` spread in inverse proportion to each log's run time, at least ``min_per_log``."""
    inv = {p: 1.0 / c for p, c in cost.items()}
    s = sum(inv.values())
    n = {p: max(min_per_log, int(round(total * v / s))) for p, v in inv.items()}
    while sum(n.values()) < total:  # rounding: top up the cheapest
        n[min(cost, key=cost.get)] += total - sum(n.values())  # type: ignore[arg-type]
    return n


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mutants", type=int, default=10000, help="mutants in all (default 10000)")
    ap.add_argument("--min-per-log", type=int, default=60, help="at least this many mutants of each log")
    ap.add_argument("--workers", type=int, default=2, help="forked children at a time (default 2)")
    ap.add_argument("--timeout", type=float, default=60.0, help="seconds before a child counts as a hang")
    ap.add_argument("--set", choices=SETS, default="all", help="which logs (default all): ardupilot, px4")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--kinds", default=",".join(KINDS), help="mutation kinds (comma separated)")
    ap.add_argument("logs", nargs="*", type=Path, help="logs to mutate (default: sitl_logs and ../shared/data/real)")
    args = ap.parse_args(argv)
    logs = args.logs or default_logs(args.set)
    kinds = [k for k in args.kinds.split(",") if k]
    _warm_up()
    t_start = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="mavcal-fuzz-") as tmp:
        runner = Runner(max(1, args.workers), args.timeout, Path(tmp))
        cost = _baseline_cost(logs, runner)
        per_log = allocate(cost, args.mutants, args.min_per_log)
        print(f"{sum(per_log.values())} mutants of {len(logs)} logs, {args.workers} workers; estimated "
              f"{sum(per_log[p] * cost[p] for p in logs) / max(1, args.workers) / 60:.0f} min", file=sys.stderr)
        tasks = []
        rng = random.Random(args.seed)
        for p in logs:
            tasks += [(p, kinds[i % len(kinds)], rng.randrange(1 << 30)) for i in range(per_log[p])]
        rng.shuffle(tasks)
        counts = collections.defaultdict(lambda: collections.Counter())  # (log, kind) -> Counter
        failures: list[dict] = []
        keep = OUT / "fuzz_failures"
        data_of: dict[Path, bytes] = {}
        pending = list(tasks)
        done_n = 0
        stop: list[int] = []  # SIGTERM/SIGINT: finish the table with what was run
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda s, _f: stop.append(s))
        while (pending or runner.running) and not stop:
            while pending and len(runner.running) < runner.workers:
                p, kind, seed = pending.pop()
                if p not in data_of:
                    data_of[p] = p.read_bytes()
                runner.start((p, kind, seed), mutate(data_of[p], kind, random.Random(seed)))
            for (p, kind, seed), res, dt, f in runner.wait_one():
                c = counts[(p.name, kind)]
                c["mutants"] += 1
                bad = None
                if res is None:
                    c["hangs"] += 1
                    bad = {"hang_s": round(dt, 1)}
                else:
                    for r in res:
                        c[f"exit{r.get('code')}_{r.get('argv', ['?'])[0]}"] += 1
                        if r.get("error"):
                            c["tracebacks"] += 1
                            bad = r
                            break
                if bad is not None:
                    keep.mkdir(parents=True, exist_ok=True)
                    name = f"{p.stem.replace(' ', '_')}.{kind}.{seed}{p.suffix}"
                    (keep / name).write_bytes(f.read_bytes())
                    failures.append({"log": p.name, "kind": kind, "seed": seed, "mutant": name, **bad})
                    print(f"FAIL {name}: {bad.get('error') or bad}", file=sys.stderr)
                f.unlink(missing_ok=True)
                done_n += 1
                if done_n % 500 == 0:  # a partial table too, in case the run is stopped
                    print(f"{done_n}/{len(tasks)} mutants, {len(failures)} failures, "
                          f"{(time.monotonic() - t_start) / 60:.1f} min", file=sys.stderr)
                    _write(args, logs, kinds, counts, failures, per_log, cost, time.monotonic() - t_start,
                           quiet=True, partial=f"{done_n} of {len(tasks)}")
            if stop:
                print(f"stopped after {done_n} mutants", file=sys.stderr)
                for pid in list(runner.running):
                    os.kill(pid, signal.SIGKILL)
                    os.waitpid(pid, 0)
                return _write(args, logs, kinds, counts, failures, per_log, cost, time.monotonic() - t_start,
                              partial=f"{done_n} of {len(tasks)} (stopped)")
    return _write(args, logs, kinds, counts, failures, per_log, cost, time.monotonic() - t_start)


def _write(args, logs, kinds, counts, failures, per_log, cost, elapsed, quiet: bool = False,
           partial: str = "") -> int:
    rows = []
    lines = ["# Fuzzing the readers: mutants of every bundled and shared log", "",
             f"Produced by `python benchmarks/fuzz_logs.py --set {args.set} --mutants {args.mutants} "
             f"--min-per-log {args.min_per_log} --workers {args.workers} "
             f"--timeout {args.timeout:g} --seed {args.seed}` in {elapsed / 60:.1f} min. Each mutant ran through "
             "`mavcal -q segments F` and `mavcal -q calibrate F --json J` in a forked child."
             + (f" **Partial: {partial} mutants.**" if partial else ""), "",
             "| log | kind | mutants | tracebacks | hangs | segments exit codes | calibrate exit codes |",
             "|---|---|---:|---:|---:|---|---|"]
    for p in logs:
        for k in kinds:
            c = counts.get((p.name, k))
            if not c:
                continue
            seg = ", ".join(f"{key[4:].split('_')[0]}:{v}" for key, v in sorted(c.items())
                            if key.startswith("exit") and key.endswith("_segments"))
            cal = ", ".join(f"{key[4:].split('_')[0]}:{v}" for key, v in sorted(c.items())
                            if key.startswith("exit") and key.endswith("_calibrate"))
            rows.append({"log": p.name, "kind": k, "mutants": c["mutants"], "tracebacks": c["tracebacks"],
                         "hangs": c["hangs"], "segments_exit": seg, "calibrate_exit": cal})
            lines.append(f"| {p.name} | {k} | {c['mutants']} | {c['tracebacks']} | {c['hangs']} | {seg} | {cal} |")
    tot = {x: sum(r[x] for r in rows) for x in ("mutants", "tracebacks", "hangs")}
    lines += [f"| **all** | | **{tot['mutants']}** | **{tot['tracebacks']}** | **{tot['hangs']}** | | |", ""]
    if failures:
        lines += ["## Failures", ""] + [f"- {f['mutant']}: {f.get('error') or f}" for f in failures[:200]]
    text = "\n".join(lines) + "\n"
    if not quiet:
        print(text)
    stem = "fuzz_logs" if args.set == "all" and not args.logs else f"fuzz_logs_{args.set}"
    (OUT / f"{stem}.md").write_text(text)
    (OUT / f"{stem}.json").write_text(json.dumps({"totals": tot, "rows": rows, "failures": failures,
                                                    "per_log": {p.name: per_log[p] for p in logs},
                                                    "baseline_s": {p.name: round(cost[p], 3) for p in logs}},
                                                   indent=1))
    return 1 if tot["tracebacks"] or tot["hangs"] else 0


if __name__ == "__main__":
    from bench_output import output_dir  # --save / --out: where the results go (benchmarks/README.md)

    OUT, _argv = output_dir(sys.argv[1:])  # the other arguments go on to main's own parser
    sys.exit(main(_argv))
