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


@pytest.fixture(scope="module")
def flights(tmp_path_factory):
    """Two synthetic DataFlash flights (tests/test_flight_real.py's writer) and a broken one."""
    from mavcal.testing.flight_synth import SynthCompass, synth_flight, write_flight_bin

    root = tmp_path_factory.mktemp("flights")
    for k, mot in enumerate(((1.0, -1.0, 0.5), (4.0, -3.0, 2.0))):
        write_flight_bin(root / f"f{k}.bin", synth_flight([SynthCompass(interference=mot)] * 2, seed=k,
                                                          duration_s=90.0))
    (root / "broken.bin").write_bytes(b"\xa3\x95" + bytes(range(200)))
    return root, sorted(str(p) for p in root.iterdir())


@pytest.mark.timeout(300)
def test_separate_scheduler_and_two_workers_give_the_fork_pool_rows(fleet, flights, tmp_path, monkeypatch, capsys):
    from distributed import Client

    from mavcal.fleet.flight import FLIGHT, FLIGHT_COLUMNS, FlightOptions
    from mavcal.testing.fleet import heap_probe

    root, logs, fork = fleet
    monkeypatch.setattr(fleet_run, "MIN_WINDOW", 1)  # two jobs on the cluster at a time: the rest wait here
    monkeypatch.setattr(fleet_run, "WINDOW_PER_WORKER", 1)
    with dask_cluster(workers=2) as address:
        table = tmp_path / "dask.csv"
        done = run_fleet(logs, FAST, table=str(table), scheduler_address=address)
        assert [r.source for r in done.rows] == logs
        assert_same_rows(comparable(read_table(table), str(root)), comparable(fork, str(root)))
        # Dask's nanny sets MALLOC_TRIM_THRESHOLD_ in its workers; each job undoes its cost (roomy_heap)
        with Client(address) as c:
            assert set(c.run(heap_probe).values()) == {("65536", True)}
        # `mavcal flight` over many logs: the same rows on the cluster as in the fork pool here
        froot, flogs = flights
        ft = {}
        for how, kw in (("fork", {"jobs": 2}), ("dask", {"scheduler_address": address})):
            ft[how] = tmp_path / f"flight-{how}.csv"
            run_fleet(flogs, FlightOptions(), table=str(ft[how]), kind="flight", **kw)
        fd, ff = (comparable(read_table(ft[h], FLIGHT), str(froot), FLIGHT_COLUMNS) for h in ("dask", "fork"))
        assert len(fd) == 3 and sum(1 for r in fd if r[FLIGHT_COLUMNS.index("ok") - 1]) == 2
        assert_same_rows(fd, ff)
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
