"""Damaged inputs end fast with a line about the file (issue 35, items 9 and 10).

* no input hangs: the ULog on which pyulog 1.3 loops forever (made here,
  :func:`mavcal.testing.damaged.ulog_definitions_loop`, and the shared mutant it was found in) ends at
  once with exit 3 and one line; a loop of pyulog's that mavcal's own check of the definitions does
  not foresee still ends (a bounded number of reads per byte of the file);
* errors that say what is wrong: a damaged PARM format of a .bin, a damaged parameter type of a ULog,
  a CSV with a lone carriage return, pyulog's own refusal: one line naming the record or the parser,
  never a Python exception; an internal bug of a reader (an IndexError on an undamaged log) is not
  dressed as a one-liner, and the fuzz checks catch it.
"""
from __future__ import annotations

import os
import struct
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from mavcal.cli import EXIT_INTERNAL, main
from mavcal.errors import SourceError
from mavcal.sources.reader import read_log
from mavcal.testing.damaged import error_line_problem, python_exception_named, ulog_definitions_loop

ROOT = Path(__file__).resolve().parents[1]
PX4_LOGS = ROOT.parent / "shared" / "data" / "px4"
SITL = ROOT / "sitl_logs"
#: a damaged file must be refused within this (seconds; it takes well under one here: the bound is for
#: a loaded CI machine, and a hang is what it catches)
ENDS_WITHIN_S = 60


def _need(path: Path) -> Path:
    """``path``, or skip (a failure under CI=true: the shared data must be there)."""
    if not path.is_file():
        if os.environ.get("CI", "").strip().lower() == "true":
            pytest.fail(f"CI=true but {path} is missing (shared/ must sit beside the repo)", pytrace=False)
        pytest.skip(f"{path} not available")
    return path


def _cli(*argv: str) -> tuple[int, str]:
    """``python -m mavcal ARGV`` in a child with a deadline: (exit code, stderr); a hang fails the test."""
    try:
        p = subprocess.run([sys.executable, "-m", "mavcal", *argv], capture_output=True, text=True,
                           timeout=ENDS_WITHIN_S, cwd=ROOT)
    except subprocess.TimeoutExpired:
        pytest.fail(f"mavcal {' '.join(argv)} did not end within {ENDS_WITHIN_S} s")
    return p.returncode, p.stderr


def _one_line_about_the_file(code: int, err: str, *words: str) -> str:
    assert code == 3, (code, err)
    assert error_line_problem(code, err) is None, err
    line = err.strip()
    for w in words:
        assert w in line, line
    return line


# ------------------------------------------------------------------------------------ item 9: no hangs
def test_the_ulog_pyulog_loops_on_is_refused_at_once(tmp_path):
    f = tmp_path / "loop.ulg"
    f.write_bytes(ulog_definitions_loop())
    assert len(f.read_bytes()) == 10_019
    code, err = _cli("segments", str(f))
    _one_line_about_the_file(code, err, "damaged ULog", "byte 16", "10001 bytes", "past the end of the file")


def test_the_shared_hanging_mutant_ends_with_one_line():
    f = _need(PX4_LOGS / "corrupt_hang.ulg")  # read in place: shared data is never copied into the repo
    for command in ("segments", "calibrate"):
        code, err = _cli(command, str(f))
        _one_line_about_the_file(code, err, "damaged ULog", "byte 39538", "58560 bytes")


def test_a_pyulog_loop_the_check_does_not_foresee_still_ends(tmp_path):
    """Without mavcal's check of the definitions, pyulog's endless loop is ended by the bound on its reads
    (8 per byte of the file and 10,000), with the byte it was stuck at."""
    f = tmp_path / "loop.ulg"
    f.write_bytes(ulog_definitions_loop(20_000))
    script = ("import mavcal.sources.ulog as u\n"
              "u._check_definitions = lambda path, data: None\n"
              "from mavcal.errors import SourceError\n"
              f"try:\n    u.read_ulog({str(f)!r})\n"
              "except SourceError as e:\n    print(e)\n")
    try:
        p = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=ENDS_WITHIN_S)
    except subprocess.TimeoutExpired:
        pytest.fail("pyulog's loop was not ended")
    assert p.returncode == 0, p.stderr
    assert "pyulog makes no progress at byte 19 of 20018" in p.stdout, p.stdout  # the payload after the header
    assert python_exception_named(p.stdout) is None


def test_the_read_bound_leaves_every_shared_ulog_whole():
    """The bound is far above what pyulog needs on an undamaged log (0.02-0.04 reads per byte)."""
    from mavcal.sources import ulog as u

    for name in ("sample_log_small.ulg", "sample_px4_events.ulg", "sample.ulg"):
        path = _need(PX4_LOGS / name)
        f = u._BoundedFile(str(path), path.stat().st_size)
        try:
            from pyulog import ULog

            ULog(f, message_name_filter_list=["sensor_accel"], disable_str_exceptions=True)
        finally:
            f.close()
        assert f.reads < 0.1 * f.size < f.budget, (name, f.reads, f.size)


