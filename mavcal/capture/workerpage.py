"""The live capture page for a :class:`~mavcal.capture.worker.CaptureWorker`: ``mavcal ui`` in
the MAVProxy module.

:class:`WorkerPage` serves the page (:class:`mavcal.capture.web.CapturePage`: 127.0.0.1, a
per-session token, Host/Origin/CSRF checks) and runs one feeder thread
(``mavcal-ui-feed``) that, every ``poll_s``,

* turns the IMU messages the host filed (:meth:`WorkerPage.add_imu`, MAVProxy's thread) into
  the page's live attitude, and the worker's capture statuses into the page's state;
* once the worker has fitted (its ``run``) and is not capturing, shows the verdict and the
  parameters that ``mavcal write`` would write, and waits for the page's decision;
* Write (confirmed on the page) queues the worker's ``write`` job, confirmed, with the
  module's settings at that moment; the page shows the outcome (the worker's
  ``write_result``), then the page stops. Don't write stops it at once.

The worker's own jobs and words are unchanged: the console says everything the page shows.
"""
from __future__ import annotations

import logging
import threading
from typing import Any, Callable

from mavcal.capture.pagestate import PageFeed, result_view
from mavcal.capture.web import LOCALHOST, CapturePage

__all__ = ["WorkerPage", "FEED_THREAD", "PAGE_HINTS"]

log = logging.getLogger(__name__)

FEED_THREAD = "mavcal-ui-feed"
#: how the page names the next steps in MAVProxy
PAGE_HINTS = {"force_hint": "'mavcal set force 1'", "write_hint": "the Write button below", "only_hint": ""}
_MAX_IMU = 5000  # IMU messages kept for the live view if the feeder falls behind


class WorkerPage:
    """The page of a worker's capture (see the module docstring).

    Parameters
    ----------
    worker : CaptureWorker
    settings : callable
        ``() -> WorkerSettings``: the host's settings when Write is pressed.
    host, port : str, int
        Where to serve (127.0.0.1 and a free port by default).
    """

    def __init__(self, worker: Any, settings: Callable[[], Any], host: str = LOCALHOST, port: int = 0,
                 poll_s: float = 0.1) -> None:
        self.worker = worker
        self.settings = settings
        self.page = CapturePage(host, port)
        self.poll_s = poll_s
        self._imu: list[Any] = []
        self._lock = threading.Lock()
        self._halt = threading.Event()
        self._feed: PageFeed | None = None
        self._status: Any = None
        self._run: Any = None
        self._write_job: int | None = None  # jobs_done when the write was queued
        self.finished = threading.Event()
        self.thread = threading.Thread(target=self._loop, name=FEED_THREAD, daemon=True)

    @property
    def url(self) -> str:
        return self.page.url

    def start(self) -> WorkerPage:
        self.page.start()
        self.thread.start()
        return self

    def add_imu(self, m: Any) -> None:
        """File one IMU message for the live attitude (the host's thread)."""
        with self._lock:
            if len(self._imu) < _MAX_IMU:
                self._imu.append(m)

    def close(self, timeout_s: float = 8.0) -> bool:
        """Stop the feeder and the page; True if no thread of theirs is left."""
        self._halt.set()
        if self.thread.is_alive() and self.thread is not threading.current_thread():
            self.thread.join(timeout=timeout_s)
        self.page.close(linger_s=0.5)
        return not self.thread.is_alive()

    # ------------------------------------------------------------------ the feeder thread
    def _loop(self) -> None:
        try:
            while not self._halt.wait(self.poll_s):
                try:
                    if self._step():
                        break
                except Exception:  # keep the page alive; the console has the worker's own words
                    log.exception("capture page feed failed")
        finally:
            self.finished.set()
            self.page.close(linger_s=2.0)

    def _step(self) -> bool:
        """One round; True when the page is done (written, declined)."""
        w = self.worker
        session = w.session
        if session is not None and (self._feed is None or self._feed.config is not session.config):
            opts = session.options
            self._feed = PageFeed(self.page.state.set, session.config, opts.accel_instance, opts.mag_instance)
            self._run = None
        self._feed_imu(session)
        st = w.status
        if self._feed is not None and st is not None and st is not self._status:
            self._status = st
            self._feed.status(st, session.run if session is not None else None)
        if self.page.take_finish():
            try:  # the worker's own job tells the session, on its thread
                w.submit("finish")
            except KeyError:
                log.info("this worker cannot finish without a sensor")
        if self.page.take_skip():  # "can't do this one": the worker's job asks the session, on its thread
            w.submit("skip")
        if w.busy == "fit":
            self.page.state.set(phase="fitting")
        run = w.run
        if run is not None and not w.capturing and run is not self._run:
            self._show_result(run)
        return self._decide()

    def _feed_imu(self, session: Any) -> None:
        from mavcal.link.live import imu_batch_from_messages

        with self._lock:
            msgs, self._imu = self._imu, []
        if msgs and self._feed is not None and session is not None:
            ids = self.worker.vehicle_ids()
            self._feed.batch(session, imu_batch_from_messages(msgs, target_system=ids[0] if ids else None))

    def _show_result(self, run: Any) -> None:
        from mavcal.report.html import missing_dependencies

        self._run = run
        view = result_view(run, run.params_to_write(self.settings().force), hints=PAGE_HINTS)
        if self.page.report_html is None and not missing_dependencies():
            self.page.report_html = _report_html(run)
        self.page.state.set(phase="result", result=view,
                            report=f"report?t={self.page.token}" if self.page.report_html else None)
        self.page.offer(view["n_write"])

    def _decide(self) -> bool:
        w = self.worker
        if self._write_job is not None:  # the write queued: wait for the worker to finish it
            if w.jobs_done <= self._write_job or w.busy or not w.jobs.empty():
                return False
            res = w.write_result
            if res is not None and getattr(res, "complete", False):
                self.page.state.set(phase="written", write={"text": "written and verified"})
            else:
                why = str(res) if res is not None else "the write did not run: see the MAVProxy console"
                self.page.state.set(phase="failed", write={"message": why})
            return True
        decision = self.page.poll_decision()
        if decision == "decline":
            self.page.state.set(phase="declined")
            return True
        if decision == "write":
            self.page.state.set(phase="writing")
            w.write_result = None
            self._write_job = w.jobs_done + (1 if w.busy else 0)
            w.submit("write", self.settings(), True)
        return False


def _report_html(run: Any) -> str | None:
    import tempfile
    from pathlib import Path

    from mavcal.report import write_html

    try:
        with tempfile.TemporaryDirectory(prefix="mavcal-page-") as d:
            return write_html(run, Path(d) / "report.html").read_text(encoding="utf-8")
    except Exception:  # the page works without its report link
        log.exception("the HTML report for the page failed")
        return None
