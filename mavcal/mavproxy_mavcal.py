"""MAVProxy module: guided accelerometer + compass calibration inside MAVProxy.

Load it in MAVProxy with ``module load mavcal.mavproxy_mavcal`` (MAVProxy tries
``MAVProxy.modules.mavproxy_<name>`` first, then the dotted name). One command::

    mavcal start            fetch the parameters, stream the IMU, advise poses as you go
    mavcal status           intervals kept, coverage map, heading error bound, next pose
    mavcal next             the next pose to hold, in words
    mavcal stop             end the capture (what was captured is kept)
    mavcal fit              fit what was captured and show the summary
    mavcal write [yes]      show the parameter diff; with "yes" (or confirm=0) write it
    mavcal restore FILE [yes]   put back a backup .param (same safe writer)
    mavcal set [NAME [VALUE]]   settings: target_deg accel compass rate_hz hold_s ...
    mavcal threads          the module's threads (debugging)

How it fits into MAVProxy:

* ``mavlink_packet`` runs on MAVProxy's thread and only *files* messages from the primary
  vehicle: IMU messages into a buffer while capturing, and HEARTBEAT/PARAM_VALUE/
  COMMAND_ACK/STATUSTEXT into a :class:`mavcal.link.fed.FedConnection` while a
  parameter operation runs. It never reads the master (MAVProxy owns the read loop).
* Everything slow runs in one worker thread (``mavcal-worker``): ``CaptureSession.update``
  about twice a second, ``result()``, the parameter download and the writes. The worker
  sends through an outbox that ``idle_task`` flushes with ``self.master.mav`` on MAVProxy's
  thread, and its text goes through a queue that ``idle_task`` prints.
* Parameter writes (and ``restore``) go through :func:`mavcal.link.writer.write_params`, the
  same safe writer as ``mavcal calibrate --write`` (backup first, every value confirmed by its
  PARAM_VALUE echo, force-save, read-back, restore on failure), on a
  :class:`mavcal.link.connection.Link` over the fed connection.
* ``unload`` stops the worker and reports that no mavcal thread is left.

No calibration logic lives here: the module calls :class:`mavcal.capture.CaptureSession`,
the pipeline and the writer, like the ``capture`` command.
"""
from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from MAVProxy.modules.lib import mp_module, mp_settings

from mavcal.errors import MavcalError

log = logging.getLogger(__name__)

IMU_TYPES = frozenset(("RAW_IMU", "SCALED_IMU2", "SCALED_IMU3"))
FED_TYPES = frozenset(("HEARTBEAT", "PARAM_VALUE", "COMMAND_ACK", "STATUSTEXT"))
SUBCOMMANDS = ("start", "stop", "status", "next", "fit", "write", "restore", "set", "threads")
THREAD_PREFIX = "mavcal"
_PREFIX = "mavcal: "  # of every line the module prints (tables excepted)
_MAX_BUFFERED = 200_000  # IMU messages kept if the worker falls behind
_MAV_TYPE_GCS = 6
_MAV_AUTOPILOT_INVALID = 8


@dataclass(frozen=True)
class ModuleSettings:
    """A snapshot of the module's settings, handed to the worker with each job."""

    target_deg: float = 0.5
    accel: int = 0
    compass: int = 0
    rate_hz: float = 25.0
    hold_s: float = 1.0
    max_poses: int = 40
    min_poses: int = 8
    confirm: bool = True
    force: bool = False
    backup_dir: str = "."
    param_timeout: float = 1.0
    retries: int = 3
    verbose: bool = True


def _settings_table() -> list[Any]:
    d = ModuleSettings()
    S = mp_settings.MPSetting
    return [S("target_deg", float, d.target_deg, "heading error target (deg, 95 %)", range=(0.01, 20.0)),
            S("accel", int, d.accel, "IMU instance", range=(0, 2)),
            S("compass", int, d.compass, "compass instance", range=(0, 2)),
            S("rate_hz", float, d.rate_hz, "IMU stream rate (Hz)", range=(25.0, 200.0)),
            S("hold_s", float, d.hold_s, "shortest still hold (s)", range=(0.3, 30.0)),
            S("max_poses", int, d.max_poses, "stop after this many poses", range=(1, 200)),
            S("min_poses", int, d.min_poses, "never stop before this many poses", range=(1, 200)),
            S("confirm", bool, d.confirm, "write only with 'mavcal write yes'"),
            S("force", bool, d.force, "write even if a quality gate failed"),
            S("backup_dir", str, d.backup_dir, "directory of the backup .param files"),
            S("param_timeout", float, d.param_timeout, "wait for each parameter echo (s)", range=(0.1, 10.0)),
            S("retries", int, d.retries, "PARAM_SET attempts per parameter", range=(1, 20)),
            S("verbose", bool, d.verbose, "print a line whenever the capture state changes")]


