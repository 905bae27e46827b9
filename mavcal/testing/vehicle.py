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
    ``param_index`` 65535; setting the X element of a Vector3 parameter echoes all three, Y or
    Z only itself (``AP_Param::send_parameter``);
  - a parameter flagged internal-use-only (``MIS_TOTAL``) is refused with STATUSTEXT
    "Param write denied (NAME)" and an echo of the unchanged value, unless ``BRD_OPTIONS``
    has ``ALLOW_SET_INTERNAL_PARM`` (``AP_Param::allow_set_via_mavlink``); device ids are
    writable, as in ArduPilot (no flag on them; checked against SITL by
    ``tests/test_vehicle_agrees_with_sitl.py``);
  - with ``param_errors=True`` the vehicle behaves as ArduPilot master since PR #31062
    (2025-10): PARAM_ERROR (to the sender) for a PARAM_SET of an unknown name
    (``MAV_PARAM_ERROR_DOES_NOT_EXIST``), of NaN/Inf (``VALUE_OUT_OF_RANGE``), of a denied
    parameter (``PERMISSION_DENIED``, besides the STATUSTEXT and the echo), and for a
    PARAM_REQUEST_READ of an unknown name or index (``DOES_NOT_EXIST``);
  - ``deny_params`` names parameters to deny the same way (a read-only defaults entry,
    ``@READONLY``, or a scripting lock on a real vehicle).

* COMMAND_LONG: MAV_CMD_PREFLIGHT_CALIBRATION param2=76 / param5=76 (force-save compass /
  accel calibration, recorded in :attr:`TestVehicle.force_saves`), MAV_CMD_SET_MESSAGE_INTERVAL,
  MAV_CMD_REQUEST_MESSAGE / REQUEST_AUTOPILOT_CAPABILITIES (AUTOPILOT_VERSION; with ``position``
  also GPS_RAW_INT with a 3D fix, GLOBAL_POSITION_INT and HOME_POSITION there),
  MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN (a simulated reboot: silent for ``reboot_s``, then the
  compass parameter sets are reordered by ``COMPASS_PRIOn_ID`` and the custom rotations are
  rebuilt, as at boot). Everything else gets MAV_RESULT_UNSUPPORTED. REQUEST_DATA_STREAM sets
  stream rates (no ACK, as ArduPilot).
* Channels: an answer goes to the asking client only (the PARAM_VALUE of a read or a list,
  COMMAND_ACK, a requested AUTOPILOT_VERSION, PARAM_ERROR); heartbeats, the echo of a set,
  STATUSTEXT and the streams go to every client (ArduPilot keeps stream rates per channel;
  this vehicle keeps one set).
* IMU streams RAW_IMU, SCALED_IMU2, SCALED_IMU3 (and ATTITUDE on EXTRA1) from a simulated
  vehicle with known *true* sensor errors, with the vehicle's **current** calibration
  parameters applied the way ArduPilot applies them (see :meth:`TestVehicle.corrected_sensors`)
  and converted to int16 by truncation toward zero.
* STATUSTEXT "Internal Errors 0x400000" (CRITICAL), once per boot, when an external
  compass's orientation is set to a rotation the firmware does not know (``bad_rotation``),
  as SITL reports it; from then on the HEARTBEAT's system_status is MAV_STATE_CRITICAL.
* Fault injection per direction (drop / delay / duplicate), :meth:`kill`, :meth:`revive` and
  ``die_after_n_sets``.
* MAVLink 2 signing (``signing_key``, 32 bytes): everything sent is signed and unsigned or
  wrongly signed messages are dropped, as ArduPilot on any channel but the first.

Transports (``transport=``): ``"udpout"`` (the vehicle sends to the GCS port; the GCS uses
``udpin:127.0.0.1:PORT``), ``"udpin"`` (the vehicle listens; the GCS uses ``udpout:``) and
``"tcp"`` (the vehicle is a TCP server; the GCS uses ``tcp:``). :attr:`TestVehicle.gcs_device`
is the device string a GCS should open.

