"""The results table of a fleet run: one flat row per log, written as each log finishes.

``--table results.csv``: the CSV file itself is appended one row at a time, each row one
``write`` followed by ``fsync``, so a run killed at any point (SIGKILL, power cut after the
sync) leaves every finished log's row; a torn last line (no newline) is cut off when the
table is opened again.

``--table results.parquet``: the rows go as they finish to a journal beside it,
``results.parquet.journal.csv`` (the CSV above), and ``results.parquet`` is rewritten from
the journal atomically (a temporary file renamed over it) every so often and at the end of
the run, when the journal is removed. So ``results.parquet`` is always a whole Parquet file
(one file, which pandas, polars and duckdb read as is); after a kill, the next run with the
same table starts from the journal, which holds every row. Parquet needs pyarrow
(``mavcal[fleet]``).

A run with a table skips the logs whose key, the log's content hash (SHA-256) and mavcal's
version, is in it already: killed and run again, no row is lost and none is written twice.
"""
from __future__ import annotations

import csv
import io
import os
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

from mavcal.errors import SourceError, UsageError

__all__ = ["COLUMNS", "COLUMN_TYPES", "CALIBRATE", "Layout", "ResultsTable", "flat_row", "row_key", "read_table",
           "done_keys", "unread_key",
           "utc"]

_XYZ = ("x", "y", "z")
#: Rows per batch when a Parquet table is read or rewritten (memory: one batch, not the table)
_BATCH_ROWS = 5000


def _vec_cols(name: str, unit: str) -> list[tuple[str, type]]:
    out: list[tuple[str, type]] = []
    for when in ("old", "new"):
        out += [(f"{name}_{when}_{a}{unit}", float) for a in _XYZ]
    return out


#: The table's columns and their types, in order (a CSV table's header).
COLUMN_TYPES: dict[str, type] = dict([
    ("source", str), ("content_sha256", str), ("size_bytes", int), ("mavcal_version", str),
    ("log_start_utc", str), ("finished_utc", str),
    ("ok", bool), ("exit_code", int), ("result", str), ("error", str),
    ("sysid", int), ("firmware", str), ("compass_instance", int), ("compass_dev_id", int),
    ("accel_instance", int), ("accel_id", int),
    ("accepted", bool), ("sensors", str), ("rejections", str),
    ("heading_95_deg", float), ("tilt_95_deg", float), ("heading_determined", bool), ("tilt_determined", bool),
    ("not_determined_why", str), ("compass_determined", bool), ("accel_determined", bool),
    *_vec_cols("compass_ofs", "_mgauss"), ("compass_ofs_change_mgauss", float),
    *_vec_cols("accel_ofs", "_mps2"), ("accel_ofs_change_mps2", float),
    *_vec_cols("accel_scale", ""), ("accel_scale_change", float),
    ("drift_ratio", float), ("drift_flag", str), ("model", str), ("n_intervals", int),
    ("warnings", str), ("elapsed_s", float),
])
COLUMNS: tuple[str, ...] = tuple(COLUMN_TYPES)


@dataclass(frozen=True)
class Layout:
    """A kind of table: its columns and their types, in order (``mavcal calibrate``'s, or
    ``mavcal flight``'s: :data:`mavcal.fleet.flight.FLIGHT`), and the text columns whose empty
    cell reads back as "" (the others' as None). Every layout starts with the key columns
    ``source``, ``content_sha256``, ``mavcal_version``, ``ok``, ``exit_code``."""

    types: dict[str, type]
    blank_text: frozenset[str] = frozenset()

    @property
    def columns(self) -> tuple[str, ...]:
        return tuple(self.types)


#: ``mavcal calibrate``'s table
CALIBRATE = Layout(COLUMN_TYPES, frozenset(("rejections", "sensors", "warnings", "drift_flag", "not_determined_why")))


def row_key(sha256: str, version: str) -> str:
    """The key of a log's row: its content hash and mavcal's version."""
    return f"{sha256}:{version}"


