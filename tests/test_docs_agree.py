"""Docs and program agree (issue 35, item 7): a test per documented flag behaviour."""
from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from test_docs import PAGES, samples

from mavcal.cli import main
from mavcal.pipeline import Options, calibrate_source
from mavcal.report.text import next_step, summary_text

REPO = Path(__file__).resolve().parents[1]
SITL02 = REPO / "sitl_logs" / "sitl02.tlog"


def _sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def sitl02_run():
    return calibrate_source(str(SITL02), Options())  # the command line's options: its printed numbers


# --------------------------------------------------------------------------- -q

def _mavcal(*argv: str) -> subprocess.CompletedProcess:
    """The command as a person runs it (its own process: logging configured by it alone)."""
    return subprocess.run([sys.executable, "-m", "mavcal", *argv], capture_output=True, text=True, timeout=300)


def test_quiet_leaves_only_errors_on_stderr_and_the_results_on_stdout(real_dir):
    """docs/commands.md: ``-q`` shows no warnings, notes or progress, only errors; the results
    still print. A log that warns (a compass calibration changed during it) and is rejected."""
    log = str(real_dir / "2024-04-05 09-36-27.tlog")
    loud = _mavcal("calibrate", log)
    assert loud.returncode == 4 and "mavcal: WARNING:" in loud.stderr  # the case has something to hide
    quiet = _mavcal("-q", "calibrate", log)
    assert quiet.returncode == 4
    assert quiet.stdout == loud.stdout and quiet.stdout.startswith("REJECTED:")
    assert quiet.stderr and all(ln.startswith("mavcal: error: ") for ln in quiet.stderr.splitlines()), quiet.stderr
    after = _mavcal("calibrate", log, "-q")  # after the subcommand: the same
    assert (after.returncode, after.stderr) == (4, quiet.stderr)


def test_quiet_hides_the_jobs_cap_note(capsys, tmp_path):
    bad = tmp_path / "x.tlog"
    bad.write_bytes(b"\x00" * 100)
    main(["calibrate", str(bad), str(bad), "--jobs", "100000"])
    assert "--jobs 100000 is more than" in capsys.readouterr().err
    main(["calibrate", str(bad), str(bad), "--jobs", "100000", "-q"])
    assert "--jobs" not in capsys.readouterr().err


