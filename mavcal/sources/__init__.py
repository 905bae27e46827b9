"""Log and live-link readers: the only layer (with :mod:`mavcal.link`) that imports pymavlink.

Public entry points: :func:`open_source` (file or device string) and :func:`read_log`
(file), both returning an :class:`ImuLog`; :class:`LiveSource` for a live link;
:func:`field_at` / :func:`field_ned` for Earth's field.
"""
from mavcal.sources.types import ImuLog, LogEvent, ParamTimeline, SensorSeries  # noqa: F401


def __getattr__(name):  # lazy: importing the types must not import pymavlink
    if name in ("open_source", "read_log", "read_csv", "is_device"):
        from mavcal.sources import reader

        return getattr(reader, name)
    if name == "LiveSource":
        from mavcal.sources.live import LiveSource

        return LiveSource
    if name in ("field_at", "field_ned"):
        from mavcal.sources import wmm

        return getattr(wmm, name)
    raise AttributeError(f"module 'mavcal.sources' has no attribute {name!r}")


__all__ = ["ImuLog", "LogEvent", "ParamTimeline", "SensorSeries", "open_source", "read_log", "read_csv",
           "is_device", "LiveSource", "field_at", "field_ned"]
