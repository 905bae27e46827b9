"""ArduPilot's calibration forward/inverse models and parameter names."""
import numpy as np
import pytest

from mavcal.ardupilot import firmware as fw
from mavcal.autopilot.rotations import rotation_matrix


def test_param_names():
    c0, c1, c2 = (fw.compass_param_names(k) for k in range(3))
    assert c0["ofs"] == ("COMPASS_OFS_X", "COMPASS_OFS_Y", "COMPASS_OFS_Z")
    assert c1["ofs"][0] == "COMPASS_OFS2_X" and c2["odi"][1] == "COMPASS_ODI3_Y"
    assert c0["scale"] == "COMPASS_SCALE" and c1["scale"] == "COMPASS_SCALE2"
    assert c0["external"] == "COMPASS_EXTERNAL" and c1["external"] == "COMPASS_EXTERN2"
    assert c1["dev_id"] == "COMPASS_DEV_ID2" and c0["prio_id"] == "COMPASS_PRIO1_ID"
    assert c0["orient"] == "COMPASS_ORIENT" and c2["orient"] == "COMPASS_ORIENT3"
    a = [fw.accel_param_names(i) for i in range(5)]
    assert a[0]["ofs"][0] == "INS_ACCOFFS_X" and a[0]["scale"][2] == "INS_ACCSCAL_Z"
    assert a[1]["ofs"][0] == "INS_ACC2OFFS_X" and a[2]["scale"][0] == "INS_ACC3SCAL_X"
    assert a[3]["ofs"][0] == "INS4_ACCOFFS_X" and a[4]["id"] == "INS5_ACC_ID"
    with pytest.raises(ValueError):
        fw.compass_param_names(3)


def test_scale_window_and_zero_dia():
    assert fw.effective_scale(0.0) == 1.0
    assert fw.effective_scale(1.6) == 1.0
    assert fw.effective_scale(1.5) == 1.5
    assert fw.effective_scale(0.7) == 0.7
    assert fw.effective_scale(0.6) == 1.0
    np.testing.assert_array_equal(fw.soft_iron_matrix((0, 0, 0), (0.3, 0.2, 0.1)), np.eye(3))


def test_compass_forward_matches_formula_and_inverse():
    rng = np.random.default_rng(3)
    cal = fw.CompassCal(ofs_mgauss=(120, -40, 33), dia=(1.05, 0.97, 1.01), odi=(0.02, -0.01, 0.03),
                        scale=1.1, orient=4, external=True)
    raw = rng.normal(0, 300, (20, 3))
    mot = rng.normal(0, 5, (20, 3))
    M = np.array([[1.05, 0.02, -0.01], [0.02, 0.97, 0.03], [-0.01, 0.03, 1.01]])
    expect = (M @ (1.1 * (rotation_matrix(4) @ raw.T + np.array([[120], [-40], [33]])))).T + mot
    got = fw.apply_compass(cal, raw, mot)
    np.testing.assert_allclose(got, expect, atol=1e-9)
    np.testing.assert_allclose(fw.undo_compass(cal, got, mot, sensor_frame=True), raw, atol=1e-9)
    np.testing.assert_allclose(fw.undo_compass(cal, got, mot), raw @ rotation_matrix(4).T, atol=1e-9)
    # scale out of range is ignored
    cal2 = fw.CompassCal(ofs_mgauss=(1, 2, 3), scale=2.0)
    np.testing.assert_allclose(fw.apply_compass(cal2, raw), raw + [1, 2, 3])


def test_accel_forward_inverse_and_calibrating():
    rng = np.random.default_rng(4)
    cal = fw.AccelCal(ofs_mps2=(0.05, -0.02, 0.2), scale=(0.998, 0.942, 0.997), board_orient=16)
    raw = rng.normal(0, 5, (10, 3))
    expect = ((raw - [0.05, -0.02, 0.2]) * [0.998, 0.942, 0.997]) @ rotation_matrix(16).T
    got = fw.apply_accel(cal, raw)
    np.testing.assert_allclose(got, expect, atol=1e-12)
    np.testing.assert_allclose(fw.undo_accel(cal, got), raw, atol=1e-12)
    during = fw.apply_accel(cal, raw, calibrating=True)
    np.testing.assert_allclose(during, raw @ rotation_matrix(16).T, atol=1e-12)
    np.testing.assert_allclose(fw.undo_accel(cal, during, calibrating=True), raw, atol=1e-12)
    # the real vehicle: level, board Y vertical; |a| 9.81 corrected is 10.42 raw
    level_raw = np.array([0.05, -9.80665 / 0.942 - 0.02, 0.2])
    assert np.linalg.norm(fw.apply_accel(cal, level_raw)) == pytest.approx(9.80665, abs=1e-9)


def test_cal_from_params_defaults_and_mounting():
    missing = []
    c = fw.compass_cal_from_params({"COMPASS_OFS2_X": 5.0, "AHRS_ORIENTATION": 16}, 1, missing)
    assert c.ofs_mgauss == (5.0, 0.0, 0.0) and c.dia == (1.0, 1.0, 1.0)
    assert c.orient == 16  # internal (no ORIENT, no EXTERN): board orientation
    assert "COMPASS_OFS2_Y" in missing and "COMPASS_SCALE2" in missing
    ext = fw.compass_cal_from_params({"COMPASS_EXTERNAL": 1, "COMPASS_ORIENT": 38, "AHRS_ORIENTATION": 12}, 0)
    assert ext.orient == 38 and ext.external is True
    custom = fw.compass_cal_from_params({"COMPASS_EXTERNAL": 1, "COMPASS_ORIENT": 101, "CUST_ROT1_ROLL": 0,
                                         "CUST_ROT1_PITCH": 0, "CUST_ROT1_YAW": 90}, 0)
    np.testing.assert_allclose(custom.mount_matrix, rotation_matrix(2), atol=1e-12)
    a = fw.accel_cal_from_params({"INS_ACC2SCAL_Y": 0.9, "AHRS_ORIENTATION": 8}, 1)
    assert a.scale == (1.0, 0.9, 1.0) and a.board_orient == 8
    vals = fw.accel_param_values(a, 1)
    assert vals["INS_ACC2SCAL_Y"] == 0.9
    assert fw.accel_cal_from_params({**vals, "AHRS_ORIENTATION": 8}, 1) == a
    cv = fw.compass_param_values(c, 1)
    assert cv["COMPASS_OFS2_X"] == 5.0 and cv["COMPASS_SCALE2"] == 1.0
