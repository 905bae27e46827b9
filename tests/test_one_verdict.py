"""One verdict, whatever the path (issue 35, item 3): a log's row in a many-log run is exactly
its verdict alone, the table says "not determined" where the summary does, and the many-log
exit code is the worst by the documented order."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from mavcal.autopilot.gates import SensorVerdict
from mavcal.batch import BatchRow, fleet_exit_code, format_fleet_table
from mavcal.cli import main
from mavcal.testing.numbers import assert_json_close, numbers_close

REPO = Path(__file__).resolve().parents[1]
PX4 = REPO.parent / "shared" / "data" / "px4"
LOGS = {".tlog", ".bin", ".log", ".ulg", ".csv"}


def _logs(*dirs: Path) -> list[str]:
    return [str(p) for d in dirs if d.is_dir() for p in sorted(d.iterdir())
            if p.suffix.lower() in LOGS]


@pytest.fixture(scope="module")
def fleet(real_dir, sitl_dir, tmp_path_factory):
    """One many-log run (``--jobs 2``, as a user runs it) over every log at hand."""
    logs = _logs(real_dir, sitl_dir, PX4)
    out = tmp_path_factory.mktemp("fleet") / "fleet.json"
    import contextlib
    import io

    text = io.StringIO()
    with contextlib.redirect_stdout(text):
        code = main(["calibrate", *logs, "--jobs", "2", "--json", str(out)])
    rows = json.loads(out.read_text())
    assert [r["source"] for r in rows] == logs
    return logs, rows, code, text.getvalue()


def _single(log: str, tmp_path: Path, capsys) -> tuple[int, dict, str]:
    j = tmp_path / (Path(log).name + ".json")
    code = main(["calibrate", log, "--json", str(j)])
    out = capsys.readouterr().out
    return code, json.loads(j.read_text()), out


def test_every_row_is_the_verdict_of_its_log_alone(fleet, tmp_path, capsys):
    logs, rows, _, table = fleet
    assert len(logs) >= 14  # the real logs, both SITL logs and the PX4 logs
    lines = table.splitlines()
    for log, row in zip(logs, rows):
        code, alone, summary = _single(log, tmp_path, capsys)
        assert row["exit_code"] == code == alone["exit_code"], log
        sensors = [{"sensor": s["sensor"], "accepted": s["accepted"], "reasons": list(s["reasons"])}
                   for s in row["sensors"]]
        assert_json_close(sensors, alone["sensors"])  # same sensors, same reasons, same numbers in them
        assert row["failed_gates"] == [f"{s['sensor']} {r}" for s in alone["sensors"] for r in s["reasons"]]
        name = Path(log).name
        mine = next(ln for ln in lines if f"  {name}  " in ln)
        if "error" in alone:  # refused: the same one-line error
            assert not row["ok"] and row["error"] == alone["error"], log
            assert f"ERROR {code}" in mine
            continue
        q = alone["quality"]
        assert row["ok"] and row["accepted"] == alone["accepted"], log
        assert numbers_close(row["heading_95_deg"], q["heading_95_deg"])
        assert numbers_close(row["tilt_95_deg"], q["tilt_95_deg"])
        assert (row["heading_determined"], row["tilt_determined"], row["not_determined_why"]) == (
            q["heading_determined"], q["tilt_determined"], q["not_determined_why"]), log
        assert row["warnings"] == alone["warnings"]
        assert row["model"] == alone["calibration"]["model"]
        assert row["n_intervals"] == sum(iv["used"] for iv in alone["intervals"])
        # the table's words are the summary's
        overall = summary.splitlines()[0].split(":")[0]
        assert f"  {overall}" in mine, (mine, overall)
        heading_nd = "heading error not determined" in summary or "heading and tilt errors not determined" in summary
        assert heading_nd == (not q["heading_determined"])
        assert ("not determined" in mine) == (heading_nd or not q["tilt_determined"] or bool(q["not_determined_why"]))
        i = lines.index(mine) + 1
        under = []
        while i < len(lines) and lines[i].startswith("    "):
            under.append(lines[i])
            i += 1
        want = [x for s in alone["sensors"] if not s["accepted"]
                for x in [f"    {s['sensor']}: REJECTED", *(f"        {r}" for r in s["reasons"])]]
        assert under == want, log


def test_the_fleet_exit_code_is_the_worst(fleet):
    _, rows, code, table = fleet
    worst = fleet_exit_code([BatchRow(source=r["source"], ok=r["ok"], exit_code=r["exit_code"]) for r in rows])
    assert code == worst and f"exit code {code} " in table


def _r(name: str, ok: bool, code: int) -> BatchRow:
    return BatchRow(source=name, ok=ok, exit_code=code, accepted=ok and code == 0)


@pytest.mark.parametrize("mix, worst", [
    ([(True, 0), (True, 7)], 7),
    ([(True, 0), (True, 7), (True, 4)], 4),
    ([(True, 7), (True, 4), (False, 4)], 4),  # too short to calibrate: a failure, and 4 too
    ([(True, 7), (True, 4), (False, 4), (False, 3)], 3),  # unreadable outranks too short
    ([(True, 0), (False, 70), (False, 3)], 70),
    ([(True, 0), (True, 0)], 0),
    ([], 0),
])
def test_the_order_of_outcomes(mix, worst):
    """A failure outranks a rejection outranks a partial acceptance outranks full acceptance
    (docs/fleet.md, docs/results.md): never the largest number (7 > 4)."""
    rows = [_r(f"l{i}.tlog", ok, c) for i, (ok, c) in enumerate(mix)]
    assert fleet_exit_code(rows) == worst
    if rows:
        assert f"exit code {worst} " in format_fleet_table(rows)


def test_a_mix_through_the_command_line(sitl_dir, real_dir, tmp_path, capsys):
    """sitl01 accepted (0), a real log partly accepted (7), a corrupt file (3): exit 3; without
    the corrupt file 7, not 0 nor the largest."""
    bad = tmp_path / "bad.tlog"
    bad.write_bytes(b"\x00" * 2000)
    ok, partial = str(sitl_dir / "sitl01.tlog"), str(real_dir / "00000124.BIN")
    assert main(["calibrate", ok, partial, "--jobs", "2"]) == 7
    table = capsys.readouterr().out
    assert "PARTLY ACCEPTED (1 of 3)" in table and "1 accepted, 1 partly accepted, 0 rejected" in table
    assert main(["calibrate", ok, partial, str(bad), "--jobs", "2"]) == 3


def test_a_rows_verdicts_print_as_the_summary_does():
    row = BatchRow(source="a.tlog", ok=True, exit_code=7, accepted=False, heading_95_deg=170.7, tilt_95_deg=0.088,
                   heading_determined=False, tilt_determined=True, compass_determined=False, accel_determined=True,
                   not_determined_why="the poses do not identify compass0: only 6 distinct field directions",
                   compass_ofs_old=(1.0, 2.0, 3.0), compass_ofs_new=(300.0, 2.0, 3.0), compass_ofs_change_mgauss=299.0,
                   sensors=(SensorVerdict("accel0", True), SensorVerdict("compass0", False, ("field directions: x",))))
    text = format_fleet_table([row])
    line = next(ln for ln in text.splitlines() if "a.tlog" in ln)
    assert "PARTLY ACCEPTED (1 of 2)" in line and "170.7" not in line and "299" not in line
    assert line.count("not determined") == 3  # |dOFS|, the offsets, HDG95
    assert "    compass0: REJECTED\n        field directions: x" in text and "accel0" not in text
    assert "DRIFT" not in line and "drift?" not in line  # an undetermined change is no drift
