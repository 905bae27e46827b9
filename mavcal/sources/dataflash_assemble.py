"""DataFlash (``.bin``) message columns -> :class:`~mavcal.sources.types.ImuLog`: the IMU/ACC/GYR and MAG
records (``I`` field or old IMU2/MAG3 names; MAG extras ``ofs_mgauss``, ``motor_ofs_mgauss``,
``health``; time from TimeUS, or TimeMS in very old logs; IMU preferred over ACC/GYR), the PARM
timeline, MSG events, the firmware and the position (ORGN, GPS, POS).
"""
from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence

import numpy as np

from mavcal.errors import SourceError
from mavcal.sources.param_columns import dataflash_params, with_column
from mavcal.sources.param_columns import decode_text as _text
from mavcal.sources.series_set import FIRMWARE_RE, Columns, SeriesSet, column_matrix, n_rows, take_rows
from mavcal.sources.types import ImuLog, LogEvent, ParamTimeline

__all__ = ["DATAFLASH_MESSAGES", "DF_IMU_NAMES", "DF_MAG_NAMES", "assemble_dataflash"]

DF_IMU_NAMES = ("IMU", "IMU2", "IMU3", "ACC", "ACC1", "ACC2", "ACC3", "GYR", "GYR1", "GYR2", "GYR3")
DF_MAG_NAMES = ("MAG", "MAG2", "MAG3")
DATAFLASH_MESSAGES = DF_IMU_NAMES + DF_MAG_NAMES + ("PARM", "MSG", "GPS", "ORGN", "POS")


def _df_time(c: Mapping[str, np.ndarray]) -> np.ndarray:
    if "TimeUS" in c:
        return np.asarray(c["TimeUS"], dtype=float) * 1e-6
    if "TimeMS" in c:
        return np.asarray(c["TimeMS"], dtype=float) * 1e-3
    raise SourceError("DataFlash message without TimeUS/TimeMS")


def _df_instances(name: str, c: Mapping[str, np.ndarray], limit: int, warns: list[str],
                  keys: Sequence[str]) -> Iterator[tuple[int, Mapping[str, np.ndarray]]]:
    """Yield (instance, columns) of a DataFlash message (I field, or the digit in the name).

    Records whose instance is not 0..``limit``-1 (a corrupt I byte: ArduPilot has no such
    sensor slot) are skipped and counted in ``warns``. Of a log with several instances, only
    the columns ``keys`` (those the caller reads) are taken apart."""
    if "I" in c:
        col = np.asarray(c["I"])
        if col.dtype.kind in "iu":  # the logged byte: a whole number, finite
            raw = col
            ok = (col >= 0) & (col < limit)
        else:
            raw = col.astype(float)
            ok = np.isfinite(raw) & (raw >= 0) & (raw < limit) & (raw == np.round(raw))
        if not ok.all():
            bad = sorted({int(x) for x in raw[~ok & np.isfinite(raw)][:1000].tolist()})[:5]
            warns.append(f"skipped {int((~ok).sum())} {name} records with an impossible instance number "
                         f"({', '.join(map(str, bad)) or 'not a number'}; valid 0..{limit - 1}): corrupt records")
        inst = np.where(ok, raw, -1).astype(int)
        for i in np.flatnonzero(np.bincount(inst[ok], minlength=limit)).tolist():
            m = inst == i
            # one instance (the usual case): no copy; else gathered by index (instances often alternate)
            yield i, (c if m.all() else take_rows({k: c[k] for k in keys if k in c}, np.flatnonzero(m)))
    else:
        digit = name[-1]
        if digit.isdigit():  # IMU2 -> 1, MAG3 -> 2, ACC1 -> 0
            yield int(digit) - 1, c
        else:
            yield 0, c


def _df_add(out: SeriesSet, sensor: str, inst: int, msg: str, t: np.ndarray, v: np.ndarray,
            extra: Mapping[str, np.ndarray] | None = None) -> None:
    """Keep a DataFlash series without its non-finite samples (stated in the warnings)."""
    if len(t) == 0 or out.has(sensor, inst):
        return
    ok: np.ndarray | slice = slice(None)  # every sample finite (the usual case): no copy
    finite = np.isfinite(v)
    if not finite.all():
        ok = finite.all(axis=1)
        out.warns.append(f"dropped {int((~ok).sum())} {msg} samples with non-finite values")
    out.keep(sensor, inst, msg, t[ok], v[ok], None, {k: a[ok] for k, a in (extra or {}).items()},
             dup_label=f"{msg}[{inst}]")


_DF_TIME_KEYS = ("TimeUS", "TimeMS")
_DF_ACC = ("AccX", "AccY", "AccZ")
_DF_GYR = ("GyrX", "GyrY", "GyrZ")
_DF_MAG_KEYS = ("MagX", "MagY", "MagZ", "OfsX", "OfsY", "OfsZ", "MOX", "MOY", "MOZ", "Health")


