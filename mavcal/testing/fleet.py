"""Fixtures of the fleet tests and benchmark: a small fleet of logs on disk, moto's S3 server
and a Dask scheduler with workers, each started on 127.0.0.1 as separate processes and
stopped (killed) on leaving.

Nothing here listens anywhere but loopback. moto and dask come with the ``test`` extra.
"""
from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

__all__ = ["make_fleet", "moto_s3", "dask_cluster", "comparable", "free_port", "VOLATILE", "row_differences",
           "assert_same_rows", "heap_probe"]

#: Columns that differ between two runs of the same logs (when, how long, where from).
VOLATILE = ("source", "finished_utc", "elapsed_s")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait_port(port: int, proc: subprocess.Popen, timeout_s: float, what: str) -> None:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if proc.poll() is not None:
            raise RuntimeError(f"{what} ended with status {proc.returncode} before listening")
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.1)
    raise TimeoutError(f"{what} did not listen on 127.0.0.1:{port} within {timeout_s:.0f} s")


def _stop(procs: Sequence[subprocess.Popen]) -> None:
    for p in procs:
        if p.poll() is None:
            try:
                os.killpg(p.pid, signal.SIGKILL)  # its own group: the process and any it started
            except ProcessLookupError:
                pass
    for p in procs:
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            pass


def _bin(name: str) -> str:
    here = Path(sys.executable).parent / name
    return str(here) if here.exists() else (shutil.which(name) or name)


def make_fleet(root: Path, sitl_dir: Path, real_dir: Path | None = None) -> list[Path]:
    """A small fleet under ``root``: the two SITL logs in sub-directories, each also as a copy
    with a few bytes appended (another content, the same calibration), a corrupt tlog, a short
    real DataFlash log when ``real_dir`` has it, and a file that is no log (ignored). Returns
    the logs, sorted."""
    (root / "a").mkdir(parents=True, exist_ok=True)
    (root / "b" / "c").mkdir(parents=True, exist_ok=True)
    logs = []
    for name, sub, again in (("sitl01.tlog", "a", "a"), ("sitl02.tlog", "b", "b/c")):
        data = (sitl_dir / name).read_bytes()
        (root / sub / name).write_bytes(data)
        (root / again / f"again-{name}").write_bytes(data + b"\x00" * 7)
    corrupt = bytes((i * 37 + 11) % 251 for i in range(3000)).replace(b"\xfd", b"\x00").replace(b"\xfe", b"\x00")
    (root / "b" / "corrupt.tlog").write_bytes(corrupt)
    if real_dir is not None and (real_dir / "test.BIN").exists():
        (root / "short.BIN").write_bytes((real_dir / "test.BIN").read_bytes())
    (root / "notes.txt").write_text("not a log\n")
    for dirpath, _, files in os.walk(root):
        logs += [Path(dirpath) / f for f in files if not f.endswith(".txt")]
    return sorted(logs)


@contextmanager
def moto_s3(bucket: str = "fleet") -> Iterator[dict[str, str]]:
    """moto's S3 server on 127.0.0.1 (a process of its own) with ``bucket`` made; yields the
    environment that points the AWS clients at it (``AWS_ENDPOINT_URL``, dummy keys), which
    the caller sets (``monkeypatch.setenv``) for itself and its child processes."""
    port = free_port()
    env = {"AWS_ENDPOINT_URL": f"http://127.0.0.1:{port}", "AWS_ACCESS_KEY_ID": "testing",
           "AWS_SECRET_ACCESS_KEY": "testing", "AWS_DEFAULT_REGION": "us-east-1"}
    proc = subprocess.Popen([_bin("moto_server"), "-H", "127.0.0.1", "-p", str(port)], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True, env={**os.environ, **env})
    try:
        _wait_port(port, proc, 60, "moto_server")
        import fsspec

        fs = fsspec.filesystem("s3", endpoint_url=env["AWS_ENDPOINT_URL"], key="testing", secret="testing")
        fs.mkdir(bucket)
        yield env
    finally:
        _stop([proc])


@contextmanager
def dask_cluster(workers: int = 2, timeout_s: float = 90) -> Iterator[str]:
    """A ``dask scheduler`` and ``workers`` ``dask worker`` processes (one thread each) on
    127.0.0.1, started separately as on a cluster; yields the scheduler's address; all killed
    on leaving. Each is a process group of its own (killed as one) in this session: a session
    of its own would give each its own share of the CPUs under Linux's autogroup scheduling,
    which made the benchmark's separate workers faster than the fork pool under other load."""
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "DASK_DISTRIBUTED__WORKER__DAEMON": "False"}
    procs = [subprocess.Popen([_bin("dask"), "scheduler", "--host", "127.0.0.1", "--port", str(port),
                               "--no-dashboard"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                              preexec_fn=os.setpgrp, env=env)]
    try:
        _wait_port(port, procs[0], timeout_s, "dask scheduler")
        for _ in range(workers):
            procs.append(subprocess.Popen([_bin("dask"), "worker", address, "--host", "127.0.0.1", "--nthreads", "1",
                                           "--nworkers", "1", "--no-dashboard", "--memory-limit", "0"],
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                          preexec_fn=os.setpgrp, env=env))
        from distributed import Client

        with Client(address, timeout=f"{timeout_s}s") as c:
            c.wait_for_workers(workers, timeout=timeout_s)
        yield address
    finally:
        _stop(procs)


def heap_probe() -> tuple[str | None, bool]:
    """In a Dask worker (``client.run``): its ``MALLOC_TRIM_THRESHOLD_`` and whether
    :func:`mavcal.fleet.run.roomy_heap` changes glibc's heap settings for a job there."""
    from mavcal.fleet.run import roomy_heap

    with roomy_heap() as changed:
        return os.environ.get("MALLOC_TRIM_THRESHOLD_"), changed


def comparable(rows: Sequence[dict], root: str | None = None, columns: Sequence[str] | None = None) -> list[tuple]:
    """A table's rows as sorted tuples without the columns that differ between runs, each
    row's log named by its path under ``root`` (a directory, a bucket URL); ``columns``: the
    table's (``mavcal calibrate``'s by default)."""
    from mavcal.fleet.table import COLUMNS

    columns = COLUMNS if columns is None else columns

    def named(v):  # the root in messages too ("no MAVLink frames in ROOT/b/x.tlog")
        return v.replace(root.rstrip("/") + "/", "") if isinstance(v, str) and root is not None else v

    out = []
    for r in rows:
        out.append((named(str(r["source"])), *(named(r[c]) for c in columns if c not in VOLATILE)))
    return sorted(out, key=lambda t: t[0])


def row_differences(actual: Sequence[tuple], expected: Sequence[tuple]) -> list[str]:
    """Where two :func:`comparable` tables differ: text, integers and flags exactly, numbers
    at :func:`mavcal.testing.numbers.numbers_close`'s golden tolerance."""
    from mavcal.testing.numbers import numbers_close

    if [r[0] for r in actual] != [r[0] for r in expected]:
        return [f"logs {[r[0] for r in actual]} vs {[r[0] for r in expected]}"]
    out = []
    for a, e in zip(actual, expected):
        for i, (x, y) in enumerate(zip(a, e)):
            same = (x == y) if not (isinstance(x, float) and isinstance(y, float)) else numbers_close(x, y)
            if not same:
                out.append(f"{a[0]}: field {i}: {x!r} vs {y!r}")
    return out


def assert_same_rows(actual: Sequence[tuple], expected: Sequence[tuple]) -> None:
    diffs = row_differences(actual, expected)
    assert not diffs, "\n".join(diffs[:20])
