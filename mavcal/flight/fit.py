"""The in-flight fit of one compass: offsets and motor interference against a reference the
compass cannot bend.

The firmware's model in the neutral form of :mod:`mavcal.autopilot.flight` (ArduPilot's
``correct_field``: ``A = M(DIA, ODI) · SCALE``; PX4's ``Correct``: ``A = R S``, the motor term
``A · COMP``), with ``A`` kept as in force::

    mag_i = A (b_i + o) + m x(t_i - tau)                      (1)

must equal the Earth field seen in the body frame, ``R_i^T B`` (``R_i``: body to NED). With
``y_i = A b_i`` (the raw field ``b_i`` recovered from the log) the residual

    e_i = y_i - (R_i^T B - A o - m x_i)                        (2)

is linear in ``theta = (B, o, m)``: solved first, for a starting point, the outliers (beyond
5 sigma) and the field's declination. But ``R_i``'s yaw is the EKF's, which the compasses
themselves bend, by the very interference fitted (a yaw that follows the current biases ``m``).
So the estimate is the fit of what no yaw enters: with ``T_i`` the roll and pitch of ``R_i``
alone and ``c_i = A (b_i + o) + m x_i`` (1),

    r_i = ( (T_i c_i)_D - B_D ,  |(T_i c_i)_NE| - H )          (3)

the field's down component and horizontal length, against ``B_D`` and ``H``. Maximum
likelihood under white Gaussian noise of one standard deviation ``sigma`` per component is
least squares (Gauss-Newton on (3), the normal equations); ``B_D`` and ``H`` have a prior at
the World Magnetic Model's field (``sigma_B``, 3 % of the field: the table's accuracy), which
keeps the down component apart from the z offset in a level flight. ``tau`` (the delay between
the current and the field) is chosen on a grid (+-0.5 s, 0.05 s steps) by the smallest
residual. The covariance is ``sigma^2 (J^T J)^-1`` inflated by the residuals' correlation in
time (AR(1): ``(1+rho)/(1-rho)``), the 95 % bounds ``1.96`` standard deviations. A term the
flight does not identify (the driver ``x`` barely varied; under 200 deg of headings for the
offsets) is kept at its value in force and not fitted.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FitInput", "CompassFit", "fit_compass", "DELAY_GRID_S", "Z95"]

Z95 = 1.959963984540054
DELAY_GRID_S = np.round(np.arange(-0.5, 0.5001, 0.05), 3)
MIN_DRIVER_SPAN = {"current": 8.0, "throttle": 0.15}  # A / throttle fraction: less is not identified
MIN_HEADING_SPAN_DEG = 200.0


@dataclass(frozen=True)
class FitInput:
    """One compass's series on the compass's own time base.

    ``raw_mgauss`` (n, 3): ``b_i``; ``A`` (3, 3); ``R`` (n, 3, 3) body to NED; ``driver_time_s``,
    ``driver``: the current (A) or throttle (0..1) series; ``B0_ned_mgauss``: the field model's.
    """

    time_s: np.ndarray
    raw_mgauss: np.ndarray
    A: np.ndarray
    R: np.ndarray
    driver_time_s: np.ndarray
    driver: np.ndarray
    driver_kind: str  # "current" or "throttle"
    B0_ned_mgauss: np.ndarray
    ofs_in_force_mgauss: np.ndarray
    mot_in_force: np.ndarray
    sigma_B_mgauss: float = 15.0


@dataclass(frozen=True)
class CompassFit:
    """The result of :func:`fit_compass` (mGauss; ``mot`` per A or per full throttle)."""

    ofs_mgauss: np.ndarray
    ofs_bound95_mgauss: np.ndarray
    mot_per_unit: np.ndarray
    mot_bound95_per_unit: np.ndarray
    B_ned_mgauss: np.ndarray
    B_bound95_mgauss: np.ndarray
    delay_s: float
    sigma_mgauss: float
    inflation: float
    fitted_ofs: bool
    fitted_mot: bool
    driver_span: float
    driver_max: float
    heading_span_deg: float
    rms_before_mgauss: float
    rms_after_mgauss: float
    heading_err_before_deg: float
    heading_err_after_deg: float
    n_samples: int
    residual_mgauss: np.ndarray  # (n, 3) after the fit: corrected field - reference
    reference_mgauss: np.ndarray  # (n, 3) the reference R_i^T B of the samples used


def heading_span_deg(R: np.ndarray) -> float:
    """How much of the circle the nose covered: 360 minus the largest gap between headings."""
    yaw = np.sort(np.degrees(np.arctan2(R[:, 1, 0], R[:, 0, 0])) % 360.0)
    if len(yaw) < 2:
        return 0.0
    gaps = np.diff(np.concatenate([yaw, [yaw[0] + 360.0]]))
    return float(360.0 - gaps.max())


def _ar1(e: np.ndarray) -> float:
    """Variance inflation of a mean-like estimate under AR(1) residuals, the largest over axes (>= 1)."""
    f = 1.0
    for k in range(e.shape[1]):
        r = e[:, k] - e[:, k].mean()
        d = float(r @ r)
        if d <= 0 or len(r) < 3:
            continue
        rho = float(np.clip((r[1:] @ r[:-1]) / d, 0.0, 0.95))
        f = max(f, (1 + rho) / (1 - rho))
    return f


def _rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(e * e, axis=1))))


def _heading_err_deg(R: np.ndarray, mag_body: np.ndarray, B: np.ndarray) -> float:
    """RMS of the heading the compass gives (its field in NED by the reference attitude) minus the field's."""
    h = np.einsum("nij,nj->ni", R, mag_body)
    d = np.arctan2(h[:, 1], h[:, 0]) - np.arctan2(B[1], B[0])
    d = (d + np.pi) % (2 * np.pi) - np.pi
    return float(np.degrees(np.sqrt(np.mean(d * d)))) if len(d) else float("nan")


