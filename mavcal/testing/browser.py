"""Headless chromium driven by selenium (Debian's ``chromium`` and ``chromium-driver``), for the
capture page's browser test (``tests/test_capture_page_browser.py``) and the documentation's
screenshots (``benchmarks/capture_page_shots.py``).

:func:`missing` names what is not installed; :func:`headless_chromium` starts the browser in a
fresh profile and quits it at the end. The driver (and the browser it starts) inherits the
network namespace of the thread that starts it: inside ``with sitl.netns():`` it reaches a page
served in a SITL vehicle's namespace (:mod:`mavcal.testing.sitl`).
"""
from __future__ import annotations

import contextlib
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

__all__ = ["CHROMIUM_FLAGS", "missing", "headless_chromium", "wait_for", "page_text"]

CHROMIUM_FLAGS = ["--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--disable-dev-shm-usage", "--force-device-scale-factor=1"]


def _executables() -> tuple[str | None, str | None]:
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver") or ("/usr/bin/chromedriver" if Path("/usr/bin/chromedriver").exists()
                                              else None)
    return exe, driver


def missing() -> list[str]:
    """What is not installed of chromium, chromium-driver and selenium (empty: all there)."""
    exe, driver = _executables()
    try:
        import selenium  # noqa: F401
        have_selenium = True
    except ImportError:
        have_selenium = False
    return [name for name, ok in (("chromium", exe), ("chromium-driver", driver), ("selenium", have_selenium))
            if not ok]


@contextlib.contextmanager
def headless_chromium(width: int = 1366, height: int = 900) -> Iterator[Any]:
    """A selenium ``webdriver.Chrome`` on headless chromium with a window of ``width`` x
    ``height`` CSS pixels (device scale 1), in a temporary profile removed at the end."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    exe, driver_exe = _executables()
    if exe is None or driver_exe is None:
        raise RuntimeError(f"{', '.join(missing())} not installed")
    profile = tempfile.mkdtemp(prefix="mavcal-chromium-")
    opts = webdriver.ChromeOptions()
    opts.binary_location = exe
    for flag in CHROMIUM_FLAGS + [f"--window-size={width},{height}", f"--user-data-dir={profile}"]:
        opts.add_argument(flag)
    drv = webdriver.Chrome(service=Service(driver_exe), options=opts)
    try:
        drv.set_page_load_timeout(30)
        drv.set_script_timeout(30)
        yield drv
    finally:
        drv.quit()
        shutil.rmtree(profile, ignore_errors=True)


def wait_for(what: str, cond: Callable[[], Any], timeout_s: float, poll_s: float = 0.1,
             show: Callable[[], Any] | None = None) -> Any:
    """``cond()`` once true; raises AssertionError after ``timeout_s`` saying what ``show()``
    returns (e.g. the page's state). Timeouts are generous: a loaded 2-core machine."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        got = cond()
        if got:
            return got
        time.sleep(poll_s)
    seen = f"; seen: {show()}" if show is not None else ""
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}{seen}")


def page_text(drv: Any, element_id: str) -> str:
    """The text of the page's element ``element_id``."""
    return drv.execute_script(f"return document.getElementById('{element_id}').textContent")
