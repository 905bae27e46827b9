"""The live capture page in a real browser (headless chromium driven by selenium through
Debian's chromium-driver), on a whole guided capture of the loopback vehicle:

* the page loads with the token and is refused without it, or under another host name;
* while the capture runs it shows the advised pose (the words and the drawing) and the
  vehicle's live attitude; a hand (a thread) follows the advice it reads from the page's own
  state, as a person follows the drawing;
* it reaches the verdict with the parameter table; a page of another origin in the same
  browser cannot make it write, even knowing the URL with its token;
* Write, reached with the keyboard and confirmed in the dialog, writes, and the vehicle reads
  back the new values.

Screenshots of four moments go to ``benchmarks/out/capture_page/`` (untracked; another
directory with ``MAVCAL_PAGE_SHOTS``). With ``CI`` set, a missing chromium, chromium-driver or
selenium fails the test instead of skipping it.
"""
from __future__ import annotations

import json
import os
import threading
import time
import urllib.request
import webbrowser
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
import pytest
from test_live_capture import AdviceHand

from mavcal import cli
from mavcal.autopilot.paramfile import read_param_file
from mavcal.capture.web import THREAD_NAME
from mavcal.testing.browser import headless_chromium, missing, page_text, wait_for
from mavcal.testing.vehicle import VehicleTruth

REPO = Path(__file__).resolve().parents[1]
#: on the worker of the PX4 SITL tests (--dist loadgroup): a guided capture on the page runs the vehicle,
#: the capture, the page server and chromium's client in real time, and it once stalled at 1 interval for
#: 300 s beside the other heavy tests (CI, -n 3); so never beside PX4's lockstep simulation nor each other
pytestmark = pytest.mark.xdist_group("heavy")

SHOTS = Path(os.environ.get("MAVCAL_PAGE_SHOTS") or REPO / "benchmarks" / "out" / "capture_page")


def _in_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no")


@pytest.fixture(scope="module")
def browser():
    gone = missing()
    if gone:
        msg = f"{', '.join(gone)} not installed (apt-get install chromium chromium-driver; pip install selenium)"
        if _in_ci():
            pytest.fail("CI: the capture page's browser test must run: " + msg)
        pytest.skip(msg)
    with headless_chromium() as drv:
        yield drv


def shoot(drv, name: str) -> Path:
    SHOTS.mkdir(parents=True, exist_ok=True)
    if SHOTS.parent.name == "out" and not (SHOTS.parent / ".gitignore").exists():
        (SHOTS.parent / ".gitignore").write_text("# benchmark results of unsaved runs (benchmarks/README.md)\n*\n")
    path = SHOTS / f"{name}.png"
    drv.save_screenshot(str(path))
    assert path.stat().st_size > 10_000
    return path


class PageClient:
    """Reads the page's state as the page does (GET /state with the token)."""

    def __init__(self, url: str) -> None:
        parts = urlsplit(url)
        self.base = f"{parts.scheme}://{parts.netloc}"
        self.token = dict(q.split("=", 1) for q in parts.query.split("&"))["t"]

    def get(self, path: str) -> tuple[int, bytes]:
        req = urllib.request.Request(f"{self.base}{path}?t={self.token}")
        try:
            with urllib.request.urlopen(req, timeout=10) as r:
                return r.status, r.read()
        except urllib.error.HTTPError as exc:
            return exc.code, exc.read()

    def state(self) -> dict:
        code, body = self.get("/state")
        return json.loads(body) if code == 200 else {}

    def advice(self):
        """(intervals kept, advised (roll, pitch, yaw magnetic) or None, done): what the page shows."""
        st = self.state().get("status")
        if not st:
            return 0, None, False
        a = st.get("next")
        return st["n"], (None if a is None else (a["roll"], a["pitch"], a["yaw"])), st["done"]


class _Evil(BaseHTTPRequestHandler):
    """Another web site open in the same browser."""

    def do_GET(self) -> None:
        body = b"<!DOCTYPE html><title>another site</title><p>another site</p>"
        self.send_response(200)
        self.send_header("Content-Type", "text/html")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *a) -> None:
        pass