def test_the_help_says_what_quiet_does(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    assert "only errors on stderr" in " ".join(out.split())
    assert "`-q` (no warnings, notes or progress" in " ".join(PAGES["commands.md"].split())


# --------------------------------------------------------------------------- the .param file

def test_the_param_file_is_what_results_md_says(tmp_path, capsys):
    out = tmp_path / "new.param"
    assert main(["calibrate", str(SITL02), "--param-out", str(out)]) == 0
    capsys.readouterr()
    lines = out.read_text().splitlines()
    values = [ln for ln in lines if not ln.startswith("#")]
    assert values and all(re.fullmatch(r"[A-Z][A-Z0-9_]*,-?[0-9.]+(e[-+]?[0-9]+)?", ln) for ln in values), values
    assert [ln.split(",")[0] for ln in values] == sorted(ln.split(",")[0] for ln in values)
    page = " ".join(PAGES["results.md"].split())
    assert "`NAME,VALUE` lines sorted by name" in page and "`NAME VALUE`" not in page.replace("reads `NAME VALUE`", "")
    example = re.search(r"\(e\.g\. `([A-Z0-9_]+),([0-9.]+)`\)", page)
    assert example is not None
    name, value = example.groups()
    got = dict(ln.split(",") for ln in values)
    assert got[name] == value  # the printed value, as the program writes it


# --------------------------------------------------------------------------- the printed bound

def test_every_sample_line_is_a_golden_line_as_printed():
    """A sample shows what the program prints: each line of it (but "...") is a line of its golden
    file, character for character (the golden files are the program's output at the numbers'
    tolerance: tests/test_cli_golden.py); 0.224 where the program prints 0.223 is not."""
    for page, path, body in samples():
        golden = (REPO / path).read_text().splitlines()
        lines = [ln for ln in body.splitlines() if ln != "..." and not ln.startswith("$ ")]
        k = 0
        for line in lines:
            assert line in golden[k:], f"docs/{page}: {line!r} is not in {path} (in order) as printed"
            k = golden.index(line, k) + 1


def test_the_quick_starts_bound_is_the_programs(sitl02_run):
    printed = next(ln for ln in summary_text(sitl02_run).splitlines() if ln.startswith("heading error"))
    shown = next(ln for ln in PAGES["quickstart.md"].splitlines() if ln.startswith("heading error"))
    from mavcal.testing.numbers import text_differences

    assert not text_differences(shown, printed), (shown, printed)


# --------------------------------------------------------------------------- mavcal stop

def test_mavcal_stop_is_shown_as_mavproxys_command_not_a_shells(capsys):
    with pytest.raises(SystemExit) as e:
        main(["stop"])
    assert e.value.code == 2 and "invalid choice: 'stop'" in capsys.readouterr().err
    for page, text in PAGES.items():
        flat = " ".join(text.split())
        for m in re.finditer(r"`mavcal stop`", flat):
            around = flat[max(0, m.start() - 200):m.end() + 200]
            assert page == "mavproxy.md" or "MAVProxy" in around, (page, around)


# --------------------------------------------------------------------------- the next step

def test_the_next_step_after_a_log_names_connect_and_after_a_live_link_not(sitl02_run, capsys):
    assert sitl02_run.exit_code == 0
    after_log = next_step(sitl02_run)
    assert "--write --connect DEVICE" in after_log
    live = dataclasses.replace(sitl02_run, log=dataclasses.replace(sitl02_run.log, kind="live"))
    assert "(--write, or load the .param file)" in next_step(live)
    # what it says works: --write of a log without --connect is refused
    assert main(["calibrate", str(SITL02), "--write"]) == 2
    assert "--write needs --connect DEVICE when SOURCE is a log" in capsys.readouterr().err


# --------------------------------------------------------------------------- flags and the log name

def test_json_before_the_log_never_takes_the_log(tmp_path, capsys):
    """``calibrate --json LOG`` reads LOG and writes the JSON on stdout, as ``segments --json LOG``
    does; a log given to --json beside a SOURCE is refused, and never written over."""
    log, other = tmp_path / "sitl02.tlog", tmp_path / "other.tlog"
    shutil.copyfile(SITL02, log)
    shutil.copyfile(SITL02, other)
    before = _sha(log)
    assert main(["calibrate", "--json", str(log)]) == 0
    cap = capsys.readouterr()
    assert json.loads(cap.out)["source"] == str(log) and cap.err.startswith("ACCEPTED:")
    for cmd in (["calibrate", "--json", str(other), str(log)], ["segments", "--json", str(other), str(log)]):
        assert main(cmd) == 2
        err = capsys.readouterr().err
        assert f"--json {other}: that is a log (an input), not the JSON file to write" in err, err
    assert _sha(log) == _sha(other) == before


@pytest.mark.parametrize("order", ["after", "before"])
def test_json_with_a_file_name_before_or_after_the_log(tmp_path, capsys, order):
    out = tmp_path / "r.json"
    argv = ["calibrate", str(SITL02), "--json", str(out)] if order == "after" else \
        ["calibrate", "--json", str(out), str(SITL02)]
    assert main(argv) == 0
    assert json.loads(out.read_text())["exit_code"] == 0
    assert f"JSON report written to {out}" in capsys.readouterr().out


def test_json_dash_before_the_log_writes_stdout(capsys):
    assert main(["calibrate", "--json", "-", str(SITL02)]) == 0
    cap = capsys.readouterr()
    assert json.loads(cap.out)["exit_code"] == 0 and cap.err.startswith("ACCEPTED:")


def test_json_dash_of_many_logs_is_the_json_alone(tmp_path, capsys):
    """docs/commands.md: ``--json -`` writes the JSON alone to stdout, the text to stderr; many logs too."""
    bad = tmp_path / "bad.tlog"
    bad.write_bytes(b"\x00" * 100)
    assert main(["calibrate", str(SITL02), str(bad), "--json", "-"]) == 3
    cap = capsys.readouterr()
    rows = json.loads(cap.out)
    assert [r["exit_code"] for r in rows] == [0, 3] and "VEHICLE" in cap.err and "2 logs:" in cap.err


@pytest.mark.parametrize("cmd", [["calibrate", "x.tlog", "--bogus"], ["segments", "x.tlog", "--bogus"],
                                 ["apply", "x.param", "--connect", "udp:127.0.0.1:1", "--bogus"]])
def test_a_wrong_flag_shows_its_subcommands_usage(capsys, cmd):
    with pytest.raises(SystemExit) as e:
        main(cmd)
    err = capsys.readouterr().err
    assert e.value.code == 2
    assert f"usage: mavcal {cmd[0]}" in err and "unrecognized arguments: --bogus" in err


# --------------------------------------------------------------------------- an absent IMU

def test_an_absent_imu_streamed_as_zeros_is_no_warning(sitl02_run, caplog):
    """ArduPilot SITL streams SCALED_IMU3 for its third compass with zero accel and gyro (there is
    no IMU 3): that is said at INFO, not as a warning of every run."""
    assert sitl02_run.raw.accel_instances() == [0, 1] and 2 in sitl02_run.raw.mag_instances()
    assert not any("all zero" in w for w in sitl02_run.warnings)
    assert "all zero" not in summary_text(sitl02_run)
    from mavcal.sources.reader import read_log

    with caplog.at_level(logging.INFO, logger="mavcal.sources.assemble"):
        read_log(str(SITL02))
    assert any("SCALED_IMU3: accel and gyro are all zero (no IMU 3)" in r.getMessage() and r.levelno == logging.INFO
               for r in caplog.records)
