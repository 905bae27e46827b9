"""Read and write ArduPilot ``.param`` files (the format MAVProxy and Mission Planner load).

Format
------
One parameter per line, ``NAME,VALUE`` or ``NAME VALUE`` (any run of spaces, tabs or one
comma), ``#`` starts a comment (whole line or end of line), blank lines are ignored.
QGroundControl's saved parameter files (``VEHICLE COMPONENT NAME VALUE TYPE``, tab-separated)
are read too.
Values are decimal (``1.5``, ``-2e-07``) or hexadecimal integers (``0x1F``), as
``pymavlink.mavparm.MAVParmDict.load`` accepts them. Names are at most 16 characters of
``[A-Z0-9_]`` (ArduPilot's ``AP_MAX_NAME_SIZE``).

Writing uses ``NAME,VALUE`` sorted by name (Mission Planner's layout; MAVProxy reads it too)
and prints every value as the *shortest decimal that rounds back to the same float32*, so
nothing is lost (MAVProxy's own ``%f`` keeps 6 decimals, which loses small values).
"""
from __future__ import annotations

import logging
import math
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Union

import numpy as np

from mavcal.autopilot.mavlink import valid_param_name
from mavcal.errors import SourceError, UsageError
from mavcal.outputs import write_atomic

__all__ = ["ParamFileError", "read_param_file", "parse_param_text", "write_param_file",
           "format_param_value"]

log = logging.getLogger(__name__)

PathLike = Union[str, "os.PathLike[str]"]


class ParamFileError(SourceError, ValueError):
    """A .param file cannot be read or has a malformed line (exit code 3).

    ``line`` is the 1-based line number of the bad line, or None.
    """

    def __init__(self, message: str, line: int | None = None) -> None:
        super().__init__(message)
        self.line = line


def format_param_value(value: float) -> str:
    """Shortest decimal text that reads back as the same float32 as ``value``.

    Parameters
    ----------
    value : float
        Any finite number; it is first rounded to float32 (what the vehicle stores).

    Returns
    -------
    str
        E.g. ``"0.1"``, ``"-12.375"``, ``"1234567"``, ``"1e-07"``.
    """
    v = float(value)
    if not math.isfinite(v):
        raise UsageError(f"parameter value must be finite, got {value!r}")
    f = np.float32(v)
    if not np.isfinite(f):
        raise UsageError(f"parameter value {value!r} does not fit a float32")
    if f == 0:
        return "0"
    if f == np.round(f) and abs(f) < 1e9:
        return str(int(f))
    a = abs(float(f))
    if 1e-4 <= a < 1e9:
        return np.format_float_positional(f, unique=True, trim="-")
    return np.format_float_scientific(f, unique=True, trim="-", exp_digits=1).replace("e+", "e")


def _parse_value(text: str, lineno: int, source: str) -> float:
    t = text.strip()
    try:
        if t.lower().startswith(("0x", "-0x", "+0x")):
            v = float(int(t, 16))
        else:
            v = float(t)
    except ValueError:
        raise ParamFileError(f"{source}:{lineno}: value {t!r} is not a number", lineno) from None
    if not math.isfinite(v):
        raise ParamFileError(f"{source}:{lineno}: value {t!r} is not finite", lineno)
    return v


def parse_param_text(text: str, source: str = "<text>") -> dict[str, float]:
    """Parse the contents of a .param file.

    Parameters
    ----------
    text : str
        File contents.
    source : str
        Name used in error messages.

    Returns
    -------
    dict of str to float
        Parameters in file order. A name given twice keeps the last value (as MAVProxy does)
        and logs a warning.

    Raises
    ------
    ParamFileError
        On a malformed line (wrong field count, bad name, value not a finite number); the
        message carries ``source:line``.
    """
    out: dict[str, float] = {}
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        fields = line.replace(",", " ").split()
        if len(fields) == 5 and all(f.isdigit() for f in (fields[0], fields[1], fields[4])):
            fields = fields[2:4]  # QGroundControl's "vehicle component NAME VALUE type" (tab-separated)
        if len(fields) != 2:
            raise ParamFileError(
                f"{source}:{lineno}: expected 'NAME VALUE' or 'NAME,VALUE', got {raw.strip()!r}", lineno)
        name, value = fields
        if not valid_param_name(name):
            raise ParamFileError(
                f"{source}:{lineno}: bad parameter name {name!r} (at most 16 characters of A-Z, 0-9, _)",
                lineno)
        if name in out:
            log.warning("%s:%d: %s given again; the last value wins", source, lineno, name)
        out[name] = _parse_value(value, lineno, source)
    return out


def read_param_file(path: PathLike) -> dict[str, float]:
    """Read a .param file (see the module docstring for the format).

    Raises
    ------
    ParamFileError
        If the file is missing, unreadable, not text, has a malformed line or holds no
        parameter at all (an empty file is unreadable input, exit code 3, not a usage error).
        A UTF-8 byte-order mark (as some Windows editors write) is accepted.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise ParamFileError(f"cannot read parameter file {str(p)!r}: {exc}") from None
    params = parse_param_text(text, source=str(p))
    if not params:
        raise ParamFileError(f"{str(p)!r} holds no parameters (empty, or only comments)")
    return params


def write_param_file(path: PathLike, params: Mapping[str, float], *, header: Iterable[str] | None = None,
                     exclusive: bool = False, comments: Mapping[str, str] | None = None) -> Path:
    """Write ``params`` as a .param file, sorted by name, atomically and durably
    (:func:`mavcal.outputs.write_atomic`: an existing file stays whole until the new one replaces it).

    Parameters
    ----------
    path : str or path-like
        Destination.
    params : mapping of str to float
        Parameter values; each is written at full float32 precision.
    header : iterable of str, optional
        Comment lines written first (``# `` is prepended).
    exclusive : bool
        If True, refuse to overwrite an existing file (used for backups).
    comments : mapping of str to str, optional
        An end-of-line comment per parameter (``NAME,VALUE  # text``; readers strip it).

    Returns
    -------
    pathlib.Path
        The path written.

    Raises
    ------
    UsageError
        Bad name or value, or ``exclusive`` and the file exists.
    SourceError
        The file cannot be written.
    """
    p = Path(path)
    lines = [f"# {h}" for h in (header or ())]
    for name in sorted(params):
        if not valid_param_name(name):
            raise UsageError(f"bad parameter name {name!r}")
        note = (comments or {}).get(name)
        tail = "  # " + " ".join(str(note).split()) if note else ""
        lines.append(f"{name},{format_param_value(params[name])}{tail}")
    data = ("\n".join(lines) + "\n").encode("utf-8")
    write_atomic(p, data, exclusive=exclusive)
    return p
