"""The loopback test vehicle follows ArduPilot's parameter protocol and sensor pipeline.

These talk to it with a bare pymavlink connection, so the emulation is checked without the
code under test (the writer).
"""
from __future__ import annotations

import math
import time

import numpy as np
import pytest
from pymavlink import mavutil

from mavcal.ardupilot import firmware as fw
from mavcal.autopilot.rotations import rotation_matrix
from mavcal.core.constants import GRAVITY_MPS2
from mavcal.testing.vehicle import AccelCalTruth, CompassTruth, TestVehicle, VehicleTruth

A = mavutil.mavlink


@pytest.fixture
def vehicle(start_vehicle):
    return start_vehicle("udpout", heartbeat_hz=20, seed=3)


@pytest.fixture
def gcs(vehicle):
    conn = mavutil.mavlink_connection(vehicle.gcs_device, source_system=255, source_component=190,
                                      dialect="ardupilotmega")
    assert conn.wait_heartbeat(timeout=5) is not None
    yield conn
    conn.close()


def collect(conn, seconds, types=None):
    out = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        m = conn.recv_match(blocking=True, timeout=0.02)
        if m is not None and (types is None or m.get_type() in types):
            out.append(m)
    return out


def wait_for(conn, pred, seconds=2.0):
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        m = conn.recv_match(blocking=True, timeout=0.05)
        if m is not None and pred(m):
            return m
    return None


def param_set(conn, name, value, ptype=A.MAV_PARAM_TYPE_REAL32):
    conn.mav.param_set_send(1, 1, name.encode(), value, ptype)


def test_heartbeat_identifies_an_ardupilot_quad(gcs):
    hb = wait_for(gcs, lambda m: m.get_type() == "HEARTBEAT")
    assert (hb.type, hb.autopilot) == (A.MAV_TYPE_QUADROTOR, A.MAV_AUTOPILOT_ARDUPILOTMEGA)
    assert (hb.get_srcSystem(), hb.get_srcComponent()) == (1, 1)
    assert hb.get_msgbuf()[0] == 0xFD  # MAVLink 2


def test_unknown_name_and_nan_are_silently_ignored(vehicle, gcs):
    param_set(gcs, "NO_SUCH_PARAM", 1.0)
    param_set(gcs, "COMPASS_OFS_X", float("nan"))
    param_set(gcs, "COMPASS_OFS_Y", float("inf"))
    got = collect(gcs, 0.3, {"PARAM_VALUE"})
    assert got == []
    assert vehicle.get_param("COMPASS_OFS_X") == 0.0 and vehicle.get_param("COMPASS_OFS_Y") == 0.0
    assert [s[2] for s in vehicle.param_sets] == [None, None, None]


@pytest.mark.parametrize("name,sent,stored", [
    ("COMPASS_ORIENT", 300.0, 127.0),       # INT8 clamped
    ("COMPASS_ORIENT", -1000.0, -128.0),
    ("COMPASS_ORIENT", 2.995, 3.0),         # +0.01 then truncation
    ("COMPASS_ORIENT", -2.995, -3.0),
    ("COMPASS_ORIENT", 2.98, 2.0),
    ("COMPASS_OFFS_MAX", 1e6, 32767.0),     # INT16
    ("COMPASS_PRIO1_ID", 1e12, 2147483647.0),  # INT32
    ("COMPASS_OFS_X", 0.1, float(np.float32(0.1))),  # REAL32 rounding
])
def test_values_are_converted_to_the_stored_type(vehicle, gcs, name, sent, stored):
    param_set(gcs, name, sent)
    m = wait_for(gcs, lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == name)
    assert m is not None and m.param_index == 65535
    assert vehicle.get_param(name) == stored
    assert m.param_value == np.float32(stored)  # cast_to_float: the echo is a float32
    assert m.param_type == vehicle.param_type(name)


def test_param_type_in_param_set_is_ignored(vehicle, gcs):
    param_set(gcs, "COMPASS_OFS_X", 1.75, A.MAV_PARAM_TYPE_INT8)
    m = wait_for(gcs, lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == "COMPASS_OFS_X")
    assert m.param_value == 1.75 and m.param_type == A.MAV_PARAM_TYPE_REAL32


