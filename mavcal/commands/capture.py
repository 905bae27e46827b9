"""``mavcal capture --connect DEVICE``: guided live capture, then the calibration and an optional safe write.

The vehicle streams its IMU; after every new still pose the calibration is refitted and
the next pose to hold is shown in words ("nose down, rolled 45 deg left, nose towards
magnetic east") until every sensor meets its target: every compass's 95 % heading error bound
and every accelerometer's own tilt bound (or the capture is aborted, stopped with Ctrl-C,
which also finishes without a sensor that cannot reach its target, or runs out of poses or
time). Then the calibration summary is
printed, the outputs are written, and the parameters are written to the vehicle only after
confirmation (interactive y/N, or ``--write``/``--write --yes``) through the same safe
writer as ``calibrate --write``.

With ``--ui`` the capture is also shown on a local web page (:mod:`mavcal.capture.web`, opened
in the browser unless ``--no-browser``): the pose to hold drawn beside the vehicle now, the
poses done, each sensor's bound, then the verdict and the parameters; the write is then
confirmed on the page (Write, and its dialog) instead of y/N, or happens at once with
``--write --yes``; Don't write, Ctrl-C or ``--ui-wait`` seconds without an answer write nothing.
The page's server stops when the command ends.

Exit codes as ``calibrate``: 0 every sensor accepted (and written when asked); 7 some sensors
accepted (only their parameters are written), some rejected; 2 usage; 3 the device does not
answer; 4 aborted (impossible field, magnetic disturbance), no sensor accepted or too little
data; 5 write failed and the vehicle was restored; 6 write failed and the restore failed; 8 the
vehicle requires MAVLink 2 signing and ``--signing-key`` is missing or wrong.
"""
from __future__ import annotations

import argparse
import sys
from typing import TextIO

from mavcal.commands.common import (
    BACKUP_HELP,
    add_json_argument,
    add_link_arguments,
    add_save_tlog_argument,
    check_new_backup,
    check_optional_dependencies,
    check_save_tlog,
    parse_location,
    resolve_connect,
    say_tlog_saved,
    signing_key,
    start_budget_s,
    write_outputs,
    write_with_report,
)
from mavcal.errors import GateError, MavcalError, UsageError

HELP = "guided live capture: says which pose to hold next, fits as it goes, then writes on confirmation"


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_link_arguments(p)  # --connect, --baud, --timeout, --param-timeout, --retries, --dry-run, --yes
    _add_page_arguments(p)
    cap = p.add_argument_group("capture")
    cap.add_argument("--target-deg", type=float, default=0.5, metavar="DEG",
                     help="stop when every compass's 95 %% heading error bound is below this (default 0.5) ...")
    cap.add_argument("--target-tilt-deg", type=float, default=0.3, metavar="DEG",
                     help="... and every accelerometer's own 95 %% tilt error bound is below this (default 0.3)")
    cap.add_argument("--max-poses", type=int, default=None, metavar="N",
                     help="stop after N still poses (default 40; 25 with --max-tilt)")
    cap.add_argument("--min-poses", type=int, default=8, metavar="N", help="never stop before N poses (default 8)")
    cap.add_argument("--duration", type=float, default=600.0, metavar="S",
                     help="stop after S seconds at the latest (default 600)")
    cap.add_argument("--hold", type=float, default=1.0, metavar="S",
                     help="shortest still hold that counts as a pose (default 1)")
    cap.add_argument("--rate", type=float, default=25.0, metavar="HZ", help="IMU stream rate (default 25, at least 25)")
    cap.add_argument("--max-tilt", type=float, default=None, metavar="DEG",
                     help="a vehicle that cannot be turned over: advise only poses tilted at most DEG from level (any "
                          "heading; e.g. one side on a block); the accelerometers then keep their calibration and the "
                          "compasses are fitted with it held (default: no limit, the full capture)")
    fit = p.add_argument_group("calibration")
    fit.add_argument("--accel", type=int, default=0, metavar="I", help="IMU instance (0-based, default 0)")
    fit.add_argument("--compass", type=int, default=0, metavar="I", help="compass instance (priority, 0-based)")
    fit.add_argument("--field-mgauss", type=float, help="Earth field magnitude to scale the compass to")
    fit.add_argument("--location", type=parse_location, metavar="LAT,LON[,ALT]",
                     help="position for the World Magnetic Model")
    out = p.add_argument_group("outputs")
    out.add_argument("--param-out", metavar="F", help="write the new parameters as a .param file")
    add_json_argument(out, "the full JSON report")
    out.add_argument("--report", metavar="F", help="write a self-contained HTML report (needs mavcal[plots])")
    add_save_tlog_argument(out)
    w = p.add_argument_group("writing to the vehicle")
    w.add_argument("--write", action="store_true", help="write the parameters (asks first unless --yes)")
    w.add_argument("--force", action="store_true",
                   help="write the rejected sensors' parameters too (and values outside ArduPilot's limits)")
    w.add_argument("--backup", metavar="F", help=BACKUP_HELP)


