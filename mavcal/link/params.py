"""The MAVLink parameter protocol, as ArduPilot implements it (read side).

* :func:`fetch_all_params` (and :func:`download_params`, which also returns a partial table):
  PARAM_REQUEST_LIST, collect PARAM_VALUE by index, then fetch
  the missing indices one by one with PARAM_REQUEST_READ, keeping a small window of
  requests in flight (ArduPilot queues at most 20 read requests and answers 5 per loop).
  Once the count is known the budget grows with it (``per_param_s`` per parameter): a slow or
  lossy link gets time in proportion to the work, and a dead one (nothing heard for
  ``silent_s``) ends the download at once. Names in ``need`` still missing after the index pass
  are also asked for by name.
* :func:`fetch_for_write`: the part of the table a write needs (by name, the whole table only
  when some names do not answer).
* :func:`read_params` / :func:`read_params_by_name`: PARAM_REQUEST_READ by name for a few
  parameters. ArduPilot answers a read by name with ``param_index = -1`` (65535 on the wire).
  For an unknown name ArduPilot up to 4.6 does not answer at all (a name that never answers is
  reported as missing after its attempts); master since PR #31062 (2025-10) answers with
  PARAM_ERROR ``MAV_PARAM_ERROR_DOES_NOT_EXIST``, which ends the reads of that name at once and
  is reported in the vehicle's words.

Values are returned as ``(value, param_type)`` with ``param_type`` a ``MAV_PARAM_TYPE``
(ArduPilot: INT8=2, INT16=4, INT32=6, REAL32=9). ArduPilot sends integers as plain float
values (``MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT``), never byte-wise; PX4 sends them bytewise (the
integer's bytes in the float field), decoded by :meth:`mavcal.link.connection.Link.param_value`.
"""
from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from pymavlink import mavutil

from mavcal.errors import LinkError, UnknownParameterError
from mavcal.link.connection import Link, as_link

__all__ = ["fetch_all_params", "download_params", "ParamDownload", "read_params", "read_params_by_name",
           "NameRead", "ParamTable", "param_error_words", "vehicle_param_error", "fetch_for_write"]

log = logging.getLogger(__name__)

#: name -> (value, MAV_PARAM_TYPE)
ParamTable = dict[str, tuple[float, int]]

_NO_INDEX = 65535


def _param_name(m: Any) -> str:
    name = m.param_id
    if isinstance(name, bytes):
        name = name.decode("ascii", "replace")
    return name.rstrip("\x00")


def param_error_words(code: int) -> str:
    """A PARAM_ERROR code in MAVLink's words: ``"MAV_PARAM_ERROR_DOES_NOT_EXIST (Parameter does not exist)"``."""
    entry = mavutil.mavlink.enums.get("MAV_PARAM_ERROR", {}).get(int(code))
    if entry is None:
        return f"PARAM_ERROR {int(code)}"
    return f"{entry.name} ({entry.description.strip().rstrip('.')})" if entry.description else entry.name


