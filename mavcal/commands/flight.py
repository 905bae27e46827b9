"""``mavcal flight LOG.bin``: the compasses in flight: motor and current interference, and which
compass is wrong, from an ordinary flight log.

Per compass: the calibration in force undone as logged, the firmware's in-flight model
(offsets and the motor term per amp or per full throttle) fitted against a
reference the compass cannot bend (the EKF's roll and pitch, the field's down component and
horizontal length from the World Magnetic Model), with the delay between current and field
estimated and 95 % bounds on each term; the verdict in words (:mod:`mavcal.flight.verdict`).

Exit codes: 0 done (every compass accepted or fine); 7 some compass wrong or not accepted
(the outputs are written); 3 unreadable log; 4 too little data (no flight in the log, no
current sensor); 2 bad options; with ``--write``: 5/6 the write failed (restored / not), 11 the
connected vehicle is not the log's.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mavcal.commands.common import add_json_argument
from mavcal.errors import EXIT_PARTIAL, UsageError

if TYPE_CHECKING:  # the stage (numpy, the field model) is imported when the command runs, not by --help
    from mavcal.flight.stage import FlightResult

HELP = "fit the compasses' motor/current interference from a flight log and say which compass is wrong"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = ("exit codes:\n  0  every compass fine or accepted   7  a compass wrong or not accepted\n"
                     "  3  unreadable log   4  too little data   2  bad options   70  internal error\n"
                     "  5  write failed, vehicle restored   6  write and restore failed\n"
                     "  11 the connected vehicle is not the log's (nothing written)")
    parser.add_argument("log", metavar="LOG", nargs="+",
                        help="flight log: ArduPilot DataFlash (.bin), PX4 ULog (.ulg) or tlog; several, a directory, "
                             "a glob, @LIST or a URL: a fleet (docs/fleet.md)")
    add_json_argument(parser)
    parser.add_argument("--param-out", metavar="FILE", default=None,
                        help="write the motor compensation (its type, the accepted compasses' terms) to this .param")
    parser.add_argument("--driver", choices=("auto", "current", "throttle"), default="auto",
                        help="what drives the interference: the battery current or the throttle; "
                             "auto: the compensation type in force, else the current (a log without a current "
                             "sensor is refused: the throttle only when asked)")
    parser.add_argument("--html", metavar="FILE", default=None,
                        help="write a self-contained HTML report with pictures per compass (needs matplotlib: "
                             "pip install 'mavcal[plots]')")
    parser.add_argument("--yaw", choices=("ekf", "gsf", "auto"), default="ekf",
                        help="the yaw used for the heading checks: the EKF's, or the EKF-GSF estimator's "
                             "(compass-independent; samples where it has not converged are left out)")
    add_write_arguments(parser)
    from mavcal.fleet.flight_cli import add_fleet_arguments

    add_fleet_arguments(parser)


def add_write_arguments(parser: argparse.ArgumentParser) -> None:
    """``--write`` with the vehicle link's options: the accepted compasses' compensation written to
    the vehicle through the safe writer (as ``mavcal calibrate --write``)."""
    from mavcal.commands.common import BACKUP_HELP, add_link_arguments

    w = parser.add_argument_group("writing to the vehicle")
    w.add_argument("--write", action="store_true",
                   help="write the accepted compasses' compensation to the vehicle (--connect; backup, read-back, "
                        "restore on failure); refused when the vehicle is not the log's (system id, device ids)")
    w.add_argument("--backup", metavar="F", default=None, help=BACKUP_HELP)
    add_link_arguments(w)  # type: ignore[arg-type]


def write_to_vehicle(args: argparse.Namespace, r: FlightResult, say) -> int:
    """Write ``param_values(r)`` to ``args.connect`` with the safe writer, once the vehicle is
    found to be the log's (:func:`vehicle_is_the_logs`)."""
    from mavcal.commands.common import check_new_backup, write_with_report
    from mavcal.flight.stage import param_values

    params = param_values(r)
    if not params:
        print("no compass accepted: nothing to write to the vehicle", file=say)
        return 0
    check_new_backup(args.backup)
    written = [c.id_name for c in r.compasses if c.id_name and c.verdict.accepted and c.compensation]
    return write_with_report(args, params, args.backup, "in-flight compensation write", out=say,
                             vehicle_check=lambda link, table: vehicle_is_the_logs(link, r, written, args))


