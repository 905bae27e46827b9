"""MAVLink message columns (a tlog, a live link) -> :class:`~mavcal.sources.types.ImuLog`: the one
assembly of MAVLink IMU data.

Shared by the tlog readers (:mod:`mavcal.sources.reader`: fast decoders and pymavlink) and the
live recorder (:mod:`mavcal.link.live`): all of them produce *columns* - per message type, a
dict of field name -> numpy array, plus ``_index`` (receive order), ``_log_time_s`` (receive
time, unix s), ``_sysid``, ``_compid`` - and this module turns them into sensor series, a
parameter timeline, events and vehicle facts. A DataFlash log's columns are assembled by
:mod:`mavcal.sources.dataflash_assemble`, the series of both by :mod:`mavcal.sources.series_set`.

Units and conventions (what goes into :class:`SensorSeries`)
------------------------------------------------------------
* RAW_IMU / SCALED_IMU / SCALED_IMU2 / SCALED_IMU3: accel milli-g x 9.80665/1000 -> m/s^2,
  gyro mrad/s / 1000 -> rad/s, mag mGauss. Instance 0/0/1/2. The series keep the int16
  readings (:class:`~mavcal.sources.types.PackedValues`, a quarter of the float64 memory) and
  compute those float64 values on access, bit for bit the same. RAW_IMU is preferred over
  SCALED_IMU for instance 0 (ArduPilot sends the same data in both). Samples whose accel
  and gyro are all exactly zero are dropped from accel/gyro (no IMU for that instance, e.g.
  SCALED_IMU2 on a single-IMU board); samples whose mag is all zero from mag (no compass).
* HIGHRES_IMU: float m/s^2, rad/s; mag is documented as gauss but ArduPilot before PR
  #32286 sent mGauss x 1000. Decided per log by the median field magnitude (> 100 "gauss"
  means the buggy unit) and converted to mGauss; the choice is stated in the warnings.
  Used for an instance only when no RAW_IMU/SCALED_IMU* carries it.

Time base of tlogs (and live captures)
--------------------------------------
``time_s`` is the vehicle's boot time from the message (time_usec / time_boot_ms);
``log_time_s`` is the tlog receive timestamp (unix s). A vehicle reboot shows up as the boot
time falling back by more than 2 s; each boot segment after the first is shifted so that
it continues from the end of the previous one by the elapsed log (wall) time: ``time_s``
stays monotonic, equals the boot time in the first segment, and the shift is reported in
the warnings. Messages without a boot time (PARAM_VALUE, STATUSTEXT, COMMAND_*) are mapped
from their receive time onto this time base with the median (receive - boot) delay of the
IMU messages of their segment.
"""
from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable, Mapping, Sequence

import numpy as np

from mavcal.autopilot.mavlink import (
    MAV_AUTOPILOT_PX4,
    MAV_CMD,
    MAV_CMD_ACCELCAL_VEHICLE_POS,
    MAV_CMD_SET_MESSAGE_INTERVAL,
)
from mavcal.core.constants import GRAVITY_MPS2
from mavcal.errors import SourceError
from mavcal.sources.decoded import DecodedImu, PreparedImu
from mavcal.sources.param_columns import (
    bytewise_param_values,
    text_codes,
    timeline_from_codes,
)
from mavcal.sources.param_columns import decode_text as _text
from mavcal.sources.series_set import FIRMWARE_RE, Columns, SeriesSet, column_matrix, n_rows, take_rows
from mavcal.sources.types import ImuLog, LogEvent, PackedValues, ParamTimeline, SensorSeries

__all__ = ["assemble_tlog", "imu_series", "IMU_MESSAGES", "TLOG_MESSAGES", "SCALED_INSTANCE", "CALIBRATION_COMMANDS",
           "MG_TO_MS2", "REBOOT_BACKSTEP_S"]

log = logging.getLogger(__name__)

