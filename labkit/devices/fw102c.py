"""Driver of the Thorlabs FW102C / FW212C motorised filter wheel, over pyserial.

Protocol (Thorlabs FW102C/FW212C manual Rev H, section 5.2; simulated by
:mod:`labkit.sim.fw102c`): 115200 baud 8N1, lower-case ``keyword=value`` commands and
``keyword?`` queries terminated by CR. The wheel echoes every command followed by CR, sends
the answer of a query followed by CR (or ``Command error …`` followed by CR), then the prompt
``"> "``; after ``pos=n`` the prompt comes only when the move is over.

Every exchange reads up to the prompt with a serial timeout (no busy waiting). A reply that
does not arrive, does not start with the echo of the command, or has the wrong shape is
retried, after re-synchronising (the input is drained until the line is quiet), up to
``retries`` times in all; then a :class:`~labkit.errors.DeviceError` names the port, the
command and the last reply.
"""

from __future__ import annotations

import logging
from typing import ClassVar

import serial

from labkit.devices._serial_slider import SerialSlider, attempts_text, show_reply
from labkit.devices.serial_ports import open_port
from labkit.errors import ConfigError, DeviceError

__all__ = ["FW102C", "PROMPT", "MalformedReply", "identify_fw102c", "parse_reply"]

logger = logging.getLogger(__name__)

#: The wheel's prompt: ends every reply.
PROMPT = b"> "


class MalformedReply(ValueError):
    """A reply that is incomplete or does not have the expected shape (retried)."""


def parse_reply(command: str, reply: bytes) -> list[str]:
    """Split a complete FW102C reply into its answer lines.

    Parameters
    ----------
    command : str
        The command that was sent, without its CR (e.g. ``"pos?"``).
    reply : bytes
        Everything read up to and including the prompt (e.g. ``b"pos?\\r3\\r> "``).

    Returns
    -------
    list of str
        The lines between the echo and the prompt: ``[]`` for a setting (``pos=3``), one
        line for a query (``["3"]``) or an error (``["Command error CMD_ARG_INVALID"]``).

    Raises
    ------
    MalformedReply
        If the prompt is missing (timeout), the echo does not match `command`, or the
        lines are not printable ASCII (a corrupted reply).
    """
    echo = command.encode("ascii") + b"\r"
    if not reply.endswith(PROMPT):
        raise MalformedReply("no prompt (the reply is incomplete or missing)")
    if not reply.startswith(echo):
        raise MalformedReply("the reply does not start with the echo of the command")
    body = reply[len(echo) : -len(PROMPT)]
    if not body:
        return []
    if not body.endswith(b"\r"):
        raise MalformedReply("the answer is not terminated by CR")
    try:
        lines = body[:-1].decode("ascii").split("\r")
    except UnicodeDecodeError:
        raise MalformedReply("the answer is not ASCII") from None
    if not all(line.isprintable() for line in lines):
        raise MalformedReply("the answer holds control characters")
    return lines


def identify_fw102c(ser: serial.Serial) -> str | None:
    """Ask an open port for an FW102C's identification (``*idn?``), for discovery.

    Sends a bare CR first (it ends whatever partial line the wheel holds; the wheel answers
    it with ``Command error CMD_NOT_DEFINED``), then ``*idn?``.

    Parameters
    ----------
    ser : serial.Serial
        An open port (115200 baud) whose timeout bounds each read, s.

    Returns
    -------
    str or None
        The identification string, or None when no FW102C answers.
    """
    ser.reset_input_buffer()
    ser.write(b"\r*idn?\r")
    received = b""
    for _ in range(3):  # the empty line's reply, then the *idn? reply
        chunk = ser.read_until(PROMPT)
        received += chunk
        if not chunk.endswith(PROMPT):
            return None
        start = received.rfind(b"*idn?\r")
        if start < 0:
            continue
        try:
            lines = parse_reply("*idn?", received[start:])
        except MalformedReply:
            return None
        if len(lines) == 1 and lines[0] and not lines[0].startswith("Command error"):
            return lines[0]
        return None
    return None


