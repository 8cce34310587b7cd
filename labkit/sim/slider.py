"""Simulated serial devices on a pseudo-terminal: a Thorlabs FW102C/FW212C filter wheel.

The simulator owns the master end of a pseudo-terminal (``os.openpty``); client code opens
the slave end (:attr:`PtySerialSimulator.port`, e.g. ``/dev/pts/5``) exactly as it would open
a real USB-serial adapter::

    with FW102CSimulator(time_scale=0) as sim:
        with serial.Serial(sim.port, 115200, timeout=2) as ser:
            ser.write(b"pos=3\\r")
            ser.read_until(b"> ")   # b"pos=3\\r> "

The module has two layers:

* :class:`PtySerialSimulator`, a protocol-agnostic base: the pty, a daemon thread that reads
  bytes and frames them into commands, fault injection, and a bounded transcript.
* :class:`ProtocolHandler` subclasses, which hold the protocol logic and its timing. A handler
  turns one command into a sequence of reply chunks (:class:`bytes`) and pauses
  (:class:`Wait`); the base writes the chunks and performs the pauses (interruptibly, so that
  :meth:`PtySerialSimulator.stop` is prompt even in the middle of a move). Framing (how bytes
  split into commands) is also the handler's choice, through :meth:`ProtocolHandler.make_framer`,
  because not every protocol is line based (Thorlabs Elliptec commands have no terminator).

Protocol reference for the FW102C/FW212C: Thorlabs, "FW102C/FW212C Motorized Filter Wheel"
user manual, Rev H (2 October 2014), chapter 5 "Software Control", section 5.2 (command line
interface, 115.2 kbaud 8N1 no flow control; ``keyword=argument`` commands and ``keyword?``
queries, all lower case, terminated by CR; an incorrect keyword, format or argument returns
an error string; Enter on an empty line prints ``Command error CMD_NOT_DEFINED`` followed by
the ``>`` prompt) and section 5.2.3 (keyword table: ``*idn?``, ``pos=n``/``pos?``,
``pcount=n``/``pcount?``, ``trig=0|1``/``trig?``, ``speed=0|1``/``speed?``,
``sensors=0|1``/``sensors?``, ``baud=0|1``/``baud?``, ``save``). The manual does not spell
out the reply framing byte by byte; the framing used here (echo + CR, answer + CR, prompt
``"> "`` without CR, prompt only after a move completes) is the one that published drivers
for the real device rely on.
"""

from __future__ import annotations

import collections
import contextlib
import errno
import logging
import os
import random
import re
import select
import threading
import time
import tty
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import ClassVar, Literal, NamedTuple, Protocol

from labkit.errors import ConfigError, DeviceError

__all__ = [
    "BASE_FAULT_KINDS",
    "FW102CHandler",
    "FW102CSimulator",
    "FaultInjector",
    "Framer",
    "LineFramer",
    "ProtocolHandler",
    "PtySerialSimulator",
    "TranscriptEntry",
    "Wait",
]

logger = logging.getLogger(__name__)

#: Fault kinds every simulator supports; handlers add their own (``"stuck"`` for the FW102C).
BASE_FAULT_KINDS: frozenset[str] = frozenset({"no_reply", "garbled"})

_CR = 0x0D
_LF = 0x0A


# --------------------------------------------------------------------------------------------
# Building blocks shared by every protocol
# --------------------------------------------------------------------------------------------


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
            if byte == _LF and self._after_cr:
                self._after_cr = False
                continue
            if byte in (_CR, _LF):
                self._after_cr = byte == _CR
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


# --------------------------------------------------------------------------------------------
# The transport: a pseudo-terminal and a thread
# --------------------------------------------------------------------------------------------


