"""The real autopilot as a test peer: ArduPilot SITL in a private network namespace.

``../shared/sitl/arducopter`` (beside the repository; ``MAVCAL_SITL`` names another binary) is
ArduPilot's own flight code built as SITL. It binds UDP 0.0.0.0:5501 while it boots, so it is
only ever started inside a **private network namespace** whose only interface is loopback
(root, or CAP_SYS_ADMIN: ``unshare(CLONE_NEWNET)``). :class:`SitlVehicle` does that:

* a *keeper* process (``python -c``) unshares the network namespace, brings ``lo`` up and
  waits; the namespace lives as long as the keeper, ``/proc/KEEPER/ns/net``;
* every process of the vehicle (SITL itself, and whatever a test runs with :meth:`~SitlVehicle.popen`
  / :meth:`~SitlVehicle.run`: the ``mavcal`` CLI, MAVProxy, a relay) starts through a small
  launcher that enters that namespace (``setns``), sets ``PR_SET_PDEATHSIG`` = SIGKILL and
  execs; so nothing survives the process that started it, even when it is killed;
* the current thread enters the namespace with ``with sitl.netns():`` (``setns``, and back to
  the thread's own namespace at the end): sockets opened inside stay in the vehicle's
  namespace afterwards, so in-process code (``mavcal.cli.main``, the live capture) can talk to
  the vehicle from any thread once its socket is open;
* SITL runs in its own temporary working directory (``eeprom.bin``, ``terrain/``), with
  ``--model calibration`` (the vehicle is held in place and turned as servo outputs 5-8 say),
  ``--speedup 1`` (real time) and ``-I N``, N unique per process (the pytest-xdist worker
  number and a counter);
* :meth:`~SitlVehicle.stop` stops the processes by PID (SIGTERM, then SIGKILL) and removes the
  working directory; it runs at ``__exit__`` (and the teardown of ``tests/conftest.py``'s
  ``start_sitl``) and ``atexit`` for any vehicle still running; a process killed outright
  takes its vehicle with it through the parent-death signal.

Serial ports (all UDP *clients* to loopback in the namespace; nothing listens):

===========  ===========================  ==========================================================
SERIAL0      :attr:`control_device`        the fixture's own link (``set_pose``, ``set_params``);
                                           ArduPilot's first channel always accepts unsigned
                                           messages, so the fixture keeps control after signing
SERIAL1      :attr:`tool_device`           for the tool under test: ``udpin:127.0.0.1:14551``
SERIAL2      :attr:`relay_device`          a third channel (``relay=True``; e.g. for a loss relay)
===========  ===========================  ==========================================================

Sensor errors and the truth. :class:`InjectedErrors` (``InjectedErrors.random(seed)``) are the
simulator's errors of compass 1 and IMU 1 (``SIM_MAG1_OFS/DIA/ODI/ORIENT``,
``SIM_ACC1_BIAS/SCAL``, ``SIM_MAG_RND``); they go into an extra defaults file loaded after
``copter.parm``, with :data:`WRONG_CALIBRATION` (a deliberately wrong calibration in force,
``COMPASS_ORIENT`` 0 included) unless ``wrong_calibration=False``. :attr:`SitlVehicle.truth`
is the ideal ArduPilot calibration they imply (``COMPASS_OFS`` = ``SIM_MAG1_OFS``,
``COMPASS_DIA/ODI`` = ``SIM_MAG1_DIA/ODI``, ``COMPASS_ORIENT`` = ``SIM_MAG1_ORIENT``,
``INS_ACCOFFS`` = ``SIM_ACC1_BIAS``, ``INS_ACCSCAL`` = ``SIM_ACC1_SCAL``);
:attr:`SitlVehicle.field_ned_mgauss` is SITL's Earth field at home, measured at start from the
compass readings (the errors and the calibration in force undone); :func:`score` scores a
written calibration against the truth (max heading / tilt error over the flight envelope,
offset errors, orientation).

Typical use (pytest; :func:`require_sitl` skips, or fails under ``CI=true``, without a SITL)::

    with SitlVehicle(InjectedErrors.random(7, mag_orient=6)) as sitl:
        sitl.set_pose(0, 90, 45)                  # roll, pitch, yaw from TRUE north (deg); returns settled
        out = sitl.run([sys.executable, "-m", "mavcal", "apply", "x.param", "--connect", sitl.tool_device])
        with sitl.netns():                          # or in-process, in the namespace
            link = open_link(sitl.tool_device)
        sitl.get_params(["COMPASS_OFS_X"])          # over the control link

The API in short: :attr:`~SitlVehicle.tool_device` / :attr:`~SitlVehicle.relay_device` /
:attr:`~SitlVehicle.control_device`; :meth:`~SitlVehicle.netns`, :meth:`~SitlVehicle.popen`,
:meth:`~SitlVehicle.run`, :meth:`~SitlVehicle.launch_argv`, :attr:`~SitlVehicle.netns_path`;
:meth:`~SitlVehicle.set_pose` (returns the settled :class:`SimState`),
:attr:`~SitlVehicle.simstate`, :meth:`~SitlVehicle.set_servo`; :meth:`~SitlVehicle.get_params`,
:meth:`~SitlVehicle.set_params` (waits for the echo), :meth:`~SitlVehicle.send_param_set` (does
not), :meth:`~SitlVehicle.writes_since` (what some GCS wrote, seen on the control channel),
:meth:`~SitlVehicle.read_imu`, :attr:`~SitlVehicle.statustexts`; :attr:`~SitlVehicle.truth`,
:attr:`~SitlVehicle.errors`, :attr:`~SitlVehicle.field_ned_mgauss`,
:attr:`~SitlVehicle.declination_deg`, :attr:`~SitlVehicle.home`, :meth:`~SitlVehicle.score`.
A scripted hand that follows a capture's advice: :mod:`mavcal.testing.sitl_hand`.

What this build (ArduCopter 4.7.0-dev, 90700977) does that a test may not expect, and where the
loopback vehicle (:mod:`mavcal.testing.vehicle`) differs:

* no ``PARAM_ERROR``: a PARAM_SET of an unknown name, or of NaN, gets no answer at all (as the
  loopback vehicle without ``param_errors=True``);
* no range check: ``INS_ACCSCAL_X`` 1.5 or ``COMPASS_ORIENT`` 77 are stored and echoed (the
  latter with a STATUSTEXT "Internal Errors 0x400000"); only mavcal's own limits refuse them;
* device ids (``COMPASS_DEV_ID``, ``INS_ACC_ID``) are **writable** over MAVLink, as on every
  ArduPilot board (they carry no ``AP_PARAM_FLAG_INTERNAL_USE_ONLY``; "@ReadOnly" is only a
  note for ground stations); the loopback vehicle does the same
  (``tests/test_vehicle_agrees_with_sitl.py``);
* an accepted PARAM_SET is echoed on every channel (so the fixture sees what a tool wrote), and
  the vehicle announces its own changes (``STAT_RUNTIME``, ``MIS_TOTAL``) the same way;
* the IMU streams are off on every channel until a GCS asks for them; heartbeats at 1 Hz.

Call :class:`SitlVehicle` (and :meth:`~SitlVehicle.popen`) from a thread that lives as long as
the processes should: the parent-death signal fires when the *thread* that started a process
ends (pytest runs fixtures and tests in the main thread).
"""
from __future__ import annotations

