"""Tests of serial-port listing and opening with clear errors."""

from __future__ import annotations

import errno

import pytest
import serial

from labkit.devices import serial_ports
from labkit.devices.serial_ports import SerialPortInfo, list_serial_ports, open_port
from labkit.errors import DeviceError
from labkit.sim.fw102c import FW102CSimulator


def test_list_serial_ports_sorted_with_descriptions(fake_ports: None) -> None:
    assert list_serial_ports() == [
        SerialPortInfo("/dev/ttyS0", "n/a", "n/a"),
        SerialPortInfo("/dev/ttyUSB0", "FT230X Basic UART", "USB VID:PID"),
    ]
    assert str(list_serial_ports()[1]) == "/dev/ttyUSB0 (FT230X Basic UART)"


def test_list_serial_ports_on_this_machine() -> None:
    ports = list_serial_ports()
    assert all(isinstance(port, SerialPortInfo) and port.device for port in ports)
    assert [port.device for port in ports] == sorted(port.device for port in ports)


def test_missing_port_lists_the_ports_found(fake_ports: None) -> None:
    with pytest.raises(DeviceError) as caught:
        open_port("/dev/ttyUSB9", baudrate=9600)
    assert str(caught.value) == (
        "serial port /dev/ttyUSB9 does not exist (ports found: /dev/ttyS0, /dev/ttyUSB0); "
        "check the cable or set slider.port in the rig file"
    )


def test_missing_port_when_there_are_none(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(serial_ports.list_ports, "comports", list)
    with pytest.raises(DeviceError, match=r"\(ports found: none\)"):
        open_port("/dev/ttyUSB9")


def test_permission_denied_says_how_to_fix(monkeypatch: pytest.MonkeyPatch) -> None:
    def deny(port: str, **kwargs: object) -> None:
        raise serial.SerialException(errno.EACCES, f"could not open port {port}: Permission")

    monkeypatch.setattr(serial_ports.serial, "Serial", deny)
    with pytest.raises(DeviceError) as caught:
        open_port("/dev/ttyUSB0")
    message = str(caught.value)
    assert message.startswith("permission denied opening serial port /dev/ttyUSB0;")
    assert "dialout" in message


def test_port_in_use_is_reported() -> None:
    with FW102CSimulator(time_scale=0) as sim:
        with open_port(sim.port, baudrate=115200, exclusive=True) as first:
            assert first.is_open
            with pytest.raises(DeviceError) as caught:
                open_port(sim.port, baudrate=115200, exclusive=True)
    assert str(caught.value).startswith(f"serial port {sim.port} is in use by another program;")


def test_bad_setting_is_a_device_error(silent_port: str) -> None:
    with pytest.raises(DeviceError, match=f"serial port {silent_port}: invalid setting"):
        open_port(silent_port, baudrate=-5)
