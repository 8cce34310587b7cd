"""A simulated Thorlabs Elliptec ELL6 / ELL9 multi-position filter slider on a pseudo-terminal.

Open the simulator's :attr:`~labkit.sim._pty.PtySerialSimulator.port` with pyserial at
9600 8N1, exactly as a real USB-serial adapter::

    with ElliptecSimulator("ELL9", time_scale=0) as sim:
        with serial.Serial(sim.port, 9600, timeout=2) as ser:
            ser.write(b"0ma0000003E")       # no terminator
            ser.read_until(b"\\r\\n")         # b"0PO0000003E\\r\\n" (slot 3)

Protocol reference: Thorlabs, "ELLx modules protocol manual" (Elliptec resonant piezo motor
communication protocol, Issue 5, November 2019, and later issues), sections "Introduction"
and "Control Messages":

* 9600 baud, 8 data bits, no parity, 1 stop bit, no flow control (the interface board is a
  USB virtual COM port); ASCII text.
* Host to device: a one-character address (``0``-``9``, ``A``-``F``; ``0`` by default), a
  two-letter lower-case mnemonic, then the command's data as upper-case hex ASCII. There is
  no terminator: each command has a fixed length, which is how the device frames the stream.
  A command addressed to another device gets no reply.
* Device to host: the address, a two-letter upper-case mnemonic and the data, terminated by
  CR LF.
* ``in`` (``_DEVGET_INFORMATION``) -> ``IN`` + ELL type (2 hex: ``06`` ELL6, ``09`` ELL9) +
  serial number (8) + year of manufacture (4) + firmware release (2) + hardware release
  (2 hex; bit 7 set for imperial threads) + travel (4 hex) + pulses per measurement unit
  (8 hex). A published driver for a real ELL6K expects
  ``0IN061060005120170801001F00000000`` (travel 31, 0 pulses per unit).
* ``gs`` (``_HOSTREQ_STATUS``) -> ``GS`` + status code (2 hex): 00 OK, 01 communication time
  out, 02 mechanical time out, 03 command error or not supported, 04 value out of range,
  05 module isolated, 06 module out of isolation, 07 initialising error, 08 thermal error,
  09 busy, 0A sensor error, 0B motor error, 0C out of range (e.g. instructed to move
  beyond the travel), 0D over-current error.
* ``gp`` -> ``PO`` + position (8 hex, 32-bit two's complement, in pulses).
* ``ma`` + position (8 hex) moves to an absolute position, ``mr`` + offset (8 hex) by a
  relative one, ``fw`` / ``bw`` to the next / previous position of an indexed slider, and
  ``ho`` + direction (``0`` or ``1``) homes; each replies ``PO`` + the position when the
  move is over, or ``GS`` + an error code.

What the manual leaves open, and this simulator assumes:

* The slot positions in pulses. The default detents are 0, 31, 62 and 93 (0x00, 0x1F,
  0x3E, 0x5D), the experimentally determined positions of the Micro-Manager
  ``ThorlabsElliptecSlider`` adapter; other published drivers use 0, 32, 64, 96, so a
  client must map positions to the *nearest* slot. ``slot_positions`` sets other detents.
* An absolute or relative move goes to the detent nearest the requested position; a
  request more than half a slot pitch beyond the first or last detent, or ``fw`` at the
  last slot / ``bw`` at the first, answers ``GS0C`` (out of range) and does not move.
* The travel field of the ELL9 (not confirmed on a real device): 31, like the ELL6.
* The simulator answers one command at a time, so a status request sent during a move is
  answered after it (``GS00``), never ``GS09``; the ``"busy"`` fault produces ``GS09``.
* Malformed data (not hex) and unknown mnemonics answer ``GS03``; a ``ho`` direction other
  than ``0``/``1`` answers ``GS04``.
"""

from __future__ import annotations

import itertools
import re
from collections.abc import Callable, Iterator, Sequence
from typing import ClassVar

from labkit.errors import ConfigError
from labkit.sim._pty import SliderSimulator
from labkit.sim.serial_protocol import ProtocolHandler, Reply, Wait

