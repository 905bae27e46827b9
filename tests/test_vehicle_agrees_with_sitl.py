"""The loopback test vehicle must keep agreeing with the real ArduPilot (SITL 4.7.0-dev).

One list of protocol probes (:data:`PROBES`) runs against BOTH vehicles -- the loopback
:class:`~mavcal.testing.vehicle.TestVehicle` and :class:`~mavcal.testing.sitl.SitlVehicle`'s
tool port (SERIAL1) -- through the same GCS client (:class:`~mavcal.testing.vehicle_probe.MavProbe`),
and each returns the observable outcome as a dict. The two dicts must be equal, except for the
keys listed in :data:`DIFFERENCES`: the places where the imitation deliberately differs, each
with its reason and the value each vehicle is expected to show (so a difference that goes away
is noticed too).

One SITL for the module (``wrong_calibration=False``, ``SIM_MAG_RND 0`` so the compass is as
noise-free as the loopback vehicle's; the accelerometer at rest is below 1 milli-g of noise),
and a loopback vehicle with noise-free sensors; both held still and level. A second GCS on
another channel (SITL's SERIAL2, a second client of the loopback vehicle) serves the channels
probe. The probes run on both vehicles at once (~75 s for the module). Every probe puts back
what it changed.

What SITL showed that the loopback vehicle had wrong (fixed there): device ids are writable
(no ``AP_PARAM_FLAG_INTERNAL_USE_ONLY`` on them; the flagged ``MIS_TOTAL`` is denied unless
``BRD_OPTIONS`` has bit 2); a set of a Vector3's Y or Z echoes only itself (X echoes all
three); an unknown rotation on an external compass raises "Internal Errors 0x400000" and
system_status CRITICAL; answers go to the asking channel only; heartbeat base_mode 81; an
unknown message interval id gets "No ap_message for mavlink id (N)".
"""
from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import pytest

from mavcal.ardupilot import firmware as fw
from mavcal.testing.vehicle import AccelCalTruth, CompassTruth, TestVehicle, VehicleTruth
from mavcal.testing.vehicle_params import COMPASS_DEV_IDS, N_IMUS
from mavcal.testing.vehicle_probe import MavProbe, Received, const

pytestmark = pytest.mark.sitl

REAL32, INT8, INT32 = (const("MAV_PARAM_TYPE_REAL32"), const("MAV_PARAM_TYPE_INT8"),
                       const("MAV_PARAM_TYPE_INT32"))
ACCEPTED, DENIED, UNSUPPORTED = (const("MAV_RESULT_ACCEPTED"), const("MAV_RESULT_DENIED"),
                                 const("MAV_RESULT_UNSUPPORTED"))
IMU_TYPES = {"RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3"}
NO_INDEX = 65535  # param_index of a PARAM_VALUE answering by name, or echoing a set (-1 as uint16)
QUIET_S = 1.5  # how long "no answer" is waited for


@dataclass
class Peer:
    name: str
    probe: MavProbe
    other: MavProbe  # a second GCS on another channel of the same vehicle


@dataclass(frozen=True)
class Difference:
    """A documented, deliberate difference: ``key`` of ``probe``'s outcome is ``loopback`` on
    the imitation and ``sitl`` on ArduPilot SITL, because ``reason``."""

    probe: str
    key: str
    loopback: object  # None: any value
    sitl: object
    reason: str


# ------------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------------
def _values(got: list[Received], name: str) -> list[float]:
    return [r["param_value"] for r in got if r.type == "PARAM_VALUE" and r["param_id"] == name]


def _texts(got: list[Received], about: tuple[str, ...] = ("Param ", "Internal Errors", "No ap_message")) -> list[str]:
    """The STATUSTEXTs about parameters, internal errors and message ids (SITL also reports
    its EKF and GPS as it boots, and its pre-arm failures every 30 s)."""
    return [r["text"] for r in got if r.type == "STATUSTEXT" and r["text"].startswith(about)]


def _set_echo(p: MavProbe, name: str, value: float) -> tuple[list[float], list[str], int]:
    """PARAM_SET and its answer: echoed values of ``name``, STATUSTEXTs, PARAM_ERROR count."""
    got = p.set_and_wait(name, value)
    return _values(got, name), _texts(got), sum(r.type == "PARAM_ERROR" for r in got)


