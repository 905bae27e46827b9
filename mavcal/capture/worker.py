"""A guided capture, its fits and its parameter writes on one worker thread, for a host that owns
the vehicle link's read loop (MAVProxy; see :mod:`mavcal.mavproxy_mavcal`).

The host talks to the worker only through thread-safe hand-offs:

* it files the vehicle's IMU messages with :meth:`CaptureWorker.add_imu` while
  :attr:`CaptureWorker.capturing`, and HEARTBEAT/PARAM_VALUE/PARAM_ERROR/COMMAND_ACK/STATUSTEXT
  into :attr:`CaptureWorker.fed` (a :class:`~mavcal.link.fed.FedConnection`) while a parameter
  operation runs;
* it sends what the worker queued in :attr:`CaptureWorker.outbox`
  (:func:`mavcal.link.fed.flush_outbox`) and shows the text queued in :attr:`CaptureWorker.out`;
* it reads :attr:`CaptureWorker.streams_active` *before* each flush of the outbox: True while
  the worker wants its own IMU rates, so the host stops asking for its own stream rates (which
  would lower them) before the worker's request goes out.

Jobs (:meth:`CaptureWorker.submit` of ``start``, ``stop``, ``finish``, ``skip``, ``fit``, ``write``, ``restore``):

* ``start``: the vehicle's parameters (the calibration in force on the readings), a
  :class:`~mavcal.capture.CaptureSession`, and SET_MESSAGE_INTERVAL for the IMU messages the
  vehicle has (:func:`~mavcal.link.streams.needed_stream_ids`); about twice a second the
  session is updated and its status line said when it changes; it ends when every sensor meets its
  target (:mod:`mavcal.capture.progress`), and at the end it is fitted;
* ``finish``: go on without the sensors that cannot reach their target
  (:meth:`~mavcal.capture.CaptureSession.finish_without`): the capture ends as soon as the others
  meet theirs;
* ``fit``: the per-sensor verdicts and the next step first (:func:`mavcal.report.text.summary_text`);
* ``write``: the accepted sensors' parameters (every sensor's with ``force``), refused only
  when no sensor was accepted, through the write flow of ``mavcal calibrate --write``:
  :func:`~mavcal.link.writer.fetch_for_write`, the limits check, the time budget,
  :func:`~mavcal.link.writer.write_params` (backup, echo, force-save, read-back, restore);
* ``restore``: a backup .param file through the same writer.

Every word about a write comes from :mod:`mavcal.report.text`. The library logs, never prints.
"""
from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from mavcal.errors import MavcalError

__all__ = ["CaptureWorker", "WorkerSettings", "IMU_TYPES", "FED_TYPES", "POSITION_TYPES", "THREAD_PREFIX"]

log = logging.getLogger(__name__)

#: the IMU messages a capture files (SCALED_IMU: PX4's first IMU, which refuses RAW_IMU; on ArduPilot the
#: same data as RAW_IMU, which the recovery prefers, as for ``mavcal capture``)
IMU_TYPES = frozenset(("RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3"))
#: what a parameter operation needs from the vehicle
FED_TYPES = frozenset(("HEARTBEAT", "PARAM_VALUE", "PARAM_ERROR", "COMMAND_ACK", "STATUSTEXT"))
#: where the vehicle is (for the World Magnetic Model; :mod:`mavcal.link.position`)
POSITION_TYPES = frozenset(("GPS_RAW_INT", "GLOBAL_POSITION_INT", "HOME_POSITION"))
_POSITION_WAIT_S = 3.0
#: every thread of the worker is named with this prefix
THREAD_PREFIX = "mavcal"
_MAX_BUFFERED = 200_000  # IMU messages kept if the worker falls behind
_UPDATE_PERIOD_S = 0.5
_RATE_CHECK_S = 1.0  # RAW_IMU rate measured over this long
_RATE_LOW = 0.6  # ask again below this fraction of the rate asked for
_REASK_GUARD_S = 2.0