import atexit
import contextlib
import logging
import math
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink import mavutil

from mavcal.ardupilot import firmware as fw
from mavcal.autopilot.rotations import euler_to_matrix
from mavcal.testing.netns import NamespaceError, enter, launch_argv, require, start_keeper
from mavcal.testing.netns import stop_pid as _stop_pid
from mavcal.testing.sitl_truth import InjectedErrors, Score, SitlTruth, score

__all__ = ["SitlVehicle", "InjectedErrors", "SimState", "Home", "Score", "SitlError", "WRONG_CALIBRATION",
           "sitl_binary", "unavailable_reason", "require_sitl", "score", "CALIBRATION_NAMES"]

log = logging.getLogger(__name__)

ENV_BINARY = "MAVCAL_SITL"
PR_SET_PDEATHSIG = 1
DEFAULT_HOME = (-35.363261, 149.165230, 584.0, 353.0)  # CMAC, Canberra: lat, lon, alt (m), heading (deg)
CONTROL_PORT, TOOL_PORT, RELAY_PORT = 14550, 14551, 14552
FIXTURE_SYSTEM, FIXTURE_COMPONENT = 254, 250  # not the GCS ids mavcal and MAVProxy use (255/190)
MSG_SIMSTATE = 164
MSG_RAW_IMU = 27
#: parameter reads unanswered at a time (:meth:`SitlVehicle.get_params`): ArduPilot queues 20 requests
READ_WINDOW = 10