class PtySerialSimulator:
    """A serial device simulated on a pseudo-terminal, speaking `handler`'s protocol.

    Parameters
    ----------
    handler : ProtocolHandler
        The protocol logic.
    seed : int, optional
        Seed of the random generator used to corrupt ``"garbled"`` replies; with a fixed
        seed, the same exchanges produce the same corrupted bytes.
    transcript_limit : int
        How many :class:`TranscriptEntry` events to keep (oldest dropped first).
    poll_interval : float
        Longest time the thread blocks in ``select`` before checking for :meth:`stop`, s.
    write_timeout : float
        If the client does not drain its input for this long, s, the rest of a reply is
        dropped (a real device transmits into the void rather than stalling).

    Notes
    -----
    The slave end is put in raw mode (``tty.setraw``: no echo, no line editing, no CR/LF
    translation); any echo on the line comes from the protocol handler. The simulator keeps
    its own descriptor on the slave open, so clients may connect and disconnect repeatedly;
    bytes written while no client is connected wait in the pty, and pyserial discards them
    when it opens the port.

    The simulator can be started once; after :meth:`stop` create a new one.
    """

    def __init__(
        self,
        handler: ProtocolHandler,
        *,
        seed: int | None = None,
        transcript_limit: int = 1000,
        poll_interval: float = 0.05,
        write_timeout: float = 1.0,
    ) -> None:
        if transcript_limit < 0:
            raise ConfigError(f"transcript_limit must be >= 0, got {transcript_limit}")
        if not poll_interval > 0:
            raise ConfigError(f"poll_interval must be > 0 s, got {poll_interval}")
        if not write_timeout > 0:
            raise ConfigError(f"write_timeout must be > 0 s, got {write_timeout}")
        self.handler = handler
        self.poll_interval = poll_interval
        self.write_timeout = write_timeout
        self._rng = random.Random(seed)
        self._faults = handler.faults
        self._faults.on_fire = self._record_fault
        self._transcript: collections.deque[TranscriptEntry] = collections.deque(
            maxlen=transcript_limit
        )
        self._transcript_lock = threading.Lock()
        self._lock = threading.Lock()
        self._state: Literal["new", "running", "stopped"] = "new"
        self._stop_event = threading.Event()
        self._thread: threading.Thread | None = None
        self._master = -1
        self._slave = -1
        self._port: str | None = None
        self._error: BaseException | None = None
        self._error_reported = False

    # -- lifecycle ---------------------------------------------------------------------------

    @property
    def port(self) -> str:
        """Path of the slave device to open as a serial port, e.g. ``/dev/pts/5``.

        Raises
        ------
        DeviceError
            If the simulator has not been started.
        """
        if self._port is None:
            raise DeviceError(
                f"{type(self).__name__} has no port yet: call start() (or use it as a "
                "context manager) first"
            )
        return self._port

    @property
    def running(self) -> bool:
        """Whether the simulator thread is serving the port."""
        thread = self._thread
        return self._state == "running" and thread is not None and thread.is_alive()

    @property
    def error(self) -> BaseException | None:
        """The exception that killed the simulator thread, if any."""
        return self._error

    def start(self) -> PtySerialSimulator:
        """Open the pseudo-terminal and start serving it (no-op if already running).

        Returns
        -------
        PtySerialSimulator
            ``self``, for chaining.

        Raises
        ------
        DeviceError
            If the simulator was already stopped, or no pseudo-terminal can be opened.
        """
        with self._lock:
            if self._state == "running":
                return self
            if self._state == "stopped":
                raise DeviceError(
                    f"{type(self).__name__} was stopped and cannot be restarted; create a new one"
                )
            try:
                master, slave = os.openpty()
            except OSError as exc:
                raise DeviceError(f"could not open a pseudo-terminal: {exc}") from exc
            try:
                tty.setraw(slave)
                os.set_blocking(master, False)
                port = os.ttyname(slave)
            except OSError as exc:
                os.close(master)
                os.close(slave)
                raise DeviceError(f"could not set up the pseudo-terminal: {exc}") from exc
            self._master, self._slave, self._port = master, slave, port
            self._thread = threading.Thread(
                target=self._run, name=f"{type(self).__name__}({port})", daemon=True
            )
            self._state = "running"
            self._thread.start()
        return self

    def stop(self, timeout: float = 2.0) -> None:
        """Stop serving, join the thread and close the pseudo-terminal (idempotent).

        Safe while a client has the port open: a move in progress is abandoned, and the
        client's next read fails or times out.

        Parameters
        ----------
        timeout : float
            Longest wait for the thread to finish, s.

        Raises
        ------
        DeviceError
            If the thread does not finish within `timeout` (its descriptors are then closed
            when it does), or if it had died from an unexpected exception (reported once).
        """
        with self._lock:
            previous, self._state = self._state, "stopped"
        self._stop_event.set()
        thread = self._thread
        if thread is threading.current_thread():  # stop() from a callback: _run will clean up
            return
        if previous == "running" and thread is not None:
            thread.join(timeout)
            if thread.is_alive():
                raise DeviceError(
                    f"{type(self).__name__} thread did not stop within {timeout} s "
                    "(is an on_move callback blocking?)"
                )
        self._close_fds()
        if self._error is not None and not self._error_reported:
            self._error_reported = True
            raise DeviceError(
                f"{type(self).__name__} thread died: {self._error!r}"
            ) from self._error

    def __enter__(self) -> PtySerialSimulator:
        return self.start()

    def __exit__(self, *exc_info: object) -> None:
        self.stop()

    # -- faults and transcript ---------------------------------------------------------------

    @property
    def fault_kinds(self) -> frozenset[str]:
        """The fault kinds this simulator supports."""
        return self._faults.kinds

    def inject_fault(self, kind: str, count: int = 1) -> None:
        """Arm `count` faults of `kind`; they fire on the next commands and are consumed.

        Parameters
        ----------
        kind : str
            ``"no_reply"``: the next `count` commands are swallowed (not executed, nothing
            sent back). ``"garbled"``: the replies to the next `count` commands are
            replaced by corrupted bytes of the same length, then the handler's
            :attr:`~ProtocolHandler.resync_suffix` (the command is executed). Handlers may
            add kinds; see :attr:`fault_kinds`.
        count : int
            Number of commands affected; counts of the same kind add up.

        Raises
        ------
        ConfigError
            If `kind` is unknown or `count` is not a positive integer.
        """
        self._faults.inject(kind, count)

    def pending_faults(self) -> dict[str, int]:
        """Return the armed faults not yet fired, ``{kind: count}``."""
        return self._faults.pending()

    def clear_faults(self, kind: str | None = None) -> None:
        """Disarm pending faults of `kind`, or all when `kind` is None."""
        self._faults.clear(kind)

    def transcript(self) -> list[TranscriptEntry]:
        """Return a copy of the recorded events, oldest first."""
        with self._transcript_lock:
            return list(self._transcript)

    def clear_transcript(self) -> None:
        """Forget the recorded events."""
        with self._transcript_lock:
            self._transcript.clear()

    def _record(self, direction: Literal["rx", "tx", "fault"], data: bytes) -> None:
        with self._transcript_lock:
            self._transcript.append(TranscriptEntry(time.monotonic(), direction, data))

    def _record_fault(self, kind: str) -> None:
        self._record("fault", kind.encode("ascii", "replace"))

    # -- the thread --------------------------------------------------------------------------

    def _run(self) -> None:
        framer = self.handler.make_framer()
        try:
            while not self._stop_event.is_set():
                ready, _, _ = select.select([self._master], [], [], self.poll_interval)
                if not ready:
                    continue
                try:
                    data = os.read(self._master, 4096)
                except BlockingIOError:
                    continue
                except OSError as exc:
                    if exc.errno != errno.EIO:
                        raise
                    data = b""
                if not data:  # nobody on the slave side (cannot last: we hold it open)
                    self._stop_event.wait(self.poll_interval)
                    continue
                for command in framer.feed(data):
                    if self._stop_event.is_set():
                        break
                    self._process(command)
        except Exception as exc:
            self._error = exc
            logger.exception("%s thread died", type(self).__name__)
        finally:
            self._close_fds()

    def _process(self, command: bytes) -> None:
        self._record("rx", command)
        if self._faults.take("no_reply"):
            return
        garble = self._faults.take("garbled")
        held = bytearray()
        replies = iter(self.handler.handle(command.decode("latin-1")))
        try:
            for item in replies:
                if isinstance(item, Wait):
                    if item.seconds > 0 and self._stop_event.wait(item.seconds):
                        return
                elif garble:
                    held += item
                else:
                    self._send(item)
        finally:
            close = getattr(replies, "close", None)
            if close is not None:
                close()
        if garble:
            self._send(self._garble(bytes(held)))

    def _garble(self, reply: bytes) -> bytes:
        """Flip one random bit in every byte before the resync suffix.

        The corrupted bytes never contain CR, LF or a byte of the suffix, so the suffix that
        follows is the first place a client can resynchronise.
        """
        suffix = self.handler.resync_suffix
        if suffix and reply.endswith(suffix):
            body = reply[: -len(suffix)]
        else:
            body, suffix = reply, b""
        forbidden = {_CR, _LF, *suffix}
        if not body:
            body = b"\x00"
        out = bytearray()
        for byte in body:
            choices = [byte ^ (1 << bit) for bit in range(8)]
            out.append(self._rng.choice([c for c in choices if c not in forbidden]))
        return bytes(out) + suffix

    def _send(self, data: bytes) -> None:
        if not data:
            return
        self._record("tx", data)
        view = memoryview(data)
        deadline = time.monotonic() + self.write_timeout
        while view:
            try:
                written = os.write(self._master, view)
            except BlockingIOError:
                written = 0
            view = view[written:]
            if not view:
                break
            if self._stop_event.is_set() or time.monotonic() > deadline:
                logger.warning(
                    "%s: client is not reading; dropped %d reply bytes",
                    type(self).__name__,
                    len(view),
                )
                return
            select.select([], [self._master], [], self.poll_interval)

    def _close_fds(self) -> None:
        with self._lock:
            fds, self._master, self._slave = (self._master, self._slave), -1, -1
        for fd in fds:
            if fd >= 0:
                with contextlib.suppress(OSError):  # already closed by the OS: nothing to do
                    os.close(fd)


