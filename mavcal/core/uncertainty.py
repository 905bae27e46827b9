"""Parameter uncertainty: draws from the Gaussian approximation of the estimate.

``Calibration.param_cov`` is the Gauss-Newton inverse Fisher information of the global
parameters (orientations marginalised), inflated per sensor by its misfit only when J' rejects
the noise model at p <= 1 % (:func:`mavcal.core.misfit.inflated_covariance`). Drawing
parameter sets from N(theta_hat, param_cov) and pushing them through any derived quantity
(ArduPilot parameters, heading and tilt errors over a grid of attitudes) gives that quantity's confidence interval.

Also the Wald tests :mod:`mavcal.core.calibrate`'s model selection runs on the full fit
(:func:`wald`, ``REDUCTIONS``) and the covariance after a discrete gauge change
(:func:`transform_cov`).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from mavcal.core.refine import JointParams, RefineResult
from mavcal.core.stats import chi2_sf
from mavcal.core.types import Calibration


def parameter_vector(cal: Calibration) -> np.ndarray:
    """The global parameters of ``cal`` in the order of ``cal.param_names``."""
    return np.array([param_value(cal.accel.gain, cal.accel.bias, cal.mag.gain, cal.mag.bias, cal.h_z, name)
                     for name in cal.param_names])


def param_value(Ka, ba, Km, bm, hz, name: str) -> float:
    """The value of the global parameter ``name`` ("K_a[12]", "b_m[y]", "h_z", ...)."""
    if name == "h_z":
        return hz
    sym, lab = name.split("[")
    lab = lab.rstrip("]")
    if sym == "K_a":
        return Ka[int(lab[0]) - 1, int(lab[1]) - 1] if lab != "s" else Ka[0, 0]
    if sym == "K_m":
        return Km[int(lab[0]) - 1, int(lab[1]) - 1] if lab != "s" else Km[0, 0]
    if sym == "b_a":
        return ba["xyz".index(lab)]
    if sym == "b_m":
        return bm["xyz".index(lab)]
    raise KeyError(name)


def _set(d: dict[str, np.ndarray], name: str, values: np.ndarray, forms: dict[str, str]) -> None:
    """Set the global parameter ``name`` of n stacked parameter sets (``d["K_a"]`` (n, 3, 3),
    ``d["b_a"]`` (n, 3), ...) to ``values`` (n,)."""
    if name == "h_z":
        d["h"][:, 2] = values
        return
    sym, lab = name.split("[")
    lab = lab.rstrip("]")
    if sym in ("K_a", "K_m"):
        K = d[sym]
        if lab == "s":
            K[:] = values[:, None, None] * np.eye(3)
            return
        r, c = int(lab[0]) - 1, int(lab[1]) - 1
        K[:, r, c] = values
        if forms[sym] == "sym":
            K[:, c, r] = values
    else:
        d[sym][:, "xyz".index(lab)] = values


def _forms(cal: Calibration) -> dict[str, str]:
    from mavcal.core.models import MODELS

    spec = MODELS.get(cal.model, MODELS["full"])
    return {"K_a": spec.accel_form, "K_m": spec.mag_form}


def sample_parameters(cal: Calibration, n: int, rng: np.random.Generator | None = None) -> list[dict]:
    """``n`` draws of (K_a, b_a, K_m, b_m, h) from N(theta_hat, param_cov).

    Entries not among the estimated parameters (e.g. the zero off-diagonals of a diagonal
    K_a) keep their fitted values. Without a covariance every draw equals the estimate.
    """
    rng = np.random.default_rng() if rng is None else rng
    base = {"K_a": np.array(cal.accel.gain), "b_a": np.array(cal.accel.bias), "K_m": np.array(cal.mag.gain),
            "b_m": np.array(cal.mag.bias), "h": np.array(cal.field)}
    if cal.param_cov is None or not cal.param_names:
        return [{k: v.copy() for k, v in base.items()} for _ in range(n)]
    theta = parameter_vector(cal)
    C = np.asarray(cal.param_cov)
    w, V = np.linalg.eigh(0.5 * (C + C.T))
    L = V * np.sqrt(np.maximum(w, 0.0))
    draws = theta + rng.standard_normal((n, len(theta))) @ L.T
    forms = _forms(cal)
    stacked = {k: np.repeat(v[None], n, axis=0) for k, v in base.items()}  # every draw at once
    for col, name in enumerate(cal.param_names):
        _set(stacked, name, draws[:, col], forms)
    return [{k: v[i] for k, v in stacked.items()} for i in range(n)]


def parameter_std(cal: Calibration) -> dict[str, float]:
    """1-sigma uncertainty of each global parameter, by name."""
    if cal.param_cov is None:
        return {}
    return {n: float(np.sqrt(max(v, 0.0))) for n, v in zip(cal.param_names, np.diag(cal.param_cov))}


# --- Wald tests of the model reductions and the covariance under a gauge change (calibrate) ---

def wald(res: RefineResult, constraints: Sequence[dict], scale: float) -> tuple[float, int, float]:
    """Wald statistic of linear constraints sum_k c_k theta_k = 0 on the global parameters."""
    if res.cov is None:
        return np.inf, len(constraints), 0.0
    idx = {n: i for i, n in enumerate(res.names)}
    C = np.zeros((len(constraints), len(res.names)))
    for r, con in enumerate(constraints):
        for name, coef in con.items():
            C[r, idx[name]] = coef
    prob_theta = np.concatenate([np.ravel(x) for x in theta_by_names(res)])
    v = C @ prob_theta
    V = C @ (res.cov * scale) @ C.T
    try:
        W = float(v @ np.linalg.solve(V, v))
    except np.linalg.LinAlgError:
        return np.inf, len(constraints), 0.0
    return W, len(constraints), chi2_sf(W, len(constraints))


def theta_by_names(res: RefineResult):
    """Global parameter vector in ``res.names`` order (recomputed from the structured params)."""
    p = res.params
    return [np.array([param_value(p.gains[0], p.biases[0], p.gains[1], p.biases[1], p.h_z, n) for n in res.names])]


# constraints that turn each model of MODEL_CHAIN into the next (on the *full* parameterisation)
REDUCTIONS = {
    "diag-accel": [{"K_a[12]": 1}, {"K_a[13]": 1}, {"K_a[23]": 1}],
    "ardupilot": [{"K_m[12]": 1, "K_m[21]": -1}, {"K_m[13]": 1, "K_m[31]": -1}, {"K_m[23]": 1, "K_m[32]": -1}],
    "offsets-scales": [{"K_m[12]": 1}, {"K_m[13]": 1}, {"K_m[23]": 1}],
}


def transform_cov(res: RefineResult, p: JointParams, K_a, K_m, h_z) -> np.ndarray | None:
    """Covariance after a discrete gauge change: every parameter maps to +-1 times itself."""
    if res.cov is None:
        return None
    old = theta_by_names(res)[0]
    new_res = replace(res, params=JointParams((K_a, K_m), p.biases, h_z, p.R))
    new = theta_by_names(new_res)[0]
    sign = np.where(np.isclose(new, -old) & (old != 0), -1.0, 1.0)
    return res.cov * np.outer(sign, sign)
