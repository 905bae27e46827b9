"""The live page of a guided capture: a small local web server, safe by default.

``mavcal capture --connect DEV --ui`` (and ``mavcal ui`` in the MAVProxy module) serves a page
that draws the pose to hold next beside the vehicle's live attitude, fills a ring while a pose
is held still, shows the poses done and each sensor's bound against its target, and at the end
the verdict, the parameters that will be written and a Write button. Updates go to the page by
Server-Sent Events (``/events``); the page and its script and style ship in
``mavcal/capture/page/`` (no external scripts, fonts or CDNs: it works offline).

A local web page is a door into the vehicle, so by default:

* the server binds 127.0.0.1 on a free port (another interface only when the caller names it,
  e.g. ``--ui-host``, and the command warns);
* every request must carry the session's random token (``?t=``, ``secrets.token_urlsafe``):
  without it, or with a wrong one, 403;
* the ``Host`` header must name this server (``127.0.0.1:PORT`` / ``localhost:PORT``, or the
  host given): a DNS-rebinding page gets 403;
* a POST (``/write``, ``/decline``, ``/finish``) must also come from this page: ``Origin`` present and equal
  to this server, ``Sec-Fetch-Site`` (when sent) ``same-origin``, a JSON body (a cross-site
  form cannot send one without a CORS preflight, which is refused: no CORS header is ever
  sent) carrying the per-session CSRF token that only the page's event stream reveals;
* a Content-Security-Policy lets the page load nothing but its own script and style;
* the server stops when the capture ends (after the write or the decline) or on Ctrl-C, and
  :meth:`CapturePage.close` joins every thread it started.

The decision (write or not) is handed to the caller: :meth:`CapturePage.wait_decision`.
The library logs and never prints.
"""
from __future__ import annotations

import json
import logging
import secrets
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any
from urllib.parse import parse_qs, urlsplit

__all__ = ["CapturePage", "PageState", "THREAD_NAME", "LOCALHOST"]

log = logging.getLogger(__name__)

LOCALHOST = "127.0.0.1"
THREAD_NAME = "mavcal-ui"
_ASSETS = {"/": ("index.html", "text/html; charset=utf-8"),
           "/page.js": ("page.js", "text/javascript; charset=utf-8"),
           "/page.css": ("page.css", "text/css; charset=utf-8")}
_CSP = ("default-src 'none'; script-src 'self'; style-src 'self'; connect-src 'self'; img-src 'self' data:; "
        "frame-ancestors 'none'; base-uri 'none'; form-action 'none'")
_REPORT_CSP = "default-src 'none'; style-src 'unsafe-inline'; img-src data:; frame-ancestors 'none'"
_MAX_BODY = 4096
_MAX_STREAMS = 8  # event streams open at once (a tab or two; more is refused)
_MAX_CONNECTIONS = 16  # connections served at once (the event streams included)
_KEEPALIVE_S = 10.0


