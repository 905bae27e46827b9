"""Realistic ArduPilot logs from a known truth.

A hand-held calibration session is simulated: the vehicle is held still (with hand tremor)
in a sequence of poses and moved between them. Each sensor instance has its own raw
errors; the simulated autopilot applies the calibration *in force* exactly as ArduPilot
does (:mod:`mavcal.ardupilot.firmware`), truncates to int16 where the firmware does, and
the result is written as a .tlog (RAW_IMU / SCALED_IMU2 / SCALED_IMU3, PARAM_VALUE,
STATUSTEXT, HEARTBEAT) and/or a DataFlash .bin (PARM, MSG, IMU, MAG with I, Ofs, MO).

Raw sensor models (frames as :func:`mavcal.ardupilot.recover.recover_raw` returns them):

* accelerometer, board frame: ``u = K_a @ (R_A.T @ f_body) + b_a + noise`` with
  ``K_a = diag(gain) + upper off-diagonals (cross)`` and ``R_A`` = AHRS_ORIENTATION
  (:class:`AccelErrorTruth`);
* compass, sensor frame: ``s = R_phys.T @ (K_m @ B_body + h) + noise`` (``R_phys`` the
  physical mounting rotation, ``K_m`` soft iron, ``h`` hard iron); the firmware rotates it
  by its configured orientation, ``b = R_param @ s`` -- ``b`` is the "raw" truth returned.

Times in the result are seconds since the start of the simulated session; the tlog
stores ``t0_unix_s + t`` as receive time and ``boot_s + t`` as vehicle time, the .bin
``TimeUS = (boot_s + t) * 1e6``.
"""
from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from mavcal.ardupilot import firmware as fw
from mavcal.autopilot.rotations import euler_to_matrix, rotation_matrix
from mavcal.core.constants import GRAVITY_MPS2
from mavcal.testing.logwriters import DataFlashWriter, TlogWriter

log = logging.getLogger(__name__)

__all__ = ["AccelErrorTruth", "MagTruth", "SimConfig", "SimLog", "simulate_session", "write_tlog", "write_bin",
           "poses_within_reach",
           "DEFAULT_POSES_DEG"]

G = GRAVITY_MPS2

#: 14 hand-held poses (roll, pitch, yaw in degrees) spread over the sphere of gravity
#: directions: the six faces, plus tilted poses and yaw variety.
DEFAULT_POSES_DEG: tuple[tuple[float, float, float], ...] = (
    (0, 0, 0), (0, 0, 120), (90, 0, 30), (-90, 0, 200), (0, 80, 60), (0, -80, 300),
    (180, 0, 90), (45, 30, 150), (-45, 35, 240), (40, -40, 20), (-35, -45, 100),
    (135, 30, 330), (-130, -35, 45), (150, -40, 270),
)


def poses_within_reach(max_tilt_deg: float, n: int = 12, seed: int = 0, headings: int | None = None
                       ) -> tuple[tuple[float, float, float], ...]:
    """``n`` poses (roll, pitch, yaw deg) of a vehicle that cannot be turned over: turned to
    ``headings`` (default ``n``) headings evenly all the way round, every third pose level, the
    others tilted in a random direction by 40-100 % of ``max_tilt_deg`` (one side on a block)."""
    rng = np.random.default_rng(seed)
    k_h = headings or n
    out = []
    for k in range(n):
        d = rng.uniform(0.0, 2.0 * np.pi)
        t = 0.0 if k % 3 == 0 else max_tilt_deg * rng.uniform(0.4, 1.0)
        out.append((float(t * np.cos(d)), float(t * np.sin(d)), float(360.0 * (k % k_h) / k_h)))
    return tuple(out)


