"""The logs of a fleet run: what the user names, expanded to one entry per log.

A SOURCE of ``mavcal calibrate`` with several logs may be

- a log file (``.tlog``, ``.bin``, ``.log``, ``.ulg``, ``.csv``);
- a directory: every log file under it, recursively (by extension, case-insensitive);
- a glob (``flights/2024-*/*.tlog``; ``**`` recurses);
- ``@LIST``: a text file with one path, glob, directory or URL per line (blank lines and
  lines starting with ``#`` ignored; relative paths are relative to the list file);
- an fsspec URL: ``s3://bucket/prefix/`` (every log under the prefix), ``s3://bucket/key.tlog``,
  ``https://host/log.tlog``, ``file:///path``; globs work in URLs too. Credentials and
  endpoints come from the storage's own conventions (for S3 the AWS environment and config
  files, ``AWS_ENDPOINT_URL`` for an S3-compatible server). URLs need ``mavcal[fleet]``.

The list is sorted within each SOURCE, duplicates dropped (first kept). A worker reads its log
itself (:func:`fetch`): no log's bytes go through the process that hands out the jobs.
"""
from __future__ import annotations

import glob as globmod
import hashlib
import os
import re
import tempfile
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from mavcal.errors import SourceError, UsageError

__all__ = ["LOG_EXTENSIONS", "is_url", "expand_sources", "fetch", "need_fleet_extra", "FLEET_EXTRA_HINT"]

#: The extensions of log files a directory or a prefix is searched for.
LOG_EXTENSIONS = (".tlog", ".bin", ".log", ".ulg", ".csv")
FLEET_EXTRA_HINT = "pip install 'mavcal[fleet]'"
_URL = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*://")
_GLOB = re.compile(r"[*?\[]")
_CHUNK = 1 << 20


def _line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def is_url(source: str) -> bool:
    """Whether ``source`` is a URL (``scheme://...``), read through fsspec."""
    return bool(_URL.match(source))


def need_fleet_extra(what: str):
    """The fsspec module, or a UsageError (exit 2) naming the extra that provides it."""
    try:
        import fsspec
    except ImportError:
        raise UsageError(f"{what} needs the fleet extra, which is not installed: {FLEET_EXTRA_HINT}") from None
    return fsspec


def _is_log(name: str) -> bool:
    return name.lower().endswith(LOG_EXTENSIONS)


def _local(spec: str, base: Path | None) -> list[str]:
    p = Path(spec).expanduser()
    if base is not None and not p.is_absolute():
        p = base / p
    if _GLOB.search(spec) and not p.exists():
        hits = sorted(globmod.glob(str(p), recursive=True))
        out = []
        for h in hits:
            out += _local(h, None) if os.path.isdir(h) else [h]
        if not out:
            raise SourceError(f"{spec}: no file matches")
        return out
    if p.is_dir():
        found = sorted(str(Path(root) / f) for root, _, files in os.walk(p) for f in files if _is_log(f))
        if not found:
            raise SourceError(f"{spec}: no log file ({', '.join(LOG_EXTENSIONS)}) under this directory")
        return found
    return [str(p)]


def _remote(url: str) -> list[str]:
    fsspec = need_fleet_extra(f"{url}: reading a URL")
    try:
        fs, path = fsspec.core.url_to_fs(url)
    except (ImportError, ValueError) as exc:  # an unknown protocol, or its package missing (s3fs)
        raise UsageError(f"{url}: {exc} ({FLEET_EXTRA_HINT})") from None
    proto = url.split("://", 1)[0]

    def full(p: str) -> str:
        return p if is_url(p) else f"{proto}://{p}"

    try:
        if _GLOB.search(path):
            found = sorted(full(p) for p in fs.glob(path) if _is_log(p))
        elif url.endswith("/") or (proto not in ("http", "https") and fs.isdir(path)):
            found = sorted(full(p) for p in fs.find(path) if _is_log(p))
        else:
            return [url]
    except Exception as exc:  # the storage's own errors (no credentials, access denied, no such bucket)
        raise SourceError(f"{url}: {type(exc).__name__}: {_line(exc)}") from None
    if not found:
        raise SourceError(f"{url}: no log file ({', '.join(LOG_EXTENSIONS)}) there")
    return found


def _list_file(spec: str) -> list[str]:
    path = Path(spec).expanduser()
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise SourceError(f"@{spec}: cannot read the list file ({exc})") from None
    out: list[str] = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            out += _remote(line) if is_url(line) else _local(line, path.parent)
    return out


def expand_sources(specs: Sequence[str]) -> list[str]:
    """One entry per log for the SOURCEs given (module docstring); a device string is kept as is.

    Raises
    ------
    mavcal.errors.SourceError
        A directory, glob or prefix with no log, an unreadable list file (exit 3).
    mavcal.errors.UsageError
        A URL without ``mavcal[fleet]`` installed (exit 2).
    """
    out: list[str] = []
    for spec in specs:
        spec = str(spec)
        if spec.startswith("@") and len(spec) > 1:
            out += _list_file(spec[1:])
        elif is_url(spec):
            out += _remote(spec)
        elif os.path.isdir(spec) or (_GLOB.search(spec) and not os.path.exists(spec)):  # "log[1].tlog" is a file
            out += _local(spec, None)
        else:
            out.append(spec)
    seen: set[str] = set()
    return [s for s in out if not (s in seen or seen.add(s))]  # type: ignore[func-returns-value]


@contextmanager
def fetch(source: str) -> Iterator[tuple[str, str, int]]:
    """A local path of the log and its content: ``(path, sha256 hex, size in bytes)``.

    A local file is hashed where it is; a URL is copied (streamed) into a temporary file with
    the same extension, removed on leaving. Runs in the worker that calibrates the log.

    Raises
    ------
    mavcal.errors.SourceError
        The log cannot be read (exit 3).
    """
    h = hashlib.sha256()
    size = 0
    if not is_url(source):
        try:
            with open(source, "rb") as f:
                while chunk := f.read(_CHUNK):
                    h.update(chunk)
                    size += len(chunk)
        except OSError as exc:
            raise SourceError(f"{source}: {exc.strerror or exc}") from None
        yield source, h.hexdigest(), size
        return
    fsspec = need_fleet_extra(f"{source}: reading a URL")
    suffix = Path(source.split("?", 1)[0]).suffix
    fd, tmp = tempfile.mkstemp(prefix="mavcal-fleet-", suffix=suffix)
    try:
        try:
            with os.fdopen(fd, "wb") as out, fsspec.open(source, "rb") as f:
                while chunk := f.read(_CHUNK):
                    h.update(chunk)
                    size += len(chunk)
                    out.write(chunk)
        except Exception as exc:  # the storage's own errors (no credentials, access denied, gone)
            raise SourceError(f"{source}: {type(exc).__name__}: {_line(exc)}") from None
        yield tmp, h.hexdigest(), size
    finally:
        try:
            os.unlink(tmp)
        except OSError:
            pass


