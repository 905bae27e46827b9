"""The decoders' grow-in-place columns (mavcal.sources.framing.GrowArray) when a view of the map
is still referenced as it grows, as a sampling profiler's frame (a Dask worker's) can hold one
a moment: the column is copied into a new map instead of failing with "BufferError: mmap can't
resize" (seen once in tests/test_fleet_dask.py under load)."""
from __future__ import annotations

import numpy as np

from mavcal.sources.framing import GrowArray


def test_a_column_grows_and_trims_with_a_view_still_held():
    g = GrowArray(np.float64, (3,))
    g.extend(4000)[:] = np.arange(12000.0).reshape(4000, 3)
    held = g.rows()  # a view of the map, still referenced when it must grow
    g.extend(5000)[:] = 1.0  # past the capacity of 4096 rows: mremap refused, a copy instead
    held2 = g.rows()
    out = g.array()  # trimming with a view held: a copy too
    assert out.shape == (9000, 3)
    assert np.array_equal(out[:4000], np.arange(12000.0).reshape(4000, 3)) and (out[4000:] == 1.0).all()
    assert np.array_equal(held, out[:4000]) and np.array_equal(held2, out)  # the old views still read right