def _restore(p: MavProbe, values: dict[str, float]) -> None:
    for n, v in values.items():
        vals, _, _ = _set_echo(p, n, v)
        assert vals and vals[-1] == pytest.approx(v, abs=1e-6), f"could not restore {n}"


def _read(p: MavProbe, names: list[str]) -> dict[str, float]:
    out = {}
    for n in names:
        r = p.read_param(n)
        assert r is not None, f"no answer for {n}"
        out[n] = r["param_value"]
    return out


def _near(rate_hz: float, want_hz: float) -> bool:
    """A measured stream rate is the requested one (within 30 %: a loaded machine jitters)."""
    return abs(rate_hz - want_hz) <= 0.3 * want_hz


def _f32(x: float) -> float:
    return float(np.float32(x))


def _imu(p: MavProbe, seconds: float = 0.4, settle_s: float = 0.8) -> list[Received]:
    """RAW_IMU messages after ``settle_s`` (a parameter change shows ~0.1 s after its echo;
    ArduPilot's 20 Hz accel filter settles within 0.5 s)."""
    p.collect(settle_s)
    return p.collect(seconds, {"RAW_IMU"})


# ------------------------------------------------------------------------------------------
# the probes (each returns the observable outcome as a dict)
# ------------------------------------------------------------------------------------------
def probe_heartbeat(p: MavProbe) -> dict:
    hbs = p.collect(5.0, {"HEARTBEAT"}, until=lambda g: len(g) >= 3)
    iv = np.diff([h.time_s for h in hbs])
    h = hbs[0]
    return {"src": h.src, "type": h["type"], "autopilot": h["autopilot"], "base_mode": h["base_mode"],
            "system_status": h["system_status"], "n": len(hbs),
            "interval_s": round(float(np.median(iv)), 0) if len(iv) else None}


def probe_read_by_name(p: MavProbe) -> dict:
    f, i = p.read_param("COMPASS_OFS_X"), p.read_param("INS_ACC_ID")
    assert f is not None and i is not None
    return {"float": (f["param_index"], f["param_type"], f["param_count"] > 0),
            "int32": (i["param_index"], i["param_type"])}


def probe_read_by_index(p: MavProbe) -> dict:
    p.drain()
    p.param_request_read("", 3)
    got = p.collect(3.0, {"PARAM_VALUE"}, until=lambda g: any(r["param_index"] == 3 for r in g))
    ans = [r for r in got if r["param_index"] == 3]
    back = p.read_param(ans[0]["param_id"]) if ans else None  # the name it gave reads back by name
    return {"answered": len(ans), "name_reads_back": back is not None}


def probe_read_unknown(p: MavProbe) -> dict:
    p.drain()
    p.param_request_read("NO_SUCH_PARAM")
    p.param_request_read("", 30000)  # beyond either table (int16 field)
    got = p.collect(QUIET_S, {"PARAM_VALUE", "PARAM_ERROR", "STATUSTEXT"})
    return {"answers": [(r.type, r.fields.get("param_id")) for r in got if r.type == "PARAM_ERROR" or (
        r.type == "PARAM_VALUE" and (r["param_index"] != NO_INDEX or r["param_id"] == "NO_SUCH_PARAM"))],
        "texts": _texts(got)}


def probe_set_float(p: MavProbe) -> dict:
    old = _read(p, ["COMPASS_DEC"])
    vals, texts, errs = _set_echo(p, "COMPASS_DEC", 0.123)
    back = p.read_param("COMPASS_DEC")
    _restore(p, old)
    return {"echo": vals, "texts": texts, "errors": errs, "read_back": back["param_value"] if back else None,
            "type": back["param_type"] if back else None, "expected": [_f32(0.123)]}


def probe_set_integer(p: MavProbe) -> dict:
    old = _read(p, ["COMPASS_AUTODEC"])
    out = {}
    for v in (2.995, -0.996, 300.0, -1000.0):  # +/-0.01 then truncation; clamped to int8
        vals, texts, _ = _set_echo(p, "COMPASS_AUTODEC", v)
        out[v] = (vals, texts)
    _restore(p, old)
    return {"echoes": out, "type": p.read_param("COMPASS_AUTODEC")["param_type"]}  # type: ignore[index]


