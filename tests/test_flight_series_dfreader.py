"""The flight series ``mavcal flight`` reads equal what pymavlink's DFReader reads from the same
``.bin`` (issue 39: the fast read keeps its correctness), on every real log in ``../shared/data/real``
and on a synthetic flight: every message the stage reads, record by record, every numeric column
at a stated tolerance; and the series built from them (the compasses per instance, the current,
the attitude) equal the same built from DFReader's messages.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pymavlink import DFReader

from mavcal.errors import SourceError
from mavcal.sources.fast_dataflash import decode_dataflash
from mavcal.sources.flight_series import MESSAGES, read_flight_series
from mavcal.testing.flight_synth import SynthCompass, synth_flight, write_flight_bin
from mavcal.testing.numbers import assert_close

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
LOGS = sorted(p.name for p in REAL.glob("*")) if REAL.is_dir() else []
BINS = [n for n in LOGS if n.lower().endswith(".bin")]
RTOL = 1e-12  # the same float32/int values, scaled by the same multipliers: equal but for the last bit


def _dfreader(path: Path, names: tuple[str, ...]) -> dict[str, list]:
    r = DFReader.DFReader_binary(str(path), zero_time_base=False)
    out: dict[str, list] = {n: [] for n in names}
    while True:
        m = r.recv_match(type=list(names))
        if m is None:
            return out
        out[m.get_type()].append(m)


def _same_as_dfreader(path: Path) -> int:
    cols, _, _ = decode_dataflash(str(path), MESSAGES)
    want = _dfreader(path, MESSAGES)
    compared = 0
    for name in MESSAGES:
        msgs = want[name]
        got = cols.get(name)
        if got is None:
            assert not msgs, name
            continue
        assert len(got["_index"]) == len(msgs), name
        for k in msgs[0].get_fieldnames() if msgs else ():
            vals = [getattr(m, k) for m in msgs]
            if k not in got or not all(isinstance(v, (int, float)) for v in vals):
                continue  # text and array columns: not series the stage reads as numbers
            assert_close(np.asarray(got[k], dtype=float), np.asarray(vals, dtype=float), rtol=RTOL, atol=0.0)
            compared += len(vals)
    return compared


def _series_as_dfreader(path: Path) -> None:
    try:
        s = read_flight_series(path)
    except SourceError:
        return  # not a flight log the stage reads (no attitude, timed in TimeMS): nothing to compare
    want = _dfreader(path, ("MAG", "ATT", "BAT"))
    for c in s.compasses:
        mags = [m for m in want["MAG"] if getattr(m, "I", 0) == c.instance]
        assert len(mags) == len(c.time_s)
        assert_close(c.time_s, np.array([m.TimeUS * 1e-6 for m in mags]), rtol=RTOL, atol=0.0)
        assert_close(c.field_mgauss, np.array([[m.MagX, m.MagY, m.MagZ] for m in mags], float), rtol=RTOL, atol=0.0)
        assert_close(c.ofs_mgauss, np.array([[m.OfsX, m.OfsY, m.OfsZ] for m in mags], float), rtol=RTOL, atol=0.0)
    att = want["ATT"]
    assert_close(np.column_stack([s.roll_deg, s.pitch_deg, s.yaw_deg]),
                 np.array([[m.Roll, m.Pitch, m.Yaw] for m in att], float), rtol=RTOL, atol=0.0)
    bat = [m for m in want["BAT"] if getattr(m, "Inst", getattr(m, "Instance", 0)) == 0]
    if len(s.current_a):
        assert_close(s.current_a, np.array([m.Curr for m in bat], float), rtol=RTOL, atol=0.0)


@pytest.mark.skipif(not BINS, reason="real logs not available")
@pytest.mark.parametrize("name", BINS)
def test_flight_messages_equal_dfreader_on_real_logs(name):
    assert _same_as_dfreader(REAL / name) > 0
    _series_as_dfreader(REAL / name)


def test_flight_messages_equal_dfreader_on_a_synthetic_flight(tmp_path):
    s = synth_flight([SynthCompass(interference=(3.0, -2.0, 4.0)), SynthCompass()], seed=7)
    log = write_flight_bin(tmp_path / "flight.bin", s)
    assert _same_as_dfreader(log) > 1000
    _series_as_dfreader(log)
