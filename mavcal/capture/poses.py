"""The poses a capture can advise and what each would add: the candidate attitudes and their words
(:func:`candidate_poses`, :func:`describe_pose`), the readings a fit predicts there
(:func:`predicted_means`) and the information a still interval there adds to the heading error
(:func:`pose_scores`, :func:`heading_variances`). Which one is advised next, and when the capture
stops, is :mod:`mavcal.capture.session`.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mavcal.autopilot.rotations import euler_to_matrix
from mavcal.capture.reach import reach_tilts
from mavcal.core.constants import GRAVITY_MPS2
from mavcal.core.models import FORMS, MODELS
from mavcal.core.refine import JointParams, JointProblem, Term
from mavcal.pipeline import CalibrationRun

__all__ = ["euler_matrix", "describe_pose", "candidate_poses", "predicted_means", "heading_gradients", "pose_scores",
           "heading_variances", "pose_information", "predicted_readings", "SMALL_TILT_DEG", "SMALL_TILT_COS"]

G0 = GRAVITY_MPS2


def euler_matrix(roll_deg: float, pitch_deg: float, yaw_deg: float) -> np.ndarray:
    """Body-to-NED rotation Rz(yaw) Ry(pitch) Rx(roll) from degrees (ArduPilot ``from_euler``)."""
    return euler_to_matrix(*np.radians([roll_deg, pitch_deg, yaw_deg]))


#: tilts from this size on are said in words ("nose up 5 deg"): a pose within reach may be tilted only a few deg
SMALL_TILT_DEG = 2.5
SMALL_TILT_COS = float(np.cos(np.radians(SMALL_TILT_DEG)))

_POINTS = ["north", "north-east", "east", "south-east", "south", "south-west", "west", "north-west"]


def describe_pose(roll_deg: float, pitch_deg: float, yaw_deg: float) -> str:
    """Words a person holding the vehicle can follow, e.g. "nose down, rolled 45 deg left"."""
    C = euler_matrix(roll_deg, pitch_deg, yaw_deg)
    down_b = C.T @ np.array([0.0, 0.0, 1.0])  # the body direction that points down
    parts: list[str] = []
    ax = int(np.argmax(np.abs(down_b)))
    if ax == 2 and down_b[2] > 0.7:
        parts.append("level" if down_b[2] > SMALL_TILT_COS else "upright")
    elif ax == 2 and down_b[2] < -0.7:
        parts.append("upside down")
    elif ax == 0 and abs(down_b[0]) > 0.7:
        parts.append("nose down" if down_b[0] > 0 else "nose up")
    elif ax == 1 and abs(down_b[1]) > 0.7:
        parts.append("on its right side" if down_b[1] > 0 else "on its left side")
    # the finer tilts, from the angles
    pitch = float(pitch_deg)
    roll = float((roll_deg + 180) % 360 - 180)
    if "nose" not in parts[0] if parts else True:
        if SMALL_TILT_DEG <= abs(pitch) < 80:
            parts.append(f"nose {'up' if pitch > 0 else 'down'} {abs(pitch):.0f} deg")
    if abs(pitch) < 80 and SMALL_TILT_DEG <= abs(roll) <= 170 and "side" not in (parts[0] if parts else ""):
        parts.append(f"rolled {abs(roll):.0f} deg {'right' if roll > 0 else 'left'}")
    elif abs(pitch) >= 80 and 10 <= abs(roll) <= 170:
        parts.append(f"rolled {abs(roll):.0f} deg {'right' if roll > 0 else 'left'}")
    if not parts:
        parts.append("level")
    # heading: where the nose (or, when the nose is vertical, the top) points, magnetically
    ref = C @ np.array([1.0, 0.0, 0.0])
    what = "nose"
    if abs(ref[2]) > 0.8:
        ref, what = C @ np.array([0.0, 0.0, -1.0]), "top"
    hdg = np.degrees(np.arctan2(ref[1], ref[0])) % 360
    parts.append(f"{what} towards magnetic {_POINTS[int(((hdg + 22.5) % 360) // 45)]}")
    return ", ".join(parts)


def candidate_poses(max_tilt_deg: float | None = None) -> list[tuple[float, float, float]]:
    """Attitudes a person can hold and name: roll, pitch and heading in 45 deg steps; with
    ``max_tilt_deg`` (a vehicle that cannot be turned over) level and tilted by half and all of
    it in 8 directions (one side or a corner on a block), every heading in 45 deg steps."""
    out = []
    if max_tilt_deg is not None:
        for roll, pitch in reach_tilts(max_tilt_deg):
            for yaw in range(0, 360, 45):
                out.append((roll, pitch, float(yaw)))
        return out
    for pitch in (-90, -45, 0, 45, 90):
        rolls = (0,) if abs(pitch) == 90 else (-135, -90, -45, 0, 45, 90, 135, 180)
        for roll in rolls:
            for yaw in range(0, 360, 45):
                out.append((float(roll), float(pitch), float(yaw)))
    return out


def pose_information(run: CalibrationRun, poses: Sequence[tuple[float, float, float]], n_samples: float):
    """Information of the intervals so far and of one more interval at each candidate pose.

    Both are Schur complements of the Gauss-Newton normal equations
    (:class:`mavcal.core.refine.JointProblem`) at the current estimate, the orientations
    marginalised; a candidate's means are predicted by the current model. Returns
    (S_cur (P, P), dS (K, P, P), problem, params).
    """
    cal = run.calibration
    spec = MODELS[cal.model]
    seg = run.segmentation
    ai, mi = run.mapping.accel[0].instance, run.mapping.compass[0].instance
    mu_a = np.array([seg.intervals[k].accel_mps2[ai].mean(0) for k in run.intervals_used])
    mu_m = np.array([seg.intervals[k].mag_mgauss[mi].mean(0) for k in run.intervals_used])
    n_a = np.array([seg.intervals[k].accel_mps2[ai].shape[0] for k in run.intervals_used], float)
    n_m = np.array([seg.intervals[k].mag_mgauss[mi].shape[0] for k in run.intervals_used], float)
    fa, fm = FORMS[spec.accel_form], FORMS[spec.mag_form]
    Sa, Sm = cal.accel.noise_cov, cal.mag.noise_cov

    def info(mua, mum, na, nm, R):
        prob = JointProblem([Term("accel", fa, mua, na, Sa), Term("mag", fm, mum, nm, Sm)])
        p = JointParams((cal.accel.gain, cal.mag.gain), (cal.accel.bias, cal.mag.bias), cal.h_z, R)
        _, Jg, Jr = prob.jacobians(p)
        Hgg = np.einsum("nmp,nmq->npq", Jg, Jg)
        Hgr = np.einsum("nmp,nmr->npr", Jg, Jr)
        Hrr = np.einsum("nmr,nms->nrs", Jr, Jr) + 1e-12 * np.eye(3)
        return Hgg - np.einsum("npr,nrs,nqs->npq", Hgr, np.linalg.inv(Hrr), Hgr), prob, p

    S_parts, prob, p = info(mu_a, mu_m, n_a, n_m, cal.orientations)
    pa, pm, R = predicted_readings(run, poses)
    nn = np.full(len(poses), float(n_samples))
    dS, _, _ = info(pa, pm, nn, nn, R)
    S = S_parts.sum(axis=0)
    if cal.held and cal.param_cov is not None:  # held parameters: their prior's information (mavcal.core.held)
        k = [prob.names.index(n) for n in cal.held]
        S[k, k] += 1.0 / np.maximum(np.diag(cal.param_cov)[k], 1e-300)
    return S, dS, prob, p


def predicted_readings(run: CalibrationRun, poses: Sequence[tuple[float, float, float]]
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Accel and compass means (K, 3) the current model predicts at each pose, and the
    rotations (K, 3, 3) inertial (NED, magnetic) -> engine frame E."""
    cal = run.calibration
    board = run.mapping.accel[0].old.board_matrix @ run.mapping.accel[0].frame_rotation  # E -> body
    Cs = np.array([euler_matrix(*q) for q in poses])
    R = np.einsum("ji,nkj->nik", board, Cs)  # (board)^T C^T: inertial (NED, magnetic) -> E
    pa = (cal.accel.gain @ (R @ cal.gravity)[..., None])[..., 0] + cal.accel.bias
    pm = (cal.mag.gain @ (R @ cal.field)[..., None])[..., 0] + cal.mag.bias
    return pa, pm, R


