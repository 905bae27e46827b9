"""Issue 35 item 2: outputs never destroy inputs, and are written atomically.

An output path that is an input (the same name, a symbolic link, a hard link) or another output
is refused before any work with one line and exit code 9; every output file goes through a
temporary file and a rename, so an interrupted run leaves the old file whole.
"""
from __future__ import annotations

import hashlib
import os
import shutil

import pytest

from mavcal.autopilot.paramfile import read_param_file, write_param_file
from mavcal.cli import main
from mavcal.errors import OutputIsInputError, UsageError
from mavcal.outputs import check_outputs, write_atomic

EXIT_OUTPUT_IS_INPUT = OutputIsInputError.exit_code


def _digest(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture
def log_copy(sitl_dir, tmp_path):
    path = tmp_path / "sitl02.tlog"
    shutil.copyfile(sitl_dir / "sitl02.tlog", path)
    return path


def test_the_exit_code_is_its_own():
    from mavcal.errors import EXIT_PARTIAL, GateError, SigningError, SourceError

    assert EXIT_OUTPUT_IS_INPUT == 9
    assert EXIT_OUTPUT_IS_INPUT not in {0, UsageError.exit_code, SourceError.exit_code, GateError.exit_code, 5, 6,
                                        EXIT_PARTIAL, SigningError.exit_code, 70}


@pytest.mark.parametrize("option", ["--param-out", "--json", "--report"])
@pytest.mark.parametrize("how", ["same", "symlink", "hardlink", "relative"])
def test_an_output_that_is_the_input_is_refused_before_any_work(log_copy, tmp_path, capsys, monkeypatch, option,
                                                                   how):
    before = _digest(log_copy)
    if how == "same":
        out = str(log_copy)
    elif how == "symlink":
        out = str(tmp_path / "link.tlog")
        os.symlink(log_copy, out)
    elif how == "hardlink":
        out = str(tmp_path / "hard.tlog")
        os.link(log_copy, out)
    else:
        monkeypatch.chdir(tmp_path)
        out = "./sub/../sitl02.tlog"
        (tmp_path / "sub").mkdir()
    import mavcal.commands.calibrate as cal

    monkeypatch.setattr(cal, "_single", lambda *a: pytest.fail("work started"))  # refused before any work
    assert main(["calibrate", str(log_copy), option, out]) == EXIT_OUTPUT_IS_INPUT
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("mavcal: error:") and "input" in err[0]
    assert _digest(log_copy) == before
    if how == "symlink":
        assert os.path.islink(out)


def test_the_input_through_a_symlinked_source(log_copy, tmp_path):
    link = tmp_path / "link.tlog"
    os.symlink(log_copy, link)
    before = _digest(log_copy)
    assert main(["calibrate", str(link), "--param-out", str(log_copy)]) == EXIT_OUTPUT_IS_INPUT
    assert _digest(log_copy) == before


def test_params_file_and_other_commands(log_copy, tmp_path):
    param = tmp_path / "vehicle.param"
    write_param_file(param, {"INS_ACCOFFS_X": 0.1})
    before = param.read_bytes()
    assert main(["calibrate", str(log_copy), "--params", str(param), "--param-out", str(param)]) \
        == EXIT_OUTPUT_IS_INPUT
    assert param.read_bytes() == before
    assert main(["segments", str(log_copy), "--json", str(log_copy)]) == EXIT_OUTPUT_IS_INPUT
    assert main(["apply", str(param), "--connect", "udpin:127.0.0.1:1", "--backup", str(param)]) \
        == EXIT_OUTPUT_IS_INPUT
    assert param.read_bytes() == before


def test_two_outputs_naming_one_file(log_copy, tmp_path):
    out = tmp_path / "x.out"
    assert main(["calibrate", str(log_copy), "--json", str(out), "--param-out", str(tmp_path / "." / "x.out")]) \
        == EXIT_OUTPUT_IS_INPUT
    assert not out.exists()


def test_check_outputs_passes_new_files_and_stdout(tmp_path, log_copy):
    check_outputs([("--json", "-"), ("--param-out", str(tmp_path / "new.param")), ("--report", None)],
                  [str(log_copy), "udpin:0.0.0.0:14550", None])


def test_api_write_param_file_refuses_the_log(sitl_dir, tmp_path, log_copy):
    from mavcal.pipeline import Options, calibrate_source

    run = calibrate_source(log_copy, Options(uncertainty_draws=40, holdout=False))
    before = _digest(log_copy)
    with pytest.raises(OutputIsInputError):
        run.write_param_file(log_copy)
    assert _digest(log_copy) == before


def test_an_interrupted_write_leaves_the_old_file_whole(tmp_path, monkeypatch):
    path = tmp_path / "out.param"
    write_param_file(path, {"INS_ACCOFFS_X": 0.5})
    before = path.read_bytes()

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "replace", interrupted)  # the run stops just before the rename
    with pytest.raises(KeyboardInterrupt):
        write_param_file(path, {"INS_ACCOFFS_X": 0.25, "INS_ACCOFFS_Y": 1.0})
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.param"]  # no temporary file left
    monkeypatch.undo()
    write_param_file(path, {"INS_ACCOFFS_X": 0.25})
    assert read_param_file(path) == {"INS_ACCOFFS_X": 0.25}


def test_a_failed_write_leaves_the_old_file_whole(tmp_path, monkeypatch):
    path = tmp_path / "report.json"
    write_atomic(path, "old")

    def full_disk(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", full_disk)
    from mavcal.errors import SourceError

    with pytest.raises(SourceError, match="No space left"):
        write_atomic(path, "new contents")
    assert path.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["report.json"]


def test_atomic_write_keeps_exclusive_and_mode(tmp_path):
    path = tmp_path / "backup.param"
    write_atomic(path, b"A,1\n", exclusive=True)
    with pytest.raises(UsageError, match="already exists"):
        write_atomic(path, b"A,2\n", exclusive=True)
    assert path.read_bytes() == b"A,1\n"
    umask = os.umask(0)
    os.umask(umask)
    assert (path.stat().st_mode & 0o777) == (0o644 & ~umask)


def test_write_over_a_symlinked_output_replaces_the_link_only(tmp_path):
    """An output named through a link to a file that is no input: the new file takes the link's name,
    the file it pointed to is left as it was (a rename never writes through a link)."""
    target = tmp_path / "target.txt"
    target.write_text("keep")
    link = tmp_path / "out.txt"
    os.symlink(target, link)
    write_atomic(link, "new")
    assert target.read_text() == "keep" and link.read_text() == "new" and not link.is_symlink()
