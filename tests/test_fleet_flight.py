"""`mavcal flight` over a fleet (issue 40, "every many-log command"): synthetic DataFlash flights
(tests/test_flight_real.py's writer, no SITL), each row what the flight check of that log alone
says, the table resumed, and a vehicle whose compass interference grew between flights flagged."""
from __future__ import annotations

import argparse
import math

import pytest

from mavcal.fleet.flight import (
    FLIGHT,
    FLIGHT_COLUMNS,
    INTERFERENCE_GROWTH_PCT,
    FlightOptions,
    interference_html,
    interference_over_time,
)
from mavcal.fleet.flight_cli import is_many, run_many
from mavcal.fleet.run import run_fleet
from mavcal.fleet.table import read_table
from mavcal.flight.stage import analyse
from mavcal.sources.flight_series import read_flight_series
from mavcal.testing.flight_synth import SynthCompass, synth_flight, write_flight_bin

# vehicle A: two compasses; its interference (mGauss per amp) grows at the third flight (a new
# cable by the GPS mast, say); vehicle B: other device ids, steady
A = {"COMPASS_DEV_ID": 97539.0, "COMPASS_DEV_ID2": 131874.0}
B = {"COMPASS_DEV_ID": 76291.0, "COMPASS_DEV_ID2": 131874.0}
FLIGHTS = (("a/2024-05-01.bin", A, (1.0, -1.0, 0.5), 1), ("a/2024-05-08.bin", A, (1.2, -0.8, 0.5), 2),
           ("a/2024-05-15.bin", A, (4.5, -4.0, 2.0), 3), ("b/2024-05-02.bin", B, (0.8, 0.6, 0.0), 4),
           ("b/2024-05-09.bin", B, (0.9, 0.5, 0.1), 5))


@pytest.fixture(scope="module")
def flights(tmp_path_factory):
    root = tmp_path_factory.mktemp("flights")
    for name, params, mot, seed in FLIGHTS:
        (root / name).parent.mkdir(exist_ok=True)
        s = synth_flight([SynthCompass(interference=mot), SynthCompass(interference=mot)], seed=seed,
                         duration_s=90.0, params=params)
        write_flight_bin(root / name, s)
    (root / "b" / "broken.bin").write_bytes(b"\xa3\x95" + bytes(range(200)))
    return root, sorted(str(p) for p in root.rglob("*.bin"))


def _pct(row: dict, k: int) -> float:
    return row[f"compass{k}_interference_pct"]


def test_fleet_rows_are_each_flight_alone_and_the_growth_is_flagged(flights, tmp_path):
    root, logs = flights
    table = tmp_path / "flights.csv"
    done = run_fleet(logs, FlightOptions(), jobs=2, table=str(table), kind="flight")
    rows = {r["source"]: r for r in read_table(table, FLIGHT)}
    assert sorted(rows) == logs and [r.source for r in done.rows] == logs
    for src in logs:
        row = rows[src]
        if src.endswith("broken.bin"):
            assert not row["ok"] and row["exit_code"] == 3 and row["result"] == "ERROR 3" and src in row["error"]
            continue
        alone = analyse(read_flight_series(src))  # `mavcal flight LOG` of it alone
        assert row["ok"] and row["n_compasses"] == len(alone.compasses) == 2
        for c in alone.compasses:
            k, v, f = c.instance, c.verdict, c.fit
            assert math.isclose(_pct(row, k), v.interference_pct, rel_tol=1e-9)
            assert row[f"compass{k}_wrong"] == v.wrong and row[f"compass{k}_accepted"] == v.accepted
            assert row[f"compass{k}_level"] == v.level
            assert [row[f"compass{k}_mot_{a}"] for a in "xyz"] == pytest.approx(list(f.mot_per_unit), rel=1e-9)
            assert [row[f"compass{k}_mot_bound95_{a}"] for a in "xyz"] == pytest.approx(
                list(f.mot_bound95_per_unit), rel=1e-9)
        assert row["compass0_dev_id"] == int((A if "/a/" in src else B)["COMPASS_DEV_ID"])
        assert row["compass2_result"] is None  # no third compass
    assert done.exit_code == 3  # the worst log's: the unreadable one
    # interference over time: A grew (third flight), B steady
    vs = {v.vehicle.rsplit(" ", 1)[-1]: v for v in interference_over_time(read_table(table, FLIGHT))}
    va, vb = vs["97539/131874"], vs["76291/131874"]
    assert va.flagged and not vb.flagged and len(va.logs) == 3
    a2, a3 = rows[str(root / "a/2024-05-08.bin")], rows[str(root / "a/2024-05-15.bin")]
    assert _pct(a3, 0) - _pct(a2, 0) > INTERFERENCE_GROWTH_PCT
    assert all(y - x <= INTERFERENCE_GROWTH_PCT for *_, x, y in vb.steps)
    page = interference_html(done.drift)
    assert page.count("<svg") == 1 and "GREW" in page and "src=" not in page and "<script" not in page
    # run again with the same table: every log skipped, no row twice
    again = run_fleet(logs, FlightOptions(), jobs=2, table=str(table), kind="flight")
    assert again.n_calibrated == 0 and again.n_skipped == len(logs)
    assert len(read_table(table, FLIGHT)) == len(logs)


def _args(*argv: str) -> argparse.Namespace:
    """``mavcal flight``'s own parser (its LOG takes several, the many-log options added)."""
    from mavcal.commands.flight import add_arguments

    p = argparse.ArgumentParser()
    p.add_argument("-q", "--quiet", action="store_true")
    add_arguments(p)
    return p.parse_args(argv)


def test_the_many_log_command_over_a_directory(flights, tmp_path, capsys):
    """What `mavcal flight DIR --table T --drift-html H` runs (the command's hook calls run_many)."""
    root, logs = flights
    table, page = tmp_path / "t.parquet", tmp_path / "i.html"
    args = _args(str(root / "a"), "--table", str(table), "--drift-html", str(page), "-q")
    assert is_many(args) and not is_many(_args(logs[0]))
    assert run_many(args) == 0  # vehicle A's three flights: every compass fine
    out = capsys.readouterr().out
    assert "2024-05-15.bin" in out and "GREW" in out and "interference over time written to" in out
    got = read_table(table, FLIGHT)
    assert len(got) == 3 and tuple(got[0]) == FLIGHT_COLUMNS
    assert "<svg" in page.read_text()
    with pytest.raises(Exception, match="--param-out"):
        run_many(_args(str(root), "--param-out", str(tmp_path / "x.param")))


def test_the_command_line_runs_a_fleet_and_keeps_one_vehicle_options_for_one_log(flights, tmp_path):
    """`mavcal flight DIR --table T --jobs 2` through the command itself; --write / --html with a
    fleet: one line, exit 2, nothing run."""
    import subprocess
    import sys

    root, _ = flights
    table = tmp_path / "t.csv"
    out = subprocess.run([sys.executable, "-m", "mavcal", "flight", str(root / "a"), "--table", str(table),
                          "--jobs", "2", "-q"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout + out.stderr
    assert len(read_table(table, FLIGHT)) == 3 and "GREW" in out.stdout
    for opt in (["--write", "--connect", "udp:127.0.0.1:9"], ["--html", str(tmp_path / "h.html")]):
        bad = subprocess.run([sys.executable, "-m", "mavcal", "flight", str(root / "a"), *opt],
                             capture_output=True, text=True, timeout=60)
        assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1, bad.stderr
        assert "single LOG" in bad.stderr
