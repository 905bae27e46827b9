"""Read the IMU log files an ArduPilot user has into an :class:`~mavcal.sources.types.ImuLog`.

Entry points
------------
:func:`read_log` reads a file: MAVLink telemetry log (``.tlog``), DataFlash log (binary
``.bin``/``.BIN``, binary or text ``.log``), or a CSV of accelerometer readings.
:func:`is_device` tells a pymavlink device string from a file name; a live vehicle is
recorded by :func:`mavcal.link.live.record_device` (this package knows nothing of devices).

Files are decoded with the vectorised decoders of :mod:`mavcal.sources.fast_tlog` and
:mod:`mavcal.sources.fast_dataflash`; ``fast=False`` uses pymavlink instead (reference,
and the only path for text DataFlash logs). Both paths produce the same intermediate
columns and go through the same assembly code (:mod:`mavcal.sources.assemble`, which also
documents the units, conventions and the time base), so their results are identical.
"""
from __future__ import annotations

import contextlib
import csv
import io
import logging
import os
import re
import stat
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, Callable

import numpy as np

from mavcal.errors import MavcalError, SourceError
from mavcal.sources.assemble import G0, TLOG_MESSAGES, assemble_tlog
from mavcal.sources.dataflash_assemble import DATAFLASH_MESSAGES, assemble_dataflash
from mavcal.sources.series_set import Columns
from mavcal.sources.types import ImuLog, SensorSeries

__all__ = ["read_log", "read_csv", "is_device", "pymavlink_tlog_columns",
           "pymavlink_dataflash_columns", "DEFAULT_CSV_RATE_HZ", "CSV_RATE_ASSUMED", "csv_rate_was_assumed"]

log = logging.getLogger(__name__)

ProgressFn = Callable[[int, int], None]

#: sample rate assumed for a CSV without a time column (stated in the warnings)
DEFAULT_CSV_RATE_HZ = 100.0
#: how that warning begins
CSV_RATE_ASSUMED = "CSV has no time column: assumed"


# --------------------------------------------------------------------------- pymavlink reference readers
def pymavlink_tlog_columns(path: str, names: Sequence[str] = TLOG_MESSAGES) -> tuple[Columns, list[str]]:
    """Columns of a tlog decoded by pymavlink ``recv_msg`` (reference for the fast decoder)."""
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(path, robust_parsing=True)
    rows: dict[str, list[tuple[int, Any]]] = {n: [] for n in names}
    wanted = set(names)
    index = 0
    bad = 0
    try:
        while True:
            m = conn.recv_msg()
            if m is None:
                break
            index += 1
            typ = m.get_type()
            if typ == "BAD_DATA":
                bad += 1
                continue
            if typ in wanted:
                rows[typ].append((index - 1, m))
    finally:
        conn.close()
    cols: Columns = {}
    for n, lst in rows.items():
        if not lst:
            continue
        fields = lst[0][1].get_fieldnames()
        c = {f: np.array([getattr(m, f) for _, m in lst]) for f in fields}
        c["_log_time_s"] = np.array([m._timestamp for _, m in lst], dtype=float)
        c["_index"] = np.array([i for i, _ in lst], dtype=np.int64)
        c["_sysid"] = np.array([m.get_srcSystem() for _, m in lst])
        c["_compid"] = np.array([m.get_srcComponent() for _, m in lst])
        cols[n] = c
    warns = [f"skipped {bad} bad MAVLink data records (bad CRC or framing)"] if bad else []
    return cols, warns


def pymavlink_dataflash_columns(path: str, names: Sequence[str] = DATAFLASH_MESSAGES) -> Columns:
    """Columns of a DataFlash log (binary or text) decoded by pymavlink DFReader."""
    from pymavlink import DFReader

    with open(path, "rb") as fh:
        head = fh.read(2)
    reader = (DFReader.DFReader_binary(path, zero_time_base=True) if head == b"\xa3\x95"
              else DFReader.DFReader_text(path, zero_time_base=True))
    rows: dict[str, list[tuple[int, Any]]] = {n: [] for n in names}
    index = 0
    while True:
        m = reader.recv_match(type=list(names))
        if m is None:
            break
        rows[m.get_type()].append((index, m))
        index += 1
    cols: Columns = {}
    for n, lst in rows.items():
        if not lst:
            continue
        fields = lst[0][1].get_fieldnames()
        c = {f: np.array([getattr(m, f) for _, m in lst]) for f in fields}
        c["_index"] = np.array([i for i, _ in lst], dtype=np.int64)
        cols[n] = c
    return cols


