"""Damaged logs never raise (issue 10, item 5): hypothesis mutates bundled and small real logs
(bit flips, truncation, splices, zeroed runs, inserted bytes) and runs them through
``mavcal segments`` and ``mavcal calibrate`` (``mavcal.cli.main``): a documented exit code,
one ``mavcal: error:`` line on error, never an exception. Bounded for the suite's speed; the
long run (>= 10,000 mutants in forked children) is ``benchmarks/fuzz_logs.py``."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from mavcal.cli import main  # noqa: E402
from mavcal.testing.damaged import error_line_problem  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
REAL = Path("/work/shared/data/real") if not (ROOT.parent / "shared" / "data" / "real").is_dir() \
    else ROOT.parent / "shared" / "data" / "real"
DOCUMENTED = {0, 2, 3, 4, 5, 6, 7}
PREFIX = 160_000  # bytes of a bundled SITL tlog: a few poses, so a run stays short


def _bases() -> dict[str, bytes]:
    out = {p.name: p.read_bytes()[:PREFIX] for p in sorted((ROOT / "sitl_logs").glob("*.tlog"))}
    for name in ("test.BIN", "00000-2021-12-02_13-34-15.bin", "flight.tlog"):
        if (REAL / name).is_file():
            out[name] = (REAL / name).read_bytes()
    if (REAL.parent / "px4" / "sample_px4_events.ulg").is_file():  # a PX4 ULog (pyulog, issue 35)
        out["sample_px4_events.ulg"] = (REAL.parent / "px4" / "sample_px4_events.ulg").read_bytes()
    return out


BASES = _bases()


@st.composite
def mutants(draw) -> tuple[str, bytes]:
    name = draw(st.sampled_from(sorted(BASES)))
    data = bytearray(BASES[name])
    n = len(data)
    kind = draw(st.sampled_from(["bitflip", "truncate", "splice", "zero", "insert"]))
    pos = draw(st.integers(0, n - 1))
    if kind == "bitflip":
        for p in [pos] + draw(st.lists(st.integers(0, n - 1), max_size=15)):
            data[p] ^= 1 << draw(st.integers(0, 7))
    elif kind == "truncate":
        del data[pos:]
    elif kind == "splice":
        src = draw(st.integers(0, n - 1))
        length = draw(st.integers(1, 4096))
        if draw(st.booleans()):
            del data[pos:pos + length]
        else:
            data[pos:pos] = data[src:src + length]
    elif kind == "zero":
        length = draw(st.sampled_from([1, 16, 256, 4096, 65536]))
        data[pos:pos + length] = bytes(len(data[pos:pos + length]))
    else:
        data[pos:pos] = draw(st.binary(min_size=1, max_size=64))
    return name, bytes(data)


def _check(argv: list[str], capsys) -> int:
    """Run the CLI: a documented exit code (an internal error, 70, is not one), and on error one
    ``mavcal: error:`` line that names no Python exception (issue 35)."""
    code = main(argv)  # an exception here fails the test: that is what is looked for
    err = capsys.readouterr().err
    assert code in DOCUMENTED, (code, err)
    problem = error_line_problem(code, err)
    assert problem is None, problem
    return code


@settings(max_examples=60, deadline=20_000, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                                 HealthCheck.data_too_large])
@given(mutants())
def test_mutated_logs_never_raise(tmp_path, capsys, mutant):
    name, data = mutant
    path = tmp_path / ("m" + Path(name).suffix)
    path.write_bytes(data)
    _check(["-q", "segments", str(path)], capsys)
    out = tmp_path / "r.json"
    out.unlink(missing_ok=True)
    code = _check(["-q", "calibrate", str(path), "--json", str(out)], capsys)
    if code in (0, 4, 7) and out.exists():  # read, then calibrated or refused: per-sensor verdicts
        doc = json.loads(out.read_text())
        assert doc["exit_code"] == code and isinstance(doc["sensors"], list)