# --------------------------------------------------------------------------------------------
# Thorlabs FW102C / FW212C filter wheel
# --------------------------------------------------------------------------------------------

_FW_PROMPT = b"> "
_FW_NOT_DEFINED = "CMD_NOT_DEFINED"
_FW_ARG_INVALID = "CMD_ARG_INVALID"
_DIGITS = re.compile(r"[0-9]{1,3}")


class FW102CHandler(ProtocolHandler):
    """Protocol logic of a Thorlabs FW102C/FW212C motorised filter wheel.

    Every command is echoed with CR; a query answer follows with CR; an error is
    ``Command error CMD_NOT_DEFINED`` (unknown keyword, including upper case and empty
    lines) or ``Command error CMD_ARG_INVALID`` (bad or out-of-range argument) with CR;
    every reply ends with the prompt ``"> "`` (no CR). ``pos=n`` sends its echo at once and
    the prompt only when the move is over.

    Parameters
    ----------
    positions : {6, 12}
        Number of filter positions (``pcount``).
    position : int
        Initial position, 1..`positions`.
    speed : {0, 1}
        Initial speed mode: 0 slow, 1 high.
    trigger, sensors, baud : {0, 1}
        Initial values reported by ``trig?``, ``sensors?`` and ``baud?`` (they have no
        effect in the simulation; ``baud=`` does not change the pty).
    move_overhead : float
        Fixed part of a high-speed move (acceleration, settling), s.
    move_per_slot : float
        High-speed travel time per slot, s.
    slow_factor : float
        Slow-speed move time divided by high-speed move time.
    time_scale : float
        Multiplies every move time; 0 makes moves instantaneous.
    on_move : callable, optional
        Called with the new position after every successful ``pos=`` (also when the target
        equals the current position; not for a ``"stuck"`` move), on the simulator thread
        and before the prompt is sent, so a client that has seen the prompt knows the
        callback has returned.
    idn : str
        Answer to ``*idn?``.

    Notes
    -----
    The wheel turns the shortest way round: on a 12-position wheel 1 -> 12 is one slot.
    Changing ``pcount`` to fewer positions than the current one re-homes the simulated wheel
    to position 1 (calling `on_move`).
    """

    fault_kinds: ClassVar[frozenset[str]] = frozenset({"stuck"})
    resync_suffix: ClassVar[bytes] = _FW_PROMPT

    DEFAULT_IDN: ClassVar[str] = "THORLABS FW102C/FW212C Filter Wheel version 1.07"

    def __init__(
        self,
        positions: int = 12,
        *,
        position: int = 1,
        speed: int = 1,
        trigger: int = 0,
        sensors: int = 0,
        baud: int = 1,
        move_overhead: float = 0.25,
        move_per_slot: float = 0.2,
        slow_factor: float = 2.0,
        time_scale: float = 1.0,
        on_move: Callable[[int], None] | None = None,
        idn: str = DEFAULT_IDN,
    ) -> None:
        super().__init__()
        if positions not in (6, 12):
            raise ConfigError(f"an FW102C/FW212C wheel has 6 or 12 positions, not {positions}")
        if not 1 <= position <= positions:
            raise ConfigError(f"initial position must be in 1..{positions}, got {position}")
        for name, value in (("speed", speed), ("trigger", trigger), ("sensors", sensors)):
            if value not in (0, 1):
                raise ConfigError(f"{name} must be 0 or 1, got {value!r}")
        if baud not in (0, 1):
            raise ConfigError(f"baud must be 0 (9600) or 1 (115200), got {baud!r}")
        for name, value in (
            ("move_overhead", move_overhead),
            ("move_per_slot", move_per_slot),
            ("slow_factor", slow_factor),
            ("time_scale", time_scale),
        ):
            if not value >= 0:
                raise ConfigError(f"{name} must be >= 0, got {value!r}")
        self._positions = positions
        self._position = position
        self._settings = {"speed": speed, "trig": trigger, "sensors": sensors, "baud": baud}
        self.move_overhead = move_overhead
        self.move_per_slot = move_per_slot
        self.slow_factor = slow_factor
        self.time_scale = time_scale
        self.on_move = on_move
        self.idn = idn

    # -- state, readable from any thread ------------------------------------------------------

    @property
    def position(self) -> int:
        """Current filter position, 1..:attr:`positions`."""
        with self.lock:
            return self._position

    @property
    def positions(self) -> int:
        """Number of filter positions (6 or 12)."""
        with self.lock:
            return self._positions

    @property
    def speed(self) -> int:
        """Speed mode: 0 slow, 1 high."""
        with self.lock:
            return self._settings["speed"]

    @staticmethod
    def slots_between(start: int, target: int, positions: int) -> int:
        """Number of slots the wheel turns from `start` to `target`, the shortest way round."""
        forward = (target - start) % positions
        return min(forward, positions - forward)

    def move_time(self, start: int, target: int, speed: int | None = None) -> float:
        """Duration of a move from `start` to `target`, s, including :attr:`time_scale`.

        Parameters
        ----------
        start, target : int
            Positions, 1..:attr:`positions`.
        speed : {0, 1}, optional
            Speed mode; the current one when omitted.

        Returns
        -------
        float
            ``(move_overhead + move_per_slot * slots) * time_scale``, times
            :attr:`slow_factor` at slow speed; 0 when `start` equals `target`.
        """
        with self.lock:
            positions = self._positions
            if speed is None:
                speed = self._settings["speed"]
        slots = self.slots_between(start, target, positions)
        if slots == 0:
            return 0.0
        seconds = self.move_overhead + self.move_per_slot * slots
        if speed == 0:
            seconds *= self.slow_factor
        return seconds * self.time_scale

    # -- the protocol -------------------------------------------------------------------------

    def handle(self, command: str) -> Iterator[Reply]:
        """Answer one FW102C command (see the class docstring for the reply format)."""
        yield command.encode("latin-1") + b"\r"
        kind, value = self._dispatch(command)
        if kind == "move":
            target = int(value)
            start = self.position
            stuck = self.faults.take("stuck")
            delay = self.move_time(start, target)
            if delay > 0:
                yield Wait(delay)
            if not stuck:
                with self.lock:
                    self._position = target
                if self.on_move is not None:
                    self.on_move(target)
        elif kind == "answer":
            yield value.encode("latin-1") + b"\r"
        elif kind == "error":
            yield f"Command error {value}\r".encode("ascii")
        elif kind == "rehome" and self.on_move is not None:
            self.on_move(1)
        yield _FW_PROMPT

    def _dispatch(
        self, command: str
    ) -> tuple[Literal["ok", "answer", "error", "move", "rehome"], str]:
        """Execute everything but the move itself; say what to send back."""
        if command == "*idn?":
            return "answer", self.idn
        if command == "save":
            return "ok", ""
        if command.endswith("?"):
            key = command[:-1]
            with self.lock:
                if key == "pos":
                    return "answer", str(self._position)
                if key == "pcount":
                    return "answer", str(self._positions)
                if key in self._settings:
                    return "answer", str(self._settings[key])
            return "error", _FW_NOT_DEFINED
        key, equals, argument = command.partition("=")
        if not equals or key not in ("pos", "pcount", *self._settings):
            return "error", _FW_NOT_DEFINED
        if not _DIGITS.fullmatch(argument):
            return "error", _FW_ARG_INVALID
        number = int(argument)
        with self.lock:
            if key == "pos":
                if not 1 <= number <= self._positions:
                    return "error", _FW_ARG_INVALID
                return "move", str(number)
            if key == "pcount":
                if number not in (6, 12):
                    return "error", _FW_ARG_INVALID
                self._positions = number
                if self._position > number:
                    self._position = 1
                    return "rehome", ""
                return "ok", ""
            if number not in (0, 1):
                return "error", _FW_ARG_INVALID
            self._settings[key] = number
            return "ok", ""


