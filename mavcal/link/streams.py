"""The one place that asks a vehicle for message rates.

ArduPilot streams the IMU messages a calibration needs (RAW_IMU, SCALED_IMU2, SCALED_IMU3)
at the rate asked for with ``MAV_CMD_SET_MESSAGE_INTERVAL`` (param1 message id, param2
interval in us; 0 = the default rate). Older firmware, or a vehicle behind a router that
drops commands, only knows ``REQUEST_DATA_STREAM`` (``MAV_DATA_STREAM_RAW_SENSORS``):
:func:`start_streams` falls back to it when the interval is not acknowledged or gives no
data.

:func:`send_message_intervals` only sends (it works on any encoder with ``command_long_send``,
including :class:`mavcal.link.fed.QueuedSender` whose owner sends later), so the MAVProxy
module, which does not own its read loop, uses it too.
"""
from __future__ import annotations

import logging
import time
from collections.abc import Mapping, Sequence
from typing import Any

from pymavlink import mavutil

from mavcal.errors import LinkError
from mavcal.link.connection import Link

__all__ = ["STREAM_MESSAGES", "STREAM_MESSAGE_IDS", "PX4_STREAM_MESSAGES", "MIN_STREAM_RATE_HZ",
           "send_message_intervals", "start_streams", "reset_streams", "needed_stream_ids", "message_name"]

log = logging.getLogger(__name__)

_A = mavutil.mavlink

#: the IMU messages a capture streams: name -> MAVLink message id
STREAM_MESSAGES: dict[str, int] = {"RAW_IMU": _A.MAVLINK_MSG_ID_RAW_IMU,
                                   "SCALED_IMU2": _A.MAVLINK_MSG_ID_SCALED_IMU2,
                                   "SCALED_IMU3": _A.MAVLINK_MSG_ID_SCALED_IMU3}
STREAM_MESSAGE_IDS: tuple[int, ...] = tuple(STREAM_MESSAGES.values())
#: what a PX4 streams for a capture (it refuses RAW_IMU): SCALED_IMU* carry the calibrated, rotated
#: accelerometer and the raw magnetometer, HIGHRES_IMU the calibrated magnetometer
PX4_STREAM_MESSAGES: dict[str, int] = {"SCALED_IMU": _A.MAVLINK_MSG_ID_SCALED_IMU,
                                       "SCALED_IMU2": _A.MAVLINK_MSG_ID_SCALED_IMU2,
                                       "SCALED_IMU3": _A.MAVLINK_MSG_ID_SCALED_IMU3,
                                       "HIGHRES_IMU": _A.MAVLINK_MSG_ID_HIGHRES_IMU}


def message_name(message_id: int) -> str:
    """The MAVLink name of a message id (pymavlink's table), e.g. ``"SCALED_IMU"``."""
    return _A.mavlink_map[int(message_id)].msgname


#: :func:`start_streams` never asks for less (the still-interval detector needs the samples)
MIN_STREAM_RATE_HZ = 25.0


def needed_stream_ids(params: Mapping[str, float] | None) -> tuple[int, ...]:
    """The IMU messages worth asking for on a vehicle with the parameter table ``params``.

    Message k carries IMU k and compass slot k (RAW_IMU: 0, SCALED_IMU2: 1, SCALED_IMU3: 2).
    RAW_IMU is always asked for; SCALED_IMU2/3 only when that IMU (``INS_ACCn_ID``) or that
    compass slot (``COMPASS_DEV_IDn``) has a device, or when the table does not say (a name
    missing: asked for, to be safe). Asking for a message of a sensor the board does not have
    changes nothing but costs a COMMAND_ACK, which MAVProxy prints.
    """
    if params is None:
        return STREAM_MESSAGE_IDS
    from mavcal.autopilot import is_px4_params, model_named
    from mavcal.sources.types import ImuLog

    if is_px4_params(params):  # a PX4: no RAW_IMU (refused), SCALED_IMU* and HIGHRES_IMU
        return tuple(PX4_STREAM_MESSAGES.values())
    out = []
    ardupilot, no_log = model_named("ArduPilot"), ImuLog(source="", kind="live", series=())
    for k, mid in enumerate(STREAM_MESSAGE_IDS):
        ids = list(ardupilot.device_ids(no_log, params, k, k))  # the IMU's and the compass slot's device ids
        if k == 0 or any(v is None or int(v) != 0 for v in ids):
            out.append(mid)
    return tuple(out)


def send_message_intervals(mav: Any, target_system: int, target_component: int, rate_hz: float | None,
                           message_ids: Sequence[int] = STREAM_MESSAGE_IDS) -> None:
    """Send one SET_MESSAGE_INTERVAL per message: ``rate_hz`` (at least 1 Hz), or None: the default rate.

    ``mav`` is a pymavlink encoder (``conn.mav``) or anything with its ``command_long_send``.
    """
    interval_us = 0 if rate_hz is None else int(round(1e6 / max(float(rate_hz), 1.0)))
    for mid in message_ids:
        mav.command_long_send(target_system, target_component, _A.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                              mid, interval_us, 0, 0, 0, 0, 0)