def _df_sensor_series(cols: Columns, out: SeriesSet) -> None:
    """IMU/ACC/GYR -> accel and gyro, MAG -> mag (with offsets, motor offsets and health)."""
    from mavcal.autopilot import model_named

    most = model_named("ArduPilot").max_instances  # a DataFlash log is ArduPilot's
    for name in DF_IMU_NAMES:
        c = cols.get(name) or {}
        if not n_rows(c):
            continue
        for inst, ci in _df_instances(name, c, most["accel"], out.warns, _DF_TIME_KEYS + _DF_ACC + _DF_GYR):
            t = _df_time(ci)
            if all(k in ci for k in _DF_ACC):
                _df_add(out, "accel", inst, name, t, column_matrix(ci, _DF_ACC))
            if all(k in ci for k in _DF_GYR):
                _df_add(out, "gyro", inst, name, t, column_matrix(ci, _DF_GYR))
    for name in DF_MAG_NAMES:
        c = cols.get(name) or {}
        if not n_rows(c):
            continue
        for inst, ci in _df_instances(name, c, most["mag"], out.warns, _DF_TIME_KEYS + _DF_MAG_KEYS):
            if not all(k in ci for k in ("MagX", "MagY", "MagZ")):
                continue
            extra = {}
            if all(k in ci for k in ("OfsX", "OfsY", "OfsZ")):
                extra["ofs_mgauss"] = column_matrix(ci, ("OfsX", "OfsY", "OfsZ"))
            if all(k in ci for k in ("MOX", "MOY", "MOZ")):
                extra["motor_ofs_mgauss"] = column_matrix(ci, ("MOX", "MOY", "MOZ"))
            if "Health" in ci:
                extra["health"] = np.asarray(ci["Health"], dtype=float)
            _df_add(out, "mag", inst, name, _df_time(ci), column_matrix(ci, ("MagX", "MagY", "MagZ")), extra)


class _DfRecordTime:
    """Time of any DataFlash record: its TimeUS/TimeMS, or (old PARM, MSG without one) the time of the
    latest timed record before it."""

    def __init__(self, cols: Columns) -> None:
        self.cols = cols
        self._timeline: tuple[np.ndarray, np.ndarray] | None = None

    def _timed(self) -> tuple[np.ndarray, np.ndarray]:
        """(record numbers, running-max times) of every timed record, built when first needed
        (only for records without a time of their own: most logs never need them)."""
        if self._timeline is None:
            timed = [(np.asarray(c["_index"]), _df_time(c)) for n, c in self.cols.items()
                     if n_rows(c) and ("TimeUS" in c or "TimeMS" in c) and "_index" in c]
            if timed:
                t_idx = np.concatenate([a for a, _ in timed])
                t_val = np.concatenate([b for _, b in timed])
                o = np.argsort(t_idx, kind="stable")
                self._timeline = (t_idx[o], np.maximum.accumulate(t_val[o]))
            else:
                self._timeline = (np.zeros(1, np.int64), np.zeros(1))
        return self._timeline

    def __call__(self, c: Mapping[str, np.ndarray]) -> np.ndarray:
        if "TimeUS" in c or "TimeMS" in c:
            return _df_time(c)
        t_idx, t_val = self._timed()
        k = np.searchsorted(t_idx, np.asarray(c["_index"]), side="right") - 1
        return np.where(k >= 0, t_val[np.clip(k, 0, None)], t_val[0])


def assemble_dataflash(cols: Columns, source: str, warnings: Sequence[str] = ()) -> ImuLog:
    """Build an ImuLog from DataFlash message columns (fast decoder or DFReader)."""
    warns = list(warnings)
    out = SeriesSet(warns)
    _df_sensor_series(cols, out)
    if not out.series:
        raise SourceError(f"no IMU data (IMU/ACC/GYR/MAG records) in {source}")
    rec_time = _DfRecordTime(cols)
    params = ParamTimeline()
    pm = cols.get("PARM") or {}
    if n_rows(pm):
        params = dataflash_params(pm, rec_time(pm), warns, source)
    events: list[LogEvent] = []
    firmware = None
    msg = with_column(cols.get("MSG") or {}, "Message", "MSG", warns)  # {} when its FMT is damaged
    if n_rows(msg):
        for t, text in zip(rec_time(msg).tolist(), msg["Message"]):
            txt = _text(text)
            events.append(LogEvent(float(t), "statustext", txt))
            if firmware is None and FIRMWARE_RE.match(txt):
                firmware = txt
    events.sort(key=lambda e: e.time_s)
    vehicle: dict[str, object] = {}
    if firmware:
        vehicle["firmware"] = firmware
    return ImuLog(source=source, kind="dataflash", series=out.sorted(), params=params, events=tuple(events),
                  position=_df_position(cols), vehicle=vehicle, warnings=tuple(warns))


def _df_position(cols: Columns) -> tuple[float, float, float] | None:
    o = cols.get("ORGN") or {}
    if n_rows(o) and all(k in o for k in ("Lat", "Lng", "Alt")):
        m = (np.asarray(o["Lat"]) != 0) | (np.asarray(o["Lng"]) != 0)
        if m.any():
            i = np.flatnonzero(m)[0]
            return (float(o["Lat"][i]), float(o["Lng"][i]), float(o["Alt"][i]))
    g = cols.get("GPS") or {}
    if n_rows(g) and all(k in g for k in ("Lat", "Lng", "Alt", "Status")):
        m = np.asarray(g["Status"]) >= 3
        if "I" in g:
            m &= np.asarray(g["I"]) == 0
        if m.any():
            return (float(np.median(np.asarray(g["Lat"])[m])), float(np.median(np.asarray(g["Lng"])[m])),
                    float(np.median(np.asarray(g["Alt"])[m])))
    p = cols.get("POS") or {}
    if n_rows(p) and all(k in p for k in ("Lat", "Lng", "Alt")):
        m = (np.asarray(p["Lat"]) != 0) | (np.asarray(p["Lng"]) != 0)
        if m.any():
            return (float(np.median(np.asarray(p["Lat"])[m])), float(np.median(np.asarray(p["Lng"])[m])),
                    float(np.median(np.asarray(p["Alt"])[m])))
    return None