G0 = GRAVITY_MPS2
MG_TO_MS2 = G0 / 1000.0

#: MAVLink commands kept as LogEvents (calibration related): number -> name
CALIBRATION_COMMANDS: dict[int, str] = {num: name for name, num in MAV_CMD.items()
                                        if num != MAV_CMD_SET_MESSAGE_INTERVAL}
#: MAV_AUTOPILOT_INVALID: the autopilot field of a ground station's HEARTBEAT
MAV_AUTOPILOT_INVALID = 8

IMU_MESSAGES = ("RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3", "HIGHRES_IMU")
TLOG_MESSAGES = IMU_MESSAGES + ("PARAM_VALUE", "STATUSTEXT", "COMMAND_LONG", "COMMAND_INT", "COMMAND_ACK",
                                "GPS_RAW_INT", "GLOBAL_POSITION_INT", "HOME_POSITION", "HEARTBEAT")
#: IMU instance carried by each integer IMU message
SCALED_INSTANCE = {"RAW_IMU": 0, "SCALED_IMU": 0, "SCALED_IMU2": 1, "SCALED_IMU3": 2}
PARAM_COMPONENTS = (1, 190)
REBOOT_BACKSTEP_S = 2.0
HIGHRES_BUG_THRESHOLD = 100.0  # median |mag| in "gauss" above which the mGauss*1000 bug is assumed

#: the float arithmetic of each integer IMU reading (value = count * mul / div): milli-g x
#: 9.80665/1000 -> m/s^2, mrad/s / 1000 -> rad/s, mGauss as sent
_INT_UNITS = {"accel": (MG_TO_MS2, 1.0), "gyro": (1.0, 1000.0), "mag": (1.0, 1.0)}
_INT16 = np.iinfo(np.int16)


def _packed(sensor: str, counts: np.ndarray) -> PackedValues:
    """Integer readings of ``sensor`` as the values of a series (computed on access, bit for bit
    what ``counts`` cast to float64, times ``MG_TO_MS2`` (accel) or divided by 1000 (gyro) gives)."""
    mul, div = _INT_UNITS[sensor]
    return PackedValues(counts, mul, div)


# --------------------------------------------------------------------------- helpers
def _any_nonzero(c: Mapping[str, np.ndarray], names: Sequence[str]) -> np.ndarray:
    """Per row: is any of the columns ``names`` non-zero."""
    out = np.asarray(c[names[0]]) != 0
    for n in names[1:]:
        out |= np.asarray(c[n]) != 0
    return out


# --------------------------------------------------------------------------- tlog assembly
def _boot_time(name: str, c: Mapping[str, np.ndarray]) -> np.ndarray:
    if "time_boot_ms" in c:
        return np.asarray(c["time_boot_ms"], dtype=float) * 1e-3
    return np.asarray(c["time_usec"], dtype=float) * 1e-6


def _next_reboot(boot: np.ndarray, i0: int) -> int | None:
    """First ``i > i0`` with ``boot[i] < max(boot[i0:i]) - REBOOT_BACKSTEP_S``, else None.

    Scans windows of doubling length (up to 2**18 samples, which bounds the temporaries), so
    that finding k reboots costs about the length of the log rather than k times it.
    """
    n = len(boot)
    i = i0 + 1
    prior = boot[i0]
    w = 4096
    while i < n:
        seg = boot[i:min(n, i + w)]
        runmax = np.empty_like(seg)
        runmax[0] = prior
        np.maximum(np.maximum.accumulate(seg[:-1]), prior, out=runmax[1:])
        drop = np.flatnonzero(seg < runmax - REBOOT_BACKSTEP_S)
        if len(drop):
            return i + int(drop[0])
        prior = max(prior, seg.max())
        i += len(seg)
        w = min(2 * w, 1 << 18)  # long enough to be linear, short enough for small temporaries
    return None


