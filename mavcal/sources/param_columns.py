"""Parameter records (DataFlash PARM, MAVLink PARAM_VALUE) -> :class:`~mavcal.sources.types.ParamTimeline`.

A log holds the same few hundred parameter names thousands of times (every restart of the
logger, every copy of a log writes them all again), so the work is done per distinct name and
per distinct (name, value) pair and the records are grouped with sorts: no Python call per
record. The results are those of the per-record rules stated in each function.
"""
from __future__ import annotations

import re
from collections.abc import Mapping

import numpy as np

from mavcal.errors import SourceError
from mavcal.sources.types import ParamTimeline

__all__ = ["decode_text", "text_codes", "timeline_from_codes", "dataflash_params", "columns_named", "with_column",
           "bytewise_param_values"]

_PARAM_NAME_RE = re.compile(r"^[A-Za-z0-9_]{1,16}$")  # ArduPilot: up to 16 letters, digits, _


def decode_text(v) -> str:
    """A logged string: up to its first NUL, UTF-8 (undecodable bytes replaced)."""
    if isinstance(v, (bytes, bytearray, np.bytes_)):
        return bytes(v).split(b"\0", 1)[0].decode("utf-8", errors="replace")
    return str(v).split("\0", 1)[0]


def text_codes(raw) -> tuple[np.ndarray, list[str]]:
    """``(codes, labels)`` with ``labels[codes[i]] == decode_text(raw[i])`` for every element.

    Fixed-width byte or str arrays are reduced to their distinct elements first (one
    :func:`decode_text` per distinct element); other sequences are decoded one by one.
    """
    arr = np.asarray(raw)
    if arr.ndim == 1 and arr.dtype.kind in "SU":
        uniq, inv = np.unique(arr, return_inverse=True)
        texts = [decode_text(u) for u in uniq.tolist()]
        inv = inv.reshape(-1)
    else:
        texts = [decode_text(x) for x in raw]
        inv = np.arange(len(texts), dtype=np.int64)
    index: dict[str, int] = {}
    remap = np.array([index.setdefault(s, len(index)) for s in texts], dtype=np.int64)
    return remap[inv] if len(inv) else np.zeros(0, dtype=np.int64), list(index)


def timeline_from_codes(codes: np.ndarray, labels: list[str], times, values) -> ParamTimeline:
    """ParamTimeline of records ``(labels[codes[i]], times[i], values[i])``.

    Per name (empty names left out): its records in time order (a stable sort: ties keep the
    record order), keeping a record only where the value differs from the record before (NaN
    repeating NaN is no change). Names come in the order of their first record in time.
    """
    codes = np.asarray(codes, dtype=np.int64)
    if len(codes) == 0:
        return ParamTimeline()
    times = np.asarray(times, dtype=float)
    values = np.asarray(values, dtype=float)
    by_time = np.argsort(times, kind="stable")
    c = codes[by_time]
    g = np.argsort(c, kind="stable")  # by name, time order kept within each name
    cs = c[g]
    starts = np.flatnonzero(np.r_[True, cs[1:] != cs[:-1]])
    idx = by_time[g]
    t, v = times[idx], values[idx]
    keep = np.ones(len(v), dtype=bool)
    keep[1:] = ~((v[1:] == v[:-1]) | (np.isnan(v[1:]) & np.isnan(v[:-1])))
    keep[starts] = True
    t, v = t[keep], v[keep]
    kstart = (np.cumsum(keep) - 1)[starts]
    kend = np.r_[kstart[1:], len(t)]
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for k in np.argsort(g[starts]).tolist():  # first record in time of each name
        name = labels[int(cs[starts[k]])]
        if name:
            a, b = int(kstart[k]), int(kend[k])
            out[name] = (t[a:b].copy(), v[a:b].copy())
    return ParamTimeline(out)