def test_setting_x_of_a_vector_echoes_all_three_y_only_itself(vehicle, gcs):
    # AP_Param::send_parameter (and SITL, tests/test_vehicle_agrees_with_sitl.py): the X
    # element's pointer is the vector's, so its echo is the whole vector; Y and Z echo alone
    vehicle.set_param_local("COMPASS_OFS2_Z", 2.0)
    param_set(gcs, "COMPASS_OFS2_X", 7.0)
    got = [m for m in collect(gcs, 0.3, {"PARAM_VALUE"})]
    assert [(m.param_id, m.param_value, m.param_index) for m in got] == [
        ("COMPASS_OFS2_X", 7.0, 65535), ("COMPASS_OFS2_Y", 0.0, 65535), ("COMPASS_OFS2_Z", 2.0, 65535)]
    param_set(gcs, "COMPASS_OFS2_Y", -4.5)
    got = [m for m in collect(gcs, 0.3, {"PARAM_VALUE"})]
    assert [(m.param_id, m.param_value, m.param_index) for m in got] == [("COMPASS_OFS2_Y", -4.5, 65535)]


def test_internal_use_only_is_write_denied_unless_brd_options_allows(vehicle, gcs):
    param_set(gcs, "MIS_TOTAL", 5.0)
    m = wait_for(gcs, lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == "MIS_TOTAL")
    assert m.param_value == 0.0 and vehicle.get_param("MIS_TOTAL") == 0.0
    vehicle.set_param_local("BRD_OPTIONS", 4)  # ALLOW_SET_INTERNAL_PARM
    param_set(gcs, "MIS_TOTAL", 5.0)
    m = wait_for(gcs, lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == "MIS_TOTAL")
    assert m.param_value == 5.0 and vehicle.get_param("MIS_TOTAL") == 5.0


def test_device_ids_are_writable_as_in_ardupilot(vehicle, gcs):
    # no AP_PARAM_FLAG_INTERNAL_USE_ONLY on COMPASS_DEV_ID (SITL stores and echoes it too)
    param_set(gcs, "COMPASS_DEV_ID", 5.0)
    m = wait_for(gcs, lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == "COMPASS_DEV_ID")
    assert m.param_value == 5.0 and vehicle.get_param("COMPASS_DEV_ID") == 5.0


def test_read_by_name_and_by_index_and_list(vehicle, gcs):
    gcs.mav.param_request_read_send(1, 1, b"COMPASS_DEV_ID2", -1)
    m = wait_for(gcs, lambda m: m.get_type() == "PARAM_VALUE")
    assert (m.param_id, m.param_value, m.param_index, m.param_type) == (
        "COMPASS_DEV_ID2", 131874.0, 65535, A.MAV_PARAM_TYPE_INT32)
    gcs.mav.param_request_read_send(1, 1, b"", 3)
    m = wait_for(gcs, lambda m: m.get_type() == "PARAM_VALUE")
    assert m.param_index == 3
    gcs.mav.param_request_list_send(1, 1)
    got = collect(gcs, 0.5, {"PARAM_VALUE"})
    count = got[0].param_count
    assert sorted(m.param_index for m in got) == list(range(count))
    assert len({m.param_id for m in got}) == count == len(vehicle.params)


def test_commands_force_save_message_interval_and_unsupported(vehicle, gcs):
    gcs.mav.command_long_send(1, 1, A.MAV_CMD_PREFLIGHT_CALIBRATION, 0, 0, 76, 0, 0, 0, 0, 0)
    ack = wait_for(gcs, lambda m: m.get_type() == "COMMAND_ACK")
    assert (ack.command, ack.result) == (A.MAV_CMD_PREFLIGHT_CALIBRATION, A.MAV_RESULT_ACCEPTED)
    gcs.mav.command_long_send(1, 1, A.MAV_CMD_PREFLIGHT_CALIBRATION, 0, 0, 0, 0, 0, 76, 0, 0)
    assert wait_for(gcs, lambda m: m.get_type() == "COMMAND_ACK").result == A.MAV_RESULT_ACCEPTED
    assert vehicle.force_saves == ["compass", "accel"]
    gcs.mav.command_long_send(1, 1, A.MAV_CMD_SET_MESSAGE_INTERVAL, 0, A.MAVLINK_MSG_ID_SCALED_IMU2,
                              20000, 0, 0, 0, 0, 0)
    assert wait_for(gcs, lambda m: m.get_type() == "COMMAND_ACK").result == A.MAV_RESULT_ACCEPTED
    assert len(collect(gcs, 0.3, {"SCALED_IMU2"})) >= 5
    gcs.mav.command_long_send(1, 1, A.MAV_CMD_DO_SET_MODE, 0, 0, 0, 0, 0, 0, 0, 0)
    assert wait_for(gcs, lambda m: m.get_type() == "COMMAND_ACK").result == A.MAV_RESULT_UNSUPPORTED