class _TimeBase:
    """Maps boot times and log times of a tlog onto one monotonic time base (see module doc)."""

    def __init__(self, index: np.ndarray, boot: Callable[[], np.ndarray], logt: Callable[[], np.ndarray]) -> None:
        """``index`` the frame order of every IMU sample; ``boot()`` / ``logt()`` build their boot
        and log times in the same order (built one at a time, so that no more than two
        full-length temporaries live beside the columns)."""
        order = np.argsort(index, kind="stable")
        boot_s = boot()[order]
        logt_s = logt()[order]
        boot, logt = boot_s, logt_s
        starts = [0]
        nxt = _next_reboot(boot, 0)
        while nxt is not None:
            starts.append(nxt)
            nxt = _next_reboot(boot, nxt)
        bounds = starts + [len(boot)]
        self.seg_index = index[order[starts]].astype(np.int64)
        del order
        self.delay = np.zeros(len(starts))
        self.offset = np.zeros(len(starts))
        self.reboot_s = np.zeros(len(starts))  # just after the last IMU message of the boot before
        prev_end_time = None
        prev_end_log = None
        for k in range(len(starts)):
            a, b = bounds[k], bounds[k + 1]
            log_a, log_max = logt[a], float(logt[a:b].max())
            # the median of (log - boot) over the segment, computed in the segment's own log
            # times (not needed afterwards): no full-length temporary
            np.subtract(logt[a:b], boot[a:b], out=logt[a:b])
            self.delay[k] = float(np.median(logt[a:b], overwrite_input=True))
            if k > 0:
                self.offset[k] = prev_end_time + (log_a - prev_end_log) - boot[a]
                self.reboot_s[k] = float(np.nextafter(prev_end_time, np.inf))
            # max(boot + offset) = max(boot) + offset: rounding is monotonic
            prev_end_time = float(boot[a:b].max() + self.offset[k])
            prev_end_log = log_max
        self.reboots = len(starts) - 1

    @classmethod
    def from_segments(cls, p: PreparedImu) -> _TimeBase:
        """The time base a decoder built while reading (:class:`PreparedImu`)."""
        tb = cls.__new__(cls)
        tb.seg_index, tb.delay, tb.offset, tb.reboot_s = p.seg_index, p.delay, p.offset, p.reboot_s
        tb.reboots = len(p.seg_index) - 1
        return tb

    def segment(self, index: np.ndarray) -> np.ndarray:
        return np.clip(np.searchsorted(self.seg_index, index, side="right") - 1, 0, len(self.seg_index) - 1)

    def from_boot(self, index: np.ndarray, boot: np.ndarray) -> np.ndarray:
        return boot + self.offset[self.segment(index)]

    def from_log(self, index: np.ndarray, logt: np.ndarray) -> np.ndarray:
        k = self.segment(index)
        return np.asarray(logt, dtype=float) - self.delay[k] + self.offset[k]


_TIME_COLUMNS = ("_index", "_log_time_s", "time_boot_ms", "time_usec")


def _tlog_vehicle_imu(cols: Columns, source: str, warns: list[str]) -> tuple[int, Columns]:
    """The vehicle's system id (most IMU messages) and its IMU message columns."""
    present = {n: cols[n] for n in IMU_MESSAGES if n_rows(cols.get(n))}
    if not present:
        raise SourceError(f"no IMU messages (RAW_IMU, SCALED_IMU*, HIGHRES_IMU) in {source}")
    sys_counts: Counter = Counter()
    for c in present.values():
        ids, cnt = np.unique(np.asarray(c["_sysid"]), return_counts=True)
        for i, n in zip(ids.tolist(), cnt.tolist()):
            sys_counts[i] += n
    sysid = sys_counts.most_common(1)[0][0]
    other = sum(n for s, n in sys_counts.items() if s != sysid)
    if other:
        warns.append(f"ignored {other} IMU messages from other systems than sysid {sysid}")
    imu: Columns = {}
    for n, c in present.items():
        m = np.asarray(c["_sysid"]) == sysid
        if n == "SCALED_IMU" and "RAW_IMU" in imu and m.any():
            # not used (RAW_IMU carries instance 0): keep only what the time base needs, release the rest
            times = {k: v for k, v in c.items() if k in _TIME_COLUMNS}
            imu[n] = times if m.all() else take_rows(times, m)
            if isinstance(cols, dict):
                del cols[n]
        elif m.all():
            imu[n] = c  # the vehicle's alone: no copy
        elif m.any():
            imu[n] = take_rows(c, m)
    return sysid, imu