def predicted_means(run: CalibrationRun, poses: Sequence[tuple[float, float, float]]) -> tuple[np.ndarray, np.ndarray]:
    """(K, 3) accel (m/s^2) and (K, 3) compass (mGauss) means the current fit predicts for a
    still interval at each pose (roll, pitch, magnetic yaw in degrees), in the frames of the
    recovered readings the fit used."""
    pa, pm, _ = predicted_readings(run, poses)
    return pa, pm


def heading_gradients(run: CalibrationRun, prob: JointProblem, p) -> np.ndarray:
    """d(heading error)/d(theta) at every attitude of the flight-envelope grid, (M, P).

    The written ArduPilot parameters are held fixed and the *truth* is moved away from the
    estimate along each global parameter (central differences), so ``g_k^T Cov g_k`` is the
    variance of the heading error at attitude k caused by the estimation uncertainty.
    """
    from mavcal.autopilot.evaluate import attitude_grid, heading_errors_deg
    from mavcal.judging.quality import truth_functions

    am, cm = run.mapping.accel[0], run.mapping.compass[0]
    grid = attitude_grid(step_deg=30.0)
    incl = np.radians(cm.inclination_deg)
    B_ned = cm.field_mgauss * np.array([np.cos(incl), 0.0, np.sin(incl)])
    R_A = am.old.board_matrix
    theta = prob.pack(p)
    sd = np.sqrt(np.maximum(np.diag(run.calibration.param_cov), 1e-300)) if run.calibration.param_cov is not None \
        else np.maximum(np.abs(theta), 1.0) * 1e-4
    G = np.empty((len(grid), len(theta)))
    for j in range(len(theta)):
        errs = []
        for sgn in (1.0, -1.0):
            th = theta.copy()
            th[j] += sgn * 1e-3 * sd[j]
            q = prob.unpack(th, p.R)
            ra, rm = truth_functions(q.gains[0], q.biases[0], q.gains[1], q.biases[1],
                                      np.array([1.0, 0.0, q.h_z]), R_A, cm.old.mount_matrix, cm.field_mgauss)
            errs.append(heading_errors_deg(ra, rm, am.new, cm.new, B_ned, grid))
        G[:, j] = (errs[0] - errs[1]) / (2e-3 * sd[j])
    return G