def _solve(inp: FitInput, x: np.ndarray, fit_ofs: bool, fit_mot: bool, keep: np.ndarray):
    """Least squares of (2) on the samples ``keep``; returns theta (9,), J^T J (with prior), residuals (n, 3)."""
    n = int(keep.sum())
    R, y, A = inp.R[keep], inp.A @ inp.raw_mgauss[keep].T, inp.A
    y = y.T  # (n, 3)
    xs = x[keep]
    cols = [np.transpose(R, (0, 2, 1))]  # d(model)/dB: R^T
    fixed = np.zeros((n, 3))
    if fit_ofs:
        cols.append(np.broadcast_to(-A, (n, 3, 3)))
    else:
        fixed += (A @ inp.ofs_in_force_mgauss)[None, :]
    if fit_mot:
        cols.append(-xs[:, None, None] * np.eye(3)[None])
    else:
        fixed += xs[:, None] * inp.mot_in_force[None, :]
    J = np.concatenate(cols, axis=2).reshape(3 * n, -1)  # model: y = J theta - fixed
    rhs = (y + fixed).reshape(3 * n)
    p = J.shape[1]
    return J, rhs, p


def _solve_normal(JtJ: np.ndarray, g: np.ndarray) -> np.ndarray:
    """``JtJ^-1 g`` by the normal equations, columns equilibrated (a few parameters, thousands of rows)."""
    d = np.sqrt(np.clip(np.diag(JtJ), 1e-300, None))
    return np.linalg.lstsq(JtJ / np.outer(d, d), g / d, rcond=None)[0] / d


def _lsq(J: np.ndarray, rhs: np.ndarray, B0: np.ndarray, w_prior: float):
    """Least squares with the prior rows ``w_prior (B - B0)`` (in units of the noise)."""
    p = J.shape[1]
    P = np.zeros((3, p))
    P[:, :3] = np.eye(3) * w_prior
    JtJ = J.T @ J + P.T @ P
    theta = _solve_normal(JtJ, J.T @ rhs + P.T @ (w_prior * B0))
    return theta, JtJ


def _tilt_only(R: np.ndarray) -> np.ndarray:
    """``Rz(-yaw) R``: the rotations with their yaw removed (roll and pitch only)."""
    psi = np.arctan2(R[:, 1, 0], R[:, 0, 0])
    c, s = np.cos(psi), np.sin(psi)
    Rz = np.zeros_like(R)
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, s, -s, c, 1.0
    return np.einsum("nij,njk->nik", Rz, R)