def _integer_imu_series(imu: Mapping[str, DecodedImu | Mapping[str, np.ndarray]], tb: _TimeBase, out: SeriesSet,
                        consumed: Callable[[str], None]) -> None:
    """RAW_IMU / SCALED_IMU / SCALED_IMU2 / SCALED_IMU3 -> accel, gyro, mag series.

    Each message's columns are released (``consumed(name)``) once its series are built, and
    no copy is made of what every row keeps (the usual case): the peak memory stays near
    the columns plus the series, not several full-size temporaries more."""
    for name in ("RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3"):
        c = imu.get(name)
        if c is None:
            continue
        unused = c.accel_mg is None if isinstance(c, DecodedImu) else "xacc" not in c
        if unused:  # SCALED_IMU beside RAW_IMU: its time columns alone (_tlog_vehicle_imu)
            # expected of every ArduPilot tlog (both stream instance 0): said under -v only
            log.info("SCALED_IMU not used: RAW_IMU carries the same instance 0")
            consumed(name)
            continue
        inst = SCALED_INSTANCE[name]
        if isinstance(c, DecodedImu):
            _decoded_imu_series(name, inst, c, out)
            consumed(name)
            continue
        t = tb.from_boot(c["_index"], _boot_time(name, c))
        lt = np.asarray(c["_log_time_s"], float)
        # zero tests on the integer fields (same result as on the float copies, cheaper)
        has_imu = _any_nonzero(c, ("xacc", "yacc", "zacc", "xgyro", "ygyro", "zgyro"))
        has_mag = _any_nonzero(c, ("xmag", "ymag", "zmag"))
        nz = int((~has_imu).sum())
        _zero_imu_warning(out, name, inst, nz, len(t))
        if nz < len(t):
            keep = slice(None) if not nz else has_imu
            out.add("accel", inst, name, t[keep], _int_values(c, "accel", ("xacc", "yacc", "zacc"), keep), lt[keep])
            out.add("gyro", inst, name, t[keep], _int_values(c, "gyro", ("xgyro", "ygyro", "zgyro"), keep), lt[keep])
        keep = slice(None) if has_mag.all() else has_mag
        out.add("mag", inst, name, t[keep], _int_values(c, "mag", ("xmag", "ymag", "zmag"), keep), lt[keep])
        del c
        consumed(name)


def _int_values(c: Mapping[str, np.ndarray], sensor: str, names: Sequence[str], keep) -> np.ndarray | PackedValues:
    """The rows ``keep`` of an integer IMU reading's columns: packed when they hold int16 integers
    (what MAVLink sends), else (a reader that gave other numbers) float64 with the same arithmetic."""
    cols = [np.asarray(c[n]) for n in names]
    if all(a.dtype.kind in "iu" for a in cols) and all(
            not len(a) or (int(a.min()) >= _INT16.min and int(a.max()) <= _INT16.max) for a in cols):
        counts = np.empty((len(cols[0]), 3), dtype=np.int16)
        for j, a in enumerate(cols):
            counts[:, j] = a
        return _packed(sensor, counts[keep])
    v = column_matrix(c, names)[keep]
    mul, div = _INT_UNITS[sensor]
    if mul != 1.0:
        v *= mul
    if div != 1.0:
        v /= div
    return v


