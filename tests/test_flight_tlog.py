"""``mavcal flight`` on tlogs, as far as they carry what the fit needs (issue 39).

A synthetic flight (:mod:`mavcal.testing.flight_synth`, ArduPilot's model) written as a ground
station records it (:func:`~mavcal.testing.flight_synth.write_flight_tlog`): the corrected field in
RAW_IMU / SCALED_IMU2, the current in SYS_STATUS, the parameters in PARAM_VALUE. With all of it
the fit runs and recovers ``COMPASS_MOT`` within the issue's tolerance; without the current, with
the compass streamed too slowly, or from a PX4, it is refused in one line naming what is missing.
"""
from __future__ import annotations

import contextlib
import io

import pytest

from mavcal.autopilot.paramfile import read_param_file
from mavcal.cli import main
from mavcal.testing.flight_synth import SynthCompass, synth_flight, write_flight_tlog
from mavcal.testing.numbers import numbers_close

MOT = (3.0, -2.0, 4.0)


def run(*args: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["flight", *map(str, args)])
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def flight():
    return synth_flight([SynthCompass(interference=MOT), SynthCompass(interference=MOT)], seed=11)


def test_a_tlog_with_what_the_fit_needs_runs(tmp_path, flight):
    log = write_flight_tlog(tmp_path / "f.tlog", flight)
    par = tmp_path / "m.param"
    code, out, err = run(log, "--param-out", par)
    assert code == 0, out + err
    assert "rotation judged against: nothing" in out  # a tlog carries no EKF-GSF yaw
    p = read_param_file(par)
    assert p["COMPASS_MOTCT"] == 2.0
    for s in ("", "2"):
        for a, truth in zip("XYZ", MOT):
            assert numbers_close(p[f"COMPASS_MOT{s}_{a}"], -truth, rtol=0.0, atol=max(0.3, 0.05 * abs(truth)))


@pytest.mark.parametrize("kw, code, says", [
    ({"every": 5}, 3, "compass0's field (RAW_IMU) is logged at 2.0 Hz: the in-flight fit needs it at 4 Hz"),
    ({"current": False}, 4, "no current sensor: the battery current never varies"),
    ({"autopilot": 12}, 3, "a PX4 tlog"),
])
def test_a_tlog_without_what_the_fit_needs_is_refused_in_one_line(tmp_path, flight, kw, code, says):
    log = write_flight_tlog(tmp_path / "r.tlog", flight, **kw)
    got, out, err = run(log)
    assert got == code and err.count("\n") == 1 and err.startswith("mavcal: error:") and says in err, (got, err)