def probe_set_vector_element(p: MavProbe) -> dict:
    """AP_Param::send_parameter: a set of X echoes the whole vector, of Y or Z only itself."""
    names = ["COMPASS_OFS2_X", "COMPASS_OFS2_Y", "COMPASS_OFS2_Z"]
    old = _read(p, names)
    out = {}
    for n in names[:2]:
        got = p.set_and_wait(n, old[n] + 1.5)
        p.collect(0.5)
        echoed = sorted({r["param_id"] for r in got if r.type == "PARAM_VALUE" and r["param_id"] in names})
        v = _values(got, n)
        out[n] = {"echoed": echoed, "changed_by": round(v[-1] - old[n], 4) if v else None}
    _restore(p, {n: old[n] for n in names[:2]})
    return out


def probe_rapid_sets(p: MavProbe) -> dict:
    """Three PARAM_SETs of one parameter back to back: SITL may answer the queued saves with
    fewer echoes (seen: 2 of 4), the loopback vehicle answers each; either way the last echo
    carries the last value and no echo is of a value never sent."""
    old = _read(p, ["COMPASS_DEC"])
    sent = [0.31, 0.32, 0.33]
    for v in sent:
        p.param_set("COMPASS_DEC", v)
    got = _values(p.collect(2.0, {"PARAM_VALUE"}), "COMPASS_DEC")
    _restore(p, old)
    return {"last_is_last": bool(got) and got[-1] == _f32(sent[-1]), "count_1_to_3": 1 <= len(got) <= 3,
            "only_sent_values": set(got) <= {_f32(v) for v in sent}}


def probe_set_unknown_and_nan(p: MavProbe) -> dict:
    p.drain()
    p.param_set("NO_SUCH_PARAM", 1.0)
    p.param_set("COMPASS_DEC", math.nan)
    got = p.collect(QUIET_S, {"PARAM_VALUE", "PARAM_ERROR", "STATUSTEXT"})
    return {"answers": [(r.type, r.fields.get("param_id")) for r in got if r.type == "PARAM_ERROR" or (
        r.type == "PARAM_VALUE" and r["param_id"] in ("NO_SUCH_PARAM", "COMPASS_DEC"))], "texts": _texts(got)}


def probe_set_device_id(p: MavProbe) -> dict:
    old = _read(p, ["COMPASS_DEV_ID", "INS_ACC_ID"])
    out = {}
    for n in old:
        vals, texts, _ = _set_echo(p, n, 12345.0)
        out[n] = (vals, [t for t in texts if "denied" in t])
    _restore(p, old)
    return out


def probe_internal_use_only(p: MavProbe) -> dict:
    """MIS_TOTAL (AP_PARAM_FLAG_INTERNAL_USE_ONLY): denied unless BRD_OPTIONS has bit 2.
    Its value is the vehicle's mission size (SITL: 1 once home is set), so the outcome is
    relative to it."""
    brd = _read(p, ["BRD_OPTIONS", "MIS_TOTAL"])
    was = brd["MIS_TOTAL"]
    denied = _set_echo(p, "MIS_TOTAL", was + 1)
    _set_echo(p, "BRD_OPTIONS", float(int(brd["BRD_OPTIONS"]) | 4))  # ALLOW_SET_INTERNAL_PARM
    allowed = _set_echo(p, "MIS_TOTAL", was + 1)
    _restore(p, {"MIS_TOTAL": was, "BRD_OPTIONS": brd["BRD_OPTIONS"]})
    return {"BRD_OPTIONS": brd["BRD_OPTIONS"], "denied": ([v - was for v in denied[0]], denied[1]),
            "allowed": ([v - was for v in allowed[0]], allowed[1])}