def unread_key(source: str) -> str:
    """The ``content_sha256`` of the row of a log that could not be read (no content to hash):
    ``unreadable:`` and its name, so that a resumed run does not write its row again."""
    return f"unreadable:{source}"


def _one_line(s: str) -> str:
    return " | ".join(part.strip() for part in str(s).splitlines() if part.strip())


def utc(t: float | None) -> str | None:
    """Unix seconds as an ISO 8601 UTC time (``2024-06-01T12:00:00.000000Z``); None stays None."""
    if t is None:
        return None
    return datetime.fromtimestamp(t, tz=timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def flat_row(row, sha256: str, size: int, version: str) -> dict:
    """The table's row of a :class:`mavcal.batch.BatchRow` (every column of :data:`COLUMNS`)."""

    d = row.drift if row.ok else None
    out: dict = {
        "source": row.source, "content_sha256": sha256, "size_bytes": size, "mavcal_version": version,
        "log_start_utc": utc(getattr(row, "log_start_unix_s", None)), "finished_utc": utc(time.time()),
        "ok": row.ok, "exit_code": row.exit_code, "result": row.result,
        "error": None if row.error is None else _one_line(row.error),
        "sysid": row.sysid, "firmware": row.firmware, "compass_instance": row.compass_instance,
        "compass_dev_id": row.compass_dev_id, "accel_instance": row.accel_instance, "accel_id": row.accel_id,
        "accepted": row.accepted,
        "sensors": "; ".join(f"{v.sensor} {'ACCEPTED' if v.accepted else 'REJECTED'}" for v in row.sensors),
        "rejections": "; ".join(_one_line(f"{v.sensor}: {r}") for v in row.sensors for r in v.reasons
                                if not v.accepted) or "; ".join(_one_line(g) for g in row.failed_gates),
        "heading_95_deg": row.heading_95_deg, "tilt_95_deg": row.tilt_95_deg,
        "heading_determined": row.heading_determined, "tilt_determined": row.tilt_determined,
        "not_determined_why": _one_line(row.not_determined_why), "compass_determined": row.compass_determined,
        "accel_determined": row.accel_determined,
        "compass_ofs_change_mgauss": row.compass_ofs_change_mgauss, "accel_ofs_change_mps2": row.accel_ofs_change_mps2,
        "accel_scale_change": row.accel_scale_change, "drift_ratio": d,
        "drift_flag": ("DRIFT" if row.accepted else "drift?") if d is not None and d >= 1.0 else "",
        "model": row.model, "n_intervals": row.n_intervals, "warnings": "; ".join(_one_line(w) for w in row.warnings),
        "elapsed_s": row.elapsed_s,
    }
    for name, unit in (("compass_ofs", "_mgauss"), ("accel_ofs", "_mps2"), ("accel_scale", "")):
        for when in ("old", "new"):
            v = getattr(row, f"{name}_{when}")
            for i, a in enumerate(_XYZ):
                out[f"{name}_{when}_{a}{unit}"] = None if v is None else float(v[i])
    return {c: out.get(c) for c in COLUMNS}


def _cell(v) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return repr(v)
    return _one_line(v) if isinstance(v, str) else str(v)


def _parse(col: str, s: str, layout: Layout = CALIBRATE):
    t = layout.types[col]
    if s == "":
        return "" if t is str and col in layout.blank_text else None
    if t is bool:
        return s == "true"
    return t(s)


def _csv_line(row: dict, layout: Layout = CALIBRATE) -> bytes:
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerow([_cell(row.get(c)) for c in layout.types])
    return buf.getvalue().encode("utf-8")


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path.parent, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _repair(path: Path) -> None:
    """Cut a torn last line (a kill mid-row) off a CSV table."""
    with open(path, "r+b") as f:
        size = f.seek(0, os.SEEK_END)
        if size == 0:
            return
        f.seek(size - 1)
        if f.read(1) == b"\n":
            return
        back = min(size, 1 << 20)
        while True:  # the last newline, reading backwards a MiB at a time
            f.seek(size - back)
            tail = f.read(back)
            at = tail.rfind(b"\n")
            if at >= 0 or back == size:
                cut = size - back + at + 1 if at >= 0 else 0
                break
            back = min(size, 2 * back)
        f.truncate(cut)
        os.fsync(f.fileno())


def _iter_csv(path: Path, layout: Layout = CALIBRATE) -> Iterator[dict]:
    """The rows of a CSV table one at a time (a torn last line, without its newline, left out)."""
    with open(path, encoding="utf-8", errors="replace", newline="") as f:
        reader = csv.reader(_whole_lines(f))
        header = next(reader, None)
        if header is None:
            return
        cols = layout.columns
        if tuple(header) != cols:
            missing = [c for c in cols if c not in header]
            raise UsageError(f"{path}: not a table of this mavcal (columns differ: "
                             f"{', '.join(missing[:3]) or 'order'}); give a new --table file")
        for cells in reader:
            if len(cells) == len(cols):
                yield {c: _parse(c, v, layout) for c, v in zip(cols, cells)}


def _whole_lines(f) -> Iterator[str]:
    for line in f:
        if line.endswith("\n"):
            yield line


def _read_csv(path: Path, *, repair: bool, layout: Layout = CALIBRATE) -> list[dict]:
    """The rows of a CSV table; with ``repair`` a torn last line (a kill mid-row) is cut off."""
    if repair:
        _repair(path)
    return list(_iter_csv(path, layout))


def _arrow_schema(layout: Layout = CALIBRATE):
    import pyarrow as pa

    types = {str: pa.string(), int: pa.int64(), float: pa.float64(), bool: pa.bool_()}
    return pa.schema([(c, types[t]) for c, t in layout.types.items()])


def _need_pyarrow():
    try:
        import pyarrow  # noqa: F401
        import pyarrow.parquet as pq
    except ImportError:
        raise UsageError("a Parquet --table needs pyarrow, which is not installed: pip install 'mavcal[fleet]' "
                         "(or give a .csv table)") from None
    return pq


def _iter_parquet(path: Path, layout: Layout = CALIBRATE) -> Iterator[dict]:
    pq = _need_pyarrow()
    f = pq.ParquetFile(path)
    if tuple(f.schema_arrow.names) != layout.columns:
        raise UsageError(f"{path}: not a table of this mavcal (other columns); give a new --table file")
    for batch in f.iter_batches(batch_size=_BATCH_ROWS):
        yield from batch.to_pylist()


def read_table(path: str | os.PathLike, layout: Layout = CALIBRATE) -> list[dict]:
    """The rows of a results table (CSV or Parquet, with a Parquet table's journal when a run was
    interrupted), as dicts of the layout's columns (:data:`COLUMNS` for ``mavcal calibrate``'s)."""
    p = Path(path)
    if p.suffix.lower() == ".parquet":
        journal = p.with_name(p.name + ".journal.csv")
        if journal.exists():
            return _read_csv(journal, repair=False, layout=layout)
        if not p.exists():
            return []
        return list(_iter_parquet(p, layout))
    return _read_csv(p, repair=False, layout=layout) if p.exists() else []


class ResultsTable:
    """A results table being written (module docstring). Open with :meth:`open`, then
    :meth:`append` each finished log's flat row, then :meth:`close`.

    ``snapshot_s``: a Parquet table is rewritten from its journal at most this often (and at
    least ten times the last rewrite's duration apart), and at :meth:`close`."""

    def __init__(self, path: str | os.PathLike, *, snapshot_s: float = 30.0, layout: Layout = CALIBRATE) -> None:
        self.path = Path(path)
        self.layout = layout
        kind = self.path.suffix.lower()
        if kind not in (".csv", ".parquet"):
            raise UsageError(f"--table {path}: give a .csv or a .parquet file")
        self.parquet = kind == ".parquet"
        if self.parquet:
            _need_pyarrow()
        self.journal = self.path.with_name(self.path.name + ".journal.csv") if self.parquet else self.path
        self.snapshot_s = snapshot_s
        self._fd: int | None = None
        self._last_snapshot = time.monotonic()
        self._snapshot_cost = 0.0
        self._dirty = False

    def open(self, each: Callable[[dict], None] | None = None) -> list[dict]:
        """Open for appending. Returns the rows already there (a torn last row cut off), or with
        ``each`` passes them to it one at a time and returns [] (no row held here)."""
        rows: list[dict] = []
        take = each if each is not None else rows.append
        try:
            if self.parquet and not self.journal.exists():
                tmp = self.journal.with_name(self.journal.name + ".tmp")
                with open(tmp, "wb") as f:
                    f.write(_csv_line({c: c for c in self.layout.types}, self.layout))
                    if self.path.exists():
                        for r in _iter_parquet(self.path, self.layout):
                            f.write(_csv_line(r, self.layout))
                            take(r)
                    f.flush()
                    os.fsync(f.fileno())
                os.replace(tmp, self.journal)
                _fsync_dir(self.journal)
            elif self.journal.exists() and self.journal.stat().st_size > 0:
                _repair(self.journal)
                for r in _iter_csv(self.journal, self.layout):
                    take(r)
            else:
                with open(self.journal, "wb") as f:
                    f.write(_csv_line({c: c for c in self.layout.types}, self.layout))
                    f.flush()
                    os.fsync(f.fileno())
                _fsync_dir(self.journal)
            self._fd = os.open(self.journal, os.O_WRONLY | os.O_APPEND)
        except OSError as exc:
            raise SourceError(f"--table {self.path}: {exc.strerror or exc}") from None
        except Exception as exc:  # a file that is not a table (pyarrow's own errors)
            if isinstance(exc, UsageError):
                raise
            raise UsageError(f"--table {self.path}: cannot read it as a results table ({exc}); "
                             "give a new --table file") from None
        return rows

    def each_row(self, fn: Callable[[dict], None]) -> None:
        """Pass every row written so far to ``fn``, one at a time (read from the file)."""
        for r in _iter_csv(self.journal, self.layout):
            fn(r)

    def append(self, row: dict) -> None:
        """Write one row now: one write, then fsync (it survives a kill of this process)."""
        assert self._fd is not None, "open() first"
        line = _csv_line(row, self.layout)
        n = os.write(self._fd, line)
        while n < len(line):  # a short write (rare on a regular file): the rest
            n += os.write(self._fd, line[n:])
        os.fsync(self._fd)
        self._dirty = True
        if self.parquet and time.monotonic() - self._last_snapshot >= max(self.snapshot_s, 10 * self._snapshot_cost):
            self._snapshot()

    def _snapshot(self) -> None:
        import pyarrow as pa
        import pyarrow.parquet as pq

        t0 = time.monotonic()
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        schema = _arrow_schema(self.layout)
        with pq.ParquetWriter(tmp, schema) as out:  # a batch of rows at a time: the rows are never all in memory
            batch: list[dict] = []
            wrote = False
            for r in _iter_csv(self.journal, self.layout):
                batch.append(r)
                if len(batch) >= _BATCH_ROWS:
                    out.write_table(pa.Table.from_pylist(batch, schema=schema))
                    batch, wrote = [], True
            if batch or not wrote:
                out.write_table(pa.Table.from_pylist(batch, schema=schema))
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.replace(tmp, self.path)
        _fsync_dir(self.path)
        self._last_snapshot = time.monotonic()
        self._snapshot_cost = self._last_snapshot - t0
        self._dirty = False

    def close(self, *, finished: bool = True) -> None:
        """Close; a Parquet table is written whole, and its journal removed when ``finished``."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
        if self.parquet and (self._dirty or finished or not self.path.exists()):
            self._snapshot()
            if finished:
                self.journal.unlink(missing_ok=True)
                _fsync_dir(self.journal)


def done_keys(rows: Iterable[dict]) -> set[str]:
    """The keys (:func:`row_key`) of the rows of a table."""
    return {row_key(r["content_sha256"], r["mavcal_version"]) for r in rows if r.get("content_sha256")}


