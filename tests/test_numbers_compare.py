"""Issue 23: the one rule for comparing computed numbers (mavcal.testing.numbers): tolerant of
the last bits a BLAS kernel or CPU changes, strict about words, counts and real changes."""
from __future__ import annotations

import math

import numpy as np
import pytest

from mavcal.testing.numbers import (
    assert_close,
    assert_json_close,
    assert_text_close,
    json_differences,
    numbers_close,
    text_differences,
)

GOLDEN = "  INS_ACC2OFFS_XYZ  (0.001, 0.001, 0.001) -> (0.00011292261, 0.00043066006, -0.00068841095)  *\n"
EPYC = "  INS_ACC2OFFS_XYZ  (0.001, 0.001, 0.001) -> (0.00011292257, 0.0004306601, -0.0006884109)  *\n"


def test_the_issues_amd_epyc_line_equals_the_golden_one():
    assert text_differences(EPYC, GOLDEN) == []


def test_words_counts_and_real_changes_are_differences():
    assert text_differences(GOLDEN.replace("*", " "), GOLDEN)  # the "changed" mark
    assert text_differences(GOLDEN.replace("ACC2", "ACC3"), GOLDEN)  # an instance number (integer: exact)
    assert text_differences("21 of 21 still intervals", "20 of 21 still intervals")
    assert text_differences(GOLDEN.replace("0.00043066006", "0.00043076006"), GOLDEN)  # 2.3e-4 relative
    assert text_differences("OFS -114.92157", "OFS -114.92127")  # 2.6e-6 relative
    assert text_differences(GOLDEN + "one more line\n", GOLDEN) == ["2 lines, expected 1"]
    assert text_differences(GOLDEN.rstrip("\n"), GOLDEN) == ["the final newline differs"]
    with pytest.raises(AssertionError, match="line 1: numbers differ: 0.3 vs 0.1"):
        assert_text_close("x 0.3\n", "x 0.1\n")
    with pytest.raises(AssertionError, match="line 1: text differs"):
        assert_text_close("accepted 1", "rejected 1")


def test_a_printed_number_may_round_the_other_way():
    """0.22449999 and 0.22450001 print as 0.224 and 0.225: one unit of the last printed digit
    is allowed, two are not; exponents count (6.87e+04: a unit is 100)."""
    assert text_differences("heading <= 0.225 deg", "heading <= 0.224 deg") == []
    assert text_differences("heading <= 0.226 deg", "heading <= 0.224 deg")
    assert text_differences("chi2=6.88e+04", "chi2=6.87e+04") == []
    assert text_differences("chi2=6.89e+04", "chi2=6.87e+04")


def test_numbers_near_zero_have_an_absolute_floor():
    assert text_differences("(0, 1e-17, -2.5e-12)", "(0, -0, 0)") == []
    assert text_differences("(0, 3e-6, 0)", "(0, 0, 0)")  # 1e-6 would be one printed unit
    assert numbers_close(1.0, 1.0 + 5e-7) and not numbers_close(1.0, 1.0 + 2e-6)
    assert numbers_close(math.nan, math.nan) and not numbers_close(math.nan, 0.0)
    assert numbers_close(math.inf, math.inf) and not numbers_close(math.inf, 1e308)


def test_json_compares_structure_exactly_and_floats_at_the_tolerance():
    want = {"exit_code": 0, "accepted": True, "error": None, "ofs": [32.525894123, 65.388275, -114.92127],
            "reasons": ["heading 0.22 deg > 0.2"], "n": 15}
    got = {**want, "ofs": [32.525894123 * (1 + 3e-8), 65.388275, -114.92127]}
    assert_json_close(got, want)
    assert json_differences({**want, "n": 14}, want) == ["$.n: 14 vs 15"]
    assert json_differences({**want, "accepted": 1}, want) == ["$.accepted: 1 vs True"]
    assert json_differences({**want, "ofs": want["ofs"][:2]}, want)
    assert json_differences({**want, "x": 1}, want) == ["$: keys ['x'] in only one"]
    assert json_differences({**want, "reasons": ["heading 0.25 deg > 0.2"]}, want)
    assert json_differences({**want, "ofs": [33.0, 65.388275, -114.92127]}, want)


def test_a_refactor_is_equal_within_1e_9_at_the_scale_of_the_array():
    x = np.array([[1.0, 1e-17], [3.0, -2.0]])
    assert_close(x * (1 + 1e-12) + np.array([[0, 3e-13], [0, 0]]), x)  # an element that cancels: the array's scale
    with pytest.raises(AssertionError):
        assert_close(x * (1 + 1e-8), x)
    with pytest.raises(AssertionError, match="shape"):
        assert_close(x[:1], x)
    assert_close({"a": [1.0, np.float64(2.0)], "b": "p=0.193"}, {"a": [1.0, 2.0 + 1e-15], "b": "p=0.193"})
    assert_close([np.ones(2), np.zeros(3)], [np.ones(2), np.zeros(3)])
    assert_close(np.array([np.nan, 1.0]), np.array([np.nan, 1.0]))
