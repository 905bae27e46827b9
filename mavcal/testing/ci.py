"""Under ``CI=true`` a test that needs the shared real logs, the PX4 logs or a browser must run: its skip
is turned into a failure (issue 35; the SITL tests do the same through
:func:`mavcal.testing.netns.require`). ``tests/conftest.py`` installs :func:`pytest_runtest_makereport`.

A skip counts as such when its reason says what is missing in the words the suite uses
(:data:`MUST_RUN`): "real logs", "PX4 logs", "... not available" (a shared log), "shared/",
"chromium", "browser", "selenium", "not installed".
"""
from __future__ import annotations

import os
import re

import pytest

__all__ = ["MUST_RUN", "in_ci", "must_not_skip", "pytest_runtest_makereport"]

MUST_RUN = re.compile(r"real logs|PX4 logs|not available|shared/|chromium|browser|selenium|not installed", re.I)


def in_ci() -> bool:
    """``CI=true`` (the value CI services set)."""
    return os.environ.get("CI", "").strip().lower() == "true"


def must_not_skip(reason: str) -> bool:
    """Whether a skip with ``reason`` is a failure under ``CI=true``."""
    return bool(MUST_RUN.search(reason))


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """A skip whose reason is a missing real log or browser becomes a failure under ``CI=true``."""
    outcome = yield
    rep = outcome.get_result()
    if not (rep.skipped and in_ci()) or hasattr(rep, "wasxfail"):
        return
    reason = rep.longrepr[2] if isinstance(rep.longrepr, tuple) and len(rep.longrepr) == 3 else str(rep.longrepr)
    if must_not_skip(reason):
        rep.outcome = "failed"
        rep.longrepr = f"CI=true: this test needs what is missing here and must run, not skip: {reason}"
