"""The one autopilot registry (issue 38): which model a recording or a name gets, and that nothing
outside the autopilot folders, the neutral layer and the fixtures names ``mavcal.ardupilot`` or
``mavcal.px4`` (nor one autopilot folder the other)."""
from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

from mavcal.autopilot import NAMES, model_for, model_named
from mavcal.sources.types import ImuLog, SensorSeries

PKG = Path(__file__).resolve().parents[1] / "mavcal"
AUTOPILOTS = ("ardupilot", "px4")


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


def test_only_the_neutral_layer_names_an_autopilot():
    offenders, cross = [], []
    for path in PKG.rglob("*.py"):
        folder = _folder(path)
        named = {ap for imp in _imports(path) for ap in AUTOPILOTS if imp == f"mavcal.{ap}"
                 or imp.startswith(f"mavcal.{ap}.")}
        if folder in AUTOPILOTS:
            cross += [f"{path.relative_to(PKG)} -> {ap}" for ap in named if ap != folder]
        elif folder not in ("autopilot", "testing") and named:
            offenders.append(f"{path.relative_to(PKG)} -> {sorted(named)}")
    assert not offenders, offenders
    assert not cross, cross


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