#: a calibration in force that is wrong for any :class:`InjectedErrors` (orientation 0 included)
WRONG_CALIBRATION: dict[str, float] = {
    "COMPASS_OFS_X": 10.0, "COMPASS_OFS_Y": -20.0, "COMPASS_OFS_Z": 30.0,
    "COMPASS_DIA_X": 0.97, "COMPASS_DIA_Y": 1.02, "COMPASS_DIA_Z": 0.99,
    "COMPASS_ODI_X": -0.01, "COMPASS_ODI_Y": 0.005, "COMPASS_ODI_Z": 0.0,
    "COMPASS_SCALE": 1.0, "COMPASS_ORIENT": 0.0,
    "INS_ACCOFFS_X": 0.05, "INS_ACCOFFS_Y": -0.04, "INS_ACCOFFS_Z": 0.08,
    "INS_ACCSCAL_X": 0.99, "INS_ACCSCAL_Y": 1.01, "INS_ACCSCAL_Z": 1.005,
}

#: every calibration parameter of compass 1-3 and IMU 1-2 (what a calibration write touches)
CALIBRATION_NAMES: tuple[str, ...] = tuple(
    [n for i in range(3) for key in ("ofs", "dia", "odi") for n in fw.compass_param_names(i)[key]]  # type: ignore[literal-required]
    + [fw.compass_param_names(i)[k] for i in range(3) for k in ("scale", "orient", "external")]  # type: ignore[literal-required]
    + [n for i in range(2) for key in ("ofs", "scale") for n in fw.accel_param_names(i)[key]]  # type: ignore[literal-required]
    + [fw.board_param_names()["orientation"]])

class SitlError(RuntimeError):
    """SITL could not be started or did not do what it was asked in time."""


def _start_keeper():
    """The namespace's keeper (:func:`mavcal.testing.netns.start_keeper`), its failure a SitlError."""
    try:
        return start_keeper()
    except NamespaceError as exc:
        raise SitlError(str(exc)) from None


# ------------------------------------------------------------------------------------------
# availability
# ------------------------------------------------------------------------------------------
def sitl_binary() -> Path:
    """``$MAVCAL_SITL``, else ``../shared/sitl/arducopter`` beside the repository root."""
    env = os.environ.get(ENV_BINARY)
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2].parent / "shared" / "sitl" / "arducopter"


_probe_lock = threading.Lock()
_probe: list[str | None] = []


def unavailable_reason() -> str | None:
    """Why SITL cannot run here (no binary, not Linux, no right to make a network namespace),
    or None. The namespace is probed once per process."""
    if not sys.platform.startswith("linux"):
        return f"SITL needs Linux network namespaces (this is {sys.platform})"
    b = sitl_binary()
    if not b.is_file():
        return f"no SITL binary at {b} (set {ENV_BINARY}, or put shared/sitl beside the repository)"
    if not os.access(b, os.X_OK):
        return f"SITL binary {b} is not executable"
    with _probe_lock:
        if not _probe:
            try:
                keeper = _start_keeper()
                _stop_pid(keeper)
                _probe.append(None)
            except SitlError as exc:
                _probe.append(f"cannot make a private network namespace for SITL ({exc}); needs root")
        return _probe[0]


def require_sitl() -> None:
    """In a pytest test or fixture: skip when SITL cannot run here, with the reason; under
    ``CI=true`` fail instead (CI must run the SITL tests, never skip them)."""
    require(unavailable_reason(), "SITL")


# ------------------------------------------------------------------------------------------
# processes
# ------------------------------------------------------------------------------------------
_instances = iter(range(1 << 30))
_instance_lock = threading.Lock()


def _next_instance() -> int:
    """-I N: unique per process of a pytest-xdist run (gw0: 0-99, gw1: 100-199, ...)."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    try:
        w = int(worker.lstrip("gw"))
    except ValueError:
        w = 0
    with _instance_lock:
        return (w * 100 + next(_instances) % 100) % 250


def _sweep_workdirs() -> None:
    """Remove the working directories of test processes that were killed outright (SIGKILL:
    their SITL died with them, nothing removed the directory); named mavcal-sitl-PID-*."""
    for d in Path(tempfile.gettempdir()).glob("mavcal-sitl-*-*-*"):
        try:
            os.kill(int(d.name.split("-")[2]), 0)
        except ProcessLookupError:
            shutil.rmtree(d, ignore_errors=True)
        except (ValueError, PermissionError, IndexError):
            continue


_live: set[SitlVehicle] = set()  # started and not stopped: atexit stops them


@atexit.register
def _stop_all() -> None:
    for v in list(_live):
        v.stop()


def _f32(x: float) -> float:
    """As stored: ArduPilot's parameters are float32."""
    return float(np.float32(x))


@dataclass(frozen=True)
class Home:
    lat_deg: float
    lon_deg: float
    alt_m: float
    heading_deg: float

    def arg(self) -> str:
        return f"{self.lat_deg:.6f},{self.lon_deg:.6f},{self.alt_m:g},{self.heading_deg:g}"


