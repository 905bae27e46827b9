"""Write MAVLink telemetry logs (.tlog) and ArduPilot DataFlash logs (.bin).

Used by the simulator (:mod:`mavcal.testing.simlog`) to produce logs that the readers, and
pymavlink, read exactly like real ones.

* tlog: each record is an 8-byte big-endian unsigned UNIX time in microseconds followed by
  one MAVLink packet, framed and checksummed by pymavlink (MAVLink 1 by default, or 2).
* DataFlash: each record is ``0xA3 0x95 <type>`` followed by the little-endian payload of
  the type's FMT format. The FMT record of a type is written before its first record, as
  ArduPilot does. The formats of PARM, MSG, IMU and MAG are ArduPilot's
  (``LogStructure.h``: IMU "QBffffffIIfBBHH", MAG "QBhhhhhhhhhBI", PARM "QNff", MSG "QZ").
"""
from __future__ import annotations

import struct
from collections.abc import Sequence
from pathlib import Path
from typing import BinaryIO, Union

import numpy as np

__all__ = ["TlogWriter", "DataFlashWriter", "DF_FORMATS", "int16_trunc"]

PathLike = Union[str, Path]


def int16_trunc(x) -> np.ndarray:
    """Truncate toward zero and clip to int16, as the firmware's ``(int16_t)`` casts do."""
    a = np.trunc(np.asarray(x, dtype=float))
    return np.clip(a, -32768, 32767).astype(np.int64)


# =========================================================================== tlog

class _FileWriter:
    """Context-manager plumbing shared by the log writers (``self._f`` is the open file)."""

    _f: BinaryIO

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if not self._f.closed:
            self._f.close()


class TlogWriter(_FileWriter):
    """Write a .tlog: MAVLink packets with 8-byte big-endian µs UNIX timestamps.

    Parameters
    ----------
    path : str or Path
    sysid, compid : int
        Source system/component of the vehicle's messages.
    mavlink2 : bool
        Frame packets as MAVLink 2 (with extension fields) instead of MAVLink 1.

    Examples
    --------
    >>> with TlogWriter("x.tlog") as w:                          # doctest: +SKIP
    ...     w.heartbeat(1.7e9)
    ...     w.raw_imu(1.7e9 + 0.02, 20_000, (0, 0, -1000), (0, 0, 0), (200, 10, 400))
    """

    def __init__(self, path: PathLike, sysid: int = 1, compid: int = 1, mavlink2: bool = False) -> None:
        if mavlink2:
            from pymavlink.dialects.v20 import ardupilotmega as dialect
        else:
            from pymavlink.dialects.v10 import ardupilotmega as dialect
        self._d = dialect
        self._f: BinaryIO = open(path, "wb")
        self._mav = dialect.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        self._gcs = dialect.MAVLink(None, srcSystem=255, srcComponent=190)
        self.path = Path(path)
        self.count = 0

    @property
    def dialect(self):
        """The pymavlink dialect module the messages are made with (for :meth:`write`)."""
        return self._d

    # -- plumbing
    def write(self, t_unix_s: float, msg, from_gcs: bool = False) -> None:
        """Write one pymavlink message object at receive time ``t_unix_s`` (seconds)."""
        mav = self._gcs if from_gcs else self._mav
        buf = msg.pack(mav)
        mav.seq = (mav.seq + 1) % 256
        self._f.write(struct.pack(">Q", int(round(t_unix_s * 1e6))) + buf)
        self.count += 1

    # -- messages
    def heartbeat(self, t_unix_s: float, vehicle_type: int = 2, autopilot: int = 3,
                  base_mode: int = 81, custom_mode: int = 0, system_status: int = 3) -> None:
        """HEARTBEAT (default: quadrotor, ArduPilot, disarmed, standby)."""
        self.write(t_unix_s, self._d.MAVLink_heartbeat_message(vehicle_type, autopilot, base_mode,
                                                                custom_mode, system_status, 3))

    def param_value(self, t_unix_s: float, name: str, value: float, index: int = 65535,
                    count: int = 0, param_type: int = 9) -> None:
        """PARAM_VALUE (REAL32 unless ``param_type`` says otherwise; index 65535 = broadcast)."""
        self.write(t_unix_s, self._d.MAVLink_param_value_message(name.encode("ascii"), float(value),
                                                                  param_type, count, index))

    def raw_imu(self, t_unix_s: float, time_usec: int, acc_mg, gyro_mrad_s, mag_mgauss) -> None:
        """RAW_IMU: accel in mG, gyro in mrad/s, mag in mGauss (int16, truncated toward zero)."""
        a, g, m = (int16_trunc(v) for v in (acc_mg, gyro_mrad_s, mag_mgauss))
        self.write(t_unix_s, self._d.MAVLink_raw_imu_message(int(time_usec), *map(int, a), *map(int, g),
                                                              *map(int, m)))

    def scaled_imu(self, n: int, t_unix_s: float, time_boot_ms: int, acc_mg, gyro_mrad_s, mag_mgauss) -> None:
        """SCALED_IMU (n=1), SCALED_IMU2 (n=2) or SCALED_IMU3 (n=3)."""
        a, g, m = (int16_trunc(v) for v in (acc_mg, gyro_mrad_s, mag_mgauss))
        cls = {1: self._d.MAVLink_scaled_imu_message, 2: self._d.MAVLink_scaled_imu2_message,
               3: self._d.MAVLink_scaled_imu3_message}[int(n)]
        self.write(t_unix_s, cls(int(time_boot_ms) & 0xFFFFFFFF, *map(int, a), *map(int, g), *map(int, m)))

    def statustext(self, t_unix_s: float, text: str, severity: int = 6) -> None:
        """STATUSTEXT (max 50 characters; severity 6 = INFO)."""
        self.write(t_unix_s, self._d.MAVLink_statustext_message(severity, text[:50].encode("ascii")))

    def command_long(self, t_unix_s: float, command: int, params: Sequence[float] = (),
                     target_system: int = 1, target_component: int = 1, from_gcs: bool = True) -> None:
        """COMMAND_LONG (by default sent by the GCS to the vehicle)."""
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        self.write(t_unix_s, self._d.MAVLink_command_long_message(target_system, target_component, int(command),
                                                                   0, *p[:7]), from_gcs=from_gcs)

    def command_ack(self, t_unix_s: float, command: int, result: int = 0) -> None:
        self.write(t_unix_s, self._d.MAVLink_command_ack_message(int(command), int(result)))

    def attitude(self, t_unix_s: float, time_boot_ms: int, roll: float, pitch: float, yaw: float) -> None:
        self.write(t_unix_s, self._d.MAVLink_attitude_message(int(time_boot_ms), roll, pitch, yaw, 0, 0, 0))


