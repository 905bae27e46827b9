"""Mapping a joint calibration onto ArduPilot's parameters."""
import numpy as np
import pytest

from mavcal.ardupilot import firmware as fw
from mavcal.ardupilot.mapping import map_accel, map_compass
from mavcal.ardupilot.rotations import euler_to_matrix, rotation_matrix
from mavcal.errors import ParameterMappingError

G0 = fw.GRAVITY_MSS


def _engine_truth(S_acc, ofs_acc, M, ofs_mag, R_mount_true, B=500.0, incl_deg=60.0):
    """Engine-frame K_a, b_a, K_m, b_m, h_z for sensors that ArduPilot would correct with
    INS_ACCSCAL=S_acc, INS_ACCOFFS=ofs_acc, DIA/ODI=M, COMPASS_OFS=ofs_mag (R_A = I), with the
    compass physically rotated by R_mount_true relative to the configured mounting (identity)."""
    K_a = G0 * np.diag(1.0 / np.asarray(S_acc))  # raw = f / S + ofs  (E = board frame)
    h_z = np.tan(np.radians(incl_deg))
    h = np.array([1.0, 0.0, h_z])
    # raw_body = R^T (M^-1 B_body) - ofs  (the configured frame sees the field rotated)
    K_m = R_mount_true.T @ np.linalg.inv(M) * (B / np.linalg.norm(h))
    b_m = -np.asarray(ofs_mag)
    return K_a, np.asarray(ofs_acc, float), K_m, b_m, h_z


M_TRUE = fw.soft_iron_matrix((1.05, 0.97, 1.02), (0.02, -0.01, 0.015))


def _map(R_true, external=True, **kw):
    K_a, b_a, K_m, b_m, h_z = _engine_truth((0.99, 1.02, 0.97), (0.1, -0.2, 0.3), M_TRUE, (40.0, -60.0, 120.0), R_true)
    old_a = fw.AccelCal()
    am = map_accel(K_a, b_a, old_a)
    params = {"COMPASS_EXTERNAL": 1.0 if external else 0.0, "COMPASS_ORIENT": 0.0, "AHRS_ORIENTATION": 0.0,
              "CUST_ROT_ENABLE": 0.0, "CUST_ROT1_ROLL": 0.0}
    old_c = fw.compass_cal_from_params(params, 0)
    cm = map_compass(K_m, b_m, h_z, am.frame_rotation, old_c, params, field_mgauss=500.0, field_source="test",
                     board_rotation=np.eye(3), **kw)
    return am, cm


def test_exact_ardupilot_sensors_map_back_exactly():
    am, cm = _map(np.eye(3))
    np.testing.assert_allclose(am.new.scale, (0.99, 1.02, 0.97), atol=1e-12)
    np.testing.assert_allclose(am.new.ofs_mps2, (0.1, -0.2, 0.3), atol=1e-12)
    assert am.dropped_tilt_deg < 1e-6
    np.testing.assert_allclose(cm.new.ofs_mgauss, (40.0, -60.0, 120.0), atol=1e-9)
    np.testing.assert_allclose(cm.new.matrix * cm.new.k, M_TRUE, atol=1e-9)
    assert cm.new.orient == 0 and cm.residual_rotation_deg < 1e-6
    assert cm.inclination_deg == pytest.approx(60.0)


def test_standard_rotation_is_snapped_to_the_enum():
    am, cm = _map(rotation_matrix(4))  # mounted YAW_180, configured 0
    assert cm.new.orient == 4 and cm.params()["COMPASS_ORIENT"] == 4.0
    # the sensor reads s = R^T M^-1 B - ofs, so the perfect correction is M (R s + R ofs):
    # the offsets are expressed in the new (rotated) frame
    R = rotation_matrix(4)
    np.testing.assert_allclose(cm.new.ofs_mgauss, R @ [40.0, -60.0, 120.0], atol=1e-9)
    raw_s = np.array([[100.0, 50.0, -300.0]])
    B = fw.apply_compass(cm.new, raw_s)
    np.testing.assert_allclose(B[0], M_TRUE @ (R @ raw_s[0] + R @ [40.0, -60.0, 120.0]), atol=1e-6)


def test_odd_rotation_becomes_a_custom_rotation_with_reboot():
    R = euler_to_matrix(*np.radians([3.0, -2.0, 30.0]))
    am, cm = _map(R)
    assert cm.new.orient in (101, 102) and cm.reboot_required
    p = cm.params()
    assert p["CUST_ROT_ENABLE"] == 1.0
    slot = cm.new.orient - 100
    assert p[f"CUST_ROT{slot}_YAW"] == pytest.approx(30.0, abs=1e-6)
    assert p[f"CUST_ROT{slot}_ROLL"] == pytest.approx(3.0, abs=1e-6)
    assert cm.residual_rotation_deg < 1e-6
    # without custom rotations: the nearest enum and the rest reported
    am, cm2 = _map(R, allow_custom=False)
    assert cm2.new.orient in (1, 0, 2) and cm2.residual_rotation_deg > 2


def test_internal_compass_misalignment_is_reported_not_written():
    R = euler_to_matrix(*np.radians([0.0, 0.0, 2.0]))
    am, cm = _map(R, external=False)
    assert "COMPASS_ORIENT" not in cm.params() and cm.new.orient == 0
    assert cm.rotation_deg == pytest.approx(2.0, abs=1e-6)
    assert "internal compass" in cm.orientation_note
    am, cm = _map(R, external=False, force_external=True)
    assert cm.params()["COMPASS_EXTERNAL"] == 2.0
    assert cm.new.orient in (101, 102)


def test_accel_cross_axis_terms_are_dropped_and_reported():
    K_a = G0 * np.array([[1.0, 0.01, 0.0], [0.0, 1.02, 0.0], [0.0, 0.0, 0.98]])
    am = map_accel(K_a, np.zeros(3), fw.AccelCal())
    assert 0.2 < am.dropped_tilt_deg < 0.6  # ~0.01 rad of skew
    np.testing.assert_allclose(am.new.scale, G0 / np.linalg.norm(K_a, axis=1))


def test_dip_of_the_wrong_sign_means_a_mirrored_compass():
    K_a, b_a, K_m, b_m, h_z = _engine_truth((1, 1, 1), (0, 0, 0), np.eye(3), (0, 0, 0), np.eye(3), incl_deg=-60)
    am = map_accel(K_a, b_a, fw.AccelCal())
    with pytest.raises(ParameterMappingError, match="mirrored"):
        map_compass(K_m, b_m, h_z, am.frame_rotation, fw.CompassCal(external=True), {}, field_mgauss=500,
                    field_source="t", board_rotation=np.eye(3), inclination_model_deg=60.0)