def vehicle_param_error(link: Link, m: Any) -> tuple[str, str] | None:
    """``(name, words)`` of a PARAM_ERROR from the vehicle addressed to us, else None."""
    if not link.is_from_vehicle(m):
        return None
    own = getattr(link.conn.mav, "srcSystem", None)  # None: a fed connection whose owner did not say
    if own is not None and getattr(m, "target_system", 0) not in (0, own):
        return None
    return _param_name(m), param_error_words(int(m.error))


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

    def __init__(self, link: Link, need: Iterable[str] = ()) -> None:
        self.link = link
        self.by_index: dict[int, str] = {}
        self.values: ParamTable = {}
        self.count: int | None = None
        self.last_rx = time.monotonic()
        self.list_sent = float("-inf")
        self.outstanding: dict[int, float] = {}
        self.need = list(dict.fromkeys(need))
        self.named: dict[str, float] = {}  # by-name requests in flight
        self.errors: dict[str, str] = {}  # PARAM_ERROR by name
        self._tokens = [link.add_handler("PARAM_VALUE", self._on_value),
                        link.add_handler("PARAM_ERROR", self._on_error)]

    def _on_value(self, m: Any) -> None:
        if not self.link.is_from_vehicle(m):
            return
        name = _param_name(m)
        self.last_rx = time.monotonic()
        self.values[name] = (self.link.param_value(m), int(m.param_type))
        idx, count = int(m.param_index), int(m.param_count)
        if idx != _NO_INDEX and count > 0 and idx < count:
            self.count = count
            self.by_index[idx] = name

    def _on_error(self, m: Any) -> None:
        hit = vehicle_param_error(self.link, m)
        if hit is not None and hit[0]:
            self.errors[hit[0]] = hit[1]

    def complete(self) -> bool:
        return self.count is not None and len(self.by_index) >= self.count

    def needed_done(self) -> bool:
        """Every name in ``need`` is known (by index or by name) or refused by the vehicle."""
        return all(n in self.values or n in self.errors for n in self.need)

    def request_list(self, now: float) -> None:
        self.link.mav.param_request_list_send(self.link.target_system, self.link.target_component)
        self.list_sent = now

    def _request_index(self, idx: int, now: float) -> None:
        self.link.mav.param_request_read_send(self.link.target_system, self.link.target_component, b"", idx)
        self.outstanding[idx] = now

    def _request_names(self, now: float, retry_s: float, room: int) -> None:
        """PARAM_REQUEST_READ by name for needed names the index pass has not brought."""
        for n in self.need:
            if room <= 0:
                return
            if n in self.values or n in self.errors or now - self.named.get(n, float("-inf")) <= retry_s:
                continue
            self.link.mav.param_request_read_send(self.link.target_system, self.link.target_component,
                                                  n.encode("ascii"), -1)
            self.named[n] = now
            room -= 1

    def step(self, now: float, retry_s: float, window: int) -> None:
        """Repeat the list request while nothing is heard; once the list stream stops, fetch the
        holes by index and the needed names by name, at most ``window`` requests in flight."""
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
        self._request_names(now, retry_s, max(1, window - len(self.outstanding)))

    def table(self) -> ParamTable:
        out = {self.by_index[i]: self.values[self.by_index[i]] for i in sorted(self.by_index)}
        for n in self.need:  # needed names that came by name only
            if n in self.values and n not in out:
                out[n] = self.values[n]
        return out

    def close(self) -> None:
        for t in self._tokens:
            self.link.remove_handler(t)


def download_params(conn: Any, timeout_s: float = 30.0, *, retry_s: float = 0.5, window: int = 10,
                    per_param_s: float = 0.05, silent_s: float = 10.0, need: Iterable[str] = (),
                    until_needed: bool = False) -> ParamDownload:
    """Download the vehicle's parameter table, as far as it gets within its time budget.

    The one parameter download (PARAM_REQUEST_LIST, then PARAM_REQUEST_READ of the missing
    indices, at most ``window`` in flight, each repeated after ``retry_s``); the list request
    is repeated while nothing at all arrives for ``retry_s``. :func:`fetch_all_params` is this
    with an incomplete table as an error.

    Parameters
    ----------
    timeout_s : float
        The budget before the count is known, and the least budget in total.
    per_param_s : float
        Once the vehicle announced ``count`` parameters the budget is
        ``max(timeout_s, per_param_s * count)``: re-requests go on while it lasts.
    silent_s : float
        Give up when the vehicle sent nothing at all for this long (a dead link).
    need : iterable of str
        Names to ask for by name as well when the index pass has not brought them.
    until_needed : bool
        Stop as soon as every name in ``need`` is known (the table may then be partial).

    Raises
    ------
    LinkError
        The connection fails.
    """
    link: Link = as_link(conn)
    dl = _Download(link, need)
    start = time.monotonic()
    deadline = start + timeout_s
    try:
        dl.request_list(time.monotonic())
        while not (dl.complete() or until_needed and bool(dl.need) and dl.needed_done()):
            now = time.monotonic()
            if dl.count is not None:
                deadline = start + max(timeout_s, per_param_s * dl.count)
            if now >= deadline or link.silent_for() > silent_s:
                break
            dl.step(now, retry_s, window)
            link.pump(min(0.02, max(deadline - time.monotonic(), 0.0)))
    finally:
        dl.close()
    out = ParamDownload(dl.table(), dl.count, dl.complete(), time.monotonic() - start)
    log.info("fetched %d of %s parameters in %.2f s", len(out.table), out.count, out.elapsed_s)
    return out


