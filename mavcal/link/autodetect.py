"""``--connect auto``: the serial port a flight controller is on, found without typing it.

pyserial lists the ports (``serial.tools.list_ports.comports``); each gets a rank
(:func:`rank_port`):

* **2, an autopilot**: a USB vendor id of flight-controller makers (:data:`AUTOPILOT_VIDS`:
  ArduPilot's own pid.codes id, CubePilot/Hex, 3D Robotics/PX4, Holybro, CUAV, and
  STMicroelectronics' virtual COM port that many boards keep), or a description matching one
  of MAVProxy's ``preferred_ports`` patterns (``MAVProxy/modules/mavproxy_link.py``: ``*Ardu*``,
  ``*PX4*``, ``*FMU*``, ``*CubePilot*``...);
* **1, a telemetry radio**: the USB-serial chips SiK radios use (FTDI, Silicon Labs CP210x);
* **0, another USB serial port**; a port with no USB vendor id and no such description (a
  motherboard's ``/dev/ttyS0``) is never a candidate.

A board's bootloader port (``-BL_`` / ``_BL_`` in its name, as MAVProxy skips them) is left out,
and a board that shows two CDC ports (ArduPilot's MAVLink and SLCAN/second MAVLink ports: one
USB serial number) counts once, by its first interface. The candidates are the ports of the best
rank present: one is picked (:func:`find_port`); several are listed and the user is asked to
choose one (:class:`~mavcal.errors.AmbiguousPortError`, its own exit code); none is a
:class:`~mavcal.errors.LinkError` that names the network alternative.
"""
from __future__ import annotations

import fnmatch
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from mavcal.errors import AmbiguousPortError, LinkError

__all__ = ["PortInfo", "find_port", "list_candidates", "rank_port", "AUTOPILOT_VIDS", "RADIO_VIDS",
           "PREFERRED_PATTERNS", "AUTO"]

log = logging.getLogger(__name__)

#: the device string that asks for the port to be found
AUTO = "auto"

#: USB vendor ids (and the product id where the vendor makes other things too) of flight controllers
AUTOPILOT_VIDS: dict[tuple[int, int | None], str] = {
    (0x1209, 0x5740): "ArduPilot",
    (0x1209, 0x5741): "ArduPilot",
    (0x2DAE, None): "CubePilot",
    (0x26AC, None): "3D Robotics / PX4",
    (0x3162, None): "Holybro",
    (0x3163, None): "CUAV",
    (0x0483, 0x5740): "STM32 virtual COM port",
}
#: USB-serial chips of telemetry radios (SiK)
RADIO_VIDS: dict[tuple[int, int | None], str] = {
    (0x0403, None): "FTDI",
    (0x10C4, 0xEA60): "Silicon Labs CP210x",
}
#: MAVProxy's ``preferred_ports`` (MAVProxy/modules/mavproxy_link.py), matched without case
PREFERRED_PATTERNS = ("*FTDI*", "*Arduino_Mega_2560*", "*3D*", "*USB_to_UART*", "*Ardu*", "*PX4*", "*Hex_*",
                      "*Holybro_*", "*mRo*", "*FMU*", "*Swift-Flyer*", "*Serial*", "*CubePilot*", "*Qiotek*",
                      "*Sierra*")
_RADIO_WORDS = ("*FTDI*", "*USB_to_UART*", "*CP210*", "*Radio*", "*SiK*")


@dataclass(frozen=True)
class PortInfo:
    """One serial port as pyserial lists it (the fields mavcal uses)."""

    device: str
    description: str = ""
    hwid: str = ""
    vid: int | None = None
    pid: int | None = None
    serial_number: str | None = None
    manufacturer: str | None = None
    product: str | None = None
    location: str | None = None

    @classmethod
    def of(cls, p: Any) -> PortInfo:
        """From a pyserial ``ListPortInfo`` (or anything with its attributes)."""
        return cls(device=str(p.device), description=str(getattr(p, "description", "") or ""),
                   hwid=str(getattr(p, "hwid", "") or ""), vid=getattr(p, "vid", None), pid=getattr(p, "pid", None),
                   serial_number=getattr(p, "serial_number", None), manufacturer=getattr(p, "manufacturer", None),
                   product=getattr(p, "product", None), location=getattr(p, "location", None))

    @property
    def text(self) -> str:
        """Everything that names the port, for the patterns."""
        return " ".join(x for x in (self.device, self.description, self.hwid, self.manufacturer or "",
                                    self.product or "") if x)

    def label(self) -> str:
        """``/dev/ttyACM0 (CubeOrange, 2dae:1016)``."""
        name = self.product or (self.description if self.description not in ("", "n/a", self.device) else "")
        ids = f"{self.vid:04x}:{self.pid or 0:04x}" if self.vid is not None else ""
        inner = ", ".join(x for x in (name, ids) if x)
        return f"{self.device} ({inner})" if inner else self.device


def _vid_match(table: dict[tuple[int, int | None], str], p: PortInfo) -> str | None:
    if p.vid is None:
        return None
    return table.get((p.vid, p.pid)) or table.get((p.vid, None))


def _matches(patterns: Sequence[str], text: str) -> bool:
    low = text.lower()
    return any(fnmatch.fnmatch(low, pat.lower()) for pat in patterns)


def rank_port(p: PortInfo) -> int | None:
    """2: an autopilot, 1: a telemetry radio, 0: another USB serial port, None: not a candidate."""
    if _vid_match(AUTOPILOT_VIDS, p):
        return 2
    if _vid_match(RADIO_VIDS, p) or _matches(_RADIO_WORDS, p.text):
        return 1
    if _matches(PREFERRED_PATTERNS, p.text):
        return 2
    return 0 if p.vid is not None else None


def _is_bootloader(p: PortInfo) -> bool:
    return any(tag in p.text for tag in ("-BL_", "_BL_", "-BL ", "BL_FMU"))


def list_candidates(ports: Sequence[Any] | None = None) -> list[PortInfo]:
    """The ports of the best rank present (sorted by device), one per USB device; ``ports``: pyserial's
    list (default: ``serial.tools.list_ports.comports()``)."""
    if ports is None:
        from serial.tools import list_ports

        ports = list_ports.comports()
    infos = [PortInfo.of(p) for p in ports]
    ranked = [(r, p) for p in infos if not _is_bootloader(p) for r in [rank_port(p)] if r is not None]
    if not ranked:
        return []
    best = max(r for r, _ in ranked)
    chosen = sorted((p for r, p in ranked if r == best), key=lambda p: (p.location or "", p.device))
    seen: set[tuple[Any, ...]] = set()
    out = []
    for p in chosen:  # a board's second CDC port (same USB serial number) counts once
        key = (p.vid, p.pid, p.serial_number) if p.serial_number else (p.device,)
        if key not in seen:
            seen.add(key)
            out.append(p)
    return sorted(out, key=lambda p: p.device)


def find_port(ports: Sequence[Any] | None = None) -> PortInfo:
    """The one serial port that looks like a flight controller (or radio).

    Raises
    ------
    AmbiguousPortError
        Several look alike: the message lists them (choose one with ``--connect``).
    LinkError
        None at all.
    """
    cands = list_candidates(ports)
    if not cands:
        raise LinkError("no serial port that could be a flight controller or a telemetry radio was found: "
                        "plug it in, or name the link with --connect (a port, or udpin:0.0.0.0:14551 behind a "
                        "ground station, docs/live-link.md)")
    if len(cands) > 1:
        raise AmbiguousPortError([c.label() for c in cands])
    log.info("--connect auto: %s", cands[0].label())
    return cands[0]
