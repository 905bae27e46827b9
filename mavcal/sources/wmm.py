"""Earth magnetic field from the world magnetic model shipped with pymavlink.

pymavlink 2.4.50 ships no full WMM (no ``mavwmm``); it has ArduPilot's 10-degree lookup
tables of declination, inclination and intensity (``pymavlink.mavextra.get_mag_field_ef``,
WMM epoch 2020, generated 2019-12-20), interpolated bilinearly. That is what ArduPilot
itself uses (``AP_Declination``). Its accuracy is about 1 degree and a few percent of the
intensity; altitude and date are not modelled (accepted for a stable signature, ignored).
"""
from __future__ import annotations

import math

import numpy as np
from pymavlink import mavextra

from mavcal.errors import UsageError


def field_at(lat_deg: float, lon_deg: float, alt_m: float = 0.0, when: object | None = None
             ) -> tuple[float, float, float]:
    """Declination, inclination and intensity of Earth's field at a place.

    Parameters
    ----------
    lat_deg, lon_deg : float
        Geodetic latitude [-90, 90] and longitude (any, wrapped to [-180, 180)) in degrees.
    alt_m : float
        Altitude; not modelled by the table (ignored).
    when : date/datetime or None
        Date; not modelled by the table (ignored, epoch 2020).

    Returns
    -------
    declination_deg : float
        Angle of the horizontal field east of true north.
    inclination_deg : float
        Dip angle, positive down.
    intensity_mgauss : float
        Total field strength in mGauss.
    """
    lat = float(lat_deg)
    lon = float(lon_deg)
    if not (math.isfinite(lat) and math.isfinite(lon)) or abs(lat) > 90.0:
        raise UsageError(f"invalid position lat={lat_deg} lon={lon_deg}")
    lat = min(lat, 90.0 - 1e-9)
    lon = ((lon + 180.0) % 360.0) - 180.0
    res = mavextra.get_mag_field_ef(lat, lon)
    if res is None:  # pragma: no cover - bounds are handled above
        raise UsageError(f"position outside the field table: lat={lat_deg} lon={lon_deg}")
    dec, inc, intensity_gauss = res
    return float(dec), float(inc), float(intensity_gauss) * 1000.0


def field_ned(lat_deg: float, lon_deg: float, alt_m: float = 0.0, when: object | None = None) -> np.ndarray:
    """Earth's field as a (3,) NED vector in mGauss (north, east, down) at a place.

    Same as pymavlink ``mavextra.expected_earth_field_lat_lon``.
    """
    dec, inc, f = field_at(lat_deg, lon_deg, alt_m, when)
    d, i = math.radians(dec), math.radians(inc)
    return np.array([f * math.cos(i) * math.cos(d), f * math.cos(i) * math.sin(d), f * math.sin(i)])