class _StreamWatch:
    """Counts SET_MESSAGE_INTERVAL acks and RAW_IMU messages (a PX4's SCALED_IMU) from the vehicle
    while registered."""

    def __init__(self, link: Link) -> None:
        self.link = link
        self.acks: list[int] = []
        self.raw_imu = 0
        data = "SCALED_IMU" if link.bytewise_params else "RAW_IMU"
        self._tokens = [link.add_handler("COMMAND_ACK", self._on_ack), link.add_handler(data, self._on_imu)]

    def _on_ack(self, m: Any) -> None:
        if m.get_srcSystem() == self.link.target_system and m.command == _A.MAV_CMD_SET_MESSAGE_INTERVAL:
            self.acks.append(int(m.result))

    def _on_imu(self, m: Any) -> None:
        if m.get_srcSystem() == self.link.target_system:
            self.raw_imu += 1

    def wait_data(self, rate_hz: float, timeout_s: float) -> bool:
        """Wait until 0.2 s worth of RAW_IMU at ``rate_hz`` (at least 2) arrived."""
        n0, need = self.raw_imu, max(2, int(rate_hz * 0.2))
        return self.link.wait(lambda: self.raw_imu - n0 >= need, timeout_s)

    def close(self) -> None:
        for t in self._tokens:
            self.link.remove_handler(t)


def _ask_intervals(link: Link, watch: _StreamWatch, rate_hz: float, message_ids: Sequence[int],
                   ack_timeout_s: float, until: float) -> str:
    """SET_MESSAGE_INTERVAL one message at a time (a COMMAND_ACK does not say which message it
    answers), each sent again every ``ack_timeout_s`` until acknowledged or ``until``.

    Returns ``"accepted"`` (every one), ``"refused"`` (an ack other than accepted) or
    ``"unanswered"``.
    """
    for mid in message_ids:
        while True:
            n0 = len(watch.acks)
            send_message_intervals(link.mav, link.target_system, link.target_component, rate_hz, (mid,))
            if link.wait(lambda n0=n0: len(watch.acks) > n0, ack_timeout_s):
                if watch.acks[n0] != _A.MAV_RESULT_ACCEPTED:
                    return "refused"
                break
            if time.monotonic() >= until:
                return "unanswered"
    return "accepted"


def start_streams(link: Link, rate_hz: float = 50.0, *, ack_timeout_s: float = 1.0,
                  data_timeout_s: float = 2.0, message_ids: Sequence[int] = STREAM_MESSAGE_IDS,
                  budget_s: float = 0.0) -> str:
    """Ask for RAW_IMU, SCALED_IMU2 and SCALED_IMU3 (``message_ids``, e.g. :func:`needed_stream_ids`)
    at ``rate_hz`` (at least 25 Hz) and check data comes.

    Uses MAV_CMD_SET_MESSAGE_INTERVAL, one message at a time, each sent again every
    ``ack_timeout_s`` while no COMMAND_ACK comes back, and the whole request again while no
    RAW_IMU follows within ``data_timeout_s``, for up to a third of ``budget_s`` (at least one
    round); falls back to REQUEST_DATA_STREAM (MAV_DATA_STREAM_RAW_SENSORS) when it is refused,
    never acknowledged, or gives no RAW_IMU. The fallback request is repeated every
    ``data_timeout_s`` until data comes or the budget (at least one ``data_timeout_s``) is
    spent: on a lossy link each request may be lost, as may the first answers.

    Returns
    -------
    str
        ``"interval"`` or ``"data_stream"``.

    Raises
    ------
    LinkError
        No RAW_IMU even after the fallback.
    """
    rate_hz = max(float(rate_hz), MIN_STREAM_RATE_HZ)
    watch = _StreamWatch(link)
    start = time.monotonic()
    try:
        while True:
            outcome = _ask_intervals(link, watch, rate_hz, message_ids, ack_timeout_s, start + budget_s / 3)
            if outcome == "accepted" and watch.wait_data(rate_hz, data_timeout_s):
                return "interval"
            if outcome == "refused" or time.monotonic() >= start + budget_s / 3:
                break
        log.info("SET_MESSAGE_INTERVAL %s; falling back to REQUEST_DATA_STREAM",
                 {"accepted": "gave no data", "refused": "not accepted"}.get(outcome, "not acknowledged"))
        end = max(start + budget_s, time.monotonic() + data_timeout_s)
        while True:
            link.mav.request_data_stream_send(link.target_system, link.target_component,
                                              _A.MAV_DATA_STREAM_RAW_SENSORS, int(round(rate_hz)), 1)
            if watch.wait_data(1.0, min(data_timeout_s, max(end - time.monotonic(), 0.0))):
                return "data_stream"
            if time.monotonic() >= end:
                raise LinkError(f"no RAW_IMU data from {link.device} after requesting it")
    finally:
        watch.close()


def reset_streams(link: Link, message_ids: Sequence[int] = STREAM_MESSAGE_IDS, *, attempts: int = 3,
                  ack_timeout_s: float = 0.3) -> None:
    """Give the IMU messages back their default rates (best effort: the link may be dead or
    lossy; asked up to ``attempts`` times until every request is acknowledged)."""
    try:
        watch = _StreamWatch(link)
        try:
            for _ in range(max(1, attempts)):
                n0 = len(watch.acks)
                send_message_intervals(link.mav, link.target_system, link.target_component, None, message_ids)
                if link.wait(lambda n0=n0: len(watch.acks) - n0 >= len(message_ids), ack_timeout_s):
                    return
        finally:
            watch.close()
    except Exception as exc:  # a dead socket, a closed connection: nothing to restore
        log.debug("could not reset the stream rates: %s", exc)
