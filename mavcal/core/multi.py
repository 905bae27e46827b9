"""Several accelerometers and magnetometers observed in the same still intervals, in one fit.

All sensors share the orientations R_i; accelerometers share g = [0, 0, -1] and
magnetometers h = [1, 0, h_z]. The reference accelerometer (index 0) keeps the
upper-triangular gain that fixes the frame; every other sensor gets a full gain (which
holds its misalignment to the reference). The fit starts from the paper's algorithm on the
reference pair (accelerometer 0, magnetometer 0), gives every other sensor its linear
least-squares gain and bias for those orientations, and then refines everything jointly
(:mod:`mavcal.core.refine`), so every sensor contributes to the orientations.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mavcal.core.calibrate import calibrate
from mavcal.core.initial import G_UNIT
from mavcal.core.models import FORMS
from mavcal.core.refine import JointParams, JointProblem, Term, refit_covariances
from mavcal.core.stats import interval_stats
from mavcal.core.types import SensorModel, frozen_array
from mavcal.errors import EstimationError


@dataclass(frozen=True, eq=False)
class MultiCalibration:
    """Result of :func:`calibrate_multi`: one SensorModel per sensor, shared orientations."""

    accels: tuple[SensorModel, ...]
    mags: tuple[SensorModel, ...]
    gravity: np.ndarray
    field: np.ndarray
    orientations: np.ndarray
    cost: float
    iterations: int
    converged: bool
    message: str
    param_names: tuple[str, ...] = ()
    param_cov: np.ndarray | None = None
    dof: int = 0

    def __post_init__(self) -> None:
        for n in ("gravity", "field", "orientations", "param_cov"):
            object.__setattr__(self, n, frozen_array(getattr(self, n)))

    @property
    def h_z(self) -> float:
        return float(self.field[2])


def _linear_gain(mu: np.ndarray, n: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least squares mu_i = K v_i + b (weights n_i) for a full K and b."""
    X = np.concatenate([v, np.ones((len(v), 1))], axis=1)  # (N, 4)
    W = n[:, None]
    A = X.T @ (X * W)
    B = X.T @ (mu * W)
    sol = np.linalg.solve(A, B)  # (4, 3): rows K^T, b
    return sol[:3].T, sol[3]


def calibrate_multi(accel_sensors: Sequence, mag_sensors: Sequence, *, method: str = "ncar", tol: float = 1e-4,
                    seed: int | None = None, noise_floor=None) -> MultiCalibration:
    """Calibrate A accelerometers and M magnetometers that share the same still intervals.

    Parameters
    ----------
    accel_sensors : sequence of A >= 1 items, each a sequence of N arrays (n_i, 3)
    mag_sensors : sequence of M >= 1 items, each a sequence of N arrays (n_i, 3)
    method, tol, seed, noise_floor : as for :func:`mavcal.calibrate` (reference pair)

    Returns
    -------
    MultiCalibration with ``accels[k]`` / ``mags[k]`` in input order; accels[0].gain is
    upper triangular, all others full; mean reading of sensor s in interval i is
    gain_s @ orientations[i] @ (gravity or field) + bias_s.
    """
    accel_sensors, mag_sensors = list(accel_sensors), list(mag_sensors)
    if not accel_sensors or not mag_sensors:
        raise EstimationError("calibrate_multi needs at least one accelerometer and one magnetometer")
    ref = calibrate(accel_sensors[0], mag_sensors[0], method=method, tol=tol, seed=seed, model="full",
                    noise_floor=noise_floor)
    N = ref.n_intervals
    stats = []
    for kind, sensors in (("accel", accel_sensors), ("mag", mag_sensors)):
        for k, sets in enumerate(sensors):
            st = interval_stats(sets, f"{kind}_sensors[{k}]", noise_floor=noise_floor)
            if st.mu.shape[0] != N:
                raise EstimationError(f"{kind}_sensors[{k}] has {st.mu.shape[0]} intervals, the reference has {N}")
            stats.append((kind, k, st))
    R = np.asarray(ref.orientations)
    terms, gains, biases, scatters = [], [], [], []
    for kind, k, st in stats:
        f = G_UNIT if kind == "accel" else np.asarray(ref.field)
        if kind == "accel" and k == 0:
            K, b, form, Sigma = ref.accel.gain, ref.accel.bias, FORMS["upper"], ref.accel.noise_cov
        elif kind == "mag" and k == 0:
            K, b, form, Sigma = ref.mag.gain, ref.mag.bias, FORMS["full"], ref.mag.noise_cov
        else:
            K, b = _linear_gain(st.mu, st.n, R @ f)
            form, Sigma = FORMS["full"], st.sigma_hat
        terms.append(Term(kind, form, st.mu, st.n, Sigma, name=str(k)))
        gains.append(np.asarray(K))
        biases.append(np.asarray(b))
        scatters.append(st.scatter)
    p = JointParams(tuple(gains), tuple(biases), ref.h_z, R)
    iters = ref.iterations
    refit = method in ("fcar", "dcar")
    for _ in range(30 if refit else 1):
        prob = JointProblem(terms)
        res = prob.solve(p)
        iters += res.iterations
        p = res.params
        if not refit:
            break
        covs = refit_covariances(prob, p, scatters, diagonal=(method == "dcar"))
        change = max(np.max(np.abs(c - t.Sigma)) / np.max(np.abs(t.Sigma)) for c, t in zip(covs, terms))
        terms = [Term(t.kind, t.form, t.mu, t.n, c, t.name) for t, c in zip(terms, covs)]
        if change < 1e-6:
            prob = JointProblem(terms)
            res = prob.solve(p)
            p = res.params
            break
    scale = max(1.0, res.cost / res.dof) if res.dof > 0 else 1.0
    accels = tuple(SensorModel(K, b, t.Sigma, "accel") for t, K, b in zip(terms, p.gains, p.biases)
                   if t.kind == "accel")
    mags = tuple(SensorModel(K, b, t.Sigma, "mag") for t, K, b in zip(terms, p.gains, p.biases) if t.kind == "mag")
    msg = (f"{len(accels)} accelerometer(s) and {len(mags)} magnetometer(s) over {N} intervals: "
           f"J'={res.cost:.6g}, {res.dof} degrees of freedom")
    return MultiCalibration(accels=accels, mags=mags, gravity=G_UNIT.copy(), field=np.array([1.0, 0.0, p.h_z]),
                            orientations=p.R, cost=float(res.cost), iterations=int(iters),
                            converged=bool(res.converged and ref.converged), message=msg,
                            param_names=res.names, param_cov=None if res.cov is None else res.cov * scale,
                            dof=int(res.dof))
