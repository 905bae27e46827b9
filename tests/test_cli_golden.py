"""Golden output of the CLI's summary on the bundled SITL logs (as pyulog tests its CLI).

The summary is what a user reads first; any change to it must be a decision, made by
regenerating the golden files and reading the diff:

    MAVCAL_UPDATE_GOLDEN=1 python -m pytest tests/test_cli_golden.py
"""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from mavcal.cli import main

GOLDEN = Path(__file__).resolve().parent / "golden"
REPO = Path(__file__).resolve().parents[1]


def _summary(capsys, args: list[str]) -> tuple[int, str]:
    code = main(args)
    cap = capsys.readouterr()
    return code, cap.out


@pytest.mark.parametrize("name", ["sitl01", "sitl02"])
def test_calibrate_summary_matches_golden(name, capsys, monkeypatch):
    monkeypatch.chdir(REPO)  # the summary names the log as given
    code, out = _summary(capsys, ["calibrate", f"sitl_logs/{name}.tlog"])
    golden = GOLDEN / f"calibrate_{name}.txt"
    if os.environ.get("MAVCAL_UPDATE_GOLDEN"):
        golden.write_text(out)
    assert code == 0
    assert out == golden.read_text(), f"summary changed; diff it against {golden} (MAVCAL_UPDATE_GOLDEN=1 rewrites)"


def test_segments_text_matches_golden(capsys, monkeypatch):
    monkeypatch.chdir(REPO)
    code, out = _summary(capsys, ["segments", "sitl_logs/sitl02.tlog"])
    golden = GOLDEN / "segments_sitl02.txt"
    if os.environ.get("MAVCAL_UPDATE_GOLDEN"):
        golden.write_text(out)
    assert code == 0
    assert out == golden.read_text()