# --------------------------------------------------------------------------- CSV
def read_csv(path: str, *, rate_hz: float = DEFAULT_CSV_RATE_HZ) -> ImuLog:
    """Read a CSV of accelerometer (and optionally gyro/mag) readings.

    The header must name ``ax,ay,az`` (accel in g); optional ``gx,gy,gz`` (rad/s),
    ``mx,my,mz`` (mGauss) and a time column ``t``/``time``/``time_s``/``timestamp`` (s).
    Without a time column, samples are assumed evenly spaced at ``rate_hz`` (stated in the
    warnings).
    """
    if not rate_hz or not np.isfinite(rate_hz) or rate_hz <= 0:
        raise SourceError(f"invalid CSV sample rate {rate_hz!r}")
    with open(path, newline="", errors="replace") as fh:
        text = fh.read()
    # a lone carriage return (a damaged file) is a line end, not an error of the csv module
    reader = csv.reader(io.StringIO(text.replace("\r\n", "\n").replace("\r", "\n")))
    try:
        header = [h.strip().lower() for h in next(reader)]
    except StopIteration:
        raise SourceError(f"empty CSV file {path}") from None
    except csv.Error as exc:
        raise SourceError(f"CSV {path}: its header line cannot be read as CSV ({exc})") from None
    col = {h: i for i, h in enumerate(header)}
    if not all(k in col for k in ("ax", "ay", "az")):
        raise SourceError(f"CSV {path} has no ax,ay,az header (found: {','.join(header[:8])})")
    tcol = next((col[k] for k in ("time_s", "t", "time", "timestamp") if k in col), None)
    rows = []
    bad = 0
    while True:
        try:
            r = next(reader)
        except StopIteration:
            break
        except csv.Error:  # e.g. a NUL byte or a quote left open: that line is not CSV
            bad += 1
            continue
        if not r or all(not x.strip() for x in r):
            continue
        try:
            rows.append([float(x) if x.strip() else np.nan for x in r])
        except ValueError:
            bad += 1
    width = len(header)
    rows = [r for r in rows if len(r) >= width]
    if not rows:
        raise SourceError(f"CSV {path} has no numeric rows")
    a = np.array([r[:width] for r in rows], dtype=float)
    warns = []
    if bad:
        warns.append(f"skipped {bad} CSV rows that are not numbers")
    acc = a[:, [col["ax"], col["ay"], col["az"]]]
    ok = np.isfinite(acc).all(axis=1)
    if (~ok).sum():
        warns.append(f"skipped {int((~ok).sum())} CSV rows with missing accel values")
    if tcol is not None:
        t = a[:, tcol]
        ok &= np.isfinite(t)
    else:
        t = np.arange(len(a)) / float(rate_hz)
        warns.append(f"{CSV_RATE_ASSUMED} {rate_hz:g} Hz")
    warns.append("CSV accel assumed in g (x 9.80665 -> m/s^2)")
    series = [SensorSeries("accel", 0, "CSV", t[ok], acc[ok] * G0)]
    if all(k in col for k in ("gx", "gy", "gz")):
        g = a[:, [col["gx"], col["gy"], col["gz"]]]
        m = ok & np.isfinite(g).all(axis=1)
        series.append(SensorSeries("gyro", 0, "CSV", t[m], g[m]))
        warns.append("CSV gyro assumed in rad/s")
    if all(k in col for k in ("mx", "my", "mz")):
        mg = a[:, [col["mx"], col["my"], col["mz"]]]
        m = np.isfinite(mg).all(axis=1) & (np.isfinite(t))
        series.append(SensorSeries("mag", 0, "CSV", t[m], mg[m]))
        warns.append("CSV mag assumed in mGauss")
    if len(series[0]) == 0:
        raise SourceError(f"CSV {path} has no usable accel rows")
    return ImuLog(source=str(path), kind="csv", series=tuple(series), warnings=tuple(warns))


def csv_rate_was_assumed(log_: ImuLog) -> bool:
    """True for a CSV log read without a time column (its sample rate, and so every duration
    measured on it, was assumed)."""
    return log_.kind == "csv" and any(w.startswith(CSV_RATE_ASSUMED) for w in log_.warnings)


# --------------------------------------------------------------------------- entry points
_LIVE_PREFIXES = ("udp:", "udpin:", "udpout:", "udpbcast:", "tcp:", "tcpin:", "serial:", "mcast:")


def is_device(source: str) -> bool:
    """True for a pymavlink device string (network address or serial port), not a file: also ``auto``
    (the serial port found, :mod:`mavcal.link.autodetect`) and any path to a character device, through
    symlinks too (udev's ``/dev/serial/by-id/...`` names)."""
    s = str(source)
    if s.lower().startswith(_LIVE_PREFIXES) or s == "auto":
        return True
    if s.startswith("/dev/") or re.match(r"^COM\d+$", s, re.I):
        return True
    try:
        return stat.S_ISCHR(os.stat(s).st_mode)
    except (OSError, ValueError):
        return False