def fetch_all_params(conn: Any, timeout_s: float = 30.0, *, retry_s: float = 0.5,
                     window: int = 10, per_param_s: float = 0.05) -> ParamTable:
    """Download the vehicle's whole parameter table.

    Parameters
    ----------
    conn : Link or pymavlink connection
        A link to the vehicle (a bare pymavlink connection must have seen a HEARTBEAT).
    timeout_s : float
        The least time budget (see :func:`download_params`: it grows with the count).
    retry_s : float
        A request without an answer for this long is sent again; the list request is
        repeated when nothing at all arrives for this long.
    window : int
        At most this many PARAM_REQUEST_READ in flight.
    per_param_s : float
        Budget per announced parameter.

    Returns
    -------
    dict of str to (float, int)
        Every parameter: value and MAV_PARAM_TYPE. Values announced later by the vehicle
        (a PARAM_VALUE echo) replace the listed ones.

    Raises
    ------
    LinkError
        The table is still incomplete when the budget runs out.
    """
    link: Link = as_link(conn)
    dl = download_params(link, timeout_s, retry_s=retry_s, window=window, per_param_s=per_param_s)
    if not dl.complete:
        raise LinkError(dl.describe(link.device, dl.elapsed_s))
    return dl.table


@dataclass(frozen=True)
class NameRead:
    """The outcome of :func:`read_params_by_name`.

    Attributes
    ----------
    values : dict of str to (float, int)
        The names that answered.
    errors : dict of str to str
        Names the vehicle refused with PARAM_ERROR, in its words.
    missing : tuple of str
        Names that neither answered nor were refused (unknown on ArduPilot <= 4.6, or lost).
    """

    values: ParamTable
    errors: dict[str, str]
    missing: tuple[str, ...]