def vehicle_is_the_logs(link, r: FlightResult, id_names: list[str], args: argparse.Namespace) -> None:
    """:class:`WrongVehicleError` when the connected vehicle's system id (its heartbeat) or the device
    id of a compass to be written differs from the log's; a value the log lacks is not compared."""
    from mavcal.errors import WrongVehicleError
    from mavcal.link.writer import fetch_for_write

    diff = []
    sysid_name = r.sysid_param
    if sysid_name in r.identity and int(r.identity[sysid_name]) != int(link.target_system):
        diff.append(f"system id {int(link.target_system)} (the log's {sysid_name} is {int(r.identity[sysid_name])})")
    names = [n for n in id_names if n in r.identity]
    have = fetch_for_write(link, [], context=names, timeout_s=args.param_timeout) if names else {}
    for n in names:
        if n in have and int(have[n][0]) & 0xFFFFFFFF != int(r.identity[n]) & 0xFFFFFFFF:
            diff.append(f"{n} {int(have[n][0])} (the log's {int(r.identity[n])})")
    if diff:
        raise WrongVehicleError("the connected vehicle is not the one the log comes from: it has "
                                + "; ".join(diff) + "; nothing written")


def _f(x: Any) -> Any:
    if hasattr(x, "tolist"):
        return _f(x.tolist())
    if isinstance(x, (list, tuple)):
        return [_f(v) for v in x]
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    return x


def to_json(r: FlightResult) -> dict[str, Any]:
    from mavcal.flight.stage import param_values

    comp = []
    for c in r.compasses:
        f, v = c.fit, c.verdict
        assert f is not None
        comp.append({
            "compass": c.instance, "in_use": c.in_use, "accepted": v.accepted, "wrong": v.wrong,
            "causes": list(v.causes), "advice": list(v.advice), "not_written_because": v.not_written_because or None,
            "interference_pct": _f(v.interference_pct), "interference_left_pct": _f(v.interference_left_pct),
            "level": v.level, "mot_per_unit": _f(f.mot_per_unit), "mot_bound95_per_unit": _f(f.mot_bound95_per_unit),
            "mot_fitted": f.fitted_mot, "mot_in_force": _f(c.mot_in_force),
            "ofs_mgauss": _f(f.ofs_mgauss), "ofs_bound95_mgauss": _f(f.ofs_bound95_mgauss), "ofs_fitted": f.fitted_ofs,
            "ofs_in_force_mgauss": _f(c.ofs_in_force_mgauss), "offset_lack_mgauss": _f(v.offset_lack_mgauss),
            "rotation_deg": _f(v.rotation_deg), "delay_s": f.delay_s, "sigma_mgauss": _f(f.sigma_mgauss),
            "bound_inflation": _f(f.inflation), "field_ned_mgauss": _f(f.B_ned_mgauss),
            "field_bound95_mgauss": _f(f.B_bound95_mgauss), "driver_span": _f(f.driver_span),
            "driver_max": _f(f.driver_max), "heading_span_deg": _f(f.heading_span_deg),
            "rms_before_mgauss": _f(f.rms_before_mgauss), "rms_after_mgauss": _f(f.rms_after_mgauss),
            "heading_error_before_deg": _f(f.heading_err_before_deg),
            "heading_error_after_deg": _f(f.heading_err_after_deg),
            "heading_error_vs_gsf_before_deg": _f(c.gsf_heading_err_deg[0]),
            "heading_error_vs_gsf_after_deg": _f(c.gsf_heading_err_deg[1]), "samples": f.n_samples,
            "missing_params": list(c.missing_params), "summary": v.summary})
    return {"source": r.source, "autopilot": r.autopilot, "driver": r.driver_kind, "motct_in_force": r.motct_in_force,
            "yaw_source": r.yaw_source, "field_source": r.field_source, "rotation_reference": r.rotation_reference,
            "field_model_ned_mgauss": _f(r.B0_ned_mgauss), "compasses": comp, "parameters": param_values(r),
            "warnings": list(r.warnings)}


