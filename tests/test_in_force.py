"""Issue 35 item 1: the calibration in force is known, or nothing absolute is written.

Each recording without (some of) its parameters is made here from a bundled or simulated log
(tmp_path, never committed): a tlog without PARAM_VALUE, a .bin without PARM, a ULog without
parameters, one sensor's names only dropped; and with ``--params FILE`` of the right
parameters the result equals the full log's.
"""
from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np
import pytest

from mavcal.autopilot.paramfile import read_param_file, write_param_file
from mavcal.cli import main
from mavcal.in_force import GATE_NAME, with_param_file
from mavcal.pipeline import Options, calibrate_prepared, calibrate_source, prepare
from mavcal.sources.reader import read_log
from mavcal.sources.types import ParamTimeline
from mavcal.testing.numbers import assert_close
from mavcal.testing.strip import strip_bin_params, strip_tlog_params, strip_ulog_params

NOT_IN_RECORDING = "not written: the calibration in force is not in the recording"
FAST = Options(uncertainty_draws=60, holdout=False)


@pytest.fixture(scope="module")
def sitl02(sitl_dir):
    return sitl_dir / "sitl02.tlog"


@pytest.fixture(scope="module")
def full_run(sitl02):
    return calibrate_source(sitl02, FAST)


@pytest.fixture(scope="module")
def vehicle_param(sitl02, tmp_path_factory):
    """The parameters sitl02's vehicle held when it was recorded, saved as a .param file (what
    Mission Planner's Save to file gives)."""
    p = read_log(sitl02).params
    path = tmp_path_factory.mktemp("params") / "vehicle.param"
    write_param_file(path, {n: float(v[0]) for n, (_, v) in p.changes.items()})
    return path


@pytest.fixture(scope="module")
def stripped(sitl02, tmp_path_factory):
    path = tmp_path_factory.mktemp("stripped") / "sitl02_noparams.tlog"
    assert strip_tlog_params(sitl02, path) == 165
    return path


def _not_known(run) -> set[str]:
    return {v.sensor for v in run.verdicts if v.reasons and v.reasons[0].startswith(NOT_IN_RECORDING)}


def test_tlog_without_parameters_accepts_and_writes_nothing(stripped, full_run, tmp_path):
    run = calibrate_source(stripped, FAST)
    sensors = {v.sensor for v in run.verdicts}
    assert sensors == {v.sensor for v in full_run.verdicts} == {"accel0", "accel1", "compass0", "compass1",
                                                                  "compass2"}
    assert _not_known(run) == sensors  # every sensor judged, none accepted, the reason first
    assert not any(v.accepted for v in run.verdicts) and run.verdict == "rejected" and run.exit_code == 4
    assert run.params_to_write() == {} and run.params_to_write(force=True) == {}
    assert all(not o for o in run.raw.cal_origin.values())
    reason = dict((v.sensor, v.reasons[0]) for v in run.verdicts)["accel0"]
    for what in ("INS_ACCOFFS_X/Y/Z", "Mission Planner", "QGroundControl", "MAVProxy", "--params FILE"):
        assert what in reason
    # the CLI: nothing written, not even with --force
    out = tmp_path / "x.param"
    assert main(["calibrate", str(stripped), "--param-out", str(out)]) == 4
    assert not out.exists()
    assert main(["calibrate", str(stripped), "--param-out", str(out), "--force"]) == 4  # nothing it could write
    assert not out.exists()


def test_params_file_gives_the_full_logs_result(stripped, full_run, vehicle_param, tmp_path):
    run = calibrate_source(stripped, FAST, params=vehicle_param)
    assert run.verdict == full_run.verdict == "accepted"
    assert [(v.sensor, v.accepted) for v in run.verdicts] == [(v.sensor, v.accepted) for v in full_run.verdicts]
    got, want = run.params_to_write(), full_run.params_to_write()
    assert sorted(got) == sorted(want) and len(want) >= 40
    assert_close([got[n] for n in sorted(want)], [want[n] for n in sorted(want)], rtol=1e-6)
    assert set(run.raw.cal_origin.values()) == {"--params vehicle.param"}
    # the CLI's .param files agree too
    a, b = tmp_path / "a.param", tmp_path / "b.param"
    assert main(["calibrate", str(stripped), "--params", str(vehicle_param), "--param-out", str(a)]) == 0
    assert main(["calibrate", str(full_run.source), "--param-out", str(b)]) == 0
    pa, pb = read_param_file(a), read_param_file(b)
    assert sorted(pa) == sorted(pb)
    assert_close([pa[n] for n in sorted(pb)], [pb[n] for n in sorted(pb)], rtol=1e-6)


