"""The one-pass DataFlash decoder and the vectorised parameter timeline give exactly what the
two-pass decoder and the per-record rules give (issue 11: reading a .bin faster, outputs unchanged)."""
from __future__ import annotations

import re
import struct
from pathlib import Path

import numpy as np
import pytest

from mavcal.ardupilot import firmware as fw
from mavcal.sources.dataflash_assemble import DATAFLASH_MESSAGES, assemble_dataflash
from mavcal.sources.fast_dataflash import decode_dataflash
from mavcal.sources.param_columns import dataflash_params, decode_text, text_codes, timeline_from_codes
from mavcal.sources.reader import read_log
from mavcal.sources.types import ParamTimeline
from mavcal.testing.logwriters import DF_FORMATS, DataFlashWriter

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
needs_real = pytest.mark.skipif(not (REAL / "00000124.BIN").is_file(), reason="real logs not available")
G = 9.80665


def _same_decode(a, b) -> None:
    """Two decode_dataflash results are the same: columns (order, dtype, bytes), formats (order), stats."""
    (ca, fa, sa), (cb, fb, sb) = a, b
    assert list(ca) == list(cb)
    for name in ca:
        assert list(ca[name]) == list(cb[name])
        for k in ca[name]:
            x, y = ca[name][k], cb[name][k]
            assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes(), (name, k)
    assert list(fa.items()) == list(fb.items())
    assert vars(sa) == vars(sb)


def _fmt_record(type_id: int, name: str, fmt: str, columns: str) -> bytes:
    length = 3 + struct.calcsize("<" + "".join({"Q": "Q", "B": "B", "h": "h", "I": "I", "f": "f"}[c] for c in fmt))
    return b"\xa3\x95\x80" + struct.pack("<BB4s16s64s", type_id, length, name.encode(), fmt.encode(),
                                          columns.encode())