# ------------------------------------------------------------------------- item 10: what is wrong
def test_pyulog_refusing_a_file_is_named_with_its_reason(tmp_path):
    header = b"ULog\x01\x12\x35\x01" + bytes(8)
    flags = struct.pack("<HB", 40, ord("B")) + bytes(8) + bytes([0, 1]) + bytes(6) + bytes(24)  # unknown incompat bit
    f = tmp_path / "flags.ulg"
    f.write_bytes(header + flags + struct.pack("<HB", 0, ord("A")))
    code, err = _cli("segments", str(f))
    _one_line_about_the_file(code, err, "pyulog could not parse", "incompatible flag")


def test_not_a_ulog_is_said_so(tmp_path):
    f = tmp_path / "x.ulg"
    f.write_bytes(b"this is not a ULog at all, just text\n" * 20)
    code, err = _cli("segments", str(f))
    _one_line_about_the_file(code, err, "not a ULog")


def test_a_damaged_ulog_parameter_type_is_named(tmp_path):
    data = bytearray(_need(PX4_LOGS / "sample_logging_tagged_and_default_params.ulg").read_bytes())
    i = data.find(b"int32_t CAL_ACC0_ID")
    data[i:i + 7] = b"int32_q"  # a damaged type: pyulog hands over the value's raw bytes
    f = tmp_path / "param.ulg"
    f.write_bytes(bytes(data))
    with pytest.raises(SourceError, match=r"parameter 'CAL_ACC0_ID' holds no number") as e:
        read_log(f)
    assert python_exception_named(str(e.value)) is None


def _sim_bin(tmp_path: Path) -> Path:
    from mavcal.testing.simlog import SimConfig, simulate_session

    p = tmp_path / "s.bin"
    simulate_session(replace(SimConfig(), poses_deg=SimConfig().poses_deg[:8]), bin=p)
    return p


@pytest.mark.parametrize("damage", [b"TimeUS,Nbme,Value", b"TimeUS,Name,Valuf"])
def test_a_damaged_parm_format_is_named_not_a_key_error(tmp_path, damage):
    p = _sim_bin(tmp_path)
    data = p.read_bytes()
    assert data.count(b"TimeUS,Name,Value,Default") == 1
    p.write_bytes(data.replace(b"TimeUS,Name,Value,Default", damage + b",Default"))
    code, err = _cli("segments", str(p))
    _one_line_about_the_file(code, err, "PARM", "format (FMT)", damage.decode())


def test_a_damaged_msg_format_is_a_warning(tmp_path):
    p = _sim_bin(tmp_path)
    data = p.read_bytes()
    p.write_bytes(data.replace(b"TimeUS,Message", b"TimeUS,Mess4ge"))
    lg = read_log(p)
    assert any("MSG records ignored" in w for w in lg.warnings), lg.warnings


def test_a_csv_with_a_lone_carriage_return_reads(tmp_path):
    rows = "\n".join(f"{0.01 * k:.2f},0,0,1" for k in range(50))
    f = tmp_path / "a.csv"
    f.write_bytes(("t,ax,ay,az\n" + rows).replace("0.10,0,0,1", "0.10,0\r,0,1").encode())
    lg = read_log(f)
    assert len(lg.series[0]) >= 49


def test_an_internal_bug_of_a_reader_is_not_a_one_liner(monkeypatch, capsys):
    """A reader raising IndexError on an undamaged log is a bug: it escapes read_log (the fuzz tests'
    check then fails) and the CLI reports an internal error (exit 70), which error_line_problem flags."""
    import mavcal.sources.tlog_imu as tlog_imu

    def broken(*a, **k):
        raise IndexError("index 3 is out of bounds")

    monkeypatch.setattr(tlog_imu, "decode_tlog_lean", broken)
    with pytest.raises(IndexError):
        read_log(SITL / "sitl02.tlog")
    code = main(["segments", str(SITL / "sitl02.tlog")])
    err = capsys.readouterr().err
    assert code == EXIT_INTERNAL
    assert error_line_problem(code, err) is not None


@pytest.mark.parametrize("line, named", [
    ("mavcal: error: x: corrupt or unsupported (KeyError: 'Value')", "KeyError"),
    ("mavcal: error: x: (ValueError: could not convert string to float: b'\\x00')", "ValueError"),
    ("mavcal: error: cannot read x: struct.error: unpack requires", "struct.error"),
    ("mavcal: error: x: ULogException", "ULogException"),
    ("mavcal: error: x: damaged ULog: the message at byte 16 declares 10001 bytes", None),
    ("mavcal: error: x: no IMU data (IMU/ACC/GYR/MAG records) in x", None),
])
def test_python_exception_names_are_found(line, named):
    assert python_exception_named(line) == named
    assert (error_line_problem(3, line + "\n") is None) == (named is None)


def test_error_line_problem_wants_exactly_one_error_line():
    assert error_line_problem(0, "") is None
    assert error_line_problem(7, "warning: x\n") is None
    assert error_line_problem(3, "") is not None
    assert error_line_problem(3, "mavcal: error: a\nmavcal: error: b\n") is not None
    assert error_line_problem(4, "Traceback (most recent call last):\n") is not None
