"""The test vehicle's parameter table and ArduPilot's PARAM_SET semantics.

:class:`ParamStore` holds a realistic subset of an ArduCopter parameter table and stores
values the way ``AP_Param`` does:

* ``AP_Param::set_float`` (:func:`ap_set_float`): integers get +/-0.01 in float32, are
  clamped to the type's range and truncated toward zero; floats are stored as float32;
  NaN and Inf are ignored;
* ``GCS_Param.cpp`` (:meth:`ParamStore.param_set`): an unknown name, NaN or Inf gets no
  reply; a parameter flagged ``AP_PARAM_FLAG_INTERNAL_USE_ONLY`` (here ``MIS_TOTAL``, as in
  ``AP_Mission``) is refused ("Param write denied" and an echo of the unchanged value) unless
  ``BRD_OPTIONS`` has ``ALLOW_SET_INTERNAL_PARM`` (bit 2): ``AP_Param::allow_set_via_mavlink``;
  so is a name in ``deny`` (a read-only defaults entry, ``@READONLY``, or a scripting lock on a
  real vehicle); setting the X element of a Vector3 parameter echoes all three elements,
  setting Y or Z echoes only that one (``AP_Param::send_parameter``).
  Device ids (``COMPASS_DEV_IDn``, ``INS_ACCn_ID``, ``INS_GYRn_ID``) are **writable**: their
  ``var_info`` entries are plain ``AP_GROUPINFO`` without the flag (their "@ReadOnly: True"
  is documentation for ground stations only), as ArduPilot SITL 4.7.0-dev confirms;
* at boot (:meth:`ParamStore.reorder_compass_params`), ``AP_Compass::_reorder_compass_params``
  moves whole compass parameter sets so that slot i holds the compass whose device id is
  ``COMPASS_PRIO{i+1}_ID``.

Every per-instance calibration name comes from :mod:`mavcal.ardupilot.firmware`'s name
builders (``compass_param_names``, ``accel_param_names``, ``gyro_param_names``,
``board_param_names``); only configuration parameters mavcal never reads or writes are
spelled here.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import cast

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavcal.ardupilot import firmware as fw
from mavcal.autopilot.rotations import CUSTOM_1, CUSTOM_2, ROTATIONS

__all__ = ["INT8", "INT16", "INT32", "REAL32", "ParamRow", "ParamStore", "SetOutcome", "ap_set_float",
           "default_param_table", "calibration_param_names", "COMPASS_DEV_IDS", "N_COMPASS_SLOTS", "N_IMUS",
           "INTERNAL_USE_ONLY", "BRD_OPTIONS", "ALLOW_SET_INTERNAL_PARM"]

INT8, INT16, INT32, REAL32 = (mavlink2.MAV_PARAM_TYPE_INT8, mavlink2.MAV_PARAM_TYPE_INT16,
                              mavlink2.MAV_PARAM_TYPE_INT32, mavlink2.MAV_PARAM_TYPE_REAL32)
_INT_RANGE = {INT8: (-128, 127), INT16: (-32768, 32767), INT32: (-2147483648, 2147483647)}

#: compass slots and IMUs the vehicle has
N_COMPASS_SLOTS = 3
N_IMUS = 3
#: device ids of the three compasses (slot order of the default table)
COMPASS_DEV_IDS: tuple[int, int, int] = (97539, 131874, 263178)
_ACCEL_IDS = (2753028, 2753036, 2753044)
_GYRO_IDS = (2752772, 2752780, 2752788)
#: COMPASS_DEV_ID4..8: compasses detected without a slot (none here)
_EXTRA_COMPASS_DEV_IDS = tuple(f"COMPASS_DEV_ID{n}" for n in range(4, 9))


def ap_set_float(value: float, param_type: int) -> float | None:
    """What ``AP_Param::set_float`` stores for ``value``; None for NaN/Inf (ignored)."""
    if math.isnan(value) or math.isinf(value):
        return None
    if param_type in _INT_RANGE:
        v = np.float32(value)
        add = np.float32(-0.01) if v < 0 else np.float32(0.01)
        v = np.float32(v + add)
        lo, hi = _INT_RANGE[param_type]
        clamped = min(max(float(v), lo), hi)
        return float(int(clamped))  # C cast: truncation toward zero
    return float(np.float32(value))


@dataclass(frozen=True)
class ParamRow:
    """One parameter: name, MAV_PARAM_TYPE, default, and the Vector3 it belongs to (if any)."""

    name: str
    param_type: int
    default: float
    vector: tuple[str, str, str] | None = None


def _names3(names: object) -> tuple[str, str, str]:
    a, b, c = cast(Sequence[object], names)
    return (str(a), str(b), str(c))


def _name(names: Mapping[str, object], key: str) -> str:
    return str(names[key])


def default_param_table() -> list[ParamRow]:
    """A realistic subset of an ArduCopter parameter table, in ArduPilot's group order
    (the order does not matter to the protocol)."""
    t: list[ParamRow] = []

    def s(name: str, ptype: int, default: float) -> None:
        t.append(ParamRow(name, ptype, float(default)))

    def vec(names: object, default: Sequence[float] = (0.0, 0.0, 0.0)) -> None:
        three = _names3(names)
        t.extend(ParamRow(n, REAL32, float(d), three) for n, d in zip(three, default))

    board = fw.board_param_names()
    s("FORMAT_VERSION", INT16, 120)
    s("SYSID_THISMAV", INT16, 1)
    s("SYSID_MYGCS", INT16, 255)
    s("ARMING_CHECK", INT32, 1)
    s("LOG_BITMASK", INT32, 176126)
    for ch in (0, 1):
        for st, d in (("RAW_SENS", 0), ("EXT_STAT", 2), ("RC_CHAN", 0), ("POSITION", 0),
                      ("EXTRA1", 0), ("EXTRA2", 0), ("EXTRA3", 0), ("PARAMS", 0)):
            s(f"SR{ch}_{st}", INT16, d)
    s(BRD_OPTIONS, INT32, 0)  # SITL 4.7.0-dev: 0
    s("MIS_TOTAL", INT16, 0)
    s("AHRS_EKF_TYPE", INT8, 3)
    s(_name(board, "orientation"), INT8, 0)
    vec(board["trim"])
    s("CUST_ROT_ENABLE", INT8, 0)
    for key in ("custom1", "custom2"):
        for n in _names3(board[key]):
            s(n, REAL32, 0)
    _compass_rows(s, vec)
    _imu_rows(s, vec)
    for servo in (5, 6, 7, 8):
        s(f"SERVO{servo}_FUNCTION", INT16, 0)
    return t


def _compass_rows(s, vec) -> None:
    """AP_Compass.cpp var_info: the per-slot sets, priorities and the compass options."""
    s("COMPASS_ENABLE", INT8, 1)
    for slot, devid in enumerate(COMPASS_DEV_IDS):
        cn = fw.compass_param_names(slot)
        vec(cn["ofs"])
        vec(cn["dia"], (1.0, 1.0, 1.0))
        vec(cn["odi"])
        vec(cn["mot"])
        s(_name(cn, "scale"), REAL32, 0)
        s(_name(cn, "orient"), INT8, 0)
        s(_name(cn, "external"), INT8, 1 if slot == 0 else 0)
        s(_name(cn, "use"), INT8, 1)
        s(_name(cn, "dev_id"), INT32, devid)
    for slot, devid in enumerate(COMPASS_DEV_IDS):
        s(_name(fw.compass_param_names(slot), "prio_id"), INT32, devid)
    for n in _EXTRA_COMPASS_DEV_IDS:
        s(n, INT32, 0)
    s(_name(fw.board_param_names(), "motct"), INT8, 0)
    s("COMPASS_CAL_FIT", REAL32, 16)
    s("COMPASS_OFFS_MAX", INT16, 1800)
    s("COMPASS_AUTO_ROT", INT8, 2)
    s("COMPASS_LEARN", INT8, 0)
    s("COMPASS_DEC", REAL32, 0)
    s("COMPASS_AUTODEC", INT8, 1)
    s("COMPASS_OPTIONS", INT16, 0)
    s("COMPASS_FLTR_RNG", INT8, 0)
    s("COMPASS_DISBLMSK", INT32, 0)


def _imu_rows(s, vec) -> None:
    """AP_InertialSensor.cpp: offsets, scales and ids of the three IMUs, and the options."""
    for i in range(N_IMUS):
        an = fw.accel_param_names(i)
        vec(fw.gyro_param_names(i)["ofs"])
        vec(an["ofs"])
        vec(an["scale"], (1.0, 1.0, 1.0))
    for i in range(N_IMUS):
        s(_name(fw.accel_param_names(i), "id"), INT32, _ACCEL_IDS[i])
        s(_name(fw.gyro_param_names(i), "id"), INT32, _GYRO_IDS[i])
    for n in range(1, N_IMUS + 1):
        s(f"INS_ACC{n}_CALTEMP", REAL32, -300)
    s("INS_TRIM_OPTION", INT8, 1)
    s("INS_ACCEL_FILTER", INT16, 20)
    s("INS_GYRO_FILTER", INT16, 20)
    s("INS_USE", INT8, 1)
    s("INS_USE2", INT8, 1)
    s("INS_USE3", INT8, 1)
    s("INS_FAST_SAMPLE", INT8, 1)


#: parameters flagged ``AP_PARAM_FLAG_INTERNAL_USE_ONLY`` in the table (``AP_Mission``'s
#: ``MIS_TOTAL``); a PARAM_SET of one is denied unless BRD_OPTIONS allows it
INTERNAL_USE_ONLY: frozenset[str] = frozenset({"MIS_TOTAL"})
BRD_OPTIONS = "BRD_OPTIONS"
#: ``AP_BoardConfig::board_options::ALLOW_SET_INTERNAL_PARM``
ALLOW_SET_INTERNAL_PARM = 1 << 2


def calibration_param_names() -> tuple[str, ...]:
    """Every parameter ``firmware.*_cal_from_params`` reads for the vehicle's sensors."""
    names: list[str] = [_name(fw.board_param_names(), "orientation")]
    for slot in range(N_COMPASS_SLOTS):
        cn = fw.compass_param_names(slot)
        for k in ("ofs", "dia", "odi", "mot"):
            names += _names3(cn[k])
        names += [_name(cn, "scale"), _name(cn, "orient"), _name(cn, "external")]
    for i in range(N_IMUS):
        an = fw.accel_param_names(i)
        names += _names3(an["ofs"]) + _names3(an["scale"])
    return tuple(names)