class _Worker:
    """The module's one worker thread: capture updates, fits and parameter operations.

    Talks to MAVProxy's thread only through thread-safe queues/lists: ``imu`` (filled by
    ``mavlink_packet``), ``outbox`` (sent by ``idle_task``), ``out`` (printed by ``idle_task``)
    and the fed connection of the parameter operation in progress.
    """

    def __init__(self, vehicle_ids: Callable[[], tuple[int, int] | None]) -> None:
        self.vehicle_ids = vehicle_ids
        self.out: queue.Queue[str] = queue.Queue()
        self.outbox: queue.Queue[tuple[str, tuple, dict]] = queue.Queue()
        self.jobs: queue.Queue[tuple[Callable[..., None], tuple]] = queue.Queue()
        self._imu: list[Any] = []
        self._imu_lock = threading.Lock()
        self.fed = None  # the FedConnection of the parameter operation in progress
        self.capturing = False
        self.session = None
        self.status = None
        self.run = None
        self.table: dict[str, tuple[float, int]] | None = None
        self.busy = ""
        self._cfg = ModuleSettings()
        self._last_update = 0.0
        self._last_line = ""
        self._stream_asked = 0.0
        self._imu_count = 0
        self._imu_since = time.monotonic()
        self._halt = threading.Event()
        self.thread = threading.Thread(target=self._loop, name=f"{THREAD_PREFIX}-worker", daemon=True)
        self.thread.start()

    # -------------------------------------------------------------- called from MAVProxy's thread
    def add_imu(self, m: Any) -> None:
        with self._imu_lock:
            if len(self._imu) < _MAX_BUFFERED:
                self._imu.append(m)

    def submit(self, fn: Callable[..., None], *args: Any) -> None:
        self.jobs.put((fn, args))

    def shutdown(self, timeout_s: float = 4.0) -> bool:
        """Stop the thread (after the job in progress); True if it ended within ``timeout_s``."""
        self._halt.set()
        self.thread.join(timeout=timeout_s)
        return not self.thread.is_alive()

    # -------------------------------------------------------------- the thread
    def say(self, text: str) -> None:
        self.out.put(text)

    def _loop(self) -> None:
        while not self._halt.is_set():
            try:
                fn, args = self.jobs.get(timeout=0.1)
            except queue.Empty:
                fn = None
            if fn is not None:
                self.busy = fn.__name__.strip("_")
                try:
                    fn(*args)
                except MavcalError as exc:
                    self.say(f"mavcal: error: {exc}")
                except Exception as exc:  # keep the worker alive; show what happened
                    log.exception("mavcal worker job failed")
                    self.say(f"mavcal: internal error: {exc!r}")
                finally:
                    self.busy = ""
            if self.capturing and time.monotonic() - self._last_update >= 0.5:
                try:
                    self._update()
                except Exception as exc:
                    log.exception("capture update failed")
                    self.capturing = False
                    self.say(f"mavcal: capture stopped: {exc!r}")
        if self.capturing:
            self._stream_rates(None)

    def _ids(self, wait_s: float = 3.0) -> tuple[int, int]:
        deadline = time.monotonic() + wait_s
        while True:
            ids = self.vehicle_ids()
            if ids is not None:
                return ids
            if time.monotonic() >= deadline or self._halt.wait(0.05):
                raise MavcalError("no vehicle heartbeat yet: is the vehicle connected?")

    @contextmanager
    def _link(self) -> Iterator[Any]:
        """A Link over a connection fed by mavlink_packet, sending through the outbox."""
        from mavcal.link.connection import Link
        from mavcal.link.fed import FedConnection

        sysid, compid = self._ids()
        conn = FedConnection(sysid, compid, address="mavproxy", outbox=self.outbox)
        self.fed = conn
        try:
            yield Link(conn, target_system=sysid, target_component=compid, device="mavproxy")
        finally:
            self.fed = None
            conn.close()

    def _stream_rates(self, rate_hz: float | None) -> None:
        from mavcal.link.fed import QueuedSender
        from mavcal.link.streams import send_message_intervals

        ids = self.vehicle_ids()
        if ids is not None:
            send_message_intervals(QueuedSender(self.outbox), ids[0], ids[1], rate_hz)
            self._stream_asked = time.monotonic()

    # -------------------------------------------------------------- jobs
    def _start(self, cfg: ModuleSettings) -> None:
        from mavcal.capture import CaptureConfig, CaptureSession, status_line
        from mavcal.link.params import fetch_all_params
        from mavcal.pipeline import Options
        from mavcal.segment import StillConfig

        if self.capturing:
            self.say("mavcal: already capturing ('mavcal stop' first)")
            return
        self.say("mavcal: fetching the vehicle's parameters...")
        with self._link() as link:
            table = fetch_all_params(link, timeout_s=30.0, retry_s=max(0.2, cfg.param_timeout / 2))
        still = StillConfig(min_duration_s=cfg.hold_s)
        config = CaptureConfig(target_heading_deg=cfg.target_deg, max_intervals=cfg.max_poses,
                               min_intervals=min(cfg.min_poses, cfg.max_poses), still=still)
        self.table = table
        self.session = CaptureSession({k: v for k, (v, _) in table.items()}, config,
                                      Options(still=still, accel_instance=cfg.accel, mag_instance=cfg.compass),
                                      source="mavproxy")
        self.run = None
        self._cfg = cfg
        with self._imu_lock:
            self._imu = []
        self._imu_count, self._imu_since = 0, time.monotonic()
        self._stream_rates(cfg.rate_hz)
        self.capturing = True
        self._last_update = time.monotonic()
        self.status = self.session.update()
        self._last_line = status_line(self.status)
        self.say(f"mavcal: capture started ({len(table)} parameters); hold each advised pose still until it is "
                 f"counted\nmavcal: {self._last_line}")

    def _update(self) -> None:
        from mavcal.capture import status_line
        from mavcal.link.live import imu_batch_from_messages

        now = time.monotonic()
        self._last_update = now
        with self._imu_lock:
            msgs, self._imu = self._imu, []
        ids = self.vehicle_ids()
        self.session.add(imu_batch_from_messages(msgs, target_system=ids[0] if ids else None))
        # MAVProxy re-sends REQUEST_DATA_STREAM now and then, which resets the message intervals
        # on ArduPilot: ask again when the RAW_IMU rate falls well below the one asked for
        self._imu_count += sum(1 for m in msgs if m.get_type() == "RAW_IMU")
        if now - self._imu_since >= 1.0:
            rate = self._imu_count / (now - self._imu_since)
            if rate < 0.6 * self._cfg.rate_hz and now - self._stream_asked > 2.0:
                log.info("RAW_IMU at %.1f Hz; asking for %g Hz again", rate, self._cfg.rate_hz)
                self._stream_rates(self._cfg.rate_hz)
            self._imu_count, self._imu_since = 0, now
        st = self.session.update()
        self.status = st
        line = status_line(st)
        if line != self._last_line and (self._cfg.verbose or st.done):
            self.say(f"mavcal: {line}")
        self._last_line = line
        if st.done:
            self.capturing = False
            self._stream_rates(None)
            if st.aborted:
                self.say(f"mavcal: capture aborted: {st.reason}")
            else:
                self.say(f"mavcal: capture finished ({st.reason}); fitting...")
                self._fit()

    def _stop(self) -> None:
        if not self.capturing:
            self.say("mavcal: not capturing")
            return
        self.session.stop("stopped by the user")
        self._update()

    def _fit(self) -> None:
        from mavcal.report import summary_text

        if self.session is None:
            self.say("mavcal: nothing captured yet ('mavcal start')")
            return
        if self.status is not None and self.status.aborted:
            self.say(f"mavcal: the capture was aborted ({self.status.reason}); not fitting")
            return
        self.run = self.session.result()
        self.say(summary_text(self.run))
        self.say("mavcal: fit done; 'mavcal write' shows the parameter changes")

    def _write(self, cfg: ModuleSettings, confirmed: bool) -> None:
        if self.run is None:
            if self.session is None:
                self.say("mavcal: nothing to write: no capture yet ('mavcal start')")
                return
            self._fit()
            if self.run is None:
                return
        if not self.run.accepted and not cfg.force:
            from mavcal.report.text import gate_refusal_text

            self.say(gate_refusal_text(self.run, "'mavcal set force 1'", prefix=_PREFIX).rstrip("\n"))
            return
        self._write_params(cfg, dict(self.run.mapping.new), confirmed, "calibration write",
                           "mavcal write yes", stem="mavcal-backup")

    def _restore(self, cfg: ModuleSettings, path: str, confirmed: bool) -> None:
        from mavcal.ardupilot.paramfile import read_param_file

        changes = read_param_file(path)
        if not changes:
            self.say(f"mavcal: {path}: no parameters in the file")
            return
        self._write_params(cfg, changes, confirmed, "restore", f"mavcal restore {path} yes",
                           stem=f"{Path(path).stem}-before-restore")

    def _write_params(self, cfg: ModuleSettings, changes: dict[str, float], confirmed: bool, what: str,
                      confirm_cmd: str, stem: str) -> None:
        """The safe writer over the fed link; every word from :mod:`mavcal.report.text`."""
        from mavcal.ardupilot.protocol import force_save_kinds
        from mavcal.errors import ParamWriteError
        from mavcal.link.params import fetch_all_params
        from mavcal.link.writer import default_backup_path, write_params
        from mavcal.report.text import plan_text, write_done_text, write_failed_text, writing_text

        with self._link() as link:
            table = self.table or fetch_all_params(link, timeout_s=30.0, retry_s=max(0.2, cfg.param_timeout / 2))
            self.table = table
            plan = write_params(link, changes, backup_path=None, params=table, dry_run=True,
                                retries=cfg.retries, timeout_s=cfg.param_timeout)
            if not plan.changed or (cfg.confirm and not confirmed):
                hint = f"type '{confirm_cmd}' to write them"
                self.say(plan_text(plan, confirm_hint=hint, prefix=_PREFIX).rstrip("\n"))
                return
            Path(cfg.backup_dir).mkdir(parents=True, exist_ok=True)
            bpath = str(default_backup_path(cfg.backup_dir, stem))
            self.say(writing_text(len(plan.changed), bpath, prefix=_PREFIX).rstrip("\n"))
            try:
                report = write_params(link, changes, backup_path=bpath, params=table,
                                      force_save=force_save_kinds(r.name for r in plan.changed),
                                      retries=cfg.retries, timeout_s=cfg.param_timeout,
                                      link_timeout_s=max(3.0, 3 * cfg.param_timeout))
            except ParamWriteError as exc:
                self.say(write_failed_text(exc, what, bpath, prefix=_PREFIX).rstrip("\n"))
                raise  # the worker says "mavcal: error: ..."
        self.table = None  # the values changed: fetch afresh next time
        self.say(write_done_text(report, prefix=_PREFIX).rstrip("\n"))


