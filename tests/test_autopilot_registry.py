"""The one autopilot registry (issue 38): which model a recording or a name gets, and that nothing
outside the autopilot folders, the registry and the fixtures names ``mavcal.ardupilot`` or
``mavcal.px4`` (nor one autopilot folder the other), not even in a docstring; the write rules that
ask every model give what ArduPilot's alone gave."""
from __future__ import annotations

import ast
import re
from pathlib import Path

import numpy as np
import pytest

from mavcal.autopilot import NAMES, model_for, model_named
from mavcal.sources.types import ImuLog, SensorSeries

PKG = Path(__file__).resolve().parents[1] / "mavcal"
AUTOPILOTS = ("ardupilot", "px4")
#: the one module outside the autopilot folders (and the fixtures) that names them
REGISTRY = Path("autopilot") / "registry.py"


def _imports(path: Path) -> set[str]:
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
            out.update(f"{node.module}.{a.name}" for a in node.names)
    return out


def _folder(path: Path) -> str | None:
    parts = path.relative_to(PKG).parts
    return parts[0] if len(parts) > 1 else None


def test_only_the_registry_imports_an_autopilot():
    """Imports anywhere in a module (lazy ones in functions, TYPE_CHECKING ones too)."""
    offenders, cross = [], []
    for path in PKG.rglob("*.py"):
        folder = _folder(path)
        named = {ap for imp in _imports(path) for ap in AUTOPILOTS if imp == f"mavcal.{ap}"
                 or imp.startswith(f"mavcal.{ap}.")}
        if folder in AUTOPILOTS:
            cross += [f"{path.relative_to(PKG)} -> {ap}" for ap in named if ap != folder]
        elif folder != "testing" and path.relative_to(PKG) != REGISTRY and named:
            offenders.append(f"{path.relative_to(PKG)} -> {sorted(named)}")
    assert not offenders, offenders
    assert not cross, cross


def test_only_the_registry_names_an_autopilot_folder():
    r"""``grep -rn "mavcal.ardupilot\|mavcal.px4" mavcal`` outside the two folders: the registry and the
    fixtures only (docstrings and comments count)."""
    pattern = re.compile(r"mavcal.ardupilot|mavcal.px4")
    hits = []
    for path in sorted(PKG.rglob("*.py")):
        rel = path.relative_to(PKG)
        if _folder(path) in AUTOPILOTS + ("testing",) or rel == REGISTRY:
            continue
        hits += [f"{rel}:{n}: {line.strip()}" for n, line in
                 enumerate(path.read_text(encoding="utf-8").splitlines(), 1) if pattern.search(line)]
    assert not hits, hits
    assert pattern.search((PKG / REGISTRY).read_text(encoding="utf-8"))  # the registry is where they are named


def test_no_transitional_re_export_is_left():
    """Every module of the neutral layer is neutral code: none re-exports an autopilot's."""
    for path in (PKG / "autopilot").glob("*.py"):
        assert "Transitional" not in path.read_text(encoding="utf-8"), path.name


