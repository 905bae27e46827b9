"""Undo the bias of integer telemetry truncated toward zero.

ArduPilot casts RAW_IMU / SCALED_IMU{,2,3} readings to int16 (milli-g, mrad/s, mGauss) and
DataFlash MAG fields to int16 mGauss by truncation toward zero: every reading is biased
by up to one unit toward zero, about half a unit on average when the noise spans a unit or
more. Adding half a unit away from zero to every non-zero reading removes that bias (the
remaining error is a zero-mean quantisation error of +-0.5 unit). A tool that wants to beat
the onboard calibration (which works on float samples) must do this: at 1 mGauss the bias is
a 0.5 mGauss offset error on every axis.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from mavcal.core.constants import GRAVITY_MPS2
from mavcal.sources.framing import owned_map_of
from mavcal.sources.types import ImuLog, SensorSeries

# message -> sensor -> telemetry unit in the series' units
TRUNCATED_UNITS: dict[str, dict[str, float]] = {
    **{m: {"accel": GRAVITY_MPS2 / 1000.0, "gyro": 1e-3, "mag": 1.0}
       for m in ("RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3")},
    **{m: {"mag": 1.0} for m in ("MAG", "MAG2", "MAG3")},
}


def quantization_step(series: SensorSeries) -> float:
    """The integer step of the series' readings (0 for float data)."""
    return TRUNCATED_UNITS.get(series.message, {}).get(series.sensor, 0.0)


#: rows per step of the in-place untruncation (temporaries stay small and cached)
_CHUNK_ROWS = 1 << 16


def untruncate(series: SensorSeries) -> SensorSeries:
    """The series with half a unit added away from zero to every non-zero integer reading.

    A packed series (:class:`~mavcal.sources.types.PackedValues`) keeps its integers: only its
    half step is set (the values it computes are the same, bit for bit)."""
    q = quantization_step(series)
    if q == 0.0:
        return series
    p = series.packed
    if p is not None and not p.untruncated:
        return replace(series, values=p.with_half_step(0.5 * q))
    v = np.asarray(series.values)
    return replace(series, values=v + 0.5 * q * np.sign(v))


def _owner(a: np.ndarray) -> np.ndarray | None:
    """The array that owns ``a``'s memory when ``a`` covers all of it (a reshaped view or the
    array itself), else None (a slice or a view of foreign memory: not ours to write). A
    column decoded into an :class:`~mavcal.sources.framing.OwnedMap` counts as owned."""
    root = a
    while isinstance(root.base, np.ndarray):
        root = root.base
    # heap memory of its own, or a column the decoders grew in an anonymous map of their own
    mine = root.base is None or owned_map_of(root) is not None
    if not mine or not root.flags.c_contiguous or root.nbytes != a.nbytes:
        return None
    if root.__array_interface__["data"][0] != a.__array_interface__["data"][0] or root.dtype != np.float64:
        return None
    return root


def _untruncate_in_place(root: np.ndarray, q: float) -> None:
    """``root += 0.5 * q * sign(root)`` chunk by chunk: the same arithmetic as :func:`untruncate`
    (``(0.5 * q) * sign(v)`` added to ``v``), so the values are bit-identical, with no full-size
    temporary."""
    half = 0.5 * q
    was_writeable = root.flags.writeable
    root.setflags(write=True)
    try:
        flat = root.reshape(-1)
        tmp = np.empty(min(len(flat), _CHUNK_ROWS * 3))
        for i in range(0, len(flat), len(tmp)):
            v = flat[i:i + len(tmp)]
            t = tmp[:len(v)]
            np.sign(v, out=t)
            t *= half
            v += t
    finally:
        root.setflags(write=was_writeable)


def untruncate_log(log: ImuLog, *, in_place: bool = False) -> tuple[ImuLog, int]:
    """Apply :func:`untruncate` to every series of ``log``; returns (log, series changed).

    With ``in_place=True`` (for a log nobody else holds, e.g. one :func:`mavcal.pipeline.prepare`
    has just read) the values are changed in their own arrays, without a second copy of the
    series, and ``log`` itself is returned; a series whose values are a view of memory it does
    not own, or that another series shares, is copied as usual. A packed series (what the
    tlog reader gives) only has its half step set: in place, on the series itself. The
    values are bit-identical either way.
    """
    arrays = [[*([] if s.packed is not None else [s.values]), *s.extra.values()] for s in log.series]
    out, n = [], 0
    for k, s in enumerate(log.series):
        q = quantization_step(s)
        p = s.packed
        if p is not None and q != 0.0 and not p.untruncated:  # no value is rewritten
            if in_place:
                s.mark_untruncated(0.5 * q)
                out.append(s)
            else:
                out.append(untruncate(s))
            n += 1
            continue
        root = _owner(s.values) if (in_place and q != 0.0 and p is None) else None
        if root is not None and not any(np.may_share_memory(root, a) for j, arrs in enumerate(arrays)
                                        if j != k for a in arrs):
            _untruncate_in_place(root, q)
            out.append(s)
            n += 1
            continue
        t = untruncate(s)
        n += t is not s
        out.append(t)
    if in_place and all(a is b for a, b in zip(out, log.series)):
        return log, n
    return replace(log, series=tuple(out)), n
