"""Issue 30 item 3 on the capture page, in a real browser (headless chromium): a sensor whose
95 % bound is above its limit reads "not determined", not its digits; a sensor whose bound is
under its target while the coverage rule fails it shows no tick and says what it needs.
The page is served by :class:`mavcal.capture.web.CapturePage` with a given status (no vehicle)."""
from __future__ import annotations

import os

import pytest

from mavcal.capture.pagestate import status_view
from mavcal.capture.progress import SensorProgress
from mavcal.capture.session import CaptureConfig, CaptureStatus
from mavcal.capture.web import CapturePage
from mavcal.testing import browser as chromium


def _in_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no")


def test_the_page_says_not_determined_and_what_a_sensor_needs():
    if chromium.missing():
        if _in_ci():
            pytest.fail(f"CI: {', '.join(chromium.missing())} missing")
        pytest.skip(f"{', '.join(chromium.missing())} not installed")
    needs = "field directions: only 7 distinct field directions (value 7, limit >= 8 distinct)"
    progress = (SensorProgress("accel0", "tilt", 0.06, 0.3), SensorProgress("compass0", "heading", 123.4567, 0.5),
                SensorProgress("compass1", "heading", 0.39, 0.5, needs=needs))
    st = CaptureStatus(time_s=1.0, still_now=True, n_intervals=9, gravity_dirs=((0.0, 0.0, 1.0),),
                       heading_95_deg=123.4567, tilt_95_deg=0.06, model="full", next_pose=None, done=False,
                       reason="still: keep holding", sensors=progress)
    with CapturePage() as page, chromium.headless_chromium() as drv:
        page.state.set(phase="capturing", status=status_view(st, CaptureConfig()), live=None)
        drv.get(page.url)
        rows = chromium.wait_for("the sensors' bars", lambda: [r.text for r in
                                 drv.find_elements("css selector", "#bars .bar-row")] or None, 30)
        text = "\n".join(rows)
        assert len(rows) == 3, rows
        assert "heading not determined (95 % bound above 90°)" in rows[1] and "123" not in text
        assert rows[0].startswith("✓ Accelerometer 0") and "tilt 0.06°" in rows[0]
        assert not rows[2].startswith("✓") and "heading 0.39°" in rows[2]
        assert "more poses needed: field directions: only 7 distinct field directions" in rows[2]