def _add_page_arguments(p: argparse.ArgumentParser) -> None:
    ui = p.add_argument_group("live page")
    ui.add_argument("--ui", action="store_true",
                    help="show the capture on a local web page (the pose to hold, the vehicle now, the verdict, "
                         "a Write button) and open it in the browser")
    ui.add_argument("--no-browser", action="store_true", help="with --ui: print the page's address, open no browser")
    ui.add_argument("--ui-host", default=None, metavar="HOST",
                    help="with --ui: serve on this interface instead of 127.0.0.1 (anyone who can reach it and "
                         "has the address can write to the vehicle)")
    ui.add_argument("--ui-port", type=int, default=0, metavar="PORT", help="with --ui: port (default: a free one)")
    ui.add_argument("--ui-wait", type=float, default=3600.0, metavar="S",
                    help="with --ui: wait this long for Write or Don't write on the page (default 3600)")


class StatusPrinter:
    """Shows capture statuses: one redrawn screen on a terminal, one line per change otherwise."""

    def __init__(self, out: TextIO, target_deg: float | None = None, tty: bool | None = None) -> None:
        self.out = out
        self.target_deg = target_deg
        self.tty = bool(out.isatty()) if tty is None else tty
        self._last = ""

    def __call__(self, st) -> None:
        from mavcal.capture import status_line, status_screen

        if self.tty:
            text = status_screen(st, self.target_deg)
            if text != self._last:
                self.out.write("\x1b[H\x1b[2J" + text + "\n")
        else:
            text = status_line(st)
            if text != self._last:
                self.out.write(text + "\n")
        self._last = text
        self.out.flush()


def check_max_tilt(max_tilt: float | None) -> None:
    """--max-tilt: None (no limit) or a tilt from 1 deg up to what counts as within reach."""
    from mavcal.coverage import REACH_MAX_TILT_DEG, REACH_MIN_TILT_DEG

    if max_tilt is not None and not REACH_MIN_TILT_DEG <= max_tilt <= REACH_MAX_TILT_DEG:
        raise UsageError(f"--max-tilt must be {REACH_MIN_TILT_DEG:g}-{REACH_MAX_TILT_DEG:g} deg (the poses identify "
                         f"the compass's vertical terms from {REACH_MIN_TILT_DEG:g} deg of tilt; beyond "
                         f"{REACH_MAX_TILT_DEG:g} deg use the full capture); got {max_tilt:g}")


def _check(args: argparse.Namespace) -> None:
    if not args.target_deg > 0 or not args.target_tilt_deg > 0:
        raise UsageError("--target-deg and --target-tilt-deg must be > 0")
    if (args.max_poses is not None and args.max_poses < 1) or args.min_poses < 1:
        raise UsageError("--max-poses and --min-poses must be at least 1")
    if not args.duration > 0 or not args.hold > 0 or not args.rate > 0:
        raise UsageError("--duration, --hold and --rate must be > 0")
    check_max_tilt(args.max_tilt)
    check_new_backup(args.backup)
    check_save_tlog(args.save_tlog)
    if (args.no_browser or args.ui_host or args.ui_port) and not args.ui:
        raise UsageError("--no-browser, --ui-host and --ui-port go with --ui")
    if not 0 <= args.ui_port <= 65535 or not args.ui_wait > 0:
        raise UsageError("--ui-port must be 0-65535 and --ui-wait > 0")


