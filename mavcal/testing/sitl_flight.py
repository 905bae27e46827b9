"""A short scripted flight of ArduPilot SITL's ``quad`` model, for the in-flight compass stage.

:func:`fly` takes a :class:`~mavcal.testing.sitl.SitlVehicle` started with ``model="quad"``
and flies (all in the simulator's own time, read from ``SYSTEM_TIME``-stamped messages, so a
loaded machine only makes it slower, never different): wait for the GPS and the EKF, GUIDED,
arm, take off, yaw turns in place, then legs of velocity set-points at changing speed and
climb rate with the nose turning (so the battery current varies widely while every heading is
seen), then LAND and wait for the disarm. It returns the DataFlash log SITL wrote (its working
directory's ``logs/``), copied to ``dest``.

:func:`flight_params` are the boot parameters a flight needs (``ARMING_CHECK 0`` for a test,
logging while armed only) plus the injected motor interference ``SIM_MAG_MOT_X/Y/Z``
(mGauss per amp, added to every simulated compass) and ``COMPASS_MOTCT``: with
``COMPASS_MOTCT 2`` the compensation that cancels it is ``COMPASS_MOT = -SIM_MAG_MOT``.

Used by ``tests/test_flight_sitl.py`` and ``benchmarks/flight.py``.
"""
from __future__ import annotations

import math
import shutil
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pymavlink import mavutil

from mavcal.testing.sitl import SitlError, SitlVehicle

__all__ = ["FlightPlan", "fly", "flight_params", "SHORT", "LONG"]

GUIDED, LAND = 4, 9
TYPE_MASK_VEL_YAW = 2503  # velocity and yaw used; position, acceleration and yaw rate ignored


@dataclass(frozen=True)
class FlightPlan:
    """What the scripted flight does (simulated seconds and metres)."""

    altitude_m: float = 12.0
    yaw_turns: int = 4  # 90-degree turns in place after the take-off
    legs: tuple[tuple[float, float, float], ...] = (
        # (duration s, horizontal speed m/s, climb rate m/s, positive up)
        (8.0, 3.0, 0.0), (8.0, 10.0, 0.0), (6.0, 4.0, 2.5), (6.0, 12.0, -1.5), (8.0, 6.0, 3.0),
        (8.0, 2.0, -2.0), (8.0, 14.0, 0.0))
    turn_rate_dps: float = 40.0  # the direction of travel (and the nose) turn at this rate
    timeout_s: float = 900.0  # wall-clock limit of the whole flight


SHORT = FlightPlan()
LONG = FlightPlan(legs=SHORT.legs * 3, yaw_turns=8)


def flight_params(sim_mag_mot: Sequence[float] = (0.0, 0.0, 0.0), *, motct: int = 2,
                  extra: Mapping[str, float] | None = None) -> dict[str, float]:
    """Boot parameters of a scripted flight with motor interference ``sim_mag_mot`` (mGauss/A)."""
    p = {"ARMING_CHECK": 0.0, "LOG_DISARMED": 0.0, "COMPASS_MOTCT": float(motct),
         "SIM_MAG_MOT_X": float(sim_mag_mot[0]), "SIM_MAG_MOT_Y": float(sim_mag_mot[1]),
         "SIM_MAG_MOT_Z": float(sim_mag_mot[2])}
    p.update(extra or {})
    return p


