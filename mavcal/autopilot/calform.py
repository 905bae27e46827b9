"""The calibration form the pipeline judges every autopilot's calibration in: a compass's offsets,
soft iron, scale and mounting (:class:`CompassCal`), an accelerometer's offsets, scale and board
rotation (:class:`AccelCal`), and how such a calibration corrects a reading and is undone (pure numpy).

The form is ArduPilot's (``AP_Compass_Backend::correct_field``,
``AP_InertialSensor_Backend::_rotate_and_correct_accel``; see ArduPilot's firmware model for the
equations and the parameters that hold it); PX4's calibration converts to it
(its ``ardupilot_form``). No parameter name is spelled here.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mavcal.autopilot.rotations import CUSTOM_1, CUSTOM_2, rotation_matrix

__all__ = ["COMPASS_MIN_SCALE", "COMPASS_MAX_SCALE", "CompassCal", "AccelCal", "soft_iron_matrix",
           "effective_scale", "apply_compass", "undo_compass", "apply_accel", "undo_accel"]

COMPASS_MIN_SCALE = 1.0 / 1.5
COMPASS_MAX_SCALE = 1.5


# --------------------------------------------------------------------------- models

def _vec3(v, name: str) -> tuple[float, float, float]:
    a = np.asarray(v, dtype=float).reshape(-1)
    if a.shape != (3,):
        raise ValueError(f"{name} must have 3 elements, got shape {np.shape(v)}")
    return (float(a[0]), float(a[1]), float(a[2]))


def _mount(orient: int, custom: tuple[float, float, float] | None) -> np.ndarray:
    return rotation_matrix(orient, custom if int(orient) in (CUSTOM_1, CUSTOM_2) else None)


@dataclass(frozen=True)
class CompassCal:
    """The calibration a compass applies (one parameter set, one priority slot).

    Attributes
    ----------
    ofs_mgauss : (3,) COMPASS_OFSn, body frame after orientation, *added* to the field.
    dia, odi : (3,) COMPASS_DIAn / COMPASS_ODIn (soft-iron matrix; DIA all zero = off).
    scale : COMPASS_SCALEn (used only in [1/1.5, 1.5]; 0 = not set).
    orient : rotation enum applied to the sensor before the correction: COMPASS_ORIENTn
        for an external compass, AHRS_ORIENTATION for an internal one.
    external : bool or None (unknown).
    custom_deg : (roll, pitch, yaw) of the custom rotation if ``orient`` is 101/102.
    mot : (3,) COMPASS_MOTn, informative (the logged motor offset is used to undo it).
    """

    ofs_mgauss: tuple[float, float, float] = (0.0, 0.0, 0.0)
    dia: tuple[float, float, float] = (1.0, 1.0, 1.0)
    odi: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: float = 1.0
    orient: int = 0
    external: bool | None = None
    custom_deg: tuple[float, float, float] | None = None
    mot: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        for n in ("ofs_mgauss", "dia", "odi", "mot"):
            object.__setattr__(self, n, _vec3(getattr(self, n), n))
        object.__setattr__(self, "scale", float(self.scale))
        object.__setattr__(self, "orient", int(round(float(self.orient))))
        if self.custom_deg is not None:
            object.__setattr__(self, "custom_deg", _vec3(self.custom_deg, "custom_deg"))

    @property
    def matrix(self) -> np.ndarray:
        """(3, 3) soft-iron matrix M as the firmware uses it (identity when DIA = 0)."""
        return soft_iron_matrix(self.dia, self.odi)

    @property
    def k(self) -> float:
        """Effective scale factor (1 when COMPASS_SCALE is outside its valid window)."""
        return effective_scale(self.scale)

    @property
    def mount_matrix(self) -> np.ndarray:
        """(3, 3) R_mount for ``orient``."""
        return _mount(self.orient, self.custom_deg)


@dataclass(frozen=True)
class AccelCal:
    """The calibration an accelerometer applies.

    Attributes
    ----------
    ofs_mps2 : (3,) INS_ACCnOFFS, board frame, *subtracted*.
    scale : (3,) INS_ACCnSCAL, board frame, multiplied per axis.
    board_orient : AHRS_ORIENTATION (rotation enum) applied after offsets and scale.
    custom_deg : custom rotation angles if ``board_orient`` is 101/102.
    """

    ofs_mps2: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    board_orient: int = 0
    custom_deg: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "ofs_mps2", _vec3(self.ofs_mps2, "ofs_mps2"))
        object.__setattr__(self, "scale", _vec3(self.scale, "scale"))
        object.__setattr__(self, "board_orient", int(round(float(self.board_orient))))
        if self.custom_deg is not None:
            object.__setattr__(self, "custom_deg", _vec3(self.custom_deg, "custom_deg"))

    @property
    def board_matrix(self) -> np.ndarray:
        """(3, 3) R_A for ``board_orient``."""
        return _mount(self.board_orient, self.custom_deg)


def soft_iron_matrix(dia, odi) -> np.ndarray:
    """Symmetric ``[[DX, OX, OY], [OX, DY, OZ], [OY, OZ, DZ]]``; identity if DIA is all zero
    (the firmware then skips the matrix, ODI included)."""
    d = np.asarray(dia, dtype=float)
    o = np.asarray(odi, dtype=float)
    if not np.any(d != 0.0):
        return np.eye(3)
    return np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])


def effective_scale(scale: float) -> float:
    """COMPASS_SCALE as applied: itself within [1/1.5, 1.5], else 1 (0 means "not set")."""
    s = float(scale)
    # the firmware compares float32 values; 1/1.5 rounds the same way in both
    s32 = float(np.float32(s))
    if float(np.float32(COMPASS_MIN_SCALE)) <= s32 <= COMPASS_MAX_SCALE:
        return s
    return 1.0


def _rows(v) -> np.ndarray:
    a = np.asarray(v, dtype=float)
    if a.shape[-1] != 3:
        raise ValueError(f"vectors must have a last dimension of 3, got shape {a.shape}")
    return a


def _clean(x: np.ndarray) -> bool:
    """``x`` holds no zero and no NaN or infinity (an overflowing sum only says: look closer)."""
    with np.errstate(over="ignore", invalid="ignore"):
        return bool(np.isfinite(np.sum(x)) and np.all(x))  # a NaN or an infinity makes the sum non-finite


def _special_rows(x: np.ndarray, any_zero: bool = False) -> np.ndarray | None:
    """Indices of the rows of (n, 3) ``x`` that hold a non-finite value or a negative zero (with
    ``any_zero``: any zero), None when none do. Only there can a product by a matrix of exact
    zeros and ones in BLAS/LAPACK differ from the elementwise shortcut: ``0 * inf`` spreads NaN
    to the other axes, and a sum of zeros is -0 only when every term is, so ``-0 * 1`` plus the
    other axes' ``+-0`` terms may come out +0 (with ``any_zero``, for negated columns: ``+0 * -1``
    is -0). Those rows take the library call itself."""
    with np.errstate(over="ignore", invalid="ignore"):
        finite = bool(np.isfinite(np.sum(x)))  # a NaN or an infinity makes the sum non-finite
    odd = x == 0.0
    if finite and not (np.any(odd) if any_zero else np.any(np.signbit(x[odd]))):
        return None  # (zeros are common in integer telemetry; negative zeros are not)
    if not any_zero:
        odd &= np.signbit(x)
    if not finite:
        odd |= ~np.isfinite(x)
    rows = np.flatnonzero(odd.any(axis=-1))
    return rows if len(rows) else None


def _two_rows(x: np.ndarray) -> np.ndarray:
    """(n, 3) ``x`` with a row of ones appended when n = 1: a library call on several rows takes
    the same code path as on the whole array (one row alone may take another)."""
    return np.vstack([x, np.ones((1, 3))]) if len(x) == 1 else x


def _solve_rows(m: np.ndarray, c: np.ndarray, out: np.ndarray) -> None:
    """``out = M^-1 c`` per row of (..., 3) ``c`` (``out`` may be ``c`` itself), the values
    ``np.linalg.solve(m, c.T).T`` gives.

    A diagonal ``m`` (the identity of an unset soft-iron matrix, or DIA without ODI) is
    LAPACK's LU with nothing to pivot or eliminate: every row is ``c * (1 / diag)`` (the
    back substitution multiplies by the reciprocal of each pivot; the eliminations subtract
    exact zeros), bit for bit, without the solver's cost. Rows with a zero or a non-finite
    value and any other matrix go through ``np.linalg.solve``."""
    c2, o2 = c.reshape(-1, 3), out.reshape(-1, 3)
    d = np.diagonal(m)
    if len(c2) < 2 or not (np.all(m == np.diag(d)) and np.all(np.isfinite(d)) and np.all(d != 0.0)):
        # (one right-hand side takes another LAPACK path, which divides by the pivots)
        o2[...] = np.linalg.solve(m, c2.T).T
        return
    rows = _special_rows(c2)
    if rows is None:
        np.multiply(c2, 1.0 / d, out=o2)
        return
    held = _two_rows(c2[rows])  # a copy, before ``out`` (maybe ``c``) changes
    np.multiply(c2, 1.0 / d, out=o2)
    o2[rows] = np.linalg.solve(m, held.T).T[:len(rows)]


def _times_matrix(a: np.ndarray, r: np.ndarray, out: np.ndarray) -> None:
    """``out = a @ r`` for (..., 3) ``a`` (``out`` another array), the values of the matrix product.

    A signed permutation ``r`` (every board rotation by multiples of 90 deg, the identity
    included: entries exactly 0 and +-1) only picks and negates columns: ``a[:, k] * (+-1)``,
    bit for bit what the product gives where the other terms add exact zeros. Rows with a
    zero or a non-finite value and any other matrix take the product itself."""
    a2, o2 = a.reshape(-1, 3), out.reshape(-1, 3)
    src = np.argmax(np.abs(r), axis=0)  # per output column j: the row k with r[k, j] != 0
    sign = r[src, np.arange(3)]
    if len(a2) < 2 or not (np.all(np.abs(sign) == 1.0) and np.count_nonzero(r) == 3):
        out[...] = a @ r
        return
    if np.array_equal(src, np.arange(3)) and np.all(sign == 1.0):
        np.copyto(o2, a2)  # the identity (x * 1 is x)
    else:
        np.multiply(a2[:, src], sign, out=o2)
    rows = _special_rows(a2, any_zero=bool(np.any(sign < 0.0)))
    if rows is not None:
        o2[rows] = (_two_rows(a2[rows]) @ r)[:len(rows)]


def _out_for(out: np.ndarray | None, shape: tuple[int, ...], *inputs: np.ndarray) -> np.ndarray:
    """``out`` checked (float64, C-contiguous, ``shape``, not overlapping ``inputs``), or a new array."""
    if out is None:
        return np.empty(shape)
    if out.shape != shape or out.dtype != np.float64 or not out.flags.c_contiguous or not out.flags.writeable:
        raise ValueError(f"out must be a writeable C-contiguous float64 array of shape {shape}")
    if any(np.may_share_memory(out, x) for x in inputs):
        raise ValueError("out must not overlap the inputs")
    return out


def apply_compass(cal: CompassCal, raw_mgauss, motor_ofs_mgauss=None, sensor_frame: bool = True) -> np.ndarray:
    """Forward model: what the firmware reports for a raw compass reading.

    Parameters
    ----------
    cal : CompassCal
    raw_mgauss : (..., 3) array
        Raw field in mGauss: in the sensor frame (``sensor_frame=True``; ``R_mount`` is
        applied) or already in the body frame after orientation (``sensor_frame=False``).
    motor_ofs_mgauss : (..., 3) array, optional
        Motor compensation added after the matrix.

    Returns
    -------
    (..., 3) array, corrected field in mGauss, body frame.
    """
    b = _rows(raw_mgauss)
    if sensor_frame:
        b = b @ cal.mount_matrix.T
    c = cal.k * (b + np.asarray(cal.ofs_mgauss)) @ cal.matrix.T
    if motor_ofs_mgauss is not None:
        c = c + _rows(motor_ofs_mgauss)
    return c


def undo_compass(cal: CompassCal, corrected_mgauss, motor_ofs_mgauss=None, sensor_frame: bool = False, *,
                 out: np.ndarray | None = None) -> np.ndarray:
    """Inverse model: ``b = (1/k) M^-1 (corrected - motor_ofs) - OFS``.

    Parameters
    ----------
    cal : CompassCal
    corrected_mgauss : (..., 3) array, the reported field (mGauss).
    motor_ofs_mgauss : (..., 3) array, optional, the motor offset the firmware added.
    sensor_frame : bool
        False (default): return the body-frame field after orientation (the frame of the
        offsets). True: also undo ``R_mount`` (the sensor's own axes).
    out : (..., 3) float64 array, optional
        Where to write the result (C-contiguous, not overlapping the inputs): no temporary
        of the size of the input. The values are the same either way.

    Returns
    -------
    (..., 3) array, raw field in mGauss (``out`` when given).
    """
    c = _rows(corrected_mgauss)
    motor = None if motor_ofs_mgauss is None else _rows(motor_ofs_mgauss)
    shape = c.shape if motor is None else np.broadcast_shapes(c.shape, motor.shape)
    b = _out_for(out, shape, c) if motor is None else _out_for(out, shape, c, motor)
    if motor is not None:
        np.subtract(c, motor, out=b)
        c = b
    _solve_rows(cal.matrix, c, b)
    if cal.k != 1.0:  # x / 1 is x
        b /= cal.k  # in place: the values of ``b / k``
    b -= np.asarray(cal.ofs_mgauss)
    if sensor_frame:
        b[...] = b @ cal.mount_matrix
    return b


def apply_accel(cal: AccelCal, raw_mps2, calibrating: bool = False) -> np.ndarray:
    """Forward model: ``R_A (S * (u - OFS))``; with ``calibrating`` only ``R_A u``.

    Parameters
    ----------
    raw_mps2 : (..., 3) array, board-frame raw acceleration in m/s^2.

    Returns
    -------
    (..., 3) array, body-frame corrected acceleration in m/s^2.
    """
    u = _rows(raw_mps2)
    if not calibrating:
        u = (u - np.asarray(cal.ofs_mps2)) * np.asarray(cal.scale)
    return u @ cal.board_matrix.T


def undo_accel(cal: AccelCal, corrected_mps2, calibrating: bool = False, *,
               out: np.ndarray | None = None) -> np.ndarray:
    """Inverse model: ``u = (R_A^T a) / S + OFS`` (board frame, m/s^2).

    With ``calibrating=True`` (an accel calibration was running, the firmware skipped the
    offsets and scale) only ``R_A`` is undone. A zero scale element (an unused IMU slot)
    gives NaN for that axis. ``out``: where to write the result, as in :func:`undo_compass`.
    """
    a = _rows(corrected_mps2)
    u = _out_for(out, a.shape, a)
    r, s = cal.board_matrix, np.asarray(cal.scale)
    if not calibrating and np.all(s != 0.0) and np.array_equal(r, np.eye(3)) and a.size >= 6:
        # no board rotation (the usual AHRS_ORIENTATION = 0): ``(a @ I) / s`` in one pass, ``a @ I``
        # being ``a`` except in rows with a zero or a non-finite value (see _times_matrix)
        a2, u2 = a.reshape(-1, 3), u.reshape(-1, 3)
        np.divide(a2, s, out=u2)
        # the rows to check show in the result (just written, in cache): a zero or a non-finite
        # value there comes from one in ``a`` (or from an underflow, an overflow: checked too)
        rows = None if _clean(u2) else _special_rows(a2)
        if rows is not None:
            u2[rows] = (_two_rows(a2[rows]) @ r)[:len(rows)] / s
        u += np.asarray(cal.ofs_mps2)
        return u
    _times_matrix(a, r, u)
    if calibrating:
        return u
    if np.all(s != 0.0):
        u /= s  # in place: the values of ``u / s``
    else:
        with np.errstate(divide="ignore", invalid="ignore"):
            u[...] = np.where(s != 0.0, u / np.where(s != 0.0, s, 1.0), np.nan)
    u += np.asarray(cal.ofs_mps2)
    return u