class PageState:
    """The page's state: named parts (``phase``, ``status``, ``live``, ``result``, ``write``...)
    and a version that every change bumps; event streams wait on it."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._parts: dict[str, Any] = {"phase": "starting"}
        self.version = 0
        self.closed = False

    def set(self, **parts: Any) -> None:
        with self._cond:
            self._parts.update(parts)
            self.version += 1
            self._cond.notify_all()

    def get(self, name: str, default: Any = None) -> Any:
        with self._cond:
            return self._parts.get(name, default)

    def snapshot(self) -> tuple[int, str]:
        with self._cond:
            return self.version, json.dumps(self._parts, allow_nan=False, default=_json_default)

    def wait_newer(self, version: int, timeout_s: float) -> tuple[int, str] | None:
        """The state once its version passes ``version`` (None after ``timeout_s`` or when closed
        with nothing newer)."""
        with self._cond:
            self._cond.wait_for(lambda: self.version > version or self.closed, timeout=timeout_s)
            if self.version > version:
                return self.version, json.dumps(self._parts, allow_nan=False, default=_json_default)
            return None

    def close(self) -> None:
        with self._cond:
            self.closed = True
            self._cond.notify_all()


def _json_default(x: Any) -> Any:
    try:
        return float(x)
    except (TypeError, ValueError):
        return str(x)


def _asset(name: str) -> bytes:
    return resources.files("mavcal.capture").joinpath("page", name).read_bytes()


class _Server(ThreadingHTTPServer):
    """One thread per connection, at most ``_MAX_CONNECTIONS`` at once (more are closed at once:
    the threads never grow with what a client does)."""

    daemon_threads = False  # server_close() joins the request threads: none is left behind
    block_on_close = True
    page: CapturePage

    def __init__(self, *args: Any, **kw: Any) -> None:
        super().__init__(*args, **kw)
        self._slots = threading.BoundedSemaphore(_MAX_CONNECTIONS)

    def process_request(self, request: Any, client_address: Any) -> None:
        if not self._slots.acquire(blocking=False):
            log.info("page: too many connections; one closed")
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self._slots.release()
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._slots.release()


class _Handler(BaseHTTPRequestHandler):
    server: _Server
    protocol_version = "HTTP/1.0"  # one request per connection (an event stream stays open)
    timeout = 10.0  # a client that sends its request too slowly is dropped
    server_version = "mavcal"
    sys_version = ""

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 (the base class's name)
        log.debug("page: " + format, *args)

    # ------------------------------------------------------------------ checks
    def _refuse(self, code: int, why: str) -> None:
        log.info("page: refused %s %s: %s", self.command, urlsplit(self.path).path, why)
        body = f"{code} {why}\n".encode()
        self.send_response(code)
        self.send_header("Content-Type", "text/plain; charset=utf-8")
        self.send_header("Content-Length", str(len(body)))
        self._common_headers()
        self.end_headers()
        self.wfile.write(body)

    def _common_headers(self) -> None:
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.send_header("Referrer-Policy", "no-referrer")
        self.send_header("X-Frame-Options", "DENY")

    def _allowed(self) -> tuple[str, dict[str, list[str]]] | None:
        """The path and query of a request with the right Host and token; else refused (None)."""
        page = self.server.page
        host = (self.headers.get("Host") or "").strip().lower()
        if host not in page.allowed_hosts:
            self._refuse(403, "wrong Host")
            return None
        parts = urlsplit(self.path)
        query = parse_qs(parts.query)
        token = (query.get("t") or [""])[0]
        if not secrets.compare_digest(token.encode(), page.token.encode()):
            self._refuse(403, "missing or wrong token")
            return None
        return parts.path, query

    def _same_origin(self) -> bool:
        page = self.server.page
        origin = (self.headers.get("Origin") or "").strip().lower()
        host = (self.headers.get("Host") or "").strip().lower()
        if not origin or origin != f"http://{host}" or host not in page.allowed_hosts:
            self._refuse(403, "cross-origin request")
            return False
        site = self.headers.get("Sec-Fetch-Site")
        if site is not None and site != "same-origin":
            self._refuse(403, "cross-site request")
            return False
        return True

    # ------------------------------------------------------------------ methods
    def do_GET(self) -> None:
        checked = self._allowed()
        if checked is None:
            return
        path, _ = checked
        if path in _ASSETS:
            name, ctype = _ASSETS[path]
            body = _asset(name)
            if name == "index.html":  # its script and style links carry the token too
                body = body.replace(b"{{TOKEN}}", self.server.page.token.encode())
            self._send(200, body, ctype, csp=_CSP)
        elif path == "/state":
            self._send(200, self.server.page.state.snapshot()[1].encode(), "application/json")
        elif path == "/events":
            self._events()
        elif path == "/report":
            report = self.server.page.report_html
            if report is None:
                self._refuse(404, "no report yet")
            else:
                self._send(200, report.encode(), "text/html; charset=utf-8", csp=_REPORT_CSP)
        else:
            self._refuse(404, "not found")

    def do_POST(self) -> None:
        checked = self._allowed()
        if checked is None or not self._same_origin():
            return
        path, _ = checked
        if path not in ("/write", "/decline", "/finish", "/skip"):
            self._refuse(404, "not found")
            return
        ctype = (self.headers.get("Content-Type") or "").split(";")[0].strip().lower()
        try:
            length = int(self.headers.get("Content-Length") or "0")
        except ValueError:
            length = -1
        if ctype != "application/json" or not 0 < length <= _MAX_BODY:
            self._refuse(400, "expected a small JSON body")
            return
        try:
            body = json.loads(self.rfile.read(length))
        except (ValueError, OSError):
            self._refuse(400, "bad JSON")
            return
        page = self.server.page
        csrf = body.get("csrf") if isinstance(body, dict) else None
        if not isinstance(csrf, str) or not secrets.compare_digest(csrf.encode(), page.csrf.encode()):
            self._refuse(403, "missing or wrong CSRF token")
            return
        if path == "/write" and body.get("confirmed") is not True:
            self._refuse(400, "the write was not confirmed")
            return
        if path == "/finish":
            ok, why = page.request_finish()
        elif path == "/skip":
            ok, why = page.request_skip()
        else:
            ok, why = page.decide("write" if path == "/write" else "decline")
        self._send(200 if ok else 409, json.dumps({"ok": ok, "message": why}).encode(), "application/json")

    def do_OPTIONS(self) -> None:  # a CORS preflight: refused, and no CORS header is ever sent
        self._refuse(403, "cross-origin requests are not allowed")

    def do_PUT(self) -> None:
        self._refuse(405, "method not allowed")

    do_DELETE = do_PATCH = do_PUT

    # ------------------------------------------------------------------ responses
    def _send(self, code: int, body: bytes, ctype: str, *, csp: str | None = None) -> None:
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        if csp:
            self.send_header("Content-Security-Policy", csp)
        self._common_headers()
        self.end_headers()
        self.wfile.write(body)

    def _events(self) -> None:
        """Server-Sent Events: the whole state whenever it changes, a comment every
        ``_KEEPALIVE_S``; ends when the page closes (after sending the last state)."""
        page = self.server.page
        if not page.stream_opened():
            self._refuse(503, "too many open event streams")
            return
        try:
            self.send_response(200)
            self.send_header("Content-Type", "text/event-stream; charset=utf-8")
            self._common_headers()
            self.end_headers()
            version, text = page.state.snapshot()
            self._event(text)
            last_beat = time.monotonic()
            while True:
                got = page.state.wait_newer(version, timeout_s=0.5)
                if got is not None:
                    version, text = got
                    self._event(text)
                    page.delivered(version)
                elif page.state.closed:
                    self.wfile.write(b"event: end\ndata: {}\n\n")
                    self.wfile.flush()
                    return
                elif time.monotonic() - last_beat >= _KEEPALIVE_S:
                    self.wfile.write(b": keep-alive\n\n")
                    self.wfile.flush()
                    last_beat = time.monotonic()
        except (BrokenPipeError, ConnectionResetError, TimeoutError, OSError) as exc:
            log.debug("page: event stream ended: %s", exc)
        finally:
            page.stream_closed()

    def _event(self, text: str) -> None:
        self.wfile.write(b"data: " + text.encode() + b"\n\n")
        self.wfile.flush()


class CapturePage:
    """The page's server and state (see the module docstring).

    Parameters
    ----------
    host : str
        Interface to bind; 127.0.0.1 unless the user asked for another (the caller warns).
    port : int
        0: a free port.
    """

    def __init__(self, host: str = LOCALHOST, port: int = 0) -> None:
        self.host = host
        self.token = secrets.token_urlsafe(24)
        self.csrf = secrets.token_urlsafe(24)
        self.state = PageState()
        self.report_html: str | None = None
        self._decision: str | None = None
        self._accepting = False  # True while a decision (write / decline) is awaited
        self._decided = threading.Event()
        self._can_write = False
        self._finish = False
        self._skip = False
        self._lock = threading.Lock()
        self._streams = 0
        self._delivered = 0
        self._server = _Server((host, port), _Handler)
        self._server.page = self
        self.port = int(self._server.server_address[1])
        names = {f"{LOCALHOST}:{self.port}", f"localhost:{self.port}"}
        if host not in (LOCALHOST, "localhost"):
            names.add(f"{host.lower()}:{self.port}")
        self.allowed_hosts = frozenset(names)
        self._thread: threading.Thread | None = None
        self.state.set(phase="starting", csrf=self.csrf)

    @property
    def url(self) -> str:
        shown = LOCALHOST if self.host in (LOCALHOST, "0.0.0.0", "") else self.host
        return f"http://{shown}:{self.port}/?t={self.token}"

    def start(self) -> CapturePage:
        self._thread = threading.Thread(target=self._server.serve_forever, kwargs={"poll_interval": 0.2},
                                        name=THREAD_NAME, daemon=True)
        self._thread.start()
        log.info("capture page at %s:%d", self.host, self.port)
        return self

    def __enter__(self) -> CapturePage:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ streams
    def stream_opened(self) -> bool:
        with self._lock:
            if self._streams >= _MAX_STREAMS:
                return False
            self._streams += 1
            return True

    def stream_closed(self) -> None:
        with self._lock:
            self._streams -= 1

    def delivered(self, version: int) -> None:
        with self._lock:
            self._delivered = max(self._delivered, version)

    # ------------------------------------------------------------------ the decision
    def offer(self, n_write: int) -> None:
        """From now on the page may decide: write (when ``n_write`` > 0) or decline."""
        with self._lock:
            self._accepting = True
            self._decision = None
            self._decided.clear()
            self._can_write = n_write > 0

    def decide(self, what: str) -> tuple[bool, str]:
        """A decision from the page (a server thread): taken once, while one is awaited."""
        with self._lock:
            if not self._accepting:
                return False, "nothing to decide now"
            if what == "write" and not self._can_write:
                return False, "nothing to write"
            self._accepting = False
            self._decision = what
            self._decided.set()
        log.info("page: %s", what)
        return True, what

    def request_finish(self) -> tuple[bool, str]:
        """"Finish without" the sensors the capture offers to leave out (a server thread):
        recorded only while the page shows such an offer; :meth:`take_finish` hands it over."""
        status = self.state.get("status") or {}
        if self.state.get("phase") != "capturing" or not status.get("finish_without"):
            return False, "nothing to finish without now"
        with self._lock:
            self._finish = True
        return True, "finishing without " + ", ".join(status["finish_without"])

    def take_finish(self) -> bool:
        """True once after the page asked to finish without the sensors offered (the capture's
        thread calls it and tells the session)."""
        with self._lock:
            asked, self._finish = self._finish, False
        return asked

    def request_skip(self) -> tuple[bool, str]:
        """"Can't do this one" (a server thread): recorded while capturing; :meth:`take_skip` hands it over."""
        if self.state.get("phase") != "capturing":
            return False, "no pose to skip now"
        with self._lock:
            self._skip = True
        return True, "another pose is coming"

    def take_skip(self) -> bool:
        """True once after the page said it cannot hold the advised pose (the capture's thread
        calls it and asks the session for another)."""
        with self._lock:
            asked, self._skip = self._skip, False
        return asked

    def poll_decision(self) -> str | None:
        """The decision if one was taken (not waiting)."""
        return self._decision if self._decided.is_set() else None

    def wait_decision(self, timeout_s: float | None = None) -> str | None:
        """``"write"``, ``"decline"``, or None after ``timeout_s``. Ctrl-C (KeyboardInterrupt)
        reaches the caller within a fraction of a second."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while not self._decided.wait(0.2):
            if deadline is not None and time.monotonic() >= deadline:
                with self._lock:
                    self._accepting = False
                return None
        return self._decision

    # ------------------------------------------------------------------ shut down
    def close(self, linger_s: float = 2.0) -> None:
        """Stop the server: give open event streams up to ``linger_s`` to deliver the last
        state, end them, stop serving and join every request thread and the server thread."""
        if self._thread is None:
            self._server.server_close()
            return
        deadline = time.monotonic() + linger_s
        while time.monotonic() < deadline:
            with self._lock:
                if self._streams == 0 or self._delivered >= self.state.version:
                    break
            time.sleep(0.05)
        self.state.close()
        self._server.shutdown()
        self._server.server_close()  # joins the request threads (daemon_threads False)
        self._thread.join(timeout=5.0)
        self._thread = None
        log.info("capture page closed")
