"""Serial devices simulated on a pseudo-terminal: the protocol-agnostic machinery.

The simulator owns the master end of a pseudo-terminal (``os.openpty``); client code opens
the slave end (:attr:`PtySerialSimulator.port`, e.g. ``/dev/pts/5``) exactly as it would open
a real USB-serial adapter. Two layers:

* :class:`PtySerialSimulator`, a protocol-agnostic base: the pty, a daemon thread that reads
  bytes and frames them into commands, fault injection, and a bounded transcript.
* :class:`ProtocolHandler` subclasses, which hold the protocol logic and its timing. A handler
  turns one command into a sequence of reply chunks (:class:`bytes`) and pauses
  (:class:`Wait`); the base writes the chunks and performs the pauses (interruptibly, so that
  :meth:`PtySerialSimulator.stop` is prompt even in the middle of a move). Framing (how bytes
  split into commands) is also the handler's choice, through :meth:`ProtocolHandler.make_framer`,
  because not every protocol is line based (Thorlabs Elliptec commands have no terminator).

The devices themselves live in :mod:`labkit.sim.fw102c` (Thorlabs FW102C/FW212C filter wheel)
and :mod:`labkit.sim.elliptec` (Thorlabs Elliptec ELL6/ELL9 multi-position sliders).
"""

from __future__ import annotations

import collections
import contextlib
import errno
import logging
import os
import random
import select
import threading
import time
import tty
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import ClassVar, Literal, NamedTuple, Protocol

from labkit.errors import ConfigError, DeviceError

__all__ = [
    "BASE_FAULT_KINDS",
    "FaultInjector",
    "Framer",
    "LineFramer",
    "ProtocolHandler",
    "PtySerialSimulator",
    "Reply",
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
        Longest time the thread blocks in ``select`` before checking for :meth:`stop`, s
        (a safety net: :meth:`stop` also wakes the thread through a pipe).
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
        self._wake_read = -1  # a pipe whose write end stop() uses to wake the thread
        self._wake_write = -1
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
                wake_read, wake_write = os.pipe()
            except OSError as exc:
                os.close(master)
                os.close(slave)
                raise DeviceError(f"could not set up the pseudo-terminal: {exc}") from exc
            os.set_blocking(wake_write, False)
            self._master, self._slave, self._port = master, slave, port
            self._wake_read, self._wake_write = wake_read, wake_write
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
            if self._wake_write >= 0:  # under the lock: _close_fds cannot close it meanwhile
                with contextlib.suppress(OSError):  # pipe full: the thread is awake anyway
                    os.write(self._wake_write, b"\0")
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
                ready, _, _ = select.select(
                    [self._master, self._wake_read], [], [], self.poll_interval
                )
                if self._master not in ready:
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
        if garble and held:  # nothing to corrupt when the device stays silent
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
            select.select([self._wake_read], [self._master], [], self.poll_interval)

    def _close_fds(self) -> None:
        with self._lock:
            fds = (self._master, self._slave, self._wake_read, self._wake_write)
            self._master = self._slave = self._wake_read = self._wake_write = -1
        for fd in fds:
            if fd >= 0:
                with contextlib.suppress(OSError):  # already closed by the OS: nothing to do
                    os.close(fd)


class SliderSimulator(PtySerialSimulator):
    """A simulated filter slider: its handler moves between slots and reports each move."""

    @property
    def on_move(self) -> Callable[[int], None] | None:
        """Callback invoked with the new slot after each completed move."""
        return self.handler.on_move

    @on_move.setter
    def on_move(self, callback: Callable[[int], None] | None) -> None:
        self.handler.on_move = callback
