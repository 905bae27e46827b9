"""mavcal.memory: the freed heap given back between the stages of a long log (issue 11)."""
from __future__ import annotations

import sys

import numpy as np
import pytest

from mavcal import memory


def _rss_kb() -> int:
    with open("/proc/self/status") as f:
        return int(f.read().split("VmRSS:")[1].split()[0])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc_trim")
def test_release_free_memory_gives_the_freed_heap_back():
    # many mid-sized blocks (under glibc's mmap threshold: on the heap), all but the last freed
    blocks = [np.ones(8_000) for _ in range(4_000)]  # 256 MB of 64 kB blocks
    keep = blocks[-1]
    del blocks
    before = _rss_kb()
    assert memory.release_free_memory() is True
    after = _rss_kb()
    assert before - after > 100_000  # more than 100 MB of the 256 MB went back
    assert keep.sum() == 8_000


def test_release_is_safe_to_call_anywhere():
    assert isinstance(memory.release_free_memory(), bool)


def test_without_glibc_nothing_is_done(monkeypatch):
    class NoGlibc:  # e.g. macOS's libc: no malloc_trim
        pass

    monkeypatch.setattr(memory, "_TRIM", None)
    monkeypatch.setattr(memory, "_libc", lambda: NoGlibc())
    assert memory.release_free_memory() is False

    def missing():
        raise OSError("no C library")

    monkeypatch.setattr(memory, "_TRIM", None)
    monkeypatch.setattr(memory, "_libc", missing)
    assert memory.release_free_memory() is False