def run(args: argparse.Namespace) -> int:
    if not args.ui:
        return _run(args)
    _check(args)  # usage errors before the page opens
    page = _start_page(args)
    try:
        return _run(args, page)
    except MavcalError as exc:
        if page.state.get("phase") not in ("failed", "declined", "aborted"):
            page.state.set(phase="aborted", error=str(exc))
        raise
    except KeyboardInterrupt:
        page.state.set(phase="declined" if page.state.get("result") else "aborted", error="stopped with Ctrl-C")
        raise
    finally:
        page.close()


def _run(args: argparse.Namespace, page=None) -> int:
    from mavcal.capture import CaptureConfig
    from mavcal.capture import live as live_capture
    from mavcal.pipeline import Options
    from mavcal.segment import StillConfig

    _check(args)
    check_optional_dependencies(args)
    resolve_connect(args)
    try:
        still = StillConfig(min_duration_s=args.hold)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    config = CaptureConfig(target_heading_deg=args.target_deg, target_tilt_deg=args.target_tilt_deg,
                           max_intervals=args.max_poses or 40, max_intervals_reach=args.max_poses or 25,
                           min_intervals=min(args.min_poses, args.max_poses or 40), still=still,
                           max_tilt_deg=args.max_tilt)
    options = Options(still=still, accel_instance=args.accel, mag_instance=args.compass,
                      field_mgauss=args.field_mgauss, location=args.location)
    printer = StatusPrinter(sys.stderr, args.target_deg)
    hooks: dict = {}
    if page is not None:  # the page sees every status and every batch (the live attitude)
        printer, hooks = _page_hooks(page, printer, config, args)
    session = live_capture.capture_live(args.connect, config=config, options=options, on_status=printer, **hooks,
                                        baud=args.baud, rate_hz=args.rate, max_duration_s=args.duration,
                                        heartbeat_timeout_s=args.timeout, budget_s=start_budget_s(args),
                                        signing_key=signing_key(args), tlog=args.save_tlog)
    say_tlog_saved(args)
    st = session.status
    if st is not None and st.aborted:
        raise live_capture.CaptureAbortedError(f"capture aborted: {st.reason}")
    if page is not None:
        page.state.set(phase="fitting")
    run = session.result()  # InsufficientDataError (exit 4) when too little was captured
    if page is not None:  # the verdict and Write on the page
        return _page_flow(args, page, run, run.params_to_write(args.force))
    # 0 all accepted, 7 some rejected (GateError, exit 4, when none was accepted and no --force)
    offer = args.write or args.dry_run or sys.stdin.isatty()  # a write plan (with the table) follows
    code = write_outputs(run, args, f"mavcal guided capture on {args.connect}", param_table=not offer)
    # the accepted sensors' parameters only (every sensor's with --force). No log_params for the
    # device-id check: the capture recorded the very vehicle it writes to, so its compasses and
    # IMUs are the vehicle's by construction
    changes = run.params_to_write(args.force)
    if args.write or args.dry_run:
        return write_with_report(args, changes, args.backup, "calibration write") or code
    if offer:  # offer it: the diff, then y/N
        try:
            return write_with_report(replace_ns(args, yes=False), changes, args.backup, "calibration write") or code
        except UsageError as exc:
            if str(exc).startswith("cancelled"):
                print("nothing written to the vehicle")
                return code
            raise
    print("nothing written to the vehicle (use --write to write the parameters)")
    return code


# --------------------------------------------------------------------------- the live page

PAGE_HINTS = {"force_hint": "mavcal capture --force", "write_hint": "the Write button below", "only_hint": ""}


