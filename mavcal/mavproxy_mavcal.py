"""MAVProxy module: guided accelerometer + compass calibration inside MAVProxy.

Load it in MAVProxy with ``module load mavcal.mavproxy_mavcal`` (MAVProxy tries
``MAVProxy.modules.mavproxy_<name>`` first, then the dotted name). One command::

    mavcal start            fetch the parameters, stream the IMU, advise poses as you go
    mavcal status           intervals kept, coverage map, heading error bound, next pose
    mavcal next             the next pose to hold, in words
    mavcal skip             can't do this one: advise another pose instead
    mavcal stop             end the capture (what was captured is kept)
    mavcal finish           go on without the sensors that cannot reach their target (the status names them)
    mavcal fit              fit what was captured: the per-sensor verdicts, the next step, the summary
    mavcal write [yes]      show the parameter diff of the accepted sensors; with "yes" (or confirm=0) write it
    mavcal restore FILE [yes]   put back a backup .param (same safe writer)
    mavcal set [NAME [VALUE]]   settings: target_deg max_tilt_deg accel compass rate_hz hold_s force ...
    mavcal threads          the module's threads (debugging)
    mavcal ui [nobrowser]   the live page: the pose to hold drawn beside the vehicle now, the
                            verdict and a Write button (starts a capture if none ran; 127.0.0.1 only)

A thin adapter: the capture, the fits and the writes are :class:`mavcal.capture.worker.CaptureWorker`
(one worker thread; the same write flow and words as ``mavcal calibrate --write``). Here only
MAVProxy's side:

* ``mavlink_packet`` runs on MAVProxy's thread and only *files* messages from the primary
  vehicle into the worker (IMU messages while capturing, the parameter protocol's while a
  parameter operation runs, its position messages for the World Magnetic Model). It never
  reads the master (MAVProxy owns the read loop).
* ``idle_task`` sends what the worker queued with ``self.master.mav`` and prints what it said.
  While the worker streams the IMU at its own rate, MAVProxy's periodic REQUEST_DATA_STREAM
  (setting ``streamrate``, every 15 s) would reset those rates to 4 Hz on ArduPilot: the
  module pauses it (``streamrate`` -1) *before* the worker's SET_MESSAGE_INTERVAL goes out and
  puts the user's value back when the capture ends; MAVProxy then asks for its own rates again,
  which restores the IMU messages' rates, so no reset of ours is needed (nor acknowledged).
  MAVProxy prints every COMMAND_ACK ("Got COMMAND_ACK: SET_MESSAGE_INTERVAL: ACCEPTED") before
  a module sees it and lets no module filter them, so the worker asks for as few as it can:
  one per IMU message the vehicle has, once per capture.
* ``unload`` stops the worker and reports that no mavcal thread is left.
"""
from __future__ import annotations

import logging
import queue
import threading
from pathlib import Path
from typing import Any

from MAVProxy.modules.lib import mp_module, mp_settings

from mavcal.capture.worker import FED_TYPES, IMU_TYPES, POSITION_TYPES, THREAD_PREFIX, CaptureWorker, WorkerSettings
from mavcal.determined import bound_phrase

log = logging.getLogger(__name__)

SUBCOMMANDS = ("start", "stop", "finish", "skip", "status", "next", "fit", "write", "restore", "set", "threads")
_MAV_TYPE_GCS = 6
_MAV_AUTOPILOT_INVALID = 8
_PAUSED = -1  # MAVProxy's streamrate that stops its REQUEST_DATA_STREAM
UI_USAGE = "       mavcal ui [nobrowser]   the live capture page in the browser (127.0.0.1 only)"


def _settings_table() -> list[Any]:
    d = WorkerSettings()
    S = mp_settings.MPSetting
    return [S("target_deg", float, d.target_deg, "heading error target of every compass (deg, 95 %)",
              range=(0.01, 20.0)),
            S("target_tilt_deg", float, d.target_tilt_deg, "tilt error target of every accelerometer (deg, 95 %)",
              range=(0.01, 5.0)),
            S("accel", int, d.accel, "IMU instance", range=(0, 2)),
            S("compass", int, d.compass, "compass instance", range=(0, 2)),
            S("rate_hz", float, d.rate_hz, "IMU stream rate (Hz)", range=(25.0, 200.0)),
            S("hold_s", float, d.hold_s, "shortest still hold (s)", range=(0.3, 30.0)),
            S("max_poses", int, d.max_poses, "stop after this many poses", range=(1, 200)),
            S("min_poses", int, d.min_poses, "never stop before this many poses", range=(1, 200)),
            S("confirm", bool, d.confirm, "write only with 'mavcal write yes'"),
            S("force", bool, d.force, "write rejected sensors and values outside ArduPilot's limits too"),
            S("backup_dir", str, d.backup_dir, "directory of the backup .param files"),
            S("param_timeout", float, d.param_timeout, "wait for each parameter echo (s)", range=(0.1, 10.0)),
            S("retries", int, d.retries, "PARAM_SET attempts per parameter at least", range=(1, 20)),
            S("write_budget", float, d.write_budget,
              "keep retrying each PARAM_SET/force-save/read this long (s; 0: 15 x param_timeout)", range=(0.0, 600.0)),
            S("verbose", bool, d.verbose, "print a line whenever the capture state changes"),
            S("max_tilt_deg", float, d.max_tilt_deg, "a vehicle that cannot be turned over: advise poses within this "
              "tilt only, any heading; the accelerometers keep their calibration (0: no limit)", range=(0.0, 40.0))]


