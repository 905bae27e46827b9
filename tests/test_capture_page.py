"""The live capture page's server (mavcal.capture.web) at the HTTP level: the token, the Host
and Origin checks, the CSRF token, the decision hand-off and a clean shutdown. The page in a
real browser, driving a whole capture: tests/test_capture_page_browser.py."""
from __future__ import annotations

import http.client
import json
import threading
import time

import numpy as np
import pytest

from mavcal.capture import CaptureConfig, CaptureSession
from mavcal.capture.pagestate import LiveAttitude, PageFeed, attitude_matrix, status_view
from mavcal.capture.session import euler_matrix
from mavcal.capture.web import THREAD_NAME, CapturePage
from mavcal.sources.types import SensorSeries
from mavcal.testing.vehicle import TestVehicle


@pytest.fixture
def page():
    p = CapturePage().start()
    yield p
    p.close()


def request(page: CapturePage, method: str, path: str, *, host: str | None = None, headers=None, body=None,
            token: str | None = "ok"):
    """(status, headers, body) of one request; ``token`` "ok" adds the page's token."""
    conn = http.client.HTTPConnection("127.0.0.1", page.port, timeout=10)
    sep = "&" if "?" in path else "?"
    if token == "ok":
        path = f"{path}{sep}t={page.token}"
    elif token is not None:
        path = f"{path}{sep}t={token}"
    h = {"Host": f"127.0.0.1:{page.port}" if host is None else host}
    h.update(headers or {})
    conn.putrequest(method, path, skip_host=True, skip_accept_encoding=True)
    for k, v in h.items():
        conn.putheader(k, v)
    data = json.dumps(body).encode() if isinstance(body, dict) else (body or b"")
    if data:
        conn.putheader("Content-Length", str(len(data)))
    conn.endheaders(data or None)
    r = conn.getresponse()
    out = r.status, dict(r.getheaders()), r.read()
    conn.close()
    return out


def origin(page: CapturePage) -> dict[str, str]:
    return {"Origin": f"http://127.0.0.1:{page.port}", "Content-Type": "application/json"}


def test_binds_loopback_on_a_free_port_and_serves_the_page_with_the_token(page):
    assert page.host == "127.0.0.1" and page._server.server_address[0] == "127.0.0.1"
    assert page.url == f"http://127.0.0.1:{page.port}/?t={page.token}" and len(page.token) >= 32
    code, headers, body = request(page, "GET", "/")
    assert code == 200 and b"HOLD IT LIKE THIS" in body
    # the script and style links carry the token; nothing is loaded from elsewhere
    assert f'page.js?t={page.token}'.encode() in body and f'page.css?t={page.token}'.encode() in body
    assert b"http" not in body.replace(b"http://www.w3.org", b"")
    assert "script-src 'self'" in headers["Content-Security-Policy"]
    assert not any(k.lower().startswith("access-control") for k in headers)
    for asset in ("/page.js", "/page.css"):
        code, _, text = request(page, "GET", asset)
        assert code == 200 and b"http://" not in text.replace(b"http://www.w3.org", b"")
    code, _, state = request(page, "GET", "/state")
    assert code == 200 and json.loads(state)["csrf"] == page.csrf


@pytest.mark.parametrize("token", [None, "", "wrong", "x" * 32])
def test_every_request_without_the_right_token_is_refused(page, token):
    for method, path in (("GET", "/"), ("GET", "/page.js"), ("GET", "/events"), ("GET", "/state"),
                         ("POST", "/write")):
        code, _, body = request(page, method, path, token=token, headers=origin(page),
                                body={"csrf": page.csrf, "confirmed": True} if method == "POST" else None)
        assert code == 403, (method, path, body)
    page.offer(3)
    assert page.wait_decision(0.05) is None


@pytest.mark.parametrize("host", ["evil.example:80", "127.0.0.1", "127.0.0.1:1", "localhost.evil.example", ""])
def test_a_wrong_host_header_is_refused(page, host):
    code, _, body = request(page, "GET", "/", host=host)
    assert code == 403 and b"Host" in body


def test_localhost_host_is_accepted(page):
    assert request(page, "GET", "/", host=f"localhost:{page.port}")[0] == 200