def _compass_set_keys(slot: int) -> list[str]:
    """The names of one compass parameter set that move together at boot."""
    cn = fw.compass_param_names(slot)
    out: list[str] = []
    for k in ("ofs", "dia", "odi", "mot"):
        out += _names3(cn[k])
    out += [_name(cn, k) for k in ("scale", "orient", "use", "dev_id", "external")]
    return out


@dataclass(frozen=True)
class SetOutcome:
    """What a PARAM_SET did: ``stored`` value (None if not stored), ``denied`` (send
    "Param write denied" and echo the old value), ``echo`` (names to echo as PARAM_VALUE)."""

    stored: float | None
    denied: bool = False
    echo: tuple[str, ...] = ()


class ParamStore:
    """Parameter names, types and stored values, with ArduPilot's storage semantics.

    Not thread-safe: the vehicle holds its lock around every call.
    """

    def __init__(self, overrides: Mapping[str, float] | None = None, deny: Sequence[str] = ()) -> None:
        table = default_param_table()
        self.names: list[str] = [r.name for r in table]
        self.types: dict[str, int] = {r.name: r.param_type for r in table}
        self.values: dict[str, float] = {}
        for r in table:
            self.values[r.name] = self._stored(r.default, r.param_type)
        self._vector_of: dict[str, tuple[str, str, str]] = {r.name: r.vector for r in table if r.vector}
        self.denied = frozenset(deny)
        for n, v in (overrides or {}).items():
            if n not in self.values:
                raise KeyError(f"unknown parameter {n!r}")
            self.values[n] = self._stored(float(v), self.types[n])

    @staticmethod
    def _stored(value: float, param_type: int) -> float:
        stored = ap_set_float(value, param_type)
        if stored is None:
            raise ValueError("value must be finite")
        return stored

    def set_local(self, name: str, value: float) -> float:
        """Store ``value`` as the vehicle would (KeyError if unknown, ValueError if not finite)."""
        stored = self._stored(float(value), self.types[name])
        self.values[name] = stored
        return stored

    def param_set(self, name: str, value: float) -> SetOutcome:
        """A PARAM_SET from a GCS (``GCS_MAVLINK::handle_param_set``; its param_type is ignored)."""
        if name not in self.values or math.isnan(value) or math.isinf(value):
            return SetOutcome(None)  # silently ignored: no reply
        if not self.allow_set_via_mavlink(name):
            return SetOutcome(None, denied=True, echo=(name,))
        stored = self.set_local(name, value)
        vector = self._vector_of.get(name)
        # AP_Param::send_parameter: the first element's pointer is the vector's, so a set of X
        # echoes all three; a set of Y or Z echoes only itself
        return SetOutcome(stored, echo=vector if vector is not None and vector[0] == name else (name,))

    def allow_set_via_mavlink(self, name: str) -> bool:
        """``AP_Param::allow_set_via_mavlink``: not a ``deny`` name (read-only), and not flagged
        internal-use-only unless ``BRD_OPTIONS`` has ``ALLOW_SET_INTERNAL_PARM``."""
        if name in self.denied:
            return False
        if name in INTERNAL_USE_ONLY:
            return (int(self.values[BRD_OPTIONS]) & ALLOW_SET_INTERNAL_PARM) != 0
        return True

    def reorder_compass_params(self) -> None:
        """``AP_Compass::_reorder_compass_params``: slot i gets the set of the compass whose
        device id is ``COMPASS_PRIO{i+1}_ID``; unclaimed sets fill the empty slots in order."""
        p = self.values
        keys = [_compass_set_keys(i) for i in range(N_COMPASS_SLOTS)]
        dev_key = [_name(fw.compass_param_names(i), "dev_id") for i in range(N_COMPASS_SLOTS)]
        sets = [[p[k] for k in keys[i]] for i in range(N_COMPASS_SLOTS)]
        by_id = {int(p[dev_key[i]]): sets[i] for i in range(N_COMPASS_SLOTS) if int(p[dev_key[i]]) != 0}
        new: list[list[float] | None] = []
        for i in range(N_COMPASS_SLOTS):
            prio = int(p[_name(fw.compass_param_names(i), "prio_id")])
            new.append(by_id.pop(prio) if prio in by_id else None)
        leftovers = list(by_id.values())
        for i in range(N_COMPASS_SLOTS):
            if new[i] is None and leftovers:
                new[i] = leftovers.pop(0)
        for i, values in enumerate(new):
            if values is not None:
                p.update(zip(keys[i], values))

    def bad_compass_rotation(self) -> bool:
        """An external compass's ``COMPASS_ORIENTn`` is no rotation the firmware knows: its
        ``Vector3::rotate`` flags ``AP_InternalError::error_t::bad_rotation`` (an internal
        compass ignores ORIENT)."""
        for slot in range(N_COMPASS_SLOTS):
            cn = fw.compass_param_names(slot)
            orient = int(self.values[_name(cn, "orient")])
            if self.values[_name(cn, "external")] and orient not in ROTATIONS and orient not in (CUSTOM_1, CUSTOM_2):
                return True
        return False

    def compass_dev_ids(self) -> list[int]:
        """``COMPASS_DEV_ID{,2,3}`` per slot."""
        return [int(self.values[_name(fw.compass_param_names(i), "dev_id")]) for i in range(N_COMPASS_SLOTS)]

    def custom_rotation_angles(self) -> dict[int, tuple[float, float, float]]:
        """{101: CUST_ROT1_ROLL/PITCH/YAW, 102: CUST_ROT2_*} in degrees (AP_CustomRotations
        builds the matrices once, at boot)."""
        board = fw.board_param_names()
        out: dict[int, tuple[float, float, float]] = {}
        for value, key in ((CUSTOM_1, "custom1"), (CUSTOM_2, "custom2")):
            a, b, c = (self.values[n] for n in _names3(board[key]))
            out[value] = (a, b, c)
        return out
