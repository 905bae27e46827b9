"""What MAVLink itself says, the same for every autopilot: the MAV_CMD numbers mavcal sends or
recognises, and what a parameter name may be (``PARAM_SET``'s 16-character ``param_id``)."""
from __future__ import annotations

import re

__all__ = ["MAV_AUTOPILOT_PX4",
           "MAV_CMD", "MAV_CMD_PREFLIGHT_CALIBRATION", "MAV_CMD_SET_MESSAGE_INTERVAL", "MAV_CMD_ACCELCAL_VEHICLE_POS",
           "valid_param_name"]

#: HEARTBEAT.autopilot of a PX4 (MAV_AUTOPILOT_PX4, common.xml): the one place that says it
MAV_AUTOPILOT_PX4 = 12

#: The one table of the MAV_CMD numbers mavcal sends or recognises in logs (common.xml /
#: ardupilotmega.xml; the same values as pymavlink's ``mavlink.MAV_CMD_*``, kept here so that
#: modules that must not import pymavlink can name them).
MAV_CMD = {
    "MAV_CMD_PREFLIGHT_CALIBRATION": 241,
    "MAV_CMD_PREFLIGHT_SET_SENSOR_OFFSETS": 242,
    "MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN": 246,
    "MAV_CMD_SET_MESSAGE_INTERVAL": 511,
    "MAV_CMD_FIXED_MAG_CAL_YAW": 42006,
    "MAV_CMD_DO_START_MAG_CAL": 42424,
    "MAV_CMD_DO_ACCEPT_MAG_CAL": 42425,
    "MAV_CMD_DO_CANCEL_MAG_CAL": 42426,
    "MAV_CMD_ACCELCAL_VEHICLE_POS": 42429,
}
MAV_CMD_PREFLIGHT_CALIBRATION = MAV_CMD["MAV_CMD_PREFLIGHT_CALIBRATION"]
MAV_CMD_SET_MESSAGE_INTERVAL = MAV_CMD["MAV_CMD_SET_MESSAGE_INTERVAL"]
MAV_CMD_ACCELCAL_VEHICLE_POS = MAV_CMD["MAV_CMD_ACCELCAL_VEHICLE_POS"]

#: names accepted: at most 16 characters (AP_MAX_NAME_SIZE), upper case, digits, '_'
_NAME_RE = re.compile(r"^[A-Z0-9_]{1,16}$")


def valid_param_name(name: str) -> bool:
    """True if ``name`` is a syntactically valid ArduPilot parameter name (<= 16, ``[A-Z0-9_]``)."""
    return bool(_NAME_RE.match(name))
