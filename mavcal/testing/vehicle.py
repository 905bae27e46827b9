"""A loopback test vehicle that speaks MAVLink 2 the way ArduPilot does.

No autopilot binary can run in the test environment, so :class:`TestVehicle` emulates the
parts of ArduPilot that mavcal talks to, on real sockets bound to 127.0.0.1 only, in its own
thread:

* HEARTBEAT (sysid 1, compid 1, MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA).
* The parameter protocol of ``GCS_Param.cpp`` / ``AP_Param.cpp``:

  - PARAM_REQUEST_LIST streams every parameter with its index and the count;
  - PARAM_REQUEST_READ by index answers with that index; by name with index 65535 (-1);
    an unknown name or index gets no answer;
  - PARAM_SET of an unknown name, NaN or Inf is **silently ignored** (no reply); the
    ``param_type`` field is ignored; the value is converted to the stored type
    (``AP_Param::set_float``: integers get +/-0.01 in float32, are clamped to the type's
    range and truncated; floats are stored as float32) and echoed as PARAM_VALUE with
    ``param_index`` 65535; setting one element of a Vector3 parameter echoes all three;
  - internal-use-only parameters (device ids) are refused with STATUSTEXT
    "Param write denied" and an echo of the unchanged value.

* COMMAND_LONG: MAV_CMD_PREFLIGHT_CALIBRATION param2=76 / param5=76 (force-save compass /
  accel calibration, recorded in :attr:`TestVehicle.force_saves`), MAV_CMD_SET_MESSAGE_INTERVAL,
  MAV_CMD_REQUEST_MESSAGE / REQUEST_AUTOPILOT_CAPABILITIES (AUTOPILOT_VERSION),
  MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN (a simulated reboot: silent for ``reboot_s``, then the
  compass parameter sets are reordered by ``COMPASS_PRIOn_ID`` and the custom rotations are
  rebuilt, as at boot). Everything else gets MAV_RESULT_UNSUPPORTED. REQUEST_DATA_STREAM sets
  stream rates (no ACK, as ArduPilot).
* IMU streams RAW_IMU, SCALED_IMU2, SCALED_IMU3 (and ATTITUDE on EXTRA1) from a simulated
  vehicle with known *true* sensor errors, with the vehicle's **current** calibration
  parameters applied the way ArduPilot applies them (see :meth:`TestVehicle.corrected_sensors`)
  and converted to int16 by truncation toward zero.
* Fault injection per direction (drop / delay / duplicate), :meth:`kill`, :meth:`revive` and
  ``die_after_n_sets``.

Transports (``transport=``): ``"udpout"`` (the vehicle sends to the GCS port; the GCS uses
``udpin:127.0.0.1:PORT``), ``"udpin"`` (the vehicle listens; the GCS uses ``udpout:``) and
``"tcp"`` (the vehicle is a TCP server; the GCS uses ``tcp:``). :attr:`TestVehicle.gcs_device`
is the device string a GCS should open.

The sensor correction is :mod:`mavcal.ardupilot.firmware`'s forward model
(:func:`~mavcal.ardupilot.firmware.apply_accel` / :func:`~mavcal.ardupilot.firmware.apply_compass`
with the calibrations built from the current parameters by ``accel_cal_from_params`` /
``compass_cal_from_params``), so the vehicle applies exactly the model the rest of mavcal
inverts. Two things ArduPilot does at boot are kept on top of it: custom rotations (101/102)
use the ``CUST_ROTn_*`` angles read at the last boot, and a rotation value the firmware does
not know acts as NONE. Rotations are :func:`mavcal.ardupilot.rotations.rotation_matrix`.
"""
from __future__ import annotations

import dataclasses
import heapq
import itertools
import logging
import math
import random
import select
import socket
import threading
import time
from dataclasses import dataclass
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavcal.ardupilot import firmware as fw
from mavcal.ardupilot import rotations as _rotations

__all__ = ["TestVehicle", "VehicleTruth", "AccelTruth", "CompassTruth", "Faults",
           "default_param_table", "rotation_matrix", "euler_matrix"]

log = logging.getLogger(__name__)

GRAVITY_MSS = 9.80665

INT8, INT16, INT32, REAL32 = (mavlink2.MAV_PARAM_TYPE_INT8, mavlink2.MAV_PARAM_TYPE_INT16,
                              mavlink2.MAV_PARAM_TYPE_INT32, mavlink2.MAV_PARAM_TYPE_REAL32)
_INT_RANGE = {INT8: (-128, 127), INT16: (-32768, 32767), INT32: (-2147483648, 2147483647)}

# ------------------------------------------------------------------------------------------
# rotations (AP_Math conventions: R = Rz(yaw) Ry(pitch) Rx(roll), v' = R v), from
# mavcal.ardupilot.rotations
# ------------------------------------------------------------------------------------------
def euler_matrix(roll: float, pitch: float, yaw: float, degrees: bool = True) -> np.ndarray:
    """Body-to-earth DCM ``Rz(yaw) Ry(pitch) Rx(roll)`` (AP_Math ``Matrix3::from_euler``)."""
    if degrees:
        roll, pitch, yaw = (math.radians(a) for a in (roll, pitch, yaw))
    return _rotations.euler_to_matrix(roll, pitch, yaw)


def rotation_matrix(rotation: int, custom: Optional[Mapping[int, np.ndarray]] = None) -> np.ndarray:
    """Matrix of an ArduPilot ``Rotation`` enum value (0-43; 101/102 from ``custom``).

    Unknown values and ROTATION_CUSTOM_OLD (100) give the identity, as ``Vector3::rotate``
    does after flagging an internal error.
    """
    r = int(rotation)
    if r in _rotations.ROTATIONS:
        return np.array(_rotations.rotation_matrix(r))
    if custom is not None and r in custom:
        return np.array(custom[r], dtype=float)
    return np.eye(3)


def _f32(x: float) -> float:
    return float(np.float32(x))


def ap_set_float(value: float, param_type: int) -> Optional[float]:
    """What ``AP_Param::set_float`` stores for ``value``; None for NaN/Inf (ignored)."""
    if math.isnan(value) or math.isinf(value):
        return None
    if param_type in _INT_RANGE:
        v = np.float32(value)
        add = np.float32(-0.01) if v < 0 else np.float32(0.01)
        v = np.float32(v + add)
        lo, hi = _INT_RANGE[param_type]
        v = min(max(float(v), lo), hi)
        return float(int(v))  # C cast: truncation toward zero
    return _f32(value)


