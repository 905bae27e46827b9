"""Sliding-window statistics of a long series, a chunk of rows at a time (no full-length
temporaries, the values of the full-length expressions): running sums at given indices, the
largest per-axis standard deviation per window, the RMS rate per window, counts and sums per time
window, row norms, and which samples a set of windows covers. The still-interval detector
(:mod:`mavcal.segment`) decides stillness with them.
"""
from __future__ import annotations

import numpy as np

from mavcal.sources.types import SensorSeries

__all__ = ["CHUNK", "covered", "gyro_still", "norms", "prefix_at", "rolling_sd_max", "same_times", "window_sums"]

#: samples (and window starts) per step of the running sums and sliding-window statistics:
#: their temporaries stay small and cached instead of full-length copies of the series
CHUNK = 1 << 14


def prefix_at(x: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """The running sums ``P[idx]`` for sorted indices ``idx`` in [0, len(x)], where ``P[0] = 0`` and
    ``P[1:] = cumsum(x, axis=0)``, computed a chunk at a time (no full-length array), one axis
    per contiguous row: each sum continues sequentially (``x[b0] + carry``; IEEE addition
    commutes), so the values are those of one ``cumsum`` over all rows."""
    idx = np.asarray(idx, dtype=np.int64)
    x2 = x.reshape(len(x), -1)
    out = np.zeros((len(idx), x2.shape[1]))  # the prefix at index 0 is 0
    carry = None
    for b0 in range(0, len(x2), CHUNK):
        b1 = min(b0 + CHUNK, len(x2))
        lo, hi = np.searchsorted(idx, [b0, b1], side="right")
        if hi == len(idx) and lo == hi:
            break  # nothing asked beyond here
        c = np.array(x2[b0:b1].T, dtype=float, order="C")  # a copy, whatever the layout of x
        if carry is not None and c.shape[1]:
            c[:, 0] += carry
        np.cumsum(c, axis=1, out=c)
        out[lo:hi] = c[:, idx[lo:hi] - b0 - 1].T
        carry = c[:, -1].copy()
    return out.reshape((len(idx),) + x.shape[1:])


def rolling_sd_max(x: np.ndarray, w: int) -> np.ndarray:
    """Largest per-axis standard deviation of (n, d) ``x`` over the windows x[i:i+w], i = 0..n-w.

    The running sums of the rows and of their squares are built a chunk at a time, one axis per
    row of a buffer (contiguous: fast) that keeps the last ``w`` of the previous chunk ahead of
    it (the windows across the boundary); each sum continues sequentially (``x[b0] + carry``:
    IEEE addition commutes), so the sums are those of one ``cumsum`` over all rows. Every
    window's mean and variance use the full-length expressions (``s1 / w``,
    ``max(s2 / w - m * m, 0)``); the square root of the largest variance is the largest square
    root (it is monotonic and correctly rounded): the result is bit-identical."""
    n, d = x.shape
    out = np.empty(max(n - w + 1, 0))
    buf = np.empty((2 * d, w + min(CHUNK, n)))  # running sums [x | x*x] (per axis) at prefix indices base..
    buf[:, 0] = 0.0  # the prefix at index 0
    held = 1  # columns of buf before this chunk's (the prefixes b0 - held + 1 .. b0)
    for b0 in range(0, n, CHUNK):
        b1 = min(b0 + CHUNK, n)
        c = buf[:, held:held + b1 - b0]
        xt = x[b0:b1].T
        c[:d] = xt
        np.multiply(xt, xt, out=c[d:])
        if b0:
            c[:, 0] += buf[:, held - 1]
        np.cumsum(c, axis=1, out=c)
        base = b0 - held + 1  # prefix index of buf[:, 0]
        k0, k1 = max(b0 - w + 1, 0), b1 - w + 1  # window starts whose end lies in (b0, b1]
        if k1 > k0:
            sw = buf[:, k0 + w - base:k1 + w - base] - buf[:, k0 - base:k1 - base]
            sw /= w  # [m | s2 / w]
            var = sw[d:]
            var -= sw[:d] * sw[:d]
            np.maximum(var, 0.0, out=var)
            big = var[0]
            for j in range(1, d):
                np.maximum(big, var[j], out=big)
            np.sqrt(big, out=out[k0:k1])
        keep = min(w, held + b1 - b0)
        buf[:, :keep] = buf[:, held + b1 - b0 - keep:held + b1 - b0]
        held = keep
    return out


def covered(ok: np.ndarray, w: int, n: int) -> np.ndarray:
    """(n,) bool: sample i lies in some window [s, s + w) with ``ok[s]`` (difference array;
    ``len(ok) = n - w + 1``, so every window ends inside the samples)."""
    d = np.zeros(n + 1, dtype=np.int32 if w < 2**31 // 2 else np.int64)
    d[:len(ok)] += ok
    d[w:w + len(ok)] -= ok
    return np.cumsum(d[:n], out=d[:n]) > 0


def window_sums(t: np.ndarray, v: np.ndarray, t0: np.ndarray, t1: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Count, sum and sum of squares of the rows of ``v`` with ``t0 <= t <= t1`` (t sorted)."""
    c1 = np.vstack([np.zeros((1, v.shape[1])), np.cumsum(v, axis=0)])
    c2 = np.vstack([np.zeros((1, v.shape[1])), np.cumsum(v * v, axis=0)])
    i0 = np.searchsorted(t, t0, side="left")
    i1 = np.searchsorted(t, t1, side="right")
    return i1 - i0, c1[i1] - c1[i0], c2[i1] - c2[i0]


def gyro_still(tg: np.ndarray, vg: np.ndarray | SensorSeries, t0: np.ndarray, t1: np.ndarray, limit: float,
                w: int | None = None) -> np.ndarray:
    """Per window [t0, t1]: RMS gyro rate of the samples in it below ``limit`` (no sample: still).

    Chunked: the squared rates and their running sum are one value per sample; the windows
    are evaluated a chunk at a time (same expressions, bit-identical results). ``w``: the gyro
    samples are the reference's own times, strictly increasing, and the windows its ``w``-sample
    windows (a gyro in the accelerometer's message): window k holds samples k..k+w-1, which
    the sorted searches would find. ``vg``: the rates, or their series (whose values are then
    read a chunk at a time: a packed series computes only those)."""
    rows = vg.values_at if isinstance(vg, SensorSeries) else vg.__getitem__
    c1 = np.empty(len(vg) + 1)
    c1[0] = 0.0
    for i in range(0, len(vg), CHUNK):
        g = rows(slice(i, i + CHUNK))
        sq = np.sum(g * g, axis=1)
        if i:
            sq[0] += c1[i]
        np.cumsum(sq, out=c1[i + 1:i + 1 + len(sq)])
    out = np.empty(len(t0), dtype=bool)
    for k in range(0, len(t0), CHUNK):
        if w is not None:
            m = len(t0[k:k + CHUNK])
            ms = c1[k + w:k + w + m] - c1[k:k + m]
            ms /= w  # the count of every window
        else:
            i0 = np.searchsorted(tg, t0[k:k + CHUNK], side="left")
            i1 = np.searchsorted(tg, t1[k:k + CHUNK], side="right")
            cnt = i1 - i0
            ms = np.where(cnt > 0, (c1[i1] - c1[i0]) / np.maximum(cnt, 1), 0.0)
        out[k:k + CHUNK] = np.sqrt(ms, out=ms) < limit
    return out


def same_times(tg: np.ndarray, t: np.ndarray) -> bool:
    """``tg`` holds exactly the strictly increasing times ``t`` (no duplicate, no NaN)."""
    if len(tg) != len(t) or not (tg is t or np.array_equal(tg, t)):
        return False
    for i in range(0, len(t) - 1, CHUNK):  # chunked: no full-length temporary
        seg = t[i:i + CHUNK + 1]
        if not bool(np.all(seg[1:] > seg[:-1])):
            return False
    return True


def norms(a: np.ndarray) -> np.ndarray:
    """|a| per row (``np.linalg.norm(a, axis=1)``, a chunk of rows at a time)."""
    out = np.empty(len(a))
    for i in range(0, len(a), CHUNK):
        c = a[i:i + CHUNK]
        # what np.linalg.norm(c, axis=1) computes for real rows, without its conj() copy
        np.sqrt(np.add.reduce(c * c, axis=1), out=out[i:i + CHUNK])
    return out
