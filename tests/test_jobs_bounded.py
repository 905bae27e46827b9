"""Issue 23, part 3: ``--jobs`` starts the processes the work needs, never the number typed,
and no worker outlives its parent (mavcal.workers.ForkPool, mavcal.batch, the CLI).

The limits here are correctness limits with a wide margin (60 s, 16 processes, 2 GB), not
timings: the process tree is sampled while the command runs."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

from mavcal import batch
from mavcal import workers as W
from mavcal.pipeline import Options

REPO = Path(__file__).resolve().parents[1]
pytestmark = [pytest.mark.skipif(not W.can_fork(), reason="needs fork"),
              pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads the process tree in /proc")]


def _children() -> dict[int, list[int]]:
    kids: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                stat = Path(f"/proc/{d}/stat").read_text()
            except OSError:
                continue
            ppid = int(stat.rsplit(")", 1)[1].split()[1])
            kids.setdefault(ppid, []).append(int(d))
    return kids


def _tree(root: int) -> list[int]:
    """``root`` and every process below it, alive now."""
    kids, out, todo = _children(), [], [root]
    while todo:
        p = todo.pop()
        out.append(p)
        todo += kids.get(p, [])
    return out


def _rss_mb(pids: list[int]) -> float:
    total = 0.0
    for p in pids:
        try:
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1]) / 1024
        except OSError:
            pass
    return total


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _with_marker(marker: str) -> list[int]:
    """Processes alive whose command line contains ``marker`` (a forked worker keeps its parent's)."""
    out = []
    for d in os.listdir("/proc"):
        if d.isdigit() and int(d) != os.getpid():
            try:
                if marker in Path(f"/proc/{d}/cmdline").read_bytes().decode(errors="replace") and _alive(int(d)):
                    out.append(int(d))
            except OSError:
                pass
    return out


class TreeWatch(threading.Thread):
    """Samples a process tree every 50 ms (a scan of /proc costs a few ms of CPU, which the
    tests running beside this one need): most processes and most summed RSS at once."""

    def __init__(self, root: int) -> None:
        super().__init__(daemon=True)
        self.root, self.most, self.most_mb, self.stopped = root, 0, 0.0, threading.Event()

    def run(self) -> None:
        while not self.stopped.is_set():
            pids = [p for p in _tree(self.root) if _alive(p)]
            self.most = max(self.most, len(pids))
            self.most_mb = max(self.most_mb, _rss_mb(pids))
            time.sleep(0.05)


def _mavcal(args: list[str]) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "mavcal.cli", *args], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _gone(pids: list[int], timeout_s: float = 20.0) -> list[int]:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and any(_alive(p) for p in pids):
        time.sleep(0.05)
    return [p for p in pids if _alive(p)]


def _sleep_job(shared, item):
    time.sleep(item)
    return item


def test_the_pool_forks_for_waiting_jobs_only_and_never_past_the_limit(monkeypatch):
    monkeypatch.setattr(W, "_cpus", lambda: 64)
    assert W.worker_limit() == W.MAX_WORKERS == 15
    with W.ForkPool(None, 100_000) as pool:
        assert pool.workers == 15
        seen = []
        pool.run(_sleep_job, [0.2, 0.2, 0.2], lambda item, outcome: seen.append(outcome) or [])
        assert len(pool.pids) == 3  # three jobs at once: three workers, not fifteen
    assert seen == [(True, 0.2)] * 3 and pool.pids == []
    monkeypatch.setattr(W, "_cpus", lambda: 2)
    assert W.ForkPool(None, 100_000).workers == 2 and W.ForkPool(None, 1).workers == 1


def _pid_job(shared, item):
    return os.getpid()


def test_a_worker_is_replaced_after_max_tasks():
    got = []
    with W.ForkPool(None, 2, max_tasks=1) as pool:
        pool.run(_pid_job, list(range(5)), lambda item, outcome: got.append(outcome[1]) or [])
        assert len(pool.pids) <= 2
    assert len(set(got)) == 5 and os.getpid() not in got