def test_a_cross_origin_post_does_not_write(page):
    page.offer(3)
    good = {"csrf": page.csrf, "confirmed": True}
    attempts = [
        ({"Content-Type": "application/json"}, good),  # no Origin
        ({"Origin": "http://evil.example", "Content-Type": "application/json"}, good),
        ({"Origin": f"http://127.0.0.1:{page.port + 1}", "Content-Type": "application/json"}, good),
        ({"Origin": "null", "Content-Type": "application/json"}, good),
        ({**origin(page), "Sec-Fetch-Site": "cross-site"}, good),
        ({**origin(page), "Content-Type": "text/plain"}, good),  # what a cross-site form or no-cors fetch sends
        ({**origin(page), "Content-Type": "application/x-www-form-urlencoded"}, b"csrf=x&confirmed=true"),
        (origin(page), {"confirmed": True}),  # no CSRF token
        (origin(page), {"csrf": "wrong", "confirmed": True}),
        (origin(page), {"csrf": page.csrf}),  # not confirmed
    ]
    for headers, body in attempts:
        code, resp_headers, text = request(page, "POST", "/write", headers=headers, body=body)
        assert code in (400, 403), (headers, body, code, text)
        assert not any(k.lower().startswith("access-control") for k in resp_headers)
    code, headers, _ = request(page, "OPTIONS", "/write", headers={"Origin": "http://evil.example",
                                                                   "Access-Control-Request-Method": "POST"})
    assert code == 403 and not any(k.lower().startswith("access-control") for k in headers)
    assert page.wait_decision(0.05) is None  # nothing decided: nothing written
    page.offer(3)  # (a wait that timed out takes no decision any more)
    # the page itself: same origin, JSON, the CSRF token, confirmed
    code, _, text = request(page, "POST", "/write", headers=origin(page), body=good)
    assert code == 200 and json.loads(text)["ok"]
    assert page.wait_decision(1) == "write"
    # a decision is taken once
    code, _, _ = request(page, "POST", "/decline", headers=origin(page), body={"csrf": page.csrf})
    assert code == 409


def test_decline_and_nothing_to_decide(page):
    code, _, _ = request(page, "POST", "/decline", headers=origin(page), body={"csrf": page.csrf})
    assert code == 409  # no decision awaited yet
    page.offer(0)  # nothing to write: only a decline is taken
    assert request(page, "POST", "/write", headers=origin(page), body={"csrf": page.csrf, "confirmed": True})[0] == 409
    assert request(page, "POST", "/decline", headers=origin(page), body={"csrf": page.csrf})[0] == 200
    assert page.wait_decision(1) == "decline"


def test_event_stream_sends_every_change_and_ends_when_the_page_closes():
    page = CapturePage().start()
    conn = http.client.HTTPConnection("127.0.0.1", page.port, timeout=10)
    conn.request("GET", f"/events?t={page.token}", headers={"Host": f"127.0.0.1:{page.port}"})
    r = conn.getresponse()
    assert r.status == 200 and r.getheader("Content-Type").startswith("text/event-stream")
    first = r.fp.readline()
    assert first.startswith(b"data: ") and json.loads(first[6:])["phase"] == "starting"
    page.state.set(phase="capturing", status={"n": 3})
    lines = []
    while len([x for x in lines if x.startswith(b"data: ")]) < 1:
        line = r.fp.readline()
        if line.strip():
            lines.append(line)
    assert json.loads(lines[-1][6:])["status"] == {"n": 3}
    t0 = time.monotonic()
    page.close()
    assert time.monotonic() - t0 < 8
    rest = r.read()
    assert b"event: end" in rest
    conn.close()
    assert not [t for t in threading.enumerate() if t.name == THREAD_NAME]
    # closed: nothing answers any more
    with pytest.raises(OSError):
        c = http.client.HTTPConnection("127.0.0.1", page.port, timeout=2)
        c.request("GET", f"/?t={page.token}")
        c.getresponse()


def test_close_leaves_no_thread_and_refuses_a_third_stream_past_the_limit():
    before = {t.ident for t in threading.enumerate()}
    page = CapturePage().start()
    conns = []
    for _ in range(8):
        c = http.client.HTTPConnection("127.0.0.1", page.port, timeout=10)
        c.request("GET", f"/events?t={page.token}", headers={"Host": f"127.0.0.1:{page.port}"})
        r = c.getresponse()
        assert r.status == 200
        r.fp.readline()
        conns.append((c, r))
    assert request(page, "GET", "/events")[0] == 503  # no unbounded streams
    page.close(linger_s=0.1)
    for c, _ in conns:
        c.close()
    time.sleep(0.2)
    assert {t.ident for t in threading.enumerate()} <= before


