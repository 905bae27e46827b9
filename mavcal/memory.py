"""Give the memory this process has freed back to the operating system.

glibc's ``malloc`` keeps freed heap memory for reuse: after a stage that made large
temporaries (reading a 100 MB log, the interval statistics) the process stays that much
bigger, and a forked fit worker that reuses those free chunks copies their pages. Between
the stages of a long log :func:`release_free_memory` hands them back (``malloc_trim``:
a few milliseconds); elsewhere than glibc it does nothing.
"""
from __future__ import annotations

import ctypes
import ctypes.util

__all__ = ["release_free_memory", "return_large_blocks"]

_TRIM = None  # libc's malloc_trim, False when there is none
_M_MMAP_THRESHOLD = -3  # mallopt's parameter number (malloc.h)


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


def return_large_blocks(threshold_bytes: int = 256 * 1024) -> bool:
    """From now on, allocate blocks of ``threshold_bytes`` or more as their own mappings, given
    back to the operating system when freed (``mallopt(M_MMAP_THRESHOLD)``; glibc raises its
    threshold as big blocks are freed, after which their memory stays with the process).
    For a fit worker, whose large arrays come and go; True when it could."""
    try:
        return bool(_libc().mallopt(_M_MMAP_THRESHOLD, int(threshold_bytes)))
    except (OSError, AttributeError, TypeError):  # not glibc
        return False
