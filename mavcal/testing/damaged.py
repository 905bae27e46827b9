"""Damaged inputs and what a person may be told about them (issue 35, items 9 and 10).

* :func:`python_exception_named` -- the Python exception class a line names (``KeyError``,
  ``struct.error``, ``ULogException``...), or None: an error line shown to a person must say what
  is wrong with the file, never which exception a parser raised.
* :func:`error_line_problem` -- what is wrong with a CLI run's stderr for a damaged input (not
  exactly one ``mavcal: error:`` line, an internal error, a Python exception's name), or None.
* :func:`ulog_definitions_loop` -- the smallest ULog on which pyulog 1.3's
  ``ULog._read_file_definitions`` never returns (the loop reported upstream in issue 35's note).
"""
from __future__ import annotations

import builtins
import re
import struct

__all__ = ["python_exception_named", "error_line_problem", "ulog_definitions_loop"]

_BUILTIN = sorted((n for n, v in vars(builtins).items()
                   if isinstance(v, type) and issubclass(v, BaseException) and not issubclass(v, Warning)),
                  key=len, reverse=True)
#: builtin exception classes, the parsers' own, and any ``...Error`` / ``...Exception`` class-like word
_NAMED = re.compile(r"\b(?:" + "|".join(_BUILTIN)
                    + r"|struct\.error|ULogException|[A-Z][A-Za-z0-9]*(?:Error|Exception))\b")


def python_exception_named(line: str) -> str | None:
    """The first Python exception class named in ``line`` (``"KeyError"``), or None."""
    m = _NAMED.search(line)
    return m.group(0) if m else None


def error_line_problem(code: int, stderr: str, ok_codes: tuple[int, ...] = (0, 7)) -> str | None:
    """What is wrong with a run that ended with ``code`` and printed ``stderr``: an exit code outside
    ``ok_codes`` must come with exactly one ``mavcal: error:`` line naming no Python exception (an
    internal error, exit 70, always is a problem). None when all is well."""
    lines = [x for x in stderr.splitlines() if x.strip()]
    if code in ok_codes:
        return None
    if len(lines) != 1 or not lines[0].startswith("mavcal: error:"):
        return f"exit {code} with {len(lines)} stderr lines: " + " | ".join(lines)[:300]
    named = python_exception_named(lines[0])
    if named:
        return f"exit {code}, the line names the Python exception {named}: {lines[0][:300]}"
    return None


def ulog_definitions_loop(payload_size: int = 10001) -> bytes:
    """A 16-byte ULog file header, then one message header of an unknown type (``b``) declaring
    ``payload_size`` (> 10,000) bytes, and ``payload_size - 1`` zero bytes: the file ends 2 bytes
    short of the declared payload.

    pyulog 1.3 (``pyulog/core.py``, ``ULog._read_file_definitions``) reads the payload (short, at
    the end of the file), calls the header corrupt (``_check_packet_corruption``: size > 10000) and
    seeks ``-2 - msg_size`` from where the short read ended to step one byte past the header: that
    lands back on the header itself, and the loop reads it again, forever."""
    if payload_size <= 10000 or payload_size > 0xFFFF:
        raise ValueError("payload_size must be in 10001..65535 (pyulog's 'corrupt' sizes)")
    header = b"ULog\x01\x12\x35\x01" + bytes(8)
    return header + struct.pack("<HB", payload_size, ord("b")) + bytes(payload_size - 1)