def test_attitude_from_accel_and_compass_matches_the_pose():
    B = np.array([200.0, 0.0, 400.0])  # magnetic NED
    for pose in [(0, 0, 0), (30, -20, 135), (-90, 0, 90), (180, 0, 270), (0, 45, 300), (120, -30, 10)]:
        C = euler_matrix(*pose)
        f = C.T @ np.array([0.0, 0.0, -9.81])
        m = C.T @ B
        est = attitude_matrix(f, m)
        angle = np.degrees(np.arccos(np.clip((np.trace(est.T @ C) - 1) / 2, -1, 1)))
        assert angle < 1e-6, (pose, angle)
    assert attitude_matrix([0, 0, 0], None) is None
    level = attitude_matrix([0, 0, -9.8], None)  # no compass: down is right, the heading arbitrary
    assert np.allclose(level[2], [0, 0, 1])


def test_live_attitude_tracks_still_and_moving():
    live = LiveAttitude(accel_instance=0, mag_instance=0)
    assert live.view() is None
    rng = np.random.default_rng(0)
    t = np.arange(0, 3, 0.04)
    acc = np.tile([0.0, 0.0, -9.81], (len(t), 1)) + rng.normal(0, 0.01, (len(t), 3))
    gyr = rng.normal(0, 0.002, (len(t), 3))
    mag = np.tile([200.0, 0.0, 400.0], (len(t), 1))
    for k in range(0, len(t), 3):  # as received: batches of 0.12 s
        sl = slice(k, k + 3)
        live.feed([SensorSeries(name, 0, "RAW_IMU", t[sl], x[sl]) for name, x in
                   (("accel", acc), ("gyro", gyr), ("mag", mag))])
    v = live.view()
    assert v["still"] and v["still_s"] >= 1.5 and v["hold_s"] > 1.5
    assert np.allclose(np.array(v["C"]), np.eye(3), atol=1e-2)
    t2 = t + 3.04
    live.feed([SensorSeries("accel", 0, "RAW_IMU", t2, acc), SensorSeries("gyro", 0, "RAW_IMU", t2, gyr + 1.0)])
    v = live.view()
    assert not v["still"] and v["still_s"] == 0.0


def test_status_view_and_feed_from_a_session():
    session = CaptureSession(TestVehicle(seed=1).params)
    st = session.update()  # no data yet: the first pose of the plan
    view = status_view(st, CaptureConfig())
    assert view["n"] == 0 and view["next"]["words"] == "level, nose towards magnetic north"
    assert np.allclose(np.array(view["next"]["C"]), np.eye(3))
    json.dumps(view, allow_nan=False)
    got = {}
    feed = PageFeed(got.update, CaptureConfig())
    feed.status(st)
    assert got["phase"] == "capturing" and got["status"]["next"]["down"] == [0.0, 0.0, 1.0]


def test_live_heading_uses_the_fit_so_far():
    """An uncalibrated compass (hard iron of 300 mGauss) shows a heading tens of degrees off;
    with the fit's correction the live attitude is the true one."""
    from mavcal.ardupilot.firmware import CompassCal

    B = np.array([220.0, 0.0, 420.0])
    C = euler_matrix(0.0, 0.0, 60.0)
    hard_iron = np.array([300.0, -150.0, 40.0])
    sent = C.T @ B + hard_iron  # the vehicle corrects nothing (offsets 0 in force)
    t = np.arange(0, 1, 0.04)
    batch = [SensorSeries("accel", 0, "RAW_IMU", t, np.tile(C.T @ [0, 0, -9.81], (len(t), 1))),
             SensorSeries("mag", 0, "RAW_IMU", t, np.tile(sent, (len(t), 1)))]

    def off_deg(live: LiveAttitude) -> float:
        v = live.view()
        return float(np.degrees(np.arccos(np.clip((np.trace(np.array(v["C"]).T @ C) - 1) / 2, -1, 1))))

    live = LiveAttitude()
    live.feed(batch)
    assert live.view()["heading_source"] == "raw" and off_deg(live) > 20
    live.use_compass_fit(CompassCal(), CompassCal(ofs_mgauss=tuple(-hard_iron)))
    assert live.view()["heading_source"] == "fit" and np.allclose(np.array(live.view()["C"]), C, atol=1e-3)