def test_imu_stream_applies_current_calibration_like_ardupilot(start_vehicle):
    truth = VehicleTruth(
        accels=(AccelCalTruth(offsets=(0.3, -0.2, 0.5), scale=(1.02, 0.98, 1.01), noise_mps2=0.0),) * 3,
        compasses=(CompassTruth(97539, offsets=(120, -80, 45), dia=(1.05, 0.95, 1.02), odi=(0.02, -0.01, 0.03),
                                orientation=6, external=True, noise_mgauss=0.0),
                   CompassTruth(131874, offsets=(-30, 60, 10), noise_mgauss=0.0),
                   CompassTruth(263178, noise_mgauss=0.0)),
        gyro_noise_rads=0.0)
    v = start_vehicle("tcp", truth=truth, heartbeat_hz=20)
    conn = mavutil.mavlink_connection(v.gcs_device, source_system=255, dialect="ardupilotmega")
    try:
        assert conn.wait_heartbeat(timeout=5)
        conn.mav.request_data_stream_send(1, 1, A.MAV_DATA_STREAM_RAW_SENSORS, 50, 1)
        v.set_attitude(roll=30, pitch=-20, yaw=100)
        m = wait_for(conn, lambda m: m.get_type() == "RAW_IMU")
        ideal = v.corrected_sensors(noise=False)
        # int16 truncation toward zero of the corrected, body-frame values
        exp_acc = [math.trunc(x * 1000 / GRAVITY_MPS2) for x in ideal["accel_mps2"][0]]
        exp_mag = [math.trunc(x) for x in ideal["mag_mgauss"][0]]
        assert [m.xacc, m.yacc, m.zacc] == exp_acc and [m.xmag, m.ymag, m.zmag] == exp_mag
        # uncalibrated: the field is off; with the ideal calibration it is the Earth field
        field = np.array(truth.earth_field_ned_mgauss)
        R = v.attitude
        assert np.linalg.norm(ideal["mag_mgauss"][0] - R.T @ field) > 50
        ideal_params = {"COMPASS_OFS_X": 120, "COMPASS_OFS_Y": -80, "COMPASS_OFS_Z": 45,
                        "COMPASS_DIA_X": 1.05, "COMPASS_DIA_Y": 0.95, "COMPASS_DIA_Z": 1.02,
                        "COMPASS_ODI_X": 0.02, "COMPASS_ODI_Y": -0.01, "COMPASS_ODI_Z": 0.03,
                        "COMPASS_ORIENT": 6, "INS_ACCOFFS_X": 0.3, "INS_ACCOFFS_Y": -0.2,
                        "INS_ACCOFFS_Z": 0.5, "INS_ACCSCAL_X": 1.02, "INS_ACCSCAL_Y": 0.98,
                        "INS_ACCSCAL_Z": 1.01}
        for k, val in ideal_params.items():  # over the protocol: takes effect at once
            conn.mav.param_set_send(1, 1, k.encode(), val, A.MAV_PARAM_TYPE_REAL32)
        time.sleep(0.1)
        assert v.get_param("COMPASS_ORIENT") == 6
        now = v.corrected_sensors(noise=False)
        np.testing.assert_allclose(now["mag_mgauss"][0], R.T @ field, atol=1e-3)
        np.testing.assert_allclose(now["accel_mps2"][0], R.T @ [0, 0, -9.80665], atol=1e-5)
        # DIA all zero skips the whole matrix (ODI too); SCALE outside [1/1.5, 1.5] is ignored
        for k in ("COMPASS_DIA_X", "COMPASS_DIA_Y", "COMPASS_DIA_Z"):
            v.set_param_local(k, 0.0)
        v.set_param_local("COMPASS_SCALE", 2.0)
        raw_rot = rotation_matrix(6) @ (rotation_matrix(6).T @ (
            np.linalg.solve([[1.05, 0.02, -0.01], [0.02, 0.95, 0.03], [-0.01, 0.03, 1.02]], R.T @ field)
            - [120, -80, 45]))
        np.testing.assert_allclose(v.corrected_sensors(noise=False)["mag_mgauss"][0],
                                   raw_rot + [120, -80, 45], atol=1e-3)
    finally:
        conn.close()


