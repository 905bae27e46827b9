"""The simulated experiment of the paper (Sec. VIII-A, Table I).

Per Monte Carlo run: fields g = [0, 0, g_z], g_z ~ U[-1.5, -0.5]; h = [h_x, 0, h_z],
h_x ~ U[0.5, 1.5], h_z ~ U[-1.5, 1.5]; biases b_{s,i} ~ U[-1, 1]; gains
K_s = I_3 + dK_s, dK_s ~ U[-0.1, 0.1] element-wise (Eq. ``experiment_gain``); covariances
Sigma_s = alpha_s S with S_ii ~ U[0.5, 2], S_ij ~ U[-0.2, 0.2] (symmetric) and
alpha_s = 10^e, e ~ U[-4, -2] (Eq. ``experiment_covariance``); the magnetometer is rotated by
a random R' and mirrored by M = diag(+-1) so K_m' = M R' K_m (det M = -1, a mirrored
magnetometer, in half the runs); rotations R_i uniformly
random (Kuffner 2004); Delta[i] ~ U{400, ..., 600} samples per interval, the same for both
sensors; readings v = K_s R_i s^I + b_s + eps, eps ~ N(0, Sigma_s).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import rq

from mavcal.core.gauge import canonical
from mavcal.core.rotations import exp_so3, random_rotations


@dataclass(frozen=True, eq=False)
class Sensors:
    """True parameters of one accelerometer + magnetometer pair and Earth's fields."""

    K_a: np.ndarray
    b_a: np.ndarray
    Sigma_a: np.ndarray
    K_m: np.ndarray
    b_m: np.ndarray
    Sigma_m: np.ndarray
    g: np.ndarray  # [0, 0, g_z]
    h: np.ndarray  # [h_x, 0, h_z]


@dataclass(frozen=True, eq=False)
class Truth:
    """Ground truth of one simulated data set (sensors + the intervals' orientations)."""

    sensors: Sensors
    orientations: np.ndarray  # (N, 3, 3)
    n_accel: np.ndarray  # (N,)
    n_mag: np.ndarray

    @property
    def mu_accel(self) -> np.ndarray:
        s = self.sensors
        return np.einsum("ij,njk,k->ni", s.K_a, self.orientations, s.g) + s.b_a

    @property
    def mu_mag(self) -> np.ndarray:
        s = self.sensors
        return np.einsum("ij,njk,k->ni", s.K_m, self.orientations, s.h) + s.b_m

    @property
    def noise_cov_accel(self) -> np.ndarray:
        return self.sensors.Sigma_a

    @property
    def noise_cov_mag(self) -> np.ndarray:
        return self.sensors.Sigma_m

    def in_paper_gauge(self):
        """The same truth expressed with g_z = -1, h_x = 1 and upper-triangular K_a.

        Returns (K_a, b_a, K_m, b_m, h_z, orientations) such that the mean readings are
        unchanged: K_a' = |g_z| K_a = U Q (RQ decomposition, U upper triangular with a
        positive diagonal), R_i' = Q R_i, K_m' = h_x K_m Q^T, h_z' = h_z / h_x, and then the
        canonical mirror twin (det K_m > 0, see :mod:`mavcal.core.gauge`).
        """
        s = self.sensors
        Ka = -s.g[2] * s.K_a
        U, Q = rq(Ka)
        D = np.diag(np.sign(np.diag(U)))
        U, Q = U @ D, D @ Q
        if np.linalg.det(Q) < 0:  # a mirrored accelerometer cannot be put in this gauge
            raise ValueError("accelerometer gain with negative determinant")
        Km = s.h[0] * s.K_m @ Q.T
        U, Km, h_z, R, _ = canonical(U, Km, float(s.h[2] / s.h[0]), Q @ self.orientations)
        return U, s.b_a.copy(), Km, s.b_m.copy(), h_z, R


@dataclass(frozen=True, eq=False)
class SimData:
    accel_sets: list[np.ndarray]
    mag_sets: list[np.ndarray]
    truth: Truth


