"""Under CI=true a skipped real-log or browser test is a failure (issue 35, item 10): the hook of
:mod:`mavcal.testing.ci`, run in a child pytest on tests that skip for each reason."""
from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest

from mavcal.testing.ci import must_not_skip

TESTS = '''
import pytest

def test_real():
    pytest.skip("real logs not found at /x/shared/data/real (shared/ must sit beside the repo)")

@pytest.mark.skipif(True, reason="real logs not available")
def test_marked():
    pass

def test_browser():
    pytest.skip("chromium not installed (apt-get install chromium)")

def test_other():
    pytest.skip("tomllib needs Python 3.11")
'''


@pytest.mark.parametrize("ci, failed, skipped", [("true", 3, 1), ("", 0, 4)])
def test_real_log_and_browser_skips_fail_under_ci(tmp_path, ci, failed, skipped):
    (tmp_path / "conftest.py").write_text("from mavcal.testing.ci import pytest_runtest_makereport  # noqa: F401\n")
    (tmp_path / "test_skips.py").write_text(TESTS)
    env = {**os.environ, "CI": ci}
    p = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:xdist", "-p", "no:cacheprovider",
                        str(tmp_path)], capture_output=True, text=True, env=env, cwd=tmp_path, timeout=120)
    tail = p.stdout.strip().splitlines()[-1]
    counts = {word: int(n) for n, word in re.findall(r"(\d+) (failed|error|skipped|passed)", tail)}
    # a skipif mark skips in the set-up phase: turned into a failure there, pytest counts an error
    assert counts.get("failed", 0) + counts.get("error", 0) == failed, p.stdout
    assert counts.get("skipped", 0) == skipped, p.stdout


@pytest.mark.parametrize("reason, must", [
    ("PX4 logs not found at ../shared/data/px4 (shared/ must sit beside the repo)", True),
    ("/x/2024-04-05 09-36-27.tlog not available", True),
    ("chromium, chromium-driver not installed", True),
    ("needs fork", False),
    ("glibc's malloc_trim", False),
])
def test_which_skips_must_run(reason, must):
    assert must_not_skip(reason) == must
