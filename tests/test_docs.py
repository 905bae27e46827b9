"""The documentation (docs/*.md) stays true: every output it shows is the program's, its Python
examples run, and what it lists matches the tree.

* Each sample output (a ``text`` block, which must follow a ``<!-- golden: F -->`` marker) is
  lines of the golden file F, in order ("..." for the lines left out), numbers compared at the
  golden rule's tolerance (:mod:`mavcal.testing.numbers`); the golden files are compared with the
  program's output by tests/test_cli_golden.py and tests/test_golden_real.py. A sample's first
  line ``$ mavcal ...`` is its command, and must be the one that makes F there (their
  ``GOLDEN_COMMANDS``).
* Each ``python`` block of docs/api.md runs as it is written, from a scratch directory that holds
  the bundled ``sitl_logs/`` (so relative paths work and what it writes stays out of the
  repository).

The site itself (links, anchors, pages, the API reference) is checked by ``mkdocs build
--strict`` in .ci/run.
"""
from __future__ import annotations

import re
import shlex
import sys
from pathlib import Path

import pytest
import test_cli_golden
import test_golden_real

from mavcal.autopilot.paramfile import read_param_file
from mavcal.testing.numbers import GOLDEN_RTOL, text_differences

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
PAGES = {p.name: p.read_text(encoding="utf-8") for p in sorted(DOCS.glob("*.md"))}
GOLDEN_COMMANDS = {**test_cli_golden.GOLDEN_COMMANDS, **test_golden_real.GOLDEN_COMMANDS}
# the real logs' fits are disturbed or do not converge, so their golden test allows 1e-3
# (test_golden_real.same_at_tolerance); a sample of them is held to the same
REAL_RTOL = 1e-3


def fenced_blocks(text: str, lang: str) -> list[str]:
    """The contents of the fenced code blocks of language ``lang``, in order."""
    return re.findall(rf"^```{re.escape(lang)}\n(.*?)^```$", text, flags=re.S | re.M)


def samples() -> list[tuple[str, str, str]]:
    """(page, golden file, sample text) of every marked sample."""
    return [(page, path, body) for page, text in PAGES.items()
            for path, body in re.findall(r"^<!-- golden: (\S+) -->\n```text\n(.*?)^```$", text, flags=re.S | re.M)]


def test_the_pages_show_samples():
    assert len(samples()) >= 5
    assert {"quickstart.md", "results.md", "fleet.md"} <= {page for page, _, _ in samples()}


def test_every_output_shown_is_a_marked_sample():
    """An output block without its golden file would drift unnoticed."""
    for page, text in PAGES.items():
        n_text = len(fenced_blocks(text, "text"))
        n_marked = sum(1 for p, _, _ in samples() if p == page)
        assert n_text == n_marked, f"docs/{page}: a ```text block without a <!-- golden: F --> marker"


@pytest.mark.parametrize("page,path,body", samples(), ids=lambda x: x if isinstance(x, str) and "\n" not in x
                         else None)
def test_sample_is_the_golden_output(page, path, body):
    golden = (REPO / path).read_text().splitlines()
    rtol = REAL_RTOL if Path(path).name.startswith("calibrate_real_") else GOLDEN_RTOL
    lines = body.splitlines()
    if lines and lines[0].startswith("$ "):
        argv = shlex.split(lines.pop(0)[2:])
        assert Path(path).name in GOLDEN_COMMANDS, f"docs/{page}: no test makes {path}"
        assert argv == ["mavcal", *GOLDEN_COMMANDS[Path(path).name]], \
            f"docs/{page}: the command shown is not the one that makes {path}"
    k = 0
    for line in lines:
        if line == "...":
            continue
        while k < len(golden) and text_differences(line, golden[k], rtol=rtol):
            k += 1
        assert k < len(golden), f"docs/{page}: sample line not in {path} (in order): {line}"
        k += 1


def test_sample_check_catches_a_drift():
    """The comparison above fails on a changed number or word, not on the last printed digit."""
    g = "heading error <= 0.224 deg, tilt error <= 0.018 deg"
    assert not text_differences(g.replace("0.224", "0.2241"), g)
    assert text_differences(g.replace("0.224", "0.230"), g)
    assert text_differences(g.replace("heading", "yaw"), g)


PYTHON_BLOCKS = fenced_blocks(PAGES["api.md"], "python")


