"""A private network namespace on loopback for the SITL fixtures (ArduPilot's and PX4's).

Both autopilots bind their MAVLink ports on every interface, so they only ever run inside a
network namespace of their own whose only interface is loopback (root, or CAP_SYS_ADMIN):

* a *keeper* process unshares the namespace, brings ``lo`` up and waits; the namespace lives as
  long as the keeper (``/proc/KEEPER/ns/net``) and the keeper dies with its parent;
* every process started in it (:meth:`PrivateNetwork.popen`) goes through a launcher that enters
  the namespace (``setns``), sets ``PR_SET_PDEATHSIG`` = SIGKILL and execs;
* :func:`enter` runs the current thread in the namespace (and back after): sockets opened there
  stay in it.
"""
from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator, Sequence
from typing import Any

__all__ = ["require", "CLONE_NEWNET", "LAUNCHER", "KEEPER", "NamespaceError", "start_keeper", "stop_pid", "enter",
           "launch_argv", "PrivateNetwork"]

CLONE_NEWNET = 0x40000000


class NamespaceError(RuntimeError):
    """The namespace could not be made or entered."""


# The launcher every process of the vehicle starts through: enter the namespace, die with the
# parent, exec. argv: NS_PATH PARENT_PID PROGRAM ARGS...
LAUNCHER = r"""
import ctypes, os, signal, sys
libc = ctypes.CDLL(None, use_errno=True)
if libc.prctl(1, signal.SIGKILL, 0, 0, 0) != 0:
    sys.exit("sitl launcher: prctl(PR_SET_PDEATHSIG) failed")
if os.getppid() != int(sys.argv[2]):
    sys.exit("sitl launcher: parent gone")
fd = os.open(sys.argv[1], os.O_RDONLY)
if libc.setns(fd, 0x40000000) != 0:
    sys.exit("sitl launcher: setns: " + os.strerror(ctypes.get_errno()))
os.close(fd)
os.execvp(sys.argv[3], sys.argv[3:])
"""

# The keeper: a new network namespace with lo up, alive until its stdin closes or its parent dies.
KEEPER = r"""
import ctypes, fcntl, os, signal, socket, struct, sys
libc = ctypes.CDLL(None, use_errno=True)
libc.prctl(1, signal.SIGKILL, 0, 0, 0)
if os.getppid() != int(sys.argv[1]):
    sys.exit(1)
if libc.unshare(0x40000000) != 0:
    print("unshare(CLONE_NEWNET): " + os.strerror(ctypes.get_errno()), flush=True)
    sys.exit(1)
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
fcntl.ioctl(s, 0x8914, struct.pack("16sH14x", b"lo", 0x1 | 0x8 | 0x40))  # SIOCSIFFLAGS: UP|LOOPBACK|RUNNING
s.close()
print("ready", flush=True)
sys.stdin.read()
"""


def start_keeper() -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, "-I", "-c", KEEPER, str(os.getpid())], stdin=subprocess.PIPE,
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    assert p.stdout is not None
    line = p.stdout.readline().strip()
    if line != "ready":
        stop_pid(p)
        raise NamespaceError(line or f"namespace keeper exited with {p.poll()}")
    return p


def stop_pid(p: subprocess.Popen, term_s: float = 3.0) -> None:
    """SIGTERM, then SIGKILL after ``term_s``; reap it."""
    if p.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            p.send_signal(signal.SIGTERM)
        try:
            p.wait(timeout=term_s)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                p.kill()
            p.wait(timeout=10)
    for f in (p.stdin, p.stdout, p.stderr):
        if f is not None:
            with contextlib.suppress(OSError):
                f.close()



@contextlib.contextmanager
def enter(ns_path: str) -> Iterator[None]:
    """Run the current thread in the network namespace ``ns_path`` (and back to its own after)."""
    libc = ctypes.CDLL(None, use_errno=True)
    own = os.open(f"/proc/self/task/{threading.get_native_id()}/ns/net", os.O_RDONLY)
    target = os.open(ns_path, os.O_RDONLY)
    try:
        if libc.setns(target, CLONE_NEWNET) != 0:
            raise NamespaceError(f"setns: {os.strerror(ctypes.get_errno())}")
        try:
            yield
        finally:
            if libc.setns(own, CLONE_NEWNET) != 0:  # never leave a thread in the wrong namespace
                raise NamespaceError(f"setns back: {os.strerror(ctypes.get_errno())}")
    finally:
        os.close(target)
        os.close(own)


def launch_argv(ns_path: str, argv: Sequence[str]) -> list[str]:
    """``argv`` wrapped to run in the namespace ``ns_path`` and die with this process."""
    return [sys.executable, "-I", "-c", LAUNCHER, ns_path, str(os.getpid()), *map(str, argv)]


class PrivateNetwork:
    """A namespace (its keeper) and the processes started in it; :meth:`stop` ends them all by PID."""

    def __init__(self) -> None:
        self._keeper: subprocess.Popen | None = None
        self._children: list[subprocess.Popen] = []

    def start(self) -> PrivateNetwork:
        self._keeper = start_keeper()
        return self

    @property
    def path(self) -> str:
        if self._keeper is None:
            raise NamespaceError("the namespace is not running")
        return f"/proc/{self._keeper.pid}/ns/net"

    def netns(self):
        """``with net.netns():`` the current thread in the namespace."""
        return enter(self.path)

    def popen(self, argv: Sequence[str], **kw: Any) -> subprocess.Popen:
        p = subprocess.Popen(launch_argv(self.path, argv), **kw)
        self._children.append(p)
        return p

    def stop(self) -> None:
        for p in reversed(self._children):
            stop_pid(p, 3.0)
        self._children.clear()
        if self._keeper is not None:
            stop_pid(self._keeper)
            self._keeper = None


def require(reason: str | None, what: str) -> None:
    """In a pytest test or fixture: skip with ``reason`` (why ``what`` cannot run here), or fail under
    ``CI=true`` (CI must run the SITL tests, never skip them); nothing when ``reason`` is None."""
    import pytest

    if reason is None:
        return
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(f"CI=true but {what} cannot run: {reason}", pytrace=False)
    pytest.skip(reason)