class FW102C(SerialSlider):
    """A Thorlabs FW102C / FW212C filter wheel on a serial port (a :class:`FilterSlider`).

    Opening the port reads the wheel's identification (``*idn?``) and number of positions
    (``pcount?``). Not thread-safe: use one instance from one thread.

    Parameters
    ----------
    port : str
        Serial port, e.g. ``/dev/ttyUSB0`` (or a simulator's ``/dev/pts/N``).
    slots : int, optional
        The highest slot the caller needs (e.g. the largest position number in the rig
        file); opening fails if the wheel has fewer positions. None: no check.
    timeout_s : float
        Longest wait for the reply to a query, s.
    retries : int
        How many times a command is tried before giving up (>= 1).
    baudrate : int
        115200 (factory setting) or 9600 (after ``baud=0``).
    move_timeout_s : float
        Longest wait for a move to finish, s (a 6-slot move at slow speed takes about 3 s).

    Raises
    ------
    ConfigError
        If an option is invalid.
    DeviceError
        If the port cannot be opened, the wheel does not answer, or it has fewer than
        `slots` positions.

    Examples
    --------
    >>> with FW102C("/dev/ttyUSB0", slots=8) as wheel:  # doctest: +SKIP
    ...     wheel.move(3)
    ...     wheel.position()
    3
    """

    driver: ClassVar[str] = "fw102c"

    def __init__(
        self,
        port: str,
        *,
        slots: int | None = None,
        timeout_s: float = 2.0,
        retries: int = 3,
        baudrate: int = 115200,
        move_timeout_s: float = 5.0,
    ) -> None:
        for name, value in (("timeout_s", timeout_s), ("move_timeout_s", move_timeout_s)):
            if not value > 0:
                raise ConfigError(f"FW102C {name} must be > 0 s, got {value!r}")
        if isinstance(retries, bool) or not isinstance(retries, int) or retries < 1:
            raise ConfigError(f"FW102C retries must be an integer >= 1, got {retries!r}")
        if slots is not None and (isinstance(slots, bool) or not isinstance(slots, int)):
            raise ConfigError(f"FW102C slots must be an integer or None, got {slots!r}")
        self.port = port
        self.timeout_s = float(timeout_s)
        self.move_timeout_s = float(move_timeout_s)
        self.retries = retries
        self.baudrate = baudrate
        self._serial: serial.Serial | None = open_port(
            port, baudrate=baudrate, timeout=timeout_s, write_timeout=timeout_s, exclusive=True
        )
        try:
            self._start_clean()
            self._identity, _ = self._query("*idn?")
            answer, reply = self._query("pcount?")
            if not answer.isdigit() or int(answer) < 1:
                raise DeviceError(
                    f"{self._where}: `pcount?` — unexpected answer (reply {show_reply(reply, 0)}); "
                    f"check that {port} is an FW102C/FW212C"
                )
            self._slot_count = int(answer)
            if slots is not None and slots > self._slot_count:
                raise DeviceError(
                    f"{self._where}: slot {slots} is needed but the wheel has "
                    f"{self._slot_count} positions (pcount?); fix slider.positions in the rig "
                    "file, or set the wheel type with `pcount=12` (FW212C)"
                )
        except BaseException:
            self.close()
            raise

    # -- FilterSlider -------------------------------------------------------------------------

    @property
    def identity(self) -> str:
        """The wheel's answer to ``*idn?``, e.g. ``THORLABS FW102C/FW212C Filter Wheel …``."""
        return self._identity

    @property
    def slot_count(self) -> int:
        """Number of positions (``pcount?``): 6 (FW102C) or 12 (FW212C)."""
        return self._slot_count

    def position(self) -> int:
        """The current slot, read from the wheel (``pos?``).

        Raises
        ------
        DeviceError
            If the wheel does not answer validly within `retries` attempts.
        """
        answer, reply = self._query("pos?")
        return self._parse_position(answer, reply)

    def move(self, slot: int) -> None:
        """Move to `slot` (``pos=n``), wait for the prompt, and verify it with ``pos?``.

        Parameters
        ----------
        slot : int
            Target slot, 1..:attr:`slot_count`.

        Raises
        ------
        DeviceError
            If `slot` is out of range (nothing is sent), the wheel rejects the command, or
            after `retries` attempts the wheel has not answered validly or its position
            does not read back as `slot` (the message names port, command and last reply).
        """
        target = self._check_slot(slot)
        command = f"pos={target}"
        problem = hint = ""
        for attempt in range(1, self.retries + 1):
            lines, reply = self._attempt(command, self.move_timeout_s)
            if lines == []:
                answer, reply = self._query("pos?")
                reached = self._parse_position(answer, reply)
                if reached == target:
                    return
                problem = f"position reads back {reached}"
                hint = "check that the wheel is not blocked"
                shown = show_reply(reply, self.timeout_s)
            else:
                if lines:  # an answer where none belongs
                    self._resync()
                problem = "no valid reply" if lines is None else "unexpected answer"
                hint = self._link_hint
                shown = show_reply(reply, self.move_timeout_s)
            problem += f" after {attempts_text(attempt)} (last reply {shown})"
            logger.warning("%s: `%s` — %s", self._where, command, problem)
        raise DeviceError(f"{self._where}: `{command}` — {problem}; {hint}")

    def __repr__(self) -> str:
        state = "open" if self._serial is not None else "closed"
        return f"FW102C(port={self.port!r}, {state})"

    # -- the exchange -------------------------------------------------------------------------

    @property
    def _link_hint(self) -> str:
        return (
            f"check that the wheel is powered and connected and that {self.port} is an "
            f"FW102C at {self.baudrate} baud"
        )

    def _parse_position(self, answer: str, reply: bytes) -> int:
        if answer.isdigit() and 1 <= int(answer) <= self._slot_count:
            return int(answer)
        raise DeviceError(
            f"{self._where}: `pos?` — position {answer!r} is not in 1..{self._slot_count} "
            f"(reply {show_reply(reply, self.timeout_s)}); check that {self.port} is an FW102C"
        )

    def _write(self, data: bytes, command: str) -> None:
        try:
            self._serial_port().write(data)
        except serial.SerialException as exc:
            raise DeviceError(
                f"{self._where}: `{command}` — writing failed ({exc}); {self._link_hint}"
            ) from exc

    def _exchange(self, command: str, timeout_s: float) -> bytes:
        """Send `command` once; return what arrives up to the prompt or the timeout."""
        ser = self._serial_port()
        self._write(command.encode("ascii") + b"\r", command)
        try:
            ser.timeout = timeout_s
            return ser.read_until(PROMPT)
        except serial.SerialException as exc:
            raise DeviceError(
                f"{self._where}: `{command}` — reading failed ({exc}); {self._link_hint}"
            ) from exc

    def _attempt(self, command: str, timeout_s: float) -> tuple[list[str] | None, bytes]:
        """One exchange: the answer lines, or None for a missing or malformed reply.

        A malformed reply is followed by a re-synchronisation; ``Command error`` raises.
        """
        reply = self._exchange(command, timeout_s)
        try:
            lines = parse_reply(command, reply)
        except MalformedReply as exc:
            logger.debug(
                "%s: `%s` — %s (reply %s)", self._where, command, exc, show_reply(reply, timeout_s)
            )
            self._resync()
            return None, reply
        if lines and lines[0].startswith("Command error"):
            raise DeviceError(
                f"{self._where}: `{command}` — the wheel answered {lines[0]!r} (reply "
                f"{show_reply(reply, timeout_s)}); check the slot against the wheel's position "
                "count (pcount?) and the rig file"
            )
        return lines, reply

    def _query(self, command: str) -> tuple[str, bytes]:
        """Ask a one-line query, retrying; return the answer and the raw reply."""
        reply = b""
        for attempt in range(1, self.retries + 1):
            lines, reply = self._attempt(command, self.timeout_s)
            if lines is not None and len(lines) == 1:
                return lines[0], reply
            if lines is not None:
                self._resync()
            logger.warning(
                "%s: `%s` — no valid reply after %s (last reply %s)",
                self._where,
                command,
                attempts_text(attempt),
                show_reply(reply, self.timeout_s),
            )
        raise DeviceError(
            f"{self._where}: `{command}` — no valid reply after {attempts_text(self.retries)} "
            f"(last reply {show_reply(reply, self.timeout_s)}); {self._link_hint}"
        )

    def _start_clean(self) -> None:
        """End any partial line the wheel holds (a bare CR) and discard the answer to it."""
        ser = self._serial_port()
        self._write(b"\r", "(empty line)")
        try:
            ser.timeout = self.timeout_s
            ser.read_until(PROMPT)  # "Command error CMD_NOT_DEFINED" and the prompt
            ser.reset_input_buffer()
        except serial.SerialException as exc:
            raise DeviceError(f"{self._where}: reading failed ({exc}); {self._link_hint}") from exc
