"""What any autopilot's gates say: one check (:class:`Gate`), a sensor's verdict
(:class:`SensorVerdict`) and all of a calibration's checks (:class:`GateReport`), in words a user can act on.
The thresholds and the checks themselves are each autopilot's (:meth:`mavcal.autopilot.AutopilotModel.gate_config`)."""
from __future__ import annotations

from dataclasses import dataclass

from mavcal.determined import LIMIT_DEG, determined

__all__ = ["EARTH_FIELD_MGAUSS", "Gate", "SensorVerdict", "GateReport", "CAUSE_IN_FORCE", "YES_NO_GATES", "reason_text"]

#: Earth's field strength anywhere (World Magnetic Model: about 220 mGauss in the South Atlantic
#: anomaly to 670 near the magnetic poles), the plausibility check of a compass whose field
#: strength is not known (no position, no --field-mgauss)
EARTH_FIELD_MGAUSS = (220.0, 680.0)


@dataclass(frozen=True)
class Gate:
    """One check of one sensor: ``value`` in the same terms as ``limit``; ``ran`` False when
    the check could not run (value NaN, e.g. no interval to hold out), which never rejects."""

    sensor: str
    name: str
    ok: bool
    value: float
    limit: str
    reason: str = ""
    ran: bool = True
    cause: str = ""  # "data" when it failed because the intervals cannot identify the sensor


@dataclass(frozen=True)
class SensorVerdict:
    """Accepted, or rejected with the reasons (gate, value, limit, what to do)."""

    sensor: str  # accel0, accel1, compass0, ...
    accepted: bool
    reasons: tuple[str, ...] = ()


#: the cause of the gate a sensor whose calibration in force is not known fails (:mod:`mavcal.in_force`):
#: it comes first in the verdict, and no ``--force`` writes that sensor
CAUSE_IN_FORCE = "in force"

#: gates that are a yes/no question (value 1 yes, 0 no): their reason alone says it all
#: ("fit": the sensor's fit gave a result; no when its worker process died)
YES_NO_GATES = ("converged", "fit")


def reason_text(g: Gate) -> str:
    """The reason of a failed gate in words a user can act on: the gate, what to do, the value
    and the limit (a yes/no gate's value in words)."""
    if g.cause == CAUSE_IN_FORCE:  # "not written: ..." says it all
        return g.reason
    if g.name in YES_NO_GATES:
        return f"{g.name}: {g.reason} (value: {'yes' if g.value else 'no'}, limit: {g.limit})"
    kind = {"heading uncertainty": "heading", "tilt uncertainty": "tilt"}.get(g.name)
    if kind is not None and not determined(kind, g.value):  # no digits the data do not hold
        return f"{g.name}: {g.reason} (value above {LIMIT_DEG[kind]:g} deg, limit {g.limit})"
    return f"{g.name}: {g.reason} (value {g.value:.4g}, limit {g.limit})"


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

    def verdicts(self) -> tuple[SensorVerdict, ...]:
        """One verdict per sensor, in the order of the gates (accelerometers first). A sensor
        the data cannot identify gets only the data's reasons (a fit of too few directions
        fails the other gates too, and naming steel there would send the user the wrong way). A
        sensor whose calibration in force is not known says that first (it is never written)."""
        out = []
        for s, gs in self.by_sensor().items():
            failed = [g for g in gs if not g.ok]
            first = [g for g in failed if g.cause == CAUSE_IN_FORCE]
            rest = [g for g in failed if g.cause != CAUSE_IN_FORCE]
            shown = first + ([g for g in rest if g.cause == "data"] or rest)
            out.append(SensorVerdict(s, not failed, tuple(reason_text(g) for g in shown)))
        return tuple(out)

    def accepted_sensors(self) -> list[str]:
        return [v.sensor for v in self.verdicts() if v.accepted]

    def rejected_sensors(self) -> list[str]:
        return [v.sensor for v in self.verdicts() if not v.accepted]

    def not_known_sensors(self) -> list[str]:
        """The sensors whose calibration in force is not known: never written, not even with ``--force``."""
        return list(dict.fromkeys(g.sensor for g in self.gates if not g.ok and g.cause == CAUSE_IN_FORCE))
