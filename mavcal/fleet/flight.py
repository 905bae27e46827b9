"""A fleet's flight logs: the in-flight compass check (``mavcal flight LOG``) over many logs.

Each log is what ``mavcal flight`` of it alone says (:func:`mavcal.flight.stage.analyse` of
its :func:`mavcal.sources.flight_series.read_flight_series`, the same ``--yaw`` and
``--driver``), reduced in the worker to one flat row of the results table (:data:`FLIGHT`):
per compass its verdict, the interference at the flight's highest current as compassmot
measures it (% of the Earth field), the ``COMPASS_MOT`` fit with its 95 % bounds, the offsets
fitted with theirs, and whether it is wrong in flight. The same inputs, ``--table``, engines
(the fork pool, a Dask cluster) and progress as ``mavcal calibrate`` over many logs
(:func:`mavcal.fleet.run.run_fleet` with ``kind="flight"``).

**Interference over time** (:class:`InterferenceLog`): per vehicle (the firmware and the
compasses' device ids, as the log tells), its flights in time order (a log's start time where
it has one, else its name, which downloads usually carry the date in), and a vehicle is
flagged when a compass's interference grew from one flight to the next by more than
:data:`INTERFERENCE_GROWTH_PCT` percentage points of the Earth field: half of ArduPilot's grey
band (30-60 %), so a compass that moved from fine to bad across two flights is always flagged,
and ordinary flight-to-flight scatter is not. The interference is taken at each flight's highest
current, so a much harder flight shows more of it: the page shows the steps to judge.
"""
from __future__ import annotations

import math
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from mavcal.errors import EXIT_PARTIAL, MavcalError
from mavcal.fleet.table import Layout, utc

__all__ = ["FLIGHT", "FLIGHT_COLUMNS", "FlightOptions", "FlightRow", "InterferenceLog", "VehicleInterference",
           "INTERFERENCE_GROWTH_PCT", "analyse_one", "failed_row", "flat_flight_row", "interference_over_time",
           "interference_text", "interference_html", "format_flight_table", "N_COMPASSES", "PRINTED_MAX"]

#: A fleet run with --table prints its table at the end up to this many logs
PRINTED_MAX = 1000

#: Compasses with columns in the table (ArduPilot's three)
N_COMPASSES = 3
#: A compass's interference growing from one flight to the next by more than this (percentage
#: points of the Earth field) flags its vehicle: half of ArduPilot's grey band, 30-60 %.
INTERFERENCE_GROWTH_PCT = 15.0

_XYZ = ("x", "y", "z")


def _compass_cols(k: int) -> list[tuple[str, type]]:
    c = f"compass{k}_"
    cols: list[tuple[str, type]] = [
        (c + "dev_id", int), (c + "in_use", bool), (c + "result", str), (c + "level", str), (c + "accepted", bool),
        (c + "wrong", bool), (c + "causes", str), (c + "not_written_because", str),
        (c + "interference_pct", float), (c + "interference_left_pct", float)]
    for name, unit in (("mot", ""), ("mot_bound95", ""), ("mot_in_force", ""), ("ofs", "_mgauss"),
                       ("ofs_bound95", "_mgauss"), ("ofs_in_force", "_mgauss")):
        cols += [(f"{c}{name}_{a}{unit}", float) for a in _XYZ]
    return cols + [(c + "rotation_deg", float), (c + "delay_s", float), (c + "rms_before_mgauss", float),
                   (c + "rms_after_mgauss", float), (c + "samples", int)]


#: The flight table's columns and their types, in order (the key columns first, as every table's)
FLIGHT_TYPES: dict[str, type] = dict([
    ("source", str), ("content_sha256", str), ("size_bytes", int), ("mavcal_version", str),
    ("log_start_utc", str), ("finished_utc", str), ("ok", bool), ("exit_code", int), ("result", str), ("error", str),
    ("firmware", str), ("driver", str), ("motct_in_force", int), ("yaw_source", str), ("field_source", str),
    ("rotation_reference", str), ("n_compasses", int),
    *[col for k in range(N_COMPASSES) for col in _compass_cols(k)],
    ("warnings", str), ("elapsed_s", float),
])
FLIGHT_COLUMNS: tuple[str, ...] = tuple(FLIGHT_TYPES)
#: ``mavcal flight``'s table
FLIGHT = Layout(FLIGHT_TYPES, frozenset(["warnings", *(f"compass{k}_{c}" for k in range(N_COMPASSES)
                                                       for c in ("causes", "not_written_because"))]))