def _trunc_i16(x: float) -> int:
    """float -> int16 the way a C cast in the MAVLink send code does (toward zero, saturated)."""
    if not math.isfinite(x):
        return 0
    return int(max(-32768.0, min(32767.0, math.trunc(x))))


# ------------------------------------------------------------------------------------------
# parameter table
# ------------------------------------------------------------------------------------------
def _vec(prefix: str, default: Sequence[float] = (0.0, 0.0, 0.0)) -> List[Tuple[str, int, float, str]]:
    return [(f"{prefix}_{ax}", REAL32, float(d), prefix) for ax, d in zip("XYZ", default)]


def default_param_table() -> List[Tuple[str, int, float, Optional[str]]]:
    """A realistic subset of an ArduCopter parameter table.

    Returns
    -------
    list of (name, MAV_PARAM_TYPE, default, vector_prefix or None)
        In ArduPilot order of groups (the order does not matter to the protocol).
    """
    t: List[Tuple[str, int, float, Optional[str]]] = []

    def s(name: str, ptype: int, default: float) -> None:
        t.append((name, ptype, float(default), None))

    s("FORMAT_VERSION", INT16, 120)
    s("SYSID_THISMAV", INT16, 1)
    s("SYSID_MYGCS", INT16, 255)
    s("ARMING_CHECK", INT32, 1)
    s("LOG_BITMASK", INT32, 176126)
    for ch in (0, 1):
        for st, d in (("RAW_SENS", 0), ("EXT_STAT", 2), ("RC_CHAN", 0), ("POSITION", 0),
                      ("EXTRA1", 0), ("EXTRA2", 0), ("EXTRA3", 0), ("PARAMS", 0)):
            s(f"SR{ch}_{st}", INT16, d)
    s("AHRS_EKF_TYPE", INT8, 3)
    s("AHRS_ORIENTATION", INT8, 0)
    t += _vec("AHRS_TRIM")
    s("CUST_ROT_ENABLE", INT8, 0)
    for n in (1, 2):
        for ax in ("ROLL", "PITCH", "YAW"):
            s(f"CUST_ROT{n}_{ax}", REAL32, 0)
    # compass (AP_Compass.cpp var_info)
    s("COMPASS_ENABLE", INT8, 1)
    for sfx, ext_name, devid in (("", "COMPASS_EXTERNAL", 97539), ("2", "COMPASS_EXTERN2", 131874),
                                 ("3", "COMPASS_EXTERN3", 263178)):
        t += _vec(f"COMPASS_OFS{sfx}")
        t += _vec(f"COMPASS_DIA{sfx}", (1.0, 1.0, 1.0))
        t += _vec(f"COMPASS_ODI{sfx}")
        t += _vec(f"COMPASS_MOT{sfx}")
        s(f"COMPASS_SCALE{sfx}", REAL32, 0)
        s(f"COMPASS_ORIENT{sfx}", INT8, 0)
        s(ext_name, INT8, 1 if sfx == "" else 0)
        s(f"COMPASS_USE{sfx}", INT8, 1)
        s(f"COMPASS_DEV_ID{sfx}", INT32, devid)
    for n, devid in ((1, 97539), (2, 131874), (3, 263178)):
        s(f"COMPASS_PRIO{n}_ID", INT32, devid)
    for n in range(4, 9):
        s(f"COMPASS_DEV_ID{n}", INT32, 0)
    s("COMPASS_MOTCT", INT8, 0)
    s("COMPASS_CAL_FIT", REAL32, 16)
    s("COMPASS_OFFS_MAX", INT16, 1800)
    s("COMPASS_AUTO_ROT", INT8, 2)
    s("COMPASS_LEARN", INT8, 0)
    s("COMPASS_DEC", REAL32, 0)
    s("COMPASS_AUTODEC", INT8, 1)
    s("COMPASS_OPTIONS", INT16, 0)
    s("COMPASS_FLTR_RNG", INT8, 0)
    s("COMPASS_DISBLMSK", INT32, 0)
    # inertial sensors (AP_InertialSensor.cpp)
    for n, sfx in ((1, ""), (2, "2"), (3, "3")):
        t += _vec(f"INS_GYR{sfx}OFFS")
        t += _vec(f"INS_ACC{sfx}OFFS")
        t += _vec(f"INS_ACC{sfx}SCAL", (1.0, 1.0, 1.0))
    for sfx, acc_id, gyr_id in (("", 2753028, 2752772), ("2", 2753036, 2752780), ("3", 2753044, 2752788)):
        s(f"INS_ACC{sfx}_ID", INT32, acc_id)
        s(f"INS_GYR{sfx}_ID", INT32, gyr_id)
    for n in (1, 2, 3):
        s(f"INS_ACC{n}_CALTEMP", REAL32, -300)
    s("INS_TRIM_OPTION", INT8, 1)
    s("INS_ACCEL_FILTER", INT16, 20)
    s("INS_GYRO_FILTER", INT16, 20)
    s("INS_USE", INT8, 1)
    s("INS_USE2", INT8, 1)
    s("INS_USE3", INT8, 1)
    s("INS_FAST_SAMPLE", INT8, 1)
    for n in (5, 6, 7, 8):
        s(f"SERVO{n}_FUNCTION", INT16, 0)
    return t


#: parameters with AP_PARAM_FLAG_INTERNAL_USE_ONLY: PARAM_SET is denied
_INTERNAL_USE_ONLY_PREFIXES = ("COMPASS_DEV_ID", "INS_ACC_ID", "INS_ACC2_ID", "INS_ACC3_ID",
                               "INS_GYR_ID", "INS_GYR2_ID", "INS_GYR3_ID")

_COMPASS_SET_FIELDS = ("OFS{s}_X", "OFS{s}_Y", "OFS{s}_Z", "DIA{s}_X", "DIA{s}_Y", "DIA{s}_Z",
                       "ODI{s}_X", "ODI{s}_Y", "ODI{s}_Z", "MOT{s}_X", "MOT{s}_Y", "MOT{s}_Z",
                       "SCALE{s}", "ORIENT{s}", "USE{s}", "DEV_ID{s}")
_EXTERNAL_NAMES = ("COMPASS_EXTERNAL", "COMPASS_EXTERN2", "COMPASS_EXTERN3")
_COMPASS_SFX = ("", "2", "3")
_ACCEL_SFX = ("", "2", "3")


