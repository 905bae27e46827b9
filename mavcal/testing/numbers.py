"""Comparing computed numbers at a stated tolerance: text, JSON and arrays (issue 23).

Floating-point results are not the same bits on every machine: BLAS kernels (OpenBLAS picks
one per CPU: Haswell, SkylakeX, Zen...), their thread counts and numpy's SIMD paths sum in
different orders, and the last bits differ (the 8th significant digit of a printed summary,
after a least-squares fit amplifies them). A test that compares computed floats exactly
passes on one CPU and fails on the next. So every comparison of a computed result goes
through this module, one rule everywhere:

* **two numbers** ``a`` (actual), ``b`` (expected) are equal when
  ``|a - b| <= rtol * max(|a|, |b|) + atol``; NaN equals NaN, infinities equal themselves.
* **golden text** (:func:`assert_text_close`): the text between the numbers must match
  exactly; the numbers are parsed and compared with :data:`GOLDEN_RTOL` = 1e-6 relative and
  :data:`GOLDEN_ATOL` = 1e-9 absolute (for numbers near zero, where a relative tolerance means
  nothing: a value that is 0 on one CPU is ~1e-17 on another; 1e-9 is far below the noise of
  any reading in any unit mavcal prints: m/s^2, mGauss, degrees), **plus one unit in the last
  printed digit** of the coarser of the two (a printed number stands for every value that
  rounds to it: 0.22449999 and 0.22450001 print as 0.224 and 0.225). Two integers (no
  decimal point, no exponent: counts, instance numbers, exit codes) must be equal.
* **JSON** (:func:`assert_json_close`): the same structure (keys, lengths, types), integers
  and booleans and ``null`` equal, floats at the tolerance above (without the printed-digit
  term: JSON floats keep every bit), strings as golden text.
* **refactors** (:func:`assert_close`): a rewrite of the math gives results equal within
  :data:`REFACTOR_RTOL` = 1e-9 relative; for an array, the absolute floor is 1e-9 times its
  largest element (the elements that cancel to near zero are judged at the array's scale).

1e-6 and 1e-9 are far below the sensors' noise (a 0.1 % gain error is 1e-3) and far above
rounding (1e-16 per operation, amplified by the fit's conditioning to 1e-10 at worst here).
"""
from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

__all__ = ["GOLDEN_RTOL", "GOLDEN_ATOL", "REFACTOR_RTOL", "numbers_close", "text_differences",
           "assert_text_close", "json_differences", "assert_json_close", "array_differences", "assert_close"]

#: Relative tolerance of golden outputs (text and JSON).
GOLDEN_RTOL = 1e-6
#: Absolute floor of golden outputs, for numbers near zero.
GOLDEN_ATOL = 1e-9
#: Relative tolerance of a refactor of the math (docs/development.md, "Contributor rules for numbers").
REFACTOR_RTOL = 1e-9

# a number as printed: optional sign, digits with an optional fraction (or a bare fraction),
# optional exponent; "sitl02" gives "02" (an integer, compared exactly), which is harmless
_NUMBER = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")


def numbers_close(a: float, b: float, rtol: float = GOLDEN_RTOL, atol: float = GOLDEN_ATOL) -> bool:
    """``|a - b| <= rtol * max(|a|, |b|) + atol`` (NaN equals NaN, an infinity itself)."""
    a, b = float(a), float(b)
    if math.isnan(a) or math.isnan(b):
        return math.isnan(a) and math.isnan(b)
    if math.isinf(a) or math.isinf(b):
        return a == b
    return abs(a - b) <= rtol * max(abs(a), abs(b)) + atol


def _is_integer(token: str) -> bool:
    return not any(c in token for c in ".eE")


def _last_digit(token: str) -> float:
    """One unit in the last printed digit of a decimal token ("0.224" -> 0.001, "6.87e+04" -> 100)."""
    mant, _, exp = token.lower().partition("e")
    decimals = len(mant.partition(".")[2])
    return 10.0 ** (int(exp or 0) - decimals)


