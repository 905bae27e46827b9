"""Device ids and slots: which log slot is which vehicle slot, and the id parameters that go with a sensor.

The neutral layer's name for it: the rest of mavcal imports it from here, never from
:mod:`mavcal.ardupilot.devices`, which holds its ArduPilot implementation.

Transitional (issue 38, in part): the names below are still ArduPilot's implementation, re-exported
from :mod:`mavcal.ardupilot`; the rest of mavcal imports them from here so that the next step can
move them into per-autopilot model methods without touching the callers. Until then PX4 depends on
ArduPilot's code through this module, although no module outside the autopilot folders names it."""
from __future__ import annotations

from mavcal.ardupilot.devices import (
    SlotMap,
    device_id_problems,
    id_names,
    parse_slot_map,
    remap_changes,
)

__all__ = ["SlotMap", "device_id_problems", "id_names", "parse_slot_map", "remap_changes"]