def _start_page(args: argparse.Namespace):
    """Serve the page (127.0.0.1 unless --ui-host, with a warning) and open the browser."""
    import webbrowser

    from mavcal.capture.web import LOCALHOST, CapturePage

    host = args.ui_host or LOCALHOST
    if host not in (LOCALHOST, "localhost"):
        print(f"mavcal: WARNING: the capture page is served on {host}, not only on this computer: anyone who can "
              "reach it and has its address (with the token) can write to the vehicle", file=sys.stderr)
    try:
        page = CapturePage(host, args.ui_port).start()
    except OSError as exc:
        raise UsageError(f"--ui: cannot serve the page on {host}:{args.ui_port}: {exc}") from None
    print(f"capture page: {page.url}", file=sys.stderr)
    if not args.no_browser:
        try:
            opened = webbrowser.open(page.url)
        except Exception:  # any browser launcher failure: the address is printed
            opened = False
        if not opened:
            print("mavcal: no browser found; open the address above", file=sys.stderr)
    sys.stderr.flush()
    return page


def _page_hooks(page, printer, config, args: argparse.Namespace):
    """(on_status, extra capture_live arguments) that also feed the page: every status (and a
    'finish without' asked on the page, told to the session on the capture's thread) and every
    batch (the live attitude)."""
    from mavcal.capture.pagestate import PageFeed

    feed = PageFeed(page.state.set, config, args.accel, args.compass)

    def on_status(st) -> None:
        printer(st)
        feed.status(st, finish=page.take_finish(), skip=page.take_skip())

    return on_status, {"on_batch": feed.batch}


def _page_report(args: argparse.Namespace, run) -> str | None:
    """The HTML report for the page's link: --report's file, else one made in a temporary
    directory (None without matplotlib)."""
    import tempfile
    from pathlib import Path

    from mavcal.report.html import missing_dependencies

    if args.report:
        path = Path(args.report)
        return path.read_text(encoding="utf-8") if path.is_file() else None
    if missing_dependencies():
        return None
    from mavcal.report import write_html

    with tempfile.TemporaryDirectory(prefix="mavcal-page-") as d:
        return write_html(run, Path(d) / "report.html").read_text(encoding="utf-8")


class _Tee:
    """Writes to a stream and keeps a copy (the writer's words, for the page)."""

    def __init__(self, stream: TextIO) -> None:
        self.stream, self.parts = stream, []

    def write(self, text: str) -> int:
        self.parts.append(text)
        return self.stream.write(text)

    def flush(self) -> None:
        self.stream.flush()

    def text(self) -> str:
        return "".join(self.parts)


def _page_flow(args: argparse.Namespace, page, run, changes: dict) -> int:
    """Show the verdict and the parameters on the page, wait for Write (confirmed there) or
    Don't write, then write through the safe writer; the page shows the outcome."""
    from mavcal.capture.pagestate import result_view

    view = result_view(run, changes, hints=PAGE_HINTS)
    page.report_html = _page_report(args, run)
    page.state.set(phase="result", result=view, report=f"report?t={page.token}" if page.report_html else None)
    try:
        code = write_outputs(run, args, f"mavcal guided capture on {args.connect}", param_table=False)
    except GateError:
        page.state.set(phase="declined")
        raise
    if args.dry_run:
        write_with_report(args, changes, args.backup, "calibration write")
        page.state.set(phase="declined", error="dry run: nothing written")
        return code
    if not view["n_write"]:
        page.state.set(phase="declined")
        print("nothing to write: the vehicle already has these values")
        return code
    if args.write and args.yes:
        decision = "write"
    else:
        page.offer(view["n_write"])
        print(f"waiting for Write or Don't write on the page ({page.url}); Ctrl-C: nothing written",
              file=sys.stderr)
        decision = page.wait_decision(args.ui_wait)
    if decision != "write":
        page.state.set(phase="declined")
        print("nothing written to the vehicle" + (" (no answer on the page)" if decision is None else ""))
        return code
    page.state.set(phase="writing")
    tee = _Tee(sys.stdout)
    try:  # confirmed on the page (its dialog) or by --write --yes
        write_with_report(replace_ns(args, yes=True), changes, args.backup, "calibration write", out=tee)
    except MavcalError as exc:
        page.state.set(phase="failed", write={"message": str(exc), "text": tee.text()})
        raise
    page.state.set(phase="written", write={"text": tee.text()})
    return code


def replace_ns(ns: argparse.Namespace, **kw) -> argparse.Namespace:
    """A copy of ``ns`` with some attributes changed."""
    d = dict(vars(ns))
    d.update(kw)
    return argparse.Namespace(**d)
