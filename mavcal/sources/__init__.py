"""Log file readers: the only layer (with :mod:`mavcal.link`) that imports pymavlink.

Public entry points: :func:`read_log` (a log file -> :class:`ImuLog`), :func:`read_csv`,
:func:`is_device` (tells a device string from a file name), :func:`field_at` /
:func:`field_ned` for Earth's field. A live vehicle is recorded by :mod:`mavcal.link.live`
(:func:`mavcal.pipeline.open_source` takes a file or a device); this package knows nothing
of devices beyond refusing a device string with that advice.
"""
from mavcal.sources.types import ImuLog, LogEvent, ParamTimeline, SensorSeries  # noqa: F401


def __getattr__(name):  # lazy: importing the types must not import pymavlink
    if name in ("read_log", "read_csv", "is_device"):
        from mavcal.sources import reader

        return getattr(reader, name)
    if name in ("field_at", "field_ned"):
        from mavcal.sources import wmm

        return getattr(wmm, name)
    raise AttributeError(f"module 'mavcal.sources' has no attribute {name!r}")


__all__ = ["ImuLog", "LogEvent", "ParamTimeline", "SensorSeries", "read_log", "read_csv",
           "is_device", "field_at", "field_ned"]