__all__ = [
    "ELLIPTEC_MODELS",
    "SLOT_PITCH",
    "ElliptecFramer",
    "ElliptecHandler",
    "ElliptecSimulator",
]

#: Supported models: name -> (ELL type code as reported by ``in``, number of slots).
ELLIPTEC_MODELS: dict[str, tuple[int, int]] = {"ELL6": (0x06, 2), "ELL9": (0x09, 4)}

#: Default distance between two slots, pulses (0x1F).
SLOT_PITCH = 31

#: Status codes the simulator sends (see the module docstring for the full table).
_OK = 0x00
_MECHANICAL_TIMEOUT = 0x02
_COMMAND_ERROR = 0x03
_VALUE_OUT_OF_RANGE = 0x04
_BUSY = 0x09
_OUT_OF_RANGE = 0x0C

#: Length of the data that follows each mnemonic, characters; absent = no data.
_DATA_LENGTHS: dict[bytes, int] = {
    b"ma": 8,
    b"mr": 8,
    b"so": 8,
    b"sj": 8,
    b"ho": 1,
    b"ca": 1,
    b"sv": 2,
}
_ADDRESS_CHARS = frozenset(b"0123456789ABCDEF")
_HEX8 = re.compile(r"[0-9A-Fa-f]{8}")


def _signed32(value: int) -> int:
    """Interpret an unsigned 32-bit value as two's complement."""
    return value - (1 << 32) if value & 0x8000_0000 else value


class ElliptecFramer:
    """Frame Elliptec commands by their length (address + mnemonic + fixed-length data).

    Bytes that cannot start a command (anything but ``0``-``9``/``A``-``F``, e.g. a CR or
    LF some host programs append) are dropped, so the framer resynchronises on the next
    address character. An unknown mnemonic is taken to have no data.
    """

    def __init__(self) -> None:
        self._buffer = bytearray()

    def feed(self, data: bytes) -> list[bytes]:
        """Add received bytes; return the commands they complete.

        Parameters
        ----------
        data : bytes
            Bytes just read from the line.

        Returns
        -------
        list of bytes
            Complete commands (address, mnemonic and data), oldest first.
        """
        self._buffer += data
        commands: list[bytes] = []
        while self._buffer:
            if self._buffer[0] not in _ADDRESS_CHARS:
                del self._buffer[0]
                continue
            if len(self._buffer) < 3:
                break
            length = 3 + _DATA_LENGTHS.get(bytes(self._buffer[1:3]), 0)
            if len(self._buffer) < length:
                break
            commands.append(bytes(self._buffer[:length]))
            del self._buffer[:length]
        return commands