def _tokens_close(a: str, b: str, rtol: float, atol: float) -> bool:
    if _is_integer(a) and _is_integer(b):
        return int(a) == int(b)
    digit = max(0.0 if _is_integer(a) else _last_digit(a), 0.0 if _is_integer(b) else _last_digit(b))
    return numbers_close(float(a), float(b), rtol, atol + digit)


def _line_difference(got: str, want: str, rtol: float, atol: float) -> str | None:
    g_num, w_num = _NUMBER.findall(got), _NUMBER.findall(want)
    if _NUMBER.split(got) != _NUMBER.split(want) or len(g_num) != len(w_num):
        return "text differs"
    bad = [f"{g} vs {w}" for g, w in zip(g_num, w_num) if not _tokens_close(g, w, rtol, atol)]
    return "numbers differ: " + ", ".join(bad) if bad else None


def text_differences(actual: str, expected: str, rtol: float = GOLDEN_RTOL, atol: float = GOLDEN_ATOL) -> list[str]:
    """The lines where ``actual`` and ``expected`` differ under the golden rule (module
    docstring), each as ``"line N: why\\n  got:  ...\\n  want: ..."``; empty when they agree."""
    got, want = actual.splitlines(), expected.splitlines()
    out = []
    for i, (g, w) in enumerate(zip(got, want), 1):
        why = _line_difference(g, w, rtol, atol)
        if why:
            out.append(f"line {i}: {why}\n  got:  {g}\n  want: {w}")
    if len(got) != len(want):
        out.append(f"{len(got)} lines, expected {len(want)}")
    elif actual.endswith("\n") != expected.endswith("\n"):
        out.append("the final newline differs")
    return out


def assert_text_close(actual: str, expected: str, rtol: float = GOLDEN_RTOL, atol: float = GOLDEN_ATOL,
                      what: str = "text") -> None:
    """Raise AssertionError naming every differing line (see :func:`text_differences`)."""
    diff = text_differences(actual, expected, rtol, atol)
    if diff:
        raise AssertionError(f"{what} differs (numbers at rtol={rtol:g}, atol={atol:g}):\n" + "\n".join(diff[:20]))


def json_differences(actual: Any, expected: Any, rtol: float = GOLDEN_RTOL, atol: float = GOLDEN_ATOL,
                     path: str = "$") -> list[str]:
    """Where two JSON-like values (dicts, lists, numbers, strings, None) differ, one line each."""
    if isinstance(expected, Mapping):
        if not isinstance(actual, Mapping):
            return [f"{path}: {type(actual).__name__}, expected an object"]
        out = [f"{path}: keys {sorted(set(actual) ^ set(expected))} in only one"] \
            if set(actual) != set(expected) else []
        for k in expected:
            if k in actual:
                out += json_differences(actual[k], expected[k], rtol, atol, f"{path}.{k}")
        return out
    if isinstance(expected, (list, tuple)):
        if not isinstance(actual, (list, tuple)) or len(actual) != len(expected):
            return [f"{path}: {actual!r:.80} vs {expected!r:.80} (length or type)"]
        return [d for i, (a, e) in enumerate(zip(actual, expected))
                for d in json_differences(a, e, rtol, atol, f"{path}[{i}]")]
    if isinstance(expected, str):
        if not isinstance(actual, str):
            return [f"{path}: {actual!r} vs {expected!r}"]
        return [f"{path}: {d}" for d in text_differences(actual, expected, rtol, atol)]
    if expected is None or isinstance(expected, bool) or isinstance(actual, bool):
        return [] if actual is expected or (type(actual) is type(expected) and actual == expected) \
            else [f"{path}: {actual!r} vs {expected!r}"]
    if isinstance(expected, (int, float, np.number)) and isinstance(actual, (int, float, np.number)):
        if isinstance(expected, (int, np.integer)) and isinstance(actual, (int, np.integer)):
            return [] if int(actual) == int(expected) else [f"{path}: {actual} vs {expected}"]
        return [] if numbers_close(actual, expected, rtol, atol) else [f"{path}: {actual!r} vs {expected!r}"]
    return [] if actual == expected else [f"{path}: {actual!r} vs {expected!r}"]


