"""Serial protocols for the pty simulators: the building blocks every protocol shares.

A :class:`ProtocolHandler` holds a device's protocol logic and timing: it turns one command
into reply chunks (:class:`bytes`) and pauses (:class:`Wait`), and chooses how bytes split
into commands (a :class:`Framer`; :class:`LineFramer` for line-based protocols). A
:class:`FaultInjector` holds the faults a test has asked for; :class:`TranscriptEntry` is
one line of what went over the wire. The transport that runs a handler on a
pseudo-terminal is :class:`labkit.sim._pty.PtySerialSimulator`.
"""

from __future__ import annotations

import threading
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import ClassVar, Literal, NamedTuple, Protocol

from labkit.errors import ConfigError

__all__ = [
    "BASE_FAULT_KINDS",
    "CR",
    "LF",
    "FaultInjector",
    "Framer",
    "LineFramer",
    "ProtocolHandler",
    "Reply",
    "TranscriptEntry",
    "Wait",
]

#: Fault kinds every simulator supports; handlers add their own (``"stuck"`` for the FW102C).
BASE_FAULT_KINDS: frozenset[str] = frozenset({"no_reply", "garbled"})

#: Carriage return: ends a command of a line-based protocol (:class:`LineFramer`); a
#: garbled reply never contains it.
CR = 0x0D
#: Line feed: ends a command too (CR LF is one end); a garbled reply never contains it.
LF = 0x0A


@dataclass(frozen=True)
class Wait:
    """A pause in a reply, yielded by :meth:`ProtocolHandler.handle`.

    Attributes
    ----------
    seconds : float
        How long to pause before the next reply chunk, s. Non-positive values do not pause.
    """

    seconds: float


#: One item of a handler's reply: bytes to send, or a pause.
Reply = bytes | Wait


class TranscriptEntry(NamedTuple):
    """One event of a simulator transcript.

    Attributes
    ----------
    time : float
        ``time.monotonic()`` when the event happened, s.
    direction : {"rx", "tx", "fault"}
        ``"rx"``: one complete command received from the client (terminator excluded);
        ``"tx"``: bytes written to the client; ``"fault"``: an injected fault fired (`data`
        is its kind, ASCII).
    data : bytes
        The bytes concerned.
    """

    time: float
    direction: Literal["rx", "tx", "fault"]
    data: bytes


class Framer(Protocol):
    """Splits the received byte stream into commands."""

    def feed(self, data: bytes) -> list[bytes]:
        """Add received bytes; return the commands they complete, terminators removed."""
        ...


class LineFramer:
    """Frame commands terminated by CR, LF or CR LF.

    A CR immediately followed by LF counts as one terminator, even when the two bytes arrive
    in different reads, so ``b"pos?\\r\\n"`` is one command, not a command and an empty one.
    A bare terminator yields an empty command (a real FW102C answers that with
    ``CMD_NOT_DEFINED``).

    Parameters
    ----------
    max_length : int
        A command that grows to this many bytes without a terminator is handed on as it is
        (the handler will normally reject it), so a client that never sends CR cannot make
        the buffer grow without bound.
    """

    def __init__(self, max_length: int = 256) -> None:
        if max_length < 1:
            raise ConfigError(f"LineFramer max_length must be >= 1, got {max_length}")
        self.max_length = max_length
        self._buffer = bytearray()
        self._after_cr = False

    def feed(self, data: bytes) -> list[bytes]:
        """Add received bytes; return the commands they complete, terminators removed.

        Parameters
        ----------
        data : bytes
            Bytes just read from the line.

        Returns
        -------
        list of bytes
            Complete commands, oldest first.
        """
        commands: list[bytes] = []
        for byte in data:
            if byte == LF and self._after_cr:
                self._after_cr = False
                continue
            if byte in (CR, LF):
                self._after_cr = byte == CR
                commands.append(bytes(self._buffer))
                self._buffer.clear()
                continue
            self._after_cr = False
            self._buffer.append(byte)
            if len(self._buffer) >= self.max_length:
                commands.append(bytes(self._buffer))
                self._buffer.clear()
        return commands