class ElliptecHandler(ProtocolHandler):
    """Protocol logic of a Thorlabs Elliptec ELL6 (2 slots) or ELL9 (4 slots) slider.

    Parameters
    ----------
    model : {"ELL6", "ELL9"}
        Device type; sets the ``in`` type code and the number of slots.
    address : int or str
        Bus address, 0-15 or one hex character.
    slot : int
        Initial slot, 1..number of slots (1 = the home end, position 0).
    slot_positions : sequence of int, optional
        Detent of each slot, pulses, strictly increasing; default ``0, 31, 62, …``.
    serial_number : str
        Eight characters reported by ``in``.
    year : int
        Year of manufacture reported by ``in``.
    firmware, hardware : int
        Firmware and hardware release bytes reported by ``in`` (hardware bit 7: imperial
        thread).
    travel : int
        Travel reported by ``in`` (mm).
    pulses_per_unit : int
        Pulses per measurement unit reported by ``in``.
    move_overhead : float
        Fixed part of a move (start-up, settling), s.
    move_per_slot : float
        Travel time per slot, s.
    time_scale : float
        Multiplies every move time; 0 makes moves instantaneous.
    on_move : callable, optional
        Called with the new slot after every completed move (also when the slot does not
        change; not for a faulted move), on the simulator thread and before the reply is
        sent, so a client that has the reply knows the callback has returned.

    Notes
    -----
    Extra fault kinds: ``"stuck"`` (the next move replies normally after the normal move
    time, but the slider stays put, so the ``PO`` reply carries the old position),
    ``"busy"`` (the next move answers ``GS09`` at once, without moving) and
    ``"mechanical_timeout"`` (the next move answers ``GS02`` after the move time, without
    moving). Each affects valid moves only.
    """

    fault_kinds: ClassVar[frozenset[str]] = frozenset({"stuck", "busy", "mechanical_timeout"})
    resync_suffix: ClassVar[bytes] = b"\r\n"

    def __init__(
        self,
        model: str = "ELL9",
        *,
        address: int | str = 0,
        slot: int = 1,
        slot_positions: Sequence[int] | None = None,
        serial_number: str = "11200456",
        year: int = 2019,
        firmware: int = 0x17,
        hardware: int = 0x01,
        travel: int = SLOT_PITCH,
        pulses_per_unit: int = 0,
        move_overhead: float = 0.15,
        move_per_slot: float = 0.3,
        time_scale: float = 1.0,
        on_move: Callable[[int], None] | None = None,
    ) -> None:
        super().__init__()
        if model not in ELLIPTEC_MODELS:
            raise ConfigError(
                f"unknown Elliptec model {model!r}; the simulator knows {sorted(ELLIPTEC_MODELS)}"
            )
        self.model = model
        self.type_code, slots = ELLIPTEC_MODELS[model]
        self.address = _address_char(address)
        if slot_positions is None:
            slot_positions = [SLOT_PITCH * i for i in range(slots)]
        positions = [int(p) for p in slot_positions]
        if len(positions) != slots:
            raise ConfigError(f"an {model} has {slots} slots; got {len(positions)} slot_positions")
        if any(b <= a for a, b in itertools.pairwise(positions)):
            raise ConfigError(f"slot_positions must increase strictly, got {positions}")
        if positions[0] < -(2**31) or positions[-1] >= 2**31:
            raise ConfigError(f"slot_positions must fit in 32 bits, got {positions}")
        if not 1 <= slot <= slots:
            raise ConfigError(f"initial slot must be in 1..{slots}, got {slot}")
        if len(serial_number) != 8 or not serial_number.isascii():
            raise ConfigError(f"serial_number must be 8 ASCII characters, got {serial_number!r}")
        for name, value, top in (
            ("year", year, 9999),
            ("firmware", firmware, 0xFF),
            ("hardware", hardware, 0xFF),
            ("travel", travel, 0xFFFF),
            ("pulses_per_unit", pulses_per_unit, 0xFFFF_FFFF),
        ):
            if not 0 <= value <= top:
                raise ConfigError(f"{name} must be in 0..{top}, got {value!r}")
        for name, seconds in (
            ("move_overhead", move_overhead),
            ("move_per_slot", move_per_slot),
            ("time_scale", time_scale),
        ):
            if not seconds >= 0:
                raise ConfigError(f"{name} must be >= 0, got {seconds!r}")
        self.slot_positions: tuple[int, ...] = tuple(positions)
        self._slot = slot
        self.serial_number = serial_number
        self.year = year
        self.firmware = firmware
        self.hardware = hardware
        self.travel = travel
        self.pulses_per_unit = pulses_per_unit
        self.move_overhead = move_overhead
        self.move_per_slot = move_per_slot
        self.time_scale = time_scale
        self.on_move = on_move

    # -- state, readable from any thread ------------------------------------------------------

    @property
    def slot_count(self) -> int:
        """Number of slots (2 for the ELL6, 4 for the ELL9)."""
        return len(self.slot_positions)

    @property
    def slot(self) -> int:
        """Current slot, 1..:attr:`slot_count`."""
        with self.lock:
            return self._slot

    @property
    def pulses(self) -> int:
        """Current position, pulses (the detent of the current slot)."""
        with self.lock:
            return self.slot_positions[self._slot - 1]

    def info_reply(self) -> str:
        """The ``in`` answer, without the CR LF (e.g. ``0IN0911200456…``)."""
        return (
            f"{self.address}IN{self.type_code:02X}{self.serial_number}{self.year:04d}"
            f"{self.firmware:02X}{self.hardware:02X}{self.travel:04X}{self.pulses_per_unit:08X}"
        )

    def move_time(self, start: int, target: int) -> float:
        """Duration of a move from slot `start` to slot `target`, s, including time_scale.

        Returns
        -------
        float
            ``(move_overhead + move_per_slot * |target - start|) * time_scale``; 0 when
            `start` equals `target`.
        """
        if start == target:
            return 0.0
        return (self.move_overhead + self.move_per_slot * abs(target - start)) * self.time_scale

    def nearest_slot(self, pulses: int) -> int | None:
        """The slot whose detent is nearest `pulses`, or None beyond the travel.

        A position is beyond the travel when it lies more than half the smallest slot
        pitch before the first detent or after the last one.
        """
        positions = self.slot_positions
        gaps = [b - a for a, b in itertools.pairwise(positions)]
        half = min(gaps) / 2 if gaps else SLOT_PITCH / 2
        if pulses < positions[0] - half or pulses > positions[-1] + half:
            return None
        distances = [abs(pulses - p) for p in positions]
        return distances.index(min(distances)) + 1

    # -- the protocol -------------------------------------------------------------------------

    def handle(self, command: str) -> Iterator[Reply]:
        """Answer one Elliptec command (see the module docstring for the protocol)."""
        if len(command) < 3 or command[0] != self.address:
            return  # another device's command (or noise): stay silent
        mnemonic, data = command[1:3], command[3:]
        if mnemonic == "in":
            yield self.info_reply().encode("ascii") + b"\r\n"
        elif mnemonic == "gs":
            yield self._status(_OK)
        elif mnemonic == "gp":
            yield self._position_reply()
        elif mnemonic in ("ma", "mr"):
            if not _HEX8.fullmatch(data):
                yield self._status(_COMMAND_ERROR)
                return
            requested = _signed32(int(data, 16))
            if mnemonic == "mr":
                requested += self.pulses
            yield from self._move(self.nearest_slot(requested))
        elif mnemonic in ("fw", "bw"):
            target = self.slot + (1 if mnemonic == "fw" else -1)
            yield from self._move(target if 1 <= target <= self.slot_count else None)
        elif mnemonic == "ho":
            if data not in ("0", "1"):
                yield self._status(_VALUE_OUT_OF_RANGE)
                return
            yield from self._move(1)
        else:
            yield self._status(_COMMAND_ERROR)

    def _move(self, target: int | None) -> Iterator[Reply]:
        """Move to slot `target` (None: out of range) and answer PO or GS."""
        if target is None:
            yield self._status(_OUT_OF_RANGE)
            return
        if self.faults.take("busy"):
            yield self._status(_BUSY)
            return
        start = self.slot
        delay = self.move_time(start, target)
        if self.faults.take("mechanical_timeout"):
            yield Wait(max(delay, self.move_overhead * self.time_scale))
            yield self._status(_MECHANICAL_TIMEOUT)
            return
        stuck = self.faults.take("stuck")
        if delay > 0:
            yield Wait(delay)
        if not stuck:
            with self.lock:
                self._slot = target
            if self.on_move is not None:
                self.on_move(target)
        yield self._position_reply()

    def _status(self, code: int) -> bytes:
        return f"{self.address}GS{code:02X}\r\n".encode("ascii")

    def _position_reply(self) -> bytes:
        return f"{self.address}PO{self.pulses & 0xFFFF_FFFF:08X}\r\n".encode("ascii")

    def make_framer(self) -> ElliptecFramer:
        """Return a new length-based framer (Elliptec commands have no terminator)."""
        return ElliptecFramer()