def probe_no_range_check(p: MavProbe) -> dict:
    """Values beyond the documented ranges are stored; an unknown rotation on the external
    compass 1 is reported once as an internal error (bad_rotation, 0x400000), and the same
    value on the internal compass 2 (which ignores ORIENT) is not."""
    old = _read(p, ["INS_ACCSCAL_X", "COMPASS_ORIENT", "COMPASS_ORIENT2", "COMPASS_EXTERNAL", "COMPASS_EXTERN2"])
    scal = _set_echo(p, "INS_ACCSCAL_X", 1.5)
    internal = _set_echo(p, "COMPASS_ORIENT2", 77.0)
    internal_texts = _texts(p.collect(0.7, {"STATUSTEXT"}))
    p.param_set("COMPASS_ORIENT", 77.0)
    got = p.collect(1.5, {"PARAM_VALUE", "STATUSTEXT"})
    _restore(p, {n: old[n] for n in ("INS_ACCSCAL_X", "COMPASS_ORIENT", "COMPASS_ORIENT2")})
    status = p.collect(2.5, {"HEARTBEAT"}, until=lambda g: len(g) >= 1)  # the error stays until a reboot
    # (SITL's pre-arm check repeats it every 30 s as "PreArm: Internal errors ...": not counted)
    errors = [(r["severity"], r["text"]) for r in got if r.type == "STATUSTEXT" and r["text"].startswith("Internal E")]
    return {"INS_ACCSCAL_X": scal[0], "COMPASS_ORIENT2": internal[0],
            "externals": (old["COMPASS_EXTERNAL"] != 0, old["COMPASS_EXTERN2"] != 0),
            "after_internal": internal[1] + internal_texts, "COMPASS_ORIENT": _values(got, "COMPASS_ORIENT"),
            "after_external": errors, "system_status": [h["system_status"] for h in status]}


def probe_param_list(p: MavProbe) -> dict:
    p.drain()
    p.param_request_list()
    seen: dict[int, str] = {}
    counts: set[int] = set()
    read = [0]

    def done(got: list[Received]) -> bool:
        for r in got[read[0]:]:
            if r["param_index"] != NO_INDEX:  # NO_INDEX: an unsolicited announcement, not the list
                seen[r["param_index"]] = r["param_id"]
                counts.add(r["param_count"])
        read[0] = len(got)
        return bool(counts) and len(seen) >= max(counts)

    p.collect(40.0, {"PARAM_VALUE"}, until=done)
    count = max(counts) if counts else 0
    return {"complete": sorted(seen) == list(range(count)), "one_count": len(counts) == 1,
            "names_unique": len(set(seen.values())) == len(seen), "count": count}


def probe_data_stream(p: MavProbe) -> dict:
    p.request_data_stream("MAV_DATA_STREAM_RAW_SENSORS", 10, True)
    got = p.collect(2.5)
    p.request_data_stream("MAV_DATA_STREAM_RAW_SENSORS", 0, False)
    p.collect(0.5)
    after = p.collect(1.5)
    raw = [r.time_s for r in got if r.type == "RAW_IMU"][2:]
    rate = (len(raw) - 1) / (raw[-1] - raw[0]) if len(raw) > 2 else 0.0
    return {"imu_types": sorted({r.type for r in got} & IMU_TYPES), "raw_imu_10hz": _near(rate, 10.0),
            "after_stop": sorted({r.type for r in after} & IMU_TYPES),
            "pressure_types": sorted({r.type for r in got if r.type.startswith("SCALED_PRESSURE")})}


def probe_message_interval(p: MavProbe) -> dict:
    scaled = const("MAVLINK_MSG_ID_SCALED_IMU")
    on = p.command_and_wait("MAV_CMD_SET_MESSAGE_INTERVAL", scaled, 50000)
    got = [r.time_s for r in p.collect(2.0, {"SCALED_IMU"})][2:]
    rate = (len(got) - 1) / (got[-1] - got[0]) if len(got) > 2 else 0.0
    off = p.command_and_wait("MAV_CMD_SET_MESSAGE_INTERVAL", scaled, -1)
    p.collect(0.5)
    after = p.collect(1.0, {"SCALED_IMU"})
    bad = p.command_and_wait("MAV_CMD_SET_MESSAGE_INTERVAL", 9999, 50000, types=("STATUSTEXT",))
    acks = [r["result"] for r in on + off + bad if r.type == "COMMAND_ACK"]
    return {"acks": acks, "scaled_imu_20hz": _near(rate, 20.0), "after_off": len(after),
            "unknown_id_text": [t for t in _texts(bad) if "mavlink id" in t]}


