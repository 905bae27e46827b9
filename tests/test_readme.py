"""README.md stays true: its Python examples run, its set-up commands and Layout match the tree.

Each fenced ``python`` block of README.md is run as it is written, from a scratch directory
that holds the bundled ``sitl_logs/`` (so relative paths work and what it writes stays out of
the repository).
"""
from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

from mavcal.ardupilot.paramfile import read_param_file

REPO = Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text(encoding="utf-8")


def fenced_blocks(text: str, lang: str) -> list[str]:
    """The contents of the fenced code blocks of language ``lang``, in order."""
    return re.findall(rf"^```{re.escape(lang)}\n(.*?)^```$", text, flags=re.S | re.M)


PYTHON_BLOCKS = fenced_blocks(README, "python")


def run_block(code: str, where: Path, monkeypatch) -> dict:
    """Run one README block as a script in ``where``; returns its globals."""
    (where / "sitl_logs").symlink_to(REPO / "sitl_logs", target_is_directory=True)
    monkeypatch.chdir(where)
    namespace: dict = {"__name__": "__readme__"}
    exec(compile(code, "README.md", "exec"), namespace)  # noqa: S102 - the README's own example
    return namespace


def test_readme_has_the_examples():
    assert len(PYTHON_BLOCKS) >= 2
    assert 'calibrate_source("sitl_logs/sitl02.tlog"' in PYTHON_BLOCKS[0]


def test_log_example_runs_and_writes_the_param_file(tmp_path, monkeypatch, capsys):
    ns = run_block(PYTHON_BLOCKS[0], tmp_path, monkeypatch)
    run = ns["run"]
    assert run.accepted
    # keyed by parameter name, one entry per axis, and the .param file holds exactly that mapping
    assert all(isinstance(k, str) and k == k.upper() for k in run.mapping.new)
    written = read_param_file(tmp_path / "sitl02.param")
    assert set(written) == set(run.mapping.new)
    assert all(abs(written[k] - v) <= 1e-6 * max(1.0, abs(v)) for k, v in run.mapping.new.items())
    assert ns["report"]["accepted"] is True
    out = capsys.readouterr().out
    assert "heading <=" in out and "was" in out


def test_array_example_runs(tmp_path, monkeypatch):
    ns = run_block(PYTHON_BLOCKS[1], tmp_path, monkeypatch)
    assert ns["delta_a"] < 0.1 and ns["delta_m"] < 0.1
    assert ns["R"].shape == (5, 3, 3)
    assert len(ns["multi"].mags) == 2


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


def test_extras_named_in_the_readme_exist():
    for name in ("plots", "mavproxy", "test"):
        assert f'".[{name}]"' in README
        assert _extra(name)


def test_mavproxy_no_deps_pin_matches_the_mavproxy_extra():
    """The test command installs MAVProxy without its GUI requirements, at the extra's version."""
    (spec,) = _extra("mavproxy")
    assert f'pip install --no-deps "{spec}"' in fenced_blocks(README, "sh")[1]
    assert not any(d.lower().startswith("mavproxy") for d in _extra("test"))


def test_layout_names_every_package_and_module():
    layout = README[README.index("## Layout"):]
    pkg = REPO / "mavcal"
    names = [p.name for p in pkg.iterdir() if p.is_dir() and (p / "__init__.py").exists()]
    names += [p.name for p in pkg.glob("*.py") if p.name not in ("__init__.py", "__main__.py")]
    missing = [n for n in sorted(names) if f"mavcal/{n}" not in layout]
    assert not missing, f"README Layout does not mention {missing}"


def test_readme_samples_are_the_golden_outputs():
    """Issue 24: each sample output in the README (a ``text`` block after a ``<!-- golden: F -->``
    marker) is lines of the golden file F, in order ("..." for the lines left out), numbers
    compared at the golden tests' tolerance; the golden files are compared with the program's
    output by tests/test_cli_golden.py and tests/test_golden_real.py."""
    from test_golden_real import same_at_tolerance

    samples = re.findall(r"^<!-- golden: (\S+) -->\n```text\n(.*?)^```$", README, flags=re.S | re.M)
    assert len(samples) >= 2
    for path, text in samples:
        golden = (REPO / path).read_text().splitlines()
        k = 0
        for line in text.splitlines():
            if line == "...":
                continue
            while k < len(golden) and same_at_tolerance(line, golden[k]):
                k += 1
            assert k < len(golden), f"README sample line not in {path} (in order): {line}"
            k += 1


def test_readme_timings_are_measured_ones():
    """The suite's time is stated as measured, with how and when (issue 24)."""
    dev = README[README.index("## Development"):]
    m = re.search(r"the suite \(([^)]*)\)", dev)
    assert m and "measured" in m.group(1) and "time " in m.group(1), m and m.group(1)
