"""Issue 35 item 5: the API's easy path is the safe path.

docs/api.md's example runs as written and writes the very .param file ``mavcal calibrate
--param-out`` writes, on an accepted log and on a partly accepted one (the example's log path
swapped for it); a partly accepted run is told from a fully accepted one by name.
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest

from mavcal.autopilot.paramfile import read_param_file
from mavcal.cli import main
from mavcal.testing.numbers import assert_close
from mavcal.testing.strip import strip_tlog_params

REPO = Path(__file__).resolve().parents[1]
BLOCKS = re.findall(r"```python\n(.*?)```", (REPO / "docs" / "api.md").read_text(), re.S)
LOG = "sitl_logs/sitl02.tlog"


def _run_example(code: str, where: Path, monkeypatch) -> dict:
    monkeypatch.chdir(where)
    namespace: dict = {"__name__": "__docs__"}
    exec(compile(code, "docs/api.md", "exec"), namespace)  # noqa: S102 - the documentation's own example
    return namespace


def _same_param_files(api: Path, cli: Path) -> None:
    a, c = api.read_text().splitlines(), cli.read_text().splitlines()
    assert [x for x in a if x.startswith("#")] == [x for x in c if x.startswith("#")]  # same header
    pa, pc = read_param_file(api), read_param_file(cli)
    assert sorted(pa) == sorted(pc) and pa
    assert_close([pa[n] for n in sorted(pc)], [pc[n] for n in sorted(pc)], rtol=1e-7)


@pytest.fixture
def scratch(tmp_path):
    (tmp_path / "sitl_logs").symlink_to(REPO / "sitl_logs", target_is_directory=True)
    return tmp_path


def test_the_example_never_shows_mapping_new_as_what_to_write():
    text = (REPO / "docs" / "api.md").read_text()
    assert 'calibrate_source("sitl_logs/sitl02.tlog"' in BLOCKS[0] and "run.write_param_file(" in BLOCKS[0]
    assert "write_param_file(\"sitl02.param\", new)" not in text
    assert not re.search(r"mapping\.new[^\n]*what `?--param-out`? writes", text)


def test_accepted_log_writes_what_the_cli_writes(scratch, monkeypatch, capsys):
    ns = _run_example(BLOCKS[0], scratch, monkeypatch)
    run = ns["run"]
    assert run.verdict == "accepted" and run.accepted and not run.partly_accepted
    assert main(["calibrate", LOG, "--param-out", "cli.param"]) == 0
    _same_param_files(scratch / "sitl02.param", scratch / "cli.param")


def test_partly_accepted_log_writes_what_the_cli_writes(scratch, monkeypatch, capsys):
    """A log whose compass 1 lacks its offsets' parameters: partly accepted; the example writes the
    accepted sensors (where ``if run.accepted`` would have written nothing), as the CLI does (exit 7)."""
    strip_tlog_params(REPO / LOG, scratch / "partial.tlog", ("COMPASS_OFS2_",))
    code = BLOCKS[0].replace(LOG, "partial.tlog")
    assert code != BLOCKS[0]
    ns = _run_example(code, scratch, monkeypatch)
    run = ns["run"]
    assert run.verdict == "partly accepted" and run.partly_accepted and not run.accepted and run.exit_code == 7
    assert main(["calibrate", "partial.tlog", "--param-out", "cli.param"]) == 7
    _same_param_files(scratch / "sitl02.param", scratch / "cli.param")
    written = read_param_file(scratch / "sitl02.param")
    assert not any(n.startswith("COMPASS_OFS2") for n in written)  # the rejected compass is left out ...
    assert "COMPASS_OFS2_X" in run.mapping.new                      # ... though the fit has its values


def test_rejected_run_writes_nothing(scratch, monkeypatch, capsys):
    strip_tlog_params(REPO / LOG, scratch / "bare.tlog")
    ns = _run_example(BLOCKS[0].replace(LOG, "bare.tlog"), scratch, monkeypatch)
    assert ns["run"].verdict == "rejected" and ns["run"].params_to_write(force=True) == {}
    assert not (scratch / "sitl02.param").exists()
