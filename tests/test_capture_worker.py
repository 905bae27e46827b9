"""The front ends catch up with the per-sensor verdicts and the safe write flow (issue 10, issue 13
items 4/5): the MAVProxy module's worker (:mod:`mavcal.capture.worker`) without MAVProxy, the
``capture`` command's exit code and write, the IMU messages asked for, and the progress of a live
``calibrate DEVICE`` recording."""
import argparse
import io
import queue
import threading
import time

import pytest

from mavcal.capture.worker import FED_TYPES, CaptureWorker, WorkerSettings
from mavcal.link.connection import open_link
from mavcal.link.fed import flush_outbox
from mavcal.link.streams import STREAM_MESSAGE_IDS, needed_stream_ids
from mavcal.testing.vehicle import VehicleTruth

PARTIAL_TLOG = "2024-04-05 09-19-03.tlog"  # accel0 accepted, both compasses rejected: exit 7


@pytest.fixture(scope="module")
def partial_run(real_dir):
    from mavcal.pipeline import calibrate_source

    run = calibrate_source(str(real_dir / PARTIAL_TLOG))
    assert run.exit_code == 7
    return run


class Host:
    """What MAVProxy does for the worker: owns the socket, files the parameter protocol's messages
    into the worker's fed connection, sends its outbox, and collects what it says."""

    def __init__(self, device: str):
        self.link = open_link(device, timeout_s=5)
        self.worker = CaptureWorker(lambda: (self.link.target_system, self.link.target_component))
        self.said: list[str] = []
        self.sent: list[tuple] = []
        self.halt = threading.Event()
        self.thread = threading.Thread(target=self._own, name="test-host", daemon=True)
        self.thread.start()

    def _own(self) -> None:
        while not self.halt.is_set():
            flush_outbox(self.worker.outbox, self.link.mav)
            m = self.link.conn.recv_match(blocking=True, timeout=0.01)
            fed = self.worker.fed
            if m is not None and fed is not None and m.get_type() in FED_TYPES:
                fed.feed(m)
            while True:
                try:
                    self.said.append(self.worker.out.get_nowait())
                except queue.Empty:
                    break

    def wait_said(self, text: str, timeout: float = 30.0) -> str:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            hit = [s for s in list(self.said) if text in s]
            if hit:
                return hit[0]
            time.sleep(0.05)
        pytest.fail(f"the worker did not say {text!r}; said:\n" + "\n".join(self.said))

    def close(self) -> None:
        assert self.worker.shutdown(timeout_s=10)
        self.halt.set()
        self.thread.join(timeout=5)
        self.link.close()


@pytest.fixture
def host(start_vehicle):
    v = start_vehicle(truth=VehicleTruth.random(3), seed=3, heartbeat_hz=5, param_errors=True)
    h = Host(v.gcs_device)
    h.vehicle = v
    yield h
    h.close()


def test_worker_writes_only_the_accepted_sensors(host, partial_run, tmp_path):
    v, w = host.vehicle, host.worker
    w.run = partial_run
    cfg = WorkerSettings(confirm=False, backup_dir=str(tmp_path))
    w.submit("write", cfg, True)
    host.wait_said("written and verified")
    written = {name for name, _, stored in v.param_sets if stored is not None}
    assert written == set(partial_run.params_to_write()) and not any(n.startswith("COMPASS") for n in written)
    assert v.force_saves == ["accel"]  # only the sensor whose values were written is marked calibrated
    for n, x in partial_run.params_to_write().items():
        assert v.get_param(n) == pytest.approx(x, rel=1e-6, abs=1e-6)
    # read by name (fetch_for_write), never the whole table
    assert len(list(tmp_path.glob("mavcal-backup-*.param"))) == 1


def test_worker_shows_the_verdicts_and_refuses_only_when_none_is_accepted(host, partial_run, tmp_path):
    from mavcal.report.text import verdict_lines

    w = host.worker
    w.run = partial_run
    w.submit("write", WorkerSettings(backup_dir=str(tmp_path)), False)  # confirm: the diff only
    host.wait_said("type 'mavcal write yes' to write them")
    assert host.vehicle.param_sets == []

    class NoneAccepted:  # the same run, as if its accelerometer had been rejected too
        exit_code = 4
        gates = partial_run.gates

    w.run = NoneAccepted()
    w.submit("write", WorkerSettings(confirm=False, backup_dir=str(tmp_path)), True)
    refusal = host.wait_said("nothing written: the calibration failed a quality gate")
    assert "'mavcal set force 1' to override" in refusal and refusal.startswith("mavcal: ")
    assert host.vehicle.param_sets == []
    # the summary after a fit: per-sensor verdicts and the module's next step first
    from mavcal.report.text import MAVPROXY_HINTS, summary_text

    text = summary_text(partial_run, hints=MAVPROXY_HINTS)
    assert text.splitlines()[1:1 + len(verdict_lines(partial_run))] == verdict_lines(partial_run)
    assert "'mavcal set force 1' to write them anyway" in text and "--accel-only" not in text


