"""The reference the compass cannot bend: the attitude along the flight, with a yaw independent
of the compasses, and the expected Earth field at the flight's place.

Roll and pitch are the EKF's (``ATT``; the compasses barely touch them): the fit itself uses
only them (:mod:`mavcal.flight.fit`, its residual (3)). The yaw serves its start and the
heading checks: the EKF's (the default), or the EKF-GSF yaw estimator's (``XKY0``, built from
the IMU and GPS velocity only) where it has converged (its own 1-sigma below
:data:`GSF_CONVERGED_DEG`); a compass's rotation is always judged against the GSF's when the
log has it. The field is the World Magnetic Model table's at the median GPS position
(:mod:`mavcal.sources.wmm`); without a position it is estimated freely (a wide prior).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mavcal.autopilot.rotations import euler_to_matrix
from mavcal.sources.flight_series import FlightSeries
from mavcal.sources.wmm import field_ned

__all__ = ["Reference", "reference_at", "GSF_CONVERGED_DEG"]

GSF_CONVERGED_DEG = 3.0
MIN_GSF_FRACTION = 0.3


@dataclass(frozen=True)
class Reference:
    """Body-to-NED rotations at the times asked for; ``valid``: where the reference is known."""

    R: np.ndarray  # (n, 3, 3)
    valid: np.ndarray  # (n,) bool
    yaw_source: str  # "gsf" or "ekf"
    B0_ned_mgauss: np.ndarray
    field_source: str  # "wmm" or "free"


def _interp_angle_deg(t: np.ndarray, ts: np.ndarray, a: np.ndarray) -> np.ndarray:
    u = np.unwrap(np.radians(a))
    return np.degrees(np.interp(t, ts, u))


def _matrices(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Body-to-NED rotations, (n, 3, 3), from angles in degrees."""
    return euler_to_matrix(np.radians(roll), np.radians(pitch), np.radians(yaw))


def check_matrices() -> float:
    """Largest difference of :func:`_matrices` from :func:`euler_to_matrix` on a few angles (a self-check)."""
    ang = np.array([[10.0, -20.0, 135.0], [-170.0, 80.0, -30.0], [0.0, 0.0, 0.0]])
    R = _matrices(ang[:, 0], ang[:, 1], ang[:, 2])
    return max(float(np.abs(R[k] - euler_to_matrix(*np.radians(ang[k]))).max()) for k in range(len(ang)))


def reference_at(s: FlightSeries, t: np.ndarray, yaw: str = "auto") -> Reference:
    """The reference at times ``t`` (s); ``yaw``: ``auto`` (the GSF's where converged, if it
    converged over enough of the flight), ``gsf`` or ``ekf``."""
    inside = (t >= s.att_time_s[0]) & (t <= s.att_time_s[-1])
    roll = np.interp(t, s.att_time_s, s.roll_deg)
    pitch = np.interp(t, s.att_time_s, s.pitch_deg)
    ekf_yaw = _interp_angle_deg(t, s.att_time_s, s.yaw_deg)
    source = "ekf"
    valid = inside
    yaw_deg = ekf_yaw
    if yaw in ("auto", "gsf") and len(s.gsf_time_s) > 10:
        sig = np.interp(t, s.gsf_time_s, s.gsf_yaw_sigma_deg)
        ok = inside & (t >= s.gsf_time_s[0]) & (t <= s.gsf_time_s[-1]) & (sig < GSF_CONVERGED_DEG)
        if yaw == "gsf" or ok.sum() >= MIN_GSF_FRACTION * max(1, inside.sum()):
            yaw_deg = _interp_angle_deg(t, s.gsf_time_s, s.gsf_yaw_deg)
            valid = ok
            source = "gsf"
    if s.lat_deg is not None and s.lon_deg is not None:
        B0 = field_ned(s.lat_deg, s.lon_deg)
        fsrc = "wmm"
    else:
        B0 = np.array([200.0, 0.0, 400.0])
        fsrc = "free"
    return Reference(_matrices(roll, pitch, yaw_deg), valid, source, B0, fsrc)


def heading_offset_deg(R: np.ndarray, mag_body: np.ndarray, B: np.ndarray) -> tuple[float, float, float]:
    """The compass's heading minus the reference's: its circular mean, spread and RMS (deg).

    ``mag_body`` (n, 3) is the field the firmware uses; tilt-compensated by the reference's roll
    and pitch, its horizontal direction must lie at the declination from the reference's yaw. A
    constant difference is a rotation (a wrong orientation); offsets and interference make it
    swing with the heading around zero instead.
    """
    h = np.einsum("nij,nj->ni", R, mag_body)  # in NED by the reference attitude
    d = np.arctan2(h[:, 1], h[:, 0]) - np.arctan2(B[1], B[0])
    if not len(d):
        return float("nan"), float("nan"), float("nan")
    z = np.exp(1j * d).mean()
    w = np.angle(np.exp(1j * d))
    return (float(np.degrees(np.angle(z))), float(np.degrees(np.sqrt(max(0.0, -2.0 * np.log(max(abs(z), 1e-12)))))),
            float(np.degrees(np.sqrt(np.mean(w * w)))))