def _yaw_free(inp: FitInput, T: np.ndarray, x: np.ndarray, keep: np.ndarray, o: np.ndarray, m: np.ndarray,
              fit_ofs: bool, fit_mot: bool, sigma: float, iters: int = 8):
    """Gauss-Newton on the yaw-free residuals (3): the field's down component and its horizontal
    length, against ``B_D`` and ``H`` (priors at the field model's). Returns o, m, (H, B_D), J^T J, residuals."""
    B0 = inp.B0_ned_mgauss
    H0, D0 = float(np.hypot(B0[0], B0[1])), float(B0[2])
    Tk, b, xs, A = T[keep], inp.raw_mgauss[keep], x[keep], inp.A
    H, D = H0, D0
    w = sigma / inp.sigma_B_mgauss
    JtJ = np.eye(2)
    r = np.zeros((len(xs), 2))
    for _ in range(iters):
        c = (A @ (b + o).T).T + xs[:, None] * m
        wv = np.einsum("nij,nj->ni", Tk, c)
        h = np.maximum(np.hypot(wv[:, 0], wv[:, 1]), 1e-6)
        r = np.column_stack([wv[:, 2] - D, h - H])
        u = (wv[:, 0, None] * Tk[:, 0, :] + wv[:, 1, None] * Tk[:, 1, :]) / h[:, None]  # d|h|/dc
        g = np.stack([Tk[:, 2, :], u], axis=1)  # (n, 2, 3): d r / d c
        cols = [np.stack([np.zeros(len(xs)), -np.ones(len(xs))], axis=1)[:, :, None],  # dH
                np.stack([-np.ones(len(xs)), np.zeros(len(xs))], axis=1)[:, :, None]]  # dD
        if fit_ofs:
            cols.append(g @ A)
        if fit_mot:
            cols.append(g * xs[:, None, None])
        J = np.concatenate(cols, axis=2).reshape(2 * len(xs), -1)
        p = J.shape[1]
        P = np.zeros((2, p))
        P[0, 0] = P[1, 1] = w
        JtJ = J.T @ J + P.T @ P
        step = _solve_normal(JtJ, -(J.T @ r.reshape(-1) + P.T @ np.array([w * (H - H0), w * (D - D0)])))
        H, D = H + step[0], D + step[1]
        k = 2
        if fit_ofs:
            o = o + step[k:k + 3]
            k += 3
        if fit_mot:
            m = m + step[k:k + 3]
        if np.abs(step).max() < 1e-4:
            break
    return o, m, (H, D), JtJ, r


def _linear_start(inp: FitInput, driver_at, grid: np.ndarray, fit_ofs: bool, fit_mot: bool):
    """(2) on the delay grid, dropping outliers (> 5 sigma) twice at most: the starting point, the
    samples kept and the noise. Returns ((rss, tau, theta, J^T J, residuals, x), keep, sigma)."""
    n = len(inp.time_s)
    keep = np.ones(n, dtype=bool)
    sigma = 5.0
    lin = None
    for _ in range(3):
        lin = None
        for tau in grid:
            x = driver_at(float(tau))
            J, rhs, _ = _solve(inp, x, fit_ofs, fit_mot, keep)
            theta, JtJ = _lsq(J, rhs, inp.B0_ned_mgauss, sigma / inp.sigma_B_mgauss)
            e = (rhs - J @ theta).reshape(-1, 3)
            rss = float((e * e).sum())
            if lin is None or rss < lin[0]:
                lin = (rss, float(tau), theta, JtJ, e, x)
        assert lin is not None
        rss, tau, theta, JtJ, e, x = lin
        sigma = float(np.sqrt(rss / max(1, e.size - len(theta))))
        Jall, rhs_all, _ = _solve(inp, x, fit_ofs, fit_mot, np.ones(n, dtype=bool))
        eall = (rhs_all - Jall @ theta).reshape(-1, 3)
        new_keep = np.abs(eall).max(axis=1) < max(5 * sigma, 3.0)
        if new_keep.sum() < 30 or (new_keep == keep).all():
            keep = keep if new_keep.sum() < 30 else new_keep
            break
        keep = new_keep
    assert lin is not None
    return lin, keep, sigma