@dataclass(frozen=True)
class SimState:
    """The simulator's true attitude (deg; yaw from true north) and rates (deg/s)."""

    roll_deg: float
    pitch_deg: float
    yaw_deg: float
    rates_dps: tuple[float, float, float]
    time_s: float = field(default=0.0, compare=False)  # time.monotonic() of receipt


def _wrap180(x: float) -> float:
    return (x + 180.0) % 360.0 - 180.0


# ------------------------------------------------------------------------------------------
# the vehicle
# ------------------------------------------------------------------------------------------
class SitlVehicle:
    """ArduPilot SITL (copter, calibration model) in a private network namespace.

    Parameters
    ----------
    errors : InjectedErrors, optional
        The simulator's sensor errors (default: none beyond copter.parm's).
    wrong_calibration : bool or mapping
        True: :data:`WRONG_CALIBRATION` in force at boot; a mapping: those values; False: copter.parm's.
    params : mapping, optional
        More boot defaults (e.g. ``{"SERIAL2_PROTOCOL": 2}``).
    relay : bool
        Give SERIAL2 a port too (:attr:`relay_device`).
    serial2 : str, optional
        SERIAL2 as SITL's own device string instead, e.g. ``uart:/dev/pts/3:57600`` (a serial line:
        :class:`mavcal.testing.serial_cable.SerialCable`'s ``vehicle_tty``).
    home : Home or (lat, lon, alt, heading)
    speedup : float
        SITL's ``--speedup`` (1 = real time; the capture sees time as the vehicle does).
    binary : path, optional
        Default :func:`sitl_binary`.
    model : str
        SITL's ``--model``: ``calibration`` (held in place, turned by servos 5-8) or ``quad``
        (flies; :mod:`mavcal.testing.sitl_flight` flies it; no :meth:`set_pose` then).
    boot_timeout_s : float
        How long to wait for the first heartbeat and SIMSTATE.
    """

    def __init__(self, errors: InjectedErrors | None = None, *, wrong_calibration: bool | Mapping[str, float] = True,
                 params: Mapping[str, float] | None = None, relay: bool = False, serial2: str | None = None,
                 home: Home | Sequence[float] = DEFAULT_HOME, speedup: float = 1.0, binary: str | Path | None = None,
                 boot_timeout_s: float = 60.0, measure_field: bool = True, model: str = "calibration") -> None:
        self.errors = errors if errors is not None else InjectedErrors()
        if wrong_calibration is True:
            self.calibration_at_boot = dict(WRONG_CALIBRATION)
        elif wrong_calibration is False:
            self.calibration_at_boot = {}
        else:
            self.calibration_at_boot = dict(wrong_calibration)
        self.extra_params = dict(params or {})
        self.relay = relay
        self.serial2 = serial2
        self.home = home if isinstance(home, Home) else Home(*(float(x) for x in home))
        self.speedup = float(speedup)
        self.model = model
        self.binary = Path(binary) if binary is not None else sitl_binary()
        self.boot_timeout_s = boot_timeout_s
        self.measure_field = measure_field
        self.instance = _next_instance()
        self.workdir: Path | None = None
        self.field_ned_mgauss: np.ndarray | None = None
        self._keeper: subprocess.Popen | None = None
        self._sitl: subprocess.Popen | None = None
        self._children: list[subprocess.Popen] = []
        self._conn: Any = None
        self._send_lock = threading.Lock()
        self._cond = threading.Condition()
        self._params: dict[str, float] = {}
        self._simstate: SimState | None = None
        self._raw_imu: list[Any] = []
        self._collect_raw = False
        self.statustexts: list[str] = []
        # every PARAM_VALUE seen on the control link, in order: the answers to the fixture's own
        # reads, and the echo ArduPilot sends on every channel when any GCS sets a parameter
        self.param_values: list[tuple[str, float]] = []
        self._acks: list[Any] = []
        self._halt = threading.Event()
        self._reader: threading.Thread | None = None
        self._stopped = False

    # ---------------------------------------------------------------- devices
    @property
    def control_device(self) -> str:
        return f"udpin:127.0.0.1:{CONTROL_PORT}"

    @property
    def tool_device(self) -> str:
        """The device string the tool under test opens (in the namespace): SERIAL1."""
        return f"udpin:127.0.0.1:{TOOL_PORT}"

    @property
    def relay_device(self) -> str:
        """SERIAL2's port (``relay=True``)."""
        if not self.relay:
            raise SitlError("SitlVehicle(relay=True) gives SERIAL2 a port")
        return f"udpin:127.0.0.1:{RELAY_PORT}"

    @property
    def netns_path(self) -> str:
        if self._keeper is None:
            raise SitlError("SITL is not running")
        return f"/proc/{self._keeper.pid}/ns/net"

    @property
    def pid(self) -> int | None:
        return None if self._sitl is None else self._sitl.pid

    @property
    def truth(self) -> dict[str, float]:
        """The ideal ArduPilot parameters of compass 1 and IMU 1 for the injected errors."""
        return self.errors.ideal_params()

    def sitl_truth(self) -> SitlTruth:
        if self.field_ned_mgauss is None:
            raise SitlError("the field was not measured (measure_field=False)")
        return self.errors.sitl_truth(self.field_ned_mgauss)

    def score(self, params: Mapping[str, float] | None = None) -> Score:
        """:func:`score` of ``params`` (default: the vehicle's parameters now)."""
        if self.field_ned_mgauss is None:
            raise SitlError("the field was not measured (measure_field=False)")
        if params is None:
            params = self.get_params(CALIBRATION_NAMES)
        return score(params, self.errors, self.field_ned_mgauss)

    @property
    def declination_deg(self) -> float:
        """The measured field's declination: magnetic north = true north + this."""
        if self.field_ned_mgauss is None:
            raise SitlError("the field was not measured (measure_field=False)")
        B = self.field_ned_mgauss
        return float(math.degrees(math.atan2(B[1], B[0])))

    # ---------------------------------------------------------------- namespace
    def netns(self):
        """``with sitl.netns():`` run the current thread in the vehicle's network namespace (and back after)."""
        return enter(self.netns_path)

    def launch_argv(self, argv: Sequence[str]) -> list[str]:
        """``argv`` wrapped to run in the namespace and die with this process."""
        return launch_argv(self.netns_path, argv)

    def popen(self, argv: Sequence[str], **kw: Any) -> subprocess.Popen:
        """Start ``argv`` in the namespace (``subprocess.Popen`` keywords); stopped by :meth:`stop`
        if still running then."""
        p = subprocess.Popen(self.launch_argv(argv), **kw)
        self._children.append(p)
        return p

    def run(self, argv: Sequence[str], *, timeout: float = 300.0, input: str | None = None,
            **kw: Any) -> subprocess.CompletedProcess:
        """Run ``argv`` in the namespace to its end (stdout and stderr captured as text unless
        given); killed (and TimeoutExpired raised) after ``timeout`` s."""
        kw.setdefault("stdout", subprocess.PIPE)
        kw.setdefault("stderr", subprocess.PIPE)
        kw.setdefault("text", True)
        if input is not None:
            kw.setdefault("stdin", subprocess.PIPE)
        p = self.popen(argv, **kw)
        try:
            out, err = p.communicate(input=input, timeout=timeout)
        except subprocess.TimeoutExpired:
            _stop_pid(p, 1.0)
            raise
        finally:
            if p in self._children:
                self._children.remove(p)
        return subprocess.CompletedProcess(p.args, p.returncode, out, err)

    # ---------------------------------------------------------------- start / stop
    def __enter__(self) -> SitlVehicle:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def start(self) -> SitlVehicle:
        reason = unavailable_reason() if self.binary == sitl_binary() else None
        if reason is not None:
            raise SitlError(reason)
        _live.add(self)
        try:
            self._start()
        except BaseException:
            self.stop()
            raise
        return self

    def _defaults_file(self) -> Path:
        assert self.workdir is not None
        lines = ["# written by mavcal.testing.sitl", "SERVO5_FUNCTION 0", "SERVO6_FUNCTION 0", "SERVO7_FUNCTION 0",
                 "SERVO8_FUNCTION 0"]
        values = {**self.errors.sim_params(), **self.calibration_at_boot, **self.extra_params}
        lines += [f"{n} {v!r}" for n, v in values.items()]
        path = self.workdir / "mavcal-sitl.parm"
        path.write_text("\n".join(lines) + "\n")
        return path

    def _start(self) -> None:
        _sweep_workdirs()
        self.workdir = Path(tempfile.mkdtemp(prefix=f"mavcal-sitl-{os.getpid()}-{self.instance}-"))
        self._keeper = _start_keeper()
        with self.netns():
            self._conn = mavutil.mavlink_connection(self.control_device, source_system=FIXTURE_SYSTEM,
                                                    source_component=FIXTURE_COMPONENT, dialect="ardupilotmega")
        defaults = f"{self.binary.parent / 'copter.parm'},{self._defaults_file()}"
        serial2 = self.serial2 or (f"udpclient:127.0.0.1:{RELAY_PORT}" if self.relay else "none")
        argv = [str(self.binary), "--model", self.model, "--speedup", f"{self.speedup:g}", "--home", self.home.arg(),
                "--defaults", defaults, "--serial0", f"udpclient:127.0.0.1:{CONTROL_PORT}",
                "--serial1", f"udpclient:127.0.0.1:{TOOL_PORT}", "--serial2", serial2, "--serial5", "none",
                "--serial6", "none", "--serial7", "none", "--serial8", "none", "-I", str(self.instance)]
        self._log = open(self.workdir / "sitl.log", "wb")
        self._sitl = subprocess.Popen(self.launch_argv(argv), cwd=self.workdir, stdin=subprocess.DEVNULL,
                                      stdout=self._log, stderr=subprocess.STDOUT)
        hb = self._conn.wait_heartbeat(timeout=self.boot_timeout_s)
        if hb is None:
            raise SitlError(f"no heartbeat from SITL within {self.boot_timeout_s:g} s (log: {self._log_tail()})")
        self.target_system, self.target_component = hb.get_srcSystem(), hb.get_srcComponent()
        self._reader = threading.Thread(target=self._read, name=f"sitl{self.instance}-control", daemon=True)
        self._reader.start()
        self.set_message_interval(MSG_SIMSTATE, 20.0)
        # the parameters are read while SITL gets ready to send SIMSTATE (~2.5 s after its first heartbeat)
        at_boot = self._check_injected()
        if self.wait_for(lambda: self._simstate is not None, 20.0) is False:
            raise SitlError("no SIMSTATE from SITL")
        if self.measure_field:
            self.field_ned_mgauss = self._measure_field({n: at_boot[n] for n in CALIBRATION_NAMES if n in at_boot})
        log.info("SITL %d up (pid %d, %s)", self.instance, self._sitl.pid, self.workdir)

    def _log_tail(self) -> str:
        try:
            assert self.workdir is not None
            return (self.workdir / "sitl.log").read_text(errors="replace")[-500:]
        except OSError:
            return "-"

    def stop(self) -> None:
        """Stop every process of the vehicle by PID (SIGTERM, then SIGKILL) and remove its
        working directory. Safe to call twice."""
        if self._stopped:
            return
        self._stopped = True
        self._halt.set()
        for p in reversed(self._children):
            _stop_pid(p, 2.0)
        self._children.clear()
        if self._sitl is not None:
            _stop_pid(self._sitl)
        if self._reader is not None:
            self._reader.join(timeout=5)
        if self._conn is not None:
            with contextlib.suppress(Exception):
                self._conn.close()
        if self._keeper is not None:
            _stop_pid(self._keeper)
        if getattr(self, "_log", None) is not None:
            self._log.close()
        if self.workdir is not None and os.environ.get("MAVCAL_SITL_KEEP") is None:
            shutil.rmtree(self.workdir, ignore_errors=True)
        _live.discard(self)

    def alive(self) -> bool:
        return self._sitl is not None and self._sitl.poll() is None

    # ---------------------------------------------------------------- control link
    def _read(self) -> None:
        conn = self._conn
        while not self._halt.is_set():
            try:
                m = conn.recv_match(blocking=True, timeout=0.2)
            except Exception:  # a closed socket at stop
                if self._halt.is_set():
                    return
                raise
            if m is None:
                continue
            t = m.get_type()
            with self._cond:
                if t == "SIMSTATE":
                    self._simstate = SimState(math.degrees(m.roll), math.degrees(m.pitch), math.degrees(m.yaw),
                                              (math.degrees(m.xgyro), math.degrees(m.ygyro), math.degrees(m.zgyro)),
                                              time.monotonic())
                elif t == "PARAM_VALUE":
                    self._params[m.param_id] = float(m.param_value)
                    self.param_values.append((m.param_id, float(m.param_value)))
                elif t == "COMMAND_ACK":
                    self._acks.append(m)
                elif t == "STATUSTEXT":
                    self.statustexts.append(m.text)
                elif t == "RAW_IMU" and self._collect_raw:
                    self._raw_imu.append(m)
                else:
                    continue
                self._cond.notify_all()

    def wait_for(self, predicate, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not predicate():
                left = deadline - time.monotonic()
                if left <= 0 or not self.alive():
                    return False
                self._cond.wait(min(left, 0.5))
        return True

    def _send(self, fn: str, *args: Any) -> None:
        with self._send_lock:
            getattr(self._conn.mav, fn)(*args)

    def command(self, cmd: int, *params: float, timeout_s: float = 5.0, retries: int = 3) -> int:
        """COMMAND_LONG on the control link; returns the ACK's result."""
        p = (list(params) + [0.0] * 7)[:7]
        for _ in range(retries):
            with self._cond:
                self._acks = [a for a in self._acks if a.command != cmd]
            self._send("command_long_send", self.target_system, self.target_component, cmd, 0, *p)
            if self.wait_for(lambda: any(a.command == cmd for a in self._acks), timeout_s):
                with self._cond:
                    return next(a.result for a in self._acks if a.command == cmd)
        raise SitlError(f"no COMMAND_ACK for command {cmd}")

    def set_message_interval(self, msg_id: int, rate_hz: float) -> None:
        interval_us = -1 if rate_hz <= 0 else int(1e6 / rate_hz)
        res = self.command(mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, interval_us)
        if res != 0:
            raise SitlError(f"SET_MESSAGE_INTERVAL {msg_id}: result {res}")

    # ---------------------------------------------------------------- parameters
    def get_params(self, names: Iterable[str], timeout_s: float = 10.0) -> dict[str, float]:
        """Read ``names`` (PARAM_REQUEST_READ each, at most :data:`READ_WINDOW` unanswered at a time);
        a name the vehicle does not know is missing from the result.

        ArduPilot queues 20 parameter requests (all channels together; ``GCS_Param.cpp``) and drops
        the rest: sending 49 at once had the rest asked again only after a 1 s wait (1.44 s for
        :data:`CALIBRATION_NAMES`; in windows, about 1.0 s, the rate SITL answers at)."""
        names = list(dict.fromkeys(names))
        with self._cond:
            for n in names:
                self._params.pop(n, None)
        out: dict[str, float] = {}
        deadline = time.monotonic() + timeout_s
        pending = list(names)
        while pending and time.monotonic() < deadline:
            window = pending[:READ_WINDOW]
            for n in window:
                self._send("param_request_read_send", self.target_system, self.target_component, n.encode(), -1)
            left = max(0.0, deadline - time.monotonic())
            self.wait_for(lambda w=window: all(n in self._params for n in w), min(1.0, left))
            with self._cond:
                for n in list(pending):
                    if n in self._params:
                        out[n] = self._params[n]
                        pending.remove(n)
            # unanswered (dropped, or a name the vehicle does not know) go to the back: the others are asked
            pending = [n for n in pending if n not in window] + [n for n in window if n in pending]
        return out

    def writes_since(self, mark: int, names: Iterable[str] | None = None) -> list[tuple[str, float]]:
        """The PARAM_VALUEs seen on the control link since ``mark = len(sitl.param_values)``
        (of ``names`` only, default :data:`CALIBRATION_NAMES`): while the fixture itself reads
        none of them, each one is a parameter some GCS set (ArduPilot echoes a PARAM_SET on
        every channel; reads are answered on the asking channel only). The vehicle also
        announces its own changes (``STAT_RUNTIME``, ``MIS_TOTAL``): hence the filter."""
        keep = set(CALIBRATION_NAMES if names is None else names)
        with self._cond:
            return [(n, v) for n, v in self.param_values[mark:] if n in keep]

    def get_param(self, name: str) -> float:
        got = self.get_params([name])
        if name not in got:
            raise SitlError(f"SITL has no parameter {name}")
        return got[name]

    def set_params(self, values: Mapping[str, float], timeout_s: float = 10.0) -> None:
        """PARAM_SET each over the control link and wait for its echo (float32-equal)."""
        want = {n: _f32(v) for n, v in values.items()}
        with self._cond:
            for n in want:
                self._params.pop(n, None)
        deadline = time.monotonic() + timeout_s
        pending = dict(want)
        while pending:
            if time.monotonic() > deadline:
                raise SitlError(f"SITL did not confirm {sorted(pending)}")
            for n, v in pending.items():
                self._send("param_set_send", self.target_system, self.target_component, n.encode(), v,
                           mavutil.mavlink.MAV_PARAM_TYPE_REAL32)
            self.wait_for(lambda: all(n in self._params for n in pending), 1.0)
            with self._cond:
                for n in list(pending):
                    if n in self._params and _f32(self._params[n]) == pending[n]:
                        del pending[n]
                    else:
                        self._params.pop(n, None)

    def send_param_set(self, name: str, value: float) -> None:
        """One PARAM_SET on the control link, without waiting for anything."""
        self._send("param_set_send", self.target_system, self.target_component, name.encode(), float(value),
                   mavutil.mavlink.MAV_PARAM_TYPE_REAL32)

    def _check_injected(self) -> dict[str, float]:
        """Check the boot parameters took; returns them and the calibration in force (one read for
        both: :meth:`_measure_field` needs the latter, and nothing writes in between)."""
        want = {**self.errors.sim_params(), **self.calibration_at_boot, **self.extra_params}
        got = self.get_params([*want, *(CALIBRATION_NAMES if self.measure_field else ())])
        bad = {n: (got.get(n), v) for n, v in want.items() if n not in got or _f32(got[n]) != _f32(v)}
        if bad:
            raise SitlError(f"SITL did not take its boot parameters (got, wanted): {bad}")
        return got

    # ---------------------------------------------------------------- motion
    @property
    def simstate(self) -> SimState:
        with self._cond:
            if self._simstate is None:
                raise SitlError("no SIMSTATE yet")
            return self._simstate

    def set_servo(self, servo: int, pwm: int) -> None:
        res = self.command(mavutil.mavlink.MAV_CMD_DO_SET_SERVO, servo, pwm)
        if res != 0:
            raise SitlError(f"DO_SET_SERVO {servo} {pwm}: result {res}")

    def set_pose(self, roll_deg: float, pitch_deg: float, yaw_true_deg: float, *, settle: bool = True,
                 timeout_s: float = 20.0, tol_deg: float = 0.5, still_s: float = 0.3) -> SimState:
        """Turn the vehicle to the attitude (ZYX Euler, deg, yaw from TRUE north; PWM steps of
        0.36 deg) in the calibration model's attitude mode; return the SIMSTATE once it has been
        within ``tol_deg`` of the commanded attitude, turning less than 0.2 deg/s, for ``still_s``
        (``settle=False``: return at once)."""
        pwm = [1500 + int(round(_wrap180(a) * 500.0 / 180.0)) for a in (roll_deg, pitch_deg, yaw_true_deg)]
        pwm = [min(2000, max(1000, p)) for p in pwm]
        for servo, p in zip((6, 7, 8), pwm):
            self.set_servo(servo, p)
        self.set_servo(5, 1150)
        target = euler_to_matrix(*[(p - 1500) * math.pi / 500.0 for p in pwm])
        if not settle:
            return self.simstate
        return self.wait_settled(target, timeout_s=timeout_s, tol_deg=tol_deg, still_s=still_s)

    def wait_settled(self, target: np.ndarray | None = None, *, timeout_s: float = 20.0, tol_deg: float = 0.5,
                     still_s: float = 0.3) -> SimState:
        """Wait until SIMSTATE shows the vehicle still (and at ``target``, a body-to-NED matrix)."""
        since: list[float | None] = [None]

        def ok() -> bool:
            s = self._simstate
            if s is None:
                return False
            good = max(abs(r) for r in s.rates_dps) < 0.2
            if good and target is not None:
                C = euler_to_matrix(*np.radians([s.roll_deg, s.pitch_deg, s.yaw_deg]))
                cos = (np.trace(target.T @ C) - 1.0) / 2.0
                good = math.degrees(math.acos(max(-1.0, min(1.0, cos)))) < tol_deg
            if not good:
                since[0] = None
                return False
            if since[0] is None:
                since[0] = s.time_s
            return s.time_s - since[0] >= still_s

        if not self.wait_for(ok, timeout_s):
            raise SitlError(f"the vehicle did not settle within {timeout_s:g} s (SIMSTATE {self._simstate})")
        return self.simstate

    def read_imu(self, n: int = 40) -> tuple[np.ndarray, np.ndarray]:
        """The mean of ``n`` RAW_IMU messages on the control link (IMU 1 and compass 1, as sent:
        corrected with the calibration in force): accelerometer (m/s^2), compass (mGauss)."""
        with self._cond:
            self._raw_imu, self._collect_raw = [], True
        try:
            self.set_message_interval(MSG_RAW_IMU, 50.0)
            if not self.wait_for(lambda: len(self._raw_imu) >= n, 20.0):
                raise SitlError("no RAW_IMU from SITL")
        finally:
            with self._cond:
                self._collect_raw = False
            self.set_message_interval(MSG_RAW_IMU, 0)
        msgs = self._raw_imu[:n]
        acc = np.mean([[m.xacc, m.yacc, m.zacc] for m in msgs], axis=0) * fw.GRAVITY_MSS / 1000.0
        mag = np.mean([[m.xmag, m.ymag, m.zmag] for m in msgs], axis=0)
        return acc, mag

    def _measure_field(self, in_force: Mapping[str, float] | None = None) -> np.ndarray:
        """SITL's Earth field (NED, mGauss) from compass 1 at the current pose: the calibration
        in force (``in_force``, else read now) and the injected errors undone, rotated by SIMSTATE's
        attitude."""
        s = self.wait_settled(timeout_s=20.0)
        _, reading = self.read_imu()
        cal = fw.compass_cal_from_params(self.get_params(CALIBRATION_NAMES) if in_force is None else in_force, 0)
        raw = fw.undo_compass(cal, reading[None, :], sensor_frame=True)[0]
        B_body = self.errors.body_field(raw)
        return euler_to_matrix(*np.radians([s.roll_deg, s.pitch_deg, s.yaw_deg])) @ B_body
