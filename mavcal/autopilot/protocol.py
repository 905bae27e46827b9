"""The write rules of a parameter name, each autopilot answering for the names it knows: its value
limits, its device ids and slots, which vector it belongs to (written whole), whether it needs a
reboot, which force-saves a change calls for, and the order and detours of a write (PX4's ``CAL_*``
vectors).

Every model of the registry (:func:`mavcal.autopilot.registry.models`) is asked; a name no
autopilot knows has no limit, no group, needs no reboot and calls for no force-save.
"""
from __future__ import annotations

from collections.abc import Iterable, Mapping

from mavcal.autopilot.limits import LimitViolation
from mavcal.autopilot.registry import models

__all__ = ["SlotMap", "vector_group", "needs_reboot", "force_save_kinds", "detoured_order", "detour_dwell_s",
           "check_limits", "failing_kinds", "related_names", "parse_slot_map", "id_names", "device_id_problems",
           "remap_changes"]

#: log slot -> vehicle slot (0-based)
SlotMap = Mapping[int, int]


# --------------------------------------------------------------------------- the write's order

def vector_group(name: str) -> tuple[str, str, str] | None:
    """The three element names of the vector parameter ``name`` belongs to (``COMPASS_OFS2_Y`` ->
    its X, Y, Z), or None for a scalar."""
    return next((g for g in (m.vector_group(name) for m in models()) if g is not None), None)


def needs_reboot(name: str, value: float | None = None) -> bool:
    """True if a new ``value`` of ``name`` only takes effect after a reboot."""
    return any(m.needs_reboot(name, value) for m in models())


def force_save_kinds(names: Iterable[str]) -> tuple[str, ...]:
    """Which force-saves (``"compass"``, ``"accel"``) a set of changed parameters calls for."""
    names = list(names)
    return tuple(dict.fromkeys(k for m in models() for k in m.force_save_kinds(names)))


def detoured_order(changes: Mapping[str, float]) -> tuple[dict[str, float], dict[str, float]]:
    """The order in which to send ``changes`` and the detours to send before them (a name whose
    autopilot takes none is sent as given, without detour)."""
    order, detours = dict(changes), {}
    for m in models():
        order, d = m.detoured_order(order)
        detours.update(d)
    return order, detours


def detour_dwell_s() -> float:
    """How long the vehicle is let see a write's detours (s)."""
    return max(m.detour_dwell_s for m in models())


# --------------------------------------------------------------------------- the values' limits

def check_limits(values: Mapping[str, float], vehicle: Mapping[str, float] | None = None) -> list[LimitViolation]:
    """The values in ``values`` (about to be written, judged over the vehicle's current ``vehicle``)
    that break their autopilot's limit, in the order of each autopilot's check; empty when
    everything is within its limit."""
    return [v for m in models() for v in m.check_limits(values, vehicle)]


def failing_kinds(values: Mapping[str, float], vehicle: Mapping[str, float] | None = None) -> set[str]:
    """Sensor kinds (``"compass"``, ``"accel"``) touched by ``values`` whose resulting calibration
    breaks a limit: these must not be force-saved."""
    return {k for m in models() for k in m.failing_kinds(values, vehicle)}


def related_names(names: Iterable[str]) -> list[str]:
    """What judging ``names`` needs from the vehicle besides themselves (the limit-checked names of
    each sensor they touch, the limits and device ids that go with them)."""
    names = list(names)
    return list(dict.fromkeys(n for m in models() for n in m.related_names(names)))


# --------------------------------------------------------------------------- device ids and slots

def parse_slot_map(text: str, kind: str) -> tuple[int, int]:
    """``"LOGSLOT:VEHICLESLOT"`` (1-based) -> 0-based (log, vehicle), for the autopilot whose slots
    are by position (one that finds a calibration by device id has none to map). Raises ValueError
    with a one-line message for anything else."""
    limit = next(n for n in (m.slot_limit(kind) for m in models()) if n is not None)
    try:
        a, b = (int(x) for x in text.split(":"))
    except ValueError:
        raise ValueError(f"expected LOGSLOT:VEHICLESLOT (1..{limit}), got {text!r}") from None
    if not (1 <= a <= limit and 1 <= b <= limit):
        raise ValueError(f"{kind} slots are 1..{limit}, got {text!r}")
    return a - 1, b - 1


def id_names() -> list[str]:
    """The device id (and priority) names every vehicle table of each autopilot holds."""
    return list(dict.fromkeys(n for m in models() for n in m.id_names()))


def device_id_problems(changes: Iterable[str], log_params: Mapping[str, float], vehicle: Mapping[str, float],
                       *, compass_map: SlotMap | None = None, imu_map: SlotMap | None = None) -> list[str]:
    """One-line refusals for the sensors ``changes`` touches whose log and vehicle device ids differ
    (empty: the ids match); a slot in ``compass_map``/``imu_map`` (log -> vehicle, 0-based) is not
    compared by id."""
    changes = list(changes)
    return [p for m in models() for p in m.device_id_problems(changes, log_params, vehicle,
                                                              compass_map=compass_map, imu_map=imu_map)]


def remap_changes(changes: Mapping[str, float], *, compass_map: SlotMap | None = None,
                  imu_map: SlotMap | None = None) -> dict[str, float]:
    """``changes`` with each mapped sensor's values moved from its log slot to its vehicle slot."""
    out = dict(changes)
    for m in models():
        out = m.remap_changes(out, compass_map=compass_map, imu_map=imu_map)
    return out
