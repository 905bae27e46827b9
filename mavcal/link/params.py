"""The MAVLink parameter protocol, as ArduPilot implements it (read side).

* :func:`fetch_all_params` (and :func:`download_params`, which also returns a partial table):
  PARAM_REQUEST_LIST, collect PARAM_VALUE by index, then fetch
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
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from mavcal.errors import LinkError
from mavcal.link.connection import Link, as_link

__all__ = ["fetch_all_params", "download_params", "ParamDownload", "read_params", "ParamTable"]

log = logging.getLogger(__name__)

#: name -> (value, MAV_PARAM_TYPE)
ParamTable = dict[str, tuple[float, int]]

_NO_INDEX = 65535


def _param_name(m: Any) -> str:
    name = m.param_id
    if isinstance(name, bytes):
        name = name.decode("ascii", "replace")
    return name.rstrip("\x00")


@dataclass(frozen=True)
class ParamDownload:
    """The outcome of :func:`download_params`.

    Attributes
    ----------
    table : dict of str to (float, int)
        The parameters received by index, in index order: value and MAV_PARAM_TYPE (a later
        PARAM_VALUE echo replaces the listed value).
    count : int or None
        How many parameters the vehicle announced (None: no PARAM_VALUE at all).
    complete : bool
        Every announced index was received.
    elapsed_s : float
    """

    table: ParamTable
    count: int | None
    complete: bool
    elapsed_s: float

    def describe(self, device: str, timeout_s: float) -> str:
        """``"DEVICE: parameter download incomplete after T s (GOT of COUNT)"``."""
        count = self.count if self.count is not None else "?"
        return f"{device}: parameter download incomplete after {timeout_s:g} s ({len(self.table)} of {count})"


class _Download:
    """State of one download: PARAM_VALUE by index, and the read requests in flight."""

    def __init__(self, link: Link) -> None:
        self.link = link
        self.by_index: dict[int, str] = {}
        self.values: ParamTable = {}
        self.count: int | None = None
        self.last_rx = time.monotonic()
        self.list_sent = float("-inf")
        self.outstanding: dict[int, float] = {}
        self._token = link.add_handler("PARAM_VALUE", self._on_value)

    def _on_value(self, m: Any) -> None:
        if not self.link.is_from_vehicle(m):
            return
        name = _param_name(m)
        self.last_rx = time.monotonic()
        self.values[name] = (float(m.param_value), int(m.param_type))
        idx, count = int(m.param_index), int(m.param_count)
        if idx != _NO_INDEX and count > 0 and idx < count:
            self.count = count
            self.by_index[idx] = name

    def complete(self) -> bool:
        return self.count is not None and len(self.by_index) >= self.count

    def request_list(self, now: float) -> None:
        self.link.mav.param_request_list_send(self.link.target_system, self.link.target_component)
        self.list_sent = now

    def _request_index(self, idx: int, now: float) -> None:
        self.link.mav.param_request_read_send(self.link.target_system, self.link.target_component, b"", idx)
        self.outstanding[idx] = now

    def step(self, now: float, retry_s: float, window: int) -> None:
        """Repeat the list request while nothing is heard; once the list stream stops, fetch the holes."""
        if self.count is None:
            if now - max(self.last_rx, self.list_sent) > retry_s:
                self.request_list(now)
            return
        if not (now - self.last_rx > retry_s / 2 or self.outstanding):
            return  # the list is still streaming in
        for idx in [i for i in self.outstanding if i in self.by_index]:
            del self.outstanding[idx]
        for idx, t in list(self.outstanding.items()):
            if now - t > retry_s:
                self._request_index(idx, now)
        for idx in range(self.count):
            if len(self.outstanding) >= window:
                break
            if idx not in self.by_index and idx not in self.outstanding:
                self._request_index(idx, now)

    def table(self) -> ParamTable:
        return {self.by_index[i]: self.values[self.by_index[i]] for i in sorted(self.by_index)}

    def close(self) -> None:
        self.link.remove_handler(self._token)


def download_params(conn: Any, timeout_s: float = 30.0, *, retry_s: float = 0.5, window: int = 10) -> ParamDownload:
    """Download the vehicle's parameter table, as far as it gets within ``timeout_s``.

    The one parameter download (PARAM_REQUEST_LIST, then PARAM_REQUEST_READ of the missing
    indices, at most ``window`` in flight, each repeated after ``retry_s``); the list request
    is repeated while nothing at all arrives for ``retry_s``. :func:`fetch_all_params` is this
    with an incomplete table as an error.

    Raises
    ------
    LinkError
        The connection fails.
    """
    link: Link = as_link(conn)
    dl = _Download(link)
    start = time.monotonic()
    deadline = start + timeout_s
    try:
        dl.request_list(time.monotonic())
        while not dl.complete():
            now = time.monotonic()
            if now >= deadline:
                break
            dl.step(now, retry_s, window)
            link.pump(min(0.02, max(deadline - time.monotonic(), 0.0)))
    finally:
        dl.close()
    out = ParamDownload(dl.table(), dl.count, dl.complete(), time.monotonic() - start)
    log.info("fetched %d of %s parameters in %.2f s", len(out.table), out.count, out.elapsed_s)
    return out


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
    dl = download_params(link, timeout_s, retry_s=retry_s, window=window)
    if not dl.complete:
        raise LinkError(dl.describe(link.device, timeout_s))
    return dl.table


def _all_answered(got: ParamTable, names: list[str]) -> Callable[[], bool]:
    names = list(names)
    return lambda: all(x in got for x in names)


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
    wanted: list[str] = list(dict.fromkeys(names))
    got: ParamTable = {}
    sent_at: dict[str, float] = {}
    tries: dict[str, int] = {n: 0 for n in wanted}
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
            link.pump(0.01) if not live else link.wait(_all_answered(got, live), 0.02)
    finally:
        link.remove_handler(token)
    missing = [n for n in wanted if n not in got]
    if missing:
        log.debug("no answer for %s", ", ".join(missing))
    return got