@dataclass(frozen=True)
class AccelErrorTruth:
    """Raw errors of one accelerometer, stated **as the sensor's own errors**:
    ``u = K (R_A^T f) + bias`` (f = true specific force in the body frame, u = raw reading
    in the board frame).

    The ArduPilot calibration that undoes it is *not* these numbers (INS_ACCnSCAL ~ 1/gain,
    INS_ACCnOFFS = bias); :class:`mavcal.testing.vehicle_sensors.AccelCalTruth` is the
    test vehicle's opposite convention, truth stated as the ideal calibration.

    Attributes
    ----------
    bias_mps2 : (3,) m/s^2, board frame.
    gain : (3,) diagonal of K.
    cross : (3,) upper off-diagonals of K: (K_xy, K_xz, K_yz).
    noise_mps2 : float, standard deviation per axis.
    """

    bias_mps2: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gain: tuple[float, float, float] = (1.0, 1.0, 1.0)
    cross: tuple[float, float, float] = (0.0, 0.0, 0.0)
    noise_mps2: float = 0.02

    @property
    def K(self) -> np.ndarray:
        g, c = self.gain, self.cross
        return np.array([[g[0], c[0], c[1]], [0.0, g[1], c[2]], [0.0, 0.0, g[2]]])


@dataclass(frozen=True)
class MagTruth:
    """Raw errors of one compass: ``s = R_phys^T (K B_body + hard_iron)``.

    Attributes
    ----------
    hard_iron_mgauss : (3,) body frame.
    soft_iron : (3, 3) K (identity by default).
    mount : physical mounting rotation (ArduPilot enum), or None = as configured on the
        autopilot (no orientation error).
    noise_mgauss : float, standard deviation per axis.
    """

    hard_iron_mgauss: tuple[float, float, float] = (0.0, 0.0, 0.0)
    soft_iron: tuple[tuple[float, ...], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    mount: int | None = None
    noise_mgauss: float = 1.5

    @property
    def K(self) -> np.ndarray:
        return np.asarray(self.soft_iron, dtype=float).reshape(3, 3)


@dataclass(frozen=True)
class SimConfig:
    """A simulated hand-held session.

    Attributes
    ----------
    accels, mags : per-instance raw errors (instance = position).
    accel_cals, compass_cals : the calibration in force on the autopilot at the start,
        one per instance (default: identity, AHRS_ORIENTATION 0).
    change_at_s : time of a mid-log parameter change (None = no change) to
        ``accel_cals_after`` / ``compass_cals_after``.
    accel_cal_period_s : (start, end) during which an onboard accelerometer calibration
        "runs": prompts and "Calibration successful" are logged and the firmware skips
        the accel offsets/scale. The parameters may change at ``end`` via ``change_at_s``.
    earth_field_ned_mgauss : (3,) earth field, NED.
    poses_deg : sequence of (roll, pitch, yaw) degrees, body -> NED.
    hold_s, move_s, lead_s : still time per pose, motion time between poses, still time
        before the first pose is entered (the vehicle is held in pose 0 during lead).
    rate_hz : tlog RAW_IMU/SCALED_IMU rate; ``imu_rate_hz``, ``mag_rate_hz``: .bin rates.
    jitter_deg : amplitude of hand tremor (rotation), ``tremor_mps2`` of its acceleration.
    motor_ofs_mgauss : per-compass constant motor offset added by the firmware (logged
        in .bin MAG.MO*; a tlog cannot carry it, so leave it None for tlogs).
    seed : random seed.
    """

    accels: tuple[AccelErrorTruth, ...] = (AccelErrorTruth(),)
    mags: tuple[MagTruth, ...] = (MagTruth(),)
    accel_cals: tuple[fw.AccelCal, ...] | None = None
    compass_cals: tuple[fw.CompassCal, ...] | None = None
    change_at_s: float | None = None
    accel_cals_after: tuple[fw.AccelCal, ...] | None = None
    compass_cals_after: tuple[fw.CompassCal, ...] | None = None
    accel_cal_period_s: tuple[float, float] | None = None
    earth_field_ned_mgauss: tuple[float, float, float] = (200.0, 15.0, 450.0)
    poses_deg: tuple[tuple[float, float, float], ...] = DEFAULT_POSES_DEG
    hold_s: float = 4.0
    move_s: float = 2.0
    lead_s: float = 1.0
    rate_hz: float = 50.0
    imu_rate_hz: float = 25.0
    mag_rate_hz: float = 10.0
    jitter_deg: float = 0.3
    tremor_mps2: float = 0.03
    motor_ofs_mgauss: tuple[tuple[float, float, float], ...] | None = None
    seed: int = 0

    @property
    def duration_s(self) -> float:
        n = len(self.poses_deg)
        return self.lead_s + n * self.hold_s + (n - 1) * self.move_s + 0.5


@dataclass(frozen=True, eq=False)
class SimLog:
    """Result of :func:`simulate_session` (and the paths written).

    Per instance ``i`` (lists indexed by instance):

    Attributes
    ----------
    accel_time_s, mag_time_s : list of (n,) arrays, seconds since session start.
    accel_raw_mps2 : list of (n, 3), true raw accel, board frame (noise included).
    mag_raw_mgauss : list of (n, 3), true raw field, body frame after the firmware's
        orientation (noise included).
    accel_logged_mps2, mag_logged_mgauss : what the autopilot reports, before
        truncation (float).
    gyro_rad_s : list of (n, 3) per accel instance, true body rates.
    calibrating : list of (n,) bool per accel instance (onboard accel cal running).
    still_windows_s : (N, 2), start/end of every still hold.
    attitudes : (N, 3, 3), pose rotations body -> NED.
    params_initial, params_after : name -> value of the calibration parameters.
    paths : kind ("tlog", "bin") -> Path
    config : SimConfig
    """

    accel_time_s: list[np.ndarray]
    mag_time_s: list[np.ndarray]
    accel_raw_mps2: list[np.ndarray]
    mag_raw_mgauss: list[np.ndarray]
    accel_logged_mps2: list[np.ndarray]
    mag_logged_mgauss: list[np.ndarray]
    gyro_rad_s: list[np.ndarray]
    calibrating: list[np.ndarray]
    still_windows_s: np.ndarray
    attitudes: np.ndarray
    params_initial: dict[str, float]
    params_after: dict[str, float]
    config: SimConfig
    paths: dict[str, Path] = field(default_factory=dict)


# --------------------------------------------------------------------------- motion

class _Motion:
    """Attitude and specific force of the hand-held vehicle as functions of time."""

    def __init__(self, cfg: SimConfig, rng: np.random.Generator) -> None:
        self.cfg = cfg
        rots = [euler_to_matrix(*np.radians(p)) for p in cfg.poses_deg]
        self.attitudes = np.array(rots)
        self.R = Rotation.from_matrix(self.attitudes)
        n = len(rots)
        starts = cfg.lead_s + np.arange(n) * (cfg.hold_s + cfg.move_s)
        self.windows = np.column_stack([starts, starts + cfg.hold_s])
        # hand sway/tremor: a few slow sinusoids per axis with random phase
        self.freqs = rng.uniform(0.3, 3.0, (3, 4))
        self.phases = rng.uniform(0, 2 * np.pi, (3, 4))
        self.amp = np.radians(cfg.jitter_deg) / 2.0
        self.lin_freqs = rng.uniform(0.5, 4.0, (3, 3))
        self.lin_phases = rng.uniform(0, 2 * np.pi, (3, 3))

    def _pose(self, t: np.ndarray) -> Rotation:
        cfg = self.cfg
        n = len(self.windows)
        i = np.clip(np.searchsorted(self.windows[:, 0], t, side="right") - 1, 0, n - 1)
        quats = self.R.as_quat()[i]
        moving = (t > self.windows[i, 1]) & (i < n - 1)
        for seg in np.unique(i[moving]):
            sel = moving & (i == seg)
            s = np.clip((t[sel] - self.windows[seg, 1]) / cfg.move_s, 0.0, 1.0)
            s = 0.5 - 0.5 * np.cos(np.pi * s)  # smooth start and stop
            sl = Slerp([0.0, 1.0], Rotation.concatenate([self.R[seg], self.R[seg + 1]]))
            quats[sel] = sl(s).as_quat()
        return Rotation.from_quat(quats)

    def attitude(self, t: np.ndarray) -> Rotation:
        """Body -> NED rotation at times t, tremor included."""
        t = np.asarray(t, dtype=float)
        trem = self.amp * np.sin(2 * np.pi * self.freqs[None] * t[:, None, None] + self.phases[None]).sum(axis=2)
        return self._pose(t) * Rotation.from_rotvec(trem)

    def moving(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        still = np.zeros(t.shape, dtype=bool)
        for a, b in self.windows:
            still |= (t >= a) & (t <= b)
        still |= t < self.windows[0, 0]
        still |= t > self.windows[-1, 1]
        return ~still

    def linear_accel_ned(self, t: np.ndarray) -> np.ndarray:
        """Hand acceleration in NED: tremor always, plus a push/pull while moving."""
        cfg = self.cfg
        t = np.asarray(t, dtype=float)
        a = cfg.tremor_mps2 / 1.5 * np.sin(2 * np.pi * self.lin_freqs[None] * t[:, None, None]
                                           + self.lin_phases[None]).sum(axis=2)
        mv = self.moving(t)
        if np.any(mv):
            # a sine bump of ~1.5 m/s^2 along a direction that depends on the move index
            idx = np.searchsorted(self.windows[:, 1], t, side="right") - 1
            frac = np.clip((t - self.windows[np.clip(idx, 0, None), 1]) / cfg.move_s, 0, 1)
            dirs = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [0.7, 0.7, 0], [0, 0.7, -0.7]])
            d = dirs[np.clip(idx, 0, None) % len(dirs)]
            a = a + np.where(mv[:, None], 1.5 * np.sin(2 * np.pi * frac)[:, None] * d, 0.0)
        return a

    def gyro_body(self, t: np.ndarray, dt: float = 1e-3) -> np.ndarray:
        r0 = self.attitude(t - dt / 2)
        r1 = self.attitude(t + dt / 2)
        return (r0.inv() * r1).as_rotvec() / dt


