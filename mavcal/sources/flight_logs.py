"""Which reader a flight log needs: a PX4 ULog (:mod:`mavcal.sources.flight_ulog`), a MAVLink
telemetry log (:mod:`mavcal.sources.flight_tlog`) or an ArduPilot DataFlash ``.bin``
(:mod:`mavcal.sources.flight_series`), by its first bytes and then its name."""
from __future__ import annotations

from pathlib import Path

from mavcal.errors import SourceError
from mavcal.sources.flight_series import FlightSeries, read_flight_series
from mavcal.sources.ulog import is_ulog

__all__ = ["read_flight_log"]


def read_flight_log(path: str | Path) -> FlightSeries:
    """The flight series of the log at ``path``, whichever kind it is."""
    p = Path(path)
    if not p.is_file():
        raise SourceError(f"{path}: no such file")
    if is_ulog(str(p)) or p.suffix.lower() == ".ulg":
        from mavcal.sources.flight_ulog import read_flight_ulog

        return read_flight_ulog(p)
    if p.suffix.lower() == ".tlog":
        from mavcal.sources.flight_tlog import read_flight_tlog

        return read_flight_tlog(p)
    return read_flight_series(p)
