"""Which filter slider answers on a serial port: the discovery behind ``labkit devices``.

:func:`probe` asks a port, in turn, in the FW102C protocol (115200 baud) and the Elliptec
protocol (9600 baud) and reports whichever answers. It sits above the drivers, whose
identification requests it uses, and below nothing of theirs.
"""

from __future__ import annotations

from labkit.devices.elliptec import identify_elliptec
from labkit.devices.fw102c import identify_fw102c
from labkit.devices.serial_ports import open_port
from labkit.errors import DeviceError

__all__ = ["probe"]


def probe(port: str, *, timeout_s: float = 0.5, addresses: str = "0") -> tuple[str, str] | None:
    """Find which filter-slider protocol answers on `port`.

    Tries the FW102C protocol (``*idn?`` at 115200 baud), then the Elliptec protocol (``in``
    at 9600 baud, at each of `addresses`). Nothing is moved.

    Parameters
    ----------
    port : str
        Path of the serial port.
    timeout_s : float
        Longest wait for each answer, s; a silent port takes about
        ``timeout_s * (1 + len(addresses))`` in all.
    addresses : str
        Elliptec bus addresses to ask, hex characters (``"0123456789ABCDEF"`` for all).

    Returns
    -------
    tuple of (str, str) or None
        ``(driver, identity)``: driver ``"fw102c"`` or ``"elliptec"`` (the rig file's
        ``slider.driver``) and the device's identification; None when neither answers.

    Raises
    ------
    DeviceError
        If the port cannot be opened (see :func:`open_port`).
    """
    if not timeout_s > 0:
        raise DeviceError(f"probe of {port}: timeout_s must be > 0 s, got {timeout_s!r}")
    options = {"timeout": timeout_s, "write_timeout": timeout_s, "exclusive": True}
    with open_port(port, baudrate=115200, **options) as ser:
        identity = identify_fw102c(ser)
    if identity is not None:
        return "fw102c", identity
    with open_port(port, baudrate=9600, **options) as ser:
        identity = identify_elliptec(ser, addresses=addresses)
    if identity is not None:
        return "elliptec", identity
    return None
