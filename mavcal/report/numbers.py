"""The numbers behind the report's per-interval figures (pure numpy, no matplotlib).

:func:`interval_numbers` gives, for every still interval of a run, |a| and |B| before
(readings as logged) and after (the raw samples through the new ArduPilot parameters, the
firmware's equations of :mod:`mavcal.autopilot.calform`) and the whitened model residual
``mean - (K R_i g + b)`` (the paper's Eq. ``sensor_reading_model``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mavcal.autopilot import calform as fw
from mavcal.core.constants import GRAVITY_MPS2

__all__ = ["IntervalNumbers", "interval_numbers", "corrected_after", "rms_deviation"]

G0 = GRAVITY_MPS2


@dataclass(frozen=True, eq=False)
class IntervalNumbers:
    """Per-interval numbers of the report (one entry per interval of the segmentation).

    Attributes
    ----------
    used : (N,) bool array
        Whether the interval went into the fit.
    accel_before, accel_before_std : (N,) arrays
        Mean and standard deviation of |a| (m/s^2) over the interval, readings as logged.
    accel_after, accel_after_std : (N,) arrays
        The same for the raw samples through the new INS_ACC* parameters.
    mag_before, mag_before_std, mag_after, mag_after_std : (N,) arrays
        |B| in mGauss, as logged and through the new COMPASS_* parameters.
    accel_resid_sigma, mag_resid_sigma : (N, 3) arrays
        Interval mean minus the model prediction ``gain @ R_i @ (gravity|field) + bias``
        per axis, in standard deviations of the mean, ``sqrt(noise_cov_jj / n_i)``
        (NaN for unused intervals).
    accel_resid_norm, mag_resid_norm : (N,) arrays
        The whitened length ``sqrt(r^T (noise_cov / n_i)^-1 r)`` (chi with 3 degrees of
        freedom if the model and noise level are right).
    g_target_mps2, field_target_mgauss : float
        What the corrected magnitudes should be: g0 and the field magnitude the compass
        was scaled to.

    Notes
    -----
    NaN wherever an interval holds no sample of the sensor instance.
    """

    used: np.ndarray
    accel_before: np.ndarray
    accel_before_std: np.ndarray
    accel_after: np.ndarray
    accel_after_std: np.ndarray
    mag_before: np.ndarray
    mag_before_std: np.ndarray
    mag_after: np.ndarray
    mag_after_std: np.ndarray
    accel_resid_sigma: np.ndarray
    mag_resid_sigma: np.ndarray
    accel_resid_norm: np.ndarray
    mag_resid_norm: np.ndarray
    g_target_mps2: float
    field_target_mgauss: float

    def __len__(self) -> int:
        return int(self.used.shape[0])


def instances(run) -> tuple[int, int]:
    return run.mapping.accel[0].instance, run.mapping.compass[0].instance


def _raw_mag_to_sensor(run, b_body: np.ndarray) -> np.ndarray:
    """Raw compass readings (body frame after the *old* orientation) -> sensor frame."""
    return np.asarray(b_body, float) @ run.mapping.compass[0].old.mount_matrix


def corrected_after(run, sensor: str, raw_values: np.ndarray) -> np.ndarray:
    """Raw readings of the run's instance through the new parameters (the firmware's equations).

    Parameters
    ----------
    run : CalibrationRun
    sensor : "accel" or "mag"
    raw_values : (n, 3) array
        Recovered raw readings: accel in the board frame (m/s^2), compass in the body
        frame after the old orientation (mGauss), as in ``run.raw``.

    Returns
    -------
    (n, 3) array, body frame, what ArduPilot would report with the new parameters.
    """
    if sensor == "accel":
        return fw.apply_accel(run.mapping.accel[0].new, raw_values)
    # the new COMPASS_ORIENT replaces the old rotation, so go back to the sensor's axes first
    return fw.apply_compass(run.mapping.compass[0].new, _raw_mag_to_sensor(run, raw_values), sensor_frame=True)


def _window(series, t0: float, t1: float, pad: float) -> np.ndarray:
    if series is None or len(series) == 0:
        return np.empty((0, 3))
    t = series.time_s
    i0, i1 = np.searchsorted(t, t0 - pad, "left"), np.searchsorted(t, t1 + pad, "right")
    return np.asarray(series.values_at(slice(i0, i1)), float)  # (only those rows computed when packed)


def _norm_stats(v: np.ndarray) -> tuple[float, float]:
    if v.shape[0] == 0:
        return float("nan"), float("nan")
    n = np.linalg.norm(v, axis=1)
    return float(np.mean(n)), float(np.std(n))


def interval_numbers(run) -> IntervalNumbers:
    """Magnitudes before/after and whitened model residuals of every still interval.

    Parameters
    ----------
    run : mavcal.pipeline.CalibrationRun

    Returns
    -------
    IntervalNumbers
    """
    seg = run.segmentation
    cal = run.calibration
    ai, mi = instances(run)
    N = len(seg.intervals)
    used_idx = list(run.intervals_used)
    used = np.zeros(N, bool)
    used[used_idx] = True
    la, lm = run.log.get("accel", ai), run.log.get("mag", mi)
    arr = {k: np.full(N, np.nan) for k in ("ab", "abs", "aa", "aas", "mb", "mbs", "ma", "mas")}
    for k, iv in enumerate(seg.intervals):
        pad = 0.5 * iv.sample_period_s + 1e-6
        arr["ab"][k], arr["abs"][k] = _norm_stats(_window(la, iv.start_s, iv.end_s, pad))
        arr["mb"][k], arr["mbs"][k] = _norm_stats(_window(lm, iv.start_s, iv.end_s, pad))
        ra = iv.accel_mps2.get(ai)
        if ra is not None and ra.shape[0]:
            arr["aa"][k], arr["aas"][k] = _norm_stats(corrected_after(run, "accel", ra))
        rm = iv.mag_mgauss.get(mi)
        if rm is not None and rm.shape[0]:
            arr["ma"][k], arr["mas"][k] = _norm_stats(corrected_after(run, "mag", rm))

    res = {"a": np.full((N, 3), np.nan), "m": np.full((N, 3), np.nan)}
    rn = {"a": np.full(N, np.nan), "m": np.full(N, np.nan)}
    R = np.asarray(cal.orientations)
    for j, k in enumerate(used_idx[: R.shape[0]]):
        iv = seg.intervals[k]
        for key, samples, model, ref in (("a", iv.accel_mps2[ai], cal.accel, cal.gravity),
                                         ("m", iv.mag_mgauss[mi], cal.mag, cal.field)):
            n = samples.shape[0]
            r = samples.mean(0) - (model.gain @ R[j] @ ref + model.bias)
            C = np.asarray(model.noise_cov, float) / n
            res[key][k] = r / np.sqrt(np.diag(C))
            try:
                rn[key][k] = float(np.sqrt(max(r @ np.linalg.solve(C, r), 0.0)))
            except np.linalg.LinAlgError:
                rn[key][k] = float("nan")
    return IntervalNumbers(used=used, accel_before=arr["ab"], accel_before_std=arr["abs"], accel_after=arr["aa"],
                         accel_after_std=arr["aas"], mag_before=arr["mb"], mag_before_std=arr["mbs"],
                         mag_after=arr["ma"], mag_after_std=arr["mas"], accel_resid_sigma=res["a"],
                         mag_resid_sigma=res["m"], accel_resid_norm=rn["a"], mag_resid_norm=rn["m"],
                         g_target_mps2=G0, field_target_mgauss=float(run.mapping.compass[0].field_mgauss))


def rms_deviation(x: np.ndarray, target: float) -> float:
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean((x - target) ** 2))) if x.size else float("nan")