def assert_json_close(actual: Any, expected: Any, rtol: float = GOLDEN_RTOL, atol: float = GOLDEN_ATOL) -> None:
    """Raise AssertionError listing where two JSON-like values differ (see :func:`json_differences`)."""
    diff = json_differences(actual, expected, rtol, atol)
    if diff:
        raise AssertionError(f"JSON differs (numbers at rtol={rtol:g}, atol={atol:g}):\n" + "\n".join(diff[:20]))


def array_differences(actual: Any, expected: Any, rtol: float = REFACTOR_RTOL, atol: float | None = None,
                      axis: int | None = None) -> str | None:
    """Why two numeric arrays differ under the refactor rule, or None when they agree.

    Same dtype kind (float, complex, integer/bool) and shape; NaN exactly where NaN and each
    infinity where it is; the finite elements ``|a - e| <= rtol * |e| + floor`` with ``floor``
    = ``atol`` or, by default, ``rtol`` times the largest finite ``|e|`` (along ``axis`` when
    given, e.g. ``axis=-1``: each row's own scale, where rows differ by orders of magnitude).
    Integer and boolean arrays must be equal.
    """
    a, e = np.asarray(actual), np.asarray(expected)
    if a.shape != e.shape:
        return f"shape {a.shape}, expected {e.shape}"
    kinds = {"f": "f", "c": "c", "i": "i", "u": "i", "b": "i"}
    if kinds.get(a.dtype.kind) != kinds.get(e.dtype.kind):
        return f"dtype {a.dtype}, expected {e.dtype}"
    if e.dtype.kind in "iub":
        bad = np.flatnonzero(a != e)
        return None if not bad.size else f"{bad.size} of {e.size} elements differ (first at flat index {bad[0]})"
    nan_a, nan_e = np.isnan(a), np.isnan(e)
    if np.any(nan_a != nan_e) or np.any(np.isinf(a) != np.isinf(e)) or np.any(a[np.isinf(e)] != e[np.isinf(e)]):
        return "NaN or infinity where the other has not"
    fin = np.isfinite(e)
    mag = np.where(fin, np.abs(e), 0.0)
    if atol is not None:
        floor: Any = atol
    elif axis is None:
        floor = rtol * (float(mag.max()) if mag.size else 0.0)
    else:
        floor = rtol * np.max(mag, axis=axis, keepdims=True) if mag.size else 0.0
    ok = ~fin | (np.abs(np.where(fin, a, 0.0) - np.where(fin, e, 0.0)) <= rtol * mag + floor)
    if np.all(ok):
        return None
    bad = np.flatnonzero(~ok)
    i = bad[0]
    return (f"{bad.size} of {e.size} elements differ beyond rtol={rtol:g} (first at flat index {i}: "
            f"{a.flat[i]!r} vs {e.flat[i]!r})")


def assert_close(actual: Any, expected: Any, rtol: float = REFACTOR_RTOL, atol: float | None = None) -> None:
    """``actual`` equals ``expected`` within ``rtol`` (default: a refactor's 1e-9).

    Numeric arrays (and numbers, and sequences numpy takes as numeric arrays) as in
    :func:`array_differences` (the absolute floor, unless ``atol``, is ``rtol`` times the
    largest ``|expected|``); mappings and other sequences element by element; strings as
    golden text; other values equal.
    """
    if isinstance(expected, Mapping) or isinstance(expected, str) or expected is None:
        assert_json_close(actual, expected, rtol, 0.0 if atol is None else atol)
        return
    try:
        e = np.asarray(expected)
        a = np.asarray(actual)
    except ValueError:  # ragged: element by element
        e = a = np.empty(0, dtype=object)
    if e.dtype.kind in "fciub" and a.dtype.kind in "fciub":
        why = array_differences(a, e, rtol, atol)
        assert why is None, why
        return
    if isinstance(expected, Sequence) and isinstance(actual, Sequence) and len(actual) == len(expected):
        for x, y in zip(actual, expected):
            assert_close(x, y, rtol, atol)
        return
    assert actual == expected, f"{actual!r} vs {expected!r}"