def read_params_by_name(conn: Any, names: Iterable[str], *, timeout_s: float = 1.0, attempts: int = 3,
                        window: int = 10, budget_s: float = 0.0, optional: Iterable[str] = ()) -> NameRead:
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
        Requests per name before giving up on it (at least; see ``budget_s``).
    window : int
        At most this many requests in flight.
    budget_s : float
        Keep asking for a name until ``attempts`` were sent *and* this long has passed.
    optional : iterable of str
        Names (among ``names``) that may not exist: asked for ``attempts`` times only, never
        for the whole ``budget_s`` (ArduPilot up to 4.6 does not answer an unknown name, so
        insisting on it would cost the whole budget on every healthy link).
    """
    link: Link = as_link(conn)
    maybe = set(optional)
    wanted: list[str] = list(dict.fromkeys(names))
    got: ParamTable = {}
    errors: dict[str, str] = {}
    sent_at: dict[str, float] = {}
    tries: dict[str, int] = {n: 0 for n in wanted}
    wanted_set = set(wanted)
    start = time.monotonic()

    def on_value(m: Any) -> None:
        if link.is_from_vehicle(m):
            name = _param_name(m)
            if name in wanted_set and name in sent_at:  # only answers to our requests
                got[name] = (link.param_value(m), int(m.param_type))

    def on_error(m: Any) -> None:
        hit = vehicle_param_error(link, m)
        if hit is not None and hit[0] in wanted_set and hit[0] in sent_at:
            errors[hit[0]] = hit[1]

    def given_up(n: str, now: float) -> bool:
        return tries[n] >= attempts and (n in maybe or now - start >= budget_s)

    tokens = [link.add_handler("PARAM_VALUE", on_value), link.add_handler("PARAM_ERROR", on_error)]
    try:
        while True:
            now = time.monotonic()
            pending = [n for n in wanted if n not in got and n not in errors]
            live = [n for n in pending if n in sent_at and now - sent_at[n] <= timeout_s]
            if all(given_up(n, now) and n not in live for n in pending):
                break
            for n in pending:
                if len(live) >= window:
                    break
                if n in live or given_up(n, now):
                    continue
                link.mav.param_request_read_send(link.target_system, link.target_component,
                                                 n.encode("ascii"), -1)
                sent_at[n] = now
                tries[n] += 1
                live.append(n)
            link.pump(0.01) if not live else link.wait(_all_answered(got, errors, live), 0.02)
    finally:
        for t in tokens:
            link.remove_handler(t)
    missing = tuple(n for n in wanted if n not in got and n not in errors)
    if missing:
        log.debug("no answer for %s", ", ".join(missing))
    return NameRead(got, errors, missing)


def _all_answered(got: ParamTable, errors: dict[str, str], names: list[str]) -> Callable[[], bool]:
    names = list(names)
    return lambda: all(x in got or x in errors for x in names)


def read_params(conn: Any, names: Iterable[str], *, timeout_s: float = 1.0, attempts: int = 3,
                window: int = 10, budget_s: float = 0.0) -> ParamTable:
    """Read a few parameters by name; see :func:`read_params_by_name`.

    Returns
    -------
    dict of str to (float, int)
        The parameters that answered. A name missing from the result did not answer
        (unknown to the vehicle, or the link lost every attempt).
    """
    return read_params_by_name(conn, names, timeout_s=timeout_s, attempts=attempts, window=window,
                               budget_s=budget_s).values


def fetch_for_write(conn: Any, names: Sequence[str], *, context: Sequence[str] = (), timeout_s: float = 1.0,
                    attempts: int = 5, fetch_timeout_s: float = 30.0, budget_s: float = 0.0) -> ParamTable:
    """The part of the vehicle's table a write of ``names`` needs, without a full download when
    the names answer.

    ``names`` (and ``context``, optional names such as device ids and limits) are read by name,
    ``names`` for at least ``attempts`` requests and ``budget_s`` seconds each (a lossy link),
    ``context`` for ``attempts`` requests (they may not exist);
    a name the vehicle refuses with PARAM_ERROR is unknown at once. Only when some of ``names``
    do not answer is the table downloaded (re-requesting the holes by index and the names by
    name, with a budget that grows with the count), until they are known or the table is
    complete (then the missing ones do not exist: :func:`write_params` refuses them).

    Raises
    ------
    UnknownParameterError
        The vehicle said (PARAM_ERROR) that some of ``names`` do not exist.
    LinkError
        Some of ``names`` could not be read and the download did not complete.
    """
    link = as_link(conn)
    wanted = list(dict.fromkeys(names))
    extra = [c for c in dict.fromkeys(context) if c not in wanted]
    got = read_params_by_name(link, wanted + extra, timeout_s=timeout_s, attempts=attempts, budget_s=budget_s,
                              optional=extra)
    unknown = [n for n in wanted if n in got.errors]
    if unknown:
        raise UnknownParameterError(unknown)
    table = dict(got.values)
    missing = [n for n in wanted if n not in table]
    if not missing:
        return table
    log.info("%d names did not answer by name; downloading the table", len(missing))
    dl = download_params(link, fetch_timeout_s, retry_s=max(timeout_s / 2, 0.2), need=missing, until_needed=True)
    table.update(dl.table)
    still = [n for n in missing if n not in table]
    if still and not dl.complete:
        raise LinkError(f"{link.device}: no answer reading {', '.join(still)}; "
                        + dl.describe(link.device, dl.elapsed_s).split(": ", 1)[1] + " (nothing was written)")
    return table
