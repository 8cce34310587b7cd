"""Tests of serial-port listing, opening with clear errors, and slider discovery (probe)."""

from __future__ import annotations

import errno
import os
import tty
from collections.abc import Iterator
from types import SimpleNamespace

import pytest
import serial

from labkit.devices import serial_ports
from labkit.devices.serial_ports import SerialPortInfo, list_serial_ports, open_port, probe
from labkit.errors import DeviceError
from labkit.sim.elliptec import ElliptecSimulator
from labkit.sim.fw102c import FW102CSimulator

FAKE_PORTS = [
    SimpleNamespace(device="/dev/ttyUSB0", description="FT230X Basic UART", hwid="USB VID:PID"),
    SimpleNamespace(device="/dev/ttyS0", description="", hwid=""),
]


@pytest.fixture
def fake_ports(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(serial_ports.list_ports, "comports", lambda: list(FAKE_PORTS))


@pytest.fixture
def silent_port() -> Iterator[str]:
    """A pseudo-terminal nobody answers on."""
    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        yield os.ttyname(slave)
    finally:
        os.close(master)
        os.close(slave)


# -- listing and opening ----------------------------------------------------------------------


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


# -- probe ------------------------------------------------------------------------------------


def test_probe_identifies_the_fw102c() -> None:
    moves: list[int] = []
    with FW102CSimulator(time_scale=0, on_move=moves.append) as sim:
        assert probe(sim.port, timeout_s=0.3) == (
            "fw102c",
            "THORLABS FW102C/FW212C Filter Wheel version 1.07",
        )
        assert (sim.position, moves) == (1, [])


@pytest.mark.parametrize(("model", "address"), [("ELL9", "0"), ("ELL6", "5")])
def test_probe_identifies_the_elliptec(model: str, address: str) -> None:
    moves: list[int] = []
    with ElliptecSimulator(model, address=address, time_scale=0, on_move=moves.append) as sim:
        found = probe(sim.port, timeout_s=0.2, addresses="05")
        assert (sim.position, moves) == (1, [])
    assert found == (
        "elliptec",
        f"Thorlabs Elliptec {model} serial 11200456 at address {address} "
        "(2019, firmware 17, hardware 1)",
    )


def test_probe_silent_port_is_none(silent_port: str) -> None:
    assert probe(silent_port, timeout_s=0.2) is None


def test_probe_elliptec_at_an_address_not_asked_is_none() -> None:
    with ElliptecSimulator("ELL9", address=7, time_scale=0) as sim:
        assert probe(sim.port, timeout_s=0.2) is None


def test_probe_missing_port_raises(fake_ports: None) -> None:
    with pytest.raises(DeviceError, match="serial port /dev/ttyUSB7 does not exist"):
        probe("/dev/ttyUSB7")
