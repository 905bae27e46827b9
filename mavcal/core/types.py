"""Result types of the estimator. Frozen, built in one step, arrays read-only.

Model (paper Eq. ``sensor_reading_model``): the mean reading of still interval i is

    mu_a[i] = K_a R_i g + b_a,     g = [0, 0, -1]
    mu_m[i] = K_m R_i h + b_m,     h = [1, 0, h_z]

in the units of the input readings (m/s^2, mGauss, ...). The gravity and field are
normalised (g_z = -1, h_x = 1), so the gains carry the field magnitudes. ``K_a`` is upper
triangular (it fixes the frame in which the orientations R_i are expressed); ``K_m`` is a
full matrix that contains the accelerometer-to-magnetometer rotation (and a mirroring
when det K_m < 0).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def frozen_array(a: np.ndarray | None) -> np.ndarray | None:
    """A read-only float copy of ``a`` (None stays None): what frozen results hold."""
    if a is None:
        return None
    a = np.array(a, dtype=float, copy=True)
    a.setflags(write=False)
    return a


def _arr_eq(a, b) -> bool:
    if a is None or b is None:
        return a is b
    return np.array_equal(a, b)


@dataclass(frozen=True, eq=False)
class SensorModel:
    """Affine model of one sensor: reading = gain @ nominal + bias + noise.

    Attributes
    ----------
    gain : (3, 3) array
        K_s. For the reference accelerometer upper triangular.
    bias : (3,) array
        b_s, in the units of the readings.
    noise_cov : (3, 3) array
        Sigma_s, covariance of one reading.
    kind : "accel" or "mag"
    """

    gain: np.ndarray
    bias: np.ndarray
    noise_cov: np.ndarray
    kind: str = "accel"

    def __post_init__(self) -> None:
        object.__setattr__(self, "gain", frozen_array(self.gain))
        object.__setattr__(self, "bias", frozen_array(self.bias))
        object.__setattr__(self, "noise_cov", frozen_array(self.noise_cov))

    def nominal(self, readings: np.ndarray) -> np.ndarray:
        """Invert the model: K^-1 (v - b) for readings of shape (..., 3)."""
        v = np.asarray(readings, dtype=float) - self.bias
        return np.linalg.solve(self.gain, v.reshape(-1, 3).T).T.reshape(v.shape)

    def predict(self, nominal: np.ndarray) -> np.ndarray:
        """Forward model without noise: K v* + b for nominal values (..., 3)."""
        return np.asarray(nominal, dtype=float) @ self.gain.T + self.bias

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, SensorModel):
            return NotImplemented
        return (self.kind == other.kind and _arr_eq(self.gain, other.gain)
                and _arr_eq(self.bias, other.bias) and _arr_eq(self.noise_cov, other.noise_cov))

    __hash__ = None  # type: ignore[assignment]


@dataclass(frozen=True)
class OptimumCertificate:
    """Evidence that a calibration is the global optimum of J' (see :mod:`mavcal.core.certify`).

    Attributes
    ----------
    starts : int
        Fits run from distinct deterministic starts (1 = the default start alone, used when
        it converged with enough degrees of freedom and a chi2 the noise explains).
    start_costs : tuple of float
        The cost named ``start_cost_name`` reached from each start, the basin of the returned
        point first. A search compares its starts before any reweighting, at the sample
        covariances; when the returned point minimises a reweighted cost (``cost_name``
        differs) it is that first basin followed to the reweighted optimum, so
        ``start_costs[0]`` is not its cost (that is ``cost``).
    grad_decrement : float
        Gauss-Newton decrement g^T (J^T J)^-1 g at the returned point (0 at a stationary point).
    min_hessian_eig : float
        Smallest eigenvalue of the exact Hessian of the profile cost (orientations minimised
        out) relative to its Gauss-Newton approximation: ~1 at a small-residual minimum, <= 0
        at a saddle.
    local_ok : bool
        Stationary and the exact Hessian (gauge-fixed coordinates) is positive definite.
    global_ok : bool
        The returned point is the best of the starts and the search is trusted (see ``reason``).
    reason : str
        Empty when certified; otherwise why not, in words.
    cost : float
        The cost at the returned point, which the local evidence is for (= ``Calibration.cost``).
    cost_name : str
        Which cost the returned point minimises: "J' with the sample covariances" (the
        paper's Eq. ``partial_cost`` with Sigma_hat, the ML optimum), or e.g. "J' with
        Sigma_m inflated x 12.5 (reweighted)" when the data rejected the noise model
        (:func:`mavcal.core.calibrate._reweight`), or a FCAR/DCAR covariance refit.
    start_cost_name : str
        Which cost ``start_costs`` are of.
    """

    starts: int
    start_costs: tuple[float, ...]
    grad_decrement: float
    min_hessian_eig: float
    local_ok: bool
    global_ok: bool
    reason: str = ""
    cost: float = float("nan")
    cost_name: str = "J' with the sample covariances"
    start_cost_name: str = "J' with the sample covariances"

    @property
    def certified(self) -> bool:
        return self.local_ok and self.global_ok


@dataclass(frozen=True, eq=False)
class Calibration:
    """Result of :func:`mavcal.calibrate`.

    Attributes
    ----------
    accel, mag : SensorModel
    gravity : (3,) array, always [0, 0, -1]
    field : (3,) array, [1, 0, h_z]
    orientations : (N, 3, 3) array
        R_i such that mean accel reading = accel.gain @ R_i @ gravity + accel.bias.
    cost : float
        J' (paper Eq. ``partial_cost``) at the returned parameters, with the noise
        covariances in ``noise_cov``: the sample covariances, unless the data rejected that
        noise model and the fit was reweighted (``noise_inflation``, ``cost_name``).
    iterations : int
        Block-coordinate iterations of the paper's algorithm (Sec. VII) plus joint
        refinement iterations.
    converged : bool
        The iterations reached their tolerances *and* the result is certified as the global
        optimum (``certificate``); ``message`` says why when not.
    message : str
    method : str
        "ncdr", "ncar", "fcar" or "dcar".
    model : str
        The model actually fitted (see :mod:`mavcal.core.models`), e.g. "full".
    model_reason : str
        Why that model was chosen, in words.
    param_names : tuple of str
        Names of the global parameters, in the order of ``param_cov``.
    param_cov : (P, P) array or None
        Covariance of the global parameters (orientations marginalised), from the
        Gauss-Newton approximation of the Fisher information at the optimum.
    n_accel, n_mag : (N,) int arrays
        Delta_a[i], Delta_m[i]: samples per interval.
    block_iterations, refine_iterations : int
    dof : int
        Degrees of freedom of J' (3N - global parameters); J'/dof ~ 1 for a good fit.
    certificate : OptimumCertificate or None
        Evidence that the result is the global optimum (None on the paper's path,
        ``refine=False``); ``converged`` is False when it is not certified.
    noise_inflation : (float, float)
        trace(Sigma_s) / trace(Sigma_hat_s) per sensor (accel, mag): how much the misfit
        reweighting inflated each sensor's sample noise covariance (1.0 where the noise
        model fitted and nothing was inflated). A warm-started refit
        (``calibrate(..., start=this)``) begins at these weights.
    cost_name : str
        Which cost ``cost`` is and the returned point minimises: "J' with the sample
        covariances" (the ML optimum of the paper), or the reweighted cost, e.g. "J' with
        Sigma_m inflated x 12.5 (reweighted)"; ``message`` then says on what evidence.
    held : tuple of str
        Parameters held at given values (:func:`mavcal.core.held.calibrate_held`: what poses
        within reach cannot identify); the fit is the optimum of J' over the others, and
        ``param_cov`` covers all of ``param_names``, the held ones with their prior.
    """

    accel: SensorModel
    mag: SensorModel
    gravity: np.ndarray
    field: np.ndarray
    orientations: np.ndarray
    cost: float
    iterations: int
    converged: bool
    message: str
    method: str = "ncar"
    model: str = "full"
    model_reason: str = ""
    param_names: tuple[str, ...] = ()
    param_cov: np.ndarray | None = None
    n_accel: np.ndarray | None = None
    n_mag: np.ndarray | None = None
    block_iterations: int = 0
    refine_iterations: int = 0
    dof: int = 0
    certificate: OptimumCertificate | None = None
    noise_inflation: tuple[float, float] = (1.0, 1.0)
    cost_name: str = "J' with the sample covariances"
    held: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        for name in ("gravity", "field", "orientations", "param_cov", "n_accel", "n_mag"):
            object.__setattr__(self, name, frozen_array(getattr(self, name)))
        object.__setattr__(self, "param_names", tuple(self.param_names))
        object.__setattr__(self, "held", tuple(self.held))

    @property
    def n_intervals(self) -> int:
        return int(self.orientations.shape[0])

    @property
    def h_z(self) -> float:
        return float(self.field[2])

    @property
    def inclination_deg(self) -> float:
        """Dip angle of the estimated field below the horizontal plane (positive down).

        The normalised frame has gravity along -z of the inertial frame (specific force
        of a still vehicle points up), so "down" is +z and inclination = atan2(h_z, h_x).
        """
        return float(np.degrees(np.arctan2(self.field[2], self.field[0])))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Calibration):
            return NotImplemented
        return (self.accel == other.accel and self.mag == other.mag
                and _arr_eq(self.field, other.field)
                and _arr_eq(self.orientations, other.orientations)
                and self.cost == other.cost and self.model == other.model)

    __hash__ = None  # type: ignore[assignment]