def test_the_issues_repro_no_longer_writes_the_wrong_offsets(stripped, full_run):
    """The issue's numbers: the stripped log gave INS_ACCOFFS (0.1606, -0.4200, 0.1552) where the full log
    gives (0.2124, -0.4560, 0.2346): the difference is the calibration in force, now never written."""
    ofs = [full_run.params_to_write()[f"INS_ACCOFFS_{a}"] for a in "XYZ"]
    assert_close(ofs, [0.2124, -0.4560, 0.2346], rtol=0.0, atol=5e-4)
    run = calibrate_source(stripped, FAST)
    assert not any(n.startswith("INS_ACCOFFS") for n in run.params_to_write(force=True))


def test_one_sensors_names_dropped(sitl02, full_run, tmp_path):
    path = tmp_path / "no_ofs2.tlog"
    assert strip_tlog_params(sitl02, path, ("COMPASS_OFS2_",)) >= 3  # (each sent once per parameter download)
    run = calibrate_source(path, FAST)
    assert _not_known(run) == {"compass1"}
    assert run.verdict == "partly accepted" and run.partly_accepted and not run.accepted and run.exit_code == 7
    written = run.params_to_write(force=True)
    assert not any(n.startswith(("COMPASS_OFS2", "COMPASS_DIA2", "COMPASS_ODI2", "COMPASS_SCALE2")) for n in written)
    want = full_run.params_to_write()
    assert_close([written[n] for n in sorted(written)], [want[n] for n in sorted(written)], rtol=1e-6)
    reason = dict((v.sensor, v.reasons) for v in run.verdicts)["compass1"][0]
    assert "COMPASS_OFS2_X/Y/Z missing" in reason
    gate = [g for g in run.gates.gates if g.sensor == "compass1" and g.name == GATE_NAME]
    assert len(gate) == 1 and not gate[0].ok


def test_the_recordings_values_win_over_a_different_file(sitl02, tmp_path):
    log_ = read_log(sitl02)
    changed = with_param_file(log_, {"INS_ACCOFFS_X": 1.5, "NEW_PARAM": 2.0}, origin="--params v.param")
    assert changed.params.final("INS_ACCOFFS_X") == log_.params.final("INS_ACCOFFS_X")
    assert changed.params.final("NEW_PARAM") == 2.0 and changed.param_origins == {"NEW_PARAM": "--params v.param"}
    assert any("INS_ACCOFFS_X" in w and "recording's are used" in w for w in changed.warnings)


def test_dataflash_without_parm(tmp_path):
    from mavcal.testing.simlog import SimConfig, simulate_session

    full = tmp_path / "sim.bin"
    simulate_session(SimConfig(seed=3), bin=full)
    bare = tmp_path / "sim_noparm.bin"
    assert strip_bin_params(full, bare) >= 20
    assert not read_log(bare).params.changes and read_log(full).params.changes
    prep = prepare(bare)
    sensors = {f"accel{i}" for i in prep.raw.accel_instances()} | {f"compass{i}" for i in prep.raw.mag_instances()}
    assert set(prep.raw.cal_missing) == sensors and sensors
    run = calibrate_prepared(prep, FAST)
    assert _not_known(run) == {v.sensor for v in run.verdicts} and run.params_to_write(force=True) == {}
    # only the accelerometer 0's names dropped
    part = tmp_path / "sim_noacc.bin"
    assert strip_bin_params(full, part, ("INS_ACCOFFS", "INS_ACCSCAL")) == 6 * _count_changes(full, "INS_ACC")
    assert set(prepare(part).raw.cal_missing) == {"accel0"}


def _count_changes(path, prefix: str) -> int:
    """PARM records per name of accelerometer 0 (a name logged again counts again)."""
    ch = read_log(path).params.changes
    n = {len(v[0]) for k, v in ch.items() if k.startswith((prefix + "OFFS", prefix + "SCAL"))}
    assert len(n) == 1
    return n.pop()