def probe_commands(p: MavProbe) -> dict:
    def ack(*args: float | str, types: tuple[str, ...] = ()) -> tuple[list[int], list[Received]]:
        got = p.command_and_wait(*args, types=types)  # type: ignore[arg-type]
        return [r["result"] for r in got if r.type == "COMMAND_ACK"], got

    compass, _ = ack("MAV_CMD_PREFLIGHT_CALIBRATION", 0, 76)
    accel, _ = ack("MAV_CMD_PREFLIGHT_CALIBRATION", 0, 0, 0, 0, 76)
    version, got = ack("MAV_CMD_REQUEST_MESSAGE", const("MAVLINK_MSG_ID_AUTOPILOT_VERSION"),
                       types=("AUTOPILOT_VERSION",))
    av = [r for r in got if r.type == "AUTOPILOT_VERSION"]
    caps = av[0]["capabilities"] if av else 0
    ver = av[0]["flight_sw_version"] if av else 0
    want = const("MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT") | const("MAV_PROTOCOL_CAPABILITY_MAVLINK2")
    unknown, _ = ack(31000)
    return {"force_save_compass": compass, "force_save_accel": accel, "request_version": version,
            "autopilot_version": len(av), "caps_param_float_mavlink2": (caps & want) == want,
            "version_major_minor": (ver >> 24 & 0xFF, ver >> 16 & 0xFF) if av else None, "unsupported": unknown}


def probe_accel_correction(p: MavProbe) -> dict:
    """INS_ACCOFFS_X / INS_ACCSCAL_X on RAW_IMU.xacc (milli-g) of a still, level vehicle:
    ``trunc(S (u - OFS) 1000/g)``; at +/-0.3 m/s^2 the fraction is 0.59, so truncation toward
    zero, floor and rounding all differ."""
    names = fw.accel_param_names(0)
    old = _read(p, [*names["ofs"], *names["scale"], "AHRS_ORIENTATION"])
    ox, sx = names["ofs"][0], names["scale"][0]
    p.command_and_wait("MAV_CMD_SET_MESSAGE_INTERVAL", const("MAVLINK_MSG_ID_RAW_IMU"), 20000)
    p.command_and_wait("MAV_CMD_SET_MESSAGE_INTERVAL", const("MAVLINK_MSG_ID_SCALED_IMU"), 20000)
    out = {}
    try:
        for ofs, scale in ((0.0, 1.0), (0.3, 1.0), (-0.3, 1.0), (-0.3, 1.1)):
            _set_echo(p, ox, ofs)
            _set_echo(p, sx, scale)
            p.collect(0.8)  # the change shows ~0.1 s after its echo, the 20 Hz filter settles
            got = p.collect(0.4, {"RAW_IMU", "SCALED_IMU"})
            raw = sorted({r["xacc"] for r in got if r.type == "RAW_IMU"})
            scaled = sorted({r["xacc"] for r in got if r.type == "SCALED_IMU"})
            cal = fw.accel_cal_from_params({**old, ox: ofs, sx: scale}, 0)
            model = math.trunc(float(fw.apply_accel(cal, np.zeros(3))[0]) * 1000.0 / fw.GRAVITY_MSS)
            out[(ofs, scale)] = {"xacc": raw, "scaled_equal": scaled == raw, "model": [model]}
    finally:
        for mid in ("MAVLINK_MSG_ID_RAW_IMU", "MAVLINK_MSG_ID_SCALED_IMU"):
            p.command_and_wait("MAV_CMD_SET_MESSAGE_INTERVAL", const(mid), -1)
        _restore(p, {ox: old[ox], sx: old[sx]})
    return out