# --------------------------------------------------------------------------- simulate

def _cal_params(accel_cals: Sequence[fw.AccelCal], compass_cals: Sequence[fw.CompassCal]) -> dict[str, float]:
    p: dict[str, float] = {}
    board = accel_cals[0].board_orient if accel_cals else (compass_cals[0].orient if compass_cals else 0)
    board_names = fw.board_param_names()
    p[str(board_names["orientation"])] = float(board)
    for i, acal in enumerate(accel_cals):
        p.update(fw.accel_param_values(acal, i))
    for k, ccal in enumerate(compass_cals):
        p.update(fw.compass_param_values(ccal, k))
        names = {key: str(name) for key, name in fw.compass_param_names(k).items()
                 if key in ("external", "orient", "dev_id", "prio_id")}
        ext = bool(ccal.external)
        p[names["external"]] = 1.0 if ext else 0.0
        p[names["orient"]] = float(ccal.orient) if ext else 0.0
        p[names["dev_id"]] = float(97539 + 256 * k)
        p[names["prio_id"]] = float(97539 + 256 * k)
    p[str(board_names["motct"])] = 0.0
    return {k: float(np.float32(v)) for k, v in p.items()}


def _f32(c):
    """Round the calibration values to float32, as the autopilot stores them."""
    if isinstance(c, fw.AccelCal):
        return replace(c, ofs_mps2=tuple(np.float32(c.ofs_mps2).astype(float)),
                       scale=tuple(np.float32(c.scale).astype(float)))
    return replace(c, ofs_mgauss=tuple(np.float32(c.ofs_mgauss).astype(float)),
                   dia=tuple(np.float32(c.dia).astype(float)), odi=tuple(np.float32(c.odi).astype(float)),
                   scale=float(np.float32(c.scale)))