def draw_sensors(rng: np.random.Generator, *, mirror: bool | None = None, gain_spread: float = 0.1,
                 dip_deg: float | None = None) -> Sensors:
    """Draw sensor parameters and fields as in Table I.

    Knobs for stress tests (the defaults draw exactly the paper's distribution, with the same
    random stream): ``mirror`` forces the sign matrix M to have det M = -1 (True, a mirrored
    magnetometer) or +1 (False) by flipping its last sign after the draw; ``gain_spread``
    replaces the 0.1 of dK_s ~ U[-0.1, 0.1]; ``dip_deg`` sets h_z = h_x tan(dip) (the paper's
    range is |dip| <= atan 3 = 71.6 deg).
    """
    def cov() -> np.ndarray:
        S = rng.uniform(-0.2, 0.2, (3, 3))
        S = np.triu(S, 1)
        S = S + S.T + np.diag(rng.uniform(0.5, 2.0, 3))
        return 10.0 ** rng.uniform(-4.0, -2.0) * S

    g = np.array([0.0, 0.0, rng.uniform(-1.5, -0.5)])
    h = np.array([rng.uniform(0.5, 1.5), 0.0, rng.uniform(-1.5, 1.5)])
    if dip_deg is not None:
        h[2] = h[0] * np.tan(np.radians(dip_deg))
    b_a = rng.uniform(-1, 1, 3)
    b_m = rng.uniform(-1, 1, 3)
    K_a = np.eye(3) + rng.uniform(-gain_spread, gain_spread, (3, 3))
    K_m = np.eye(3) + rng.uniform(-gain_spread, gain_spread, (3, 3))
    Rp = random_rotations(1, rng)[0]
    signs = rng.choice([-1.0, 1.0], 3)
    if mirror is not None and (np.prod(signs) < 0) != mirror:
        signs[2] = -signs[2]
    M = np.diag(signs)
    return Sensors(K_a=K_a, b_a=b_a, Sigma_a=cov(), K_m=M @ Rp @ K_m, b_m=b_m, Sigma_m=cov(), g=g, h=h)


def coplanar_rotations(n: int, rng: np.random.Generator, tilt_deg: float) -> np.ndarray:
    """Orientations that are nearly all rotations about one (random) axis.

    R_i = Q Rz(psi_i) exp(tilt) Q^T, psi_i ~ U[0, 2 pi), tilts ~ N(0, tilt_deg) about x and
    y: the hard case of poses that barely leave a plane.
    """
    psi = rng.uniform(0.0, 2 * np.pi, n)
    tilt = np.radians(tilt_deg) * rng.standard_normal((n, 2))
    w = np.zeros((n, 3))
    w[:, :2] = tilt
    c, s = np.cos(psi), np.sin(psi)
    Rz = np.zeros((n, 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1.0
    Q = random_rotations(1, rng)[0]
    return Q @ Rz @ exp_so3(w) @ Q.T


def draw_intervals(sensors: Sensors, n_intervals: int, rng: np.random.Generator,
                   samples: tuple[int, int] = (400, 600), orientations: np.ndarray | None = None) -> SimData:
    """Draw N intervals (orientations, counts, noisy readings) for given sensors.

    ``orientations`` (N, 3, 3) replaces the uniformly random ones (e.g. :func:`coplanar_rotations`).
    """
    R = random_rotations(n_intervals, rng) if orientations is None else np.asarray(orientations, dtype=float)
    n = rng.integers(samples[0], samples[1] + 1, n_intervals)
    La = np.linalg.cholesky(sensors.Sigma_a)
    Lm = np.linalg.cholesky(sensors.Sigma_m)
    acc, mag = [], []
    for i in range(n_intervals):
        mu_a = sensors.K_a @ R[i] @ sensors.g + sensors.b_a
        mu_m = sensors.K_m @ R[i] @ sensors.h + sensors.b_m
        acc.append(mu_a + rng.standard_normal((n[i], 3)) @ La.T)
        mag.append(mu_m + rng.standard_normal((n[i], 3)) @ Lm.T)
    truth = Truth(sensors=sensors, orientations=R, n_accel=n.astype(float), n_mag=n.astype(float))
    return SimData(acc, mag, truth)


def simulate(n_intervals: int = 15, seed: int | None = None, *, rng: np.random.Generator | None = None,
             samples: tuple[int, int] = (400, 600)) -> SimData:
    """One simulated data set of the paper's experiment (Table I)."""
    rng = np.random.default_rng(seed) if rng is None else rng
    return draw_intervals(draw_sensors(rng), n_intervals, rng, samples)