The parts are split along what the code separates: this module is the MAVLink server
(sockets, fault injection, message handling); the parameter table and ArduPilot's storage
semantics are :mod:`mavcal.testing.vehicle_params`; the true sensor errors, the motion and
the sensor readings (:mod:`mavcal.ardupilot.firmware`'s forward model applied to them, so the
vehicle applies exactly the model the rest of mavcal inverts) are
:mod:`mavcal.testing.vehicle_sensors`.
"""
from __future__ import annotations

import heapq
import itertools
import logging
import math
import random
import select
import socket
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavcal.autopilot.rotations import euler_to_matrix
from mavcal.core.constants import GRAVITY_MPS2
from mavcal.testing.vehicle_params import ParamStore
from mavcal.testing.vehicle_sensors import AccelCalTruth, CompassTruth, Motion, SensorModel, VehicleTruth

__all__ = ["TestVehicle", "VehicleTruth", "AccelCalTruth", "CompassTruth", "Faults"]

log = logging.getLogger(__name__)


#: HEARTBEAT base_mode of a disarmed ArduCopter in STABILIZE (SITL 4.7.0-dev sends 81)
_BASE_MODE = (mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink2.MAV_MODE_FLAG_STABILIZE_ENABLED
              | mavlink2.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED)


_BAD_ROTATION = 1 << 22  # AP_InternalError::error_t::bad_rotation


def _trunc_i16(x: float) -> int:
    """float -> int16 the way a C cast in the MAVLink send code does (toward zero, saturated)."""
    if not math.isfinite(x):
        return 0
    return int(max(-32768.0, min(32767.0, math.trunc(x))))


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
    sock: socket.socket | None
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
    param_errors : bool
        Answer refused parameter requests with PARAM_ERROR (ArduPilot master), not silence (4.6).
    deny_params : iterable of str
        Parameters whose PARAM_SET is denied (as read-only defaults entries are).
    position : (lat_deg, lon_deg, alt_m), optional
        Where the vehicle is (answers REQUEST_MESSAGE of the position messages).
    signing_key : bytes, optional
        MAVLink 2 signing key (see the module docstring).
    """

    __test__ = False  # not a pytest test class

    def __init__(self, transport: str = "udpout", port: int | None = None, *,
                 truth: VehicleTruth | None = None, params: Mapping[str, float] | None = None,
                 seed: int = 0, heartbeat_hz: float = 1.0, reboot_s: float = 0.5,
                 die_after_n_sets: int | None = None, faults: Faults | None = None,
                 sysid: int = 1, compid: int = 1, param_errors: bool = False,
                 deny_params: Sequence[str] = (), position: Sequence[float] | None = None,
                 signing_key: bytes | None = None) -> None:
        if transport not in ("udpout", "udpin", "tcp"):
            raise ValueError(f"transport must be 'udpout', 'udpin' or 'tcp', got {transport!r}")
        self.transport = transport
        self._requested_port = port
        self.port: int | None = None
        self.truth = truth if truth is not None else VehicleTruth.random(seed)
        self.sysid, self.compid = sysid, compid
        self.heartbeat_hz = heartbeat_hz
        self.reboot_s = reboot_s
        self.die_after_n_sets = die_after_n_sets
        self.faults = faults or Faults()
        self._rng = random.Random(seed)
        self._np_rng = np.random.default_rng(seed + 1)
        self._lock = threading.RLock()

        self._store = ParamStore(params, deny=deny_params)
        self.param_errors = param_errors
        #: COMMAND_ACK result of a force-save (a test may set MAV_RESULT_DENIED, as an armed vehicle)
        self.force_save_result = mavlink2.MAV_RESULT_ACCEPTED
        self._values = self._store.values  # the live name -> stored value mapping

        # event records (for tests)
        self.force_saves: list[str] = []
        self.param_sets: list[tuple[str, float, float | None]] = []  # (name, received, stored or None)
        self.commands: list[tuple[int, tuple[float, ...]]] = []
        self.stream_requests: list[tuple[float, int, int]] = []  # (monotonic s, stream id, Hz) of REQUEST_DATA_STREAM
        self.reboots = 0
        #: AP_InternalError's mask (cleared at boot); a new bit is announced by STATUSTEXT
        self.internal_errors = 0
        self.accepted_sets = 0
        self.stats: dict[str, int] = {"rx": 0, "tx": 0, "dropped_in": 0, "dropped_out": 0,
                                      "dup_in": 0, "dup_out": 0}

        # simulated motion and sensors (one noise generator, as the tumble axes)
        self._motion = Motion(self._np_rng)
        self._sensor_model = SensorModel(self.truth, self._np_rng)
        self.script_done = self._motion.script_done

        self._dead = False
        self._reboot_until: float | None = None
        self._running = False
        self._thread: threading.Thread | None = None
        self._sock: socket.socket | None = None
        self._listen: socket.socket | None = None
        self._peers: dict[Any, _Peer] = {}
        self._out_q: list[tuple[float, int, bytes, Any]] = []  # (due, seq, bytes, peer address or None: all)
        self._in_q: list[tuple[float, int, Any, Any]] = []  # (due, seq, message, the sender's peer address)
        self._sender: Any = None  # the peer whose message is being handled: replies go to it alone
        self._seq = itertools.count()
        self.position = None if position is None else tuple(float(x) for x in position)
        self.signing_key = signing_key
        self._enc = self._sign(mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=compid))
        self._list_cursor: int | None = None
        self._list_to: Any = None
        self._boot()

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> TestVehicle:
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

    def __enter__(self) -> TestVehicle:
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
        return self._store.types[name]

    @property
    def params(self) -> dict[str, float]:
        """A snapshot of every parameter value."""
        with self._lock:
            return dict(self._values)

    def set_param_local(self, name: str, value: float, *, announce: bool = False) -> None:
        """Change a parameter on the vehicle side (as a user with another GCS would).

        With ``announce`` the change is broadcast as PARAM_VALUE like any save.
        """
        with self._lock:
            self._store.set_local(name, value)
            if announce:
                self._send_param(name, 65535)

    def set_faults(self, seed: int | None = None, **kw: float) -> None:
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

    def set_attitude(self, R: np.ndarray | None = None, *, roll: float = 0.0, pitch: float = 0.0,
                     yaw: float = 0.0, degrees: bool = True) -> None:
        """Hold the vehicle still in a new attitude (body-to-NED DCM, or Euler angles 3-2-1)."""
        if R is None:
            angles = (roll, pitch, yaw)
            R = euler_to_matrix(*(np.radians(angles) if degrees else angles))
        with self._lock:
            self._motion.hold(R)

    @property
    def attitude(self) -> np.ndarray:
        """Current body-to-NED rotation matrix."""
        with self._lock:
            return self._motion.R.copy()

    def set_moving(self, moving: bool, rate_dps: float = 60.0) -> None:
        """Start (or stop) a slow tumble about a varying axis, as a hand turning the vehicle."""
        with self._lock:
            self._motion.tumble(moving, rate_dps)

    def run_pose_script(self, poses: Sequence[np.ndarray | tuple[float, float, float]], *,
                        hold_s: float = 1.0, move_s: float = 0.5) -> None:
        """Visit ``poses`` in order: turn for ``move_s`` to each, then hold it still ``hold_s``.

        Poses are rotation matrices or (roll, pitch, yaw) in degrees. :attr:`script_done` is set
        when the last hold ends.
        """
        mats = [np.array(p, dtype=float) if np.shape(p) == (3, 3) else euler_to_matrix(*np.radians(p))
                for p in poses]
        with self._lock:
            self._motion.script(mats, hold_s, move_s)

    # ------------------------------------------------------------------ sensors
    def corrected_sensors(self, noise: bool = True) -> dict[str, Any]:
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

    def _raw_sensors(self, noise: bool) -> dict[str, Any]:
        """What the sensors measure now, before any calibration (lock held)."""
        return self._sensor_model.raw(self._motion.R, self._motion.omega, noise)

    def _sensors(self, noise: bool) -> dict[str, Any]:
        return self._sensor_model.corrected(self._motion.R, self._motion.omega, self._values, noise)

    # ------------------------------------------------------------------ boot
    def _boot(self) -> None:
        """What ArduPilot does at boot that matters here."""
        p = self._values
        self._store.reorder_compass_params()
        self._sensor_model.boot(self._store.compass_dev_ids(), self._store.custom_rotation_angles())
        # stream rates from SR0_*
        self._intervals: dict[int, float | None] = {}
        self._stream_hz = {"RAW_SENS": p["SR0_RAW_SENS"], "EXTRA1": p["SR0_EXTRA1"]}
        self._apply_stream_rates()
        self._boot_time = time.monotonic()
        self._last_hb = 0.0
        self._list_cursor = None
        self.internal_errors = 0
        self._check_internal_errors()

    def _check_internal_errors(self) -> None:
        """A compass rotation the firmware does not know raises ``bad_rotation`` (0x400000)
        when the compass is next read; a new bit is reported once, as SITL does:
        STATUSTEXT (CRITICAL) "Internal Errors 0x400000"."""
        if self._store.bad_compass_rotation() and not self.internal_errors & _BAD_ROTATION:
            self.internal_errors |= _BAD_ROTATION
            self._send(self._enc.statustext_encode(mavlink2.MAV_SEVERITY_CRITICAL,
                                                   f"Internal Errors {self.internal_errors:#x}".encode()))

    def _default_interval(self, mid: int) -> float | None:
        """The interval of message ``mid`` at its stream's rate (None: not sent)."""
        stream = {mavlink2.MAVLINK_MSG_ID_RAW_IMU: "RAW_SENS", mavlink2.MAVLINK_MSG_ID_SCALED_IMU2: "RAW_SENS",
                  mavlink2.MAVLINK_MSG_ID_SCALED_IMU3: "RAW_SENS", mavlink2.MAVLINK_MSG_ID_ATTITUDE: "EXTRA1"}.get(mid)
        hz = self._stream_hz[stream] if stream is not None else 0.0
        return 1.0 / min(hz, 400.0) if hz > 0 else None

    def _apply_stream_rates(self) -> None:
        for mid in (mavlink2.MAVLINK_MSG_ID_RAW_IMU, mavlink2.MAVLINK_MSG_ID_SCALED_IMU2,
                    mavlink2.MAVLINK_MSG_ID_SCALED_IMU3, mavlink2.MAVLINK_MSG_ID_ATTITUDE):
            self._intervals[mid] = self._default_interval(mid)
        self._intervals.setdefault(mavlink2.MAVLINK_MSG_ID_SCALED_IMU, None)
        self._next_due = {mid: time.monotonic() for mid in self._intervals}

    # ------------------------------------------------------------------ I/O
    def _sign(self, mav: Any) -> Any:
        """Sign what ``mav`` sends and drop unsigned/badly signed input, with ``signing_key``."""
        if self.signing_key is not None:
            mav.signing.secret_key = self.signing_key
            mav.signing.sign_outgoing = True
            mav.signing.timestamp = int((time.time() - 1420070400) * 1e5)
            mav.signing.allow_unsigned_callback = lambda _mav, _msg_id: False
        return mav

    def _new_parser(self) -> Any:
        mav = self._sign(mavlink2.MAVLink(None, srcSystem=self.sysid, srcComponent=self.compid))
        mav.robust_parsing = True
        return mav

    def _send(self, msg: Any, to: Any = None) -> None:
        """Queue one message to peer ``to`` (an address; None: every peer), through the outbound
        fault injection. ArduPilot answers a request on the asking channel only (PARAM_VALUE of
        a read or a list, COMMAND_ACK, a requested message) and sends the rest to every channel
        (heartbeats, the echo of a set, STATUSTEXT)."""
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
            heapq.heappush(self._out_q, (due, next(self._seq), buf, to))

    def _flush_out(self, now: float) -> None:
        while self._out_q and self._out_q[0][0] <= now:
            _, _, buf, to = heapq.heappop(self._out_q)
            self.stats["tx"] += 1
            for peer in list(self._peers.values()) if to is None else [p for p in [self._peers.get(to)] if p]:
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
        rlist: list[socket.socket] = [s for s in (self._sock, self._listen) if s is not None]
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
                heapq.heappush(self._in_q, (now + f.delay_in_s, next(self._seq), m, peer.addr))

    def _run(self) -> None:
        while self._running:
            try:
                self._receive()
                with self._lock:
                    now = time.monotonic()
                    while self._in_q and self._in_q[0][0] <= now:
                        _, _, m, self._sender = heapq.heappop(self._in_q)
                        if not self._dead and self._reboot_until is None:
                            self._handle(m)
                        self._sender = None
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
        self._motion.advance(now)
        if self.heartbeat_hz > 0 and now - self._last_hb >= 1.0 / self.heartbeat_hz:
            self._last_hb = now
            self._send(self._enc.heartbeat_encode(
                mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA,
                _BASE_MODE, 0, mavlink2.MAV_STATE_CRITICAL if self.internal_errors else mavlink2.MAV_STATE_STANDBY))
        if self._list_cursor is not None:
            for _ in range(20):
                if self._list_cursor >= len(self._store.names):
                    self._list_cursor = None
                    break
                self._send_param(self._store.names[self._list_cursor], self._list_cursor, self._list_to)
                self._list_cursor += 1
        due = [(mid, iv) for mid, iv in self._intervals.items() if iv and now >= self._next_due.get(mid, 0.0)]
        if due:
            sens = self._sensors(noise=True)
            for mid, iv in due:
                nd = self._next_due.get(mid, now) + iv
                self._next_due[mid] = nd if nd > now else now + iv
                self._send_stream(mid, sens, now)

    def _send_stream(self, mid: int, sens: dict[str, Any], now: float) -> None:
        t_ms = int((now - self._boot_time) * 1000) & 0xFFFFFFFF
        temp = int(self.truth.temperature_c * 100)

        def pack(i: int) -> tuple[int, ...]:
            a = sens["accel_mps2"][i] * 1000.0 / GRAVITY_MPS2
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
            R = self._motion.R
            roll = math.atan2(R[2, 1], R[2, 2])
            pitch = -math.asin(max(-1.0, min(1.0, R[2, 0])))
            yaw = math.atan2(R[1, 0], R[0, 0])
            w = self._motion.omega
            self._send(self._enc.attitude_encode(t_ms, roll, pitch, yaw, float(w[0]), float(w[1]), float(w[2])))

    # ------------------------------------------------------------------ message handling
    def _for_us(self, m: Any) -> bool:
        ts = getattr(m, "target_system", 0)
        tc = getattr(m, "target_component", 0)
        return ts in (0, self.sysid) and tc in (0, self.compid)

    def _send_param(self, name: str, index: int, to: Any = None) -> None:
        self._send(self._enc.param_value_encode(name.encode("ascii"), self._values[name],
                                                self._store.types[name], len(self._store.names), index), to)

    def _handle(self, m: Any) -> None:
        mtype = m.get_type()
        if mtype == "PARAM_SET" and self._for_us(m):
            self._handle_param_set(m)
        elif mtype == "PARAM_REQUEST_READ" and self._for_us(m):
            if m.param_index != -1:
                if 0 <= m.param_index < len(self._store.names):
                    self._send_param(self._store.names[m.param_index], m.param_index, self._sender)
                else:
                    self._param_error(m, "", m.param_index, mavlink2.MAV_PARAM_ERROR_DOES_NOT_EXIST)
            else:
                name = _name(m.param_id)
                if name in self._values:
                    self._send_param(name, 65535, self._sender)
                else:
                    self._param_error(m, name, -1, mavlink2.MAV_PARAM_ERROR_DOES_NOT_EXIST)
        elif mtype == "PARAM_REQUEST_LIST" and self._for_us(m):
            self._list_cursor, self._list_to = 0, self._sender
        elif mtype == "COMMAND_LONG" and self._for_us(m):
            self._handle_command(m)
        elif mtype == "REQUEST_DATA_STREAM" and self._for_us(m):
            rate = m.req_message_rate if m.start_stop == 1 else 0
            if m.start_stop not in (0, 1):
                return
            self.stream_requests.append((time.monotonic(), m.req_stream_id, rate))
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
        out = self._store.param_set(name, received)
        self.param_sets.append((name, received, out.stored))
        if name not in self._values:
            self._param_error(m, name, -1, mavlink2.MAV_PARAM_ERROR_DOES_NOT_EXIST)
        elif math.isnan(received) or math.isinf(received):
            self._param_error(m, name, -1, mavlink2.MAV_PARAM_ERROR_VALUE_OUT_OF_RANGE)
        if out.denied:
            self._send(self._enc.statustext_encode(mavlink2.MAV_SEVERITY_WARNING,
                                                   f"Param write denied ({name})".encode()))
            self._param_error(m, name, -1, mavlink2.MAV_PARAM_ERROR_PERMISSION_DENIED)
        if out.stored is not None:
            self.accepted_sets += 1
            if self.die_after_n_sets is not None and self.accepted_sets >= self.die_after_n_sets:
                self._dead = True  # applied, but the echo is never sent
                return
        for n in out.echo:
            self._send_param(n, 65535)
        if out.stored is not None:
            self._check_internal_errors()

    def _send_position(self, mid: int) -> None:
        """A requested position message, to the channel that asked (as every requested message)."""
        assert self.position is not None
        lat, lon, alt = int(self.position[0] * 1e7), int(self.position[1] * 1e7), int(self.position[2] * 1e3)
        t_us = int((time.monotonic() - self._boot_time) * 1e6)
        if mid == mavlink2.MAVLINK_MSG_ID_GPS_RAW_INT:
            self._send(self._enc.gps_raw_int_encode(t_us, 3, lat, lon, alt, 80, 120, 0, 0, 12), self._sender)
        elif mid == mavlink2.MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
            self._send(self._enc.global_position_int_encode(t_us // 1000, lat, lon, alt, 0, 0, 0, 0, 0), self._sender)
        else:
            self._send(self._enc.home_position_encode(lat, lon, alt, 0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0],
                                                      0.0, 0.0, 0.0), self._sender)

    def _param_error(self, m: Any, name: str, index: int, error: int) -> None:
        """PARAM_ERROR to the sender (``GCS_MAVLINK::send_param_error``), only with ``param_errors``."""
        if self.param_errors:
            self._send(self._enc.param_error_encode(m.get_srcSystem(), m.get_srcComponent(), name.encode("ascii"),
                                                    index, error), self._sender)

    def _ack(self, m: Any, result: int) -> None:
        self._send(self._enc.command_ack_encode(m.command, result, 0, 0, m.get_srcSystem(), m.get_srcComponent()),
                   self._sender)

    def _handle_command(self, m: Any) -> None:
        cmd = m.command
        params = (m.param1, m.param2, m.param3, m.param4, m.param5, m.param6, m.param7)
        self.commands.append((cmd, params))
        A = mavlink2
        if cmd == A.MAV_CMD_PREFLIGHT_CALIBRATION:
            # GCS_MAVLINK::_handle_command_preflight_calibration: param5 arrives as an int
            kind = "compass" if math.isclose(m.param2, 76.0) else "accel" if int(m.param5) == 76 else None
            if kind is not None:
                if self.force_save_result == A.MAV_RESULT_ACCEPTED:
                    self.force_saves.append(kind)
                self._ack(m, self.force_save_result)
            else:
                self._ack(m, A.MAV_RESULT_UNSUPPORTED)
        elif cmd == A.MAV_CMD_SET_MESSAGE_INTERVAL:
            mid = int(m.param1)
            known = (A.MAVLINK_MSG_ID_RAW_IMU, A.MAVLINK_MSG_ID_SCALED_IMU, A.MAVLINK_MSG_ID_SCALED_IMU2,
                     A.MAVLINK_MSG_ID_SCALED_IMU3, A.MAVLINK_MSG_ID_ATTITUDE)
            if mid not in known:  # ArduPilot: DENIED and a STATUSTEXT (GCS_MAVLINK::set_message_interval)
                text = f"No ap_message for mavlink id ({mid})".encode()
                self._send(self._enc.statustext_encode(A.MAV_SEVERITY_INFO, text))
                self._ack(m, A.MAV_RESULT_DENIED)
                return
            us = m.param2
            if us < 0:
                self._intervals[mid] = None
            elif us == 0:  # that message's default rate (its stream's SR0_* rate), the others untouched
                self._intervals[mid] = self._default_interval(mid)
                self._next_due[mid] = time.monotonic()
            else:
                self._intervals[mid] = max(us * 1e-6, 1.0 / 400.0)
                self._next_due[mid] = time.monotonic()
            self._ack(m, A.MAV_RESULT_ACCEPTED)
        elif cmd == A.MAV_CMD_REQUEST_MESSAGE and self.position is not None and int(m.param1) in _POSITION_IDS:
            self._ack(m, A.MAV_RESULT_ACCEPTED)
            self._send_position(int(m.param1))
        elif cmd in (A.MAV_CMD_REQUEST_MESSAGE, A.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES):
            if cmd == A.MAV_CMD_REQUEST_MESSAGE and int(m.param1) != A.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
                self._ack(m, A.MAV_RESULT_UNSUPPORTED)
                return
            self._ack(m, A.MAV_RESULT_ACCEPTED)
            caps = (A.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT | A.MAV_PROTOCOL_CAPABILITY_MAVLINK2
                    | A.MAV_PROTOCOL_CAPABILITY_COMMAND_INT | A.MAV_PROTOCOL_CAPABILITY_MISSION_INT)
            version = (4 << 24) | (6 << 16) | (0 << 8) | 255  # 4.6.0 official
            self._send(self._enc.autopilot_version_encode(caps, version, 0, 0, 0, [0] * 8, [0] * 8,
                                                          [0] * 8, 0, 0, 0), self._sender)
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


_POSITION_IDS = (mavlink2.MAVLINK_MSG_ID_GPS_RAW_INT, mavlink2.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
                 mavlink2.MAVLINK_MSG_ID_HOME_POSITION)


def _name(param_id: Any) -> str:
    if isinstance(param_id, bytes):
        param_id = param_id.decode("ascii", "replace")
    return str(param_id).rstrip("\x00")

