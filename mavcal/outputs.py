"""Output files that never destroy an input, and are never left half written.

* :func:`check_outputs` refuses, before any work, an output path that is one of the inputs (the
  same file by :func:`os.path.samefile`: the same name, a symbolic link to it or a hard link)
  or another output (:class:`mavcal.errors.OutputIsInputError`, exit code 9, one line).
* :func:`write_atomic` writes a file through a temporary file in the same folder, flushed to
  disk, then renamed over the destination (:func:`os.replace`): an interrupted run leaves the
  old file whole (or no file), never a part of the new one.

Every file mavcal writes for the user goes through :func:`write_atomic` (.param files and
backups by :func:`mavcal.autopilot.paramfile.write_param_file`, JSON, HTML reports).
"""
from __future__ import annotations

import os
import tempfile
from collections.abc import Iterable, Sequence
from pathlib import Path

from mavcal.errors import OutputIsInputError, SourceError, UsageError

__all__ = ["check_outputs", "write_atomic", "same_file"]


def same_file(a: str | os.PathLike[str], b: str | os.PathLike[str]) -> bool:
    """Whether ``a`` and ``b`` are the same existing file (through links too); False when either
    does not exist (a new output cannot be an input)."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def check_outputs(outputs: Sequence[tuple[str, str | None]], inputs: Iterable[str | None]) -> None:
    """Refuse (:class:`OutputIsInputError`, nothing done) an output that is an input, or that
    another output also names.

    Parameters
    ----------
    outputs : sequence of (option, path)
        Each output the command would write, e.g. ``("--param-out", "x.param")``; a None path
        or ``"-"`` (stdout) is skipped.
    inputs : iterable of path
        The files the command reads (logs, parameter files); None, ``"-"`` and device strings
        that are no file are skipped.
    """
    outs = [(o, p) for o, p in outputs if p and p != "-"]
    ins = [p for p in inputs if p and p != "-"]
    for opt, path in outs:
        for src in ins:
            if same_file(path, src):
                via = "" if os.path.abspath(path) == os.path.abspath(src) else " (the same file through a link)"
                raise OutputIsInputError(f"{opt} {path} is the input {src}{via}: writing it would destroy the "
                                         "input; give another file name (nothing was done)")
    for i, (opt, path) in enumerate(outs):
        for opt2, path2 in outs[i + 1:]:
            if os.path.abspath(path) == os.path.abspath(path2) or same_file(path, path2):
                raise OutputIsInputError(f"{opt} and {opt2} name the same file {path}: give each its own file "
                                         "(nothing was done)")


def write_atomic(path: str | os.PathLike[str], data: bytes | str, *, exclusive: bool = False,
                 mode: int = 0o644) -> Path:
    """Write ``data`` to ``path`` atomically and durably.

    The bytes go to a temporary file in the destination's folder, are flushed and synced, and the
    file is then renamed over ``path`` (:func:`os.replace`, atomic on one file system) and the
    folder synced. An interruption before the rename leaves the old file (or no file) and removes
    the temporary one; nothing ever holds part of the new contents under ``path``.

    Parameters
    ----------
    path : str or path-like
        The destination.
    data : bytes or str
        The contents (a str is written as UTF-8).
    exclusive : bool
        Refuse to replace an existing file (:class:`UsageError`), e.g. a backup: the temporary
        file is then linked to ``path``, which fails if it exists (no window where a file made
        meanwhile would be overwritten).
    mode : int
        The new file's permission bits (before the umask).

    Raises
    ------
    UsageError
        ``exclusive`` and ``path`` exists.
    SourceError
        The file cannot be written (folder missing, no permission, disk full).
    """
    p = Path(path)
    raw = data.encode("utf-8") if isinstance(data, str) else bytes(data)
    folder = p.parent if str(p.parent) else Path(".")
    if exclusive and (p.exists() or p.is_symlink()):
        raise UsageError(f"{str(p)!r} already exists; not overwriting it")
    try:
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{p.name}.", suffix=".tmp")
    except OSError as exc:
        raise SourceError(f"cannot write {str(p)!r}: {exc.strerror or exc}") from None
    try:
        try:
            umask = os.umask(0)
            os.umask(umask)
            os.fchmod(fd, mode & ~umask)
            with os.fdopen(fd, "wb") as f:
                f.write(raw)
                f.flush()
                os.fsync(f.fileno())
            if exclusive:
                _link_new(tmp, p)
            else:
                os.replace(tmp, p)
        except FileExistsError:
            raise UsageError(f"{str(p)!r} already exists; not overwriting it") from None
        except OSError as exc:
            raise SourceError(f"cannot write {str(p)!r}: {exc.strerror or exc}") from None
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    _sync_folder(folder)
    return p


def _link_new(tmp: str, p: Path) -> None:
    """Move ``tmp`` to the new name ``p``, failing (FileExistsError) if ``p`` exists: a hard link
    where the file system has them, else a rename after a last check."""
    try:
        os.link(tmp, p)
    except FileExistsError:
        raise
    except OSError:  # no hard links here (FAT, some network shares)
        if p.exists() or p.is_symlink():
            raise FileExistsError(str(p)) from None
        os.replace(tmp, p)
        return
    os.unlink(tmp)


def _sync_folder(folder: Path) -> None:
    """Make the rename durable (the folder's entry); not every system allows it (ignored)."""
    try:
        dfd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except OSError:
        pass
