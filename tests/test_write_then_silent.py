"""A vehicle that falls silent after a write is never reported written and fine (issue 35, item 8):
after the read-back the writer waits for the vehicle's messages (its IMU messages if they streamed
during the write), and says so when none come (:class:`mavcal.link.after_write.StreamCheck`)."""
from __future__ import annotations

import pytest

from mavcal.errors import LinkError
from mavcal.link import writer
from mavcal.link.after_write import StreamCheck
from mavcal.link.connection import open_link
from mavcal.link.writer import write_params

FAST = dict(timeout_s=0.2, restore_wait_s=1.0)


@pytest.fixture
def vehicle(start_vehicle):
    return start_vehicle("udpout", heartbeat_hz=20, seed=1)


@pytest.fixture
def link(vehicle):
    lk = open_link(vehicle.gcs_device, timeout_s=5)
    yield lk
    lk.close()


def test_a_vehicle_silent_after_the_write_is_not_reported_fine(vehicle, link, tmp_path, monkeypatch):
    read_back = writer._read_back

    def then_silent(*a, **k):
        got = read_back(*a, **k)
        vehicle.kill()  # verified, then nothing more from it
        return got

    monkeypatch.setattr(writer, "_read_back", then_silent)
    with pytest.raises(LinkError, match=r"1 parameters written and verified, but then the vehicle stopped sending "
                                        r"\(any message: nothing for 3 s\)") as e:
        write_params(link, {"COMPASS_OFS_X": 12.0}, backup_path=tmp_path / "b.param", **FAST)
    assert str(tmp_path / "b.param") in str(e.value) and e.value.exit_code == 3
    assert vehicle.get_param("COMPASS_OFS_X") == 12.0


def test_a_vehicle_that_keeps_streaming_is_written_and_fine(vehicle, link, tmp_path):
    rep = write_params(link, {"COMPASS_OFS_X": 13.0}, backup_path=tmp_path / "b.param", **FAST)
    assert rep.complete and vehicle.get_param("COMPASS_OFS_X") == 13.0


def test_the_check_wants_the_imu_messages_that_streamed(vehicle, link):
    """IMU messages seen during the write must come again; a HEARTBEAT alone does not do."""
    check = StreamCheck(link)
    try:
        check.heard = {"HEARTBEAT", "SCALED_IMU2"}  # as if SCALED_IMU2 had streamed during the write
        with pytest.raises(LinkError, match=r"\(SCALED_IMU2: nothing for"):
            check.check(1, "b.param", None)  # this vehicle sends heartbeats but no SCALED_IMU2 unasked
        check.heard = {"HEARTBEAT"}
        check.check(1, "b.param", None)  # no IMU message streamed: any message will do
    finally:
        check.close()