def test_corrected_sensors_are_the_firmware_forward_model():
    """The vehicle applies exactly mavcal.ardupilot.firmware's model (the one mavcal inverts)."""
    params = {
        # compass 1: external, COMPASS_ORIENT, offsets, soft iron, scale
        "COMPASS_OFS_X": 120.5, "COMPASS_OFS_Y": -80.25, "COMPASS_OFS_Z": 45.0,
        "COMPASS_DIA_X": 1.05, "COMPASS_DIA_Y": 0.95, "COMPASS_DIA_Z": 1.02,
        "COMPASS_ODI_X": 0.02, "COMPASS_ODI_Y": -0.01, "COMPASS_ODI_Z": 0.03,
        "COMPASS_SCALE": 1.12, "COMPASS_ORIENT": 6, "COMPASS_EXTERNAL": 1,
        # compass 2: external on the custom rotation 1 (angles read at boot)
        "COMPASS_OFS2_X": -30, "COMPASS_OFS2_Y": 60, "COMPASS_OFS2_Z": 10, "COMPASS_DIA2_X": 0.97,
        "COMPASS_ODI2_Z": -0.02, "COMPASS_SCALE2": 0.9, "COMPASS_ORIENT2": 101, "COMPASS_EXTERN2": 1,
        "CUST_ROT1_ROLL": 10, "CUST_ROT1_PITCH": -5, "CUST_ROT1_YAW": 33,
        # compass 3: internal, so AHRS_ORIENTATION; SCALE outside [1/1.5, 1.5] is ignored
        "COMPASS_OFS3_X": 5, "COMPASS_SCALE3": 2.0, "COMPASS_ORIENT3": 4, "COMPASS_EXTERN3": 0,
        "AHRS_ORIENTATION": 2,
        "INS_ACCOFFS_X": 0.3, "INS_ACCOFFS_Y": -0.2, "INS_ACCOFFS_Z": 0.5,
        "INS_ACCSCAL_X": 1.02, "INS_ACCSCAL_Y": 0.98, "INS_ACCSCAL_Z": 1.01,
        "INS_ACC2OFFS_Y": 0.15, "INS_ACC2SCAL_Z": 0.97, "INS_ACC3OFFS_X": -0.4, "INS_ACC3SCAL_X": 1.03,
    }
    v = TestVehicle(truth=VehicleTruth.random(7), params=params, seed=7)  # never started: no sockets
    v.set_attitude(roll=20, pitch=-35, yaw=140)

    def check():
        got = v.corrected_sensors(noise=False)
        with v._lock:  # the same raw readings the vehicle corrected (noise off: deterministic)
            raw = v._raw_sensors(noise=False)
        p = v.params
        for i in range(3):
            cal = fw.accel_cal_from_params(p, i)
            np.testing.assert_array_equal(got["accel_mps2"][i], fw.apply_accel(cal, raw["accel_mps2"][i]))
            np.testing.assert_allclose(fw.undo_accel(cal, got["accel_mps2"][i]), raw["accel_mps2"][i], atol=1e-9)
        for slot in range(3):
            cal = fw.compass_cal_from_params(p, slot)
            exp = fw.apply_compass(cal, raw["mag_mgauss"][slot])
            np.testing.assert_array_equal(got["mag_mgauss"][slot], exp)
            np.testing.assert_allclose(fw.undo_compass(cal, exp, sensor_frame=True), raw["mag_mgauss"][slot],
                                       atol=1e-9)
        return got, raw, p

    got, raw, p = check()
    # the calibration is not trivial: every stage moved the readings
    cals = [fw.compass_cal_from_params(p, k) for k in range(3)]
    assert [c.orient for c in cals] == [6, 101, 2] and cals[1].custom_deg == pytest.approx((10, -5, 33))
    assert fw.effective_scale(cals[0].scale) == pytest.approx(1.12) and fw.effective_scale(cals[2].scale) == 1.0
    assert not np.allclose(fw.soft_iron_matrix(cals[0].dia, cals[0].odi), np.eye(3))
    for k in range(3):
        assert np.linalg.norm(got["mag_mgauss"][k] - raw["mag_mgauss"][k]) > 5
        assert np.linalg.norm(got["accel_mps2"][k] - raw["accel_mps2"][k]) > 0.1
    # compass 1 by hand: M (k (R_orient raw + OFS))
    M = fw.soft_iron_matrix((1.05, 0.95, 1.02), (0.02, -0.01, 0.03))
    hand = M @ (1.12 * (rotation_matrix(6) @ raw["mag_mgauss"][0] + [120.5, -80.25, 45.0]))
    np.testing.assert_allclose(got["mag_mgauss"][0], hand, rtol=1e-6)  # float32-stored parameters
    # new calibration values apply at once; new custom rotation angles only after a boot
    v.set_param_local("COMPASS_OFS2_X", -45.5)
    v.set_param_local("COMPASS_DIA3_Y", 1.04)
    check()
    before = v.corrected_sensors(noise=False)["mag_mgauss"][1]
    v.set_param_local("CUST_ROT1_YAW", 80)
    np.testing.assert_array_equal(v.corrected_sensors(noise=False)["mag_mgauss"][1], before)
    with v._lock:
        v._boot()  # what the simulated reboot does
    check()
    assert not np.allclose(v.corrected_sensors(noise=False)["mag_mgauss"][1], before)


