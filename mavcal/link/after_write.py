"""A write to a PX4 paced around its parameter saves, and the check after any write that the
vehicle still streams (issue 35, item 8; used by :mod:`mavcal.link.writer`).

* :class:`Px4Pacing` -- before each PARAM_SET to a PX4, waits out a save its autosave is predicted
  to run (PX4's model's ``autosave``): no parameter changes while PX4 exports and verifies its file.
* :class:`StreamCheck` -- after a complete write (and, on a PX4, after the save of its last
  change), the vehicle must be heard again within :data:`STREAM_CHECK_S`: its IMU messages if they
  streamed during the write, else any message (a HEARTBEAT comes every second). A vehicle that went
  silent after a write (PX4 after a failed parameter save) is never reported written and fine:
  :class:`~mavcal.errors.LinkError` says so.
"""
from __future__ import annotations

import logging
import time
import weakref

from mavcal.autopilot import model_named
from mavcal.errors import LinkError
from mavcal.link.connection import Link

__all__ = ["STREAM_CHECK_S", "IMU_TYPES", "Px4Pacing", "StreamCheck"]

log = logging.getLogger(__name__)

#: seconds within which the vehicle must be heard again after a write
STREAM_CHECK_S = 3.0
#: the messages that say the vehicle still streams its sensors
IMU_TYPES = frozenset(("RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3", "HIGHRES_IMU"))
#: time.monotonic() of mavcal's last PARAM_SET to a PX4, per link (the start of its save schedule)
_LAST_CHANGE: weakref.WeakKeyDictionary[Link, float] = weakref.WeakKeyDictionary()


class Px4Pacing:
    """PARAM_SETs to one PX4 kept out of its predicted parameter saves (PX4's model's ``autosave``)."""

    def __init__(self, link: Link) -> None:
        self.link = link
        saves = model_named("PX4").autosave(_LAST_CHANGE.get(link, time.monotonic()))
        assert saves is not None  # PX4 saves by a schedule
        self.saves = saves

    def before_send(self) -> None:
        """Wait out a predicted save, then count the PARAM_SET about to go as a change."""
        wait = self.saves.wait_s(time.monotonic())
        if wait > 0:
            log.debug("waiting %.2f s for PX4's parameter save", wait)
            self.link.pump(wait)
        now = time.monotonic()
        self.saves.changed(now)
        _LAST_CHANGE[self.link] = now

    def wait_saved(self) -> None:
        """Wait until the save of the last change has run."""
        by = self.saves.saved_by_s()
        if by is not None:
            self.link.pump(max(0.0, by - time.monotonic()))


class StreamCheck:
    """Notes the message types the vehicle sends during a write; :meth:`check` afterwards."""

    def __init__(self, link: Link) -> None:
        self.link = link
        self.heard: set[str] = set()
        self._token = link.add_handler("*", self._on)

    def _on(self, m) -> None:
        if self.link.is_from_vehicle(m):
            self.heard.add(m.get_type())

    def close(self) -> None:
        self.link.remove_handler(self._token)

    def check(self, written: int, backup: str, px4: Px4Pacing | None) -> None:
        """Raise LinkError unless the vehicle sends, within :data:`STREAM_CHECK_S` (on a PX4 after the
        save of the last change), one of the IMU messages it sent during the write, or any message when
        it sent none."""
        if px4 is not None:
            px4.wait_saved()
        imu = self.heard & IMU_TYPES
        self.heard = set()
        if self.link.wait(lambda: bool(self.heard & imu) if imu else bool(self.heard), STREAM_CHECK_S):
            return
        what = "/".join(sorted(imu)) if imu else "any message"
        saved = " after its parameter save" if px4 is not None else ""
        raise LinkError(f"{written} parameters written and verified, but then the vehicle stopped sending ({what}: "
                        f"nothing for {STREAM_CHECK_S:g} s{saved}): check it before flying (power-cycle it); the "
                        f"old values are in {backup}")
