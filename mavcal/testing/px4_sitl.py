"""PX4's own flight code as a test peer: the PX4 SITL of ``../shared/px4`` in a private network namespace.

PX4 binds its MAVLink ports on every interface, so it only runs inside a namespace of its own whose only
interface is loopback (:class:`mavcal.testing.netns.PrivateNetwork`, the machinery of the ArduPilot
fixture :mod:`mavcal.testing.sitl`). In it, PX4 sends its GCS link to ``udpin:127.0.0.1:14550``
(:attr:`Px4Sitl.device`); open it in the namespace (``with px4.netns(): open_link(px4.device)``).

One PX4 per machine at a time (it locks ``/tmp/px4_lock-0``): :meth:`Px4Sitl.start` takes a file lock
first, so two test processes wait for each other instead of failing. ``sim_model`` "sihsim_quadx"
(default) is PX4's in-process simulator (a quadrotor standing still on the ground), "none_iris" the external
simulator (:class:`mavcal.testing.px4_poser.Poser`, whose socket ``before_boot`` opens in the namespace);
``params`` are set at boot (``PX4_PARAM_<NAME>``). :meth:`Px4Sitl.stop` stops PX4 by PID (SIGINT, then
SIGTERM/SIGKILL) and removes its working folder.
"""
from __future__ import annotations

import contextlib
import fcntl
import os
import shutil
import signal
import subprocess
import tempfile
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import IO, Any

from mavcal.testing.netns import NamespaceError, PrivateNetwork, require, start_keeper, stop_pid

__all__ = ["Px4Sitl", "Px4SitlError", "px4_dir", "px4_unavailable_reason", "require_px4", "GCS_DEVICE"]

GCS_DEVICE = "udpin:127.0.0.1:14550"


class Px4SitlError(RuntimeError):
    """PX4 SITL could not be started."""


def px4_dir() -> Path:
    """``$MAVCAL_PX4``, else ``../shared/px4`` beside the repository root."""
    env = os.environ.get("MAVCAL_PX4")
    return Path(env) if env else Path(__file__).resolve().parents[2].parent / "shared" / "px4"


def px4_unavailable_reason() -> str | None:
    """Why PX4 SITL cannot run here, or None."""
    import sys

    if not sys.platform.startswith("linux"):
        return f"PX4 SITL needs Linux network namespaces (this is {sys.platform})"
    if not (px4_dir() / "run.sh").is_file() or not (px4_dir() / "bin" / "px4").is_file():
        return f"no PX4 SITL at {px4_dir()} (set MAVCAL_PX4, or put shared/px4 beside the repository)"
    try:
        stop_pid(start_keeper())
    except NamespaceError as exc:
        return f"cannot make a private network namespace for PX4 ({exc}); needs root"
    return None


def require_px4() -> None:
    """In a test: skip without PX4 SITL (fail instead under ``CI=true``)."""
    require(px4_unavailable_reason(), "PX4 SITL")


class Px4Sitl:
    """PX4 SITL in a private network namespace (see the module docstring)."""

    def __init__(self, *, sim_model: str = "sihsim_quadx", params: Mapping[str, float] | None = None,
                 boot_timeout_s: float = 60.0, lock_timeout_s: float = 600.0,
                 before_boot: Callable[[], Any] | None = None) -> None:
        self.sim_model = sim_model
        self.params = dict(params or {})
        self.boot_timeout_s = boot_timeout_s
        self.lock_timeout_s = lock_timeout_s
        self.net = PrivateNetwork()
        self.workdir: Path | None = None
        self._proc: subprocess.Popen | None = None
        self._lock: IO[str] | None = None
        self._log: IO[bytes] | None = None
        self.device = GCS_DEVICE
        #: called in the namespace before PX4 starts (the external simulator's listening socket)
        self.before_boot = before_boot

    def netns(self):
        """``with px4.netns():`` the current thread in PX4's network namespace."""
        return self.net.netns()

    def _take_lock(self) -> None:
        self._lock = open(Path(tempfile.gettempdir()) / "mavcal-px4.lock", "w")  # noqa: SIM115 (closed in stop)
        end = time.monotonic() + self.lock_timeout_s
        while True:
            try:
                fcntl.flock(self._lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return
            except BlockingIOError:
                if time.monotonic() > end:
                    raise Px4SitlError("another PX4 SITL held the machine's lock too long") from None
                time.sleep(0.2)

    def start(self) -> Px4Sitl:
        try:
            self._take_lock()
            self.net.start()
            if self.before_boot is not None:
                with self.netns():
                    self.before_boot()
            self.workdir = Path(tempfile.mkdtemp(prefix=f"mavcal-px4-{os.getpid()}-"))
            env = dict(os.environ, PX4_SIM_MODEL=self.sim_model)
            env["PATH"] = f"{self._module_links()}{os.pathsep}{env.get('PATH', '')}"
            env.update({f"PX4_PARAM_{k}": str(v) for k, v in self.params.items()})
            self._log = open(self.workdir / "px4.log", "wb")  # noqa: SIM115 (closed in stop)
            self._proc = self.net.popen(["sh", str(px4_dir() / "run.sh"), str(self.workdir)], env=env,
                                        stdout=self._log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
            self.wait_boot()
        except (NamespaceError, OSError) as exc:
            self.stop()
            raise Px4SitlError(str(exc)) from None
        except BaseException:
            self.stop()
            raise
        return self

    def _module_links(self) -> Path:
        """A folder of ``px4-<module>`` symlinks to ``bin/px4`` (PX4's start-up script runs its modules
        through them), first in PATH: a copy of ``bin/`` whose links became 3-byte text files ("px4",
        not executable) still starts. Symlinks only, in the working folder; nothing is copied."""
        assert self.workdir is not None
        links = self.workdir / "px4-modules"
        links.mkdir()
        binary = (px4_dir() / "bin" / "px4").resolve()
        for f in (px4_dir() / "bin").iterdir():
            if f.name.startswith("px4-") and (f.is_symlink() or f.stat().st_size < 64):
                (links / f.name).symlink_to(binary if f.name != "px4-alias.sh" else f.resolve())
            elif f.name == "px4-alias.sh":
                (links / f.name).symlink_to(f.resolve())
        return links

    def wait_boot(self) -> None:
        """Wait for PX4's first HEARTBEAT on the GCS link (opened and closed again)."""
        from mavcal.link.connection import open_link

        with self.netns():
            link = open_link(self.device, timeout_s=self.boot_timeout_s, budget_s=self.boot_timeout_s)
        link.close()

    def log_tail(self, n: int = 2000) -> str:
        try:
            assert self.workdir is not None
            return (self.workdir / "px4.log").read_text(errors="replace")[-n:]
        except (OSError, AssertionError):
            return "-"

    def alive(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def stop(self) -> None:
        """Stop PX4 (SIGINT, then SIGTERM/SIGKILL by PID), the namespace, remove the working folder."""
        if self._proc is not None:
            if self._proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    self._proc.send_signal(signal.SIGINT)
                with contextlib.suppress(subprocess.TimeoutExpired):
                    self._proc.wait(timeout=5)
            stop_pid(self._proc)
            self._proc = None
        self.net.stop()
        for f in (self._log, self._lock):
            if f is not None:
                with contextlib.suppress(OSError):
                    f.close()
        self._log = self._lock = None
        if self.workdir is not None and os.environ.get("MAVCAL_SITL_KEEP") is None:
            shutil.rmtree(self.workdir, ignore_errors=True)
            self.workdir = None

    def __enter__(self) -> Px4Sitl:
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.stop()
