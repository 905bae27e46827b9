"""Match compasses and IMUs by device id between a log (its calibration) and the vehicle.

A calibration computed from a log belongs to the *sensors* of that log, not to parameter slots:
ArduPilot moves whole compass parameter sets between slots at boot so that slot i holds the
compass whose id is ``COMPASS_PRIO{i+1}_ID`` (``AP_Compass::_reorder_compass_params``), and
users swap priorities. So before a log's values are written, each touched compass slot's
``COMPASS_DEV_ID{n}`` in the log must equal the vehicle's, and each IMU's ``INS_ACC*_ID`` too.

A mismatch is refused with both ids named, unless the user maps slots explicitly
(:func:`mavcal.autopilot.protocol.parse_slot_map`, ``--map-compass LOGSLOT:VEHICLESLOT`` / ``--map-imu``, 1-based);
:func:`remap_changes` then moves the values to the vehicle's slot. A vehicle whose slot no
longer holds the compass its priority names (a priority change waiting for a reboot) is
refused too: after the reboot the values would sit on another compass.
"""
from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from mavcal.ardupilot import firmware as fw
from mavcal.ardupilot.limits import sensor_of

__all__ = ["SlotMap", "device_id_problems", "remap_changes", "id_names"]

#: log slot -> vehicle slot (0-based)
SlotMap = Mapping[int, int]


@dataclass(frozen=True)
class _Slot:
    kind: str
    log: int
    vehicle: int


def _id_name(kind: str, k: int) -> str:
    return fw.compass_param_names(k)["dev_id"] if kind == "compass" else fw.accel_param_names(k)["id"]


def id_names() -> list[str]:
    """The compass device id and priority names and the accelerometer id names every ArduPilot
    table holds (3 compass slots, IMUs 1-3; INS4/INS5 names exist only on boards with them)."""
    out = []
    for k in range(fw.MAX_COMPASSES):
        cn = fw.compass_param_names(k)
        out += [cn["dev_id"], cn["prio_id"]]
    return out + [fw.accel_param_names(i)["id"] for i in range(3)]


def _get_id(params: Mapping[str, float], name: str) -> int | None:
    v = params.get(name)
    return int(v) if v is not None and int(v) != 0 else None


def _slots(names: Iterable[str], compass_map: SlotMap, imu_map: SlotMap) -> list[_Slot]:
    touched = sorted({s for s in map(sensor_of, names) if s is not None})
    return [_Slot(kind, k, (compass_map if kind == "compass" else imu_map).get(k, k)) for kind, k in touched]


def _where(vehicle: Mapping[str, float], kind: str, dev: int) -> int | None:
    n = fw.MAX_COMPASSES if kind == "compass" else fw.MAX_IMUS
    return next((j for j in range(n) if _get_id(vehicle, _id_name(kind, j)) == dev), None)


def _mismatch(s: _Slot, log_id: int, veh_id: int, vehicle: Mapping[str, float]) -> str:
    flag = "--map-compass" if s.kind == "compass" else "--map-imu"
    lname, vname = _id_name(s.kind, s.log), _id_name(s.kind, s.vehicle)
    msg = (f"{s.kind} {s.log + 1}: the log's device {log_id} ({lname}) is not the vehicle's device {veh_id} "
           f"({vname}); nothing written")
    there = _where(vehicle, s.kind, log_id)
    if there is not None:
        return msg + f"; the vehicle has device {log_id} in slot {there + 1}: use {flag} {s.log + 1}:{there + 1}"
    return msg + f"; if it is the same sensor, use {flag} {s.log + 1}:{s.vehicle + 1}"


def device_id_problems(changes: Iterable[str], log_params: Mapping[str, float], vehicle: Mapping[str, float],
                       *, compass_map: SlotMap | None = None, imu_map: SlotMap | None = None) -> list[str]:
    """One-line refusals for the sensors ``changes`` touches (empty: the ids match).

    Parameters
    ----------
    changes : iterable of str
        Parameter names of the calibration, in the log's slots.
    log_params : mapping
        The parameters in force in the log (``CalibrationRun.params_before``).
    vehicle : mapping
        The vehicle's values (at least the device ids and compass priorities).
    compass_map, imu_map : mapping of int to int, optional
        Explicit log slot -> vehicle slot (0-based); a mapped slot is not compared by id.
    """
    compass_map, imu_map = compass_map or {}, imu_map or {}
    out = []
    for s in _slots(changes, compass_map, imu_map):
        mapped = s.log in (compass_map if s.kind == "compass" else imu_map)
        log_id = _get_id(log_params, _id_name(s.kind, s.log))
        veh_id = _get_id(vehicle, _id_name(s.kind, s.vehicle))
        if not mapped and log_id is not None and veh_id is not None and log_id != veh_id:
            out.append(_mismatch(s, log_id, veh_id, vehicle))
        if s.kind == "compass":
            prio_name = fw.compass_param_names(s.vehicle)["prio_id"]
            prio = _get_id(vehicle, prio_name)
            if prio is not None and veh_id is not None and prio != veh_id:
                out.append(f"compass slot {s.vehicle + 1} of the vehicle holds device {veh_id} but {prio_name} is "
                           f"{prio}: the slots change at the next boot; reboot the vehicle first; nothing written")
    return out


def _slot_names(kind: str, k: int) -> list[str]:
    if kind == "compass":
        cn = fw.compass_param_names(k)
        return [*cn["ofs"], *cn["dia"], *cn["odi"], *cn["mot"], cn["scale"], cn["orient"], cn["external"],
                cn["use"]]
    an = fw.accel_param_names(k)
    return [*an["ofs"], *an["scale"]]


def remap_changes(changes: Mapping[str, float], *, compass_map: SlotMap | None = None,
                  imu_map: SlotMap | None = None) -> dict[str, float]:
    """``changes`` with each mapped sensor's values moved from its log slot to its vehicle slot."""
    rename: dict[str, str] = {}
    for kind, m in (("compass", compass_map or {}), ("accel", imu_map or {})):
        for a, b in m.items():
            rename.update(zip(_slot_names(kind, a), _slot_names(kind, b)))
    out = {rename.get(n, n): v for n, v in changes.items()}
    if len(out) < len(changes):
        raise ValueError("two log slots would be written to the same vehicle slot: map every slot that moves")
    return out
