"""The live page of a capture within reach (``--max-tilt``, issue 27), in headless chromium: the
advised tilted pose is drawn with the block under its raised side, and "Can't do this one" asks
for another pose, which the session advises in its place."""
from __future__ import annotations

import http.client
import json

from test_capture_page_browser import browser, shoot, wait_for  # noqa: F401  (the browser fixture)

from mavcal.capture import CaptureConfig, CaptureSession
from mavcal.capture.pagestate import PageFeed
from mavcal.capture.web import CapturePage
from mavcal.testing.vehicle import TestVehicle


def _post(page: CapturePage, path: str, body: dict) -> int:
    conn = http.client.HTTPConnection("127.0.0.1", page.port, timeout=10)
    data = json.dumps(body).encode()
    conn.request("POST", f"{path}?t={page.token}", body=data,
                 headers={"Host": f"127.0.0.1:{page.port}", "Origin": f"http://127.0.0.1:{page.port}",
                          "Content-Type": "application/json", "Content-Length": str(len(data))})
    code = conn.getresponse().status
    conn.close()
    return code


def test_skip_without_capturing_is_refused_and_taken_once_while_capturing():
    with CapturePage() as page:
        assert _post(page, "/skip", {"csrf": page.csrf}) == 409 and not page.take_skip()
        page.state.set(phase="capturing")
        assert _post(page, "/skip", {"csrf": "wrong"}) == 403
        assert _post(page, "/skip", {"csrf": page.csrf}) == 200
        assert page.take_skip() and not page.take_skip()


def test_block_drawn_and_cant_do_this_one_gets_another_pose(browser):  # noqa: F811
    config = CaptureConfig(max_tilt_deg=15.0)
    sess = CaptureSession(TestVehicle(seed=1).params, config)
    with CapturePage() as page:
        feed = PageFeed(page.state.set, config)
        feed.session = sess
        st = sess.update()
        feed.status(st)  # the first advice: level, no block
        browser.get(page.url)
        wait_for("the advised pose drawn", lambda: "level" in browser.find_element("id", "pose-words").text
                 and browser.execute_script("return document.querySelectorAll('#scene-target polygon').length > 3"),
                 60, show=lambda: browser.get_log("browser"))
        assert not browser.execute_script("return document.querySelector('#scene-target g[data-block]')")
        first = sess.status.next_pose
        browser.find_element("id", "skip").click()  # "can't do this one"
        wait_for("the skip handed over", page.take_skip, 10)
        feed.status(sess.status, skip=True)  # the capture's thread: the session advises another pose
        now = sess.poses_advised[-1]
        assert (now.roll_deg, now.pitch_deg, now.yaw_deg) != (first.roll_deg, first.pitch_deg, first.yaw_deg)
        assert page.state.get("status")["next"]["words"] == now.words and "nose up 15 deg" in now.words
        wait_for("the block under the raised side", lambda: browser.execute_script(
            "return document.querySelector('#scene-target g[data-block]') !== null"), 20)
        assert "nose up 15 deg" in browser.find_element("id", "pose-words").text
        assert browser.find_element("id", "skip").is_displayed()
        shoot(browser, "capture_within_reach")
