"""Serial devices simulated on a pseudo-terminal: the protocol-agnostic machinery.

The simulator owns the master end of a pseudo-terminal (``os.openpty``); client code opens
the slave end (:attr:`PtySerialSimulator.port`, e.g. ``/dev/pts/5``) exactly as it would open
a real USB-serial adapter. Two layers:

* :class:`PtySerialSimulator` (here), a protocol-agnostic base: the pty, a daemon thread that
  reads bytes and frames them into commands, fault injection, and a bounded transcript.
* :class:`~labkit.sim.serial_protocol.ProtocolHandler` subclasses, which hold the protocol
  logic and its timing (:mod:`labkit.sim.serial_protocol` has the building blocks). A handler
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
from collections.abc import Callable
from typing import Literal

from labkit.errors import ConfigError, DeviceError
from labkit.sim.serial_protocol import (
    CR,
    LF,
    ProtocolHandler,
    TranscriptEntry,
    Wait,
)

__all__ = ["PtySerialSimulator", "SliderSimulator"]

logger = logging.getLogger(__name__)


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
        forbidden = {CR, LF, *suffix}
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