def _calibration_param_names() -> Tuple[str, ...]:
    """Every parameter ``firmware.*_cal_from_params`` reads for the vehicle's sensors."""
    names: List[str] = [fw.board_param_names()["orientation"]]  # type: ignore[list-item]
    for slot in range(len(_COMPASS_SFX)):
        cn = fw.compass_param_names(slot)
        for k in ("ofs", "dia", "odi", "mot"):
            names += list(cn[k])  # type: ignore[arg-type]
        names += [cn["scale"], cn["orient"], cn["external"]]  # type: ignore[list-item]
    for i in range(len(_ACCEL_SFX)):
        an = fw.accel_param_names(i)
        names += list(an["ofs"]) + list(an["scale"])  # type: ignore[operator]
    return tuple(names)


_CAL_PARAM_NAMES = _calibration_param_names()


# ------------------------------------------------------------------------------------------
# truth (the physical sensors)
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class AccelTruth:
    """One accelerometer's true errors, expressed as the *ideal* ArduPilot calibration.

    ``raw = u / scale + offsets`` in the board frame (u = true specific force, m/s^2), so the
    perfect parameters are ``INS_ACCnOFFS = offsets`` and ``INS_ACCnSCAL = scale``.
    """

    offsets: Tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: Tuple[float, float, float] = (1.0, 1.0, 1.0)
    noise_mps2: float = 0.02


@dataclass(frozen=True)
class CompassTruth:
    """One compass's true errors, expressed as the *ideal* ArduPilot calibration.

    The sensor reads ``s = R_mount^T ((1/scale) M^-1 B - offsets)`` (mGauss) for a body field
    B, with M from ``dia``/``odi``; the perfect parameters are ``COMPASS_OFS = offsets``,
    ``DIA/ODI = dia/odi``, ``SCALE = scale`` and (external compass) ``COMPASS_ORIENT =
    orientation``. ``dev_id`` identifies the physical device (slots follow it at boot).
    """

    dev_id: int
    offsets: Tuple[float, float, float] = (0.0, 0.0, 0.0)
    dia: Tuple[float, float, float] = (1.0, 1.0, 1.0)
    odi: Tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: float = 1.0
    orientation: int = 0
    external: bool = False
    noise_mgauss: float = 2.0


@dataclass(frozen=True)
class VehicleTruth:
    """The simulated airframe: sensors' true errors, board mounting, Earth's field."""

    accels: Tuple[AccelTruth, ...]
    compasses: Tuple[CompassTruth, ...]
    earth_field_ned_mgauss: Tuple[float, float, float] = (205.0, 15.0, 420.0)
    board_orientation: int = 0
    gyro_noise_rads: float = 0.002
    temperature_c: float = 35.0

    @classmethod
    def random(cls, seed: int = 0) -> "VehicleTruth":
        """Realistic random sensor errors (reproducible with ``seed``)."""
        rng = np.random.default_rng(seed)
        accels = tuple(AccelTruth(offsets=tuple(rng.uniform(-0.4, 0.4, 3)),
                                  scale=tuple(rng.uniform(0.97, 1.03, 3))) for _ in range(3))
        comps = []
        for i, dev in enumerate((97539, 131874, 263178)):
            comps.append(CompassTruth(dev_id=dev, offsets=tuple(rng.uniform(-250, 250, 3)),
                                      dia=tuple(rng.uniform(0.92, 1.08, 3)),
                                      odi=tuple(rng.uniform(-0.04, 0.04, 3)),
                                      orientation=0, external=(i == 0)))
        return cls(accels=accels, compasses=tuple(comps))

    @classmethod
    def perfect(cls) -> "VehicleTruth":
        """Sensors without errors (the default parameter table is then the ideal calibration)."""
        return cls(accels=(AccelTruth(),) * 3,
                   compasses=tuple(CompassTruth(dev_id=d, external=(i == 0))
                                   for i, d in enumerate((97539, 131874, 263178))))


# ------------------------------------------------------------------------------------------
# fault injection
# ------------------------------------------------------------------------------------------
@dataclass
class Faults:
    """Link faults, per direction (``in`` = GCS to vehicle, ``out`` = vehicle to GCS).

    Probabilities are per MAVLink packet; delays are constant (packets keep their order).
    """

    drop_in: float = 0.0
    drop_out: float = 0.0
    delay_in_s: float = 0.0
    delay_out_s: float = 0.0
    dup_in: float = 0.0
    dup_out: float = 0.0


@dataclass
class _Peer:
    addr: Any
    sock: Optional[socket.socket]
    parser: Any


