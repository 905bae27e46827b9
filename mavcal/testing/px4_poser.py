"""The external simulator of a PX4 SITL (``PX4_SIM_MODEL=none_iris``): it poses the vehicle.

PX4 connects as a TCP client to 127.0.0.1:4560 (in its namespace); :class:`Poser` listens there and sends,
at ``rate_hz`` of simulated time in lockstep (HIL_SENSOR's ``time_usec`` drives PX4's clock), the raw
readings of a vehicle held still in a sequence of poses, turned between them with the matching gyro
rates, with known sensor errors and a little noise (PX4's voter flags a constant magnetometer STALE),
plus HIL_GPS at 5 Hz. The raw sensors (:mod:`mavcal.testing.px4_sim`'s truth, sensor frame = body frame
rotated by what PX4 is told)::

    accel (m/s^2)  u = D (R_acc^T f_body) + b          mag (gauss)  s = (M (R_mag^T B_body) + o) / 1000

The poses are given as a list of (roll, pitch, yaw) degrees; :meth:`Poser.run_poses` holds each for
``hold_s`` after a ``move_s`` turn. The poser runs in a thread of the test process whose listening
socket was opened inside PX4's namespace.
"""
from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Sequence

import numpy as np
from pymavlink.dialects.v20 import common as mavlink2
from scipy.spatial.transform import Rotation

from mavcal.autopilot.rotations import euler_to_matrix
from mavcal.core.constants import GRAVITY_MPS2
from mavcal.testing.px4_sim import FIELD_NED_MGAUSS, Px4Truth, raw_at

__all__ = ["Poser", "PosedPx4", "posed_px4", "QUIET_PARAMS", "SIM_PORT"]

SIM_PORT = 4560
#: PX4 must not learn compass biases of its own while a test poses it: neither the estimator
#: (EKF2_MAG_TYPE 5) nor the in-flight bias estimator (MBE) nor the autocal of a slot-less magnetometer
QUIET_PARAMS = {"EKF2_MAG_TYPE": 5, "MBE_ENABLE": 0, "SENS_MAG_AUTOCAL": 0}
_FIELDS_ALL = 0x1FFF  # accel, gyro, mag, baro, diff pressure, altitude, temperature


class _Out:
    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock

    def write(self, buf: bytes) -> None:
        self.sock.sendall(buf)


class Poser:
    """Listens on 127.0.0.1:4560 (create it inside PX4's namespace) and feeds PX4 in lockstep."""

    def __init__(self, truth: Px4Truth, *, rate_hz: float = 250.0, noise: tuple[float, float] = (0.004, 0.3),
                 seed: int = 0, home: tuple[float, float, float] = (47.397742, 8.545594, 488.0)) -> None:
        self.truth = truth
        self.rate_hz = rate_hz
        self.noise = noise
        self.rng = np.random.default_rng(seed)
        self.home = home
        self.attitude = Rotation.identity()
        self.rate_rad_s = np.zeros(3)
        self.time_us = 1_000_000
        self._server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._server.bind(("127.0.0.1", SIM_PORT))
        self._server.listen(1)
        self._sock: socket.socket | None = None
        self._mav: mavlink2.MAVLink | None = None
        self._lock = threading.Lock()
        self._halt = threading.Event()
        self._thread: threading.Thread | None = None
        self._gps_next = 0

    # ------------------------------------------------------------------ lifetime
    def start(self, accept_timeout_s: float = 60.0) -> Poser:
        """Accept PX4's connection (in a thread) and start sending."""
        self._thread = threading.Thread(target=self._run, args=(accept_timeout_s,), daemon=True, name="px4-poser")
        self._thread.start()
        return self

    def stop(self) -> None:
        self._halt.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        for s in (self._sock, self._server):
            if s is not None:
                with contextlib.suppress(OSError):
                    s.close()

    def _run(self, accept_timeout_s: float) -> None:
        self._server.settimeout(accept_timeout_s)
        try:
            self._sock, _ = self._server.accept()
        except OSError:
            return
        self._sock.setblocking(True)
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._mav = mavlink2.MAVLink(_Out(self._sock), srcSystem=1, srcComponent=51)
        period = 1.0 / self.rate_hz
        next_t = time.monotonic()
        while not self._halt.is_set():
            try:
                self._step(period)
                self._sock.setblocking(False)
                with contextlib.suppress(BlockingIOError):
                    self._sock.recv(65536)  # drain PX4's HIL_ACTUATOR_CONTROLS / HEARTBEAT
                self._sock.setblocking(True)
            except OSError:
                return
            next_t += period
            delay = next_t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            else:
                next_t = time.monotonic()

    # ------------------------------------------------------------------ state
    def _step(self, period: float) -> None:
        with self._lock:
            if np.any(self.rate_rad_s):
                self.attitude = self.attitude * Rotation.from_rotvec(self.rate_rad_s * period)
            att, rate = self.attitude, self.rate_rad_s.copy()
        acc, mag = raw_at(self.truth, Rotation.from_quat(att.as_quat()[None]))
        acc = acc[0] + self.rng.normal(0, self.noise[0], 3)
        mag = mag[0] + self.rng.normal(0, self.noise[1], 3)
        gyro = rate + self.rng.normal(0, 0.0005, 3)
        self.time_us += int(round(period * 1e6))
        assert self._mav is not None
        self._mav.hil_sensor_send(self.time_us, *acc, *gyro, *(mag / 1000.0), 1013.25 + self.rng.normal(0, 0.01),
                                  0.0, self.home[2] + self.rng.normal(0, 0.01), 25.0, _FIELDS_ALL, 0)
        if self.time_us >= self._gps_next:
            self._gps_next = self.time_us + 200_000
            lat, lon, alt = self.home
            self._mav.hil_gps_send(self.time_us, 3, int(lat * 1e7), int(lon * 1e7), int(alt * 1000), 80, 100,
                                   0, 0, 0, 0, 65535, 12)

    def hold(self, roll_deg: float, pitch_deg: float, yaw_deg: float) -> None:
        """Jump to a pose and hold it (no gyro rate: use :meth:`turn_to` between poses)."""
        with self._lock:
            self.attitude = Rotation.from_matrix(euler_to_matrix(*np.radians([roll_deg, pitch_deg, yaw_deg])))
            self.rate_rad_s = np.zeros(3)

    def turn_to(self, roll_deg: float, pitch_deg: float, yaw_deg: float, move_s: float) -> None:
        """Turn to a pose in ``move_s`` seconds at a constant rate (the gyro reads it), then hold."""
        target = Rotation.from_matrix(euler_to_matrix(*np.radians([roll_deg, pitch_deg, yaw_deg])))
        with self._lock:
            rotvec = (self.attitude.inv() * target).as_rotvec()
            self.rate_rad_s = rotvec / move_s
        time.sleep(move_s)
        with self._lock:
            self.attitude = target
            self.rate_rad_s = np.zeros(3)

    def run_poses(self, poses_deg: Sequence[tuple[float, float, float]], hold_s: float, move_s: float) -> None:
        for p in poses_deg:
            self.turn_to(*p, move_s)
            time.sleep(hold_s)

    def truth_body(self) -> tuple[np.ndarray, np.ndarray]:
        """The true specific force (m/s^2) and field (mGauss) in the body frame now."""
        with self._lock:
            att = self.attitude
        return (att.inv().apply(np.array([0.0, 0.0, -GRAVITY_MPS2])), att.inv().apply(np.asarray(FIELD_NED_MGAUSS)))