def test_reboot_reorders_compasses_by_priority(vehicle, gcs):
    vehicle.set_param_local("COMPASS_OFS_X", 11.0)
    vehicle.set_param_local("COMPASS_OFS2_X", 22.0)
    vehicle.set_param_local("COMPASS_PRIO1_ID", 131874)
    vehicle.set_param_local("COMPASS_PRIO2_ID", 97539)
    gcs.mav.command_long_send(1, 1, A.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 0, 1, 0, 0, 0, 0, 0, 0)
    assert wait_for(gcs, lambda m: m.get_type() == "COMMAND_ACK").result == A.MAV_RESULT_ACCEPTED
    assert not vehicle.alive
    end = time.monotonic() + 5
    while vehicle.reboots == 0 and time.monotonic() < end:
        collect(gcs, 0.05)
    assert vehicle.reboots == 1 and vehicle.alive
    assert wait_for(gcs, lambda m: m.get_type() == "HEARTBEAT", 3.0) is not None
    assert vehicle.get_param("COMPASS_DEV_ID") == 131874 and vehicle.get_param("COMPASS_OFS_X") == 22.0
    assert vehicle.get_param("COMPASS_DEV_ID2") == 97539 and vehicle.get_param("COMPASS_OFS2_X") == 11.0
    assert vehicle.get_param("COMPASS_EXTERN2") == 1 and vehicle.get_param("COMPASS_EXTERNAL") == 0


def test_kill_and_revive_keep_state(vehicle, gcs):
    vehicle.kill()
    collect(gcs, 0.1)  # drain
    assert collect(gcs, 0.3, {"HEARTBEAT"}) == []
    param_set(gcs, "COMPASS_OFS_X", 3.0)
    time.sleep(0.1)
    assert vehicle.get_param("COMPASS_OFS_X") == 0.0
    vehicle.revive()
    assert wait_for(gcs, lambda m: m.get_type() == "HEARTBEAT") is not None


def test_die_after_n_sets_applies_the_last_set_without_echo(start_vehicle):
    v = start_vehicle("udpin", heartbeat_hz=20, die_after_n_sets=2)
    conn = mavutil.mavlink_connection(v.gcs_device, source_system=255, dialect="ardupilotmega")
    try:
        conn.mav.heartbeat_send(A.MAV_TYPE_GCS, A.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        assert conn.wait_heartbeat(timeout=5)
        param_set(conn, "COMPASS_SCALE", 1.1)
        assert wait_for(conn, lambda m: m.get_type() == "PARAM_VALUE") is not None
        param_set(conn, "COMPASS_SCALE2", 1.2)
        assert wait_for(conn, lambda m: m.get_type() == "PARAM_VALUE", 0.3) is None
        assert v.get_param("COMPASS_SCALE2") == pytest.approx(1.2) and not v.alive
    finally:
        conn.close()


def test_faults_drop_and_duplicate(start_vehicle):
    v = start_vehicle("udpout", heartbeat_hz=50, seed=5)
    conn = mavutil.mavlink_connection(v.gcs_device, source_system=255, dialect="ardupilotmega")
    try:
        assert conn.wait_heartbeat(timeout=5)
        v.set_faults(dup_out=1.0)
        param_set(conn, "COMPASS_SCALE", 1.1)
        got = [m for m in collect(conn, 0.2, {"PARAM_VALUE"})]
        assert len(got) == 2
        v.set_faults(dup_out=0.0, drop_in=1.0)
        param_set(conn, "COMPASS_SCALE", 1.3)
        assert collect(conn, 0.2, {"PARAM_VALUE"}) == []
        assert v.stats["dropped_in"] >= 1 and v.get_param("COMPASS_SCALE") == pytest.approx(1.1)
    finally:
        conn.close()