def _zero_imu_warning(out: SeriesSet, name: str, inst: int, nz: int, n: int) -> None:
    if nz and nz < n:
        out.warns.append(f"dropped {nz} {name} samples with all-zero accel and gyro")
    elif nz:  # no such IMU: the message is streamed for its compass (SITL's SCALED_IMU3): nothing wrong
        log.info("%s: accel and gyro are all zero (no IMU %d); used its mag only", name, inst + 1)


def _rows_nonzero(*arrays: np.ndarray) -> np.ndarray:
    out = (arrays[0] != 0).any(axis=1)
    for a in arrays[1:]:
        out |= (a != 0).any(axis=1)
    return out


def _decoded_imu_series(name: str, inst: int, c: DecodedImu, out: SeriesSet) -> None:
    """The series of a message decoded into its final arrays (same rules as from columns)."""
    t, lt, n = c.time_s, c.log_time_s, len(c.time_s)
    assert c.accel_mg is not None and c.gyro_mrads is not None and c.mag_mgauss is not None
    nz = c.imu_zero_rows
    _zero_imu_warning(out, name, inst, nz, n)
    if nz < n:
        keep = slice(None) if not nz else _rows_nonzero(c.accel_mg, c.gyro_mrads)
        out.add("accel", inst, name, t[keep], _packed("accel", c.accel_mg[keep]), lt[keep])
        out.add("gyro", inst, name, t[keep], _packed("gyro", c.gyro_mrads[keep]), lt[keep])
    keep_m = slice(None) if not c.mag_zero_rows else _rows_nonzero(c.mag_mgauss)
    out.add("mag", inst, name, t[keep_m], _packed("mag", c.mag_mgauss[keep_m]), lt[keep_m])


def _highres_imu_series(c: Mapping[str, np.ndarray], tb: _TimeBase, out: SeriesSet) -> None:
    """HIGHRES_IMU -> series of the instances no integer IMU message carries (mag unit decided here)."""
    t = tb.from_boot(c["_index"], _boot_time("HIGHRES_IMU", c))
    lt = np.asarray(c["_log_time_s"], float)
    inst_arr = np.asarray(c.get("id", np.zeros(len(t))), dtype=int)
    mag = column_matrix(c, ("xmag", "ymag", "zmag"))
    norm = np.linalg.norm(mag, axis=1)
    med = float(np.median(norm[norm > 0])) if (norm > 0).any() else 0.0
    if med > HIGHRES_BUG_THRESHOLD:
        mag_mg = mag / 1000.0
        out.warns.append(f"HIGHRES_IMU mag is in mGauss*1000 (ArduPilot bug before PR #32286; median |mag| "
                         f"{med:.0f}); converted to mGauss")
    else:
        mag_mg = mag * 1000.0
        if med > 0:
            out.warns.append(f"HIGHRES_IMU mag is in gauss (median |mag| {med:.3f}); converted to mGauss")
    for inst in np.unique(inst_arr).tolist():
        m = inst_arr == inst
        for sensor, v in (("accel", column_matrix(c, ("xacc", "yacc", "zacc"))),
                          ("gyro", column_matrix(c, ("xgyro", "ygyro", "zgyro"))), ("mag", mag_mg)):
            if out.has(sensor, inst):
                continue
            mm = m & ~(v == 0).all(axis=1) & np.isfinite(v).all(axis=1)
            out.add(sensor, inst, "HIGHRES_IMU", t[mm], v[mm], lt[mm])


def _is_px4(cols: Columns, sysid: int) -> bool:
    hb = cols.get("HEARTBEAT") or {}
    return bool(n_rows(hb)) and bool(((np.asarray(hb["_sysid"]) == sysid)
                                  & (np.asarray(hb["autopilot"]) == MAV_AUTOPILOT_PX4)).any())