ATTACK_JS = """
const done = arguments[arguments.length - 1];
const url = arguments[0], dec = arguments[1];
const out = [];
const body = JSON.stringify({csrf: "guessed", confirmed: true});
(async () => {
  try { await fetch(url, {method: "POST", mode: "no-cors", headers: {"Content-Type": "text/plain"}, body});
        out.push("no-cors sent"); } catch (e) { out.push("no-cors refused"); }
  try { const r = await fetch(url, {method: "POST", headers: {"Content-Type": "application/json"}, body});
        out.push("cors status " + r.status); } catch (e) { out.push("cors blocked"); }
  try { await fetch(dec, {method: "POST", mode: "no-cors", body}); out.push("decline sent"); }
  catch (e) { out.push("decline refused"); }
  const f = document.createElement("form");
  f.method = "POST"; f.action = url; f.target = "sink"; f.enctype = "text/plain";
  const i = document.createElement("input"); i.name = '{"csrf":"x","confirmed":true,"pad":"'; i.value = '"}';
  f.appendChild(i);
  const frame = document.createElement("iframe"); frame.name = "sink";
  document.body.append(frame, f);
  frame.onload = () => { out.push("form posted"); done(out); };
  f.submit();
  setTimeout(() => done(out), 5000);
})();
"""


def _attack_from_another_origin(drv, page_url: str) -> list[str]:
    srv = ThreadingHTTPServer(("127.0.0.1", 0), _Evil)
    t = threading.Thread(target=srv.serve_forever, name="test-other-site", daemon=True)
    t.start()
    main = drv.current_window_handle
    try:
        drv.switch_to.new_window("tab")
        drv.get(f"http://localhost:{srv.server_address[1]}/")
        parts = urlsplit(page_url)
        base = f"{parts.scheme}://{parts.netloc}"
        return drv.execute_async_script(ATTACK_JS, f"{base}/write?{parts.query}", f"{base}/decline?{parts.query}")
    finally:
        drv.close()
        drv.switch_to.window(main)
        srv.shutdown()
        srv.server_close()
        t.join(timeout=5)