class MavcalModule(mp_module.MPModule):
    """The ``mavcal`` MAVProxy module (see the module docstring)."""

    def __init__(self, mpstate: Any) -> None:
        super().__init__(mpstate, "mavcal", "guided accelerometer + compass calibration (mavcal)")
        self.mavcal_settings = mp_settings.MPSettings(_settings_table())
        self._vehicle: tuple[int, int] | None = None
        self._autopilot: int | None = None  # the vehicle HEARTBEAT's autopilot (PX4: 12)
        self._saved_streamrate: int | None = None  # MAVProxy's streamrate while we paused it
        self._streams_seen = False  # the worker's streams_active as idle_task last saw it
        self.worker = CaptureWorker(self._vehicle_ids,
                                    host_restores_rates=lambda: self._saved_streamrate is not None,
                                    autopilot=self._vehicle_autopilot,
                                    source_system=lambda: int(self.mpstate.settings.source_system))
        self.page: Any = None  # the live page (mavcal.capture.workerpage.WorkerPage) while it is open
        self.add_command("mavcal", self.cmd_mavcal, "guided IMU/compass calibration",
                         ["<start|stop|finish|skip|status|next|fit|write|threads>", "restore (FILENAME)",
                          "set (MAVCALSETTING)"])
        self.add_completion_function("(MAVCALSETTING)", self.mavcal_settings.completion)

    # ---------------------------------------------------------------- helpers
    def usage(self) -> str:
        return ("usage: mavcal <start|stop|finish|skip|status|next|fit|write [yes]|restore FILE [yes]"
                "|set [NAME [VALUE]]|threads>")

    def _vehicle_ids(self) -> tuple[int, int] | None:
        """(sysid, compid) of the primary vehicle: from its heartbeats, else what MAVProxy's master saw."""
        if self._vehicle is None:
            master = self.master
            ts = getattr(master, "target_system", 0) if master is not None else 0
            if ts:
                self._vehicle = (int(ts), int(getattr(master, "target_component", 0) or 1))
        return self._vehicle

    def _vehicle_autopilot(self) -> int | None:
        """The primary vehicle HEARTBEAT's ``autopilot``: from the heartbeats filed since the module
        was loaded, else the last one MAVProxy's master holds (a ``mavcal start`` right after
        ``module load`` comes before the module's first heartbeat)."""
        if self._autopilot is None:
            master = self.master
            hb = getattr(master, "messages", {}).get("HEARTBEAT") if master is not None else None
            if hb is not None and hb.type != _MAV_TYPE_GCS and hb.autopilot != _MAV_AUTOPILOT_INVALID:
                self._autopilot = int(hb.autopilot)
        return self._autopilot

    def _snapshot(self) -> WorkerSettings:
        s = self.mavcal_settings
        return WorkerSettings(**{k: s.get(k) for k in WorkerSettings.__dataclass_fields__})

    @staticmethod
    def _threads() -> list[str]:
        return sorted(t.name for t in threading.enumerate() if t.name.startswith(THREAD_PREFIX))

    # ---------------------------------------------------------------- the command
    def cmd_mavcal(self, args: list[str]) -> None:
        """The ``mavcal`` command (runs on MAVProxy's thread: only quick work here)."""
        if args[:1] == ["ui"]:  # the live page (UI_USAGE)
            self._open_page(browser=args[1:2] != ["nobrowser"])
            return
        if not args or args[0] not in SUBCOMMANDS:
            print(self.usage())
            print(UI_USAGE)
            return
        sub, rest = args[0], args[1:]
        w = self.worker
        if sub == "set":
            self.mavcal_settings.command(rest)
        elif sub == "threads":
            names = self._threads()
            print(f"mavcal threads: {', '.join(names) if names else 'none'}")
        elif sub == "status":
            self._print_status()
        elif sub == "next":
            self._print_next()
        elif sub == "start":  # the worker waits a moment for a first vehicle heartbeat
            w.submit("start", self._snapshot())
        elif sub == "write":
            w.submit("write", self._snapshot(), rest[:1] == ["yes"])
        elif sub in ("stop", "finish", "fit", "skip"):
            w.submit(sub)
        elif sub == "restore":
            if not rest:
                print("usage: mavcal restore FILE [yes]")
            elif not Path(rest[0]).is_file():
                print(f"mavcal: {rest[0]}: no such file")
            else:
                w.submit("restore", self._snapshot(), rest[0], rest[1:2] == ["yes"])

    def _print_status(self) -> None:
        from mavcal.capture import status_screen
        from mavcal.report.text import MAVPROXY_HINTS, next_step, verdict_lines

        w = self.worker
        print(f"mavcal: {'capturing' if w.capturing else 'not capturing'}{'; busy: ' + w.busy if w.busy else ''}; "
              f"worker {'alive' if w.thread.is_alive() else 'stopped'}")
        if w.status is not None:
            print(status_screen(w.status, w.session.config.target_heading_deg if w.session else None))
        run = w.run
        if run is not None:
            print("\n".join(verdict_lines(run) + [next_step(run, **MAVPROXY_HINTS)]))
            model = run.calibration.model if run.calibration is not None else "accelerometers alone"
            print(f"fitted: model {model}, {bound_phrase('heading', run.quality.heading_95_deg, '.2f')} (95 %)")

    def _open_page(self, browser: bool = True) -> None:
        """Serve the live page (a new one with a new token once the last one finished), start a
        capture if none ran, and open the browser."""
        import webbrowser

        from mavcal.capture.workerpage import WorkerPage

        if self.page is not None and not self.page.finished.is_set():
            print(f"mavcal: capture page: {self.page.url}")
            return
        if self.page is not None:
            self.page.close()
        self.page = WorkerPage(self.worker, self._snapshot).start()
        print(f"mavcal: capture page: {self.page.url}")
        if not self.worker.capturing and self.worker.run is None and not self.worker.busy:
            self.worker.submit("start", self._snapshot())
        if browser:
            try:
                opened = webbrowser.open(self.page.url)
            except Exception:  # any launcher failure: the address is printed
                opened = False
            if not opened:
                print("mavcal: no browser found; open the address above")

    def _print_next(self) -> None:
        w = self.worker
        st = w.status
        if st is None or not w.capturing:
            print("mavcal: not capturing ('mavcal start')" if st is None else f"mavcal: capture over: {st.reason}")
        elif st.next_pose is not None:
            a = st.next_pose
            print(f"mavcal next pose: {a.words} (roll {a.roll_deg:.0f} pitch {a.pitch_deg:.0f} "
                  f"yaw {a.yaw_deg:.0f} deg magnetic); {st.n_intervals} intervals kept")

    # ---------------------------------------------------------------- MAVProxy hooks
    def mavlink_packet(self, m: Any) -> None:
        """File messages from the primary vehicle; nothing else (MAVProxy's thread)."""
        mtype = m.get_type()
        if mtype in IMU_TYPES:
            if self.worker.capturing and self.message_is_from_primary_vehicle(m):
                self.worker.add_imu(m)
                page = self.page
                if page is not None:
                    page.add_imu(m)
            return
        if mtype in POSITION_TYPES:
            if self.message_is_from_primary_vehicle(m):
                self.worker.add_position(m)
            return
        if mtype not in FED_TYPES or not self.message_is_from_primary_vehicle(m):
            return
        if mtype == "HEARTBEAT" and m.type != _MAV_TYPE_GCS and m.autopilot != _MAV_AUTOPILOT_INVALID:
            if self._vehicle is None:
                self._vehicle = (m.get_srcSystem(), m.get_srcComponent())
            if (m.get_srcSystem(), m.get_srcComponent()) == self._vehicle:
                self._autopilot = int(m.autopilot)
        fed = self.worker.fed
        if fed is not None:
            fed.feed(m)

    def _follow_streams(self) -> None:
        """Pause MAVProxy's own stream-rate requests while the worker streams the IMU at its
        rate; give the user's ``streamrate`` back after (MAVProxy then re-requests its rates)."""
        active = self.worker.streams_active
        if active == self._streams_seen:
            return
        self._streams_seen = active
        settings = self.mpstate.settings
        if active:
            if settings.streamrate != _PAUSED:
                self._saved_streamrate = settings.streamrate
                settings.streamrate = _PAUSED
                log.info("MAVProxy's streamrate %s paused during the capture", self._saved_streamrate)
        elif self._saved_streamrate is not None:
            if settings.streamrate == _PAUSED:  # the user did not change it meanwhile
                settings.streamrate = self._saved_streamrate
            self._saved_streamrate = None

    def idle_task(self) -> None:
        """Send what the worker queued and print what it said (MAVProxy's thread)."""
        from mavcal.link.fed import flush_outbox

        self._follow_streams()  # before the flush: no rate of ours goes out while MAVProxy may lower it
        master = self.master
        if master is not None:
            flush_outbox(self.worker.outbox, master.mav)
        self._print_said()

    def _print_said(self) -> None:
        while True:
            try:
                print(self.worker.out.get_nowait())
            except queue.Empty:
                break

    def unload(self) -> None:
        """Stop the worker (after the job in progress) and say whether a mavcal thread is left."""
        self.remove_command("mavcal")
        if self.page is not None:
            self.page.close()
            self.page = None
        stopped = self.worker.shutdown(timeout_s=4.0)
        self._follow_streams()
        master = self.master
        if master is not None:
            try:  # the default stream rates, if the worker asked for others and MAVProxy does not
                from mavcal.link.fed import flush_outbox
                flush_outbox(self.worker.outbox, master.mav)
            except Exception as exc:  # the link may be gone
                log.debug("final sends failed: %s", exc)
        self._print_said()
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