def _mag_record(time_us: int) -> bytes:
    type_id, fmt, _ = DF_FORMATS["MAG"]
    return b"\xa3\x95" + bytes([type_id]) + struct.pack("<QBhhhhhhhhhBI", time_us, 0, 200, 10, 400, 0, 0, 0, 0, 0, 0,
                                                         1, time_us // 1000)


def _imu_log(path: Path, n: int = 400) -> None:
    with DataFlashWriter(path) as w:
        for k in range(n):
            w.imu(1000 + 2500 * k, 0, (0.001 * k, 0, 0), (0.0, 0.0, -G))
            if k >= n // 2 and k % 4 == 0:
                w.mag(1000 + 2500 * k, 0, (200, 10, 400))


def test_late_format_with_an_earlier_candidate_reads_as_two_passes(tmp_path):
    """A MAG record hidden in garbage before the MAG FMT record: with the FMT records of the whole
    file (DFReader's rule) it is a record; the one pass must see that and give the same."""
    p = tmp_path / "late.bin"
    _imu_log(p)
    data = p.read_bytes()
    imu_len = 3 + struct.calcsize("<QBffffffIIfBBHH")
    first_imu = data.index(b"\xa3\x95" + bytes([DF_FORMATS["IMU"][0]]))
    cut = first_imu + 80 * imu_len  # a record boundary among the IMU records before the first MAG
    p.write_bytes(data[:cut] + b"\x00\x11" + _mag_record(999) + data[cut:])
    for chunk in (512, 4096, 1 << 21):
        two = decode_dataflash(str(p), ["IMU", "MAG"], chunk_size=chunk, one_pass=False)
        one = decode_dataflash(str(p), ["IMU", "MAG"], chunk_size=chunk)
        _same_decode(one, two)
        mag = one[0]["MAG"]["TimeUS"]
        assert mag[0] == 999 and len(mag) == 1 + 50  # the hidden record is one
        assert one[2].skipped_bytes == 2 and one[2].resyncs == 1


def test_records_before_their_format_are_read(tmp_path):
    """The MAG FMT record moved to the end of the file: every MAG record is still decoded."""
    p = tmp_path / "fmt_last.bin"
    _imu_log(p)
    data = p.read_bytes()
    fmt = _fmt_record(DF_FORMATS["MAG"][0], "MAG", DF_FORMATS["MAG"][1], DF_FORMATS["MAG"][2])
    assert data.count(fmt) == 1
    p.write_bytes(data.replace(fmt, b"") + fmt)
    for chunk in (300, 4096, 1 << 21):
        one = decode_dataflash(str(p), ["IMU", "MAG", "FMT"], chunk_size=chunk)
        _same_decode(one, decode_dataflash(str(p), ["IMU", "MAG", "FMT"], chunk_size=chunk, one_pass=False))
        assert len(one[0]["MAG"]["TimeUS"]) == 50 and len(one[0]["IMU"]["TimeUS"]) == 400
        assert list(one[0]) == ["FMT", "IMU", "MAG"]  # the order of the formats in the file


def _damaged(data: bytes, rng: np.random.Generator) -> list[bytes]:
    n = len(data)
    out = [data[: n // 3], data[: n - 41], data[:777] + data[n // 2:]]
    for _ in range(3):
        a = np.frombuffer(data, np.uint8).copy()
        idx = rng.integers(0, n, size=int(rng.integers(5, 400)))
        a[idx] = rng.integers(0, 256, size=len(idx))
        out.append(a.tobytes())
    a = np.frombuffer(data, np.uint8).copy()
    idx = rng.integers(0, min(n, 6000), size=150)  # the FMT records of the start
    a[idx] = rng.integers(0, 256, size=150)
    out.append(a.tobytes())
    out.append(data[: n // 2] + rng.integers(0, 256, 3000, dtype=np.uint8).tobytes() + data[n // 2:])
    return out


@pytest.mark.parametrize("chunk", [700, 7000, 1 << 21])
def test_one_pass_equals_two_passes_on_damaged_logs(tmp_path, chunk):
    src = tmp_path / "src.bin"
    _imu_log(src, 600)
    with DataFlashWriter(tmp_path / "p.bin") as w:
        for k in range(300):
            w.parm(k * 1000, f"P{k % 40}", float(k % 7))
            w.msg(k * 1000, "ArduSub V4.1.0 (abc)")
    datas = [src.read_bytes(), src.read_bytes() + (tmp_path / "p.bin").read_bytes()]
    if (REAL / "00000124.BIN").is_file():
        datas.append((REAL / "00000124.BIN").read_bytes()[:600_000])
    rng = np.random.default_rng(chunk)
    for i, data in enumerate(d for base in datas for d in [base] + _damaged(base, rng)):
        p = tmp_path / f"d{i}.bin"
        p.write_bytes(data)
        for names in (DATAFLASH_MESSAGES, ["FMT", "IMU", "PARM"]):
            _same_decode(decode_dataflash(str(p), names, chunk_size=chunk),
                         decode_dataflash(str(p), names, chunk_size=chunk, one_pass=False))


@needs_real
@pytest.mark.parametrize("name", ["00000124.BIN", "log171.bin", "00000-2021-12-02_13-34-15.bin", "test.BIN"])
def test_one_pass_equals_two_passes_on_real_logs(name):
    for chunk in (5000, 1 << 21):
        _same_decode(decode_dataflash(str(REAL / name), DATAFLASH_MESSAGES, chunk_size=chunk),
                     decode_dataflash(str(REAL / name), DATAFLASH_MESSAGES, chunk_size=chunk, one_pass=False))


def test_progress_never_goes_back_and_ends_at_the_size(tmp_path):
    p = tmp_path / "fmt_last.bin"
    _imu_log(p)
    data = p.read_bytes()
    fmt = _fmt_record(DF_FORMATS["MAG"][0], "MAG", DF_FORMATS["MAG"][1], DF_FORMATS["MAG"][2])
    p.write_bytes(data.replace(fmt, b"") + fmt)  # a second pass is needed
    seen: list[int] = []
    decode_dataflash(str(p), ["MAG"], chunk_size=1000, progress=lambda done, total: seen.append(done))
    assert seen == sorted(seen) and seen[-1] == p.stat().st_size and len(set(seen)) == len(seen)


# --------------------------------------------------------------------------- parameters
def _reference_timeline(names, times, values) -> ParamTimeline:
    """The per-record rule (the code the vectorised one replaced)."""
    if len(names) == 0:
        return ParamTimeline()
    names_arr = np.asarray(names, dtype=object)
    times = np.asarray(times, dtype=float)
    values = np.asarray(values, dtype=float)
    out = {}
    groups: dict[str, list[int]] = {}
    for i in np.argsort(times, kind="stable").tolist():
        groups.setdefault(names_arr[i], []).append(i)
    for name, idx in groups.items():
        if not name:
            continue
        t, v = times[idx], values[idx]
        keep = np.ones(len(v), dtype=bool)
        keep[1:] = ~((v[1:] == v[:-1]) | (np.isnan(v[1:]) & np.isnan(v[:-1])))
        out[name] = (t[keep], v[keep])
    return ParamTimeline(out)


def _same_timeline(a: ParamTimeline, b: ParamTimeline) -> None:
    assert list(a.changes) == list(b.changes)
    for k in a.changes:
        for x, y in zip(a.changes[k], b.changes[k]):
            assert x.dtype == y.dtype and x.flags.c_contiguous and y.flags.c_contiguous
            assert x.tobytes() == y.tobytes(), k


def _raw_names(rng: np.random.Generator, n: int) -> np.ndarray:
    pool = [b"COMPASS_OFS_X", b"INS_ACCOFFS_X", b"AHRS_ORIENTATION", b"A\0junk", b"A", b"", b"\xff\xfeBAD",
            b"COMPASS_ORIENT2", b"X" * 16, b"SPACE NAME", b"INS_ACCOFFS_X\0\x01"]
    return np.array([pool[i] for i in rng.integers(0, len(pool), n)], dtype="S16")


def test_text_codes_decode_every_element():
    rng = np.random.default_rng(1)
    raw = _raw_names(rng, 500)
    for arr in (raw, raw.astype(object), [decode_text(x) for x in raw], np.array([decode_text(x) for x in raw]),
                raw[:0]):
        codes, labels = text_codes(arr)
        assert [labels[c] for c in codes.tolist()] == [decode_text(x) for x in arr]
        assert len(set(labels)) == len(labels)


@pytest.mark.parametrize("seed", range(6))
def test_timeline_equals_the_per_record_rule(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(0, 400))
    raw = _raw_names(rng, n)
    times = np.round(rng.uniform(0, 20, n), 0 if seed % 2 else 3)  # ties when rounded to whole seconds
    times[rng.random(n) < 0.05] = np.nan
    values = rng.integers(0, 3, n).astype(float)
    values[rng.random(n) < 0.1] = np.nan
    values[rng.random(n) < 0.05] = -0.0
    codes, labels = text_codes(raw)
    _same_timeline(timeline_from_codes(codes, labels, times, values),
                   _reference_timeline([decode_text(x) for x in raw], times, values))


def _reference_params(pm, t, warns) -> ParamTimeline:
    names = [decode_text(x) for x in pm["Name"]]
    values = np.asarray(pm["Value"], dtype=float)
    ok = np.array([bool(re.match(r"^[A-Za-z0-9_]{1,16}$", n)) and fw.param_value_plausible(n, v)
                   for n, v in zip(names, values.tolist())], dtype=bool)
    ok &= np.isfinite(t)
    if not ok.all():
        bad = [f"{n}={v:g}" for n, v, k in zip(names, values.tolist(), ok.tolist()) if not k][:3]
        warns.append(f"skipped {int((~ok).sum())} PARM records with an impossible name or value "
                     f"({', '.join(bad)}): corrupt records")
    keep = np.flatnonzero(ok)
    return _reference_timeline([names[i] for i in keep.tolist()], t[keep], values[keep])


@pytest.mark.parametrize("seed", range(6))
def test_dataflash_params_equal_the_per_record_rule(seed):
    rng = np.random.default_rng(100 + seed)
    n = int(rng.integers(1, 600))
    values = rng.choice([0.0, 2.0, 6.0, 109.0, 101.0, 2.5, -1.0, np.nan, np.inf, 1e7], n)
    pm = {"Name": _raw_names(rng, n), "Value": values.astype(np.float32)}
    t = np.sort(rng.uniform(0, 50, n))
    t[rng.random(n) < 0.03] = np.nan
    w_new: list[str] = []
    w_ref: list[str] = []
    _same_timeline(dataflash_params(pm, t, w_new), _reference_params(pm, t, w_ref))
    assert w_new == w_ref


def test_impossible_rotation_is_skipped_once_per_record(tmp_path):
    with DataFlashWriter(tmp_path / "r.bin") as w:
        for k in range(30):
            w.parm(k * 1000, "AHRS_ORIENTATION", 109.0 if k % 3 == 0 else 2.0)
            w.imu(k * 1000 + 1, 0, (0, 0, 0), (0.0, 0.0, -G))
    lg = read_log(tmp_path / "r.bin")
    assert any(x.startswith("skipped 10 PARM records") and "AHRS_ORIENTATION=109" in x for x in lg.warnings)
    ts, vs = lg.params.changes["AHRS_ORIENTATION"]
    assert vs.tolist() == [2.0] and ts.tolist() == [0.001]


def test_integer_and_float_instance_columns_give_the_same_log(tmp_path):
    p = tmp_path / "i.bin"
    with DataFlashWriter(p) as w:
        for k in range(100):
            w.imu(1000 + 2500 * k, k % 2, (0.001 * k, 0, 0), (0.0, 0.0, -G))
            if k % 9 == 0:
                w.imu(1000 + 2500 * k, 7, (0, 0, 0), (0.0, 0.0, -G))  # no such IMU: skipped
            w.mag(1000 + 2500 * k, k % 3, (200, 10, 400))
    cols, _, stats = decode_dataflash(str(p), DATAFLASH_MESSAGES)
    assert cols["IMU"]["I"].dtype == np.uint8
    as_float = {n: {k: (v.astype(float) if k == "I" else v) for k, v in c.items()} for n, c in cols.items()}
    a, b = assemble_dataflash(cols, "x", stats.warnings()), assemble_dataflash(as_float, "x", stats.warnings())
    assert a.warnings == b.warnings and any("impossible instance number (7;" in x for x in a.warnings)
    assert [(s.sensor, s.instance, len(s)) for s in a.series] == [(s.sensor, s.instance, len(s)) for s in b.series]
    for s, r in zip(a.series, b.series):
        assert s.time_s.tobytes() == r.time_s.tobytes() and s.values.tobytes() == r.values.tobytes()
        assert list(s.extra) == list(r.extra)
        assert all(s.extra[k].tobytes() == r.extra[k].tobytes() for k in s.extra)
