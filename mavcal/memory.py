"""Give the memory this process has freed back to the operating system.

glibc's ``malloc`` keeps freed heap memory for reuse: after a stage that made large
temporaries (reading a 100 MB log, the interval statistics) the process stays that much
bigger, and a forked fit worker that reuses those free chunks copies their pages. Between
the stages of a long log :func:`release_free_memory` hands them back (``malloc_trim``:
a few milliseconds); elsewhere than glibc it does nothing. Measured on ``mavcal calibrate``
(``benchmarks/results/memory_machinery.md``): without it the process tree's peak is 12-16 %
higher on long logs.
"""
from __future__ import annotations

import ctypes
import ctypes.util

__all__ = ["release_free_memory"]

_TRIM = None  # libc's malloc_trim, False when there is none


def _malloc_trim():
    global _TRIM
    if _TRIM is None:
        try:
            _TRIM = _libc().malloc_trim
            _TRIM.argtypes, _TRIM.restype = [ctypes.c_size_t], ctypes.c_int
        except (OSError, AttributeError, TypeError):  # not glibc (macOS, Windows, musl without it)
            _TRIM = False
    return _TRIM


def _libc() -> ctypes.CDLL:
    """The C library: glibc's by its soname (``find_library`` would run ``ldconfig`` in a
    subprocess, forking this process with all its readings), else whatever ``find_library`` finds."""
    try:
        return ctypes.CDLL("libc.so.6")
    except OSError:
        return ctypes.CDLL(ctypes.util.find_library("c"))


def release_free_memory() -> bool:
    """Return the heap's free pages to the operating system; True when it could."""
    trim = _malloc_trim()
    if not trim:
        return False
    trim(0)
    return True
