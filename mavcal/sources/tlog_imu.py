"""Lean tlog reading: the integer IMU messages decoded straight into their final arrays.

:func:`decode_tlog_lean` frames and checks a tlog exactly as :func:`mavcal.sources.fast_tlog.decode_tlog`
does (same :func:`~mavcal.sources.fast_tlog.scan_tlog`), but RAW_IMU / SCALED_IMU / SCALED_IMU2
/ SCALED_IMU3 do not become message columns: each chunk's records are converted into the
arrays the sensor series keep (boot time and receive time in s, float64 with the arithmetic of
:mod:`mavcal.sources.assemble`; the accel, gyro and mag readings as the int16 integers sent, from
which the series compute their float values on access), grown in place
(:class:`~mavcal.sources.framing.GrowArray`). The time base (reboots, shifts, receive delays)
is built while reading, in frame order, so no frame number is kept per sample; the median
receive delay of each boot segment is selected afterwards from the stored times without a
full-length temporary (:func:`exact_median`). A chunk whose accel and gyro (or mag) are all
zero writes nothing (an IMU that is absent costs no memory), and the values of a SCALED_IMU
beside RAW_IMU are dropped as soon as RAW_IMU appears (they are not used). The peak memory of
a read is then the series themselves plus a few chunks.

The lean path assumes one system sends IMU messages (the usual case). When IMU messages of a
second system appear, it gives up (returns None) and the caller reads the log from columns,
which chooses the vehicle among them: the result is identical either way.
"""
from __future__ import annotations

import numpy as np

from mavcal.sources.assemble import IMU_MESSAGES, REBOOT_BACKSTEP_S, TLOG_MESSAGES
from mavcal.sources.decoded import DecodedImu, PreparedImu
from mavcal.sources.fast_tlog import DEFAULT_CHUNK, ColumnSink, TlogStats, scan_tlog, wanted_messages
from mavcal.sources.framing import GrowArray
from mavcal.sources.progress import ProgressFn

__all__ = ["decode_tlog_lean", "exact_median", "LEAN_MESSAGES"]

#: the messages decoded into final arrays (the others become columns)
LEAN_MESSAGES = ("RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3")
_ACC, _GYR, _MAG = ("xacc", "yacc", "zacc"), ("xgyro", "ygyro", "zgyro"), ("xmag", "ymag", "zmag")
_WINDOW = 1 << 16  # rows per step of the passes over stored times
_GATHER = 1 << 16  # values gathered at most to select a median from
_BINS = 1 << 14


class _NotLean(Exception):
    """IMU messages from more than one system: the vehicle is chosen from columns instead."""