def test_worker_refuses_out_of_range_unless_forced(host, tmp_path):
    v, w = host.vehicle, host.worker
    bad = tmp_path / "bad.param"
    bad.write_text("COMPASS_DIA_X -5\n")
    w.submit("restore", WorkerSettings(confirm=False, backup_dir=str(tmp_path)), str(bad), True)
    said = host.wait_said("COMPASS_DIA_X")
    assert "error" in said and "limit" in said and v.param_sets == []
    w.submit("restore", WorkerSettings(confirm=False, force=True, backup_dir=str(tmp_path)), str(bad), True)
    warn = host.wait_said("WARNING: force: writing COMPASS_DIA_X = -5")
    assert "compass will NOT be marked calibrated" in warn
    host.wait_said("written and verified")
    assert v.get_param("COMPASS_DIA_X") == -5 and "compass" not in v.force_saves


def test_capture_exits_7_and_writes_the_accepted_params_only(partial_run, monkeypatch, tmp_path):
    from mavcal.capture import live as live_capture
    from mavcal.commands import capture

    class Session:
        status = None

        def result(self):
            return partial_run

    calls = []
    monkeypatch.setattr(live_capture, "capture_live", lambda *a, **kw: Session())
    monkeypatch.setattr(capture, "write_with_report", lambda *a, **kw: calls.append((a, kw)) or 0)
    p = argparse.ArgumentParser()
    capture.add_arguments(p)
    args = p.parse_args(["--connect", "udpin:127.0.0.1:1", "--write", "--yes", "--param-out",
                         str(tmp_path / "new.param")])
    assert capture.run(args) == 7
    (a, kw), = calls
    assert a[1] == partial_run.params_to_write() and "log_params" not in kw
    args.force = True
    calls.clear()
    assert capture.run(args) == 0 and calls[0][0][1] == dict(partial_run.mapping.new)


def test_only_the_imu_messages_the_vehicle_has_are_asked_for():
    raw, imu2, imu3 = STREAM_MESSAGE_IDS
    full = VehicleTruth.random(1)  # the test vehicle: 3 IMUs, 3 compasses
    from mavcal.testing.vehicle import TestVehicle

    assert needed_stream_ids(TestVehicle(truth=full).params) == (raw, imu2, imu3)
    assert needed_stream_ids(None) == STREAM_MESSAGE_IDS
    assert needed_stream_ids({}) == STREAM_MESSAGE_IDS  # the table does not say: ask
    one = {"INS_ACC_ID": 1, "INS_ACC2_ID": 0, "INS_ACC3_ID": 0, "COMPASS_DEV_ID": 7, "COMPASS_DEV_ID2": 0,
           "COMPASS_DEV_ID3": 0}
    assert needed_stream_ids(one) == (raw,)
    assert needed_stream_ids({**one, "COMPASS_DEV_ID2": 5}) == (raw, imu2)


def test_recording_progress_on_a_terminal_only():
    from mavcal.commands.calibrate import RecordingPrinter, recording_printer
    from mavcal.link.live import RecordingProgress

    class Tty(io.StringIO):
        def isatty(self):
            return True

    assert recording_printer(io.StringIO()) is None  # piped: silent
    assert recording_printer(Tty(), quiet=True) is None  # --quiet: silent
    out = Tty()
    printer = recording_printer(out)
    assert isinstance(printer, RecordingPrinter)
    printer(RecordingProgress(12.2, 60.0, 610))
    printer(RecordingProgress(60.0, 60.0, 3000))
    text = out.getvalue()
    assert "\rrecording:   12 of 60 s, 48 s left, 610 samples" in text
    assert text.endswith("0 s left, 3000 samples\x1b[K\n") and text.count("\n") == 1


def test_record_device_reports_its_progress(start_vehicle):
    from mavcal.link.live import PROGRESS_PERIOD_S, record_device

    v = start_vehicle(truth=VehicleTruth.random(2), seed=2, heartbeat_hz=5)
    seen, pairs = [], []
    log_ = record_device(v.gcs_device, duration_s=1.6, rate_hz=25, on_progress=seen.append,
                         progress=lambda d, t: pairs.append((d, t)))
    assert log_.series
    assert len(seen) >= int(1.6 / PROGRESS_PERIOD_S) and seen[-1].done and seen[-1].remaining_s == 0
    assert [p.elapsed_s for p in seen] == sorted(p.elapsed_s for p in seen)
    assert 0 < seen[0].samples <= seen[-1].samples
    n_accel = sum(len(s.time_s) for s in log_.series if s.sensor == "accel")
    assert seen[-1].samples == n_accel
    assert pairs[-1] == (1600, 1600) and len(pairs) == len(seen)