@dataclass(frozen=True)
class FlightOptions:
    """What every log of a fleet's flight run is analysed with (``mavcal flight``'s options)."""

    yaw: str = "ekf"
    driver: str = "auto"


@dataclass(frozen=True)
class FlightRow:
    """One log's in-flight result, small (made in the worker): ``cells`` are the table's columns
    other than the key ones (:func:`flat_flight_row` adds those)."""

    source: str
    ok: bool
    exit_code: int
    error: str | None = None
    cells: tuple[tuple[str, object], ...] = ()
    elapsed_s: float = 0.0


def _one_line(s: str) -> str:
    return " | ".join(part.strip() for part in str(s).splitlines() if part.strip())


def _num(x) -> float | None:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def failed_row(source: str, exc: BaseException, options: object = None) -> FlightRow:
    """The row of a log that could not be analysed (its error's exit code; 70 for any other)."""
    code = int(exc.exit_code) if isinstance(exc, MavcalError) else 70
    return FlightRow(source, False, code, _one_line(str(exc)) or type(exc).__name__)


def analyse_one(path: str, source: str, options: FlightOptions) -> FlightRow:
    """``mavcal flight`` of the log at ``path`` (named ``source``) alone, as a table row."""
    from mavcal.autopilot import model_named
    from mavcal.flight.stage import analyse
    from mavcal.sources.flight_logs import read_flight_log

    t0 = time.perf_counter()
    try:
        s = read_flight_log(path)
        r = analyse(s, yaw=options.yaw, driver=options.driver)
    except MavcalError as exc:
        return FlightRow(source, False, int(exc.exit_code), _one_line(str(exc).replace(path, source)),
                         elapsed_s=time.perf_counter() - t0)
    except Exception as exc:  # a bug on one log fails its row (exit 70), never the fleet
        return FlightRow(source, False, 70, f"internal error: {type(exc).__name__}: {_one_line(str(exc))}",
                         elapsed_s=time.perf_counter() - t0)
    cells: dict[str, object] = {
        "firmware": s.evidence.firmware or None, "driver": r.driver_kind, "motct_in_force": r.motct_in_force,
        "yaw_source": r.yaw_source, "field_source": r.field_source, "rotation_reference": r.rotation_reference,
        "n_compasses": len(r.compasses), "warnings": "; ".join(_one_line(w) for w in r.warnings)}
    model = model_named(s.autopilot).flight()
    logged_ids = {c.instance: c.device_id for c in s.compasses if c.device_id}
    for k in range(N_COMPASSES):
        dev = logged_ids.get(k)
        if dev is None:  # a .bin: the device id is the parameter's of that compass's slot
            name = model.id_name(k)
            dev = s.params.get(name) if name else None
        cells[f"compass{k}_dev_id"] = int(dev) if dev is not None and int(dev) != 0 else None
    for c in r.compasses:
        if not 0 <= c.instance < N_COMPASSES or c.fit is None:
            continue
        v, f, p = c.verdict, c.fit, f"compass{c.instance}_"
        cells.update({
            p + "in_use": c.in_use, p + "result": "WRONG" if v.wrong else ("fine" if v.accepted else "not accepted"),
            p + "level": v.level, p + "accepted": v.accepted, p + "wrong": v.wrong,
            p + "causes": "; ".join(_one_line(x) for x in v.causes),
            p + "not_written_because": _one_line(v.not_written_because or ""),
            p + "interference_pct": _num(v.interference_pct),
            p + "interference_left_pct": _num(v.interference_left_pct),
            p + "rotation_deg": _num(v.rotation_deg), p + "delay_s": _num(f.delay_s),
            p + "rms_before_mgauss": _num(f.rms_before_mgauss), p + "rms_after_mgauss": _num(f.rms_after_mgauss),
            p + "samples": int(f.n_samples)})
        for name, unit, vec in (("mot", "", f.mot_per_unit), ("mot_bound95", "", f.mot_bound95_per_unit),
                                ("mot_in_force", "", c.mot_in_force), ("ofs", "_mgauss", f.ofs_mgauss),
                                ("ofs_bound95", "_mgauss", f.ofs_bound95_mgauss),
                                ("ofs_in_force", "_mgauss", c.ofs_in_force_mgauss)):
            for i, a in enumerate(_XYZ):
                cells[f"{p}{name}_{a}{unit}"] = _num(vec[i])
    bad = any(c.verdict.wrong or not c.verdict.accepted for c in r.compasses)
    return FlightRow(source, True, EXIT_PARTIAL if bad else 0, None, tuple(cells.items()),
                     time.perf_counter() - t0)