class _LeanMessage:
    """The final arrays of one integer IMU message, filled chunk by chunk."""

    def __init__(self, time_field: str) -> None:
        self.time_field = time_field
        self.scale = 1e-3 if time_field == "time_boot_ms" else 1e-6
        self.t = GrowArray(np.float64)
        self.lt = GrowArray(np.float64)
        self.vals: dict[str, GrowArray] | None = {k: GrowArray(np.int16, (3,)) for k in ("acc", "gyr", "mag")}
        self.imu_zero = 0
        self.mag_zero = 0

    def take(self, rec: np.ndarray, ts_us: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Append the records; returns copies of their (boot, receive) times for the time base."""
        m = len(rec)
        t = self.t.extend(m)
        t[:] = rec[self.time_field]  # as np.asarray(col, float) * scale
        t *= self.scale
        lt = self.lt.extend(m)
        lt[:] = ts_us
        lt *= 1.0e-6
        times = (t.copy(), lt.copy())
        del t, lt
        imu = _nonzero_rows(rec, _ACC + _GYR)
        mag = _nonzero_rows(rec, _MAG)
        n_imu, n_mag = int(imu.sum()), int(mag.sum())
        self.imu_zero += m - n_imu
        self.mag_zero += m - n_mag
        if self.vals is not None:
            self._put("acc", rec, _ACC, m, n_imu)
            self._put("gyr", rec, _GYR, m, n_imu)
            self._put("mag", rec, _MAG, m, n_mag)
        return times

    def _put(self, key: str, rec: np.ndarray, names: tuple[str, ...], m: int, nonzero: int) -> None:
        """The int16 readings as sent (the series compute their units on access)."""
        assert self.vals is not None
        out = self.vals[key].extend(m)
        if nonzero:  # else the rows stay zero without being written (nor resident)
            for j, n in enumerate(names):
                out[:, j] = rec[n]

    def drop_values(self) -> None:
        self.vals = None

    def result(self, offsets: list[tuple[int, int, float]]) -> DecodedImu:
        t = self.t.array()
        for r0, r1, off in offsets:  # the shift of each later boot segment, in place
            t[r0:r1] += off
        v = {k: g.array() for k, g in self.vals.items()} if self.vals is not None else {}
        return DecodedImu(t, self.lt.array(), v.get("acc"), v.get("gyr"), v.get("mag"), self.imu_zero, self.mag_zero)


def _nonzero_rows(rec: np.ndarray, names: tuple[str, ...]) -> np.ndarray:
    out = rec[names[0]] != 0
    for n in names[1:]:
        out |= rec[n] != 0
    return out


class _Segment:
    """One boot segment of the time base: where it starts and the extremes of its times."""

    def __init__(self, frame: int, boot: float, logt: float, rows: np.ndarray) -> None:
        self.frame = frame
        self.boot_a, self.log_a = boot, logt
        self.boot_max, self.log_max = boot, logt
        self.rows = rows.copy()  # rows of each IMU message before the segment


class _BootStream:
    """Reboot detection in frame order over the IMU samples of all messages, chunk by chunk.

    The same rule as :func:`mavcal.sources.assemble._next_reboot`: a sample starts a new boot
    segment when its boot time is more than ``REBOOT_BACKSTEP_S`` below the largest boot
    time of the segment so far."""

    def __init__(self, n_messages: int) -> None:
        self.rows = np.zeros(n_messages, dtype=np.int64)
        self.segments: list[_Segment] = []
        self.runmax = 0.0
        self._parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, int]] = []

    def add(self, frame_no: np.ndarray, boot: np.ndarray, logt: np.ndarray, code: int) -> None:
        self._parts.append((frame_no, boot, logt, code))

    def flush(self) -> None:
        """Feed the samples added since the last flush (one chunk) in frame order."""
        if not self._parts:
            return
        parts, self._parts = self._parts, []
        frame = np.concatenate([p[0] for p in parts])
        order = np.argsort(frame, kind="stable")
        frame = frame[order]
        boot = np.concatenate([p[1] for p in parts])[order]
        logt = np.concatenate([p[2] for p in parts])[order]
        code = np.concatenate([np.full(len(p[0]), p[3], dtype=np.int64) for p in parts])[order]
        self._feed(frame, boot, logt, code)

    def _start(self, frame: np.ndarray, boot: np.ndarray, logt: np.ndarray, code: np.ndarray, j: int) -> None:
        rows = self.rows + np.bincount(code[:j], minlength=len(self.rows))
        self.segments.append(_Segment(int(frame[j]), boot[j], logt[j], rows))
        self.runmax = boot[j]

    def _feed(self, frame: np.ndarray, boot: np.ndarray, logt: np.ndarray, code: np.ndarray) -> None:
        n = len(boot)
        i = 0
        if not self.segments:
            self._start(frame, boot, logt, code, 0)
            i = 1
        w = 1024
        while i < n:
            seg = boot[i:min(n, i + w)]
            runmax = np.empty_like(seg)
            runmax[0] = self.runmax
            np.maximum(np.maximum.accumulate(seg[:-1]), self.runmax, out=runmax[1:])
            drop = np.flatnonzero(seg < runmax - REBOOT_BACKSTEP_S)
            j = i + (int(drop[0]) if len(drop) else len(seg))
            cur = self.segments[-1]
            if j > i:  # samples i..j-1 continue the current segment
                cur.boot_max = max(cur.boot_max, boot[i:j].max())
                cur.log_max = max(cur.log_max, logt[i:j].max())
                self.runmax = max(self.runmax, boot[i:j].max())
            if len(drop):
                self._start(frame, boot, logt, code, j)
                i = j + 1
                w = 1024
            else:
                i = j
                w = min(2 * w, 1 << 18)
        self.rows += np.bincount(code, minlength=len(self.rows))


class _LeanSink:
    """Sink of :func:`scan_tlog`: integer IMU messages into final arrays, the others into columns."""

    def __init__(self, wanted: dict) -> None:
        self.ids = {name: mid for mid, (name, _, _) in wanted.items()}
        self.columns = ColumnSink({mid: w for mid, w in wanted.items() if w[0] not in LEAN_MESSAGES})
        self.lean = {self.ids[n]: _LeanMessage("time_usec" if n == "RAW_IMU" else "time_boot_ms")
                     for n in LEAN_MESSAGES}
        self.code = {self.ids[n]: k for k, n in enumerate(IMU_MESSAGES)}
        self.stream = _BootStream(len(IMU_MESSAGES))
        self.sysid: int | None = None
        self.raw_imu_seen = False

    def take(self, mid: int, rec: np.ndarray, ts_us: np.ndarray, frame_no: np.ndarray, sysid: np.ndarray,
             compid: np.ndarray) -> None:
        code = self.code.get(mid)
        if code is None:
            self.columns.take(mid, rec, ts_us, frame_no, sysid, compid)
            return
        if self.sysid is None:
            self.sysid = int(sysid[0])
        if bool((sysid != self.sysid).any()):
            raise _NotLean
        lean = self.lean.get(mid)
        if lean is None:  # HIGHRES_IMU: columns, and its times for the time base
            self.columns.take(mid, rec, ts_us, frame_no, sysid, compid)
            boot, logt = np.asarray(rec["time_usec"], dtype=float) * 1e-6, ts_us.astype(np.float64) * 1.0e-6
        else:
            if mid == self.ids["RAW_IMU"] and not self.raw_imu_seen:
                self.raw_imu_seen = True  # SCALED_IMU is not used beside RAW_IMU: drop its values
                self.lean[self.ids["SCALED_IMU"]].drop_values()
            boot, logt = lean.take(rec, ts_us)
        self.stream.add(frame_no, boot, logt, code)

    def chunk_done(self) -> None:
        self.stream.flush()


def decode_tlog_lean(path: str, *, chunk_size: int = DEFAULT_CHUNK, progress: ProgressFn | None = None
                     ) -> tuple[dict[str, dict[str, np.ndarray]], PreparedImu | None, TlogStats] | None:
    """Decode the messages :func:`mavcal.sources.reader.read_log` needs from a tlog.

    Returns ``(columns, prepared, stats)`` for :func:`mavcal.sources.assemble.assemble_tlog`
    (``columns``: the messages other than the integer IMU ones; ``prepared`` None when the
    log has no IMU sample), or None when IMU messages come from more than one system (read
    the log with :func:`~mavcal.sources.fast_tlog.decode_tlog` then).
    """
    sink = _LeanSink(wanted_messages(TLOG_MESSAGES))
    try:
        stats = scan_tlog(path, wanted_messages(TLOG_MESSAGES), sink, chunk_size=chunk_size, progress=progress)
    except _NotLean:
        return None
    cols = sink.columns.columns()
    if sink.sysid is None:
        return cols, None, stats
    return cols, _prepare(sink, cols), stats


def _prepare(sink: _LeanSink, cols: dict[str, dict[str, np.ndarray]]) -> PreparedImu:
    """The time base's delays and shifts, the shifted times and the decoded messages."""
    segs = sink.stream.segments
    ends = [s.rows for s in segs[1:]] + [sink.stream.rows]
    bounds = [(s.rows, e) for s, e in zip(segs, ends)]  # rows of each message in each segment
    names = list(IMU_MESSAGES)
    lean = {n: sink.lean[sink.ids[n]] for n in LEAN_MESSAGES}
    hr = cols.pop("HIGHRES_IMU", {})
    if not len(hr.get("_index", ())):
        hr = {}
    hr_times = (np.asarray(hr["_log_time_s"], float), np.asarray(hr["time_usec"], dtype=float) * 1e-6) if hr else None

    def times(code: int) -> tuple[np.ndarray, np.ndarray] | None:  # (receive, boot) of all rows of a message
        if names[code] == "HIGHRES_IMU":
            return hr_times
        m = lean[names[code]]
        return (m.lt.rows(), m.t.rows()) if m.t.n else None

    delay = np.zeros(len(segs))
    for k, (r0, r1) in enumerate(bounds):
        parts = []
        for code in range(len(names)):
            tt = times(code) if r1[code] > r0[code] else None
            if tt is not None:
                parts.append((tt[0][r0[code]:r1[code]], tt[1][r0[code]:r1[code]]))
        delay[k] = exact_median(parts)
        del parts
    offset = np.zeros(len(segs))
    reboot_s = np.zeros(len(segs))
    prev_end_time = prev_end_log = 0.0
    for k, s in enumerate(segs):  # the arithmetic of assemble._TimeBase
        if k > 0:
            offset[k] = prev_end_time + (s.log_a - prev_end_log) - s.boot_a
            reboot_s[k] = float(np.nextafter(prev_end_time, np.inf))
        prev_end_time = float(s.boot_max + offset[k])
        prev_end_log = float(s.log_max)
    imu: dict[str, DecodedImu | dict[str, np.ndarray]] = {}
    for name, m in lean.items():
        if m.t.n:
            code = names.index(name)
            shifts = [(int(r0[code]), int(r1[code]), float(offset[k])) for k, (r0, r1) in enumerate(bounds)
                      if offset[k] != 0.0 and r1[code] > r0[code]]
            imu[name] = m.result(shifts)
    if hr:
        imu["HIGHRES_IMU"] = hr
    return PreparedImu(int(sink.sysid or 0), imu, np.array([s.frame for s in segs], dtype=np.int64), delay,
                       offset, reboot_s)


def _windows(parts: list[tuple[np.ndarray, np.ndarray]]):
    """``logt - boot`` of the parts, a window of rows at a time."""
    for lt, t in parts:
        for i in range(0, len(lt), _WINDOW):
            yield lt[i:i + _WINDOW] - t[i:i + _WINDOW]


def exact_median(parts: list[tuple[np.ndarray, np.ndarray]]) -> float:
    """``np.median(np.concatenate([a - b for a, b in parts]))``, bit for bit, without the concatenation.

    The middle order statistics are selected by counting (:func:`_kth`); for an even count
    the mean of the two, as numpy does.
    """
    n = sum(len(a) for a, _ in parts)
    if n <= _GATHER:
        return float(np.median(np.concatenate([a - b for a, b in parts]) if parts else np.zeros(0)))
    lo = min(float(d.min()) for d in _windows(parts))
    hi = max(float(d.max()) for d in _windows(parts))
    if not (np.isfinite(lo) and np.isfinite(hi)):  # NaN or inf: numpy's own handling
        return float(np.median(np.concatenate([a - b for a, b in parts])))
    v1 = _kth(parts, (n - 1) // 2, lo, hi)
    if n % 2:
        return v1
    # the next order statistic: v1 again if it repeats, else the smallest value above it
    at_most = sum(int(np.count_nonzero(d <= v1)) for d in _windows(parts))
    v2 = v1 if at_most > n // 2 else min(float(d[d > v1].min()) for d in _windows(parts) if (d > v1).any())
    return float(np.mean(np.array([v1, v2])))


def _kth(parts: list[tuple[np.ndarray, np.ndarray]], r: int, lo: float, hi: float) -> float:
    """The ``r``-th smallest (0-based) ``logt - boot`` of ``parts``, all of which lie in ``[lo, hi]``.

    A pass counts the values per bin of a monotonic binning of ``[lo, hi]`` (the values of
    the bins before a bin are exactly the smaller ones); the bin of rank ``r`` is gathered
    and partitioned, or, while it holds too many values, its range is binned again."""
    while lo < hi:
        scale = (_BINS - 1) / (hi - lo)
        if not np.isfinite(scale):
            break
        counts = np.zeros(_BINS + 2, dtype=np.int64)
        for d in _windows(parts):
            counts += np.bincount(_bins(d, lo, scale), minlength=_BINS + 2)
        cum = np.cumsum(counts)
        j = int(np.searchsorted(cum, r, side="right"))  # the bin of rank r
        first = int(cum[j - 1]) if j else 0
        sel = [d[_bins(d, lo, scale) == j] for d in _windows(parts)]
        if int(counts[j]) <= _GATHER:
            return float(np.partition(np.concatenate(sel), r - first)[r - first])
        lo_j = min(float(x.min()) for x in sel if len(x))
        hi_j = max(float(x.max()) for x in sel if len(x))
        del sel
        if (lo_j, hi_j) == (lo, hi):
            break
        lo, hi = lo_j, hi_j
    if lo == hi:
        return lo
    got = np.concatenate([d[(d >= lo) & (d <= hi)] for d in _windows(parts)])  # a few ulps apart
    below = sum(int(np.count_nonzero(d < lo)) for d in _windows(parts))
    return float(np.partition(got, r - below)[r - below])


def _bins(d: np.ndarray, lo: float, scale: float) -> np.ndarray:
    """A monotonic (non-decreasing) bin number of each value: 0 below ``lo``, then 1 ... ``_BINS + 1``."""
    x = np.subtract(d, lo)
    x *= scale
    np.clip(x, -1.0, _BINS, out=x)
    b = np.floor(x).astype(np.int64)
    b += 1
    return b