@dataclass(frozen=True)
class WorkerSettings:
    """The settings a job runs with (a snapshot handed over with each job)."""

    target_deg: float = 0.5  # every compass's heading bound
    target_tilt_deg: float = 0.3  # every accelerometer's own tilt bound
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
    write_budget: float = 0.0  # s per PARAM_SET / force-save / read; 0: 15 x param_timeout
    verbose: bool = True
    max_tilt_deg: float = 0.0  # a vehicle that cannot be turned over: poses within this tilt (0: no limit)


class CaptureWorker:
    """The one worker thread: capture updates, fits and parameter operations (see the module docstring).

    Parameters
    ----------
    vehicle_ids : callable
        ``() -> (sysid, compid)`` of the vehicle, or None while unknown (called on the worker thread).
    host_restores_rates : callable
        ``() -> bool``: True when the host itself gives the IMU messages their usual rates back
        once :attr:`streams_active` goes False (MAVProxy re-requests its stream rates when they
        are no longer paused); then the worker sends no reset of its own.
    prefix : str
        Start of every line the worker says (tables excepted).
    autopilot : callable, optional
        ``() -> int | None``: the vehicle HEARTBEAT's ``autopilot`` (None while unknown). PX4 (12)
        sends its integer parameters bytewise: the parameter protocol decodes them by it.
    source_system : callable
        ``() -> int | None``: the system id the host sends as (MAVProxy's ``source_system``), so
        that a PARAM_ERROR addressed to another ground station is not taken as ours.
    """

    def __init__(self, vehicle_ids: Callable[[], tuple[int, int] | None], *,
                 host_restores_rates: Callable[[], bool] = lambda: False, prefix: str = "mavcal: ",
                 autopilot: Callable[[], int | None] | None = None,
                 source_system: Callable[[], int | None] = lambda: None) -> None:
        self.vehicle_ids = vehicle_ids
        self.autopilot = autopilot
        self.source_system = source_system
        self.host_restores_rates = host_restores_rates
        self.prefix = prefix
        self.out: queue.Queue[str] = queue.Queue()
        self.outbox: queue.Queue[tuple[str, tuple, dict]] = queue.Queue()
        self.jobs: queue.Queue[tuple[Callable[..., None], tuple]] = queue.Queue()
        self._imu: list[Any] = []
        self._imu_lock = threading.Lock()
        self._positions: list[Any] = []  # position messages filed by the host, read by the worker
        self.fed: Any = None  # the FedConnection of the parameter operation in progress
        self.capturing = False
        self.streams_active = False
        self.session: Any = None
        self.status: Any = None
        self.run: Any = None
        self.busy = ""
        self.jobs_done = 0  # jobs finished (however they ended): a host waiting for its job counts them
        self.write_result: Any = None  # the last write's WriteReport, or the ParamWriteError it raised
        self._cfg = WorkerSettings()
        self._stream_ids: tuple[int, ...] = ()
        self._watched = "RAW_IMU"  # the first of them, whose rate _watch_rate watches
        self._last_update = 0.0
        self._last_line = ""
        self._stream_asked = 0.0
        self._imu_count = 0
        self._imu_since = time.monotonic()
        self._halt = threading.Event()
        self.thread = threading.Thread(target=self._loop, name=f"{THREAD_PREFIX}-worker", daemon=True)
        self.thread.start()

    # -------------------------------------------------------------- called from the host's thread
    def add_imu(self, m: Any) -> None:
        """File one IMU message of the vehicle (kept only while capturing)."""
        with self._imu_lock:
            if len(self._imu) < _MAX_BUFFERED:
                self._imu.append(m)

    def add_position(self, m: Any) -> None:
        """File one position message of the vehicle (GPS_RAW_INT, GLOBAL_POSITION_INT, HOME_POSITION):
        the latest few are kept for the World Magnetic Model."""
        with self._imu_lock:
            self._positions = (self._positions + [m])[-8:]

    def submit(self, job: str, *args: Any) -> None:
        """Queue a job: ``start(settings)``, ``stop()``, ``finish()``, ``fit()``, ``write(settings, confirmed)``,
        ``restore(settings, path, confirmed)``."""
        jobs: dict[str, Callable[..., None]] = {"start": self._start, "stop": self._stop, "finish": self._finish,
                                                "fit": self._fit, "write": self._write, "restore": self._restore,
                                                "skip": self._skip}
        fn = jobs[job]
        self.jobs.put((fn, args))

    def shutdown(self, timeout_s: float = 4.0) -> bool:
        """Stop the thread (after the job in progress); True if it ended within ``timeout_s``."""
        self._halt.set()
        self.thread.join(timeout=timeout_s)
        return not self.thread.is_alive()

    # -------------------------------------------------------------- the thread
    def say(self, text: str) -> None:
        """Say ``text`` as it is (trailing newlines dropped; nothing for an empty text)."""
        text = text.rstrip("\n")
        if text:
            self.out.put(text)

    def _say(self, text: str) -> None:
        """Say ``text`` (one or more lines) with the prefix on every line."""
        self.out.put("\n".join(self.prefix + line for line in text.rstrip("\n").split("\n")))

    def _loop(self) -> None:
        while not self._halt.is_set():
            try:
                fn, args = self.jobs.get(timeout=0.1)
            except queue.Empty:
                fn = None
            if fn is not None:
                self._run_job(fn, args)
            if self.capturing and time.monotonic() - self._last_update >= _UPDATE_PERIOD_S:
                try:
                    self._update()
                except Exception as exc:
                    log.exception("capture update failed")
                    self._end_capture()
                    self._say(f"capture stopped: {exc!r}")
        if self.capturing:
            self._end_capture()

    def _run_job(self, fn: Callable[..., None], args: tuple) -> None:
        self.busy = fn.__name__.strip("_")
        try:
            fn(*args)
        except MavcalError as exc:
            self._say(f"error: {exc}")
        except Exception as exc:  # keep the worker alive; show what happened
            log.exception("mavcal worker job failed")
            self._say(f"internal error: {exc!r}")
        finally:
            self.busy = ""
            self.jobs_done += 1

    def _ids(self, wait_s: float = 3.0) -> tuple[int, int]:
        deadline = time.monotonic() + wait_s
        while True:
            ids = self.vehicle_ids()
            if ids is not None:
                return ids
            if time.monotonic() >= deadline or self._halt.wait(0.05):
                raise MavcalError("no vehicle heartbeat yet: is the vehicle connected?")

    def _autopilot_now(self, wait_s: float = 3.0) -> int | None:
        """The vehicle's autopilot, waited for up to ``wait_s`` (its next heartbeat) while unknown;
        None at once when the host gives none."""
        if self.autopilot is None:
            return None
        deadline = time.monotonic() + wait_s
        ap = self.autopilot()
        while ap is None and time.monotonic() < deadline and not self._halt.wait(0.05):
            ap = self.autopilot()
        return ap

    @contextmanager
    def _link(self) -> Iterator[Any]:
        """A Link over a connection fed by the host, sending through the outbox."""
        from mavcal.link.connection import Link
        from mavcal.link.fed import FedConnection

        sysid, compid = self._ids()
        conn = FedConnection(sysid, compid, address="mavproxy", outbox=self.outbox, source_system=self.source_system())
        self.fed = conn
        link = Link(conn, target_system=sysid, target_component=compid, device="mavproxy")
        link.autopilot = self._autopilot_now()  # PX4's integer parameters travel bytewise
        try:
            yield link
        finally:
            self.fed = None
            conn.close()

    # -------------------------------------------------------------- stream rates
    def _ask_streams(self, rate_hz: float) -> None:
        """SET_MESSAGE_INTERVAL of the needed IMU messages; the host pauses its own stream
        requests first (:attr:`streams_active` is set before anything is queued)."""
        from mavcal.link.fed import QueuedSender
        from mavcal.link.streams import send_message_intervals

        ids = self.vehicle_ids()
        if ids is None:
            return
        self.streams_active = True
        send_message_intervals(QueuedSender(self.outbox), ids[0], ids[1], rate_hz, self._stream_ids)
        self._stream_asked = time.monotonic()

    def _end_capture(self) -> None:
        """Capture over: the IMU messages get their usual rates back, from the host when it
        re-requests its own (no reset needed), else by a SET_MESSAGE_INTERVAL of 0 here."""
        from mavcal.link.fed import QueuedSender
        from mavcal.link.streams import send_message_intervals

        self.capturing = False
        if not self.streams_active:
            return
        ids = self.vehicle_ids()
        self.streams_active = False
        if ids is not None and not self.host_restores_rates():
            send_message_intervals(QueuedSender(self.outbox), ids[0], ids[1], None, self._stream_ids)

    def _watch_rate(self, msgs: list[Any], now: float) -> None:
        """Ask again when the rate of the first IMU message asked for (RAW_IMU; SCALED_IMU on PX4,
        which refuses RAW_IMU) falls well below the one asked for (another ground station's
        REQUEST_DATA_STREAM resets the message intervals on ArduPilot)."""
        watched = self._watched
        self._imu_count += sum(1 for m in msgs if m.get_type() == watched)
        if now - self._imu_since < _RATE_CHECK_S:
            return
        rate = self._imu_count / (now - self._imu_since)
        if rate < _RATE_LOW * self._cfg.rate_hz and now - self._stream_asked > _REASK_GUARD_S:
            log.info("%s at %.1f Hz; asking for %g Hz again", watched, rate, self._cfg.rate_hz)
            self._ask_streams(self._cfg.rate_hz)
        self._imu_count, self._imu_since = 0, now

    def _filed_position(self) -> Any:
        """The best position among the filed messages (None: none)."""
        from mavcal.link.position import PositionWatch

        watch = PositionWatch()
        with self._imu_lock:
            msgs = list(self._positions)
        for m in msgs:
            watch.feed(m)
        return watch.best()

    def _take_position(self, position: Any) -> None:
        if position is not None and self.session is not None:
            self.session.position, self.session.position_source = position.location, position.source
            self._say(f"field from the World Magnetic Model at {position.describe()}")

    def _vehicle_position(self) -> Any:
        """The vehicle's position from the filed messages (MAVProxy streams them); asked for once
        (MAV_CMD_REQUEST_MESSAGE through the outbox: MAVProxy prints every COMMAND_ACK, so not
        again and again) when none is known yet, then waited for up to 3 s. None: unknown (a later
        fix is taken by :meth:`_update`)."""
        from mavcal.link.fed import QueuedSender
        from mavcal.link.position import request_position

        best, ids = self._filed_position(), self.vehicle_ids()
        if best is not None or ids is None:
            return best
        request_position(QueuedSender(self.outbox), ids[0], ids[1])
        deadline = time.monotonic() + _POSITION_WAIT_S
        while best is None and time.monotonic() < deadline and not self._halt.wait(0.05):
            best = self._filed_position()
        return best

    # -------------------------------------------------------------- jobs
    def _start(self, cfg: WorkerSettings) -> None:
        from mavcal.capture import CaptureConfig, CaptureSession, status_line
        from mavcal.link.params import fetch_all_params
        from mavcal.link.streams import message_name, needed_stream_ids
        from mavcal.pipeline import Options
        from mavcal.segment import StillConfig

        if self.capturing:
            self._say("already capturing ('mavcal stop' first)")
            return
        self._say("fetching the vehicle's parameters...")
        with self._link() as link:
            table = fetch_all_params(link, timeout_s=30.0, retry_s=max(0.2, cfg.param_timeout / 2))
        values = {k: v for k, (v, _) in table.items()}
        still = StillConfig(min_duration_s=cfg.hold_s)
        config = CaptureConfig(target_heading_deg=cfg.target_deg, target_tilt_deg=cfg.target_tilt_deg,
                               max_intervals=cfg.max_poses,
                               min_intervals=min(cfg.min_poses, cfg.max_poses), still=still,
                               max_tilt_deg=cfg.max_tilt_deg or None)
        position = self._vehicle_position()
        self.session = CaptureSession(values, config, Options(still=still, accel_instance=cfg.accel,
                                                              mag_instance=cfg.compass), source="mavproxy",
                                      position=position.location if position is not None else None)
        self.session.position_source = position.source if position is not None else ""
        self.run = None
        self._cfg = cfg
        self._stream_ids = needed_stream_ids(values)
        self._watched = message_name(self._stream_ids[0]) if self._stream_ids else "RAW_IMU"
        with self._imu_lock:
            self._imu = []
        self._imu_count, self._imu_since = 0, time.monotonic()
        self._ask_streams(cfg.rate_hz)
        self.capturing = True
        self._last_update = time.monotonic()
        self.status = self.session.update()
        self._last_line = status_line(self.status)
        where = (f"field from the World Magnetic Model at {position.describe()}" if position is not None
                 else "no position from the vehicle: the compass keeps its own scale")
        self._say(f"capture started ({len(table)} parameters; {where}); hold each advised pose still until it is "
                  f"counted\n{self._last_line}")

    def _update(self) -> None:
        from mavcal.capture import status_line
        from mavcal.link.live import imu_batch_from_messages

        now = time.monotonic()
        self._last_update = now
        with self._imu_lock:
            msgs, self._imu = self._imu, []
        ids = self.vehicle_ids()
        self.session.add(imu_batch_from_messages(msgs, target_system=ids[0] if ids else None))
        if self.session.position is None:  # a GPS fix that came after the start
            self._take_position(self._filed_position())
        self._watch_rate(msgs, now)
        st = self.session.update()
        self.status = st
        line = status_line(st)
        if line != self._last_line and (self._cfg.verbose or st.done):
            self._say(line)
        self._last_line = line
        if st.done:
            self._end_capture()
            if st.aborted:
                self._say(f"capture aborted: {st.reason}")
            else:
                self._say(f"capture finished ({st.reason}); fitting...")
                self._fit()

    def _stop(self) -> None:
        if not self.capturing:
            self._say("not capturing")
            return
        self.session.stop("stopped by the user")
        self._update()

    def _finish(self) -> None:
        if not self.capturing:
            self._say("not capturing")
            return
        dropped = self.session.finish_without()
        if not dropped:
            self._say("every sensor can still reach its target: nothing to finish without ('mavcal stop' ends the "
                      "capture now)")
            return
        self._say(f"going on without {', '.join(dropped)}: the capture ends when the other sensors meet their "
                  "targets")
        self._update()

    def _skip(self) -> None:
        """"Can't do this one": another pose instead of the one advised (never advised again)."""
        if not self.capturing:
            self._say("not capturing")
            return
        advice = self.session.skip_pose()
        self.status = self.session.status
        self._say(f"another pose instead: {advice.words}")

    def _fit(self) -> None:
        from mavcal.report.text import MAVPROXY_HINTS, summary_text

        if self.session is None:
            self._say("nothing captured yet ('mavcal start')")
            return
        if self.status is not None and self.status.aborted:
            self._say(f"the capture was aborted ({self.status.reason}); not fitting")
            return
        from mavcal.sources.progress import CallbackProgress

        # the console shows each stage of the final fit (held-out refits can take seconds)
        progress = CallbackProgress(lambda stage, frac: self._say(f"{stage} {frac:.0%}"), min_interval_s=2.0)
        self.run = self.session.result(progress=progress)
        self.say(summary_text(self.run, hints=MAVPROXY_HINTS, force=self._cfg.force))
        self._say("fit done; 'mavcal write' shows the parameter changes")

    def _write(self, cfg: WorkerSettings, confirmed: bool) -> None:
        from mavcal.report.text import MAVPROXY_HINTS, gate_refusal_text

        if self.run is None:
            if self.session is None:
                self._say("nothing to write: no capture yet ('mavcal start')")
                return
            self._fit()
            if self.run is None:
                return
        if self.run.exit_code == 4 and not cfg.force:
            self.say(gate_refusal_text(self.run, MAVPROXY_HINTS["force_hint"], prefix=self.prefix))
            return
        # the capture recorded the vehicle it writes to: its compasses and IMUs are the vehicle's
        # by construction, so the device-id check of a log's calibration (``log_params`` of
        # mavcal.commands.common.write_with_report) has nothing to compare and is skipped
        self._write_params(cfg, self.run.params_to_write(cfg.force), confirmed, "calibration write",
                           "mavcal write yes", stem="mavcal-backup")

    def _restore(self, cfg: WorkerSettings, path: str, confirmed: bool) -> None:
        from mavcal.autopilot.paramfile import read_param_file

        changes = read_param_file(path)
        if not changes:
            self._say(f"{path}: no parameters in the file")
            return
        self._write_params(cfg, changes, confirmed, "restore", f"mavcal restore {path} yes",
                           stem=f"{Path(path).stem}-before-restore")

    def _write_params(self, cfg: WorkerSettings, changes: Mapping[str, float], confirmed: bool, what: str,
                      confirm_cmd: str, stem: str) -> None:
        """The write flow of ``mavcal calibrate --write`` over the fed link (every word from
        :mod:`mavcal.report.text`): read what the write needs, show the diff and the values
        outside ArduPilot's limits (refused unless ``force``), then the safe writer."""
        from mavcal.autopilot.protocol import check_limits, failing_kinds, force_save_kinds
        from mavcal.errors import ParamWriteError
        from mavcal.link.backup import default_backup_path
        from mavcal.link.writer import write_params
        from mavcal.report.text import forced_limits_text, plan_text, write_done_text, write_failed_text, writing_text

        opts: dict[str, Any] = dict(retries=cfg.retries, timeout_s=cfg.param_timeout,
                                    budget_s=cfg.write_budget or None, allow_out_of_range=cfg.force)
        with self._link() as link:
            table = self._vehicle_values(link, cfg, list(changes))
            plan = write_params(link, changes, backup_path=None, params=table, dry_run=True, **opts)
            if cfg.force:  # refused by write_params otherwise; forced: said loudly, as the CLI does
                values = {n: v for n, (v, _) in table.items()}
                self.say(forced_limits_text([v.message for v in check_limits(changes, values)],
                                            sorted(failing_kinds(changes, values)), override="force",
                                            prefix=self.prefix))
            if not plan.changed or (cfg.confirm and not confirmed):
                hint = f"type '{confirm_cmd}' to write them"
                self.say(plan_text(plan, confirm_hint=hint, prefix=self.prefix))
                return
            Path(cfg.backup_dir).mkdir(parents=True, exist_ok=True)
            bpath = str(default_backup_path(cfg.backup_dir, stem))
            self.say(writing_text(len(plan.changed), bpath, prefix=self.prefix))
            try:
                report = write_params(link, changes, backup_path=bpath, params=table,
                                      force_save=force_save_kinds(r.name for r in plan.changed),
                                      keepalive=False, **opts)  # ATTITUDE is not fed to this link
            except ParamWriteError as exc:
                self.write_result = exc
                self.say(write_failed_text(exc, what, bpath, prefix=self.prefix))
                raise  # the worker says "error: ..."
        self.write_result = report
        self.say(write_done_text(report, prefix=self.prefix))

    @staticmethod
    def _vehicle_values(link: Any, cfg: WorkerSettings, names: list[str]) -> dict[str, tuple[float, int]]:
        """The part of the vehicle's table the write needs (:func:`mavcal.link.writer.fetch_for_write`,
        as ``mavcal calibrate --write``): the names, their sensors' limits and device ids."""
        from mavcal.autopilot.protocol import id_names, related_names
        from mavcal.link.writer import fetch_for_write

        return fetch_for_write(link, names, context=related_names(names) + id_names(),
                               timeout_s=cfg.param_timeout, fetch_timeout_s=max(30.0, 10 * cfg.param_timeout))