class FaultInjector:
    """Thread-safe book of pending faults, consumed as they fire.

    Parameters
    ----------
    kinds : iterable of str
        The fault kinds this device supports.
    on_fire : callable, optional
        Called with the kind each time a fault fires (the simulator uses it for its
        transcript).
    """

    def __init__(self, kinds: Iterable[str], on_fire: Callable[[str], None] | None = None) -> None:
        self.kinds: frozenset[str] = frozenset(kinds)
        self.on_fire = on_fire
        self._pending: dict[str, int] = {}
        self._lock = threading.Lock()

    def inject(self, kind: str, count: int = 1) -> None:
        """Arm `count` more faults of `kind` (added to any already pending).

        Parameters
        ----------
        kind : str
            One of :attr:`kinds`.
        count : int
            How many commands (or moves, for ``"stuck"``) the fault affects; >= 1.

        Raises
        ------
        ConfigError
            If `kind` is unknown or `count` is not a positive integer.
        """
        if kind not in self.kinds:
            raise ConfigError(
                f"unknown fault kind {kind!r}; this device supports {sorted(self.kinds)}"
            )
        if isinstance(count, bool) or not isinstance(count, int) or count < 1:
            raise ConfigError(f"fault count must be a positive integer, got {count!r}")
        with self._lock:
            self._pending[kind] = self._pending.get(kind, 0) + count

    def take(self, kind: str) -> bool:
        """Consume one pending fault of `kind`; return whether one was pending."""
        with self._lock:
            left = self._pending.get(kind, 0)
            if left <= 0:
                return False
            if left == 1:
                del self._pending[kind]
            else:
                self._pending[kind] = left - 1
        if self.on_fire is not None:
            self.on_fire(kind)
        return True

    def pending(self) -> dict[str, int]:
        """Return a copy of the pending faults, ``{kind: count}``."""
        with self._lock:
            return dict(self._pending)

    def clear(self, kind: str | None = None) -> None:
        """Disarm pending faults of `kind`, or all of them when `kind` is None."""
        with self._lock:
            if kind is None:
                self._pending.clear()
            else:
                self._pending.pop(kind, None)


class ProtocolHandler(ABC):
    """Protocol logic of a simulated serial device, independent of the transport.

    Subclasses implement :meth:`handle` and may override :meth:`make_framer`,
    :attr:`fault_kinds` and :attr:`resync_suffix`. :meth:`handle` runs on the simulator
    thread, one command at a time; state that other threads read must be guarded by
    :attr:`lock`.

    Attributes
    ----------
    fault_kinds : frozenset of str
        Device-specific fault kinds, on top of :data:`BASE_FAULT_KINDS`. The handler checks
        them itself with ``self.faults.take(kind)``.
    resync_suffix : bytes
        Bytes that end every complete reply and let a client resynchronise (the FW102C
        prompt ``b"> "``). A ``"garbled"`` fault corrupts everything before it and keeps it.
    faults : FaultInjector
        The pending faults; shared with the simulator that owns this handler.
    lock : threading.Lock
        Guards the handler's state.
    """

    fault_kinds: ClassVar[frozenset[str]] = frozenset()
    resync_suffix: ClassVar[bytes] = b""

    def __init__(self) -> None:
        self.faults = FaultInjector(BASE_FAULT_KINDS | self.fault_kinds)
        self.lock = threading.Lock()

    def make_framer(self) -> Framer:
        """Return a new framer for the incoming byte stream (default: CR/LF lines)."""
        return LineFramer()

    @abstractmethod
    def handle(self, command: str) -> Iterable[Reply]:
        """Answer one command.

        Parameters
        ----------
        command : str
            The command, terminator removed, decoded as Latin-1 (so every byte maps to one
            character and back).

        Returns
        -------
        iterable of bytes or Wait
            Reply chunks, written in order, and pauses between them. A generator is
            closed early (``GeneratorExit`` at a pause) when the simulator stops.
        """