class _Session:
    """The sensors of one simulated session: motion, calibrations in force, noise."""

    def __init__(self, cfg: SimConfig) -> None:
        self.cfg = cfg
        self.rng = np.random.default_rng(cfg.seed)
        self.motion = _Motion(cfg, self.rng)
        n_acc, n_mag = len(cfg.accels), len(cfg.mags)
        self.acal0 = tuple(_f32(c) for c in (cfg.accel_cals or tuple(fw.AccelCal() for _ in range(n_acc))))
        self.ccal0 = tuple(_f32(c) for c in (cfg.compass_cals or tuple(fw.CompassCal() for _ in range(n_mag))))
        self.acal1 = tuple(_f32(c) for c in (cfg.accel_cals_after or self.acal0))
        self.ccal1 = tuple(_f32(c) for c in (cfg.compass_cals_after or self.ccal0))
        if (len(self.acal0) != n_acc or len(self.ccal0) != n_mag or len(self.acal1) != n_acc
                or len(self.ccal1) != n_mag):
            raise ValueError("one calibration per sensor instance is needed")
        self.t_change = np.inf if cfg.change_at_s is None else float(cfg.change_at_s)
        self.p0 = _cal_params(self.acal0, self.ccal0)
        self.p1 = _cal_params(self.acal1, self.ccal1)

    def times(self, rate: float) -> np.ndarray:
        return np.arange(0.0, self.cfg.duration_s, 1.0 / rate)

    def accel(self, i: int, t: np.ndarray):
        """(true raw u, reported, gyro, calibrating) of accelerometer ``i`` at times ``t``."""
        cfg, motion = self.cfg, self.motion
        att = motion.attitude(t)
        f_ned = motion.linear_accel_ned(t) - np.array([0.0, 0.0, G])
        f_body = att.inv().apply(f_ned)
        a_truth = cfg.accels[i]
        RA = self.acal0[i].board_matrix
        u = (f_body @ RA) @ a_truth.K.T + np.asarray(a_truth.bias_mps2)
        u = u + self.rng.normal(0.0, a_truth.noise_mps2, u.shape)
        calib = np.zeros(len(t), dtype=bool)
        if cfg.accel_cal_period_s is not None:
            calib = (t >= cfg.accel_cal_period_s[0]) & (t < cfg.accel_cal_period_s[1])
        rep = np.empty_like(u)
        before = t < self.t_change
        for mask, cal in ((before, self.acal0[i]), (~before, self.acal1[i])):
            rep[mask & ~calib] = fw.apply_accel(cal, u[mask & ~calib])
            rep[mask & calib] = fw.apply_accel(cal, u[mask & calib], calibrating=True)
        return u, rep, motion.gyro_body(t), calib

    def mag(self, k: int, t: np.ndarray):
        """(true raw b, reported, motor offset or None) of compass ``k`` at times ``t``."""
        att = self.motion.attitude(t)
        B_body = att.inv().apply(np.tile(np.asarray(self.cfg.earth_field_ned_mgauss, dtype=float), (len(t), 1)))
        m_truth = self.cfg.mags[k]
        R_param = self.ccal0[k].mount_matrix
        R_phys = R_param if m_truth.mount is None else rotation_matrix(m_truth.mount)
        s = (B_body @ m_truth.K.T + np.asarray(m_truth.hard_iron_mgauss)) @ R_phys  # R_phys^T applied
        s = s + self.rng.normal(0.0, m_truth.noise_mgauss, s.shape)
        b = s @ R_param.T
        mot = None
        if self.cfg.motor_ofs_mgauss is not None:
            mot = np.broadcast_to(np.asarray(self.cfg.motor_ofs_mgauss[k], dtype=float), b.shape)
        rep = np.empty_like(b)
        before = t < self.t_change
        for mask, cal in ((before, self.ccal0[k]), (~before, self.ccal1[k])):
            rep[mask] = fw.apply_compass(cal, b[mask], None if mot is None else mot[mask], sensor_frame=False)
        return b, rep, mot

    def samples(self, ta: np.ndarray, tm: np.ndarray):
        """Every accelerometer at ``ta``, then every compass at ``tm`` (this order of noise draws)."""
        acc = [self.accel(i, ta) for i in range(len(self.cfg.accels))]
        mag = [self.mag(k, tm) for k in range(len(self.cfg.mags))]
        return acc, mag

    def result(self, ta: np.ndarray, tm: np.ndarray, acc, mag, paths: dict[str, Path]) -> SimLog:
        n_acc, n_mag = len(acc), len(mag)
        return SimLog([ta] * n_acc, [tm] * n_mag, [a[0] for a in acc], [m[0] for m in mag],
                      [a[1] for a in acc], [m[1] for m in mag], [a[2] for a in acc], [a[3] for a in acc],
                      self.motion.windows.copy(), self.motion.attitudes.copy(), self.p0, self.p1, self.cfg, paths)


