"""The .param reader/writer and the ArduPilot name rules used by the writer."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mavcal.ardupilot.protocol import force_save_kinds, needs_reboot, vector_group
from mavcal.autopilot.paramfile import (
    ParamFileError,
    format_param_value,
    parse_param_text,
    read_param_file,
    write_param_file,
)
from mavcal.errors import SourceError, UsageError


def test_reader_accepts_mavproxy_and_mission_planner_layouts():
    text = ("# MAVProxy style\nCOMPASS_OFS_X    -12.5\n"
            "COMPASS_OFS_Y,3.25   # Mission Planner style, trailing comment\n"
            "\n   \nCOMPASS_DEV_ID\t0x17D03\nINS_ACCSCAL_X 1.0000001e0\n")
    p = parse_param_text(text)
    assert p == {"COMPASS_OFS_X": -12.5, "COMPASS_OFS_Y": 3.25, "COMPASS_DEV_ID": 97539.0,
                 "INS_ACCSCAL_X": 1.0000001}
    assert list(p) == ["COMPASS_OFS_X", "COMPASS_OFS_Y", "COMPASS_DEV_ID", "INS_ACCSCAL_X"]


@pytest.mark.parametrize("line", ["COMPASS_OFS_X", "COMPASS_OFS_X 1 2", "compass_ofs_x 1",
                                  "A_NAME_LONGER_THAN_16 1", "COMPASS_OFS_X abc", "COMPASS_OFS_X nan",
                                  "COMPASS_OFS_X inf"])
def test_bad_lines_name_the_line(line):
    with pytest.raises(ParamFileError) as exc:
        parse_param_text(f"# header\nCOMPASS_OFS_Y 1\n{line}\n", source="f.param")
    assert exc.value.line == 3
    assert "f.param:3" in str(exc.value)
    assert isinstance(exc.value, SourceError) and exc.value.exit_code == 3


def test_missing_file_is_a_source_error(tmp_path):
    with pytest.raises(ParamFileError):
        read_param_file(tmp_path / "nope.param")


def test_writer_sorts_keeps_full_precision_and_refuses_to_overwrite(tmp_path):
    vals = {"INS_ACCSCAL_X": 1.0000001, "COMPASS_OFS_X": 1e-7, "COMPASS_DEV_ID": 97539, "AHRS_TRIM_X": 0.1}
    p = write_param_file(tmp_path / "a.param", vals, header=["hello"], exclusive=True)
    text = p.read_text()
    lines = [ln for ln in text.splitlines() if not ln.startswith("#")]
    assert lines == ["AHRS_TRIM_X,0.1", "COMPASS_DEV_ID,97539", "COMPASS_OFS_X,1e-7", "INS_ACCSCAL_X,1.0000001"]
    back = read_param_file(p)
    for k, v in vals.items():
        assert np.float32(back[k]) == np.float32(v)
    with pytest.raises(UsageError):
        write_param_file(p, vals, exclusive=True)


@settings(max_examples=300, deadline=None)
@given(st.floats(width=32, allow_nan=False, allow_infinity=False))
def test_format_round_trips_every_float32(x):
    s = format_param_value(x)
    assert np.float32(float(s)) == np.float32(x)
    assert len(s) <= 16


def test_name_rules():
    assert vector_group("COMPASS_OFS2_Y") == ("COMPASS_OFS2_X", "COMPASS_OFS2_Y", "COMPASS_OFS2_Z")
    assert vector_group("INS_ACC3SCAL_Z") == ("INS_ACC3SCAL_X", "INS_ACC3SCAL_Y", "INS_ACC3SCAL_Z")
    assert vector_group("COMPASS_SCALE") is None and vector_group("CUST_ROT1_ROLL") is None
    assert needs_reboot("COMPASS_PRIO2_ID") and needs_reboot("CUST_ROT1_YAW")
    assert needs_reboot("COMPASS_ORIENT2", 101) and not needs_reboot("COMPASS_ORIENT2", 6)
    assert not needs_reboot("COMPASS_OFS_X", 10)
    assert force_save_kinds(["COMPASS_OFS_X", "INS_ACC2SCAL_Y"]) == ("compass", "accel")
    assert force_save_kinds(["SR0_RAW_SENS"]) == ()


def test_byte_order_mark_is_accepted(tmp_path):
    p = tmp_path / "bom.param"
    p.write_bytes("\ufeffCOMPASS_OFS_X,12.5\nCOMPASS_OFS_Y 3\n".encode("utf-8"))
    assert read_param_file(p) == {"COMPASS_OFS_X": 12.5, "COMPASS_OFS_Y": 3.0}


@pytest.mark.parametrize("text", ["", "# only a comment\n\n"])
def test_file_without_parameters_is_unreadable_input(tmp_path, text):
    p = tmp_path / "empty.param"
    p.write_text(text)
    with pytest.raises(ParamFileError, match="holds no parameters") as ei:
        read_param_file(p)
    assert ei.value.exit_code == 3