def _focus_by_tab(drv, element_id: str, limit: int = 40) -> None:
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.keys import Keys

    for _ in range(limit):
        if drv.execute_script("return document.activeElement && document.activeElement.id") == element_id:
            return
        ActionChains(drv).send_keys(Keys.TAB).perform()
    raise AssertionError(f"#{element_id} not reachable with Tab")


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_guided_capture_on_the_page_to_a_confirmed_write(browser, start_vehicle, tmp_path, monkeypatch):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.keys import Keys

    drv = browser
    vehicle = start_vehicle(truth=VehicleTruth.random(3), seed=3, heartbeat_hz=5)
    before = vehicle.params
    urls: list[str] = []
    monkeypatch.setattr(webbrowser, "open", lambda url, *a, **k: urls.append(url) or True)
    result: dict = {}
    argv = ["capture", "--connect", vehicle.gcs_device, "--hold", "0.6", "--rate", "25", "--duration", "300",
            "--ui", "--param-out", str(tmp_path / "new.param"), "--backup", str(tmp_path / "backup.param")]

    def run() -> None:
        try:
            result["rc"] = cli.main(argv)
        except BaseException as exc:  # shown by the assertion below
            result["exc"] = exc

    capture = threading.Thread(target=run, name="test-capture", daemon=True)
    capture.start()
    hand = None
    try:
        url = wait_for("the page's address (webbrowser.open)", lambda: urls, 60, show=lambda: result)[0]
        assert url.startswith("http://127.0.0.1:") and "?t=" in url
        client = PageClient(url)
        # refused without the token, in the browser too
        drv.get(url.split("?")[0])
        assert "403" in drv.find_element("tag name", "body").text
        # another name for this computer (chromium resolves *.localhost to 127.0.0.1), as a DNS
        # rebinding page would use: the Host header is wrong, refused even with the token
        drv.get(url.replace("127.0.0.1", "rebind.localhost"))
        assert "403 wrong Host" in drv.find_element("tag name", "body").text
        drv.get(url)
        wait_for("the first advice and the live attitude on the page",
                 lambda: drv.execute_script("return document.querySelectorAll('#scene-live polygon').length") > 3
                 and "level" in page_text(drv, "pose-words"), 180,
                 show=lambda: (str(client.state())[:600], page_text(drv, "instruction"), result))
        shoot(drv, "1-start")
        # a hand that, as a person does, also follows an advice that changed without a new interval: the
        # capture stalled at 1 interval in CI (-n 2 and -n 3) with a hand that moved only when the count grew
        hand = AdviceHand(vehicle, client.advice, follow_s=4.0)
        hand.start()

        # mid-capture: the advised pose drawn and in words, the vehicle now matching it, a few poses done
        def mid():
            st = client.state().get("status") or {}
            n = st.get("n", 0)
            words = page_text(drv, "pose-words")
            matched = drv.execute_script("return document.getElementById('live-figure').classList.contains('match')")
            holding = "Still" in page_text(drv, "hold-text")  # the ring filling
            assert client.state().get("phase") == "capturing", "the capture ended before a mid-capture view"
            bounds = any(s["bound_deg"] is not None for s in st.get("sensors", []))  # after the first fit
            return n >= 6 and bounds and st.get("next") and st["next"]["words"] in words and matched and holding
        # on a timeout: what the capture holds, where the vehicle is and where the hand took it
        wait_for("a mid-capture view with the advised pose matched", mid, 240, poll_s=0.05,
                 show=lambda: (str(client.state().get("status"))[:900], "vehicle attitude",
                               np.round(vehicle.attitude, 3).tolist(), "hand's poses", hand.poses[-12:],
                               "follows", hand.follows))
        assert drv.execute_script("return document.querySelectorAll('#scene-target polygon').length") > 3
        assert drv.execute_script("return document.querySelectorAll('#sphere circle').length") >= 5
        shoot(drv, "2-mid-capture")

        # the verdict
        wait_for("the verdict", lambda: drv.execute_script(
            "return !document.getElementById('result').hidden && !document.getElementById('write').disabled"), 240,
            show=lambda: str(client.state().get("phase")))
        hand.stop()
        state = client.state()
        res = state["result"]
        assert state["phase"] == "result" and res["verdicts"] and res["n_write"] > 0
        cards = drv.find_elements("css selector", "#verdicts .card")
        assert len(cards) == len(res["verdicts"])
        rows = drv.find_elements("css selector", "#params tbody tr")
        assert len(rows) == len(res["params"])
        for r, tr in zip(res["params"], rows):
            assert r["name"] in tr.text
            assert ("not written" in tr.text) == (not r["write"])
        assert client.get("/report")[0] == 200 if state.get("report") else True
        shoot(drv, "3-verdict")

        # another site in the same browser, even knowing the URL with its token, cannot write
        said = _attack_from_another_origin(drv, url)
        assert "cors status 200" not in said, said
        time.sleep(0.5)
        assert client.state()["phase"] == "result" and vehicle.param_sets == [], said

        # Write: Tab to it, Enter; the dialog asks; Tab to "Yes, write", Enter
        _focus_by_tab(drv, "write")
        ActionChains(drv).send_keys(Keys.ENTER).perform()
        dialog_open = "return document.getElementById('confirm').open"
        wait_for("the confirmation dialog", lambda: drv.execute_script(dialog_open), 10)
        assert vehicle.param_sets == []  # asked, not written yet
        _focus_by_tab(drv, "confirm-yes", limit=5)
        ActionChains(drv).send_keys(Keys.ENTER).perform()
        wait_for("the write's outcome on the page", lambda: "Written" in page_text(drv, "write-outcome"), 90)
        shoot(drv, "4-written")
        capture.join(timeout=60)
        assert not capture.is_alive()
    finally:
        if hand is not None:
            hand.stop()
        capture.join(timeout=30)
    assert "exc" not in result, result.get("exc")
    n_rejected = sum(not v["accepted"] for v in res["verdicts"])
    assert result["rc"] == (7 if n_rejected else 0)
    # the vehicle reads back exactly the accepted sensors' new values; the rejected keep theirs
    new = read_param_file(tmp_path / "new.param")
    written = {r["name"] for r in res["params"] if r["write"]}
    assert set(new) == written
    for n, v in new.items():
        assert vehicle.get_param(n) == pytest.approx(float(np.float32(v)), rel=1e-6, abs=1e-6), n
    for r in res["params"]:
        if not r["write"]:
            assert vehicle.get_param(r["name"]) == pytest.approx(before[r["name"]], abs=1e-6), r["name"]
    backup = read_param_file(tmp_path / "backup.param")
    assert backup and all(backup[n] == pytest.approx(before[n], abs=1e-5) for n in backup)
    # the server stopped with the capture: no thread left, nothing answers
    assert not [t for t in threading.enumerate() if t.name == THREAD_NAME]
    with pytest.raises(OSError):
        urllib.request.urlopen(url, timeout=3)


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_mavproxy_ui_page_capture_to_a_confirmed_write(browser, start_vehicle, tmp_path):
    """``mavcal ui`` in a real MAVProxy: the page starts the capture, the hand follows the page,
    Write on the page (confirmed in its dialog) writes through the worker's safe writer."""
    import importlib.util

    if importlib.util.find_spec("MAVProxy") is None:
        pytest.skip("MAVProxy is not installed (pip install --no-deps MAVProxy)")
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.keys import Keys
    from test_mavproxy_module import MAVProxy

    drv = browser
    v = start_vehicle(truth=VehicleTruth.random(5), seed=5, heartbeat_hz=2)
    before = v.params
    mp = MAVProxy(v.gcs_device, tmp_path)
    hand = None
    try:
        mp.expect(r"Detected vehicle 1:1", timeout=20)
        _, at = mp.expect(r"Loaded module mavcal\.mavproxy_mavcal", after=mp.send("module load mavcal.mavproxy_mavcal"))
        mp.send("mavcal set hold_s 0.6")
        mp.send(f"mavcal set backup_dir {tmp_path / 'backups'}")
        ui = mp.send("mavcal ui nobrowser")
        m, _ = mp.expect(r"mavcal: capture page: (http://127\.0\.0\.1:\d+/\?t=\S+)", after=ui)
        url = m.group(1)
        client = PageClient(url)
        mp.expect(r"mavcal: capture started", after=at, timeout=40)  # 'ui' started the capture
        drv.get(url)
        wait_for("the advice on the page", lambda: "level" in page_text(drv, "pose-words"), 30)
        _, threads_at = mp.expect(r"mavcal threads: (.*)$", after=mp.send("mavcal threads"))
        assert "mavcal-ui-feed" in mp.lines[threads_at - 1] and "mavcal-ui" in mp.lines[threads_at - 1]
        hand = AdviceHand(v, client.advice)
        hand.start()
        wait_for("the verdict on the page", lambda: drv.execute_script(
            "return !document.getElementById('result').hidden && !document.getElementById('write').disabled"), 150)
        hand.stop()
        res = client.state()["result"]
        assert v.param_sets == []
        _focus_by_tab(drv, "write")
        ActionChains(drv).send_keys(Keys.ENTER).perform()
        _focus_by_tab(drv, "confirm-yes", limit=5)
        ActionChains(drv).send_keys(Keys.ENTER).perform()
        wait_for("the write's outcome on the page", lambda: "Written" in page_text(drv, "write-outcome"), 60)
        mp.expect(r"mavcal: \d+ parameters written and verified", after=at, timeout=10)
        written = {r["name"] for r in res["params"] if r["write"] and r["changed"]}
        assert written and {n for n, *_ in v.param_sets} >= written
        for r in res["params"]:
            if not r["write"]:
                assert v.get_param(r["name"]) == pytest.approx(before[r["name"]], abs=1e-6)
        # the page stopped after the write; the worker goes on
        wait_for("the page to stop", lambda: _refused(url), 15)
        _, threads_at = mp.expect(r"mavcal threads: (.*)$", after=mp.send("mavcal threads"))
        assert mp.lines[threads_at - 1].endswith("mavcal threads: mavcal-worker")
        mp.expect(r"mavcal threads left: none", after=mp.send("module unload mavcal"), timeout=15)
    finally:
        if hand is not None:
            hand.stop()
        mp.close()


def _refused(url: str) -> bool:
    try:
        urllib.request.urlopen(url, timeout=2)
    except OSError:
        return True
    return False
