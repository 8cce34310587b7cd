"""Serial ports: list them, and open one with a clear error.

:func:`open_port` is how every labkit serial driver opens its port: a missing, busy or
forbidden port becomes one :class:`~labkit.errors.DeviceError` line that names the port, says
what is wrong and how to fix it. Which slider answers on a port is
:func:`labkit.devices.slider_probe.probe`, a layer above the drivers.
"""

from __future__ import annotations

import errno
import os
from dataclasses import dataclass
from typing import Any

import serial
from serial.tools import list_ports

from labkit.errors import DeviceError

__all__ = ["SerialPortInfo", "list_serial_ports", "open_port"]


@dataclass(frozen=True)
class SerialPortInfo:
    """A serial port found on this machine.

    Attributes
    ----------
    device : str
        Path to open, e.g. ``/dev/ttyUSB0``.
    description : str
        What the system says it is, e.g. ``FT230X Basic UART`` (``n/a`` when unknown).
    hwid : str
        Hardware id, e.g. ``USB VID:PID=0403:6015 SER=DK0AHAJZ``.
    """

    device: str
    description: str = "n/a"
    hwid: str = "n/a"

    def __str__(self) -> str:
        return f"{self.device} ({self.description})"


def list_serial_ports() -> list[SerialPortInfo]:
    """The serial ports of this machine (``serial.tools.list_ports``), sorted by path.

    Returns
    -------
    list of SerialPortInfo
        One entry per port; empty when there are none. Pseudo-terminals (simulators) are
        not listed.
    """
    ports = [
        SerialPortInfo(
            device=info.device,
            description=info.description or "n/a",
            hwid=info.hwid or "n/a",
        )
        for info in list_ports.comports()
    ]
    return sorted(ports, key=lambda port: port.device)


def _ports_found() -> str:
    """The found ports as a short comma-separated list, for error messages."""
    try:
        devices = [port.device for port in list_serial_ports()]
    except OSError:  # best effort: the message must still be produced
        devices = []
    return ", ".join(devices) if devices else "none"


def open_port(port: str, **serial_kwargs: Any) -> serial.Serial:
    """Open a serial port with pyserial, turning failures into one-line DeviceErrors.

    Parameters
    ----------
    port : str
        Path of the port, e.g. ``/dev/ttyUSB0`` (or a simulator's ``/dev/pts/N``).
    **serial_kwargs
        Passed to :class:`serial.Serial` (``baudrate``, ``timeout`` in s, ``exclusive``…).

    Returns
    -------
    serial.Serial
        The open port.

    Raises
    ------
    DeviceError
        If the port does not exist (the message lists the ports found), may not be opened
        (permissions), is locked by another program, or rejects the settings.
    """
    try:
        return serial.Serial(port, **serial_kwargs)
    except serial.SerialException as exc:
        raise DeviceError(_open_error(port, exc)) from exc
    except (ValueError, TypeError) as exc:  # pyserial's answer to a bad setting
        raise DeviceError(
            f"serial port {port}: invalid setting ({exc}); check the serial options"
        ) from exc


def _open_error(port: str, exc: serial.SerialException) -> str:
    """One line saying why `port` could not be opened and what to do about it."""
    code = exc.errno if isinstance(exc.errno, int) else None
    if code == errno.ENOENT or (code is None and not os.path.exists(port)):
        return (
            f"serial port {port} does not exist (ports found: {_ports_found()}); "
            "check the cable or set slider.port in the rig file"
        )
    if code in (errno.EACCES, errno.EPERM):
        return (
            f"permission denied opening serial port {port}; add your user to the group "
            f"that owns it (usually 'dialout': sudo usermod -aG dialout $USER, then log in "
            "again)"
        )
    if code in (errno.EBUSY, errno.EAGAIN, errno.EWOULDBLOCK):
        return (
            f"serial port {port} is in use by another program; close it (or the other "
            "labkit session) and try again"
        )
    reason = " ".join(str(exc).split())
    return (
        f"could not open serial port {port}: {reason} (ports found: {_ports_found()}); "
        "check the cable and slider.port in the rig file"
    )
