"""Golden output of the CLI's summary on the bundled SITL logs (as pyulog tests its CLI).

The summary is what a user reads first; any change to it must be a decision, made by
regenerating the golden files and reading the diff:

    MAVCAL_UPDATE_GOLDEN=1 python -m pytest tests/test_cli_golden.py

The words must match exactly; the numbers are parsed and compared at 1e-6 relative (1e-9
absolute near zero, plus one unit in the last printed digit), not character by character:
their last bits differ between BLAS kernels and CPUs (issue 23; mavcal.testing.numbers).
"""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from mavcal.cli import main
from mavcal.testing.numbers import assert_text_close

pytestmark = pytest.mark.cpu_sensitive  # .ci/avx2 runs these as an AVX2-only CPU would (issue 30)

GOLDEN = Path(__file__).resolve().parent / "golden"
REPO = Path(__file__).resolve().parents[1]


def _summary(capsys, args: list[str]) -> tuple[int, str]:
    code = main(args)
    cap = capsys.readouterr()
    return code, cap.out


#: the golden files of this module and the command that makes each (the docs' samples of them
#: start with that command: tests/test_docs.py checks it)
GOLDEN_COMMANDS = {
    "calibrate_sitl01.txt": ["calibrate", "sitl_logs/sitl01.tlog"],
    "calibrate_sitl02.txt": ["calibrate", "sitl_logs/sitl02.tlog"],
    "segments_sitl02.txt": ["segments", "sitl_logs/sitl02.tlog"],
    # a fleet audit: one row per log, the drift flagged (the docs' fleet page)
    "fleet_sitl.txt": ["calibrate", "sitl_logs/sitl01.tlog", "sitl_logs/sitl02.tlog", "--jobs", "2"],
}


@pytest.mark.parametrize("name", sorted(GOLDEN_COMMANDS))
def test_output_matches_golden(name, capsys, monkeypatch):
    monkeypatch.chdir(REPO)  # the output names the logs as given
    code, out = _summary(capsys, GOLDEN_COMMANDS[name])
    golden = GOLDEN / name
    if os.environ.get("MAVCAL_UPDATE_GOLDEN"):
        golden.write_text(out)
    assert code == 0
    assert_text_close(out, golden.read_text(),
                      what=f"output (diff it against {golden}; MAVCAL_UPDATE_GOLDEN=1 rewrites)")


def test_report_without_matplotlib_is_refused_before_any_work(tmp_path, capsys, monkeypatch):
    """Issue 14: an optional dependency is checked first, not after the whole calibration."""
    import mavcal.report.html as html

    monkeypatch.setattr(html, "missing_dependencies", lambda: ["matplotlib"])
    pf, js = tmp_path / "x.param", tmp_path / "x.json"
    code = main(["calibrate", str(REPO / "sitl_logs" / "sitl02.tlog"), "--report", str(tmp_path / "r.html"),
                 "--param-out", str(pf), "--json", str(js)])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "mavcal[plots]" in err
    assert not pf.exists() and not js.exists()
