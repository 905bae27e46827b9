"""When a vehicle counts as silent during a write, measured on the link rather than assumed.

A vehicle that only sends its 1 Hz HEARTBEAT falls silent for seconds on a lossy radio by
chance alone (30 % loss: 3 s without a message about once a minute), so a fixed silence limit
either fails good writes or waits too long for a dead vehicle. :class:`VehicleSilence` does two
things for the length of a write:

* **keeps the vehicle talking**: it asks for ATTITUDE at :data:`KEEPALIVE_RATE_HZ` with
  MAV_CMD_SET_MESSAGE_INTERVAL (the request of :mod:`mavcal.link.streams`, asked again while the
  vehicle is silent: a rebooted vehicle forgets it) and gives the message back its default rate
  at the end (:func:`~mavcal.link.streams.reset_streams`). ATTITUDE exists on every ArduPilot
  vehicle, is small (28 bytes) and is not one of the IMU messages a capture streams.
* **measures the link**: the fraction ``p`` of the vehicle's messages lost since the link
  opened, from the gaps in their MAVLink sequence numbers (:class:`~mavcal.link.connection.Link`
  counts them; a duplicate or a reordered message is not counted), and the rate ``r`` at which
  the vehicle sends its periodic messages (HEARTBEAT and ATTITUDE: per type, one over the median
  time between its last 16 arrivals, which is the send period while less than half are lost).
  With independent losses the vehicle's next ``n`` periodic messages are all lost with
  probability ``p**n``; the **silence limit** is the time ``n / r`` of the smallest ``n`` with
  ``p**n <`` :data:`SILENCE_FALSE_ALARM` (1e-6), never under :data:`MIN_SILENCE_S`. ``p`` is
  estimated as ``(lost + 1) / (lost + received + 2)`` (it never reads 0 on a short sample) and
  capped at :data:`MAX_LOSS`; until three arrived, the HEARTBEAT counts 1 Hz (ArduPilot's) and
  ATTITUDE nothing. Examples: 30 % loss, ATTITUDE at 5 Hz and the heartbeat: 12 messages,
  2.0 s; heartbeats alone: 12 s; 5 % loss: 5 messages, 1.0 s (the floor). Before its first
  PARAM_SET the write waits (at most :data:`SETTLE_S`) for the stream to flow. A vehicle that
  already sends HEARTBEAT/ATTITUDE at 10 Hz or more is asked nothing (and nothing is put back).

A silence longer than the limit is waited out (:meth:`VehicleSilence.wait_heard`, nothing sent)
up to an allowance the caller states (:class:`Patience`: the time spent waiting, in all), and
counts whole (:meth:`VehicleSilence.unheard_s`) when the writer measures a parameter's budget:
the writer pauses a parameter's attempts and its budget while the vehicle is unheard instead of
failing, resumes when it is heard again, and gives up only when it stays unheard past the
allowance.
"""
from __future__ import annotations

import logging
import math
import time
from typing import Any

import numpy as np
from pymavlink import mavutil

from mavcal.errors import LinkError
from mavcal.link.connection import Link
from mavcal.link.streams import reset_streams, send_message_intervals

__all__ = ["VehicleSilence", "Patience", "silence_limit_s", "SILENCE_FALSE_ALARM", "KEEPALIVE_RATE_HZ", "MIN_SILENCE_S",
           "MAX_LOSS", "KEEPALIVE_MESSAGE_ID", "SETTLE_S"]

log = logging.getLogger(__name__)

_A = mavutil.mavlink

#: probability that a talking vehicle's periodic messages are all lost for the silence limit
SILENCE_FALSE_ALARM = 1e-6
#: the rate asked for ATTITUDE during a write
KEEPALIVE_RATE_HZ = 5.0
KEEPALIVE_MESSAGE_ID = _A.MAVLINK_MSG_ID_ATTITUDE
#: the silence limit is never shorter (the vehicle's own scheduling jitter)
MIN_SILENCE_S = 1.0
#: the loss estimate is capped here (a link that loses more is not a link)
MAX_LOSS = 0.95
#: ArduPilot's heartbeat rate: the rate assumed before it is measured
_HEARTBEAT_HZ = 1.0
#: the keepalive request is sent again this often while nothing comes
_ASK_PERIOD_S = 0.5
#: requests at most while the vehicle talks but sends no ATTITUDE
_MAX_ASKS = 10
#: a vehicle whose periodic messages already flow this fast is asked nothing (twice the
#: keepalive's rate: a vehicle near that rate is not judged on noise)
_TALKING_HZ = 2 * KEEPALIVE_RATE_HZ
#: the write waits at most this long for the keepalive stream before its first PARAM_SET
SETTLE_S = 3.0