def _tlog_params(cols: Columns, sysid: int, tb: _TimeBase, warns: list[str]) -> ParamTimeline:
    """PARAM_VALUE of the vehicle (autopilot or companion component) as a timeline (a PX4's
    integers decoded bytewise, :func:`bytewise_param_values`)."""
    pv = cols.get("PARAM_VALUE") or {}
    if not n_rows(pv):
        return ParamTimeline()
    m = (np.asarray(pv["_sysid"]) == sysid) & np.isin(np.asarray(pv["_compid"]), PARAM_COMPONENTS)
    if (~m).sum():
        warns.append(f"ignored {int((~m).sum())} PARAM_VALUE from other systems/components")
    pv = take_rows(pv, m)
    if not n_rows(pv):
        return ParamTimeline()
    codes, labels = text_codes(pv["param_id"])
    times = tb.from_log(np.asarray(pv["_index"], np.int64), pv["_log_time_s"])
    values = np.asarray(pv["param_value"], dtype=np.float32)
    if _is_px4(cols, sysid) and "param_type" in pv:
        return timeline_from_codes(codes, labels, times, bytewise_param_values(values, pv["param_type"]))
    return timeline_from_codes(codes, labels, times, values.astype(float))


def _tlog_events(cols: Columns, sysid: int, tb: _TimeBase) -> tuple[list[LogEvent], str | None]:
    """STATUSTEXT and calibration COMMAND_LONG/INT/ACK as events (time order), and the firmware banner."""
    events: list[LogEvent] = []
    firmware = None
    st = cols.get("STATUSTEXT") or {}
    if n_rows(st):
        st = take_rows(st, np.asarray(st["_sysid"]) == sysid)
        times = tb.from_log(np.asarray(st["_index"], np.int64), st["_log_time_s"])
        for t, text, sev in zip(times.tolist(), st["text"], np.asarray(st["severity"]).tolist()):
            txt = _text(text)
            events.append(LogEvent(float(t), "statustext", txt, int(sev)))
            if firmware is None and FIRMWARE_RE.match(txt):
                firmware = txt
    for name in ("COMMAND_LONG", "COMMAND_INT"):
        cm = cols.get(name) or {}
        if not n_rows(cm):
            continue
        cm = take_rows(cm, np.isin(np.asarray(cm["command"]).astype(int), list(CALIBRATION_COMMANDS)))
        times = tb.from_log(np.asarray(cm["_index"], np.int64), cm["_log_time_s"])
        pnames = (["param1", "param2", "param3", "param4", "param5", "param6", "param7"] if name == "COMMAND_LONG"
                  else ["param1", "param2", "param3", "param4", "x", "y", "z"])
        pv_arr = column_matrix(cm, pnames) if n_rows(cm) else np.zeros((0, 7))
        for t, code, p in zip(times.tolist(), np.asarray(cm["command"]).astype(int).tolist(), pv_arr.tolist()):
            kind = "accelcal_pos" if code == MAV_CMD_ACCELCAL_VEHICLE_POS else "command"
            events.append(LogEvent(float(t), kind, CALIBRATION_COMMANDS[code], code, tuple(float(x) for x in p)))
    ack = cols.get("COMMAND_ACK") or {}
    if n_rows(ack):
        ack = take_rows(ack, np.isin(np.asarray(ack["command"]).astype(int), list(CALIBRATION_COMMANDS)))
        times = tb.from_log(np.asarray(ack["_index"], np.int64), ack["_log_time_s"])
        for t, code, res in zip(times.tolist(), np.asarray(ack["command"]).astype(int).tolist(),
                                np.asarray(ack["result"]).astype(float).tolist()):
            events.append(LogEvent(float(t), "command_ack", CALIBRATION_COMMANDS[code], code, (res,)))
    events += [LogEvent(float(t), "reboot", "vehicle reboot") for t in tb.reboot_s[1:]]
    events.sort(key=lambda e: e.time_s)
    return events, firmware