_PARENT_SCRIPT = textwrap.dedent("""
    import signal, sys, time
    from mavcal.workers import ForkPool

    # Ctrl-C as in a terminal: a pytest-xdist worker ignores SIGINT, and a child started with
    # SIGINT ignored gets no KeyboardInterrupt handler from Python
    signal.signal(signal.SIGINT, signal.default_int_handler)

    if sys.argv[1] == "no-prctl":
        sys.platform = "darwin"  # the workers watch the parent's pid instead

    def sleep(shared, seconds):
        time.sleep(seconds)

    with ForkPool(None, 2) as pool:
        pool.run(sleep, [600, 600], lambda item, outcome: [])
""")


@pytest.mark.parametrize("how", ["SIGKILL", "SIGINT", "no-prctl"])
def test_workers_die_with_their_parent(how):
    """A parent killed by SIGKILL in the middle of its workers' jobs (which would take ten
    minutes) leaves no worker: the kernel ends them (PR_SET_PDEATHSIG), or where there is no
    prctl, they see their parent's pid change. On Ctrl-C the parent stops them as it leaves."""
    proc = subprocess.Popen([sys.executable, "-c", _PARENT_SCRIPT, how], cwd=REPO)
    try:
        pids: list[int] = []
        end = time.monotonic() + 60
        while len(pids) < 2 and time.monotonic() < end:
            time.sleep(0.05)
            pids = [p for p in _tree(proc.pid) if p != proc.pid and _alive(p)]
        assert len(pids) == 2
        time.sleep(0.3)  # the workers are in their jobs
        proc.send_signal(signal.SIGINT if how == "SIGINT" else signal.SIGKILL)
        proc.wait(timeout=30)
        assert _gone(pids) == []
    finally:
        proc.kill()
        proc.wait()


def test_jobs_100000_on_one_log_is_capped_and_bounded(tmp_path):
    """The issue's command: it forked 5,738 processes and was killed out of memory. Now: one
    line saying how many processes, the normal result, <= 16 processes and < 2 GB at any time,
    within 60 s, and no process left."""
    marker = str(tmp_path / "jobs100000.json")
    proc = _mavcal(["calibrate", "sitl_logs/sitl02.tlog", "--jobs", "100000", "--json", marker])
    watch = TreeWatch(proc.pid)
    watch.start()
    try:
        out, err = proc.communicate(timeout=60)
    finally:
        watch.stopped.set()
        proc.kill()
    watch.join()
    assert proc.returncode == 0, err
    assert err.count("\n") == 1 and "--jobs 100000 is more than the" in err and "using" in err
    assert "ACCEPTED" in out and Path(marker).exists()
    assert 1 <= watch.most <= 16 and watch.most_mb < 2048
    assert _gone(_with_marker(marker), 10) == []


def test_kill_9_of_the_parent_during_the_fits_leaves_no_worker(tmp_path):
    marker = str(tmp_path / "kill9.json")
    proc = _mavcal(["calibrate", "sitl_logs/sitl02.tlog", "--jobs", "2", "--json", marker])
    try:
        workers: list[int] = []
        end = time.monotonic() + 60
        while not workers and proc.poll() is None and time.monotonic() < end:
            workers = [p for p in _tree(proc.pid) if p != proc.pid]
            time.sleep(0.01)
        if not workers:
            pytest.skip("the fits were over before a worker was seen")  # not seen on this machine so far
        proc.kill()
        proc.wait(timeout=30)
        assert _gone(workers + _with_marker(marker), 10) == []
    finally:
        proc.kill()
        proc.wait()