def simulate_session(cfg: SimConfig = SimConfig(), tlog: str | Path | None = None,
                     bin: str | Path | None = None, mavlink2: bool = False) -> SimLog:  # noqa: A002
    """Simulate a session and optionally write it as a tlog and/or DataFlash log.

    Parameters
    ----------
    cfg : SimConfig
    tlog, bin : path, optional
        Where to write the .tlog / .bin. The tlog carries accel, gyro and mag of each
        instance at ``cfg.rate_hz``; the .bin IMU at ``imu_rate_hz`` and MAG at
        ``mag_rate_hz``. The truth is per log kind: both kinds use the same motion and
        sensor errors; the arrays returned are those of the tlog when ``tlog`` is given,
        else of the .bin (use two calls for both truths).

    Returns
    -------
    SimLog
    """
    sim = _Session(cfg)
    result: SimLog | None = None
    paths: dict[str, Path] = {}
    if tlog is not None:
        t = sim.times(cfg.rate_hz)
        acc, mag = sim.samples(t, t)
        write_tlog(Path(tlog), cfg, t, acc, mag, sim.p0, sim.p1, sim.t_change, mavlink2=mavlink2)
        paths["tlog"] = Path(tlog)
        result = sim.result(t, t, acc, mag, paths)
    if bin is not None:
        ta = sim.times(cfg.imu_rate_hz)
        tm = sim.times(cfg.mag_rate_hz) + 0.013  # compass samples not aligned with IMU samples
        tm = tm[tm < cfg.duration_s]
        acc, mag = sim.samples(ta, tm)
        write_bin(Path(bin), cfg, ta, tm, acc, mag, sim.p0, sim.p1, sim.t_change, sim.ccal0, sim.ccal1)
        paths["bin"] = Path(bin)
        if result is None:
            result = sim.result(ta, tm, acc, mag, paths)
    if result is None:  # nothing written: the tlog-rate truth
        t = sim.times(cfg.rate_hz)
        acc, mag = sim.samples(t, t)
        result = sim.result(t, t, acc, mag, paths)
    return result