def _tlog_vehicle(cols: Columns, sysid: int, firmware: str | None) -> dict[str, object]:
    """sysid, autopilot and vehicle type (most common vehicle HEARTBEAT) and the firmware banner."""
    vehicle: dict[str, object] = {"sysid": int(sysid)}
    hb = cols.get("HEARTBEAT") or {}
    if n_rows(hb):
        m = (np.asarray(hb["_sysid"]) == sysid) & (np.asarray(hb["autopilot"]) != MAV_AUTOPILOT_INVALID)
        if m.any():
            ci = Counter(zip(np.asarray(hb["autopilot"])[m].tolist(), np.asarray(hb["type"])[m].tolist()))
            (ap, vt), _ = ci.most_common(1)[0]
            vehicle["autopilot"] = int(ap)
            vehicle["vehicle_type"] = int(vt)
    if firmware:
        vehicle["firmware"] = firmware
    return vehicle


def assemble_tlog(cols: Columns, source: str, warnings: Sequence[str] = (),
                  prepared: PreparedImu | None = None) -> ImuLog:
    """Build an ImuLog from tlog message columns (fast decoder, pymavlink or a live recording).

    ``cols[name]`` holds the message fields plus ``_log_time_s``, ``_index`` (frame order),
    ``_sysid``, ``_compid``. ``cols`` is consumed: the columns of the integer IMU messages
    are removed from it as soon as their series are built (that is what keeps a long log's
    peak memory near the size of its series); pass a copy to keep them. ``prepared``: the
    vehicle's IMU messages and time base decoded by :mod:`mavcal.sources.tlog_imu` (then
    ``cols`` holds the other messages).
    """
    warns = list(warnings)
    imu: dict[str, DecodedImu | Mapping[str, np.ndarray]]
    if prepared is None:
        sysid, imu_cols = _tlog_vehicle_imu(cols, source, warns)
        imu = dict(imu_cols)
        # time base from all IMU messages of the vehicle
        tb = _TimeBase(np.concatenate([imu_cols[n]["_index"] for n in imu_cols]).astype(np.int64, copy=False),
                       lambda: np.concatenate([_boot_time(n, imu_cols[n]) for n in imu_cols]),
                       lambda: np.concatenate([np.asarray(imu_cols[n]["_log_time_s"], float) for n in imu_cols]))
        del imu_cols
    else:
        sysid, imu, tb = prepared.sysid, dict(prepared.imu), _TimeBase.from_segments(prepared)
    if tb.reboots:
        shifts = [f"{o:+.3f}" for o in tb.offset[1:]]
        shown = ", ".join(shifts[:3]) + (f" ... ({len(shifts) - 3} more)" if len(shifts) > 3 else "")
        warns.append(f"vehicle rebooted {tb.reboots} time(s) during the log; time_s of later boots is "
                     f"shifted by {shown} s to continue the log time")
    out = SeriesSet(warns)

    def consumed(name: str) -> None:  # release a message's columns once its series are built
        imu.pop(name, None)
        if isinstance(cols, dict) and name in cols:
            del cols[name]

    _integer_imu_series(imu, tb, out, consumed)
    hr = imu.get("HIGHRES_IMU")
    if hr is not None and not isinstance(hr, DecodedImu):
        _highres_imu_series(hr, tb, out)
    if not out.series:
        raise SourceError(f"no usable IMU samples in {source} (all IMU messages are empty)")
    params = _tlog_params(cols, sysid, tb, warns)
    events, firmware = _tlog_events(cols, sysid, tb)
    return ImuLog(source=source, kind="tlog", series=out.sorted(), params=params, events=tuple(events),
                  position=_tlog_position(cols, sysid), vehicle=_tlog_vehicle(cols, sysid, firmware),
                  warnings=tuple(warns))


def _median_position(c: Mapping[str, np.ndarray], m: np.ndarray, lat: str, lon: str, alt: str,
                     scale: tuple[float, float]) -> tuple[float, float, float]:
    """Median of the rows ``m`` of ``lat``/``lon``/``alt``, scaled to deg, deg, m by ``scale`` (deg, m)."""
    return (float(np.median(np.asarray(c[lat])[m])) * scale[0], float(np.median(np.asarray(c[lon])[m])) * scale[0],
            float(np.median(np.asarray(c[alt])[m])) * scale[1])


