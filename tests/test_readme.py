"""README.md stays what it is for: short, its two commands the ones CI runs, its links alive.

What the README used to check of itself (the sample outputs, the Python examples, the Layout,
the extras, the suite's time) now lives in docs/ and is checked by tests/test_docs.py.
"""
from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text(encoding="utf-8")


def fenced_blocks(text: str, lang: str) -> list[str]:
    """The contents of the fenced code blocks of language ``lang``, in order."""
    return re.findall(rf"^```{re.escape(lang)}\n(.*?)^```$", text, flags=re.S | re.M)


def test_readme_fits_on_a_few_screens():
    assert len(README.encode("utf-8")) <= 10 * 1024


def test_setup_commands_are_the_first_two_sh_blocks():
    """CI (.ci/run) runs the second ``sh`` block verbatim: a fresh venv, the test extra, pytest."""
    sh = fenced_blocks(README, "sh")
    assert len(sh) >= 2
    main, tests = (b.strip() for b in sh[:2])
    assert "\n" not in main and "\n" not in tests
    assert main.startswith("python3 -m venv .venv") and "mavcal calibrate sitl_logs/" in main
    assert tests.startswith("python3 -m venv .venv") and 'pip install -e ".[test]"' in tests
    assert "python -m pytest" in tests


def _extra(name: str) -> list[str]:
    if sys.version_info < (3, 11):
        pytest.skip("tomllib needs Python 3.11")
    import tomllib

    with open(REPO / "pyproject.toml", "rb") as fh:
        return tomllib.load(fh)["project"]["optional-dependencies"][name]


def test_mavproxy_no_deps_pin_matches_the_mavproxy_extra():
    """The test command installs MAVProxy without its GUI requirements, at the extra's version."""
    (spec,) = _extra("mavproxy")
    assert f'pip install --no-deps "{spec}"' in fenced_blocks(README, "sh")[1]
    assert not any(d.lower().startswith("mavproxy") for d in _extra("test"))


def test_readme_links_and_image_exist():
    """Every relative link of the README (the docs, the benchmark pages, the screenshot) names a
    file of the repository: GitHub renders them, and mkdocs does not check this file."""
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", README)
    local = [t for t in targets if "://" not in t]
    assert any(t.startswith("docs/img/") for t in local) and any(t.startswith("benchmarks/results/") for t in local)
    missing = [t for t in local if not (REPO / t).exists()]
    assert not missing, missing