class MavcalModule(mp_module.MPModule):
    """The ``mavcal`` MAVProxy module (see the module docstring)."""

    def __init__(self, mpstate: Any) -> None:
        super().__init__(mpstate, "mavcal", "guided accelerometer + compass calibration (mavcal)")
        self.mavcal_settings = mp_settings.MPSettings(_settings_table())
        self._vehicle: tuple[int, int] | None = None
        self.worker = _Worker(self._vehicle_ids)
        self.add_command("mavcal", self.cmd_mavcal, "guided IMU/compass calibration",
                         ["<start|stop|status|next|fit|write|threads>", "restore (FILENAME)",
                          "set (MAVCALSETTING)"])
        self.add_completion_function("(MAVCALSETTING)", self.mavcal_settings.completion)

    # ---------------------------------------------------------------- helpers
    def usage(self) -> str:
        return "usage: mavcal <start|stop|status|next|fit|write [yes]|restore FILE [yes]|set [NAME [VALUE]]|threads>"

    def _vehicle_ids(self) -> tuple[int, int] | None:
        """(sysid, compid) of the primary vehicle: from its heartbeats, else what MAVProxy's master saw."""
        if self._vehicle is None:
            master = self.master
            ts = getattr(master, "target_system", 0) if master is not None else 0
            if ts:
                self._vehicle = (int(ts), int(getattr(master, "target_component", 0) or 1))
        return self._vehicle

    def _snapshot(self) -> ModuleSettings:
        s = self.mavcal_settings
        return ModuleSettings(**{k: s.get(k) for k in ModuleSettings.__dataclass_fields__})

    @staticmethod
    def _threads() -> list[str]:
        return sorted(t.name for t in threading.enumerate() if t.name.startswith(THREAD_PREFIX))

    # ---------------------------------------------------------------- the command
    def cmd_mavcal(self, args: list[str]) -> None:
        """The ``mavcal`` command (runs on MAVProxy's thread: only quick work here)."""
        from mavcal.capture import status_screen

        if not args or args[0] not in SUBCOMMANDS:
            print(self.usage())
            return
        sub, rest = args[0], args[1:]
        w = self.worker
        if sub == "set":
            self.mavcal_settings.command(rest)
        elif sub == "threads":
            names = self._threads()
            print(f"mavcal threads: {', '.join(names) if names else 'none'}")
        elif sub == "status":
            head = (f"mavcal: {'capturing' if w.capturing else 'not capturing'}"
                    f"{'; busy: ' + w.busy if w.busy else ''}; worker {'alive' if w.thread.is_alive() else 'stopped'}")
            print(head)
            if w.status is not None:
                print(status_screen(w.status, w.session.config.target_heading_deg if w.session else None))
            if w.run is not None:
                from mavcal.report.text import verdict_lines

                print("\n".join(verdict_lines(w.run)))
                model = w.run.calibration.model if w.run.calibration is not None else "accelerometers alone"
                print(f"fitted: model {model}, heading 95 % {w.run.quality.heading_95_deg:.2f} deg")
        elif sub == "next":
            st = w.status
            if st is None or not w.capturing:
                print("mavcal: not capturing ('mavcal start')" if st is None else f"mavcal: capture over: {st.reason}")
            elif st.next_pose is not None:
                a = st.next_pose
                print(f"mavcal next pose: {a.words} (roll {a.roll_deg:.0f} pitch {a.pitch_deg:.0f} "
                      f"yaw {a.yaw_deg:.0f} deg magnetic); {st.n_intervals} intervals kept")
        elif sub == "start":  # the worker waits a moment for a first vehicle heartbeat
            w.submit(w._start, self._snapshot())
        elif sub == "stop":
            w.submit(w._stop)
        elif sub == "fit":
            w.submit(w._fit)
        elif sub == "write":
            w.submit(w._write, self._snapshot(), rest[:1] == ["yes"])
        elif sub == "restore":
            if not rest:
                print("usage: mavcal restore FILE [yes]")
                return
            if not Path(rest[0]).is_file():
                print(f"mavcal: {rest[0]}: no such file")
                return
            w.submit(w._restore, self._snapshot(), rest[0], rest[1:2] == ["yes"])

    # ---------------------------------------------------------------- MAVProxy hooks
    def mavlink_packet(self, m: Any) -> None:
        """File messages from the primary vehicle; nothing else (MAVProxy's thread)."""
        mtype = m.get_type()
        if mtype in IMU_TYPES:
            if self.worker.capturing and self.message_is_from_primary_vehicle(m):
                self.worker.add_imu(m)
            return
        if mtype not in FED_TYPES or not self.message_is_from_primary_vehicle(m):
            return
        if (mtype == "HEARTBEAT" and m.type != _MAV_TYPE_GCS and m.autopilot != _MAV_AUTOPILOT_INVALID
                and self._vehicle is None):
            self._vehicle = (m.get_srcSystem(), m.get_srcComponent())
        fed = self.worker.fed
        if fed is not None:
            fed.feed(m)

    def idle_task(self) -> None:
        """Send what the worker queued and print what it said (MAVProxy's thread)."""
        from mavcal.link.fed import flush_outbox

        master = self.master
        if master is not None:
            flush_outbox(self.worker.outbox, master.mav)
        while True:
            try:
                text = self.worker.out.get_nowait()
            except queue.Empty:
                break
            print(text)

    def unload(self) -> None:
        """Stop the worker (after the job in progress) and say whether a mavcal thread is left."""
        self.remove_command("mavcal")
        stopped = self.worker.shutdown(timeout_s=4.0)
        master = self.master
        if master is not None:
            try:  # the default stream rates, if the worker asked for others
                from mavcal.link.fed import flush_outbox
                flush_outbox(self.worker.outbox, master.mav)
            except Exception as exc:  # the link may be gone
                log.debug("final sends failed: %s", exc)
        while True:
            try:
                print(self.worker.out.get_nowait())
            except queue.Empty:
                break
        left = self._threads()
        if stopped and not left:
            print("mavcal: unloaded; worker stopped; mavcal threads left: none")
        else:
            print(f"mavcal: unloaded; worker {'stopped' if stopped else 'STILL RUNNING (a write in progress?)'}; "
                  f"mavcal threads left: {', '.join(left) if left else 'none'}")
        super().unload()


def init(mpstate: Any) -> MavcalModule:
    """MAVProxy's entry point: ``module load mavcal.mavproxy_mavcal``."""
    return MavcalModule(mpstate)