def _tlog_position(cols: Columns, sysid: int) -> tuple[float, float, float] | None:
    """HOME_POSITION (last), else the median GPS_RAW_INT with a 3D fix, else the median GLOBAL_POSITION_INT."""
    hp = cols.get("HOME_POSITION") or {}
    if n_rows(hp):
        m = (np.asarray(hp["_sysid"]) == sysid) & ((np.asarray(hp["latitude"]) != 0)
                                                   | (np.asarray(hp["longitude"]) != 0))
        if m.any():
            i = np.flatnonzero(m)[-1]
            return (float(hp["latitude"][i]) * 1e-7, float(hp["longitude"][i]) * 1e-7, float(hp["altitude"][i]) * 1e-3)
    gps = cols.get("GPS_RAW_INT") or {}
    if n_rows(gps):
        m = (np.asarray(gps["_sysid"]) == sysid) & (np.asarray(gps["fix_type"]) >= 3)
        if m.any():
            return _median_position(gps, m, "lat", "lon", "alt", (1e-7, 1e-3))
    gp = cols.get("GLOBAL_POSITION_INT") or {}
    if n_rows(gp):
        m = (np.asarray(gp["_sysid"]) == sysid) & ((np.asarray(gp["lat"]) != 0) | (np.asarray(gp["lon"]) != 0))
        if m.any():
            return _median_position(gp, m, "lat", "lon", "alt", (1e-7, 1e-3))
    return None


# --------------------------------------------------------------------------- live IMU rows
def imu_series(name: str, fields: Sequence[str], values: Sequence[tuple],
               log_times: Sequence[float]) -> list[SensorSeries]:
    """accel/gyro/mag :class:`SensorSeries` of rows of one integer IMU message type (SI units, mGauss).

    The unit conversion of live IMU messages (the same as :func:`assemble_tlog`'s): milli-g
    -> m/s^2, mrad/s -> rad/s, mGauss as sent; rows whose accel and gyro are all zero (no IMU)
    or whose mag is all zero (no compass) are left out of that sensor's series.

    Parameters
    ----------
    name : str
        RAW_IMU, SCALED_IMU, SCALED_IMU2 or SCALED_IMU3 (instance 0, 0, 1, 2).
    fields : sequence of str
        The message's field names, in the order of each row of ``values``.
    values : sequence of tuple
        One row of field values per message.
    log_times : sequence of float
        Receive time of each message (unix s), the series' ``log_time_s``.
    """
    f = list(fields)
    v = np.array(values, dtype=float)
    t = v[:, f.index("time_boot_ms")] * 1e-3 if "time_boot_ms" in f else v[:, f.index("time_usec")] * 1e-6
    lt = np.asarray(log_times, dtype=float)
    acc = v[:, [f.index("xacc"), f.index("yacc"), f.index("zacc")]]
    gyr = v[:, [f.index("xgyro"), f.index("ygyro"), f.index("zgyro")]]
    mag = v[:, [f.index("xmag"), f.index("ymag"), f.index("zmag")]]
    inst = SCALED_INSTANCE[name]
    imu = ~((acc == 0).all(axis=1) & (gyr == 0).all(axis=1))
    hm = ~(mag == 0).all(axis=1)
    out: list[SensorSeries] = []
    if imu.any():
        out.append(SensorSeries("accel", inst, name, t[imu], acc[imu] * MG_TO_MS2, lt[imu]))
        out.append(SensorSeries("gyro", inst, name, t[imu], gyr[imu] / 1000.0, lt[imu]))
    if hm.any():
        out.append(SensorSeries("mag", inst, name, t[hm], mag[hm], lt[hm]))
    return out
