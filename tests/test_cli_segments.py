"""``mavcal segments``: text and JSON output, thresholds, exit codes."""
import json
from dataclasses import replace

import pytest

from mavcal.cli import main
from mavcal.testing.simlog import SimConfig, simulate_session


@pytest.fixture(scope="module")
def tlog(tmp_path_factory):
    p = tmp_path_factory.mktemp("cli") / "s.tlog"
    simulate_session(replace(SimConfig(), poses_deg=SimConfig().poses_deg[:9], seed=5), tlog=p)
    return p


def test_text_output(tlog, capsys):
    assert main(["segments", str(tlog)]) == 0
    out = capsys.readouterr().out
    assert "9 still intervals" in out
    assert "coverage: ok" in out and "level" in out


def test_json_output(tlog, capsys):
    assert main(["segments", str(tlog), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert len(d["intervals"]) == 9
    iv = d["intervals"][0]
    assert set(iv) >= {"start_s", "end_s", "duration_s", "n_accel", "n_mag", "gravity_dir", "label"}
    assert d["coverage"]["n_orientations"] >= 8 and d["coverage"]["status"] == "ok"
    assert d["recovery"]["frames"]["accel"].startswith("board frame")


def test_thresholds_and_no_intervals_exit_4(tlog, capsys):
    assert main(["segments", str(tlog), "--accel-std", "0.00001"]) == 4
    cap = capsys.readouterr()
    assert "0 still intervals" in cap.out and "no still intervals" in cap.err


def test_bad_option_exit_2(tlog, capsys):
    assert main(["segments", str(tlog), "--window", "-1"]) == 2


def test_unreadable_source_exit_3(tmp_path, capsys):
    bad = tmp_path / "junk.tlog"
    bad.write_bytes(b"\x00\x01garbage" * 3)
    assert main(["segments", str(tmp_path / "missing.tlog")]) == 3
    assert main(["segments", str(bad)]) == 3
