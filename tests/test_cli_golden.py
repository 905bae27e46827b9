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


@pytest.mark.parametrize("name", ["sitl01", "sitl02"])
def test_calibrate_summary_matches_golden(name, capsys, monkeypatch):
    monkeypatch.chdir(REPO)  # the summary names the log as given
    code, out = _summary(capsys, ["calibrate", f"sitl_logs/{name}.tlog"])
    golden = GOLDEN / f"calibrate_{name}.txt"
    if os.environ.get("MAVCAL_UPDATE_GOLDEN"):
        golden.write_text(out)
    assert code == 0
    assert_text_close(out, golden.read_text(),
                      what=f"summary (diff it against {golden}; MAVCAL_UPDATE_GOLDEN=1 rewrites)")


def test_segments_text_matches_golden(capsys, monkeypatch):
    monkeypatch.chdir(REPO)
    code, out = _summary(capsys, ["segments", "sitl_logs/sitl02.tlog"])
    golden = GOLDEN / "segments_sitl02.txt"
    if os.environ.get("MAVCAL_UPDATE_GOLDEN"):
        golden.write_text(out)
    assert code == 0
    assert_text_close(out, golden.read_text(), what=f"segments text ({golden})")


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