# ---------------------------------------------------------------------------- `mavcal capture --ui`
# The capture is replaced by a finished session whose result is a bundled SITL log's calibration, so
# these tests reach the page's verdict in seconds (the whole flow against the loopback vehicle, in a
# browser: tests/test_capture_page_browser.py).

@pytest.fixture(scope="module")
def sitl_run(sitl_dir):
    from mavcal.pipeline import calibrate_source

    return calibrate_source(str(sitl_dir / "sitl01.tlog"))


@pytest.fixture
def finished_capture(monkeypatch, sitl_run):
    from mavcal.capture import CaptureStatus
    from mavcal.capture import live as live_capture

    class Finished:
        status = CaptureStatus(0.0, True, 15, (), 0.2, 0.02, "full", None, True, "target reached")

        def result(self):
            return sitl_run

    calls = []

    def fake(device, **kw):
        calls.append(kw)
        return Finished()

    monkeypatch.setattr(live_capture, "capture_live", fake)
    return calls


def _run_cli(argv):
    from mavcal import cli

    out: dict = {}
    t = threading.Thread(target=lambda: out.setdefault("rc", cli.main(argv)), name="test-cli", daemon=True)
    t.start()
    return t, out


def _url_from(capsys, seen: list[str], timeout_s: float = 60.0) -> str:
    import re

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        _, err = capsys.readouterr()
        seen.append(err)
        m = re.search(r"capture page: (http://\S+)", "".join(seen))
        if m:
            return m.group(1)
        time.sleep(0.05)
    raise AssertionError("no page address printed")


def _page_of(url: str) -> CapturePage:
    """A stand-in with the port and token of the page at ``url``, for request()."""
    from urllib.parse import urlsplit

    parts = urlsplit(url)
    p = CapturePage.__new__(CapturePage)
    p.port, p.token = parts.port, parts.query.split("=", 1)[1]
    return p


