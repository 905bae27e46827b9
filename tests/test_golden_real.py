"""Issue 24 item 1: what a person reads is what will be written.

The summary (CLI and MAVProxy console alike: :func:`mavcal.report.text.summary_text`), the
HTML table and the ``.param`` hold exactly the same parameters; a rejected sensor's rows say
"not written (rejected: ...)" without its values, which stay in the JSON, marked. Golden
summaries of the two real logs named in the issue pin it; numbers are compared parsed, at a
tolerance (1e-3 relative, or a decimal's last printed digit), never bit for bit:

    MAVCAL_UPDATE_GOLDEN=1 python -m pytest tests/test_golden_real.py
"""
from __future__ import annotations

import json
import os
import re
from pathlib import Path

import pytest

from mavcal.autopilot.paramfile import read_param_file
from mavcal.cli import main
from mavcal.testing.numbers import text_differences

pytestmark = pytest.mark.cpu_sensitive  # .ci/avx2 runs these as an AVX2-only CPU would (issue 30)

GOLDEN = Path(__file__).resolve().parent / "golden"
REPO = Path(__file__).resolve().parents[1]
LOGS = {"2023-05-17 12-18-48.tlog": 7, "2024-04-05 09-36-27.tlog": 4}


def same_at_tolerance(out: str, golden: str, rel: float = 1e-3) -> str:
    """"" when ``out`` is ``golden`` under the project's golden rule
    (:func:`mavcal.testing.numbers.text_differences`: the text exactly, integers exactly, every
    decimal within ``rel`` or its last printed digit); else the differences, in words. These
    logs' fits are disturbed or do not converge, so their bounds move more with the BLAS kernel
    than a clean fit's: 1e-3 here, still far below anything a reader would act on."""
    return "\n".join(text_differences(out, golden, rtol=rel)[:5])


def _golden_name(log: str) -> Path:
    return GOLDEN / f"calibrate_real_{log.replace(' ', '_').removesuffix('.tlog')}.txt"


#: the golden files of this module and the command that makes each (``new.param`` and
#: ``run.json`` become the test's own files; the docs' samples of them start with this command:
#: tests/test_docs.py checks it)
GOLDEN_COMMANDS = {_golden_name(log).name: ["calibrate", f"../shared/data/real/{log}", "--param-out", "new.param",
                                            "--json", "run.json"] for log in LOGS}


def _table_names(summary: str) -> tuple[set[str], set[str], str]:
    """(names with values, names marked not written, the closing count line) of a summary's table."""
    lines = summary.splitlines()
    start = next(k for k, x in enumerate(lines) if x.strip().startswith("PARAMETER"))
    shown, left, count = set(), set(), ""
    for x in lines[start + 1:]:
        if not x.startswith("  "):
            break
        name = x.split()[0]
        if name.startswith("("):
            count = x.strip()
            continue
        names = {name[:-3] + c for c in "XYZ"} if name.endswith("_XYZ") else {name}
        (left if "not written (rejected: " in x else shown).update(names)
        if "not written" in x:
            assert x.split("not written", 1)[0].split() == [name] and "->" not in x, x  # no meaningless numbers
    return shown, left, count


@pytest.mark.parametrize("log", sorted(LOGS))
def test_real_log_summary_shows_exactly_what_is_written(log, real_dir, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(REPO)  # the summary names the log as given
    pf, js = tmp_path / "new.param", tmp_path / "run.json"
    files = {"new.param": str(pf), "run.json": str(js)}
    code = main([files.get(a, a) for a in GOLDEN_COMMANDS[_golden_name(log).name]])
    out = capsys.readouterr().out
    assert code == LOGS[log]
    summary = out.split("\nJSON report written to ")[0] + "\n"  # the lines after it name tmp files
    golden = _golden_name(log)
    if os.environ.get("MAVCAL_UPDATE_GOLDEN"):
        golden.write_text(summary)
    diff = same_at_tolerance(summary, golden.read_text())
    assert not diff, f"summary changed ({diff}); diff it against {golden} (MAVCAL_UPDATE_GOLDEN=1 rewrites)"

    written = set(read_param_file(pf)) if pf.exists() else set()
    shown, left, count = _table_names(summary)
    assert shown == written, (shown ^ written)
    assert count.startswith(f"({len(written)} parameter") and "will be written" in count
    doc = json.loads(js.read_text())
    rejected = {s["sensor"] for s in doc["sensors"] if not s["accepted"]}
    for name, p in doc["parameters"].items():  # every value stays in the JSON, the rejected ones marked
        assert p["written"] == (name in written)
        assert (p["rejected"] is not None) == (name in left)
        if p["rejected"] is not None:
            assert p["rejected"].split(":")[0] in rejected and p["new"] is not None
    assert "COMPASS_OFS_X" in left  # the compass values the issue saw offered as changes


def test_mavproxy_console_and_html_show_what_will_be_written(real_dir, tmp_path):
    """The console prints summary_text with the module's hints; the HTML table the same rows."""
    from mavcal.pipeline import Options, calibrate_source
    from mavcal.report.html import html_page
    from mavcal.report.text import MAVPROXY_HINTS, summary_text

    run = calibrate_source(str(real_dir / "2023-05-17 12-18-48.tlog"), Options())
    written = set(run.params_to_write())
    shown, left, count = _table_names(summary_text(run, hints=MAVPROXY_HINTS))
    assert shown == written == {f"INS_ACC{k}_{c}" for k in ("OFFS", "SCAL") for c in "XYZ"}
    assert left and not left & written and "6 parameters will be written" in count
    page = html_page(run, None, {}, 0)
    rows = re.findall(r"<tr[^>]*><td[^>]*>([A-Z0-9_]+)</td><td[^>]*>[^<]*</td><td[^>]*>([^<]*)</td>", page)
    assert {n for n, v in rows if "not written" not in v} == written
    assert {n for n, v in rows if "not written (rejected: compass" in v} == left
    assert "6 parameters will be written" in page
    forced = set(_table_names(summary_text(run, force=True))[0])
    assert forced == set(run.params_to_write(True))  # --force: the rejected ones shown, marked
    assert "REJECTED (compass0: field directions), written anyway" in summary_text(run, force=True)


def test_tolerance_comparison_catches_what_matters():
    g = "heading error <= 172.830 deg, chi2 379\n  INS_ACCOFFS_XYZ   (0.1, 2) -> (0.070614256, 3)  *\n"
    assert same_at_tolerance(g, g) == ""
    assert same_at_tolerance(g.replace("172.830", "172.831"), g) == ""  # the last printed digit
    assert same_at_tolerance(g.replace("0.070614256", "0.0706142561"), g) == ""  # far below the noise
    assert "numbers differ" in same_at_tolerance(g.replace("172.830", "174.0"), g)
    assert "numbers differ" in same_at_tolerance(g.replace("379", "380"), g)
    assert "text differs" in same_at_tolerance(g.replace("*", ""), g)