def test_ulog_without_parameters(tmp_path):
    from tests.conftest import SHARED

    src = SHARED / "data" / "px4" / "sample_px4_events.ulg"
    if not src.exists():
        pytest.skip(f"{src} not found (shared/ must sit beside the repo)")
    bare = tmp_path / "noparams.ulg"
    assert strip_ulog_params(src, bare) > 100
    full, prep = prepare(src), prepare(bare)
    assert full.raw.cal_missing == {} and set(full.raw.cal_origin.values()) == {"the recording's parameters"}
    sensors = {f"accel{i}" for i in prep.raw.accel_instances()} | {f"compass{i}" for i in prep.raw.mag_instances()}
    assert sensors and set(prep.raw.cal_missing) == sensors
    # only the magnetometers' calibration dropped: the accelerometers' is still known
    part = tmp_path / "nomag.ulg"
    assert strip_ulog_params(src, part, ("CAL_MAG",)) > 0
    missing = prepare(part).raw.cal_missing
    assert set(missing) == {s for s in sensors if s.startswith("compass")} and missing


def _px4_log(kind: str = "ulog", drop=()):
    from mavcal.testing.px4_sim import random_truth, simulate_px4

    log_ = simulate_px4(random_truth(2))
    keep = {n: v for n, v in log_.params.changes.items() if not n.startswith(tuple(drop))} if drop != "all" else {}
    return replace(log_, kind=kind, params=ParamTimeline(keep))


def test_px4_recording_without_parameters_is_not_written():
    logging.disable(logging.WARNING)
    try:
        run = calibrate_prepared(prepare(_px4_log()), FAST)
        assert run.verdict == "accepted"
        bare = calibrate_prepared(prepare(_px4_log(drop="all")), FAST)
        assert _not_known(bare) == {"accel0", "compass0"} and bare.params_to_write(force=True) == {}
        part = calibrate_prepared(prepare(_px4_log(drop=("CAL_MAG0_XOFF",))), FAST)
        assert _not_known(part) == {"compass0"} and part.verdict == "partly accepted"
        assert not any(n.startswith("CAL_MAG") for n in part.params_to_write(force=True))
        assert any(n.startswith("CAL_ACC0") for n in part.params_to_write())
    finally:
        logging.disable(logging.NOTSET)


def test_live_link_with_a_failed_read_says_so():
    logging.disable(logging.WARNING)
    try:
        run = calibrate_prepared(prepare(_px4_log(kind="live", drop=("CAL_ACC0_XOFF",))), FAST)
    finally:
        logging.disable(logging.NOTSET)
    reasons = dict((v.sensor, v.reasons) for v in run.verdicts)
    assert reasons["accel0"][0].startswith("not written: the vehicle did not send the calibration in force")
    assert "accel0" not in {s for s, r in reasons.items() if not r}
    assert not any(n.startswith("CAL_ACC0") for n in run.params_to_write(force=True))
    assert run.raw.cal_origin["compass0"] == "the vehicle"


def test_csv_readings_are_raw_by_design(tmp_path):
    """A CSV carries raw readings (no calibration to undo): its origin says so, nothing is refused for it."""
    path = tmp_path / "raw.csv"
    t = np.arange(0, 2, 0.02)
    rows = ["time_s,ax,ay,az,mx,my,mz"] + [f"{x:.2f},0.01,0.02,0.98,200,10,400" for x in t]
    path.write_text("\n".join(rows) + "\n")
    prep = prepare(path)
    assert prep.raw.cal_missing == {}
    assert all(o.startswith("raw readings") for o in prep.raw.cal_origin.values())


def test_params_option_is_checked_before_any_work(stripped, tmp_path, capsys):
    bad = tmp_path / "bad.param"
    bad.write_text("NOT A PARAM LINE\n")
    assert main(["calibrate", str(stripped), "--params", str(bad)]) == 3
    assert main(["calibrate", str(stripped), str(stripped), "--params", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(e.startswith("mavcal: error:") for e in err)


def test_qgroundcontrols_parameter_file_is_read(tmp_path):
    from mavcal.autopilot.paramfile import parse_param_text

    text = ("# Onboard parameters for Vehicle 1\n#\n# Vehicle-Id Component-Id Name Value Type\n"
            "1\t1\tCOMPASS_OFS_X\t-141.250000000000000000\t4\n1\t1\tAHRS_ORIENTATION\t0\t2\n")
    assert parse_param_text(text) == {"COMPASS_OFS_X": -141.25, "AHRS_ORIENTATION": 0.0}