def _address_char(address: int | str) -> str:
    """Normalise a bus address (0-15 or one hex character) to its upper-case character."""
    if isinstance(address, bool):
        raise ConfigError(f"Elliptec address must be 0-15 or 0-F, got {address!r}")
    if isinstance(address, int):
        if not 0 <= address <= 15:
            raise ConfigError(f"Elliptec address must be 0-15, got {address}")
        return f"{address:X}"
    if isinstance(address, str) and len(address) == 1 and address.upper() in "0123456789ABCDEF":
        return address.upper()
    raise ConfigError(f"Elliptec address must be 0-15 or one hex character 0-F, got {address!r}")


class ElliptecSimulator(SliderSimulator):
    """A Thorlabs Elliptec ELL6 / ELL9 multi-position slider on a pseudo-terminal (9600 8N1).

    Parameters
    ----------
    model : {"ELL6", "ELL9"}
        Device type: 2 slots (ELL6) or 4 slots (ELL9).
    address : int or str
        Bus address, 0-15 or one hex character.
    slot : int
        Initial slot, 1 = the home end.
    slot_positions : sequence of int, optional
        Detent of each slot, pulses; default ``0, 31, 62, 93``. Set e.g. ``(0, 32, 64, 96)``
        to simulate a device whose positions read a few pulses off the nominal ones.
    move_overhead : float
        Fixed part of a move, s.
    move_per_slot : float
        Travel time per slot, s (so slot 1 -> 2 takes 0.45 s by default).
    time_scale : float
        Multiplies every move time; 0 makes moves instantaneous (for tests).
    on_move : callable, optional
        Called with the new slot after each completed move (see :class:`ElliptecHandler`).
    seed : int, optional
        Seed for the corruption of ``"garbled"`` replies.
    transcript_limit : int
        How many transcript events to keep.
    serial_number, year, firmware, hardware, travel, pulses_per_unit
        Fields of the ``in`` reply (see :class:`ElliptecHandler`).

    Notes
    -----
    Fault kinds: ``"no_reply"`` and ``"garbled"`` (see
    :meth:`~labkit.sim._pty.PtySerialSimulator.inject_fault`; a command for another address
    also consumes them), and ``"stuck"``, ``"busy"``, ``"mechanical_timeout"`` (see
    :class:`ElliptecHandler`).
    """

    handler: ElliptecHandler

    def __init__(
        self,
        model: str = "ELL9",
        *,
        address: int | str = 0,
        slot: int = 1,
        slot_positions: Sequence[int] | None = None,
        move_overhead: float = 0.15,
        move_per_slot: float = 0.3,
        time_scale: float = 1.0,
        on_move: Callable[[int], None] | None = None,
        seed: int | None = None,
        transcript_limit: int = 1000,
        serial_number: str = "11200456",
        year: int = 2019,
        firmware: int = 0x17,
        hardware: int = 0x01,
        travel: int = SLOT_PITCH,
        pulses_per_unit: int = 0,
    ) -> None:
        handler = ElliptecHandler(
            model,
            address=address,
            slot=slot,
            slot_positions=slot_positions,
            serial_number=serial_number,
            year=year,
            firmware=firmware,
            hardware=hardware,
            travel=travel,
            pulses_per_unit=pulses_per_unit,
            move_overhead=move_overhead,
            move_per_slot=move_per_slot,
            time_scale=time_scale,
            on_move=on_move,
        )
        super().__init__(handler, seed=seed, transcript_limit=transcript_limit)

    @property
    def position(self) -> int:
        """Current slot, 1..:attr:`slot_count` (thread-safe; like FW102CSimulator.position)."""
        return self.handler.slot

    @property
    def pulses(self) -> int:
        """Current position in pulses, as ``gp`` reports it."""
        return self.handler.pulses

    @property
    def slot_count(self) -> int:
        """Number of slots."""
        return self.handler.slot_count

    @property
    def slot_positions(self) -> tuple[int, ...]:
        """Detent of each slot, pulses."""
        return self.handler.slot_positions

    @property
    def model(self) -> str:
        """``"ELL6"`` or ``"ELL9"``."""
        return self.handler.model

    @property
    def address(self) -> str:
        """Bus address, one upper-case hex character."""
        return self.handler.address

    def move_time(self, start: int, target: int) -> float:
        """Duration of a move between two slots, s (see :meth:`ElliptecHandler.move_time`)."""
        return self.handler.move_time(start, target)