def _wait_phase(page: CapturePage, phase: str, timeout_s: float = 60.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        state = json.loads(request(page, "GET", "/state")[2])
        if state.get("phase") == phase:
            return state
        time.sleep(0.05)
    raise AssertionError(f"the page never reached {phase!r}")


def test_cli_ui_decline_writes_nothing_and_stops_the_server(finished_capture, capsys, monkeypatch, tmp_path):
    import webbrowser

    opened = []
    monkeypatch.setattr(webbrowser, "open", lambda url, *a, **k: opened.append(url) or True)
    t, out = _run_cli(["capture", "--connect", "udpin:127.0.0.1:1", "--ui", "--no-browser",
                       "--backup", str(tmp_path / "b.param")])
    seen: list[str] = []
    url = _url_from(capsys, seen)
    assert url.startswith("http://127.0.0.1:") and not opened  # --no-browser: printed, not opened
    page = _page_of(url)
    state = _wait_phase(page, "result")
    assert state["result"]["n_write"] > 0 and state["report"]  # the HTML report is linked
    code, _, html = request(page, "GET", "/report")
    assert code == 200 and html.startswith(b"<!DOCTYPE html>")
    assert finished_capture[0]["on_batch"] is not None  # the live attitude is fed
    code, _, _ = request(page, "POST", "/decline", headers=origin(page), body={"csrf": state["csrf"]})
    assert code == 200
    t.join(timeout=30)
    assert not t.is_alive() and out["rc"] == 0
    printed, _ = capsys.readouterr()
    assert "nothing written to the vehicle" in printed
    assert not (tmp_path / "b.param").exists()
    assert not [x for x in threading.enumerate() if x.name == THREAD_NAME]
    with pytest.raises(OSError):
        request(page, "GET", "/")


def test_cli_ui_ctrl_c_while_waiting_stops_the_server(finished_capture, capsys, monkeypatch):
    def interrupted(self, timeout_s=None):
        raise KeyboardInterrupt

    monkeypatch.setattr(CapturePage, "wait_decision", interrupted)
    from mavcal import cli

    rc = cli.main(["capture", "--connect", "udpin:127.0.0.1:1", "--ui", "--no-browser"])
    _, err = capsys.readouterr()
    assert rc == 130 and "capture page: http://127.0.0.1:" in err
    assert not [x for x in threading.enumerate() if x.name == THREAD_NAME]


def test_cli_ui_other_interface_only_with_the_flag_and_a_warning(finished_capture, capsys, monkeypatch):
    monkeypatch.setattr(CapturePage, "wait_decision", lambda self, timeout_s=None: "decline")
    from mavcal import cli

    rc = cli.main(["capture", "--connect", "udpin:127.0.0.1:1", "--ui", "--no-browser", "--ui-host", "127.0.0.2"])
    _, err = capsys.readouterr()
    assert rc == 0 and "WARNING: the capture page is served on 127.0.0.2" in err
    assert "capture page: http://127.0.0.2:" in err


def test_cli_ui_usage_errors(capsys):
    from mavcal import cli

    assert cli.main(["capture", "--connect", "udpin:127.0.0.1:1", "--no-browser"]) == 2
    assert cli.main(["capture", "--connect", "udpin:127.0.0.1:1", "--ui-host", "0.0.0.0"]) == 2
    assert cli.main(["capture", "--connect", "udpin:127.0.0.1:1", "--ui", "--ui-port", "70000"]) == 2
    _, err = capsys.readouterr()
    assert "go with --ui" in err


def test_finish_without_a_sensor_that_cannot_get_there(page):
    """A status naming a sensor that cannot reach its target (the stop rule's ``sensors`` and
    ``offer_finish_without``): the page shows it and its button; the POST is taken only while
    offered, and the session is told on the capture's thread (PageFeed.status)."""
    from dataclasses import dataclass, replace

    from mavcal.capture.progress import SensorProgress as Progress

    @dataclass(frozen=True)
    class Status:
        base: object
        sensors: tuple = ()
        offer_finish_without: tuple = ()
        advice_for: str | None = None

        def __getattr__(self, name):
            return getattr(self.base, name)

    class Session:
        run = None
        dropped: list = []

        def finish_without(self, names):
            self.dropped.append(tuple(names))

    base = CaptureSession(TestVehicle(seed=1).params).update()
    st = Status(base, (Progress("accel0", "tilt", 0.2, 0.3), Progress("compass1", "heading", 9.0, 0.5, "disturbed")),
                ("compass1",), "compass1")
    feed = PageFeed(page.state.set, CaptureConfig())
    feed.session = Session()
    assert request(page, "POST", "/finish", headers=origin(page), body={"csrf": page.csrf})[0] == 409  # not offered
    feed.status(st)
    view = page.state.get("status")
    assert view["finish_without"] == ["compass1"] and view["advice_for"] == "compass1"
    assert [s["sensor"] for s in view["sensors"]] == ["accel0", "compass1"]
    assert view["sensors"][0]["met"] and view["sensors"][1]["blocked"] == "disturbed"
    # another origin cannot ask; the page can, once
    code, _, _ = request(page, "POST", "/finish", headers={**origin(page), "Origin": "http://evil.example"},
                         body={"csrf": page.csrf})
    assert code == 403 and not page.take_finish()
    assert request(page, "POST", "/finish", headers=origin(page), body={"csrf": page.csrf})[0] == 200
    assert page.take_finish() and not page.take_finish()
    feed.status(st, finish=True)
    assert feed.session.dropped == [("compass1",)]
    feed.status(replace(st, offer_finish_without=()), finish=True)  # nothing offered: nothing dropped
    assert feed.session.dropped == [("compass1",)]


def test_connections_are_bounded(page):
    """Idle connections hold a thread each for at most the handler's timeout, and no more than
    16 at once: the 17th is closed at once; the page answers again once they are gone."""
    import socket

    idle = [socket.create_connection(("127.0.0.1", page.port), timeout=5) for _ in range(16)]
    try:
        time.sleep(0.3)
        extra = socket.create_connection(("127.0.0.1", page.port), timeout=5)
        assert extra.recv(1) == b""  # closed by the server
        extra.close()
        assert sum("process_request_thread" in t.name for t in threading.enumerate()) <= 16
    finally:
        for s in idle:
            s.close()
    deadline = time.monotonic() + 15
    while True:
        try:
            assert request(page, "GET", "/")[0] == 200
            break
        except (OSError, http.client.HTTPException):
            assert time.monotonic() < deadline
            time.sleep(0.2)