def test_the_write_rules_of_every_model_are_those_of_each_autopilot():
    """Each autopilot answers for its own names: over a mix of ArduPilot's and PX4's names the
    neutral write rules give what ArduPilot's rules and PX4's detours give on their own."""
    from mavcal.ardupilot import devices as ap_devices
    from mavcal.ardupilot import limits as ap_limits
    from mavcal.ardupilot import protocol as ap_protocol
    from mavcal.autopilot import protocol
    from mavcal.px4 import params as px4_params

    changes = {"COMPASS_OFS_X": 2500.0, "COMPASS_OFS_Y": 10.0, "INS_ACCSCAL_X": 1.5, "COMPASS_ORIENT": 101.0,
               "CAL_MAG0_XOFF": 0.1, "CAL_MAG0_YOFF": 0.2, "CAL_ACC0_XSCALE": 1.01, "CUST_ROT_ENABLE": 1.0}
    vehicle = {"COMPASS_OFS_Z": 10.0, "COMPASS_DEV_ID": 97539.0, "COMPASS_PRIO1_ID": 97539.0, "CAL_MAG0_ID": 1.0}
    assert protocol.check_limits(changes, vehicle) == ap_limits.check_limits(changes, vehicle)
    assert protocol.check_limits(changes, vehicle)  # something to compare
    assert protocol.failing_kinds(changes, vehicle) == ap_limits.failing_kinds(changes, vehicle) == {"compass", "accel"}
    assert protocol.related_names(changes) == ap_limits.related_names(changes)
    assert protocol.id_names() == ap_devices.id_names()
    for n, v in changes.items():
        assert protocol.vector_group(n) == ap_protocol.vector_group(n)
        assert protocol.needs_reboot(n, v) == ap_protocol.needs_reboot(n, v)
    assert protocol.force_save_kinds(changes) == ap_protocol.force_save_kinds(changes) == ("compass", "accel")
    assert protocol.detoured_order(changes) == px4_params.detoured_order(changes)
    assert protocol.detour_dwell_s() == px4_params.DETOUR_DWELL_S
    log_params = {"COMPASS_DEV_ID": 1.0, "INS_ACC_ID": 2.0}
    assert protocol.device_id_problems(changes, log_params, vehicle) == ap_devices.device_id_problems(
        changes, log_params, vehicle)
    assert protocol.device_id_problems(changes, log_params, vehicle)  # the compass ids differ
    maps = dict(compass_map={0: 1}, imu_map={0: 2})
    assert protocol.remap_changes(changes, **maps) == ap_devices.remap_changes(changes, **maps)
    assert protocol.parse_slot_map("1:3", "compass") == (0, 2)  # ArduPilot's slots by position, 1-based
    with pytest.raises(ValueError, match="compass slots are 1..3"):
        protocol.parse_slot_map("1:4", "compass")


def test_the_gates_defaults_are_ardupilots_limits_in_its_words():
    from mavcal.ardupilot import limits as ap_limits
    from mavcal.autopilot.gates import GateConfig

    c = model_named("ArduPilot").gate_config(GateConfig())
    assert (c.accel_offset_max_mps2, c.accel_scale_range, c.dia_range, c.odi_max, c.field_range_mgauss) == (
        ap_limits.ACCEL_OFFSET_MAX_MPS2, ap_limits.ACCEL_SCALE_RANGE, ap_limits.DIA_RANGE, ap_limits.ODI_MAX,
        ap_limits.FIELD_RANGE_MGAUSS)
    assert (c.limits_of, c.autopilot, c.offset_limit_name) == ("ArduPilot's", "ArduPilot", "COMPASS_OFFS_MAX")
    p = model_named("PX4").gate_config(GateConfig())
    assert (p.limits_of, p.autopilot) == ("the plausible", "PX4")


def test_model_by_name():
    assert [model_named(n).name for n in NAMES] == list(NAMES)
    assert model_named(" px4 ").name == "PX4" and model_named("ArduPilot").name == "ArduPilot"
    with pytest.raises(ValueError, match="unknown autopilot 'betaflight'"):
        model_named("betaflight")


def test_model_for_a_recording():
    s = SensorSeries("accel", 0, "IMU", np.zeros(1), np.zeros((1, 3)))
    assert model_for(ImuLog(source="x.ulg", kind="ulog", series=(s,))).name == "PX4"
    assert model_for(ImuLog(source="x.bin", kind="dataflash", series=(s,))).name == "ArduPilot"
    assert model_for(ImuLog(source="udp", kind="live", series=(s,), vehicle={"autopilot": 12})).name == "PX4"
    assert model_for(ImuLog(source="udp", kind="live", series=(s,), vehicle={"autopilot": 3})).name == "ArduPilot"