# =========================================================================== DataFlash

#: name -> (type id, format, columns). Formats as ArduPilot writes them.
DF_FORMATS: dict[str, tuple[int, str, str]] = {
    "PARM": (64, "QNff", "TimeUS,Name,Value,Default"),
    "MSG": (91, "QZ", "TimeUS,Message"),
    "IMU": (168, "QBffffffIIfBBHH", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz"),
    "MAG": (175, "QBhhhhhhhhhBI", "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S"),
}

_FMT_TYPE = 0x80
_FMT_STRUCT = "<BB4s16s64s"
_HEAD = b"\xa3\x95"

# DataFlash format character -> struct code
_STRUCT = {
    "a": "64s", "b": "b", "B": "B", "h": "h", "H": "H", "i": "i", "I": "I", "f": "f", "d": "d",
    "n": "4s", "N": "16s", "Z": "64s", "c": "h", "C": "H", "e": "i", "E": "I", "L": "i", "M": "B",
    "q": "q", "Q": "Q",
}


def _struct_of(fmt: str) -> str:
    return "<" + "".join(_STRUCT[c] for c in fmt)


def _cstr(s: str, n: int) -> bytes:
    b = s.encode("ascii")[:n]
    return b + b"\0" * (n - len(b))


class DataFlashWriter(_FileWriter):
    """Write an ArduPilot DataFlash (.bin) log that pymavlink's DFReader reads.

    Times are ``TimeUS``: microseconds since boot (int).
    """

    def __init__(self, path: PathLike) -> None:
        self._f: BinaryIO = open(path, "wb")
        self.path = Path(path)
        self._written: set = set()
        self.count = 0
        self._write_fmt("FMT", _FMT_TYPE, "BBnNZ", "Type,Length,Name,Format,Columns")

    def _write_fmt(self, name: str, type_id: int, fmt: str, columns: str) -> None:
        length = 3 + struct.calcsize(_struct_of(fmt))
        body = struct.pack(_FMT_STRUCT, type_id, length, _cstr(name, 4), _cstr(fmt, 16), _cstr(columns, 64))
        self._f.write(_HEAD + bytes([_FMT_TYPE]) + body)
        self._written.add(name)

    def record(self, name: str, *values) -> None:
        """Write one record of a type in :data:`DF_FORMATS` (values in column order;
        strings for n/N/Z columns)."""
        type_id, fmt, columns = DF_FORMATS[name]
        if name not in self._written:
            self._write_fmt(name, type_id, fmt, columns)
        vals: list[bytes | float | int] = []
        for c, v in zip(fmt, values):
            if c in "nNZ":
                vals.append(_cstr(str(v), {"n": 4, "N": 16, "Z": 64}[c]))
            elif c in "fd":
                vals.append(float(v))
            else:
                vals.append(int(v))
        if len(vals) != len(fmt):
            raise ValueError(f"{name} needs {len(fmt)} values ({columns}), got {len(values)}")
        self._f.write(_HEAD + bytes([type_id]) + struct.pack(_struct_of(fmt), *vals))
        self.count += 1

    def parm(self, time_us: int, name: str, value: float, default: float = float("nan")) -> None:
        self.record("PARM", time_us, name, value, default)

    def msg(self, time_us: int, text: str) -> None:
        self.record("MSG", time_us, text)

    def imu(self, time_us: int, instance: int, gyro_rad_s, acc_mps2, temp_c: float = 25.0,
            rate_hz: int = 400) -> None:
        """IMU record: corrected gyro (rad/s) and accel (m/s^2) as float32."""
        g = np.asarray(gyro_rad_s, dtype=float)
        a = np.asarray(acc_mps2, dtype=float)
        self.record("IMU", time_us, instance, g[0], g[1], g[2], a[0], a[1], a[2], 0, 0, temp_c, 1, 1,
                    rate_hz, rate_hz)

    def mag(self, time_us: int, instance: int, mag_mgauss, ofs_mgauss=(0, 0, 0), motor_ofs_mgauss=(0, 0, 0),
            healthy: bool = True, last_update_ms: int | None = None) -> None:
        """MAG record: corrected field, offsets and motor offset, all int16 (truncated)."""
        m, o, mo = (int16_trunc(v) for v in (mag_mgauss, ofs_mgauss, motor_ofs_mgauss))
        s = int(time_us // 1000) if last_update_ms is None else int(last_update_ms)
        self.record("MAG", time_us, instance, *m, *o, *mo, int(bool(healthy)), s & 0xFFFFFFFF)
