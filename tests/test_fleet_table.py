"""The results table (issue 40, item 2): one row per log written as each finishes; a run killed
with SIGKILL at about half and run again with the same table equals an uninterrupted run (no
row lost, none twice); pandas, polars and duckdb read it as is."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections import Counter

import pytest

from mavcal.errors import UsageError
from mavcal.fleet.run import FleetJob, calibrate_entry, run_fleet
from mavcal.fleet.table import COLUMNS, ResultsTable, read_table
from mavcal.pipeline import Options
from mavcal.testing.fleet import assert_same_rows, comparable

FAST = Options(uncertainty_draws=50)
N_COPIES = 3  # of each SITL log, each with other trailing bytes: 6 calibrations, a duplicate and a corrupt log

_KILLED_RUN = """
import sys
from mavcal.fleet.run import run_fleet
from mavcal.pipeline import Options
run_fleet(sys.argv[2:], Options(uncertainty_draws=50), jobs=1, table=sys.argv[1])
"""


@pytest.fixture(scope="module")
def logs(tmp_path_factory, sitl_dir):
    root = tmp_path_factory.mktemp("fleetlogs")
    out = []
    for name in ("sitl01.tlog", "sitl02.tlog"):
        data = (sitl_dir / name).read_bytes()
        for k in range(N_COPIES):
            p = root / f"{k}-{name}"
            p.write_bytes(data + b"\x00" * k)
            out.append(str(p))
    dup = root / "dup-of-0-sitl02.tlog"  # the content of another log: its own row all the same
    dup.write_bytes((sitl_dir / "sitl02.tlog").read_bytes())
    out.append(str(dup))
    bad = root / "corrupt.tlog"
    bad.write_bytes(bytes((i * 37 + 11) % 251 for i in range(3000)).replace(b"\xfd", b"\x00").replace(b"\xfe", b"\x00"))
    return sorted(out + [str(bad)])


@pytest.fixture(scope="module")
def whole(logs, tmp_path_factory):
    """The uninterrupted run's table."""
    table = tmp_path_factory.mktemp("whole") / "whole.csv"
    done = run_fleet(logs, FAST, jobs=2, table=str(table))
    assert len(done.rows) == len(logs) and not done.skipped
    return read_table(table)


def _rows_in(path) -> int:
    try:
        with open(path, "rb") as f:
            return max(0, f.read().count(b"\n") - 1)
    except FileNotFoundError:
        return 0


