"""A fleet's logs on a Dask cluster (issue 40, item 3): a `dask scheduler` and two `dask worker`
processes started separately on 127.0.0.1 give the fork pool's rows."""
from __future__ import annotations

import pytest

from mavcal.cli import main
from mavcal.errors import UsageError
from mavcal.fleet import run as fleet_run
from mavcal.fleet.run import run_fleet
from mavcal.fleet.table import read_table
from mavcal.pipeline import Options
from mavcal.testing.fleet import assert_same_rows, comparable, dask_cluster, free_port, make_fleet

pytest.importorskip("distributed")
FAST = Options(uncertainty_draws=50)


@pytest.fixture(scope="module")
def fleet(tmp_path_factory, sitl_dir, real_dir):
    root = tmp_path_factory.mktemp("fleet")
    logs = [str(p) for p in make_fleet(root, sitl_dir, real_dir)]
    table = root.parent / "fork.csv"
    run_fleet(logs, FAST, jobs=2, table=str(table))
    return root, logs, read_table(table)


@pytest.mark.timeout(240)
def test_separate_scheduler_and_two_workers_give_the_fork_pool_rows(fleet, tmp_path, monkeypatch, capsys):
    root, logs, fork = fleet
    monkeypatch.setattr(fleet_run, "MIN_WINDOW", 1)  # two jobs on the cluster at a time: the rest wait here
    monkeypatch.setattr(fleet_run, "WINDOW_PER_WORKER", 1)
    with dask_cluster(workers=2) as address:
        table = tmp_path / "dask.csv"
        done = run_fleet(logs, FAST, table=str(table), scheduler_address=address)
        assert [r.source for r in done.rows] == logs
        assert_same_rows(comparable(read_table(table), str(root)), comparable(fork, str(root)))
        # the CLI, with the scheduler from DASK_SCHEDULER_ADDRESS (the environment Dask's own clients use)
        monkeypatch.setenv("DASK_SCHEDULER_ADDRESS", address)
        code = main(["calibrate", str(root / "a"), "-q", "--table", str(tmp_path / "cli.csv")])
        out = capsys.readouterr().out
        assert code == 0 and "sitl01.tlog" in out and "again-sitl01.tlog" in out
        assert len(read_table(tmp_path / "cli.csv")) == 2


@pytest.mark.timeout(240)
def test_a_worker_killed_mid_run_loses_no_row(fleet, tmp_path):
    """SIGKILL of one of the two worker processes after the first log (it may be running a job then):
    its jobs run again elsewhere (Dask's retries), every row as the fork pool's."""
    import os
    import signal

    from distributed import Client

    root, logs, fork = fleet
    with dask_cluster(workers=2) as address:
        with Client(address) as c:
            pids = sorted(c.run(os.getpid).values())
        killed: list[int] = []

        def kill_one(res) -> None:
            if not killed:  # after the first log, while the next ones run
                os.kill(pids[0], signal.SIGKILL)
                killed.append(pids[0])

        table = tmp_path / "dask.csv"
        done = run_fleet(logs, FAST, table=str(table), scheduler_address=address, progress=kill_one)
        assert killed and [r.source for r in done.rows] == logs
        assert_same_rows(comparable(read_table(table), str(root)), comparable(fork, str(root)))


def test_an_unreachable_scheduler_is_one_line(tmp_path, monkeypatch, sitl_dir):
    monkeypatch.setattr(fleet_run, "CONNECT_TIMEOUT_S", 1.0)
    with pytest.raises(UsageError, match="cannot reach the Dask scheduler"):
        run_fleet([str(sitl_dir / "sitl01.tlog")], FAST, scheduler_address=f"tcp://127.0.0.1:{free_port()}")
    assert main(["calibrate", str(sitl_dir / "sitl01.tlog"), "--scheduler-address", "127.0.0.1:8786"]) == 2