def fit_compass(inp: FitInput, *, fit_ofs: bool | None = None, fit_mot: bool | None = None,
                method: str = "yaw-free") -> CompassFit:
    """Fit (1) to one compass's flight (see the module's notes); ``fit_ofs`` / ``fit_mot`` None: as
    identified; ``method``: ``yaw-free`` (3, the default) or ``heading`` (2, trusting the yaw)."""
    t = inp.time_s
    n = len(t)
    if n < 30:
        raise ValueError("too few compass samples in flight")
    span = float(np.ptp(inp.driver)) if len(inp.driver) else 0.0
    dmax = float(np.max(inp.driver)) if len(inp.driver) else 0.0
    hspan = heading_span_deg(inp.R)
    if fit_mot is None:
        fit_mot = len(inp.driver) > 1 and span >= MIN_DRIVER_SPAN[inp.driver_kind]
    if fit_ofs is None:
        fit_ofs = hspan >= MIN_HEADING_SPAN_DEG

    def driver_at(tau: float) -> np.ndarray:
        if len(inp.driver) == 0:
            return np.zeros(n)
        return np.interp(t - tau, inp.driver_time_s, inp.driver)

    grid = DELAY_GRID_S if fit_mot else np.array([0.0])
    lin, keep, sigma = _linear_start(inp, driver_at, grid, fit_ofs, fit_mot)
    rss, tau, theta, JtJ, e, x = lin
    k = 3
    o0 = theta[k:k + 3] if fit_ofs else np.asarray(inp.ofs_in_force_mgauss, float)
    k += 3 if fit_ofs else 0
    m0 = theta[k:k + 3] if fit_mot else np.asarray(inp.mot_in_force, float)
    B_lin = theta[:3]
    if method == "heading":
        infl = _ar1(e)
        cov = sigma ** 2 * np.linalg.pinv(JtJ) * infl
        sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        B, B_b, ofs, mot = B_lin, Z95 * sd[:3], o0, m0
        so = Z95 * sd[3:6] if fit_ofs else np.zeros(3)
        sm = Z95 * sd[(6 if fit_ofs else 3):][:3] if fit_mot else np.zeros(3)
    else:
        T = _tilt_only(inp.R)
        best = None
        for tau_g in grid:
            xg = driver_at(float(tau_g))
            o, m, (H, D), JtJ2, r = _yaw_free(inp, T, xg, keep, o0, m0, fit_ofs, fit_mot, sigma)
            rss2 = float((r * r).sum())
            if best is None or rss2 < best[0]:
                best = (rss2, float(tau_g), o, m, H, D, JtJ2, r, xg)
        assert best is not None
        rss2, tau, ofs, mot, H, D, JtJ2, r, x = best
        sig2 = float(np.sqrt(rss2 / max(1, r.size - JtJ2.shape[0])))
        infl = _ar1(r)
        cov = sig2 ** 2 * np.linalg.pinv(JtJ2) * infl
        sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        dec = float(np.arctan2(B_lin[1], B_lin[0]))
        B = np.array([H * np.cos(dec), H * np.sin(dec), D])
        B_b = Z95 * np.array([sd[0], sd[0], sd[1]])
        so = Z95 * sd[2:5] if fit_ofs else np.zeros(3)
        sm = Z95 * sd[(5 if fit_ofs else 2):][:3] if fit_mot else np.zeros(3)
        sigma = sig2
    # before: the calibration in force (offsets and compensation as logged) against the same reference
    Rk = inp.R[keep]
    ref = np.einsum("nji,j->ni", Rk, B)
    before = (inp.A @ (inp.raw_mgauss[keep] + inp.ofs_in_force_mgauss).T).T + x[keep, None] * inp.mot_in_force
    after = (inp.A @ (inp.raw_mgauss[keep] + ofs).T).T + x[keep, None] * mot
    rb = before - ref
    ra = after - ref
    return CompassFit(np.asarray(ofs), so, np.asarray(mot), sm, B, B_b, tau, sigma, infl,
                      bool(fit_ofs), bool(fit_mot), span, dmax, hspan,
                      _rms(rb), _rms(ra),
                      _heading_err_deg(Rk, before, B), _heading_err_deg(Rk, after, B), int(keep.sum()), ra, ref)
