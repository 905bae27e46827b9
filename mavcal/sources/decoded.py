"""IMU messages decoded straight into their final columns (the lean tlog path).

:mod:`mavcal.sources.tlog_imu` decodes the integer IMU messages of a tlog into the arrays
the sensor series keep (SI units, float64) instead of raw message columns, and builds the
time base while it reads; :func:`mavcal.sources.assemble.assemble_tlog` takes the result
(:class:`PreparedImu`) in place of those messages' columns. The assembly rules are the same
(see :mod:`mavcal.sources.assemble`), so the log is identical to the one built from columns.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

__all__ = ["DecodedImu", "PreparedImu"]


@dataclass(frozen=True, eq=False)
class DecodedImu:
    """One integer IMU message (RAW_IMU, SCALED_IMU, SCALED_IMU2 or SCALED_IMU3) of the vehicle.

    ``time_s`` is on the log's time base (boot time plus the shift of its boot segment),
    ``log_time_s`` the tlog receive time; ``accel_mg`` (milli-g) / ``gyro_mrads`` (mrad/s) /
    ``mag_mgauss`` (n, 3) int16 are the readings of every row as sent, or None for a SCALED_IMU
    beside RAW_IMU (not used: RAW_IMU carries instance 0). ``imu_zero_rows`` / ``mag_zero_rows``
    count the rows whose accel and gyro (mag) are all zero (those rows hold zeros).
    """

    time_s: np.ndarray
    log_time_s: np.ndarray
    accel_mg: np.ndarray | None
    gyro_mrads: np.ndarray | None
    mag_mgauss: np.ndarray | None
    imu_zero_rows: int
    mag_zero_rows: int


@dataclass(frozen=True, eq=False)
class PreparedImu:
    """The vehicle's IMU messages and the time base of a tlog, built while decoding.

    ``imu`` maps each IMU message with rows to a :class:`DecodedImu` (integer messages) or its
    columns (HIGHRES_IMU); ``seg_index`` is the frame number at which each boot segment
    starts, ``delay`` its median (receive - boot) time, ``offset`` its shift and ``reboot_s``
    the reboot time before it (see ``_TimeBase`` in :mod:`mavcal.sources.assemble`).
    """

    sysid: int
    imu: Mapping[str, DecodedImu | Mapping[str, np.ndarray]]
    seg_index: np.ndarray
    delay: np.ndarray
    offset: np.ndarray
    reboot_s: np.ndarray
