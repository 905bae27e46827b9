"""The in-flight compass stage on synthetic flights made from ArduPilot's model (issue 39).

The truth is known exactly: ``COMPASS_MOT = -interference`` and ``COMPASS_OFS = ofs_true``
(:mod:`mavcal.testing.flight_synth`). Tolerances are the issue's: ``max(0.3 mGauss/A, 5 %)``
per axis, and the truth inside the 95 % bounds.
"""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from mavcal.commands.flight import summary_text, to_json
from mavcal.flight.stage import analyse, param_values
from mavcal.testing.flight_synth import SynthCompass, synth_flight
from mavcal.testing.numbers import numbers_close

MOT = (3.0, -2.0, 4.0)


def _tol(truth: float) -> float:
    return max(0.3, 0.05 * abs(truth))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_motor_term_recovered_within_tolerance_and_bounds(seed):
    rng = np.random.default_rng(seed)
    mot = tuple(float(v) for v in rng.uniform(-8, 8, 3))
    ofs = tuple(float(v) for v in rng.uniform(-60, 60, 3))
    r = analyse(synth_flight([SynthCompass(interference=mot, ofs_true=ofs, ofs_in_force=ofs)], seed=seed))
    (c,) = r.compasses
    f = c.fit
    assert f is not None and f.fitted_mot and f.fitted_ofs
    for k in range(3):
        truth = -mot[k]
        assert numbers_close(f.mot_per_unit[k], truth, rtol=0.0, atol=_tol(truth)), (k, f.mot_per_unit, truth)
        assert abs(f.mot_per_unit[k] - truth) <= f.mot_bound95_per_unit[k], (k, f.mot_per_unit, f.mot_bound95_per_unit)
        assert abs(f.ofs_mgauss[k] - ofs[k]) <= max(f.ofs_bound95_mgauss[k], 1.0), (k, f.ofs_mgauss, ofs)
    assert c.verdict.accepted and not c.verdict.wrong
    p = param_values(r)
    assert p["COMPASS_MOTCT"] == 2.0
    assert numbers_close(p["COMPASS_MOT_X"], -mot[0], rtol=0.0, atol=_tol(mot[0]))


def test_wrong_compasses_are_named_with_their_cause_and_the_good_one_is_not():
    r = analyse(synth_flight([SynthCompass(interference=MOT),
                              SynthCompass(interference=MOT, ofs_true=(85.0, 13.0, -18.0)),  # offset it lacks
                              SynthCompass(interference=MOT, yaw_rotation_deg=45.0)], seed=4))
    v = {c.instance: c.verdict for c in r.compasses}
    assert not v[0].wrong and v[0].accepted
    assert v[1].wrong and "constant 80 mGauss offset" in v[1].causes[0] and not v[1].accepted
    assert v[2].wrong and "wrong rotation" in v[2].causes[0] and not v[2].accepted
    text = summary_text(r)
    lines = text.splitlines()
    assert any(ln.startswith("compass1: WRONG in flight: a constant 80 mGauss offset") for ln in lines)
    assert any(ln.startswith("compass2: WRONG in flight: its heading is +") for ln in lines)
    assert not any("WRONG" in ln for ln in lines if ln.startswith("compass0"))
    p = param_values(r)  # the accepted compass only
    assert set(p) == {"COMPASS_MOTCT", "COMPASS_MOT_X", "COMPASS_MOT_Y", "COMPASS_MOT_Z"}
    doc = to_json(r)
    assert [c["wrong"] for c in doc["compasses"]] == [False, True, True]


def test_a_slope_with_current_the_other_compass_lacks_is_named():
    r = analyse(synth_flight([SynthCompass(interference=(0.2, 0.1, -0.2)),
                              SynthCompass(interference=(12.0, -6.0, 4.0))], seed=5))
    v = {c.instance: c.verdict for c in r.compasses}
    assert not v[0].wrong and v[0].level == "ok"
    assert v[1].wrong and "slope with current" in v[1].causes[0] and v[1].level == "bad"
    assert v[1].accepted  # its fix is the compensation itself: written
    assert "COMPASS_MOT2_X" in param_values(r)


def test_current_that_barely_varies_keeps_the_motor_term():
    s = synth_flight([SynthCompass(interference=MOT, mot_in_force=(-1.0, 1.0, -1.0))], seed=6, current_max_a=0.0)
    # a flight without a current sensor: the throttle when asked (constant too here) -> nothing identified
    r = analyse(s, driver="throttle")
    (c,) = r.compasses
    assert c.fit is not None and not c.fit.fitted_mot
    assert not c.verdict.accepted and "barely varied" in c.verdict.not_written_because
    assert param_values(r) == {}


def test_unknown_calibration_in_force_is_not_written():
    s = synth_flight([SynthCompass(interference=MOT)], seed=7)
    params = {k: v for k, v in s.params.items() if not k.startswith("COMPASS_DIA")}
    from dataclasses import replace
    r = analyse(replace(s, params=params))
    (c,) = r.compasses
    assert not c.verdict.accepted and "COMPASS_DIA_X" in c.verdict.not_written_because
    assert param_values(r) == {}


def test_interference_percentage_is_compassmots_measure():
    r = analyse(synth_flight([SynthCompass(interference=MOT)], seed=8))
    (c,) = r.compasses
    f = c.fit
    assert f is not None
    want = np.linalg.norm(f.mot_per_unit) * f.driver_max / np.linalg.norm(f.B_ned_mgauss) * 100
    assert numbers_close(c.verdict.interference_pct, want, rtol=1e-9)


@pytest.mark.parametrize("content, code", [(None, 3), (b"not a log at all", 3)])
def test_cli_bad_input_is_one_line_with_its_exit_code(tmp_path, content, code):
    p = tmp_path / "x.bin"
    if content is not None:
        p.write_bytes(content)
    out = subprocess.run([sys.executable, "-m", "mavcal", "flight", str(p)], capture_output=True, text=True, timeout=60)
    assert out.returncode == code, out.stderr
    assert out.stderr.count("\n") == 1 and out.stderr.startswith("mavcal: error:")
    assert "Traceback" not in out.stderr


def test_throttle_driven_interference_without_a_current_sensor():
    """COMPASS_MOTCT 1: the motor term per full throttle (the synthetic throttle is 0.6 * I / I_max)."""
    s = synth_flight([SynthCompass(interference=MOT)], seed=9)
    r = analyse(s, driver="throttle")
    (c,) = r.compasses
    f = c.fit
    assert r.driver_kind == "throttle" and f is not None and f.fitted_mot
    for k in range(3):
        truth = -MOT[k] * 40.0 / 0.6
        assert numbers_close(f.mot_per_unit[k], truth, rtol=0.05), (k, f.mot_per_unit, truth)
        assert abs(f.mot_per_unit[k] - truth) <= f.mot_bound95_per_unit[k]
    assert param_values(r)["COMPASS_MOTCT"] == 1.0
    assert "at full throttle" in c.verdict.summary


def test_reference_rotations_are_ardupilots_euler_convention():
    from mavcal.flight.reference import check_matrices

    assert check_matrices() < 1e-12
