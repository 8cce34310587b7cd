"""Driver of the Thorlabs Elliptec ELL6 / ELL9 multi-position filter sliders, over pyserial.

Protocol (Thorlabs "ELLx modules protocol manual"; summarised, with the simulator's
assumptions, in :mod:`labkit.sim.elliptec`): 9600 baud 8N1. A command is the device's
address (``0``-``F``), a two-letter lower-case mnemonic and fixed-length hex data, with no
terminator; a reply is the address, an upper-case mnemonic and hex data, ended by CR LF.
The driver uses ``in`` (identity, device type), ``ma`` + 8 hex (absolute move; the reply
``PO`` carries the position reached, ``GS`` an error status) and ``gp`` (read back).

Positions are in pulses. Slot *k* (1 = the home end) sits at ``(k - 1) * 31`` pulses, the
detents published drivers use (0x00, 0x1F, 0x3E, 0x5D); positions read back are mapped to
the *nearest* slot, because devices report positions a few pulses off.

Missing, malformed or foreign replies and the transient statuses (busy, communication or
mechanical time out) are retried, after re-synchronising (the input is drained until the
line is quiet), up to ``retries`` times in all; other statuses fail at once. Errors are one
:class:`~labkit.errors.DeviceError` line naming the port, the command and the last reply,
with the status code in words.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import serial

from labkit.devices._serial_slider import SerialSlider, attempts_text, show_reply
from labkit.devices.serial_ports import open_port
from labkit.errors import ConfigError, DeviceError

__all__ = [
    "SLIDER_MODELS",
    "SLOT_PITCH",
    "STATUS_MESSAGES",
    "Elliptec",
    "ElliptecInfo",
    "decode_position",
    "encode_position",
    "identify_elliptec",
    "nearest_slot",
    "parse_info",
    "status_text",
]

logger = logging.getLogger(__name__)

#: Meaning of the status codes of a ``GS`` reply (ELLx protocol manual, ``_HOSTREQ_STATUS``).
STATUS_MESSAGES: dict[int, str] = {
    0: "OK, no error",
    1: "communication time out",
    2: "mechanical time out",
    3: "command error or not supported",
    4: "value out of range",
    5: "module isolated",
    6: "module out of isolation",
    7: "initialising error",
    8: "thermal error",
    9: "busy",
    10: "sensor error",
    11: "motor error",
    12: "out of range",
    13: "over-current error",
}

#: Supported multi-position sliders: ELL type code -> (model name, number of slots).
SLIDER_MODELS: dict[int, tuple[str, int]] = {0x06: ("ELL6", 2), 0x09: ("ELL9", 4)}

#: Distance between two slots, pulses.
SLOT_PITCH = 31

#: Statuses worth another attempt: communication time out, mechanical time out, busy.
_TRANSIENT_STATUSES = frozenset({1, 2, 9})

_TERMINATOR = b"\r\n"
_HEX_CHARS = "0123456789ABCDEF"
_REPLY = re.compile(r"([0-9A-F])([A-Z]{2})([0-9A-Za-z]*)")


def status_text(code: int) -> str:
    """The meaning of a ``GS`` status code, e.g. ``status_text(2) == "mechanical time out"``."""
    return STATUS_MESSAGES.get(code, "reserved status code")


@dataclass(frozen=True)
class ElliptecInfo:
    """An Elliptec device's answer to ``in``.

    Attributes
    ----------
    address : str
        Bus address, one upper-case hex character.
    model_code : int
        ELL type (6 for the ELL6, 9 for the ELL9, 14 for the ELL14…).
    serial_number : str
        Eight characters.
    year : int
        Year of manufacture.
    firmware : str
        Firmware release, two hex characters.
    hardware : int
        Hardware release byte (bit 7 set: imperial thread).
    travel : int
        Travel, mm (or degrees for rotary devices).
    pulses_per_unit : int
        Pulses per mm (or per degree); 0 on indexed sliders.
    """

    address: str
    model_code: int
    serial_number: str
    year: int
    firmware: str
    hardware: int
    travel: int
    pulses_per_unit: int

    @property
    def model(self) -> str:
        """Model name, e.g. ``"ELL9"``."""
        return f"ELL{self.model_code}"

    @property
    def imperial(self) -> bool:
        """Whether the device has imperial threads."""
        return bool(self.hardware & 0x80)

    def __str__(self) -> str:
        return (
            f"Thorlabs Elliptec {self.model} serial {self.serial_number} at address "
            f"{self.address} ({self.year}, firmware {self.firmware}, hardware "
            f"{self.hardware & 0x7F})"
        )


def parse_info(reply: str) -> ElliptecInfo:
    """Parse the answer to ``in``.

    Parameters
    ----------
    reply : str
        E.g. ``"0IN061060005120170801001F00000000"`` (a trailing CR LF is ignored):
        address, ``IN``, type (2 hex), serial number (8), year (4 digits), firmware (2 hex),
        hardware (2 hex), travel (4 hex), pulses per unit (8 hex).

    Returns
    -------
    ElliptecInfo

    Raises
    ------
    ValueError
        If `reply` does not have that form.
    """
    text = reply.removesuffix("\r\n")
    fields = re.fullmatch(
        r"([0-9A-F])IN([0-9A-F]{2})(.{8})([0-9]{4})([0-9A-F]{2})([0-9A-F]{2})"
        r"([0-9A-F]{4})([0-9A-F]{8})",
        text,
    )
    if fields is None or not fields.group(3).isprintable():
        raise ValueError(f"not an Elliptec `in` reply: {reply!r}")
    address, model, serial_number, year, firmware, hardware, travel, pulses = fields.groups()
    return ElliptecInfo(
        address=address,
        model_code=int(model, 16),
        serial_number=serial_number,
        year=int(year),
        firmware=firmware,
        hardware=int(hardware, 16),
        travel=int(travel, 16),
        pulses_per_unit=int(pulses, 16),
    )


def encode_position(pulses: int) -> str:
    """A position as the protocol's 8 hex characters (32-bit two's complement).

    Examples
    --------
    >>> encode_position(62), encode_position(-1)
    ('0000003E', 'FFFFFFFF')
    """
    if not -(2**31) <= pulses < 2**31:
        raise ValueError(f"position {pulses} does not fit in 32 bits")
    return f"{pulses & 0xFFFF_FFFF:08X}"


def decode_position(data: str) -> int:
    """Decode 8 hex characters (32-bit two's complement) to pulses.

    Examples
    --------
    >>> decode_position("0000001F"), decode_position("FFFFFFFE")
    (31, -2)

    Raises
    ------
    ValueError
        If `data` is not 8 hex characters.
    """
    if len(data) != 8 or any(c not in _HEX_CHARS for c in data.upper()):
        raise ValueError(f"not an 8-character hex position: {data!r}")
    value = int(data, 16)
    return value - (1 << 32) if value & 0x8000_0000 else value


def nearest_slot(pulses: int, slot_positions: Sequence[int]) -> int:
    """The slot (1-based) whose position is nearest `pulses` (ties go to the lower slot).

    Examples
    --------
    >>> nearest_slot(33, [0, 31, 62, 93])
    2
    """
    if not slot_positions:
        raise ValueError("no slot positions")
    distances = [abs(pulses - position) for position in slot_positions]
    return distances.index(min(distances)) + 1


def _address_char(address: int | str) -> str:
    if isinstance(address, int) and not isinstance(address, bool) and 0 <= address <= 15:
        return _HEX_CHARS[address]
    if isinstance(address, str) and len(address) == 1 and address.upper() in _HEX_CHARS:
        return address.upper()
    raise ConfigError(f"Elliptec address must be 0-15 or one hex character 0-F, got {address!r}")


def _parse_packet(raw: bytes, address: str) -> tuple[str, str]:
    """Split a reply into (mnemonic, data); raise ValueError if it is not one from `address`."""
    if not raw.endswith(_TERMINATOR):
        raise ValueError("no CR LF (the reply is incomplete or missing)")
    try:
        text = raw[: -len(_TERMINATOR)].decode("ascii")
    except UnicodeDecodeError:
        raise ValueError("the reply is not ASCII") from None
    match = _REPLY.fullmatch(text)
    if match is None:
        raise ValueError("the reply is not address + mnemonic + data")
    sender, mnemonic, data = match.groups()
    if sender != address:
        raise ValueError(f"the reply comes from address {sender}, not {address}")
    if mnemonic == "PO":
        decode_position(data)
    elif mnemonic == "GS":
        if len(data) != 2 or any(c not in _HEX_CHARS for c in data):
            raise ValueError("the status is not 2 hex characters")
    elif mnemonic == "IN":
        parse_info(text)
    else:
        raise ValueError(f"unexpected reply {mnemonic!r}")
    return mnemonic, data


def _status_hint(code: int) -> str:
    if code in (1, 2, 9):
        return "check that the slider is not blocked and that nothing else drives it"
    if code in (4, 12):
        return "the slot is outside the slider's travel; check slider.positions in the rig file"
    if code == 3:
        return "the device does not support this command; check slider.driver and address"
    if code in (5, 6):
        return "the module is isolated; power-cycle it"
    return "power-cycle the slider; if the error persists, contact Thorlabs"


def identify_elliptec(ser: serial.Serial, *, addresses: str = "0") -> str | None:
    """Ask an open port for an Elliptec device's identification (``in``), for discovery.

    Parameters
    ----------
    ser : serial.Serial
        An open port (9600 baud) whose timeout bounds each read, s.
    addresses : str
        Bus addresses to ask, in order (hex characters).

    Returns
    -------
    str or None
        The identity of the first device that answers (see :class:`ElliptecInfo`), or None.
    """
    for char in addresses:
        address = _address_char(char)
        ser.reset_input_buffer()
        ser.write(f"{address}in".encode("ascii"))
        raw = ser.read_until(_TERMINATOR)
        try:
            mnemonic, _ = _parse_packet(raw, address)
        except ValueError:
            continue
        if mnemonic == "IN":
            return str(parse_info(raw.decode("ascii")))
    return None


class Elliptec(SerialSlider):
    """A Thorlabs Elliptec ELL6 (2 slots) or ELL9 (4 slots) slider (a :class:`FilterSlider`).

    Opening the port reads the device information (``in``); the device type gives the
    number of slots. Not thread-safe: use one instance from one thread.

    Parameters
    ----------
    port : str
        Serial port, e.g. ``/dev/ttyUSB0`` (or a simulator's ``/dev/pts/N``).
    address : int or str
        Bus address, 0-15 or one hex character (the rig file's ``slider.address``).
    slots : int, optional
        The highest slot the caller needs; opening fails if the slider has fewer. None: no
        check.
    timeout_s : float
        Longest wait for the reply to a query, s.
    retries : int
        How many times a command is tried before giving up (>= 1).
    move_timeout_s : float
        Longest wait for a move to finish, s.

    Raises
    ------
    ConfigError
        If an option is invalid.
    DeviceError
        If the port cannot be opened, the device does not answer, is not an ELL6/ELL9, or
        has fewer than `slots` slots.
    """

    driver: ClassVar[str] = "elliptec"
    baudrate: ClassVar[int] = 9600

    def __init__(
        self,
        port: str,
        *,
        address: int | str = 0,
        slots: int | None = None,
        timeout_s: float = 2.0,
        retries: int = 3,
        move_timeout_s: float = 5.0,
    ) -> None:
        for name, value in (("timeout_s", timeout_s), ("move_timeout_s", move_timeout_s)):
            if not value > 0:
                raise ConfigError(f"Elliptec {name} must be > 0 s, got {value!r}")
        if isinstance(retries, bool) or not isinstance(retries, int) or retries < 1:
            raise ConfigError(f"Elliptec retries must be an integer >= 1, got {retries!r}")
        if slots is not None and (isinstance(slots, bool) or not isinstance(slots, int)):
            raise ConfigError(f"Elliptec slots must be an integer or None, got {slots!r}")
        self.port = port
        self.address = _address_char(address)
        self.timeout_s = float(timeout_s)
        self.move_timeout_s = float(move_timeout_s)
        self.retries = retries
        self._serial: serial.Serial | None = open_port(
            port,
            baudrate=self.baudrate,
            timeout=timeout_s,
            write_timeout=timeout_s,
            exclusive=True,
        )
        try:
            self._serial.reset_input_buffer()
            _, raw = self._request("in", "IN")
            self.info = parse_info(raw.decode("ascii"))
            if self.info.model_code not in SLIDER_MODELS:
                raise DeviceError(
                    f"{self._where}: the device at address {self.address} is an "
                    f"{self.info.model}, not an ELL6/ELL9 multi-position slider; check "
                    "slider.driver and slider.address in the rig file"
                )
            _, count = SLIDER_MODELS[self.info.model_code]
            self.slot_positions: tuple[int, ...] = tuple(SLOT_PITCH * i for i in range(count))
            if slots is not None and slots > count:
                raise DeviceError(
                    f"{self._where}: slot {slots} is needed but the {self.info.model} has "
                    f"{count} slots; fix slider.positions in the rig file"
                )
        except BaseException:
            self.close()
            raise

    # -- FilterSlider -------------------------------------------------------------------------

    @property
    def identity(self) -> str:
        """E.g. ``Thorlabs Elliptec ELL9 serial 11200456 at address 0 (2019, …)``."""
        return str(self.info)

    @property
    def slot_count(self) -> int:
        """Number of slots: 2 (ELL6) or 4 (ELL9)."""
        return len(self.slot_positions)

    def position(self) -> int:
        """The current slot: the one nearest the position read back (``gp``).

        Raises
        ------
        DeviceError
            If the device does not answer validly within `retries` attempts.
        """
        pulses, _ = self._read_pulses()
        return nearest_slot(pulses, self.slot_positions)

    def move(self, slot: int) -> None:
        """Move to `slot` (``ma``), then verify it by reading the position back (``gp``).

        Parameters
        ----------
        slot : int
            Target slot, 1..:attr:`slot_count` (1 = the home end).

        Raises
        ------
        DeviceError
            If `slot` is out of range (nothing is sent), the device reports a non-transient
            error status, or after `retries` attempts it has not answered validly, is still
            busy or timed out, or its position does not read back as `slot`.
        """
        target = self._check_slot(slot)
        data = encode_position(self.slot_positions[target - 1])
        command = f"{self.address}ma{data}"
        problem = hint = ""
        for attempt in range(1, self.retries + 1):
            packet, raw = self._attempt("ma", data, self.move_timeout_s)
            shown = show_reply(raw, self.move_timeout_s)
            mnemonic, payload = packet if packet is not None else ("", "")
            status = int(payload, 16) if mnemonic == "GS" else 0
            if mnemonic == "GS" and status not in _TRANSIENT_STATUSES and status != 0:
                raise DeviceError(
                    f"{self._where}: `{command}` — device status {payload} "
                    f"({status_text(status)}) (reply {shown}); {_status_hint(status)}"
                )
            reached = pulses = None
            if mnemonic == "PO":  # the move is over: the reply holds the position reached
                pulses = decode_position(payload)
                reached = nearest_slot(pulses, self.slot_positions)
            if reached == target or (mnemonic == "GS" and status == 0):
                pulses, raw = self._read_pulses()  # verify
                shown = show_reply(raw, self.timeout_s)
                reached = nearest_slot(pulses, self.slot_positions)
                if reached == target:
                    return
            if reached is not None:
                problem = f"position reads back slot {reached} ({pulses} pulses)"
                hint = "check that the slider is not blocked"
            elif mnemonic == "GS":
                problem = f"device status {payload} ({status_text(status)})"
                hint = _status_hint(status)
                self._resync()
            else:
                problem, hint = "no valid reply", self._link_hint
            problem += f" after {attempts_text(attempt)} (last reply {shown})"
            logger.warning("%s: `%s` — %s", self._where, command, problem)
        raise DeviceError(f"{self._where}: `{command}` — {problem}; {hint}")

    def __repr__(self) -> str:
        state = "open" if self._serial is not None else "closed"
        return f"Elliptec(port={self.port!r}, address={self.address!r}, {state})"

    # -- the exchange -------------------------------------------------------------------------

    @property
    def _link_hint(self) -> str:
        return (
            f"check that the slider is powered and connected, that {self.port} is an "
            f"Elliptec bus at {self.baudrate} baud and that its address is {self.address}"
        )

    @property
    def _slot_range_note(self) -> str:
        return f" for the {self.info.model}"

    def _exchange(self, mnemonic: str, data: str, timeout_s: float) -> bytes:
        """Send one command; return what arrives up to CR LF or the timeout."""
        ser = self._serial_port()
        command = f"{self.address}{mnemonic}{data}"
        try:
            ser.write(command.encode("ascii"))
            ser.timeout = timeout_s
            return ser.read_until(_TERMINATOR)
        except serial.SerialException as exc:
            raise DeviceError(
                f"{self._where}: `{command}` — the serial port failed ({exc}); {self._link_hint}"
            ) from exc

    def _attempt(
        self, mnemonic: str, data: str, timeout_s: float
    ) -> tuple[tuple[str, str] | None, bytes]:
        """One exchange: (reply mnemonic, data), or None for a missing or malformed reply."""
        raw = self._exchange(mnemonic, data, timeout_s)
        try:
            return _parse_packet(raw, self.address), raw
        except ValueError as exc:
            logger.debug(
                "%s: `%s%s%s` — %s (reply %s)",
                self._where,
                self.address,
                mnemonic,
                data,
                exc,
                show_reply(raw, timeout_s),
            )
            self._resync()
            return None, raw

    def _request(self, mnemonic: str, expected: str) -> tuple[str, bytes]:
        """Send a query, retrying; return the data of the `expected` reply and the raw reply."""
        command = f"{self.address}{mnemonic}"
        problem = hint = ""
        for attempt in range(1, self.retries + 1):
            packet, raw = self._attempt(mnemonic, "", self.timeout_s)
            shown = show_reply(raw, self.timeout_s)
            if packet is not None and packet[0] == expected:
                return packet[1], raw
            if packet is not None and packet[0] == "GS":
                status = int(packet[1], 16)
                if status not in _TRANSIENT_STATUSES and status != 0:
                    raise DeviceError(
                        f"{self._where}: `{command}` — device status {packet[1]} "
                        f"({status_text(status)}) (reply {shown}); {_status_hint(status)}"
                    )
                problem = f"device status {packet[1]} ({status_text(status)})"
                hint = _status_hint(status)
            else:
                problem, hint = "no valid reply", self._link_hint
            if packet is not None:
                self._resync()
            problem += f" after {attempts_text(attempt)} (last reply {shown})"
            logger.warning("%s: `%s` — %s", self._where, command, problem)
        raise DeviceError(f"{self._where}: `{command}` — {problem}; {hint}")

    def _read_pulses(self) -> tuple[int, bytes]:
        data, raw = self._request("gp", "PO")
        return decode_position(data), raw
