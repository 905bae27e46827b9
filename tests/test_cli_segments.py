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


def test_segments_and_calibrate_list_the_same_intervals(sitl_dir, tmp_path, capsys):
    """Both run pipeline.prepare (untruncation included) with the same thresholds."""
    log = str(sitl_dir / "sitl02.tlog")
    assert main(["segments", log, "--json"]) == 0
    seg = json.loads(capsys.readouterr().out)
    out = tmp_path / "cal.json"
    assert main(["calibrate", log, "--json", str(out)]) == 0
    capsys.readouterr()
    cal = json.loads(out.read_text())
    bounds_seg = [(d["start_s"], d["end_s"], d["duration_s"]) for d in seg["intervals"]]
    bounds_cal = [(d["start_s"], d["end_s"], d["duration_s"]) for d in cal["intervals"]]
    assert len(bounds_seg) >= 6 and bounds_seg == bounds_cal
    assert seg["intervals"][-1]["start_s"] == pytest.approx(116.504, abs=1e-3)  # untruncated, as calibrate


def test_gyro_threshold_one_spelling_and_deprecated_alias(tlog, capsys):
    assert main(["segments", str(tlog), "--json", "--gyro-threshold", "0.0001"]) == 4
    new = capsys.readouterr()
    assert main(["segments", str(tlog), "--json", "--gyro", "0.0001"]) == 4
    old = capsys.readouterr()
    assert "--gyro is deprecated, use --gyro-threshold" in old.err
    assert json.loads(old.out)["config"]["gyro_rad_s"] == json.loads(new.out)["config"]["gyro_rad_s"] == 0.0001
    assert main(["segments", str(tlog), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["config"]["gyro_rad_s"] == 0.1


def test_calibrate_takes_the_same_threshold_options(tlog):
    from mavcal.cli import build_parser

    p = build_parser()
    a = p.parse_args(["calibrate", str(tlog), "--gyro-threshold", "0.05", "--window", "2", "--trim", "0.3"])
    b = p.parse_args(["segments", str(tlog), "--gyro-threshold", "0.05", "--window", "2", "--trim", "0.3"])
    from mavcal.commands.common import still_config

    assert still_config(a) == still_config(b)
    assert still_config(a).gyro_rad_s == 0.05 and still_config(a).window_s == 2.0
    assert "--gyro " not in p._subparsers._group_actions[0].choices["segments"].format_help()