def silence_limit_s(rate_hz: float, loss: float, false_alarm: float = SILENCE_FALSE_ALARM) -> float:
    """Seconds without a message after which a vehicle sending ``rate_hz`` periodic messages over
    a link losing ``loss`` of them (independently) counts as silent: ``n / rate_hz`` for the
    smallest ``n`` with ``loss**n < false_alarm``, at least :data:`MIN_SILENCE_S`."""
    p = min(max(float(loss), 1e-9), MAX_LOSS)
    n = math.floor(math.log(false_alarm) / math.log(p)) + 1
    return max(MIN_SILENCE_S, n / max(float(rate_hz), 1e-3))


class VehicleSilence:
    """The vehicle kept talking and its silence measured, while registered on ``link``.

    Parameters
    ----------
    link : Link
    keepalive : bool
        Ask for ATTITUDE at :data:`KEEPALIVE_RATE_HZ` now, unless the vehicle already sends its
        periodic messages twice as fast (and again while it is silent); :meth:`close`
        gives ATTITUDE back its default rate if it was asked for.
    answer_s : float
        How long to wait for the vehicle to acknowledge that (:func:`~mavcal.link.streams.reset_streams`).
    false_alarm : float
        See :func:`silence_limit_s`.
    """

    def __init__(self, link: Link, *, keepalive: bool = True, answer_s: float = 0.3,
                 false_alarm: float = SILENCE_FALSE_ALARM) -> None:
        self.link = link
        self.keepalive = keepalive
        self.answer_s = answer_s
        self.false_alarm = false_alarm
        #: the keepalive stream was asked for (and is put back at the end)
        self.requested = False
        self._last_rx_s: float | None = None
        self._limit_then = math.inf
        self._closed_unheard_s = 0.0
        #: silences beyond the limit that ended (the vehicle was heard again)
        self.silences = 0
        self._last_ask = float("-inf")
        self._asked = 0
        self._token = link.add_handler("*", self._on)
        self._streaming = False  # ATTITUDE arrived since the last request
        self.attitudes = 0  # ATTITUDE messages received since the start
        if keepalive and self._flowing_hz() < _TALKING_HZ:
            self._ask()

    def _flowing_hz(self) -> float:
        """The rate of the periodic messages that arrived within the last 2 s (a stream going on)."""
        now, total = time.monotonic(), 0.0
        for times in self.link.periodic_rx_s.values():
            if len(times) >= 3 and now - times[-1] < 2.0:
                step = float(np.median(np.diff(np.asarray(times))))
                total += 1.0 / step if step > 0 else 0.0
        return total

    # -- measuring ---------------------------------------------------------------------------
    def _on(self, m: Any) -> None:
        if not self.link.is_from_vehicle(m):
            return
        now = time.monotonic()
        if m.get_type() == "ATTITUDE":
            self._streaming = True
            self.attitudes += 1
        if self._last_rx_s is not None:
            gap = now - self._last_rx_s
            if gap > self._limit_then:  # the limit the gap was judged by while it lasted
                self._closed_unheard_s += gap
                self.silences += 1
                log.info("the vehicle is heard again after %.1f s of silence", gap)
        self._last_rx_s = now
        self._limit_then = self.limit_s()

    def loss(self) -> float:
        """The fraction of the vehicle's messages lost since the link opened:
        ``(lost + 1) / (lost + received + 2)``, at most :data:`MAX_LOSS`."""
        lost, received = self.link.vehicle_lost, self.link.vehicle_received
        return min((lost + 1) / (lost + received + 2), MAX_LOSS)

    def rate_hz(self) -> float:
        """The rate at which the vehicle sends its periodic messages (HEARTBEAT, ATTITUDE): per
        type, one over the median time between its last few arrivals (the send period while
        less than half are lost; a silence in the window is one outlier); a type with fewer
        than three arrivals counts 1 Hz for the HEARTBEAT, nothing for ATTITUDE, and so does a
        type that stopped (none for three of its periods, and 2 s, before the vehicle's last
        message: the keepalive put back after an earlier write)."""
        total = 0.0
        for mtype, times in self.link.periodic_rx_s.items():
            step = float(np.median(np.diff(np.asarray(times)))) if len(times) >= 3 else 0.0
            if step > 0 and self.link.last_rx_s - times[-1] <= max(2.0, 3 * step):
                total += 1.0 / step
            elif mtype == "HEARTBEAT":
                total += _HEARTBEAT_HZ
        return max(_HEARTBEAT_HZ, total)

    def limit_s(self) -> float:
        """The silence limit now (:func:`silence_limit_s` of the measured rate and loss)."""
        return silence_limit_s(self.rate_hz(), self.loss(), self.false_alarm)

    def silent(self) -> bool:
        """True when the vehicle has sent nothing for longer than the silence limit."""
        return self.link.silent_for() > self.limit_s()

    def unheard_s(self) -> float:
        """Seconds the vehicle was silent, counting the silences longer than the limit whole
        (those that ended and the one going on)."""
        quiet = self.link.silent_for()
        return self._closed_unheard_s + (quiet if quiet > self.limit_s() else 0.0)

    def describe(self) -> str:
        """``"silence limit 2.0 s: 5.8 messages/s, 31 % lost"``."""
        return f"silence limit {self.limit_s():.1f} s: {self.rate_hz():.1f} messages/s, {100 * self.loss():.0f} % lost"

    # -- waiting -----------------------------------------------------------------------------
    def settle(self, max_s: float) -> bool:
        """When the keepalive stream was asked for: wait until it flows (an ATTITUDE received),
        asking again every :data:`_ASK_PERIOD_S`, for at most ``max_s``. True when it flows."""
        if not self.requested:
            return False
        end = time.monotonic() + max_s
        while not self.attitudes and time.monotonic() < end:
            self.tend()
            self.link.wait(lambda: self.attitudes > 0, min(0.1, max(end - time.monotonic(), 0.0)))
        log.info("%s", self.describe())
        return self.attitudes > 0

    def tend(self) -> None:
        """Ask for the keepalive stream again when it has not started half a second after the last
        request (the request or its answer lost; at most :data:`_MAX_ASKS` times while nothing
        comes: a vehicle that does not stream ATTITUDE is left alone)."""
        if (self.requested and not self._streaming and self._asked < _MAX_ASKS
                and time.monotonic() - self._last_ask >= _ASK_PERIOD_S):
            self._ask()

    def _ask(self) -> None:
        self.requested = True
        self._last_ask = time.monotonic()
        self._asked += 1
        self._streaming = False
        try:
            send_message_intervals(self.link.mav, self.link.target_system, self.link.target_component,
                                   KEEPALIVE_RATE_HZ, (KEEPALIVE_MESSAGE_ID,))
        except OSError as exc:  # a socket that cannot send now: the wait goes on
            log.debug("keepalive request not sent: %s", exc)

    def wait_heard(self, max_s: float) -> bool:
        """While the vehicle is silent, wait for it (asking for the keepalive stream again every
        :data:`_ASK_PERIOD_S`) for at most ``max_s``. True once it is heard (or was not
        silent), False when ``max_s`` passed."""
        if not self.silent():
            return True
        log.info("vehicle silent for %.1f s (%s); waiting for it", self.link.silent_for(), self.describe())
        end = time.monotonic() + max_s
        while self.silent():
            if time.monotonic() >= end:
                return False
            if self.keepalive and time.monotonic() - self._last_ask >= _ASK_PERIOD_S:
                self._ask()  # a vehicle back from a reboot forgot the request
            self.link.wait(lambda: not self.silent(), 0.1)
        return True

    def close(self) -> None:
        """Stop measuring; give ATTITUDE back its default rate (best effort) if it was asked for."""
        self.link.remove_handler(self._token)
        if self.requested:
            reset_streams(self.link, (KEEPALIVE_MESSAGE_ID,), attempts=3,
                          ack_timeout_s=min(max(self.answer_s, 0.05), 0.5))

    def __enter__(self) -> VehicleSilence:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Patience:
    """How long a write (or a restore) waits for a silent vehicle: ``allowance_s`` seconds in
    all, spent while it waits (the vehicle silent beyond the limit, nothing sent).

    ``what`` names the waiter in the error (``"the write"``, ``"the restore"``).
    """

    def __init__(self, silence: VehicleSilence, allowance_s: float, what: str) -> None:
        self.silence = silence
        self.allowance_s = float(allowance_s)
        self.what = what
        #: seconds waited so far
        self.waited_s = 0.0

    def until_heard(self) -> None:
        """Return when the vehicle is heard (at once if it is not silent).

        Raises
        ------
        LinkError
            It stayed unheard past the allowance: the message says how long it was silent and
            how long the waiter waits.
        """
        self.silence.tend()
        t0 = time.monotonic()
        heard = self.silence.wait_heard(self.allowance_s - self.waited_s)
        self.waited_s += time.monotonic() - t0
        if not heard:
            link = self.silence.link
            raise LinkError(f"{link.device}: vehicle unheard for {link.silent_for():.1f} s ({self.what} waited "
                            f"{self.waited_s:.1f} s for it, its budget {self.allowance_s:g} s; "
                            f"{self.silence.describe()})")
