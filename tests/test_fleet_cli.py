"""`mavcal calibrate` over a fleet (issue 40, items 4 and 5): the progress line on a terminal
(quiet with -q), the drift over time per vehicle, and the CLI's table handling."""
from __future__ import annotations

import io
import json
import shutil

import pytest

from mavcal.batch import BatchRow
from mavcal.cli import main
from mavcal.fleet.drift import drift_over_time, drift_text
from mavcal.fleet.progress import ProgressLine, format_eta, progress_line
from mavcal.fleet.run import FleetResult
from mavcal.fleet.table import read_table


class FakeTty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_line_counts_rate_eta_and_failures():
    now = [100.0]
    out = FakeTty()
    p = ProgressLine(out, 4, every_s=0.0, clock=lambda: now[0])
    now[0] += 10.0
    p(FleetResult("a", "h", 1, BatchRow(source="a", ok=True)))
    now[0] += 10.0
    p(FleetResult("b", None, None, BatchRow(source="b", ok=False, error="x", exit_code=3)))
    p(FleetResult("c", "h2", 1, None))  # already in the table
    assert p.text() == "fleet: 3/4 logs (1 failed, 1 already in the table), 0.10 logs/s, ETA 10 s"
    p.close()
    assert out.getvalue().count("\r") == 3 and out.getvalue().endswith("\n")
    assert format_eta(185) == "3 min 05 s" and format_eta(7620) == "2 h 07 min"
    assert progress_line(io.StringIO(), 3) is None  # not a terminal
    assert progress_line(FakeTty(), 3, quiet=True) is None
    assert isinstance(progress_line(FakeTty(), 3), ProgressLine)


@pytest.fixture
def fleet_dir(tmp_path, sitl_dir):
    d = tmp_path / "flights"
    d.mkdir()
    for n in ("sitl01.tlog", "sitl02.tlog"):
        shutil.copy(sitl_dir / n, d / n)
    return d


def test_cli_progress_table_json_and_a_resumed_run(fleet_dir, tmp_path, monkeypatch, capsys):
    tty = FakeTty()
    monkeypatch.setattr("sys.stderr", tty)
    table = fleet_dir / "results.csv"  # inside the directory: never taken for a log
    js = tmp_path / "rows.json"
    assert main(["calibrate", str(fleet_dir), "--table", str(table), "--json", str(js), "--jobs", "2"]) == 0
    assert "fleet: 2/2 logs (0 failed), " in tty.getvalue()
    out = capsys.readouterr().out
    assert "sitl01.tlog" in out and "sitl02.tlog" in out and "drift over time" in out
    assert "sys 1, compass0(97539), accel0(2753028): 2 logs, MOVED" in out
    assert [r["source"] for r in json.loads(js.read_text())] == [str(fleet_dir / "sitl01.tlog"),
                                                                 str(fleet_dir / "sitl02.tlog")]
    assert len(read_table(table)) == 2
    tty2 = FakeTty()
    monkeypatch.setattr("sys.stderr", tty2)
    assert main(["calibrate", str(fleet_dir), "--table", str(table), "-q"]) == 0
    assert tty2.getvalue() == ""  # -q: no progress line
    out = capsys.readouterr().out
    assert "2 log(s) already in" in out and len(read_table(table)) == 2


def test_cli_refuses_a_bad_table_and_single_log_options(fleet_dir, capsys):
    assert main(["calibrate", str(fleet_dir), "--table", str(fleet_dir / "t.xlsx")]) == 2
    assert main(["calibrate", str(fleet_dir), "--param-out", "x.param"]) == 2
    assert main(["calibrate", str(fleet_dir / "none-*.tlog")]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and ".csv or a .parquet" in err[0] and "no file matches" in err[2]


def _row(source, t, ofs, sysid=1, accepted=True):
    r = {"source": source, "ok": True, "accepted": accepted, "sysid": sysid, "firmware": None,
         "compass_instance": 0, "compass_dev_id": 7, "accel_instance": 0, "accel_id": 9, "log_start_utc": t}
    for name, unit, v in (("compass_ofs", "_mgauss", ofs), ("accel_ofs", "_mps2", (0.0, 0.0, 0.0)),
                          ("accel_scale", "", (1.0, 1.0, 1.0))):
        for a, x in zip("xyz", v):
            r[f"{name}_new_{a}{unit}"] = x
    return r


def test_a_large_fleet_s_rows_are_not_kept_the_table_has_them(fleet_dir, tmp_path, monkeypatch, capsys):
    """Beyond PRINTED_MAX logs with --table, the parent keeps no row: one line names the table; the
    drift summary and the exit code come from what it kept as the rows went by."""
    from mavcal.commands import calibrate as cmd

    monkeypatch.setattr(cmd, "PRINTED_MAX", 1)
    table = tmp_path / "t.csv"
    assert main(["calibrate", str(fleet_dir), "-q", "--table", str(table)]) == 0
    out = capsys.readouterr().out
    assert f"2 logs calibrated in this run (0 failed): their rows are in {table}" in out
    assert "VEHICLE" not in out and "2 logs, MOVED" in out and len(read_table(table)) == 2


def test_drift_over_time_orders_by_time_and_flags_a_moved_vehicle():
    rows = [_row("v1-c", "2024-03-01T00:00:00Z", (40.0, 0.0, 0.0)),
            _row("v1-a", "2024-01-01T00:00:00Z", (0.0, 0.0, 0.0)),
            _row("v1-b", "2024-02-01T00:00:00Z", (10.0, 0.0, 0.0)),
            _row("v2-a", None, (5.0, 5.0, 5.0), sysid=2), _row("v2-b", None, (6.0, 5.0, 5.0), sysid=2),
            _row("v2-x", None, (900.0, 5.0, 5.0), sysid=2, accepted=False),  # rejected: not evidence
            _row("v3", None, (0.0, 0.0, 0.0), sysid=3)]  # one log: nothing to compare
    v1, v2 = drift_over_time(rows)
    assert v1.logs == ("v1-a", "v1-b", "v1-c") and v1.flagged
    assert [s[2] for s in v1.steps] == pytest.approx([10.0, 30.0])
    assert v2.logs == ("v2-a", "v2-b") and not v2.flagged
    text = drift_text(rows)
    assert "sys 1, compass0(7), accel0(9): 3 logs, MOVED; largest step v1-b -> v1-c: compass 30.0 mG" in text
    assert "sys 2, compass0(7), accel0(9): 2 logs, steady" in text and "sys 3" not in text
    assert drift_text(rows[-1:]) == ""


def test_drift_page_is_self_contained_with_a_plot_per_moved_vehicle(fleet_dir, tmp_path, capsys):
    page = tmp_path / "drift.html"
    assert main(["calibrate", str(fleet_dir), "-q", "--drift-html", str(page)]) == 0
    assert f"drift over time written to {page}" in capsys.readouterr().out
    html = page.read_text()
    assert html.startswith("<!DOCTYPE html>") and "MOVED" in html
    assert html.count("<svg") == 2  # one vehicle moved: its compass and accelerometer offsets
    assert "sitl01.tlog" in html and "sitl02.tlog" in html
    for external in ("src=", "href=", "<script", "@import", "url("):  # nothing fetched from elsewhere
        assert external not in html
    # the same page from rows alone, with a steady vehicle: listed, no plot
    from mavcal.fleet.drift import drift_html

    steady = drift_html([_row("a", None, (1.0, 0.0, 0.0)), _row("b", None, (2.0, 0.0, 0.0))])
    assert "<b>steady</b>" in steady and "<svg" not in steady