def run_block(code: str, where: Path, monkeypatch) -> dict:
    """Run one block of docs/api.md as a script in ``where``; returns its globals."""
    (where / "sitl_logs").symlink_to(REPO / "sitl_logs", target_is_directory=True)
    monkeypatch.chdir(where)
    namespace: dict = {"__name__": "__docs__"}
    exec(compile(code, "docs/api.md", "exec"), namespace)  # noqa: S102 - the documentation's own example
    return namespace


def test_api_page_has_the_examples():
    assert len(PYTHON_BLOCKS) >= 2
    assert 'calibrate_source("sitl_logs/sitl02.tlog"' in PYTHON_BLOCKS[0]


def test_log_example_runs_and_writes_the_param_file(tmp_path, monkeypatch, capsys):
    ns = run_block(PYTHON_BLOCKS[0], tmp_path, monkeypatch)
    run = ns["run"]
    assert run.accepted and run.verdict == "accepted"
    # keyed by parameter name, one entry per axis, and the .param file holds exactly what is to be written
    # (tests/test_api_safe_path.py compares it with the CLI's --param-out)
    new = run.params_to_write()
    assert new and all(isinstance(k, str) and k == k.upper() for k in new)
    written = read_param_file(tmp_path / "sitl02.param")
    assert set(written) == set(new)
    assert all(abs(written[k] - v) <= 1e-6 * max(1.0, abs(v)) for k, v in new.items())
    assert ns["report"]["accepted"] is True
    out = capsys.readouterr().out
    assert "heading <=" in out and "was" in out


def test_array_example_runs(tmp_path, monkeypatch):
    ns = run_block(PYTHON_BLOCKS[1], tmp_path, monkeypatch)
    assert ns["delta_a"] < 0.1 and ns["delta_m"] < 0.1
    assert ns["R"].shape == (5, 3, 3)
    assert len(ns["multi"].mags) == 2


def _extras() -> dict[str, list[str]]:
    if sys.version_info < (3, 11):
        pytest.skip("tomllib needs Python 3.11")
    import tomllib

    with open(REPO / "pyproject.toml", "rb") as fh:
        return tomllib.load(fh)["project"]["optional-dependencies"]


def test_extras_named_on_the_install_page_exist():
    named = set(re.findall(r'"\.\[(\w+)\]"', PAGES["install.md"]))
    assert {"plots", "mavproxy", "test", "docs"} <= named
    extras = _extras()
    assert all(extras.get(name) for name in named), named - set(extras)


def test_docs_extra_builds_this_site():
    assert {"mkdocs", "mkdocs-material", "mkdocstrings"} <= {re.split(r"[\[<>=!~ ]", d)[0].lower()
                                                            for d in _extras()["docs"]}


def test_layout_names_every_package_and_module():
    dev = PAGES["development.md"]
    layout = dev[dev.index("## Layout"):]
    pkg = REPO / "mavcal"
    names = [p.name for p in pkg.iterdir() if p.is_dir() and (p / "__init__.py").exists()]
    names += [p.name for p in pkg.glob("*.py") if p.name not in ("__init__.py", "__main__.py")]
    missing = [n for n in sorted(names) if f"mavcal/{n}" not in layout]
    assert not missing, f"docs/development.md Layout does not mention {missing}"


def test_suite_time_is_a_measured_one():
    """The suite's time is stated as measured, with how and when (issue 24)."""
    dev = PAGES["development.md"]
    m = re.search(r"the suite \(([^)]*)\)", dev)
    assert m and "measured" in m.group(1) and "time " in m.group(1), m and m.group(1)


def test_screenshot_script_is_the_documented_one():
    """The page's screenshots are made by the script the development page documents."""
    dev = PAGES["development.md"]
    assert "python benchmarks/capture_page_shots.py --save" in dev
    assert (REPO / "benchmarks" / "capture_page_shots.py").is_file()
    script = (REPO / "benchmarks" / "capture_page_shots.py").read_text()
    shown = set(re.findall(r"\]\(img/([\w-]+)\.png\)", "".join(PAGES.values())))
    assert {"capture-start", "capture-mid", "capture-verdict", "capture-written"} <= shown
    for name in shown:  # px4-*: the same moments against PX4 SITL (--px4)
        base = name.removeprefix("px4-")
        assert f'"{base}"' in script and (DOCS / "img" / f"{name}.png").is_file(), name
        assert base == name or ('"px4-"' in script and "--px4" in dev), name
