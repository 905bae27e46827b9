"""The MAVLink parameter protocol, as ArduPilot implements it (read side).

* :func:`fetch_all_params`: PARAM_REQUEST_LIST, collect PARAM_VALUE by index, then fetch
  the missing indices one by one with PARAM_REQUEST_READ, keeping a small window of
  requests in flight (ArduPilot queues at most 20 read requests and answers 5 per loop).
* :func:`read_params`: PARAM_REQUEST_READ by name for a few parameters. ArduPilot answers a
  read by name with ``param_index = -1`` (65535 on the wire) and does not answer at all for an
  unknown name, so a name that never answers is reported as missing after its attempts.

Values are returned as ``(value, param_type)`` with ``param_type`` a ``MAV_PARAM_TYPE``
(ArduPilot: INT8=2, INT16=4, INT32=6, REAL32=9). ArduPilot sends integers as plain float
values (``MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT``), never byte-wise.
"""
from __future__ import annotations

import logging
import time
from typing import Any, Dict, Iterable, List, Tuple

from mavcal.errors import LinkError
from mavcal.link.connection import Link, as_link

__all__ = ["fetch_all_params", "read_params", "ParamTable"]

log = logging.getLogger(__name__)

#: name -> (value, MAV_PARAM_TYPE)
ParamTable = Dict[str, Tuple[float, int]]

_NO_INDEX = 65535


def _param_name(m: Any) -> str:
    name = m.param_id
    if isinstance(name, bytes):
        name = name.decode("ascii", "replace")
    return name.rstrip("\x00")


def fetch_all_params(conn: Any, timeout_s: float = 30.0, *, retry_s: float = 0.5,
                     window: int = 10) -> ParamTable:
    """Download the vehicle's whole parameter table.

    Parameters
    ----------
    conn : Link or pymavlink connection
        A link to the vehicle (a bare pymavlink connection must have seen a HEARTBEAT).
    timeout_s : float
        Give up after this long in total.
    retry_s : float
        A request without an answer for this long is sent again; the list request is
        repeated when nothing at all arrives for this long.
    window : int
        At most this many PARAM_REQUEST_READ in flight.

    Returns
    -------
    dict of str to (float, int)
        Every parameter: value and MAV_PARAM_TYPE. Values announced later by the vehicle
        (a PARAM_VALUE echo) replace the listed ones.

    Raises
    ------
    LinkError
        The table is still incomplete after ``timeout_s``.
    """
    link: Link = as_link(conn)
    by_index: Dict[int, str] = {}
    values: ParamTable = {}
    state = {"count": None, "last_rx": time.monotonic()}

    def on_value(m: Any) -> None:
        if not link.is_from_vehicle(m):
            return
        name = _param_name(m)
        state["last_rx"] = time.monotonic()
        values[name] = (float(m.param_value), int(m.param_type))
        idx, count = int(m.param_index), int(m.param_count)
        if idx != _NO_INDEX and count > 0 and idx < count:
            state["count"] = count
            by_index[idx] = name

    token = link.add_handler("PARAM_VALUE", on_value)
    start = time.monotonic()
    deadline = start + timeout_s
    outstanding: Dict[int, float] = {}
    list_sent = 0.0
    try:
        link.mav.param_request_list_send(link.target_system, link.target_component)
        list_sent = time.monotonic()
        while True:
            now = time.monotonic()
            count = state["count"]
            if count is not None and len(by_index) >= count:
                break
            if now >= deadline:
                got = len(by_index)
                raise LinkError(f"{link.device}: parameter download incomplete after {timeout_s:g} s "
                                f"({got} of {count if count is not None else '?'})")
            if count is None:
                # nothing heard yet: repeat the list request when quiet
                if now - max(state["last_rx"], list_sent) > retry_s:
                    link.mav.param_request_list_send(link.target_system, link.target_component)
                    list_sent = now
            elif now - state["last_rx"] > retry_s / 2 or outstanding:
                # the list stream has stopped (or we are already filling holes)
                for idx in [i for i in outstanding if i in by_index]:
                    del outstanding[idx]
                for idx, t in list(outstanding.items()):
                    if now - t > retry_s:
                        link.mav.param_request_read_send(link.target_system, link.target_component, b"", idx)
                        outstanding[idx] = now
                for idx in range(count):
                    if len(outstanding) >= window:
                        break
                    if idx not in by_index and idx not in outstanding:
                        link.mav.param_request_read_send(link.target_system, link.target_component, b"", idx)
                        outstanding[idx] = now
            link.pump(min(0.02, max(deadline - time.monotonic(), 0.0)))
    finally:
        link.remove_handler(token)
    names = [by_index[i] for i in range(state["count"] or 0)]
    log.info("fetched %d parameters in %.2f s", len(names), time.monotonic() - start)
    return {n: values[n] for n in names}


def read_params(conn: Any, names: Iterable[str], *, timeout_s: float = 1.0, attempts: int = 3,
                window: int = 10) -> ParamTable:
    """Read a few parameters by name (PARAM_REQUEST_READ), in parallel, with retries.

    Parameters
    ----------
    conn : Link or pymavlink connection
        A link to the vehicle.
    names : iterable of str
        Parameters to read.
    timeout_s : float
        Wait this long for each answer before asking again.
    attempts : int
        Requests per name before giving up on it.
    window : int
        At most this many requests in flight.

    Returns
    -------
    dict of str to (float, int)
        The parameters that answered. A name missing from the result did not answer
        (unknown to the vehicle, or the link lost every attempt).
    """
    link: Link = as_link(conn)
    wanted: List[str] = list(dict.fromkeys(names))
    got: ParamTable = {}
    sent_at: Dict[str, float] = {}
    tries: Dict[str, int] = {n: 0 for n in wanted}
    wanted_set = set(wanted)

    def on_value(m: Any) -> None:
        if link.is_from_vehicle(m):
            name = _param_name(m)
            if name in wanted_set and name in sent_at:  # only answers to our requests
                got[name] = (float(m.param_value), int(m.param_type))

    token = link.add_handler("PARAM_VALUE", on_value)
    try:
        while True:
            now = time.monotonic()
            pending = [n for n in wanted if n not in got]
            live = [n for n in pending if n in sent_at and now - sent_at[n] <= timeout_s]
            exhausted = [n for n in pending if tries[n] >= attempts and n not in live]
            if len(exhausted) == len(pending):
                break
            for n in pending:
                if len(live) >= window:
                    break
                if n in live or tries[n] >= attempts:
                    continue
                link.mav.param_request_read_send(link.target_system, link.target_component,
                                                 n.encode("ascii"), -1)
                sent_at[n] = now
                tries[n] += 1
                live.append(n)
            link.pump(0.01) if not live else link.wait(lambda: all(x in got for x in live), 0.02)
    finally:
        link.remove_handler(token)
    missing = [n for n in wanted if n not in got]
    if missing:
        log.debug("no answer for %s", ", ".join(missing))
    return got