def probe_compass_correction(p: MavProbe) -> dict:
    """COMPASS_OFS / DIA / ODI / SCALE on RAW_IMU.[xyz]mag (mGauss): each step's reading is
    the firmware model (:func:`~mavcal.ardupilot.firmware.apply_compass` of the raw field
    recovered from the step before) within the truncation (1 count, times the gain)."""
    cn = fw.compass_param_names(0)
    names = [*cn["ofs"], *cn["dia"], *cn["odi"], cn["scale"], cn["orient"], cn["external"], "AHRS_ORIENTATION"]
    old = _read(p, names)
    steps = [{cn["ofs"][0]: old[cn["ofs"][0]] + 40.3},
             {cn["dia"][0]: 1.1, cn["odi"][0]: 0.02},
             {cn["scale"]: 1.2}]
    p.command_and_wait("MAV_CMD_SET_MESSAGE_INTERVAL", const("MAVLINK_MSG_ID_RAW_IMU"), 20000)
    out: dict[str, object] = {}
    try:
        params = dict(old)
        m0 = np.mean([[r["xmag"], r["ymag"], r["zmag"]] for r in _imu(p)], axis=0)
        for i, step in enumerate(steps):
            raw = fw.undo_compass(fw.compass_cal_from_params(params, 0), m0[None, :], sensor_frame=True)[0]
            for n, v in step.items():
                _set_echo(p, n, v)
            params.update(step)
            predicted = fw.apply_compass(fw.compass_cal_from_params(params, 0), raw[None, :], sensor_frame=True)[0]
            got = _imu(p)
            m1 = np.mean([[r["xmag"], r["ymag"], r["zmag"]] for r in got], axis=0)
            out[f"step{i}"] = {"moved": bool(np.any(np.abs(m1 - m0) > 3)),
                               "within_truncation": bool(np.all(np.abs(m1 - predicted) <= 1.6)),
                               "integers": all(float(r["xmag"]).is_integer() for r in got)}
            m0 = m1
    finally:
        p.command_and_wait("MAV_CMD_SET_MESSAGE_INTERVAL", const("MAVLINK_MSG_ID_RAW_IMU"), -1)
        _restore(p, {n: old[n] for s in steps for n in s})
    return out


def _about_probe(r: Received) -> bool:
    if r.type == "PARAM_VALUE":
        return r["param_id"] in ("COMPASS_DEC", "MIS_TOTAL")
    if r.type == "STATUSTEXT":
        return "denied" in r["text"]
    return True


def probe_channels(p: MavProbe, other: MavProbe) -> dict:
    """What a second GCS on another channel sees of the first one's requests: ArduPilot answers
    a request on the asking channel only, echoes a set and sends STATUSTEXT on every channel,
    and keeps stream rates per channel."""
    def seen(types: set[str], action: Callable[[], object], seconds: float = 1.0) -> list[str]:
        other.drain()
        action()
        # only what is about this request: SITL also announces its own changes (STAT_RUNTIME, ...)
        return sorted({r.type for r in other.collect(seconds, types) if _about_probe(r)})

    old = _read(p, ["COMPASS_DEC", "MIS_TOTAL"])
    out = {"read_answer": seen({"PARAM_VALUE"}, lambda: p.read_param("COMPASS_DEC")),
           "set_echo": seen({"PARAM_VALUE"}, lambda: p.set_and_wait("COMPASS_DEC", 0.2)),
           "denied_text": seen({"STATUSTEXT"}, lambda: p.set_and_wait("MIS_TOTAL", old["MIS_TOTAL"] + 1)),
           "requested": seen({"COMMAND_ACK", "AUTOPILOT_VERSION"}, lambda: p.command_and_wait(
               "MAV_CMD_REQUEST_MESSAGE", const("MAVLINK_MSG_ID_AUTOPILOT_VERSION"), types=("AUTOPILOT_VERSION",))),
           "stream": seen({"RAW_IMU"}, lambda: p.command_and_wait(
               "MAV_CMD_SET_MESSAGE_INTERVAL", const("MAVLINK_MSG_ID_RAW_IMU"), 50000)),
           "heartbeat": seen({"HEARTBEAT"}, lambda: None, 1.5)}
    p.command_and_wait("MAV_CMD_SET_MESSAGE_INTERVAL", const("MAVLINK_MSG_ID_RAW_IMU"), -1)
    _restore(p, {"COMPASS_DEC": old["COMPASS_DEC"]})
    return out


PROBES: dict[str, Callable[[MavProbe], dict]] = {
    f.__name__.removeprefix("probe_"): f for f in (
        probe_heartbeat, probe_read_by_name, probe_read_by_index, probe_read_unknown, probe_set_float,
        probe_set_integer, probe_set_vector_element, probe_rapid_sets, probe_set_unknown_and_nan, probe_set_device_id,
        probe_internal_use_only, probe_no_range_check, probe_param_list, probe_data_stream,
        probe_message_interval, probe_commands, probe_accel_correction, probe_compass_correction)}