def _events(cfg: SimConfig) -> list[tuple[float, str, str]]:
    """(time, kind, text) of the onboard accel calibration, if any."""
    if cfg.accel_cal_period_s is None:
        return []
    a, b = cfg.accel_cal_period_s
    prompts = ["level", "on its LEFT side", "on its RIGHT side", "nose DOWN", "nose UP", "on its BACK"]
    out = [(max(a - 1.5, 0.0), "command", "")]
    for j, p in enumerate(prompts):
        out.append((a + j * (b - a) / 6.0 + 0.01, "text", f"Place vehicle {p} and press any key."))
    out.append((b, "text", "Calibration successful"))
    return out


def write_tlog(path: Path, cfg: SimConfig, t: np.ndarray, acc, mag, p0: dict[str, float],
               p1: dict[str, float], t_change: float, t0_unix_s: float = 1.7e9, boot_s: float = 30.0,
               mavlink2: bool = False) -> Path:
    """Write the simulated samples as a tlog (see :func:`simulate_session`)."""
    recs: list[tuple[float, int, tuple]] = []
    for hb in np.arange(0.0, cfg.duration_s, 1.0):
        recs.append((hb, 0, ("hb",)))
    names = sorted(p0)
    for j, n in enumerate(names):
        recs.append((0.002 * j, 1, ("param", n, p0[n], j, len(names))))
    if np.isfinite(t_change):
        for n in names:
            if p1.get(n) != p0.get(n):
                recs.append((t_change, 1, ("param", n, p1[n], 65535, len(names))))
    for te, kind, text in _events(cfg):
        recs.append((te, 2, ("cmd",) if kind == "command" else ("text", text)))
    n_acc, n_mag = len(acc), len(mag)
    for j, tt in enumerate(t):
        for inst in range(max(n_acc, n_mag, 1)):
            if inst > 2:
                continue
            a = acc[inst][1][j] if inst < n_acc else np.zeros(3)
            g = acc[inst][2][j] if inst < n_acc else np.zeros(3)
            m = mag[inst][1][j] if inst < n_mag else np.zeros(3)
            recs.append((tt, 3, ("imu", inst, a * 1000.0 / G, g * 1000.0, m)))
    recs.sort(key=lambda r: (r[0], r[1]))
    with TlogWriter(path, mavlink2=mavlink2) as w:
        for tt, _, r in recs:
            tu = t0_unix_s + tt
            if r[0] == "hb":
                w.heartbeat(tu)
            elif r[0] == "param":
                w.param_value(tu, r[1], r[2], index=r[3], count=r[4])
            elif r[0] == "cmd":
                w.command_long(tu, 241, (0, 0, 0, 0, 1, 0, 0))
            elif r[0] == "text":
                w.statustext(tu, r[1])
            else:
                _, inst, a, g, m = r
                boot_us = int(round((boot_s + tt) * 1e6))
                if inst == 0:
                    w.raw_imu(tu, boot_us, a, g, m)
                else:
                    w.scaled_imu(inst + 1, tu, boot_us // 1000, a, g, m)
    log.info("wrote %s (%d records)", path, len(recs))
    return path


def write_bin(path: Path, cfg: SimConfig, ta: np.ndarray, tm: np.ndarray, acc, mag, p0: dict[str, float],
              p1: dict[str, float], t_change: float, ccal0, ccal1, boot_s: float = 30.0) -> Path:
    """Write the simulated samples as a DataFlash log (see :func:`simulate_session`)."""
    recs: list[tuple[float, int, tuple]] = []
    for n in sorted(p0):
        recs.append((0.0, 0, ("parm", n, p0[n], p0[n])))
    if np.isfinite(t_change):
        for n in sorted(p0):
            if p1.get(n) != p0.get(n):
                recs.append((t_change, 1, ("parm", n, p1[n], float("nan"))))
    recs.append((0.0, 1, ("msg", "ArduCopter V4.5.0 (mavcal simulation)")))
    for te, kind, text in _events(cfg):
        if kind == "text":
            recs.append((te, 2, ("msg", text)))
    for i, (_u, rep, gyro, _) in enumerate(acc):
        rep32 = rep.astype(np.float32)
        for j, tt in enumerate(ta):
            recs.append((tt, 3, ("imu", i, gyro[j], rep32[j])))
    for k, (_b, rep, mot) in enumerate(mag):
        for j, tt in enumerate(tm):
            cal = ccal0[k] if tt < t_change else ccal1[k]
            recs.append((tt, 3, ("mag", k, rep[j], cal.ofs_mgauss, (0, 0, 0) if mot is None else mot[j])))
    recs.sort(key=lambda r: (r[0], r[1]))
    with DataFlashWriter(path) as w:
        for tt, _, r in recs:
            tus = int(round((boot_s + tt) * 1e6))
            if r[0] == "parm":
                w.parm(tus, r[1], r[2], r[3])
            elif r[0] == "msg":
                w.msg(tus, r[1])
            elif r[0] == "imu":
                w.imu(tus, r[1], r[2], r[3])
            else:
                w.mag(tus, r[1], r[2], r[3], r[4])
    log.info("wrote %s (%d records)", path, len(recs))
    return path