class PosedPx4:
    """A PX4 SITL and its poser in the shape the scripted hands of :mod:`mavcal.testing.sitl_hand` take
    (``set_pose``, ``declination_deg``, ``popen``, ``tool_device``, ``param_values``), so that
    :func:`mavcal.testing.sitl_hand.run_guided_capture` drives a guided ``mavcal capture`` against PX4."""

    def __init__(self, px4, poser: Poser, *, move_s: float = 1.0) -> None:
        self.px4, self.poser, self.move_s = px4, poser, move_s
        self.tool_device = px4.device
        self.param_values: list[tuple[str, float]] = []  # no control link: nothing seen
        B = np.asarray(FIELD_NED_MGAUSS)
        self.declination_deg = float(np.degrees(np.arctan2(B[1], B[0])))

    def set_pose(self, roll: float, pitch: float, yaw: float, settle: bool = True) -> None:
        """Turn to the pose (true yaw) at a hand's pace; ``settle`` False: a quick turn."""
        self.poser.turn_to(roll, pitch, yaw, self.move_s if settle else 0.3)

    def popen(self, argv, **kw):
        return self.px4.net.popen(argv, **kw)

    def netns(self):
        """Enter PX4's network namespace (``with posed.netns(): ...``)."""
        return self.px4.netns()


@contextlib.contextmanager
def posed_px4(seed: int, **sitl_kw):
    """A PX4 SITL in external-simulator mode posed by a :class:`Poser` with the random sensor errors and
    calibration in force of :func:`mavcal.testing.px4_sim.random_truth` (``seed``): yields
    ``(PosedPx4, truth)``; PX4 and the poser are stopped at the end."""
    from mavcal.px4.params import mag_names
    from mavcal.testing.px4_sim import random_truth
    from mavcal.testing.px4_sitl import Px4Sitl

    truth = random_truth(seed)
    boot = {k: v for k, v in truth.params.items() if k not in mag_names(0)["custom"]}
    holder: dict = {}
    try:
        with Px4Sitl(sim_model="none_iris", params={**boot, **QUIET_PARAMS},
                     before_boot=lambda: holder.setdefault("poser", Poser(truth, seed=seed).start()),
                     **sitl_kw) as px4:
            try:
                yield PosedPx4(px4, holder["poser"]), truth
            finally:
                holder["poser"].stop()
    finally:
        if "poser" in holder:  # also when PX4 did not boot after the poser started (stop is idempotent)
            holder["poser"].stop()
