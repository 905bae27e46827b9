"""Quality gates applied before anything is written, per sensor, with reasons in words.

ArduPilot's own limits (AP_Compass arming checks and CompassCalibrator::fit_acceptable,
AccelCalibrator): compass offset length <= COMPASS_OFFS_MAX (default 1800 mGauss),
0.2 < DIA < 5, |ODI| < 1, field 185-875 mGauss; accelerometer offsets <= 3.5 m/s^2 per
axis, scales 0.8-1.2. Ours: enough intervals and orientations, held-out reconstruction
error, parameter uncertainty (95 % heading and tilt error bounds).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class GateConfig:
    accel_offset_max_mps2: float = 3.5
    accel_scale_range: tuple[float, float] = (0.8, 1.2)
    compass_offset_max_mgauss: float | None = None  # None: COMPASS_OFFS_MAX from the vehicle, else 1800
    dia_range: tuple[float, float] = (0.2, 5.0)
    odi_max: float = 1.0
    field_range_mgauss: tuple[float, float] = (185.0, 875.0)
    min_intervals: int = 6
    heading_95_max_deg: float = 2.0
    tilt_95_max_deg: float = 0.5
    holdout_accel_max_mps2: float = 0.15
    holdout_mag_max_mgauss: float = 15.0


@dataclass(frozen=True)
class Gate:
    sensor: str
    name: str
    ok: bool
    value: float
    limit: str
    reason: str = ""


@dataclass(frozen=True)
class GateReport:
    gates: tuple[Gate, ...]

    @property
    def passed(self) -> bool:
        return all(g.ok for g in self.gates)

    def failures(self) -> list[Gate]:
        return [g for g in self.gates if not g.ok]

    def by_sensor(self) -> dict[str, list[Gate]]:
        out: dict[str, list[Gate]] = {}
        for g in self.gates:
            out.setdefault(g.sensor, []).append(g)
        return out


def check(mapping, params: Mapping[str, float], *, n_intervals: int, n_orientations: int,
          heading_95_deg: float, tilt_95_deg: float, holdout_accel_mps2: float, holdout_mag_mgauss: float,
          config: GateConfig = GateConfig()) -> GateReport:
    """Evaluate every gate for a :class:`mavcal.ardupilot.mapping.ParamMapping`."""
    from mavcal.ardupilot import firmware as fw

    gates: list[Gate] = []

    def add(sensor: str, name: str, ok, value, limit: str, reason: str) -> None:
        """Record a gate; the reason is kept only when it failed."""
        gates.append(Gate(sensor, name, bool(ok), float(value), limit, "" if ok else reason))

    c = config
    for am in mapping.accel:
        s = f"accel{am.instance}"
        ofs = float(np.abs(np.asarray(am.new.ofs_mps2)).max())
        add(s, "offsets", ofs <= c.accel_offset_max_mps2, ofs, f"<= {c.accel_offset_max_mps2} m/s^2",
            f"accelerometer offset {ofs:.2f} m/s^2 is beyond ArduPilot's limit: a damaged IMU, "
            "or readings that are not in m/s^2")
        sc = np.asarray(am.new.scale)
        lo, hi = c.accel_scale_range
        add(s, "scales", np.all((sc >= lo) & (sc <= hi)), np.max(np.abs(sc - 1)), f"{lo}-{hi}",
            f"accelerometer scale {sc.min():.3f}..{sc.max():.3f} is outside ArduPilot's {lo}-{hi}: check the IMU "
            "and that the vehicle was still")
    for cm in mapping.compass:
        s = f"compass{cm.instance}"
        names = fw.compass_param_names(cm.instance)
        omax = c.compass_offset_max_mgauss or float(params.get("COMPASS_OFFS_MAX", 1800.0))
        ol = float(np.linalg.norm(cm.new.ofs_mgauss))
        add(s, "offsets", ol <= omax, ol, f"<= {omax:g} mGauss (COMPASS_OFFS_MAX)",
            f"compass offset length {ol:.0f} mGauss exceeds COMPASS_OFFS_MAX: a magnet or steel near the compass, "
            "or a magnetised part")
        dia = np.asarray(cm.new.dia)
        add(s, "diagonal", np.all((dia > c.dia_range[0]) & (dia < c.dia_range[1])), np.max(np.abs(dia - 1)),
            f"{c.dia_range[0]}-{c.dia_range[1]}", f"soft-iron diagonal {np.round(dia, 3)} outside ArduPilot's range")
        odi = float(np.abs(np.asarray(cm.new.odi)).max())
        add(s, "off-diagonal", odi < c.odi_max, odi, f"< {c.odi_max}", "soft-iron off-diagonal too large")
        f = cm.field_mgauss
        lo, hi = c.field_range_mgauss
        add(s, "field", lo <= f <= hi, f, f"{lo:g}-{hi:g} mGauss",
            f"field magnitude {f:.0f} mGauss is outside ArduPilot's arming range")
        dev = params.get(names["dev_id"])
        prio = params.get(names["prio_id"])
        if dev is not None and prio is not None and int(dev) != int(prio) and int(prio) != 0:
            add(s, "device id", False, dev, f"= COMPASS_PRIO{cm.instance + 1}_ID",
                f"compass slot {cm.instance + 1} holds device {int(dev)} but priority {cm.instance + 1} is device "
                f"{int(prio)}: the slots swapped after a priority change; reboot the vehicle and recalibrate")
    add("data", "intervals", n_intervals >= c.min_intervals, n_intervals, f">= {c.min_intervals}",
        f"only {n_intervals} still intervals; hold the vehicle still in more orientations")
    add("data", "orientations", n_orientations >= min(c.min_intervals, 6), n_orientations, ">= 6 distinct",
        f"only {n_orientations} distinct orientations; add poses on every side")
    add("data", "heading uncertainty", heading_95_deg <= c.heading_95_max_deg, heading_95_deg,
        f"<= {c.heading_95_max_deg} deg (95 %)",
        f"the heading error could reach {heading_95_deg:.2f} deg (95 %): more or better spread poses needed")
    add("data", "tilt uncertainty", tilt_95_deg <= c.tilt_95_max_deg, tilt_95_deg, f"<= {c.tilt_95_max_deg} deg (95 %)",
        f"the tilt error could reach {tilt_95_deg:.2f} deg (95 %)")
    add("data", "held-out accel error", holdout_accel_mps2 <= c.holdout_accel_max_mps2, holdout_accel_mps2,
        f"<= {c.holdout_accel_max_mps2} m/s^2",
        f"held-out accelerometer error {holdout_accel_mps2:.3f} m/s^2: the vehicle moved during the intervals or "
        "the model does not fit")
    add("data", "held-out compass error", holdout_mag_mgauss <= c.holdout_mag_max_mgauss, holdout_mag_mgauss,
        f"<= {c.holdout_mag_max_mgauss} mGauss",
        f"held-out compass error {holdout_mag_mgauss:.1f} mGauss: magnetic disturbance (steel, magnets, currents) "
        "differs between poses")
    return GateReport(tuple(gates))


def merge_reports(primary: GateReport, others: Sequence[tuple[int, int, GateReport]], *, accel_instance: int,
                  mag_instance: int) -> GateReport:
    """The primary pair's gates plus, from each other pair ``(accel, compass, report)``,
    the gates of its non-primary sensor and its data gates (named after the pair)."""
    gates = list(primary.gates)
    for a, m, rep in others:
        for g in rep.gates:
            if g.sensor == f"accel{a}" and a != accel_instance or g.sensor == f"compass{m}" and m != mag_instance:
                gates.append(g)
            elif g.sensor == "data":
                gates.append(Gate(f"data (accel{a}+compass{m})", g.name, g.ok, g.value, g.limit, g.reason))
    return GateReport(tuple(gates))
