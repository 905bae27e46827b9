"""Device ids and slots: which log slot is which vehicle slot, and the id parameters that go with a sensor.

The neutral layer's name for it: the rest of mavcal imports it from here, never from
:mod:`mavcal.ardupilot.devices`, which holds its ArduPilot implementation."""
from __future__ import annotations

from mavcal.ardupilot.devices import (
    SlotMap,
    device_id_problems,
    id_names,
    parse_slot_map,
    remap_changes,
)

__all__ = ["SlotMap", "device_id_problems", "id_names", "parse_slot_map", "remap_changes"]