DIFFERENCES: tuple[Difference, ...] = (
    Difference("channels", "stream", ["RAW_IMU"], [],
               "the imitation keeps one set of stream rates for all its clients (in most tests it has one); "
               "ArduPilot keeps them per channel"),
    Difference("param_list", "count", None, 1354,
               "the imitation holds only the parameters mavcal reads or writes (a few hundred), not all 1354"),
    Difference("commands", "version_major_minor", (4, 6), (4, 7),
               "the imitation reports 4.6.0 official, the release mavcal targets; this SITL is 4.7.0-dev"),
    Difference("data_stream", "pressure_types", [], ["SCALED_PRESSURE", "SCALED_PRESSURE2"],
               "the imitation has no barometer; RAW_SENSORS carries only its IMU messages"),
)


def _differences(probe: str) -> dict[str, Difference]:
    return {d.key: d for d in DIFFERENCES if d.probe == probe}


# ------------------------------------------------------------------------------------------
# fixtures and the test
# ------------------------------------------------------------------------------------------
def _quiet_truth() -> VehicleTruth:
    """Perfect, noise-free sensors (SITL's accelerometer at rest is below 1 milli-g of noise,
    and its compass with SIM_MAG_RND 0 is noise-free)."""
    return VehicleTruth(accels=(AccelCalTruth(noise_mps2=0.0),) * N_IMUS,
                        compasses=tuple(CompassTruth(dev_id=d, external=(i == 0), noise_mgauss=0.0)
                                        for i, d in enumerate(COMPASS_DEV_IDS)))


@pytest.fixture(scope="module")
def peers() -> Iterator[dict[str, Peer]]:
    from mavcal.testing.sitl import SitlVehicle, require_sitl

    require_sitl()
    loop = TestVehicle("udpin", truth=_quiet_truth(), heartbeat_hz=1.0, seed=5).start()
    sitl = SitlVehicle(wrong_calibration=False, measure_field=False, relay=True,
                       params={"SIM_MAG_RND": 0, "SERIAL2_PROTOCOL": 2})
    if sitl.instance % 100 == 0:  # a non-zero -I, so the heartbeat probe shows it keeps system id 1
        sitl.instance += 37
    probes: list[MavProbe] = []
    try:
        sitl.start()
        probes += [MavProbe(loop.gcs_device), MavProbe(loop.gcs_device)]
        with sitl.netns():
            probes += [MavProbe(sitl.tool_device), MavProbe(sitl.relay_device)]
        yield {"loopback": Peer("loopback", *probes[:2]), "sitl": Peer("sitl", *probes[2:])}
    finally:
        for pr in probes:
            pr.close()
        sitl.stop()
        loop.stop()


@pytest.mark.parametrize("name", [*PROBES, "channels"])
def test_loopback_vehicle_agrees_with_sitl(peers: dict[str, Peer], name: str) -> None:
    def run(peer: Peer) -> dict:
        peer.probe.drain()  # nothing left over from the probe before
        if name == "channels":
            return probe_channels(peer.probe, peer.other)
        return PROBES[name](peer.probe)

    with ThreadPoolExecutor(max_workers=1) as pool:  # both at once: the module's run time halves
        loop_future = pool.submit(run, peers["loopback"])
        sitl = run(peers["sitl"])
        loop = loop_future.result()
    diffs = _differences(name)
    for key, d in diffs.items():
        got = loop.pop(key)
        if d.loopback is not None:  # None: whatever the imitation has
            assert got == d.loopback, f"{name}.{key} on the loopback vehicle: {got!r} ({d.reason})"
        got = sitl.pop(key)
        assert got == d.sitl, f"{name}.{key} on SITL: {got!r}, the documented difference changed ({d.reason})"
    assert loop == sitl, f"{name}: loopback {loop} != SITL {sitl}"


def test_the_differences_name_real_probes_and_reasons() -> None:
    for d in DIFFERENCES:
        assert (d.probe in PROBES or d.probe == "channels") and len(d.reason) > 30