def _result(row: FlightRow) -> str:
    if not row.ok:
        return f"ERROR {row.exit_code}"
    cells = dict(row.cells)
    if any(cells.get(f"compass{k}_wrong") for k in range(N_COMPASSES)):
        return "WRONG"
    return "NOT ACCEPTED" if row.exit_code else "FINE"


def flat_flight_row(row: FlightRow, sha256: str, size: int, version: str) -> dict:
    """The flight table's row of a :class:`FlightRow` (every column of :data:`FLIGHT_COLUMNS`)."""
    out: dict = {"source": row.source, "content_sha256": sha256, "size_bytes": size, "mavcal_version": version,
                 "log_start_utc": None, "finished_utc": utc(time.time()), "ok": row.ok, "exit_code": row.exit_code,
                 "result": _result(row), "error": row.error, "elapsed_s": row.elapsed_s, "warnings": "",
                 **dict(row.cells)}
    for k in range(N_COMPASSES):
        out.setdefault(f"compass{k}_causes", "")
        out.setdefault(f"compass{k}_not_written_because", "")
    return {c: out.get(c) for c in FLIGHT_COLUMNS}


# --------------------------------------------------------------------------- the printed table

def format_flight_table(rows: Sequence[FlightRow]) -> str:
    """One line per log: its result and, per compass, its interference and verdict; a count line."""
    head = ["LOG", "RESULT", *(f"COMPASS{k}" for k in range(N_COMPASSES)), "DRIVER"]
    lines = []
    for r in rows:
        cells = dict(r.cells)
        per = []
        for k in range(N_COMPASSES):
            pct = cells.get(f"compass{k}_interference_pct")
            res = cells.get(f"compass{k}_result")
            per.append("-" if res is None else f"{pct:.0f}% {res}" if isinstance(pct, float) else str(res))
        lines.append([r.source.rsplit("/", 1)[-1], _result(r), *per, str(cells.get("driver") or "-")])
    widths = [max(len(x) for x in col) for col in zip(head, *lines)]
    out = ["  ".join(h.ljust(w) for h, w in zip(head, widths)).rstrip(),
           "  ".join("-" * w for w in widths)]
    out += ["  ".join(c.ljust(w) for c, w in zip(line, widths)).rstrip() for line in lines]
    for r in rows:
        if not r.ok:
            out.append(f"{r.source.rsplit('/', 1)[-1]}: {r.error}")
    n_fail = sum(1 for r in rows if not r.ok)
    n_bad = sum(1 for r in rows if r.ok and r.exit_code)
    out += ["", f"{len(rows)} logs: {len(rows) - n_fail - n_bad} fine, {n_bad} with a compass wrong or not accepted, "
                f"{n_fail} failed"]
    return "\n".join(out)


# --------------------------------------------------------------------------- interference over time

@dataclass(frozen=True)
class VehicleInterference:
    """One vehicle's flights in time order and, per compass, the interference of each.

    ``steps``: ``(from log, to log, compass, % before, % after)`` for consecutive flights where
    both have the compass fitted; ``flagged``: a step up by more than :data:`INTERFERENCE_GROWTH_PCT`."""

    vehicle: str
    logs: tuple[str, ...]
    series: tuple[tuple[float | None, ...], ...]  # per log: the interference % of compass 0, 1, 2
    steps: tuple[tuple[str, str, int, float, float], ...]
    flagged: bool


def _vehicle(r: dict) -> tuple:
    return (r.get("firmware"), *(r.get(f"compass{k}_dev_id") for k in range(N_COMPASSES)))


def _vehicle_name(k: tuple) -> str:
    fw, *ids = k
    devs = "/".join(str(i) for i in ids if i is not None) or "?"
    return f"{fw or 'firmware ?'}, compass device ids {devs}"


class InterferenceLog:
    """A fleet's flight rows reduced, one at a time, to what interference over time needs: per
    vehicle, each analysed flight's name, start time and per-compass interference (a small
    tuple; a failed log is counted, not kept)."""

    def __init__(self, rows: Iterable[dict] = ()) -> None:
        self.n_rows = 0
        self.vehicles: dict[tuple, list[tuple]] = {}
        for r in rows:
            self.add(r)

    def add(self, r: dict) -> None:
        self.n_rows += 1
        if r.get("ok"):
            pct = tuple(_num(r.get(f"compass{k}_interference_pct")) for k in range(N_COMPASSES))
            self.vehicles.setdefault(_vehicle(r), []).append((r.get("log_start_utc") or "", str(r["source"]), pct))


