"""Whole ``mavcal apply`` sessions against the real ArduPilot SITL through lossy relays, each
checked over the fixture's own lossless channel (tests/test_sitl_link.py, benchmarks/apply_loss.py).

:func:`relayed_channels` puts a :class:`~mavcal.testing.relay.LossRelay` on each of a SITL
vehicle's two tool channels (SERIAL1 and SERIAL2, ``relay=True``), in its network namespace;
:func:`run_sessions` runs sessions on the channels at once (one thread per channel: they mostly
wait on the lossy link) with :func:`apply_session`, which writes new values of the channel's
parameters with the CLI's default options and reads them back over SERIAL0: exit 0 must mean
every new value is held, exit 5 every old one, any other exit nothing changed; anything else is
a silent mismatch (``ok`` False).
"""
from __future__ import annotations

import contextlib
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from mavcal.testing.relay import LossRelay
from mavcal.testing.sitl import RELAY_PORT, TOOL_PORT, SitlVehicle

__all__ = ["Channel", "apply_session", "relayed_channels", "run_sessions"]

#: (vehicle, its relay, the parameters the channel's sessions write)
Channel = tuple[SitlVehicle, LossRelay, tuple[str, ...]]


def _holds(after: dict[str, float], meant: dict[str, float]) -> bool:
    return all(abs(after[n] - v) <= 1e-6 * max(1.0, abs(v)) for n, v in meant.items())


def apply_session(sitl: SitlVehicle, tool_device: str, names: Sequence[str], i: int, tmp: Path, *,
                  timeout_s: float = 300.0) -> dict:
    """``mavcal apply`` of new values of ``names`` (the old ones +-15 + k) through ``tool_device``,
    checked against what the vehicle holds after it: ``{"i", "rc", "ok", "s", "err", "after", "meant"}``."""
    before = sitl.get_params(names)
    want = {n: float(np.float32(before[n] + (15.0 if i % 2 == 0 else -15.0) + k)) for k, n in enumerate(names)}
    cal = tmp / f"s{i}.param"
    cal.write_text("".join(f"{n} {v!r}\n" for n, v in want.items()))
    t0 = time.monotonic()
    r = sitl.run([sys.executable, "-m", "mavcal", "apply", str(cal), "--connect", tool_device, "--yes",
                  "--backup", str(tmp / f"b{i}.param")], timeout=timeout_s)
    took = time.monotonic() - t0
    after = sitl.get_params(names)
    meant = want if r.returncode == 0 else before
    return {"i": i, "rc": r.returncode, "ok": _holds(after, meant), "s": round(took, 2),
            "err": r.stderr.strip().splitlines()[-1:], "after": after, "meant": meant}


def relayed_channels(stack: contextlib.ExitStack, vehicles: Sequence[SitlVehicle],
                     names: tuple[tuple[str, ...], tuple[str, ...]], tool_ports: tuple[int, int], *, seed: int,
                     loss: float = 0.3, dup: float = 0.05) -> list[Channel]:
    """A relay (seeded ``seed``, ``seed + 1``, ...) on SERIAL1 and SERIAL2 of each vehicle, the tool
    listening on ``tool_ports``; the sessions of SERIALk write ``names[k]``. Stopped by ``stack``."""
    channels = []
    for v_idx, sitl in enumerate(vehicles):
        with sitl.netns():  # the relays' sockets live in the vehicle's namespace
            for k, port in enumerate((TOOL_PORT, RELAY_PORT)):
                relay = LossRelay(tool_ports[k], vehicle_port=port, loss=loss, dup=dup, seed=seed + 2 * v_idx + k)
                channels.append((sitl, stack.enter_context(relay), names[k]))
    return channels


def run_sessions(channels: Sequence[Channel], n_sessions: int, tmp: Path,
                 on_outcome: Callable[[dict], None] | None = None) -> tuple[list[dict], float]:
    """Sessions 0..n-1 spread over the channels, one thread each; (outcomes by session, wall s)."""
    outcomes: list[dict] = []
    t0 = time.monotonic()

    def channel(c: int) -> None:
        sitl, relay, names = channels[c]
        for i in range(c, n_sessions, len(channels)):
            o = apply_session(sitl, relay.tool_device, names, i, tmp)
            outcomes.append(o)
            if on_outcome is not None:
                on_outcome(o)

    threads = [threading.Thread(target=channel, args=(c,)) for c in range(len(channels))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return sorted(outcomes, key=lambda o: o["i"]), time.monotonic() - t0
