"""The backup a write makes before its first PARAM_SET, and its default file name."""
from __future__ import annotations

import datetime as _dt
import logging
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

from mavcal.autopilot.paramfile import write_param_file
from mavcal.link.connection import Link

__all__ = ["write_backup", "default_backup_path"]

log = logging.getLogger(__name__)


def _default_header(link: Link) -> list[str]:
    now = _dt.datetime.now().astimezone().isoformat(timespec="seconds")
    return [f"mavcal backup: values on system {link.target_system} before the write, {now}",
            f"undo with: mavcal restore THIS_FILE --connect {link.device}"]


def write_backup(link: Link, backup_path: str, old: Mapping[str, float], header: Sequence[str] | None) -> Path:
    """The backup of every value about to change (``old``), written and fsync'ed (never over an existing file)."""
    bpath = write_param_file(backup_path, dict(old), header=list(header) if header is not None
                             else _default_header(link), exclusive=True)
    log.info("backup of %d values written to %s", len(old), bpath)
    return Path(bpath)


def default_backup_path(directory: str = ".", stem: str = "mavcal-backup") -> Path:
    """A new, not yet existing backup file name ``<stem>-YYYYmmdd-HHMMSS[-n].param``."""
    ts = time.strftime("%Y%m%d-%H%M%S")
    base = Path(directory) / f"{stem}-{ts}.param"
    n = 1
    p = base
    while p.exists():
        p = base.with_name(f"{stem}-{ts}-{n}.param")
        n += 1
    return p
