"""The sensor series being assembled from message columns (:class:`SeriesSet`: one per sensor and
instance, first come first kept, sorted by time, repeated timestamps dropped) and the column helpers
every assembly uses (tlogs and live links: :mod:`mavcal.sources.assemble`; DataFlash logs:
:mod:`mavcal.sources.dataflash_assemble`).
"""
from __future__ import annotations

import re
from collections.abc import Mapping, Sequence

import numpy as np

from mavcal.sources.types import PackedValues, SensorSeries

__all__ = ["Columns", "FIRMWARE_RE", "SENSOR_ORDER", "SeriesSet", "column_matrix", "dedupe_sorted", "n_rows",
           "take_rows"]

#: per message type, a dict of field name -> numpy array (plus ``_index``, and for MAVLink ``_log_time_s``,
#: ``_sysid``, ``_compid``)
Columns = dict[str, dict[str, np.ndarray]]
SENSOR_ORDER = ("accel", "gyro", "mag")
#: a STATUSTEXT / MSG that names the firmware and its version
FIRMWARE_RE = re.compile(r"^((?:Ardu|APM:)\w*|Blimp|AP_Periph)\S*\s+V?\d+\.\d+\S*")


def column_matrix(c: Mapping[str, np.ndarray], names: Sequence[str]) -> np.ndarray:
    """(n, len(names)) float64 of the columns ``names`` (each cast straight into its column:
    no float copy of each column before the interleaving)."""
    cols = [np.asarray(c[n]) for n in names]
    out = np.empty((len(cols[0]) if cols else 0, len(cols)))
    for j, col in enumerate(cols):
        out[:, j] = col.reshape(len(col)) if col.ndim != 1 else col
    return out


def n_rows(c: Mapping[str, np.ndarray] | None) -> int:
    if not c:
        return 0
    for _k, v in c.items():
        return len(v)
    return 0


def take_rows(c: Mapping[str, np.ndarray], mask) -> dict[str, np.ndarray]:
    return {k: np.asarray(v)[mask] for k, v in c.items()}


def dedupe_sorted(time_s: np.ndarray, *arrays) -> tuple[np.ndarray, int]:
    """Index that sorts by time (stable) and drops repeated timestamps (duplicated packets)."""
    order = np.argsort(time_s, kind="stable")
    t = time_s[order]
    keep = np.ones(len(t), dtype=bool)
    keep[1:] = t[1:] != t[:-1]
    return order[keep], int((~keep).sum())


class SeriesSet:
    """The sensor series being assembled: at most one per (sensor, instance), first come first kept."""

    def __init__(self, warns: list[str]) -> None:
        self.warns = warns
        self.series: list[SensorSeries] = []
        self.taken: set[tuple[str, int]] = set()

    def has(self, sensor: str, inst: int) -> bool:
        return (sensor, inst) in self.taken

    def add(self, sensor: str, inst: int, msg: str, t: np.ndarray, v: np.ndarray | PackedValues,
            lt: np.ndarray | None, extra: Mapping[str, np.ndarray] | None = None, dup_label: str | None = None) -> None:
        """Keep a series for (sensor, instance) unless there is one already or ``t`` is empty."""
        if len(t) == 0 or self.has(sensor, inst):
            return
        self.keep(sensor, inst, msg, t, v, lt, extra, dup_label)

    def keep(self, sensor: str, inst: int, msg: str, t: np.ndarray, v: np.ndarray | PackedValues,
             lt: np.ndarray | None, extra: Mapping[str, np.ndarray] | None = None,
             dup_label: str | None = None) -> None:
        """Sort by time, drop repeated timestamps (stated in the warnings) and keep the series."""
        if len(t) < 2 or bool(np.all(t[1:] > t[:-1])):  # already sorted, no repeat: keep the arrays as they are
            self.series.append(SensorSeries(sensor, inst, msg, t, v, lt, dict(extra or {})))
            self.taken.add((sensor, inst))
            return
        order, ndup = dedupe_sorted(t)
        if ndup:
            self.warns.append(f"dropped {ndup} duplicated {dup_label or msg} samples (same timestamp)")
        v = v.take(order) if isinstance(v, PackedValues) else v[order]
        self.series.append(SensorSeries(sensor, inst, msg, t[order], v, None if lt is None else lt[order],
                                        {k: a[order] for k, a in (extra or {}).items()}))
        self.taken.add((sensor, inst))

    def sorted(self) -> tuple[SensorSeries, ...]:
        return tuple(sorted(self.series, key=lambda s: SENSOR_ORDER.index(s.sensor) * 100 + s.instance))