@pytest.mark.parametrize("kind", ["csv", "parquet"])
def test_killed_at_half_and_resumed_equals_an_uninterrupted_run(kind, logs, whole, tmp_path):
    table = tmp_path / f"results.{kind}"
    journal = tmp_path / f"results.{kind}.journal.csv" if kind == "parquet" else table
    proc = subprocess.Popen([sys.executable, "-c", _KILLED_RUN, str(table), *logs], start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    half = len(logs) // 2
    end = time.monotonic() + 120
    while _rows_in(journal) < half and proc.poll() is None and time.monotonic() < end:
        time.sleep(0.02)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL, proc.stderr.read().decode() if proc.stderr else ""
    kept = read_table(table)
    assert half <= len(kept) < len(logs)  # killed at about half: those rows survived it
    done = run_fleet(logs, FAST, jobs=2, table=str(table))
    # the rest calibrated, or (the duplicate, when its twin was done before the kill) its twin's row copied
    assert len(done.skipped) == len(kept) and len(done.rows) + len(done.copied) == len(logs) - len(kept)
    rows = read_table(table)
    counts = Counter(r["source"] for r in rows)
    assert sorted(counts) == logs and set(counts.values()) == {1}  # none lost, none twice
    assert_same_rows(comparable(rows), comparable(whole))
    if kind == "parquet":
        assert not journal.exists()  # finished: the Parquet file holds every row


def test_run_again_skips_what_the_table_has_and_redoes_a_changed_log(logs, whole, tmp_path):
    table = tmp_path / "t.csv"
    first = run_fleet(logs[:3], FAST, jobs=1, table=str(table))
    assert len(first.rows) == 3
    again = run_fleet(logs[:3], FAST, jobs=1, table=str(table))
    assert again.rows == [] and sorted(again.skipped) == sorted(logs[:3])
    changed = tmp_path / "changed.tlog"
    changed.write_bytes(open(logs[1], "rb").read() + b"\x01")
    third = run_fleet([*logs[:3], str(changed)], FAST, jobs=1, table=str(table))
    assert [r.source for r in third.rows] == [str(changed)]
    assert len(read_table(table)) == 4
    # a copy under another name, in a later run: its row is the original's under its name, not calibrated again
    renamed = tmp_path / "renamed.tlog"
    renamed.write_bytes(open(logs[0], "rb").read())
    fourth = run_fleet([*logs[:3], str(renamed)], FAST, jobs=1, table=str(table))
    assert fourth.rows == [] and fourth.copied == [str(renamed)] and sorted(fourth.skipped) == sorted(logs[:3])
    rows = {r["source"]: r for r in read_table(table)}
    assert len(rows) == 5
    def but_name(r: dict) -> dict:  # a copy of the row (no number computed again)
        return {k: v for k, v in r.items() if k not in ("source", "finished_utc")}

    assert but_name(rows[str(renamed)]) == but_name(rows[logs[0]])
    # another mavcal version: the same content is calibrated again
    job = FleetJob(FAST, version="0.0.0-other", done=frozenset(f"{r['content_sha256']}:{r['mavcal_version']}"
                                                                 for r in read_table(table)))
    assert calibrate_entry(job, logs[1]).row is not None
    assert calibrate_entry(FleetJob(FAST, version=whole[0]["mavcal_version"], done=job.done), logs[1]).row is None


def test_a_torn_last_row_is_cut_off(whole, tmp_path):
    table = tmp_path / "t.csv"
    w = ResultsTable(table)
    assert w.open() == []
    for r in whole[:2]:
        w.append(r)
    w.close()
    with open(table, "ab") as f:
        f.write(b"/a/half/written,row")  # what a kill mid-write could leave
    w = ResultsTable(table)
    assert len(w.open()) == 2
    w.close()
    assert open(table, "rb").read().endswith(b"\n") and len(read_table(table)) == 2


def test_not_a_table_is_refused(tmp_path):
    bad = tmp_path / "other.csv"
    bad.write_text("a,b\n1,2\n")
    with pytest.raises(UsageError, match="not a table of this mavcal"):
        ResultsTable(bad).open()
    with pytest.raises(UsageError, match=r"\.csv or a \.parquet"):
        ResultsTable(tmp_path / "t.xlsx")


def test_pandas_polars_and_duckdb_read_the_tables_as_is(whole, tmp_path):
    pd = pytest.importorskip("pandas")
    pytest.importorskip("pyarrow")
    for kind in ("csv", "parquet"):
        t = ResultsTable(tmp_path / f"r.{kind}")
        t.open()
        for r in whole:
            t.append(r)
        t.close()
    csv_df = pd.read_csv(tmp_path / "r.csv")
    pq_df = pd.read_parquet(tmp_path / "r.parquet")
    assert list(csv_df.columns) == list(COLUMNS) == list(pq_df.columns)
    assert len(csv_df) == len(pq_df) == len(whole)
    assert sorted(pq_df["source"]) == sorted(r["source"] for r in whole)
    assert pq_df["compass_ofs_change_mgauss"].dropna().gt(100).all()  # typed: numbers, not text
    assert csv_df["ok"].dtype == bool and pq_df["ok"].dtype == bool
    try:
        import polars as pl
    except ImportError:
        pl = None
    if pl is not None:
        for df in (pl.read_csv(tmp_path / "r.csv", infer_schema_length=None), pl.read_parquet(tmp_path / "r.parquet")):
            assert df.columns == list(COLUMNS) and df.height == len(whole)
    try:
        import duckdb
    except ImportError:
        duckdb = None
    if duckdb is not None:
        for f in ("r.csv", "r.parquet"):
            [(n,)] = duckdb.sql(f"SELECT count(*) FROM '{tmp_path / f}' WHERE ok").fetchall()
            assert n == sum(1 for r in whole if r["ok"])


def test_parquet_is_rewritten_and_read_a_batch_at_a_time(whole, tmp_path, monkeypatch):
    """The snapshot and the reading go a batch of rows at a time (here 2): the same rows, in order;
    a table of another layout (a flight table) is refused, not appended to."""
    pytest.importorskip("pyarrow")
    from mavcal.fleet import table as fleet_table
    from mavcal.fleet.flight import FLIGHT

    monkeypatch.setattr(fleet_table, "_BATCH_ROWS", 2)
    t = ResultsTable(tmp_path / "r.parquet")
    t.open()
    for r in whole:
        t.append(r)
    t.close()
    got = read_table(tmp_path / "r.parquet")
    assert [r["source"] for r in got] == [r["source"] for r in whole] and len(whole) > 2
    assert got[0]["compass_ofs_new_x_mgauss"] == whole[0]["compass_ofs_new_x_mgauss"]
    seen: list[str] = []
    again = ResultsTable(tmp_path / "r.parquet")
    assert again.open(each=lambda r: seen.append(r["source"])) == [] and seen == [r["source"] for r in whole]
    again.close()
    with pytest.raises(UsageError, match="not a table of this mavcal"):
        ResultsTable(tmp_path / "r.parquet", layout=FLIGHT).open()