def _plausible(codes: np.ndarray, labels: list[str], values: np.ndarray, candidates: np.ndarray) -> np.ndarray:
    """``param_value_plausible(labels[codes[i]], values[i])`` of ArduPilot's model for the records ``candidates``
    (False elsewhere), called once per distinct (name, value bits)."""
    out = np.zeros(len(codes), dtype=bool)
    if len(candidates) == 0:
        return out
    bits = np.ascontiguousarray(values[candidates]).view(np.int64)
    cc = codes[candidates]
    order = np.lexsort((bits, cc))
    bo, co = bits[order], cc[order]
    new = np.r_[True, (bo[1:] != bo[:-1]) | (co[1:] != co[:-1])]
    reps = candidates[order[new]]
    from mavcal.autopilot import model_named

    plausible = model_named("ArduPilot").param_value_plausible  # a DataFlash log is ArduPilot's
    verdict = np.array([plausible(labels[int(codes[i])], float(values[i])) for i in reps.tolist()],
                       dtype=bool)
    out[candidates[order]] = verdict[np.cumsum(new) - 1]
    return out


def columns_named(c: Mapping[str, np.ndarray]) -> str:
    """The column names of a DataFlash message as its FMT record gave them (printable, short)."""
    names = ",".join(k for k in c if not k.startswith("_"))
    return "'" + "".join(ch if ch.isprintable() else "?" for ch in names)[:60] + "'"


def with_column(c: Mapping[str, np.ndarray], column: str, message: str, warns: list[str]) -> Mapping[str, np.ndarray]:
    """``c`` (a DataFlash message's columns), or nothing with a warning when its format (FMT) names no
    ``column`` (a damaged FMT record: DataFlash has no checksum)."""
    if not c or column in c:
        return c
    warns.append(f"{message} records ignored: their format (FMT) is damaged (it names {columns_named(c)})")
    return {}


def dataflash_params(pm: Mapping[str, np.ndarray], t: np.ndarray, warns: list[str],
                     source: str = "the log") -> ParamTimeline:
    """PARM records -> ParamTimeline; records with an impossible value or name (a damaged
    log: DataFlash has no checksum) or a non-finite time are skipped and counted in ``warns``.

    A name is possible when it is 1 to 16 letters, digits or ``_``; a value when
    ArduPilot's model says so (``param_value_plausible``).
    """
    if not {"Name", "Value"} <= set(pm):  # the PARM format (FMT) record is damaged
        raise SourceError(f"{source}: damaged DataFlash log: the format (FMT) of its PARM records names no Name and "
                          f"Value columns (it names {columns_named(pm)}), so the parameters in force cannot be read")
    codes, labels = text_codes(pm["Name"])
    values = np.asarray(pm["Value"], dtype=float)
    name_ok = np.array([bool(_PARAM_NAME_RE.match(n)) for n in labels], dtype=bool)
    ok = _plausible(codes, labels, values, np.flatnonzero(name_ok[codes]))
    ok &= np.isfinite(t)
    if not ok.all():
        bad = [f"{labels[int(codes[i])]}={float(values[i]):g}" for i in np.flatnonzero(~ok)[:3].tolist()]
        warns.append(f"skipped {int((~ok).sum())} PARM records with an impossible name or value "
                     f"({', '.join(bad)}): corrupt records")
    keep = np.flatnonzero(ok)
    return timeline_from_codes(codes[keep], labels, t[keep], values[keep])


#: MAV_PARAM_TYPE of the integer types -> (numpy type of its bytes, bytes)
_INT_PARAM_TYPES = {1: (np.uint8, 1), 2: (np.int8, 1), 3: (np.uint16, 2), 4: (np.int16, 2), 5: (np.uint32, 4),
                    6: (np.int32, 4)}


def bytewise_param_values(values_f32: np.ndarray, param_types: np.ndarray) -> np.ndarray:
    """PARAM_VALUE values of a vehicle that sends integers bytewise (PX4): an integer type's value is
    the integer in the low bytes of the float field, reinterpreted; the others are the floats."""
    f = np.ascontiguousarray(values_f32, dtype="<f4")
    out = f.astype(float)
    bits = f.view("<u4")
    types = np.asarray(param_types).astype(int)
    for t, (dtype, n) in _INT_PARAM_TYPES.items():
        m = types == t
        if m.any():
            low = bits[m] & np.uint32((1 << (8 * n)) - 1)
            out[m] = low.astype({1: np.uint8, 2: np.uint16, 4: np.uint32}[n]).view(dtype).astype(float)
    return out