def summary_text(r: FlightResult) -> str:
    unit = "A" if r.driver_kind == "current" else "(throttle)"
    lines = [f"mavcal flight: {r.source}",
             f"  interference driver: {r.driver_kind}; yaw for the checks: {r.yaw_source}"
             + (" (fused from the compasses: not independent)" if r.yaw_source == "ekf" else " (compass-independent)")
             + "; rotation judged against: "
             + ("the EKF-GSF yaw (compass-independent)" if r.rotation_reference == "gsf" else
                "nothing (no compass-independent yaw in the log)")
             + f"; field: {r.field_source} ({', '.join(f'{v:.0f}' for v in r.B0_ned_mgauss)} mGauss NED)"]
    for c in r.compasses:
        v, f = c.verdict, c.fit
        assert f is not None
        lines.append(f"compass{c.instance}: {v.summary}")
        if v.wrong:
            lines.append(f"compass{c.instance}: WRONG in flight: " + "; ".join(v.causes)
                         + (" -> " + "; ".join(v.advice) if v.advice else ""))
        elif v.advice:
            lines.append(f"  advice: {'; '.join(v.advice)}")
        if math.isfinite(c.gsf_heading_err_deg[0]):
            lines.append(f"  heading against the compass-independent (GSF) yaw: {c.gsf_heading_err_deg[0]:.1f} -> "
                         f"{c.gsf_heading_err_deg[1]:.1f} deg RMS (logged -> fitted)")
        if not v.accepted:
            lines.append(f"  not written: {v.not_written_because}")
        lines.append(f"  max {r.driver_kind} {f.driver_max:.3g} {unit}; rms field error {f.rms_before_mgauss:.1f} -> "
                     f"{f.rms_after_mgauss:.1f} mGauss; offsets fit {', '.join(f'{x:.0f}' for x in f.ofs_mgauss)} "
                     f"+- {', '.join(f'{x:.0f}' for x in f.ofs_bound95_mgauss)} mGauss")
    lines += [f"warning: {w}" for w in r.warnings]
    return "\n".join(lines)


def _atomic_write(path: str, write) -> None:
    p = Path(path)
    d = p.parent if str(p.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", dir=d)
    os.close(fd)
    os.unlink(tmp)
    try:
        write(tmp)
        os.replace(tmp, p)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _run_with_html(args: argparse.Namespace) -> FlightResult:
    """The stage on the log, and its HTML report written to ``--html`` (matplotlib checked first)."""
    if args.html == "-":
        raise UsageError("--html needs a file name")
    from mavcal.report.flight_html import missing_dependencies, write_flight_html

    if missing_dependencies():
        raise UsageError("--html needs matplotlib: pip install 'mavcal[plots]'")
    from mavcal.flight.stage import analyse
    from mavcal.sources.flight_logs import read_flight_log

    s = read_flight_log(args.log)
    r = analyse(s, yaw=args.yaw, driver=args.driver)
    write_flight_html(s, r, args.html)
    print(f"HTML report written to {args.html}", file=sys.stderr if args.json == "-" else sys.stdout)
    return r


def run(args: argparse.Namespace) -> int:
    from mavcal.fleet.flight_cli import is_many, run_many

    if is_many(args):
        return run_many(args)
    args.log = args.log[0]
    for opt in ("json", "param_out", "html"):
        v = getattr(args, opt)
        if v not in (None, "-") and Path(v).resolve() == Path(args.log).resolve():
            raise UsageError(f"--{opt.replace('_', '-')} would overwrite the log")
    if args.param_out == "-":
        raise UsageError("--param-out needs a file name")
    if args.write and args.dry_run:
        raise UsageError("--dry-run shows what --write would change without writing: give one of them")
    from mavcal.autopilot.paramfile import write_param_file
    from mavcal.flight.stage import param_values

    r = _run_with_html(args) if args.html else None
    if r is None:
        from mavcal.flight.stage import run_flight

        r = run_flight(args.log, yaw=args.yaw, driver=args.driver)
    doc = to_json(r)
    say = sys.stderr if args.json == "-" else sys.stdout  # JSON alone on stdout with '-'
    print(summary_text(r), file=say)
    if args.json == "-":
        print(json.dumps(doc, indent=1))
    elif args.json:
        try:
            _atomic_write(args.json, lambda t: Path(t).write_text(json.dumps(doc, indent=1)))
        except OSError as exc:
            raise UsageError(f"cannot write the JSON report: {exc}") from None
        print(f"JSON report written to {args.json}", file=say)
    if args.param_out:
        params = param_values(r)
        if params:
            head = [f"mavcal flight {Path(args.log).name}: motor compensation of the accepted compasses"]
            _atomic_write(args.param_out, lambda t: write_param_file(t, params, header=head, exclusive=True))
            print(f"wrote {len(params)} parameters to {args.param_out}", file=say)
        else:
            print("no compass accepted: nothing written to " + args.param_out, file=say)
    if args.write or args.dry_run:
        write_to_vehicle(args, r, say)
    bad = any(c.verdict.wrong or not c.verdict.accepted for c in r.compasses)
    return EXIT_PARTIAL if bad else 0