def test_fleet_jobs_100000_is_capped_and_bounded(tmp_path):
    logs = []
    for k in range(3):  # three logs: at most three workers whatever --jobs says
        (tmp_path / f"v{k}.tlog").symlink_to(REPO / "sitl_logs" / ("sitl01.tlog" if k == 0 else "sitl02.tlog"))
        logs.append(str(tmp_path / f"v{k}.tlog"))
    marker = str(tmp_path / "fleet.json")
    proc = _mavcal(["calibrate", *logs, "--jobs", "100000", "--json", marker])
    watch = TreeWatch(proc.pid)
    watch.start()
    try:
        out, err = proc.communicate(timeout=120)
    finally:
        watch.stopped.set()
        proc.kill()
    watch.join()
    assert proc.returncode == 0, err
    assert "--jobs 100000 is more than the" in err and "3 logs: 3 accepted" in out
    assert 1 <= watch.most <= min(4, 1 + W.worker_limit()) and watch.most_mb < 2048
    assert _gone(_with_marker(marker), 10) == []


def _one_dies(source, options, csv_rate_hz=None):
    if source.endswith("dies.tlog"):
        os.kill(os.getpid(), signal.SIGKILL)  # as the out-of-memory killer would
    return batch.BatchRow(source=source, ok=True, exit_code=0, accepted=True)


def test_a_fleet_worker_that_dies_fails_its_log_alone(monkeypatch):
    monkeypatch.setattr(batch, "_calibrate_one", _one_dies)
    rows = batch.calibrate_many(["a.tlog", "dies.tlog", "b.tlog"], Options(), jobs=2)
    assert [r.source for r in rows] == ["a.tlog", "dies.tlog", "b.tlog"]
    assert rows[0].ok and rows[2].ok and not rows[1].ok and rows[1].exit_code == 70
    assert "killed by signal 9" in (rows[1].error or "") and "\n" not in (rows[1].error or "")


_TEST_PID = os.getpid()


def _dying_pair(real, mag_instance):
    def fit(prep, o, stats):
        if os.getpid() != _TEST_PID and o.mag_instance == mag_instance:
            os.kill(os.getpid(), signal.SIGKILL)  # as the out-of-memory killer would
        return real(prep, o, stats)
    return fit


def test_a_fit_worker_that_dies_rejects_its_sensor(monkeypatch, sitl_dir):
    from mavcal import fits
    from mavcal.pipeline import calibrate_prepared, prepare

    monkeypatch.setattr(fits, "_fit_pair", _dying_pair(fits._fit_pair, 1))
    run = calibrate_prepared(prepare(str(sitl_dir / "sitl02.tlog")), Options(workers=2))
    verdicts = {v.sensor: v for v in run.verdicts}
    assert run.exit_code == 7 and not verdicts["compass1"].accepted
    assert verdicts["compass0"].accepted and verdicts["compass2"].accepted and verdicts["accel1"].accepted
    assert "killed by signal 9 (SIGKILL) (out of memory?)" in verdicts["compass1"].reasons[0]
    assert not any(n.startswith("COMPASS_OFS2") for n in run.params_to_write())


def test_the_primary_fit_worker_dying_is_one_line_and_exit_70(monkeypatch, capsys, sitl_dir):
    from mavcal import fits
    from mavcal.cli import main

    monkeypatch.setattr(fits, "_fit_pair", _dying_pair(fits._fit_pair, 0))
    assert main(["calibrate", str(sitl_dir / "sitl02.tlog"), "--jobs", "2"]) == 70
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "killed by signal 9" in err and err.startswith("mavcal: error:")


def _nested_job(shared, item):
    """A job that runs a pool of its own (a fleet worker fitting its log's sensors in workers)."""
    got = []
    with W.ForkPool(shared * 10, 2) as pool:
        pool.run(_times_shared, [item, item + 1], lambda i, outcome: got.append(outcome[1]) or [])
    return sorted(got)


def _times_shared(shared, item):
    return shared * item


def test_a_job_may_run_a_pool_of_its_own():
    got = {}
    with W.ForkPool(3, 2) as pool:
        pool.run(_nested_job, [1, 5], lambda item, outcome: got.update({item: outcome}) or [])
    assert got == {1: (True, [30, 60]), 5: (True, [150, 180])}
