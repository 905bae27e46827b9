"""A minimal ULog writer for tests: formats, parameters, info and data messages, as PX4's logger
writes them (the ULog file format, version 1: a 16-byte header, then messages of
``uint16 size, uint8 type, payload``; ``F`` format, ``I`` info, ``P`` parameter, ``A`` add
logged message, ``D`` data). Fields are packed without padding, little endian; every format
begins with ``uint64_t timestamp`` (microseconds).

    w = UlogWriter(path)
    w.info("sys_name", "PX4")
    w.param("CAL_MAG0_ID", 197388, int32=True)
    w.topic("sensor_mag", [("uint64_t", "timestamp"), ("float", "x"), ...])
    w.data("sensor_mag", 0, {"timestamp": t_us, "x": x, ...})   # arrays: one message per row
    w.close()
"""
from __future__ import annotations

import struct
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

__all__ = ["UlogWriter"]

_MAGIC = b"ULog\x01\x12\x35"
_TYPES = {"uint64_t": "<u8", "int64_t": "<i8", "uint32_t": "<u4", "int32_t": "<i4", "uint16_t": "<u2",
          "int16_t": "<i2", "uint8_t": "u1", "int8_t": "i1", "bool": "u1", "float": "<f4", "double": "<f8"}


def _field_type(t: str) -> tuple[str, int]:
    """``float[3]`` -> ("float", 3); ``float`` -> ("float", 1)."""
    if t.endswith("]"):
        base, n = t[:-1].split("[")
        return base, int(n)
    return t, 1


class UlogWriter:
    """Write a ULog file (see the module's notes); the definitions must come before the first :meth:`data`."""

    def __init__(self, path: str | Path, start_us: int = 0) -> None:
        self._fh = open(path, "wb")
        self._fh.write(_MAGIC + b"\x01" + struct.pack("<Q", int(start_us)))
        self._formats: dict[str, np.dtype] = {}
        self._ids: dict[tuple[str, int], int] = {}

    def _msg(self, kind: bytes, payload: bytes) -> None:
        if len(payload) > 0xFFFF:
            raise ValueError("ULog message too long")
        self._fh.write(struct.pack("<HB", len(payload), kind[0]) + payload)

    def info(self, key: str, value: str) -> None:
        v = value.encode()
        k = f"char[{len(v)}] {key}".encode()
        self._msg(b"I", bytes([len(k)]) + k + v)

    def param(self, name: str, value: float, *, int32: bool = False) -> None:
        k = f"{'int32_t' if int32 else 'float'} {name}".encode()
        v = struct.pack("<i", int(value)) if int32 else struct.pack("<f", float(value))
        self._msg(b"P", bytes([len(k)]) + k + v)

    def topic(self, name: str, fields: Sequence[tuple[str, str]]) -> None:
        """Define topic ``name`` with ``(type, field)`` pairs (``uint64_t timestamp`` first)."""
        if fields[0] != ("uint64_t", "timestamp"):
            raise ValueError("a ULog format begins with uint64_t timestamp")
        text = f"{name}:" + "".join(f"{t} {f};" for t, f in fields)
        self._msg(b"F", text.encode())
        dt = []
        for t, f in fields:
            base, n = _field_type(t)
            dt.append((f, _TYPES[base], (n,)) if n > 1 else (f, _TYPES[base]))
        self._formats[name] = np.dtype(dt)

    def data(self, name: str, multi_id: int, columns: Mapping[str, object]) -> None:
        """Log the rows of ``columns`` (each an array over the rows, or a scalar) as instance ``multi_id``."""
        key = (name, int(multi_id))
        if key not in self._ids:
            mid = self._ids[key] = len(self._ids)
            self._msg(b"A", struct.pack("<BH", int(multi_id), mid) + name.encode())
        mid = self._ids[key]
        dt = self._formats[name]
        n = len(np.asarray(columns["timestamp"]))
        rows = np.zeros(n, dtype=dt)
        for f in dt.names or ():
            if f in columns:
                rows[f] = np.asarray(columns[f])
        head = struct.pack("<HBH", dt.itemsize + 2, ord("D"), mid)
        self._fh.write(b"".join(head + r.tobytes() for r in rows))

    def close(self) -> None:
        self._fh.close()

    def __enter__(self) -> UlogWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