def _ilog(rows: Iterable[dict] | InterferenceLog) -> InterferenceLog:
    return rows if isinstance(rows, InterferenceLog) else InterferenceLog(rows)


def interference_over_time(rows: Iterable[dict] | InterferenceLog) -> list[VehicleInterference]:
    """Per vehicle with two analysed flights or more: each compass's interference from flight to flight."""
    out = []
    log = _ilog(rows)
    for k, recs in sorted(log.vehicles.items(), key=lambda kv: _vehicle_name(kv[0])):
        recs = sorted(recs, key=lambda t: (t[0], t[1]))
        if len(recs) < 2:
            continue
        steps = []
        for a, b in zip(recs, recs[1:]):
            for i in range(N_COMPASSES):
                x, y = a[2][i], b[2][i]
                if x is not None and y is not None:
                    steps.append((a[1], b[1], i, x, y))
        flagged = any(y - x > INTERFERENCE_GROWTH_PCT for _, _, _, x, y in steps)
        out.append(VehicleInterference(_vehicle_name(k), tuple(r[1] for r in recs), tuple(r[2] for r in recs),
                                       tuple(steps), flagged))
    return out


def interference_text(rows: Iterable[dict] | InterferenceLog) -> str:
    """The summary: per vehicle with two analysed flights or more, whether a compass's interference
    grew beyond the threshold, and the largest growth; "" if no vehicle has two flights."""
    vs = interference_over_time(rows)
    if not vs:
        return ""
    out = ["", f"interference over time (the flights of one vehicle in time order; grew: a compass's interference "
               f"up by more than {INTERFERENCE_GROWTH_PCT:g} points of the Earth field from one flight to the next):"]
    for v in vs:
        if v.steps:
            a, b, i, x, y = max(v.steps, key=lambda s: s[4] - s[3])
            step = f"largest rise compass{i} {x:.0f} % -> {y:.0f} % ({a.rsplit('/', 1)[-1]} -> {b.rsplit('/', 1)[-1]})"
        else:
            step = "no compass fitted in two flights"
        out.append(f"  {v.vehicle}: {len(v.logs)} flights, {'GREW' if v.flagged else 'steady'}; {step}")
    return "\n".join(out)


def interference_html(rows: Iterable[dict] | InterferenceLog) -> str:
    """A self-contained HTML page (no script, nothing fetched from elsewhere): the summary, and for
    each vehicle whose interference grew a plot of each compass's interference over its flights."""
    from html import escape

    from mavcal.fleet.drift import line_plot

    log = _ilog(rows)
    vs = interference_over_time(log)
    flagged = [v for v in vs if v.flagged]
    body = ["<h1>mavcal: compass interference over time</h1>",
            f"<p>{log.n_rows} logs, {len(vs)} vehicle(s) with two analysed flights or more, {len(flagged)} whose "
            f"interference grew by more than {INTERFERENCE_GROWTH_PCT:g} points of the Earth field from one flight "
            "to the next (at each flight's highest current, as compassmot measures it).</p>"]
    if not vs:
        body.append("<p>No vehicle has two analysed flights yet: nothing to compare.</p>")
    body.append("<ul>" + "".join(f"<li>{escape(v.vehicle)}: {len(v.logs)} flights, "
                                  f"<b>{'GREW' if v.flagged else 'steady'}</b></li>" for v in vs) + "</ul>")
    for v in flagged:
        body.append(f"<h2>{escape(v.vehicle)}</h2>")
        body.append(line_plot("interference at the highest current", "% of the Earth field", list(v.series), v.logs,
                              names=tuple(f"compass{k}" for k in range(N_COMPASSES))))
        body.append("<ol>" + "".join(f"<li>{escape(s)}</li>" for s in v.logs) + "</ol>")
        body.append("<table><tr><th>step</th><th>compass</th><th>%</th></tr>" + "".join(
            f"<tr><td>{escape(a.rsplit('/', 1)[-1])} → {escape(b.rsplit('/', 1)[-1])}</td><td>{i}</td>"
            f"<td>{x:.0f} → {y:.0f}</td></tr>" for a, b, i, x, y in v.steps) + "</table>")
    style = ("body{font-family:sans-serif;max-width:60em;margin:1em auto}"
             "table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:2px 6px}")
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>mavcal: compass interference "
            f"over time</title><style>{style}</style></head><body>\n" + "\n".join(body) + "\n</body></html>\n")
