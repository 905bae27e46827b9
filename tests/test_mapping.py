"""Mapping a joint calibration onto ArduPilot's parameters."""
import numpy as np
import pytest

from mavcal.ardupilot import firmware as fw
from mavcal.ardupilot.mapping import map_accel, map_compass
from mavcal.autopilot.rotations import euler_to_matrix, rotation_matrix
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


def _cal(R_true=None):
    R_true = np.eye(3) if R_true is None else R_true
    from mavcal.core.types import Calibration, SensorModel

    K_a, b_a, K_m, b_m, h_z = _engine_truth((0.99, 1.02, 0.97), (0.1, -0.2, 0.3), M_TRUE, (40.0, -60.0, 120.0), R_true)
    return Calibration(accel=SensorModel(K_a, b_a, np.eye(3) * 1e-4, "accel"),
                       mag=SensorModel(K_m, b_m, np.eye(3), "mag"), gravity=np.array([0.0, 0.0, -1.0]),
                       field=np.array([1.0, 0.0, h_z]), orientations=np.empty((0, 3, 3)), cost=0.0, iterations=0,
                       converged=True, message="test")


PARAMS = {"COMPASS_EXTERNAL": 1.0, "COMPASS_ORIENT": 0.0, "AHRS_ORIENTATION": 0.0, "COMPASS_OFS_X": 5.0}


def test_map_calibration_is_map_accel_and_map_compass_of_one_pair():
    from mavcal.ardupilot.mapping import map_calibration

    means = np.array([[300.0, 0.0, 400.0], [-300.0, 0.0, 400.0]])
    m = map_calibration(_cal(), PARAMS, means, field_mgauss=500.0)
    am, cm = _map(np.eye(3))
    assert len(m.accel) == len(m.compass) == 1
    np.testing.assert_allclose(m.accel[0].new.scale, am.new.scale, atol=1e-12)
    np.testing.assert_allclose(m.compass[0].new.ofs_mgauss, cm.new.ofs_mgauss, atol=1e-9)
    assert m.compass[0].field_source == "given" and m.compass[0].field_mgauss == 500.0
    assert dict(m.new) == {**m.accel[0].params(), **m.compass[0].params()}
    assert m.old["COMPASS_OFS_X"] == 5.0 and m.old["INS_ACCOFFS_X"] is None  # unknown old values stay None
    assert m.notes[0] == m.compass[0].orientation_note


def test_field_magnitude_choice():
    from mavcal.autopilot.mapping import field_magnitude

    old = fw.compass_cal_from_params({}, 0)
    means = np.array([[300.0, 0.0, 400.0], [0.0, 500.0, 0.0]])
    assert field_magnitude(means, old, field_mgauss=420.0) == (420.0, "given", None)
    f, src, incl = field_magnitude(means, old)  # no position: not checked, never the calibration in force
    assert f is None and src.startswith("not checked") and incl is None
    f, src, incl = field_magnitude(means, old, location=(47.4, 8.5, 400.0))
    assert 400 < f < 550 and src.startswith("World Magnetic Model") and 55 < incl < 70
    f, src, incl = field_magnitude(means, old, location=(47.4, 8.5), field_mgauss=420.0)
    assert (f, src) == (420.0, "given") and 55 < incl < 70  # the given value wins; the dip still checks


def test_merge_mappings_adds_the_other_instances():
    from mavcal.ardupilot.mapping import map_calibration
    from mavcal.autopilot.mapping import merge_mappings

    means = np.array([[300.0, 0.0, 400.0]])
    primary = map_calibration(_cal(), PARAMS, means, field_mgauss=500.0)
    other_accel = map_calibration(_cal(), PARAMS, means, accel_instance=1, field_mgauss=500.0)
    other_compass = map_calibration(_cal(), PARAMS, means, mag_instance=1, field_mgauss=500.0)
    merged = merge_mappings(primary, [other_accel, other_compass], {"INS_ACC2OFFS_X": 0.5})
    assert [a.instance for a in merged.accel] == [0, 1] and [c.instance for c in merged.compass] == [0, 1]
    assert set(merged.new) == set(primary.new) | set(other_accel.accel[0].params()) | set(
        other_compass.compass[0].params())
    assert set(merged.old) == set(merged.new)
    assert merged.old["COMPASS_OFS_X"] == 5.0 and merged.old["INS_ACC2OFFS_X"] is None  # the pair recorded None
    assert merged.notes[-1].startswith("compass 1: ")
