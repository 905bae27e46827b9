"""Copies of a recording with its parameters dropped (all, or some names): the recordings a
ground station makes when it starts logging after its parameter download, or a tool trims.

Byte level, no parser library: a telemetry log's PARAM_VALUE frames, a DataFlash log's PARM
records, a ULog's parameter messages are left out and every other byte is copied as it is.
Tests build these in a temporary folder from the bundled and real logs (never committed).
"""
from __future__ import annotations

import struct
from collections.abc import Callable
from pathlib import Path

__all__ = ["strip_tlog_params", "strip_bin_params", "strip_ulog_params"]

_PARAM_VALUE = 22
_FMT = 128
#: DataFlash format characters -> bytes (AP_Logger's table)
_DF_SIZES = {"a": 64, "b": 1, "B": 1, "h": 2, "H": 2, "i": 4, "I": 4, "f": 4, "d": 8, "n": 4, "N": 16, "Z": 64,
             "c": 2, "C": 2, "e": 4, "E": 4, "L": 4, "M": 1, "q": 8, "Q": 8}



def _dropper(names: tuple[str, ...] | None) -> Callable[[str], bool]:
    """Whether a parameter is dropped: every one (``names`` None), else those starting with one of ``names``."""
    if names is None:
        return lambda n: True
    return lambda n: n.startswith(names)


def strip_tlog_params(src: str | Path, dst: str | Path, names: tuple[str, ...] | None = None) -> int:
    """Copy the telemetry log ``src`` to ``dst`` without its PARAM_VALUE messages (those whose
    name starts with one of ``names``, or all). Returns how many were dropped."""
    drop = _dropper(names)
    data = Path(src).read_bytes()
    out = bytearray()
    pos, n = 0, 0
    while pos + 8 < len(data):
        magic = data[pos + 8]
        if magic == 0xFE:
            size = 8 + 6 + data[pos + 9] + 2
            msgid, payload = data[pos + 13], pos + 14
        elif magic == 0xFD:
            size = 8 + 10 + data[pos + 9] + 2 + (13 if data[pos + 10] & 1 else 0)
            msgid, payload = int.from_bytes(data[pos + 15:pos + 18], "little"), pos + 18
        else:
            raise ValueError(f"{src}: no MAVLink frame at byte {pos + 8}")
        frame = data[pos:pos + size]
        if msgid == _PARAM_VALUE:
            pid = data[payload + 8:min(payload + 24, pos + size - 2)].split(b"\0", 1)[0].decode("ascii", "replace")
            if drop(pid):
                n += 1
                pos += size
                continue
        out += frame
        pos += size
    out += data[pos:]
    Path(dst).write_bytes(bytes(out))
    return n


def strip_bin_params(src: str | Path, dst: str | Path, names: tuple[str, ...] | None = None) -> int:
    """Copy the DataFlash log ``src`` to ``dst`` without its PARM records (those whose name starts
    with one of ``names``, or all). Returns how many were dropped."""
    drop = _dropper(names)
    data = Path(src).read_bytes()
    lengths: dict[int, int] = {_FMT: 89}
    parm: tuple[int, int] | None = None  # (type, offset of Name in the record)
    out = bytearray()
    pos, n = 0, 0
    while pos + 3 <= len(data):
        if data[pos] != 0xA3 or data[pos + 1] != 0x95 or data[pos + 2] not in lengths:
            out.append(data[pos])
            pos += 1
            continue
        ty = data[pos + 2]
        size = lengths[ty]
        rec = data[pos:pos + size]
        if ty == _FMT and len(rec) == 89:
            t, ln = rec[3], rec[4]
            name = rec[5:9].split(b"\0", 1)[0].decode("ascii", "replace")
            fmt = rec[9:25].split(b"\0", 1)[0].decode("ascii", "replace")
            lengths[t] = ln
            if name == "PARM" and "N" in fmt:
                parm = (t, 3 + sum(_DF_SIZES.get(c, 0) for c in fmt[:fmt.index("N")]))
        elif parm is not None and ty == parm[0]:
            pid = rec[parm[1]:parm[1] + 16].split(b"\0", 1)[0].decode("ascii", "replace")
            if drop(pid):
                n += 1
                pos += size
                continue
        out += rec
        pos += size
    out += data[pos:]
    Path(dst).write_bytes(bytes(out))
    return n


def strip_ulog_params(src: str | Path, dst: str | Path, names: tuple[str, ...] | None = None) -> int:
    """Copy the ULog ``src`` to ``dst`` without its parameter messages ('P', and the defaults 'Q';
    those whose name starts with one of ``names``, or all). Returns how many were dropped."""
    drop = _dropper(names)
    data = Path(src).read_bytes()
    out = bytearray(data[:16])
    pos, n = 16, 0
    while pos + 3 <= len(data):
        size, ty = struct.unpack_from("<HB", data, pos)
        rec = data[pos:pos + 3 + size]
        # 'P': key_len, "type name", value; 'Q': default_types, key_len, "type name", value
        key_at = 4 if ty == ord("P") else 5
        key_len = rec[key_at - 1] if len(rec) >= key_at else 0
        key = rec[key_at:key_at + key_len].decode("ascii", "replace").split(" ")[-1]
        if ty in (ord("P"), ord("Q")) and drop(key):
            n += 1
        else:
            out += rec
        pos += 3 + size
    Path(dst).write_bytes(bytes(out))
    return n
