"""mavcal.testing: fixtures live apart from the product, and the test vehicle's parameter
table and truth conventions are what their names and docstrings say."""
import ast
import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest

from mavcal.ardupilot import firmware as fw
from mavcal.core.constants import GRAVITY_MPS2
from mavcal.testing.simlog import AccelErrorTruth
from mavcal.testing.vehicle_params import (
    COMPASS_DEV_IDS,
    INT8,
    INT32,
    REAL32,
    ParamStore,
    ap_set_float,
    default_param_table,
)
from mavcal.testing.vehicle_sensors import AccelCalTruth, CompassTruth, SensorModel, VehicleTruth

PKG = Path(__file__).resolve().parents[1] / "mavcal"


def _imports(path: Path):
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            yield from (a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            yield node.module
            yield from (f"{node.module}.{a.name}" for a in node.names)


def test_no_product_module_imports_mavcal_testing():
    product = [p for p in PKG.rglob("*.py") if "testing" not in p.relative_to(PKG).parts]
    assert len(product) > 30
    offenders = {str(p.relative_to(PKG)): m for p in product for m in _imports(p)
                 if m == "mavcal.testing" or m.startswith("mavcal.testing.")}
    assert offenders == {}


def test_the_fixtures_left_the_product_packages():
    for gone in ("mavcal.link.testvehicle", "mavcal.sim.logs", "mavcal.sources.writers", "mavcal.ardupilot.sitl"):
        assert importlib.util.find_spec(gone) is None, gone


def test_gyro_param_names_follow_the_accel_scheme():
    assert fw.gyro_param_names(0) == {"ofs": ("INS_GYROFFS_X", "INS_GYROFFS_Y", "INS_GYROFFS_Z"), "id": "INS_GYR_ID"}
    assert fw.gyro_param_names(2) == {"ofs": ("INS_GYR3OFFS_X", "INS_GYR3OFFS_Y", "INS_GYR3OFFS_Z"),
                                      "id": "INS_GYR3_ID"}
    assert fw.gyro_param_names(4)["id"] == "INS5_GYR_ID"
    with pytest.raises(ValueError):
        fw.gyro_param_names(fw.MAX_IMUS)


def test_param_table_holds_every_name_the_firmware_builders_give():
    rows = {r.name: r for r in default_param_table()}
    assert len(rows) == len(default_param_table())  # no duplicates
    for k in range(3):
        cn = fw.compass_param_names(k)
        for key in ("ofs", "dia", "odi", "mot"):
            names = tuple(cn[key])
            assert all(rows[n].vector == names and rows[n].param_type == REAL32 for n in names)
        assert rows[cn["dev_id"]].default == COMPASS_DEV_IDS[k] == rows[cn["prio_id"]].default
        assert rows[cn["orient"]].param_type == rows[cn["external"]].param_type == INT8
        an, gn = fw.accel_param_names(k), fw.gyro_param_names(k)
        assert [rows[n].default for n in an["scale"]] == [1.0, 1.0, 1.0]
        assert all(n in rows for n in an["ofs"] + gn["ofs"]) and rows[gn["id"]].param_type == INT32
    board = fw.board_param_names()
    assert all(n in rows for n in (board["orientation"], board["motct"], *board["custom1"], *board["custom2"]))


def test_param_set_semantics():
    store = ParamStore({fw.compass_param_names(0)["orient"]: 6})
    ofs2 = fw.compass_param_names(1)["ofs"]
    assert store.values[fw.compass_param_names(0)["orient"]] == 6.0
    assert store.param_set("NO_SUCH_PARAM", 1.0).echo == ()
    assert store.param_set(ofs2[0], math.nan).stored is None
    out = store.param_set(ofs2[0], 0.1)  # a Vector3's X: all three echoed, float32 stored
    assert out.stored == float(np.float32(0.1)) and out.echo == ofs2 and not out.denied
    assert store.param_set(ofs2[1], 0.2).echo == (ofs2[1],)  # Y (or Z): only itself
    for ident in ("COMPASS_DEV_ID", "COMPASS_DEV_ID6", fw.accel_param_names(1)["id"], fw.gyro_param_names(2)["id"]):
        out = store.param_set(ident, 5.0)  # device ids carry no internal-use-only flag: writable
        assert not out.denied and out.stored == 5.0 and out.echo == (ident,) and store.values[ident] == 5.0
    out = store.param_set("MIS_TOTAL", 5.0)  # flagged internal-use-only: denied with BRD_OPTIONS 0
    assert out.denied and out.stored is None and out.echo == ("MIS_TOTAL",) and store.values["MIS_TOTAL"] == 0.0
    store.set_local("BRD_OPTIONS", 4)  # ALLOW_SET_INTERNAL_PARM
    assert store.param_set("MIS_TOTAL", 5.0).stored == 5.0
    denying = ParamStore(deny=("COMPASS_OFS_X",))  # a read-only defaults entry
    assert denying.param_set("COMPASS_OFS_X", 1.0).denied
    assert ap_set_float(2.995, INT8) == 3.0 and ap_set_float(-1000.0, INT8) == -128.0
    with pytest.raises(KeyError):
        ParamStore({"NO_SUCH_PARAM": 1.0})


def test_boot_reorders_whole_compass_sets_by_priority():
    c0, c1 = fw.compass_param_names(0), fw.compass_param_names(1)
    store = ParamStore({c0["ofs"][0]: 11.0, c1["ofs"][0]: 22.0, c1["dia"][2]: 0.9,
                        c0["prio_id"]: COMPASS_DEV_IDS[1], c1["prio_id"]: COMPASS_DEV_IDS[0]})
    store.reorder_compass_params()
    assert store.compass_dev_ids() == [COMPASS_DEV_IDS[1], COMPASS_DEV_IDS[0], COMPASS_DEV_IDS[2]]
    assert store.values[c0["ofs"][0]] == 22.0 and store.values[c0["dia"][2]] == pytest.approx(0.9)
    assert store.values[c1["ofs"][0]] == 11.0 and store.values[c1["dia"][2]] == 1.0
    assert (store.values[c0["external"]], store.values[c1["external"]]) == (0.0, 1.0)


def test_accel_cal_truth_is_the_ideal_calibration():
    """AccelCalTruth: raw = u / scale + offsets, so INS_ACCOFFS = offsets, INS_ACCSCAL = scale."""
    at = AccelCalTruth(offsets=(0.3, -0.2, 0.5), scale=(1.02, 0.98, 1.01), noise_mps2=0.0)
    truth = VehicleTruth(accels=(at,) * 3, compasses=(CompassTruth(COMPASS_DEV_IDS[0], noise_mgauss=0.0),),
                         gyro_noise_rads=0.0)
    model = SensorModel(truth, np.random.default_rng(0))
    model.boot(COMPASS_DEV_IDS, {101: (0.0, 0.0, 0.0), 102: (0.0, 0.0, 0.0)})
    u = np.array([0.0, 0.0, -GRAVITY_MPS2])
    raw = model.raw(np.eye(3), np.zeros(3), noise=False)["accel_mps2"][0]
    np.testing.assert_allclose(raw, u / np.array(at.scale) + np.array(at.offsets), atol=1e-12)
    ideal = {**dict(zip(fw.accel_param_names(0)["ofs"], at.offsets)), **dict(zip(fw.accel_param_names(0)["scale"],
                                                                                 at.scale))}
    got = model.corrected(np.eye(3), np.zeros(3), ideal, noise=False)["accel_mps2"][0]
    np.testing.assert_allclose(got, u, atol=1e-12)


def test_accel_error_truth_is_the_sensor_error():
    """AccelErrorTruth: raw = K u + bias, K upper triangular from gain and cross."""
    at = AccelErrorTruth(bias_mps2=(0.1, 0.2, 0.3), gain=(1.1, 0.9, 1.0), cross=(0.01, 0.02, 0.03))
    np.testing.assert_array_equal(at.K, [[1.1, 0.01, 0.02], [0.0, 0.9, 0.03], [0.0, 0.0, 1.0]])
    assert not hasattr(at, "offsets") and not hasattr(AccelCalTruth(), "bias_mps2")


def test_start_vehicle_gives_a_running_vehicle_on_localhost(start_vehicle):
    v = start_vehicle("tcp", heartbeat_hz=5, seed=2)
    assert v.port is not None and v.gcs_device == f"tcp:127.0.0.1:{v.port}"
    with v as same:  # a started vehicle used as a context manager is the same, still running
        assert same is v and v.alive