def _kind_of(path: Path) -> str:
    ext = path.suffix.lower()
    if ext == ".tlog":
        return "tlog"
    if ext == ".bin":
        return "dataflash"
    if ext == ".log":
        with open(path, "rb") as fh:
            head = fh.read(2)
        return "dataflash" if head == b"\xa3\x95" else "dataflash_text"
    if ext == ".csv":
        return "csv"
    if ext == ".ulg":
        return "ulog"
    raise SourceError(f"unknown log type '{path.suffix or path.name}' of {path}: expected .tlog, .bin, .log, .ulg "
                      "or .csv")


def _check_tlog(src: str, stats) -> None:
    if stats.frames == 0:
        raise SourceError(f"no MAVLink frames in {src}: not a tlog, or corrupt")
    for note in stats.notes():
        log.debug("%s: %s", src, note)


def read_log(path, *, progress: ProgressFn | None = None, fast: bool = True, csv_rate_hz: float = DEFAULT_CSV_RATE_HZ,
             chunk_size: int | None = None) -> ImuLog:
    """Read a log file into an :class:`ImuLog`.

    Parameters
    ----------
    path : str or Path
        ``.tlog``, ``.bin``/``.BIN``, ``.log`` (binary or text DataFlash), ``.ulg`` (PX4 ULog,
        :mod:`mavcal.sources.ulog`) or ``.csv``.
    progress : callable(done_bytes, total_bytes) or None
        Progress callback for long reads (see :func:`mavcal.sources.progress.auto_progress`).
    fast : bool
        Use the vectorised decoders (default); ``False`` uses pymavlink (slow, reference).
    csv_rate_hz : float
        Assumed sample rate of a CSV without a time column.
    chunk_size : int, optional
        Bytes per read of the fast decoders.

    Raises
    ------
    SourceError
        Missing, empty, unreadable or corrupt file, unknown type, or no IMU data.
    """
    src = str(path)
    if is_device(src):  # a clear word rather than "no such file"
        raise SourceError(f"{src} is a device, not a log file: record it with mavcal.link.live.record_device "
                          "(mavcal.pipeline.open_source takes both)")
    p = Path(path)
    if not p.exists():
        raise SourceError(f"no such file: {src}")
    if not p.is_file():
        raise SourceError(f"not a file: {src}")
    kind = _kind_of(p)
    if p.stat().st_size == 0:
        raise SourceError(f"empty file: {src}")
    kw: dict[str, Any] = {"chunk_size": chunk_size} if chunk_size else {}
    try:  # mavcal's own readers raise SourceError naming what is wrong; anything else is a bug in them
        if kind == "csv":
            return read_csv(src, rate_hz=csv_rate_hz)
        if kind == "ulog":
            from mavcal.sources.ulog import read_ulog

            return read_ulog(src)  # wraps pyulog's failures itself
        if kind == "tlog":
            if fast:
                from mavcal.sources.fast_tlog import decode_tlog
                from mavcal.sources.tlog_imu import decode_tlog_lean

                lean = decode_tlog_lean(src, progress=progress, **kw)
                if lean is not None:  # one system sends IMU messages (the usual case)
                    cols, prepared, stats = lean
                    _check_tlog(src, stats)
                    return assemble_tlog(cols, src, stats.warnings(), prepared=prepared)
                cols, stats = decode_tlog(src, TLOG_MESSAGES, progress=progress, **kw)
                _check_tlog(src, stats)
                return assemble_tlog(cols, src, stats.warnings())
            with _third_party("pymavlink", src):
                cols, warns = pymavlink_tlog_columns(src)
            return assemble_tlog(cols, src, warns)
        if kind == "dataflash" and fast:
            from mavcal.sources.fast_dataflash import decode_dataflash

            df_cols, _formats, df_stats = decode_dataflash(src, DATAFLASH_MESSAGES, progress=progress, **kw)
            if df_stats.records == 0:
                raise SourceError(f"no DataFlash records in {src}: not a DataFlash log, or corrupt")
            return assemble_dataflash(df_cols, src, df_stats.warnings())
        with _third_party("pymavlink", src):
            df_ref = pymavlink_dataflash_columns(src)
        return assemble_dataflash(df_ref, src)
    except MemoryError:
        raise SourceError(f"out of memory reading {src}") from None
    except OSError as exc:
        raise SourceError(f"cannot read {src}: {exc.strerror or exc}") from None


@contextlib.contextmanager
def _third_party(parser: str, src: str) -> Iterator[None]:
    """A third-party parser's failure on a damaged file as one line naming the parser (never the
    Python exception's class: that is in the debug log)."""
    try:
        yield
    except (MavcalError, MemoryError, OSError):
        raise
    except Exception:  # noqa: BLE001 - corrupt input the parser did not anticipate
        log.debug("%s failed on %s", parser, src, exc_info=True)
        raise SourceError(f"{parser} could not parse {src}: the file is damaged or not a log of its kind") from None