# ------------------------------------------------------------------------------------------
# the vehicle
# ------------------------------------------------------------------------------------------
class TestVehicle:
    """An ArduPilot-like vehicle on 127.0.0.1 (see the module docstring).

    Parameters
    ----------
    transport : {"udpout", "udpin", "tcp"}
        How the vehicle's socket works; :attr:`gcs_device` is the matching GCS device string.
    port : int, optional
        The port (the GCS port for ``udpout``; the vehicle's listening port otherwise).
        Default: a free port.
    truth : VehicleTruth, optional
        True sensor errors; default ``VehicleTruth.random(seed)``.
    params : mapping of str to float, optional
        Initial values overriding the table defaults.
    seed : int
        Seeds the sensor noise and the fault injection.
    heartbeat_hz : float
        HEARTBEAT rate (ArduPilot: 1 Hz; tests may use more to connect faster).
    reboot_s : float
        How long a simulated reboot keeps the vehicle silent.
    die_after_n_sets : int, optional
        Stop answering right after applying the n-th accepted PARAM_SET (its echo is never
        sent), as if the link or the vehicle died mid-write; :meth:`revive` brings it back.
    faults : Faults, optional
        Initial fault injection (see :meth:`set_faults`).
    sysid, compid : int
        The vehicle's MAVLink ids.
    """

    __test__ = False  # not a pytest test class

    def __init__(self, transport: str = "udpout", port: Optional[int] = None, *,
                 truth: Optional[VehicleTruth] = None, params: Optional[Mapping[str, float]] = None,
                 seed: int = 0, heartbeat_hz: float = 1.0, reboot_s: float = 0.5,
                 die_after_n_sets: Optional[int] = None, faults: Optional[Faults] = None,
                 sysid: int = 1, compid: int = 1) -> None:
        if transport not in ("udpout", "udpin", "tcp"):
            raise ValueError(f"transport must be 'udpout', 'udpin' or 'tcp', got {transport!r}")
        self.transport = transport
        self._requested_port = port
        self.port: Optional[int] = None
        self.truth = truth if truth is not None else VehicleTruth.random(seed)
        self.sysid, self.compid = sysid, compid
        self.heartbeat_hz = heartbeat_hz
        self.reboot_s = reboot_s
        self.die_after_n_sets = die_after_n_sets
        self.faults = faults or Faults()
        self._rng = random.Random(seed)
        self._np_rng = np.random.default_rng(seed + 1)
        self._lock = threading.RLock()

        table = default_param_table()
        self._names: List[str] = [n for n, _, _, _ in table]
        self._types: Dict[str, int] = {n: t for n, t, _, _ in table}
        self._values: Dict[str, float] = {n: ap_set_float(d, t) for n, t, d, _ in table}  # type: ignore[misc]
        self._vector_of: Dict[str, Tuple[str, str, str]] = {}
        for n, _, _, prefix in table:
            if prefix:
                self._vector_of[n] = (f"{prefix}_X", f"{prefix}_Y", f"{prefix}_Z")
        for n, v in (params or {}).items():
            if n not in self._values:
                raise KeyError(f"unknown parameter {n!r}")
            self._values[n] = ap_set_float(float(v), self._types[n])  # type: ignore[assignment]

        # event records (for tests)
        self.force_saves: List[str] = []
        self.param_sets: List[Tuple[str, float, Optional[float]]] = []  # (name, received, stored or None)
        self.commands: List[Tuple[int, Tuple[float, ...]]] = []
        self.reboots = 0
        self.accepted_sets = 0
        self.stats: Dict[str, int] = {"rx": 0, "tx": 0, "dropped_in": 0, "dropped_out": 0,
                                      "dup_in": 0, "dup_out": 0}

        # simulated motion
        self._R = np.eye(3)
        self._omega = np.zeros(3)
        self._moving = False
        self._script: List[Tuple[np.ndarray, float, float]] = []
        self._script_t0 = 0.0
        self.script_done = threading.Event()
        self.script_done.set()

        self._dead = False
        self._reboot_until: Optional[float] = None
        self._running = False
        self._thread: Optional[threading.Thread] = None
        self._sock: Optional[socket.socket] = None
        self._listen: Optional[socket.socket] = None
        self._peers: Dict[Any, _Peer] = {}
        self._out_q: List[Tuple[float, int, bytes]] = []
        self._in_q: List[Tuple[float, int, Any]] = []
        self._seq = itertools.count()
        self._enc = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        self._list_cursor: Optional[int] = None
        self._cal_key: Optional[Tuple[Any, ...]] = None
        self._cal_cache: Tuple[List[fw.AccelCal], List[fw.CompassCal]] = ([], [])
        self._boot()

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> "TestVehicle":
        """Open the socket and start the vehicle thread. Returns self."""
        if self._running:
            return self
        host = "127.0.0.1"
        if self.transport == "udpout":
            if self._requested_port is None:
                probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                probe.bind((host, 0))
                self.port = probe.getsockname()[1]
                probe.close()
            else:
                self.port = self._requested_port
            self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._sock.bind((host, 0))
            self._sock.setblocking(False)
            self._peers[(host, self.port)] = _Peer((host, self.port), None, self._new_parser())
        elif self.transport == "udpin":
            self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._sock.bind((host, self._requested_port or 0))
            self._sock.setblocking(False)
            self.port = self._sock.getsockname()[1]
        else:
            self._listen = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            self._listen.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._listen.bind((host, self._requested_port or 0))
            self._listen.listen(4)
            self._listen.setblocking(False)
            self.port = self._listen.getsockname()[1]
        self._running = True
        self._thread = threading.Thread(target=self._run, name=f"TestVehicle:{self.port}", daemon=True)
        self._thread.start()
        log.debug("test vehicle up on %s (%s)", self.port, self.transport)
        return self

    def stop(self) -> None:
        """Stop the thread and close every socket (idempotent)."""
        self._running = False
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        for p in list(self._peers.values()):
            if p.sock is not None:
                try:
                    p.sock.close()
                except OSError:
                    pass
        self._peers.clear()
        for s in (self._sock, self._listen):
            if s is not None:
                s.close()
        self._sock = self._listen = None

    def __enter__(self) -> "TestVehicle":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def gcs_device(self) -> str:
        """The pymavlink device string a GCS opens to talk to this vehicle."""
        if self.port is None:
            raise RuntimeError("start() the vehicle first")
        return {"udpout": "udpin", "udpin": "udpout", "tcp": "tcp"}[self.transport] + f":127.0.0.1:{self.port}"

    # ------------------------------------------------------------------ public state API
    def get_param(self, name: str) -> float:
        """Current stored value of ``name`` (KeyError if unknown)."""
        with self._lock:
            return self._values[name]

    def param_type(self, name: str) -> int:
        """MAV_PARAM_TYPE of ``name``."""
        return self._types[name]

    @property
    def params(self) -> Dict[str, float]:
        """A snapshot of every parameter value."""
        with self._lock:
            return dict(self._values)

    def set_param_local(self, name: str, value: float, *, announce: bool = False) -> None:
        """Change a parameter on the vehicle side (as a user with another GCS would).

        With ``announce`` the change is broadcast as PARAM_VALUE like any save.
        """
        with self._lock:
            stored = ap_set_float(float(value), self._types[name])
            if stored is None:
                raise ValueError("value must be finite")
            self._values[name] = stored
            if announce:
                self._send_param(name, 65535)

    def set_faults(self, seed: Optional[int] = None, **kw: float) -> None:
        """Change fault injection at run time, e.g. ``set_faults(drop_in=0.3, drop_out=0.3)``.

        ``seed`` re-seeds the random generator that decides drops and duplicates.
        """
        with self._lock:
            if seed is not None:
                self._rng.seed(seed)
            for k, v in kw.items():
                if not hasattr(self.faults, k):
                    raise AttributeError(f"no fault {k!r}")
                setattr(self.faults, k, float(v))

    def kill(self) -> None:
        """Stop answering (no heartbeats, no replies, incoming ignored); state is kept."""
        with self._lock:
            self._dead = True

    def revive(self) -> None:
        """Answer again after :meth:`kill` or ``die_after_n_sets``, with the parameters as they were."""
        with self._lock:
            self._dead = False
            self.die_after_n_sets = None
            self._last_hb = 0.0

    @property
    def alive(self) -> bool:
        """False while killed or rebooting."""
        return not self._dead and self._reboot_until is None

    def set_attitude(self, R: Optional[np.ndarray] = None, *, roll: float = 0.0, pitch: float = 0.0,
                     yaw: float = 0.0, degrees: bool = True) -> None:
        """Hold the vehicle still in a new attitude (body-to-NED DCM, or Euler angles 3-2-1)."""
        M = np.array(R, dtype=float) if R is not None else euler_matrix(roll, pitch, yaw, degrees)
        with self._lock:
            self._R = M
            self._moving = False
            self._omega = np.zeros(3)
            self._script = []
            self.script_done.set()

    @property
    def attitude(self) -> np.ndarray:
        """Current body-to-NED rotation matrix."""
        with self._lock:
            return self._R.copy()

    def set_moving(self, moving: bool, rate_dps: float = 60.0) -> None:
        """Start (or stop) a slow tumble about a varying axis, as a hand turning the vehicle."""
        with self._lock:
            self._moving = bool(moving)
            if moving:
                axis = self._np_rng.normal(size=3)
                self._omega = math.radians(rate_dps) * axis / np.linalg.norm(axis)
            else:
                self._omega = np.zeros(3)

    def run_pose_script(self, poses: Sequence[Union[np.ndarray, Tuple[float, float, float]]], *,
                        hold_s: float = 1.0, move_s: float = 0.5) -> None:
        """Visit ``poses`` in order: turn for ``move_s`` to each, then hold it still ``hold_s``.

        Poses are rotation matrices or (roll, pitch, yaw) in degrees. :attr:`script_done` is set
        when the last hold ends.
        """
        mats = [np.array(p, dtype=float) if np.shape(p) == (3, 3) else euler_matrix(*p) for p in poses]
        with self._lock:
            start = self._R.copy()
            self._script = []
            prev = start
            for M in mats:
                self._script.append((prev, M, move_s))
                self._script.append((M, M, hold_s))
                prev = M
            self._script_t0 = time.monotonic()
            self.script_done.clear()

    # ------------------------------------------------------------------ sensors
    def corrected_sensors(self, noise: bool = True) -> Dict[str, Any]:
        """What the autopilot would report now, before the int16 conversion.

        Returns
        -------
        dict
            ``accel_mps2`` (3, 3) per IMU, ``mag_mgauss`` (3, 3) per compass priority slot,
            ``gyro_rads`` (3, 3), all in the body frame, with the current calibration
            parameters applied as ArduPilot applies them:

            * compass: ``M (SCALE (rot(ORIENT or AHRS_ORIENTATION) raw + OFS))``, M from
              DIA/ODI skipped when DIA is all zero, SCALE only within [1/1.5, 1.5];
            * accel: ``rot(AHRS_ORIENTATION) (ACCSCAL * (raw - ACCOFFS))``.

            That is :func:`mavcal.ardupilot.firmware.apply_compass` /
            :func:`~mavcal.ardupilot.firmware.apply_accel` with the calibrations
            ``compass_cal_from_params`` / ``accel_cal_from_params`` build from the current
            parameters (custom rotations: the angles of the last boot).
        """
        with self._lock:
            return self._sensors(noise)

    def _firmware_rotation(self, orient: int) -> Tuple[int, Optional[Tuple[float, float, float]]]:
        """A rotation value as the firmware applies it: (value, custom angles or None)."""
        if orient in (_rotations.CUSTOM_1, _rotations.CUSTOM_2):
            return orient, self._custom_deg[orient]  # the angles read at boot
        if orient in _rotations.ROTATIONS:
            return orient, None
        return 0, None  # Vector3::rotate of an unknown value: internal error, no rotation

    def _calibrations(self) -> Tuple[List[fw.AccelCal], List[fw.CompassCal]]:
        """The calibrations in force: accel per IMU, compass per priority slot (lock held).

        Rebuilt only when a parameter they depend on (or the boot-time custom angles) changed.
        """
        p = self._values
        key = tuple(p.get(n) for n in _CAL_PARAM_NAMES) + tuple(self._custom_deg.values())
        if key == self._cal_key:
            return self._cal_cache
        accels = []
        for i in range(len(_ACCEL_SFX)):
            cal = fw.accel_cal_from_params(p, i)
            o, c = self._firmware_rotation(cal.board_orient)
            accels.append(dataclasses.replace(cal, board_orient=o, custom_deg=c))
        compasses = []
        for slot in range(len(_COMPASS_SFX)):
            cal = fw.compass_cal_from_params(p, slot)
            o, c = self._firmware_rotation(cal.orient)
            compasses.append(dataclasses.replace(cal, orient=o, custom_deg=c))
        self._cal_key, self._cal_cache = key, (accels, compasses)
        return accels, compasses

    def _raw_sensors(self, noise: bool) -> Dict[str, Any]:
        """What the sensors measure now, before any calibration (lock held).

        ``accel_mps2`` (3, 3) board frame per IMU, ``mag_mgauss`` (3, 3) sensor frame per
        compass slot (None for a slot without a compass), ``gyro_rads`` (3, 3).
        """
        R = self._R
        tr = self.truth
        g_ned = np.array([0.0, 0.0, -GRAVITY_MSS])        # specific force at rest, NED
        f_body = R.T @ g_ned
        R_board = rotation_matrix(tr.board_orientation)
        accels = []
        for i in range(len(_ACCEL_SFX)):
            at = tr.accels[i]
            u = R_board.T @ f_body                          # board frame
            raw = u / np.array(at.scale) + np.array(at.offsets)
            if noise:
                raw = raw + self._np_rng.normal(0, at.noise_mps2, 3)
            accels.append(raw)
        B_body = R.T @ np.array(tr.earth_field_ned_mgauss)
        mags: List[Optional[np.ndarray]] = []
        for slot in range(len(_COMPASS_SFX)):
            ct = self._slot_truth[slot]
            if ct is None:
                mags.append(None)
                continue
            M = fw.soft_iron_matrix(ct.dia, ct.odi)
            ideal = np.linalg.solve(M, B_body) / ct.scale - np.array(ct.offsets)
            mount = rotation_matrix(ct.orientation) if ct.external else R_board
            raw = mount.T @ ideal
            if noise:
                raw = raw + self._np_rng.normal(0, ct.noise_mgauss, 3)
            mags.append(raw)
        gyro = np.tile(self._omega, (3, 1))
        if noise:
            gyro = gyro + self._np_rng.normal(0, tr.gyro_noise_rads, (3, 3))
        return {"accel_mps2": np.array(accels), "mag_mgauss": mags, "gyro_rads": gyro}

    def _sensors(self, noise: bool) -> Dict[str, Any]:
        raw = self._raw_sensors(noise)
        accel_cals, compass_cals = self._calibrations()
        accels = [fw.apply_accel(cal, u) for cal, u in zip(accel_cals, raw["accel_mps2"])]
        mags = [np.zeros(3) if m is None else fw.apply_compass(cal, m)
                for cal, m in zip(compass_cals, raw["mag_mgauss"])]
        return {"accel_mps2": np.array(accels), "mag_mgauss": np.array(mags), "gyro_rads": raw["gyro_rads"]}

    # ------------------------------------------------------------------ boot
    def _boot(self) -> None:
        """What ArduPilot does at boot that matters here."""
        p = self._values
        # AP_Compass::_reorder_compass_params: slot i gets the compass whose id is PRIO(i+1)
        slots = [{f: p[f"COMPASS_{f.format(s=sfx)}"] for f in _COMPASS_SET_FIELDS} | {"EXT": p[_EXTERNAL_NAMES[i]]}
                 for i, sfx in enumerate(_COMPASS_SFX)]
        by_id = {int(sl["DEV_ID{s}"]): sl for sl in slots if int(sl["DEV_ID{s}"]) != 0}
        new_slots = []
        for i in range(3):
            prio = int(p[f"COMPASS_PRIO{i + 1}_ID"])
            new_slots.append(by_id.pop(prio) if prio in by_id else None)
        leftovers = list(by_id.values())
        for i in range(3):
            if new_slots[i] is None and leftovers:
                new_slots[i] = leftovers.pop(0)
        for i, sfx in enumerate(_COMPASS_SFX):
            sl = new_slots[i]
            if sl is None:
                continue
            for f in _COMPASS_SET_FIELDS:
                p[f"COMPASS_{f.format(s=sfx)}"] = sl[f]
            p[_EXTERNAL_NAMES[i]] = sl["EXT"]
        truth_by_id = {c.dev_id: c for c in self.truth.compasses}
        self._slot_truth = [truth_by_id.get(int(p[f"COMPASS_DEV_ID{sfx}"])) for sfx in _COMPASS_SFX]
        # AP_CustomRotations: built once at boot from CUST_ROTn_* (degrees, 3-2-1)
        self._custom_deg = {100 + n: (p[f"CUST_ROT{n}_ROLL"], p[f"CUST_ROT{n}_PITCH"], p[f"CUST_ROT{n}_YAW"])
                            for n in (1, 2)}
        # stream rates from SR0_*
        self._intervals: Dict[int, Optional[float]] = {}
        self._stream_hz = {"RAW_SENS": p["SR0_RAW_SENS"], "EXTRA1": p["SR0_EXTRA1"]}
        self._apply_stream_rates()
        self._boot_time = time.monotonic()
        self._last_hb = 0.0
        self._list_cursor = None

    def _apply_stream_rates(self) -> None:
        def iv(hz: float) -> Optional[float]:
            return 1.0 / min(hz, 400.0) if hz > 0 else None
        for mid in (mavlink2.MAVLINK_MSG_ID_RAW_IMU, mavlink2.MAVLINK_MSG_ID_SCALED_IMU2,
                    mavlink2.MAVLINK_MSG_ID_SCALED_IMU3):
            self._intervals[mid] = iv(self._stream_hz["RAW_SENS"])
        self._intervals[mavlink2.MAVLINK_MSG_ID_ATTITUDE] = iv(self._stream_hz["EXTRA1"])
        self._intervals.setdefault(mavlink2.MAVLINK_MSG_ID_SCALED_IMU, None)
        self._next_due = {mid: time.monotonic() for mid in self._intervals}

    # ------------------------------------------------------------------ I/O
    def _new_parser(self) -> Any:
        mav = mavlink2.MAVLink(None, srcSystem=self.sysid, srcComponent=self.compid)
        mav.robust_parsing = True
        return mav

    def _send(self, msg: Any) -> None:
        """Queue one message to every peer, through the outbound fault injection."""
        if self._dead or self._reboot_until is not None:
            return
        buf = msg.pack(self._enc)
        self._enc.seq = (self._enc.seq + 1) % 256
        f = self.faults
        if f.drop_out and self._rng.random() < f.drop_out:
            self.stats["dropped_out"] += 1
            return
        copies = 1
        if f.dup_out and self._rng.random() < f.dup_out:
            copies = 2
            self.stats["dup_out"] += 1
        due = time.monotonic() + f.delay_out_s
        for _ in range(copies):
            heapq.heappush(self._out_q, (due, next(self._seq), buf))

    def _flush_out(self, now: float) -> None:
        while self._out_q and self._out_q[0][0] <= now:
            _, _, buf = heapq.heappop(self._out_q)
            self.stats["tx"] += 1
            for peer in list(self._peers.values()):
                try:
                    if peer.sock is not None:
                        peer.sock.sendall(buf)
                    elif self._sock is not None:
                        self._sock.sendto(buf, peer.addr)
                except (BlockingIOError, InterruptedError):
                    pass  # a full buffer loses the packet, like a radio
                except OSError:
                    if peer.sock is not None:
                        self._drop_peer(peer)

    def _drop_peer(self, peer: _Peer) -> None:
        self._peers.pop(peer.addr, None)
        if peer.sock is not None:
            try:
                peer.sock.close()
            except OSError:
                pass

    def _receive(self) -> None:
        rlist: List[socket.socket] = [s for s in (self._sock, self._listen) if s is not None]
        rlist += [p.sock for p in self._peers.values() if p.sock is not None]
        timeout = 0.004
        if self._out_q:
            timeout = max(0.0, min(timeout, self._out_q[0][0] - time.monotonic()))
        try:
            readable, _, _ = select.select(rlist, [], [], timeout)
        except (OSError, ValueError):
            return
        for s in readable:
            if s is self._listen:
                try:
                    conn, addr = s.accept()
                except OSError:
                    continue
                conn.setblocking(False)
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                self._peers[addr] = _Peer(addr, conn, self._new_parser())
                continue
            if s is self._sock:
                for _ in range(256):
                    try:
                        data, addr = s.recvfrom(65535)
                    except (BlockingIOError, InterruptedError):
                        break
                    except OSError:  # ICMP port unreachable from a closed GCS socket
                        break
                    peer = self._peers.get(addr)
                    if peer is None:
                        if self.transport == "udpout":
                            peer = next(iter(self._peers.values()))
                        else:
                            peer = self._peers[addr] = _Peer(addr, None, self._new_parser())
                            self._last_hb = 0.0  # greet a new client at once
                    self._parse(peer, data)
                continue
            peer = next((p for p in self._peers.values() if p.sock is s), None)
            if peer is None:
                continue
            try:
                data = s.recv(65536)
            except (BlockingIOError, InterruptedError):
                continue
            except OSError:
                data = b""
            if not data:
                self._drop_peer(peer)
                continue
            self._parse(peer, data)

    def _parse(self, peer: _Peer, data: bytes) -> None:
        try:
            msgs = peer.parser.parse_buffer(data) or []
        except mavlink2.MAVError:
            return
        now = time.monotonic()
        f = self.faults
        for m in msgs:
            if m.get_type() == "BAD_DATA":
                continue
            self.stats["rx"] += 1
            if f.drop_in and self._rng.random() < f.drop_in:
                self.stats["dropped_in"] += 1
                continue
            copies = 1
            if f.dup_in and self._rng.random() < f.dup_in:
                copies = 2
                self.stats["dup_in"] += 1
            for _ in range(copies):
                heapq.heappush(self._in_q, (now + f.delay_in_s, next(self._seq), m))

    def _run(self) -> None:
        while self._running:
            try:
                self._receive()
                with self._lock:
                    now = time.monotonic()
                    while self._in_q and self._in_q[0][0] <= now:
                        _, _, m = heapq.heappop(self._in_q)
                        if not self._dead and self._reboot_until is None:
                            self._handle(m)
                    self._periodic(now)
                    self._flush_out(now)
            except Exception:  # keep the vehicle alive; a test will notice the silence
                log.exception("test vehicle loop error")
                time.sleep(0.01)

    # ------------------------------------------------------------------ periodic tasks
    def _periodic(self, now: float) -> None:
        if self._reboot_until is not None:
            if now >= self._reboot_until:
                self._reboot_until = None
                self._boot()
                self.reboots += 1
            else:
                return
        if self._dead:
            return
        self._advance_motion(now)
        if self.heartbeat_hz > 0 and now - self._last_hb >= 1.0 / self.heartbeat_hz:
            self._last_hb = now
            self._send(self._enc.heartbeat_encode(
                mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA,
                mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 0, mavlink2.MAV_STATE_STANDBY))
        if self._list_cursor is not None:
            for _ in range(20):
                if self._list_cursor >= len(self._names):
                    self._list_cursor = None
                    break
                self._send_param(self._names[self._list_cursor], self._list_cursor)
                self._list_cursor += 1
        due = [mid for mid, iv in self._intervals.items() if iv and now >= self._next_due.get(mid, 0.0)]
        if due:
            sens = self._sensors(noise=True)
            for mid in due:
                iv = self._intervals[mid]
                nd = self._next_due.get(mid, now) + iv
                self._next_due[mid] = nd if nd > now else now + iv
                self._send_stream(mid, sens, now)

    def _advance_motion(self, now: float) -> None:
        dt = now - getattr(self, "_last_motion", now)
        self._last_motion = now
        if self._script:
            t = now - self._script_t0
            for A, B, dur in self._script:
                if t <= dur:
                    s = t / dur if dur > 0 else 1.0
                    rel = A.T @ B
                    ang = math.acos(max(-1.0, min(1.0, (np.trace(rel) - 1) / 2)))
                    if ang < 1e-9:
                        self._R, self._omega = B.copy(), np.zeros(3)
                    else:
                        axis = np.array([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0], rel[1, 0] - rel[0, 1]])
                        n = np.linalg.norm(axis)
                        axis = axis / n if n > 1e-12 else np.array([1.0, 0.0, 0.0])
                        self._R = A @ _axis_angle(axis, ang * s)
                        self._omega = axis * ang / dur
                    self._moving = ang >= 1e-9
                    return
                t -= dur
            self._R = self._script[-1][1].copy()
            self._omega = np.zeros(3)
            self._moving = False
            self._script = []
            self.script_done.set()
            return
        if self._moving and dt > 0:
            self._R = self._R @ _axis_angle(self._omega / max(np.linalg.norm(self._omega), 1e-12),
                                            np.linalg.norm(self._omega) * dt)
            # re-orthonormalise now and then
            u, _, vt = np.linalg.svd(self._R)
            self._R = u @ vt

    def _send_stream(self, mid: int, sens: Dict[str, Any], now: float) -> None:
        t_ms = int((now - self._boot_time) * 1000) & 0xFFFFFFFF
        temp = int(self.truth.temperature_c * 100)

        def pack(i: int) -> Tuple[int, ...]:
            a = sens["accel_mps2"][i] * 1000.0 / GRAVITY_MSS
            g = sens["gyro_rads"][i] * 1000.0
            m = sens["mag_mgauss"][i]
            return tuple(_trunc_i16(x) for x in (*a, *g, *m))

        if mid == mavlink2.MAVLINK_MSG_ID_RAW_IMU:
            self._send(self._enc.raw_imu_encode(int((now - self._boot_time) * 1e6), *pack(0), 0, temp))
        elif mid == mavlink2.MAVLINK_MSG_ID_SCALED_IMU:
            self._send(self._enc.scaled_imu_encode(t_ms, *pack(0), temp))
        elif mid == mavlink2.MAVLINK_MSG_ID_SCALED_IMU2:
            self._send(self._enc.scaled_imu2_encode(t_ms, *pack(1), temp))
        elif mid == mavlink2.MAVLINK_MSG_ID_SCALED_IMU3:
            self._send(self._enc.scaled_imu3_encode(t_ms, *pack(2), temp))
        elif mid == mavlink2.MAVLINK_MSG_ID_ATTITUDE:
            R = self._R
            roll = math.atan2(R[2, 1], R[2, 2])
            pitch = -math.asin(max(-1.0, min(1.0, R[2, 0])))
            yaw = math.atan2(R[1, 0], R[0, 0])
            w = self._omega
            self._send(self._enc.attitude_encode(t_ms, roll, pitch, yaw, float(w[0]), float(w[1]), float(w[2])))

    # ------------------------------------------------------------------ message handling
    def _for_us(self, m: Any) -> bool:
        ts = getattr(m, "target_system", 0)
        tc = getattr(m, "target_component", 0)
        return ts in (0, self.sysid) and tc in (0, self.compid)

    def _send_param(self, name: str, index: int) -> None:
        self._send(self._enc.param_value_encode(name.encode("ascii"), self._values[name],
                                                self._types[name], len(self._names), index))

    def _handle(self, m: Any) -> None:
        mtype = m.get_type()
        if mtype == "PARAM_SET" and self._for_us(m):
            self._handle_param_set(m)
        elif mtype == "PARAM_REQUEST_READ" and self._for_us(m):
            if m.param_index != -1:
                if 0 <= m.param_index < len(self._names):
                    self._send_param(self._names[m.param_index], m.param_index)
            else:
                name = _name(m.param_id)
                if name in self._values:
                    self._send_param(name, 65535)
        elif mtype == "PARAM_REQUEST_LIST" and self._for_us(m):
            self._list_cursor = 0
        elif mtype == "COMMAND_LONG" and self._for_us(m):
            self._handle_command(m)
        elif mtype == "REQUEST_DATA_STREAM" and self._for_us(m):
            rate = m.req_message_rate if m.start_stop == 1 else 0
            if m.start_stop not in (0, 1):
                return
            if m.req_stream_id in (mavlink2.MAV_DATA_STREAM_ALL, mavlink2.MAV_DATA_STREAM_RAW_SENSORS):
                self._stream_hz["RAW_SENS"] = rate
                self._values["SR0_RAW_SENS"] = float(rate)
            if m.req_stream_id in (mavlink2.MAV_DATA_STREAM_ALL, mavlink2.MAV_DATA_STREAM_EXTRA1):
                self._stream_hz["EXTRA1"] = rate
                self._values["SR0_EXTRA1"] = float(rate)
            self._apply_stream_rates()

    def _handle_param_set(self, m: Any) -> None:
        name = _name(m.param_id)[:16]
        received = float(m.param_value)
        if name not in self._values:
            self.param_sets.append((name, received, None))
            return  # GCS_MAVLINK::handle_param_set: unknown name, no reply
        if math.isnan(received) or math.isinf(received):
            self.param_sets.append((name, received, None))
            return
        if name.startswith(_INTERNAL_USE_ONLY_PREFIXES):
            self.param_sets.append((name, received, None))
            self._send(self._enc.statustext_encode(mavlink2.MAV_SEVERITY_WARNING,
                                                   f"Param write denied ({name})".encode()))
            self._send_param(name, 65535)
            return
        stored = ap_set_float(received, self._types[name])
        self._values[name] = stored  # type: ignore[assignment]
        self.param_sets.append((name, received, stored))
        self.accepted_sets += 1
        if self.die_after_n_sets is not None and self.accepted_sets >= self.die_after_n_sets:
            self._dead = True  # applied, but the echo is never sent
            return
        for n in self._vector_of.get(name, (name,)):
            self._send_param(n, 65535)

    def _ack(self, m: Any, result: int) -> None:
        self._send(self._enc.command_ack_encode(m.command, result, 0, 0, m.get_srcSystem(), m.get_srcComponent()))

    def _handle_command(self, m: Any) -> None:
        cmd = m.command
        params = (m.param1, m.param2, m.param3, m.param4, m.param5, m.param6, m.param7)
        self.commands.append((cmd, params))
        A = mavlink2
        if cmd == A.MAV_CMD_PREFLIGHT_CALIBRATION:
            # GCS_MAVLINK::_handle_command_preflight_calibration: param5 arrives as an int
            if math.isclose(m.param2, 76.0):
                self.force_saves.append("compass")
                self._ack(m, A.MAV_RESULT_ACCEPTED)
            elif int(m.param5) == 76:
                self.force_saves.append("accel")
                self._ack(m, A.MAV_RESULT_ACCEPTED)
            else:
                self._ack(m, A.MAV_RESULT_UNSUPPORTED)
        elif cmd == A.MAV_CMD_SET_MESSAGE_INTERVAL:
            mid = int(m.param1)
            known = (A.MAVLINK_MSG_ID_RAW_IMU, A.MAVLINK_MSG_ID_SCALED_IMU, A.MAVLINK_MSG_ID_SCALED_IMU2,
                     A.MAVLINK_MSG_ID_SCALED_IMU3, A.MAVLINK_MSG_ID_ATTITUDE)
            if mid not in known:
                self._ack(m, A.MAV_RESULT_DENIED)
                return
            us = m.param2
            if us < 0:
                self._intervals[mid] = None
            elif us == 0:
                self._apply_stream_rates()
            else:
                self._intervals[mid] = max(us * 1e-6, 1.0 / 400.0)
                self._next_due[mid] = time.monotonic()
            self._ack(m, A.MAV_RESULT_ACCEPTED)
        elif cmd in (A.MAV_CMD_REQUEST_MESSAGE, A.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES):
            if cmd == A.MAV_CMD_REQUEST_MESSAGE and int(m.param1) != A.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
                self._ack(m, A.MAV_RESULT_UNSUPPORTED)
                return
            self._ack(m, A.MAV_RESULT_ACCEPTED)
            caps = (A.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT | A.MAV_PROTOCOL_CAPABILITY_MAVLINK2
                    | A.MAV_PROTOCOL_CAPABILITY_COMMAND_INT | A.MAV_PROTOCOL_CAPABILITY_MISSION_INT)
            version = (4 << 24) | (6 << 16) | (0 << 8) | 255  # 4.6.0 official
            self._send(self._enc.autopilot_version_encode(caps, version, 0, 0, 0, [0] * 8, [0] * 8,
                                                          [0] * 8, 0, 0, 0))
        elif cmd == A.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN:
            if int(m.param1) in (1, 3):
                self._ack(m, A.MAV_RESULT_ACCEPTED)
                self._reboot_until = time.monotonic() + self.reboot_s
                self._in_q.clear()
                self._flush_out(time.monotonic() + self.faults.delay_out_s)  # the ACK goes out first
            else:
                self._ack(m, A.MAV_RESULT_UNSUPPORTED)
        else:
            self._ack(m, A.MAV_RESULT_UNSUPPORTED)


def _name(param_id: Any) -> str:
    if isinstance(param_id, bytes):
        param_id = param_id.decode("ascii", "replace")
    return str(param_id).rstrip("\x00")


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    x, y, z = axis
    c, s = math.cos(angle), math.sin(angle)
    C = 1 - c
    return np.array([[c + x * x * C, x * y * C - z * s, x * z * C + y * s],
                     [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
                     [z * x * C - y * s, z * y * C + x * s, c + z * z * C]])