class FW102CSimulator(PtySerialSimulator):
    """A Thorlabs FW102C/FW212C filter wheel on a pseudo-terminal (115200 8N1, CR).

    Parameters
    ----------
    positions : {6, 12}
        Number of filter positions (``pcount?``).
    position : int
        Initial position.
    speed : {0, 1}
        Initial speed mode: 0 slow, 1 high.
    move_overhead : float
        Fixed part of a high-speed move, s.
    move_per_slot : float
        High-speed travel time per slot, s (so 1 -> 2 takes 0.45 s by default).
    slow_factor : float
        Slow-speed move time divided by high-speed move time.
    time_scale : float
        Multiplies every move time; 0 makes moves instantaneous (for tests).
    on_move : callable, optional
        Called with the new position after each completed ``pos=`` (see
        :class:`FW102CHandler`).
    idn : str
        Answer to ``*idn?``.
    seed : int, optional
        Seed for the corruption of ``"garbled"`` replies.
    transcript_limit : int
        How many transcript events to keep.

    Notes
    -----
    Fault kinds: ``"no_reply"`` and ``"garbled"`` (see
    :meth:`PtySerialSimulator.inject_fault`), and ``"stuck"``: the next `count` valid
    ``pos=`` commands reply normally, after the normal move time, but the wheel does not
    turn and `on_move` is not called; ``pos?`` reports the old position.
    """

    handler: FW102CHandler

    def __init__(
        self,
        positions: int = 12,
        *,
        position: int = 1,
        speed: int = 1,
        move_overhead: float = 0.25,
        move_per_slot: float = 0.2,
        slow_factor: float = 2.0,
        time_scale: float = 1.0,
        on_move: Callable[[int], None] | None = None,
        idn: str = FW102CHandler.DEFAULT_IDN,
        seed: int | None = None,
        transcript_limit: int = 1000,
    ) -> None:
        handler = FW102CHandler(
            positions,
            position=position,
            speed=speed,
            move_overhead=move_overhead,
            move_per_slot=move_per_slot,
            slow_factor=slow_factor,
            time_scale=time_scale,
            on_move=on_move,
            idn=idn,
        )
        super().__init__(handler, seed=seed, transcript_limit=transcript_limit)

    @property
    def position(self) -> int:
        """Current filter position (thread-safe)."""
        return self.handler.position

    @property
    def positions(self) -> int:
        """Number of filter positions, as set by the constructor or ``pcount=``."""
        return self.handler.positions

    @property
    def speed(self) -> int:
        """Speed mode: 0 slow, 1 high."""
        return self.handler.speed

    @property
    def on_move(self) -> Callable[[int], None] | None:
        """Callback invoked with the new position after each completed move."""
        return self.handler.on_move

    @on_move.setter
    def on_move(self, callback: Callable[[int], None] | None) -> None:
        self.handler.on_move = callback

    def move_time(self, start: int, target: int, speed: int | None = None) -> float:
        """Duration of a move, s (see :meth:`FW102CHandler.move_time`)."""
        return self.handler.move_time(start, target, speed)
