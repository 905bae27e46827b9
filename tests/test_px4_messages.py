"""What PX4 logs' users read (issue 35, item 6): no internal names, no contradiction between two
numbers of poses, ULog times from the log's start, and help texts that name .ulg and PX4."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from mavcal.cli import build_parser, main
from mavcal.core.stats import interval_stats
from mavcal.errors import EstimationError

PX4 = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "px4"
#: item 9's input (it hangs pyulog's reader; its own test bounds that)
LOGS = ["sample.ulg", "sample_appended_multiple.ulg", "sample_log_small.ulg",
        "sample_logging_tagged_and_default_params.ulg", "sample_px4_events.ulg"]
#: names of the code (arguments, variables, exception classes) a person must not be shown
INTERNAL = re.compile(r"\b\w+_sets\b|\b\w+_sensors\[|\b[A-Z]\w*(Error|Exception)\b")


@pytest.fixture(scope="module")
def px4_dir() -> Path:
    if not PX4.is_dir():
        pytest.skip(f"PX4 logs not found at {PX4} (shared/ must sit beside the repo)")
    return PX4


@pytest.mark.parametrize("name", LOGS)
def test_a_px4_logs_refusal_names_no_internals_and_one_number_of_poses(px4_dir, name, capsys):
    code = main(["calibrate", str(px4_dir / name)])
    err = capsys.readouterr().err
    assert code in (3, 4), err
    error = [ln for ln in err.splitlines() if ln.startswith("mavcal: error:")]
    assert len(error) == 1, err
    assert not INTERNAL.search(error[0]), error[0]
    # "at least N in different orientations are needed" and "at least M different poses": N == M
    need = {int(n) for n in re.findall(r"at least (\d+) (?:in different orientations|different poses)", error[0])}
    assert len(need) <= 1, error[0]


def test_constant_readings_are_named_as_the_sensor(px4_dir, capsys):
    """sample_log_small.ulg: the accelerometer's mean reading is the same in every interval; the
    message names the sensor, not the core function's argument (``accel_sets``)."""
    assert main(["calibrate", str(px4_dir / "sample_log_small.ulg")]) == 4
    err = capsys.readouterr().err
    assert "accelerometer 0: the mean reading is the same in every interval" in err and "accel_sets" not in err


def test_the_core_api_keeps_its_argument_names_and_words_name_intervals():
    one = [np.ones((1, 3))]
    with pytest.raises(EstimationError, match=r"accel_sets\[0\] has 1 sample"):
        interval_stats(one, "accel_sets")
    with pytest.raises(EstimationError, match=r"^accelerometer 2, still interval 0 has 1 sample"):
        interval_stats(one, "accelerometer 2")


def test_segments_of_a_ulog_prints_times_from_the_log_start(px4_dir, capsys):
    """sample_px4_events.ulg was stamped with the wall clock (epoch microseconds): its intervals
    start 0.9 and 23.9 s into the log, as a tlog's or a .bin's count from their start."""
    assert main(["segments", str(px4_dir / "sample_px4_events.ulg")]) == 4  # too few poses, as calibrate says
    out = capsys.readouterr().out
    rows = [ln.split() for ln in out.splitlines() if re.match(r"^\s+\d+\s+-?\d", ln)]
    assert len(rows) == 2
    starts = [float(r[1]) for r in rows]
    assert starts == pytest.approx([0.90, 23.90], abs=0.011), out


@pytest.mark.parametrize("name", ["sample_px4_events.ulg", "sample_log_small.ulg"])
def test_ulog_times_and_parameter_times_share_the_log_start(px4_dir, name):
    from pyulog import ULog

    from mavcal.sources.ulog import read_ulog

    log_ = read_ulog(str(px4_dir / name))
    u = ULog(str(px4_dir / name), message_name_filter_list=["sensor_accel"])
    length_s = (u.last_timestamp - u.start_timestamp) / 1e6
    for s in log_.series:
        assert -1.0 <= s.time_s[0] and s.time_s[-1] <= length_s + 1.0, (s.message, s.time_s[0], s.time_s[-1])
    times = np.concatenate([t for t, _ in log_.params.changes.values()])
    assert len(times) and np.all(times <= length_s + 1.0)


def test_help_names_ulog_and_px4(capsys):
    parser = build_parser()
    assert "PX4" in parser.description and "for ArduPilot." not in parser.format_help()
    with pytest.raises(SystemExit):
        main(["calibrate", "--help"])
    assert ".ulg" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["segments", "--help"])
    assert ".ulg" in capsys.readouterr().out
