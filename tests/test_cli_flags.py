"""Issue 24 items 4 and 5: options checked before any work, one ``--json`` convention, global
options after the subcommand, consistent numbering and help, and no noise."""
import argparse
import json
import re

import pytest

import mavcal.sources.reader as reader
from mavcal.cli import build_parser, main

SITL02 = "sitl02.tlog"


@pytest.fixture
def no_reading(monkeypatch):
    """Any attempt to read a log fails the test: the refusals must come first."""
    def boom(*a, **k):
        raise AssertionError("the log was read before the options were checked")
    monkeypatch.setattr(reader, "read_log", boom)


@pytest.mark.parametrize("extra, words", [
    (["--dry-run"], "--dry-run needs --connect"),
    (["--write", "--yes"], "--write needs --connect"),
    (["--write", "--dry-run", "--connect", "udpin:127.0.0.1:1"], "give one of them"),
    (["--backup", "b.param"], "--backup only applies with --write"),
    (["--map-compass", "1:2"], "--map-compass only applies"),
    (["--connect", "udpin:127.0.0.1:1"], "--connect only applies"),
    (["--dry-run", "--connect", "udpin:127.0.0.1:1", "--map-compass", "compassX:1"], "--map-compass"),
    (["--field-mgauss", "0"], "--field-mgauss must be a positive number"),  # was a ZeroDivisionError (exit 70)
    (["--accel", "-1"], "count from 0"),
    (["--timeout", "-1"], "--timeout must be"),
    (["--orient-tol", "-1"], "--orient-tol"),
    (["--save-tlog", "x.tlog"], "--save-tlog keeps a live recording"),
])
def test_impossible_combinations_are_refused_before_reading(extra, words, sitl_dir, capsys, no_reading):
    code = main(["calibrate", str(sitl_dir / SITL02), *extra])
    err = capsys.readouterr().err
    assert code == 2 and words in err and err.count("\n") == 1, err


@pytest.mark.parametrize("cmd", [["calibrate", "udpin:127.0.0.1:9"], ["capture", "--connect", "udpin:127.0.0.1:9"]])
def test_save_tlog_never_overwrites_and_needs_its_folder_before_connecting(cmd, tmp_path, capsys, monkeypatch):
    import mavcal.link.live as live

    def boom(*a, **k):
        raise AssertionError("connected before --save-tlog was checked")
    monkeypatch.setattr(live, "open_link", boom)  # what calibrate's and capture's recorders open
    old = tmp_path / "old.tlog"
    old.write_bytes(b"a recording")
    for path, words in ((old, "already exists; not overwriting it"), (tmp_path / "no" / "x.tlog", "does not exist")):
        code = main([*cmd, "--save-tlog", str(path), "--timeout", "0.2"])
        err = capsys.readouterr().err
        assert code == 2 and words in err and err.count("\n") == 1, err
    assert old.read_bytes() == b"a recording"


def test_global_options_work_after_the_subcommand(sitl_dir, capsys):
    p = build_parser()
    for argv in (["-q", "segments", "x.tlog"], ["segments", "x.tlog", "-q"], ["segments", "-q", "x.tlog"]):
        a = p.parse_args(argv)
        assert a.quiet is True and a.verbose == 0
    assert p.parse_args(["calibrate", "x.tlog", "-vv"]).verbose == 2
    assert p.parse_args(["-v", "calibrate", "x.tlog"]).verbose == 1
    assert p.parse_args(["calibrate", "x.tlog"]).quiet is False
    assert main(["calibrate", str(sitl_dir / SITL02), "-q", "--json", "-"]) == 0
    assert json.loads(capsys.readouterr().out)["exit_code"] == 0