class _Link:
    """The flight's own MAVLink link on the vehicle's tool port (SERIAL1), in its namespace."""

    def __init__(self, sitl: SitlVehicle) -> None:
        with sitl.netns():
            self.conn: Any = mavutil.mavlink_connection(sitl.tool_device, source_system=253, source_component=190,
                                                        dialect="ardupilotmega")
        hb = self.conn.wait_heartbeat(timeout=30)
        if hb is None:
            raise SitlError("no heartbeat on the tool port")
        self.sys, self.comp = hb.get_srcSystem(), hb.get_srcComponent()
        self.sim_ms = 0
        self.rel_alt_m = 0.0
        self.fix = 0
        self.armed = False
        self.ekf_flags = 0
        self.texts: list[str] = []
        self.conn.mav.request_data_stream_send(self.sys, self.comp, mavutil.mavlink.MAV_DATA_STREAM_ALL, 10, 1)

    def pump(self, wall_s: float = 0.05) -> None:
        end = time.monotonic() + wall_s
        while True:
            m = self.conn.recv_match(blocking=True, timeout=max(0.0, end - time.monotonic()))
            if m is None:
                return
            t = m.get_type()
            if hasattr(m, "time_boot_ms"):
                self.sim_ms = max(self.sim_ms, int(m.time_boot_ms))
            if t == "GLOBAL_POSITION_INT":
                self.rel_alt_m = m.relative_alt / 1000.0
            elif t == "GPS_RAW_INT":
                self.fix = int(m.fix_type)
            elif t == "HEARTBEAT" and m.get_srcSystem() == self.sys and m.get_srcComponent() == self.comp:
                self.armed = bool(m.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            elif t == "STATUSTEXT":
                self.texts.append(m.text)
            elif t == "EKF_STATUS_REPORT":
                self.ekf_flags = int(m.flags)

    @property
    def sim_s(self) -> float:
        return self.sim_ms / 1000.0

    def wait(self, cond, sim_timeout_s: float, what: str, deadline: float) -> None:
        start = self.sim_s
        while not cond():
            if time.monotonic() > deadline:
                raise SitlError(f"flight: timed out waiting for {what}")
            if self.sim_s - start > sim_timeout_s:
                raise SitlError(f"flight: {what} did not happen within {sim_timeout_s:g} simulated s "
                               f"(vehicle said: {' | '.join(self.texts[-8:])})")
            self.pump()

    def sleep_sim(self, s: float, deadline: float, each=None) -> None:
        start = self.sim_s
        while self.sim_s - start < s:
            if time.monotonic() > deadline:
                raise SitlError("flight: timed out")
            if each is not None:
                each(self.sim_s - start)
            self.pump(0.05)

    def command(self, cmd: int, *params: float) -> None:
        p = (list(params) + [0.0] * 7)[:7]
        self.conn.mav.command_long_send(self.sys, self.comp, cmd, 0, *p)

    def command_acked(self, cmd: int, *params: float, deadline: float) -> None:
        for _ in range(20):
            self.command(cmd, *params)
            end = time.monotonic() + 2.0
            while time.monotonic() < end:
                m = self.conn.recv_match(type="COMMAND_ACK", blocking=True, timeout=0.2)
                if m is not None and m.command == cmd:
                    if m.result == 0:
                        return
                    break
            self.pump(0.5)
            if time.monotonic() > deadline:
                break
        raise SitlError(f"flight: command {cmd} refused")

    def velocity(self, vn: float, ve: float, vd: float, yaw_rad: float) -> None:
        self.conn.mav.set_position_target_local_ned_send(0, self.sys, self.comp, mavutil.mavlink.MAV_FRAME_LOCAL_NED,
                                                         TYPE_MASK_VEL_YAW, 0, 0, 0, vn, ve, vd, 0, 0, 0, yaw_rad, 0)


def fly(sitl: SitlVehicle, dest: str | Path, plan: FlightPlan = SHORT) -> Path:
    """Fly ``plan`` with ``sitl`` (``model="quad"``, booted with :func:`flight_params`) and copy
    the DataFlash log it wrote to ``dest``; returns ``dest``."""
    if sitl.workdir is None:
        raise SitlError("SITL is not running")
    deadline = time.monotonic() + plan.timeout_s
    link = _Link(sitl)
    ml = mavutil.mavlink
    link.wait(lambda: link.fix >= 3, 120, "a GPS fix", deadline)
    # the EKF's origin and its GPS use: attitude, horizontal position and absolute position flags
    need = ml.EKF_ATTITUDE | ml.EKF_POS_HORIZ_ABS | ml.EKF_VELOCITY_HORIZ
    link.wait(lambda: (link.ekf_flags & need) == need, 120, "the EKF's position", deadline)
    link.command_acked(ml.MAV_CMD_DO_SET_MODE, ml.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, GUIDED, deadline=deadline)
    link.command_acked(ml.MAV_CMD_COMPONENT_ARM_DISARM, 1, 21196, deadline=deadline)
    link.command_acked(ml.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, plan.altitude_m, deadline=deadline)
    link.wait(lambda: link.rel_alt_m > 0.9 * plan.altitude_m, 60, "the take-off altitude", deadline)
    for k in range(plan.yaw_turns):
        link.command(ml.MAV_CMD_CONDITION_YAW, (90.0 * (k + 1)) % 360.0, 90.0, 1, 0)
        link.sleep_sim(3.0, deadline)
    heading = [0.0]
    last = [time.monotonic()]
    for dur, speed, climb in plan.legs:
        def each(t: float, speed: float = speed, climb: float = climb) -> None:
            now = time.monotonic()
            if now - last[0] < 0.08:
                return
            last[0] = now
            psi = heading[0] + math.radians(plan.turn_rate_dps) * t
            vd = -climb if (climb <= 0 or link.rel_alt_m < 40) else 0.0
            if link.rel_alt_m < 5 and vd > 0:
                vd = 0.0
            link.velocity(speed * math.cos(psi), speed * math.sin(psi), vd, psi)
        link.sleep_sim(dur, deadline, each)
        heading[0] += math.radians(plan.turn_rate_dps) * dur
    link.command_acked(ml.MAV_CMD_DO_SET_MODE, ml.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, LAND, deadline=deadline)
    link.wait(lambda: not link.armed, 180, "the landing (disarm)", deadline)
    link.conn.close()
    logs = sorted((sitl.workdir / "logs").glob("*.BIN"), key=lambda p: p.stat().st_mtime)
    if not logs:
        raise SitlError("SITL wrote no DataFlash log")
    time.sleep(0.5)  # the logger's last writes after the disarm
    dest = Path(dest)
    shutil.copyfile(logs[-1], dest)
    return dest