def pose_scores(run: CalibrationRun, poses: Sequence[tuple[float, float, float]], n_samples: float,
                criterion: str = "heading") -> np.ndarray:
    """Score of adding a still interval at each pose (higher is better).

    ``"heading"``: minus the largest, over the flight envelope, predicted heading-error
    variance g_k^T (S + dS)^-1 g_k (a minimax heading-error criterion; the mean did worse in
    ``benchmarks/capture_guidance.py``); ``"d-optimal"``: log det of the information (S + dS)
    of the global parameters.
    """
    if criterion == "d-optimal":
        S_cur, dS, _, _ = pose_information(run, poses, n_samples)
        D = 1.0 / np.sqrt(np.maximum(np.diag(S_cur), 1e-300))
        sign, logdet = np.linalg.slogdet((S_cur[None] + dS) * D[None, :, None] * D[None, None, :])
        return np.where(sign > 0, logdet, -np.inf)
    return -heading_variances(run, poses, n_samples)[1]


def heading_variances(run: CalibrationRun, poses: Sequence[tuple[float, float, float]], n_samples: float
                      ) -> tuple[float, np.ndarray]:
    """The largest, over the flight envelope, predicted heading-error variance
    g_k^T S^-1 g_k of ``run``'s compass now, and (K,) with one more interval at each pose
    (S + dS): the heading criterion of :func:`pose_scores`."""
    S_cur, dS, prob, p = pose_information(run, poses, n_samples)
    D = 1.0 / np.sqrt(np.maximum(np.diag(S_cur), 1e-300))
    M = np.concatenate([S_cur[None], S_cur[None] + dS]) * D[None, :, None] * D[None, None, :]
    G = heading_gradients(run, prob, p) * D[None, :]  # in the scaled coordinates
    try:
        Minv = np.linalg.inv(M)
    except np.linalg.LinAlgError:
        Minv = np.linalg.pinv(M)
    var = np.einsum("kp,npq,kq->nk", G, Minv, G).max(axis=1)
    return float(var[0]), var[1:]