def test_json_means_the_same_in_every_subcommand(sitl_dir, tmp_path, capsys):
    log = str(sitl_dir / SITL02)
    # '-' (or no F): the JSON alone on stdout, the text on stderr
    for argv in (["segments", log, "--json", "-"], ["segments", log, "--json"], ["segments", "--json", log],
                 ["simulate", "--json", "-"], ["simulate", "--json"], ["calibrate", log, "--json", "-"]):
        assert main(["-q", *argv]) == 0, argv
        cap = capsys.readouterr()
        assert isinstance(json.loads(cap.out), dict), argv
        assert cap.err, argv  # the people's text went to stderr
    # F: the file, the text on stdout and a "written to" line, as the .param and the report
    for cmd in (["segments", log], ["simulate"], ["calibrate", log]):
        f = tmp_path / f"{cmd[0]}.json"
        assert main(["-q", *cmd, "--json", str(f)]) == 0
        out = capsys.readouterr().out
        assert f"JSON report written to {f}" in out and isinstance(json.loads(f.read_text()), dict)


def test_map_compass_takes_the_names_the_verdicts_print_and_the_old_slots(capsys):
    from mavcal.commands.common import slot_maps

    ns = argparse.Namespace(map_compass=["compass0:compass1"], map_imu=["accel1:accel0"])
    assert slot_maps(ns) == ({0: 1}, {1: 0})
    ns = argparse.Namespace(map_compass=["1:2"], map_imu=["2:1"])  # the old 1-based slots still mean the same
    assert slot_maps(ns) == ({0: 1}, {1: 0})
    from mavcal.errors import UsageError

    with pytest.raises(UsageError, match="0-based"):
        slot_maps(argparse.Namespace(map_compass=["compass0:accel1"], map_imu=[]))


def _help(cmd):
    p = build_parser()
    sub = next(a for a in p._actions if isinstance(a, argparse._SubParsersAction))  # noqa: SLF001
    return {a.dest: a.help for a in sub.choices[cmd]._actions}  # noqa: SLF001


def test_help_documents_the_write_options_and_one_backup_default():
    from mavcal.commands.common import BACKUP_HELP

    cal = _help("calibrate")
    for dest in ("baud", "retries", "param_timeout"):
        assert cal[dest] and "default" in cal[dest], dest
    assert cal["backup"] == _help("apply")["backup"] == _help("capture")["backup"] == BACKUP_HELP
    assert "YYYYmmdd-HHMMSS" in BACKUP_HELP


def test_simulate_with_too_few_intervals_says_so_in_its_own_terms(capsys):
    assert main(["simulate", "--intervals", "3"]) == 2
    err = capsys.readouterr().err
    assert "--intervals 3" in err and "hold the vehicle" not in err


def test_no_noise_and_implausible_numbers_flagged(real_dir, sitl_dir, capsys, caplog, tmp_path):
    assert main(["calibrate", str(sitl_dir / SITL02)]) == 0
    cap = capsys.readouterr()
    assert "SCALED_IMU not used" not in cap.out + cap.err  # expected of every ArduPilot tlog
    caplog.set_level("INFO")
    assert main(["-v", "segments", str(sitl_dir / SITL02)]) == 0
    assert caplog.text.count("SCALED_IMU not used") == 1  # once, under -v (INFO)
    assert not any(r.levelname == "WARNING" and "SCALED_IMU not used" in r.message for r in caplog.records)
    capsys.readouterr()
    main(["segments", str(real_dir / "acc_log.csv")])
    cap = capsys.readouterr()
    assert "INS_ACCOFFS" not in cap.out + cap.err  # a CSV never carries parameters
    # a compass the poses identify, reading ten times Earth's field (not mGauss): its field is
    # determined, and flagged (the real log's unidentified compass says "not determined" instead,
    # issue 30: tests/test_determined.py)
    from mavcal.testing.simlog import MagTruth, SimConfig, simulate_session

    simulate_session(SimConfig(mags=(MagTruth(hard_iron_mgauss=(50.0, -20.0, 10.0), noise_mgauss=5.0,
                                              soft_iron=((10.0, 0, 0), (0, 10.0, 0), (0, 0, 10.0))),), seed=3),
                     tlog=tmp_path / "units.tlog")
    assert main(["calibrate", str(tmp_path / "units.tlog")]) == 7
    out = capsys.readouterr().out
    assert re.search(r"field 49\d\d mGauss", out) and "IMPLAUSIBLE" in out
    assert "--force-external" in out and "use force_external" not in out
