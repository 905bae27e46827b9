"""``--connect auto`` (and no ``--connect``): the flight controller's serial port found from pyserial's
port list, given here as fake lists; the one picked is opened for real (a pty, the loopback vehicle
behind :class:`mavcal.testing.serial_cable.SerialCable`)."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from mavcal import cli
from mavcal.errors import AmbiguousPortError, LinkError
from mavcal.link.autodetect import PortInfo, find_port, list_candidates, rank_port
from mavcal.link.connection import open_link
from mavcal.testing.serial_cable import SerialCable
from mavcal.testing.vehicle import TestVehicle


def port(device, description="n/a", vid=None, pid=None, serial_number=None, product=None, hwid="n/a", location=None):
    return SimpleNamespace(device=device, description=description, hwid=hwid, vid=vid, pid=pid,
                           serial_number=serial_number, manufacturer=None, product=product, location=location)


TTYS0 = port("/dev/ttyS0")  # a motherboard UART: never a candidate
CUBE = port("/dev/ttyACM0", "CubeOrange", 0x2DAE, 0x1016, "3A0028", "CubeOrange", location="1-1:1.0")
CUBE_SLCAN = port("/dev/ttyACM1", "CubeOrange", 0x2DAE, 0x1016, "3A0028", "CubeOrange", location="1-1:1.2")
FMU_BY_ID = port("/dev/ttyACM2", "ArduPilot fmuv3", 0x1209, 0x5741, "42", "fmuv3")
SIK = port("/dev/ttyUSB0", "FT230X Basic UART", 0x0403, 0x6015, "DN0", "FT230X Basic UART")
BOOTLOADER = port("/dev/ttyACM3", "CubeOrange-BL", 0x2DAE, 0x1016, "77", "CubeOrange-BL_")
PRINTER = port("/dev/ttyUSB1", "USB2.0-Printer", 0x04B8, 0x0005)


def test_ranks():
    assert rank_port(PortInfo.of(CUBE)) == 2 and rank_port(PortInfo.of(FMU_BY_ID)) == 2
    assert rank_port(PortInfo.of(SIK)) == 1
    assert rank_port(PortInfo.of(PRINTER)) == 0
    assert rank_port(PortInfo.of(TTYS0)) is None
    # MAVProxy's patterns on a board without a known vendor id
    assert rank_port(PortInfo.of(port("/dev/ttyACM5", "Matek_H743 PX4 FMU", 0x1234, 0x1))) == 2


def test_the_autopilot_beats_the_radio_and_its_second_cdc_port_and_bootloader_count_not():
    assert [p.device for p in list_candidates([TTYS0, SIK, CUBE_SLCAN, CUBE, BOOTLOADER, PRINTER])] == ["/dev/ttyACM0"]
    assert find_port([TTYS0, SIK, CUBE, CUBE_SLCAN]).device == "/dev/ttyACM0"
    assert find_port([TTYS0, SIK, PRINTER]).device == "/dev/ttyUSB0"  # a radio alone
    assert find_port([PRINTER]).device == "/dev/ttyUSB1"  # any USB serial port, when nothing better


def test_several_autopilots_are_listed_and_none_is_said():
    with pytest.raises(AmbiguousPortError) as exc:
        find_port([CUBE, FMU_BY_ID, SIK])
    assert exc.value.exit_code == 10 and exc.value.ports == [PortInfo.of(CUBE).label(), PortInfo.of(FMU_BY_ID).label()]
    assert "/dev/ttyACM0 (CubeOrange, 2dae:1016)" in str(exc.value) and "--connect PORT" in str(exc.value)
    with pytest.raises(LinkError) as none:
        find_port([TTYS0])
    assert none.value.exit_code == 3 and "no serial port" in str(none.value)


@pytest.fixture()
def cabled():
    vehicle = TestVehicle("tcp", heartbeat_hz=2.0).start()
    cable = SerialCable(tcp_port=vehicle.port, baud=115200).start()
    try:
        yield vehicle, cable
    finally:
        cable.stop()
        vehicle.stop()


def _fake_ports(monkeypatch, ports):
    monkeypatch.setattr("serial.tools.list_ports.comports", lambda *a, **k: list(ports))


def test_auto_opens_the_one_autopilot_port(cabled, monkeypatch):
    vehicle, cable = cabled
    _fake_ports(monkeypatch, [TTYS0, SIK, port(cable.path, "fmuv3", 0x1209, 0x5741, "1", "fmuv3")])
    link = open_link("auto", baud=115200)
    try:
        assert link.device == cable.path and link.target_system == vehicle.sysid
    finally:
        link.close()


def test_apply_without_connect_finds_the_port_and_says_which(cabled, monkeypatch, tmp_path, capsys):
    vehicle, cable = cabled
    _fake_ports(monkeypatch, [TTYS0, port(cable.path, "CubeOrange", 0x2DAE, 0x1016, "9", "CubeOrange")])
    pfile = tmp_path / "c.param"
    pfile.write_text("COMPASS_OFS_X 12.5\n")
    rc = cli.main(["apply", str(pfile), "--yes", "--backup", str(tmp_path / "b.param")])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert f"--connect auto: {cable.path} (CubeOrange, 2dae:1016)" in cap.err
    assert vehicle.get_param("COMPASS_OFS_X") == float(np.float32(12.5))


def test_several_ports_exit_10_before_anything_opens(monkeypatch, tmp_path, capsys):
    _fake_ports(monkeypatch, [CUBE, FMU_BY_ID])
    pfile = tmp_path / "c.param"
    pfile.write_text("COMPASS_OFS_X 12.5\n")
    assert cli.main(["apply", str(pfile), "--yes"]) == 10
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "/dev/ttyACM0" in err[0] and "/dev/ttyACM2" in err[0] and "choose one" in err[0]
    # a bad file is still said first: nothing is looked for before the command's own checks
    assert cli.main(["apply", str(tmp_path / "missing.param"), "--yes"]) == 3
    assert "missing.param" in capsys.readouterr().err
