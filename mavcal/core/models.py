"""The models mavcal can fit, from the paper's full model down to ArduPilot's own.

A model fixes the form of each sensor's gain matrix. Every model has the biases b_a, b_m,
the field component h_z and one orientation per interval; the gains are:

==================  =================  ==============  ====================================
model               K_a                K_m             meaning
==================  =================  ==============  ====================================
``full``            upper triangular   full            the paper: cross-axis accel terms and
                                                       any accel-to-compass rotation/mirroring
``diag-accel``      diagonal           full            no accelerometer cross-axis coupling
``ardupilot``       diagonal           symmetric       exactly ArduPilot's parameter set
                                                       (INS_ACC*SCAL, COMPASS_DIA/ODI) with
                                                       the compass orientation as configured
``offsets-scales``  diagonal           diagonal        offsets and per-axis scales only
==================  =================  ==============  ====================================

Each still interval gives 6 equations and costs 3 orientation unknowns, so a model with P
global parameters needs 3N >= P (the paper's 6N >= 3N + 22 gives N >= 8 for ``full``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mavcal.errors import InsufficientDataError

_IDX = {
    "upper": [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)],
    "diag": [(0, 0), (1, 1), (2, 2)],
    "full": [(r, c) for c in range(3) for r in range(3)],
    "scalar": [],
}


@dataclass(frozen=True, eq=False)
class GainForm:
    """Linear parameterisation K = sum_k p_k E_k of a gain matrix."""

    name: str
    basis: np.ndarray  # (k, 3, 3)
    labels: tuple[str, ...]  # "11", "12", ... (1-based row/col), "s" for scalar

    @property
    def size(self) -> int:
        return int(self.basis.shape[0])

    def to_matrix(self, p: np.ndarray) -> np.ndarray:
        return np.einsum("k,kij->ij", p, self.basis)

    def from_matrix(self, K: np.ndarray) -> np.ndarray:
        """Least-squares projection of K onto the form (exact for K of this form)."""
        B = self.basis.reshape(self.size, 9)
        p, *_ = np.linalg.lstsq(B.T, np.asarray(K, dtype=float).reshape(9), rcond=None)
        return p

    def project(self, K: np.ndarray) -> np.ndarray:
        return self.to_matrix(self.from_matrix(K))


def _make_form(name: str) -> GainForm:
    if name == "sym":
        basis, labels = [], []
        for r in range(3):
            for c in range(r, 3):
                E = np.zeros((3, 3))
                E[r, c] = E[c, r] = 1.0
                basis.append(E)
                labels.append(f"{r + 1}{c + 1}")
        return GainForm(name, np.array(basis), tuple(labels))
    if name == "scalar":
        return GainForm(name, np.eye(3)[None], ("s",))
    basis, labels = [], []
    for r, c in _IDX[name]:
        E = np.zeros((3, 3))
        E[r, c] = 1.0
        basis.append(E)
        labels.append(f"{r + 1}{c + 1}")
    return GainForm(name, np.array(basis), tuple(labels))


FORMS: dict[str, GainForm] = {n: _make_form(n) for n in ("upper", "diag", "full", "sym", "scalar")}


@dataclass(frozen=True)
class ModelSpec:
    name: str
    accel_form: str
    mag_form: str
    description: str

    @property
    def n_global(self) -> int:
        return FORMS[self.accel_form].size + 3 + FORMS[self.mag_form].size + 3 + 1

    @property
    def min_intervals(self) -> int:
        return -(-self.n_global // 3)  # ceil(P / 3)


MODELS: dict[str, ModelSpec] = {
    "full": ModelSpec("full", "upper", "full",
                      "the paper's model: upper-triangular K_a, full K_m (any accel-to-compass rotation)"),
    "diag-accel": ModelSpec("diag-accel", "diag", "full",
                            "no accelerometer cross-axis terms; full K_m"),
    "ardupilot": ModelSpec("ardupilot", "diag", "sym",
                           "ArduPilot's own parameter set: per-axis accel scales, symmetric soft-iron "
                           "matrix, compass orientation as configured"),
    "offsets-scales": ModelSpec("offsets-scales", "diag", "diag",
                                "offsets and per-axis scales only, compass axes aligned with the accelerometer"),
}

# from most to least general; each is nested in the one before it
MODEL_CHAIN: list[str] = ["full", "diag-accel", "ardupilot", "offsets-scales"]


def choose_model(model: str, N: int) -> tuple[ModelSpec, str]:
    """The model to fit first for N intervals and why: the most general identifiable one for
    "auto" (InsufficientDataError when none, or when the requested one is not identified)."""
    if model == "auto":
        allowed = [MODELS[k] for k in MODEL_CHAIN if MODELS[k].min_intervals <= N]
        if not allowed:
            raise InsufficientDataError(
                f"{N} still intervals cannot identify even the simplest model (offsets and scales need "
                f"{MODELS['offsets-scales'].min_intervals}; the full joint model needs "
                f"{MODELS['full'].min_intervals}); hold the vehicle still in more orientations")
        spec = allowed[0]
        reason = (f"{N} intervals identify the {spec.name} model ({spec.n_global} parameters)"
                  if spec.name == "full" else
                  f"only {N} intervals: the full joint model needs >= {MODELS['full'].min_intervals} "
                  f"(6N >= 3N + 22), so the most general identifiable model, {spec.name}, was fitted")
        return spec, reason
    spec = MODELS[model]
    if N < spec.min_intervals:
        raise InsufficientDataError(
            f"{N} still intervals cannot identify the {spec.name} model ({spec.n_global} parameters "
            f"need N >= {spec.min_intervals}, from 6N >= 3N + {spec.n_global}); add intervals or "
            "choose a simpler model")
    return spec, f"model {spec.name} requested"
