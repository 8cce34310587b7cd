"""A simulated Thorlabs FW102C/FW212C motorised filter wheel on a pseudo-terminal.

Open the simulator's :attr:`~labkit.sim._pty.PtySerialSimulator.port` with pyserial at
115200 8N1, exactly as a real USB-serial adapter::

    with FW102CSimulator(time_scale=0) as sim:
        with serial.Serial(sim.port, 115200, timeout=2) as ser:
            ser.write(b"pos=3\\r")
            ser.read_until(b"> ")   # b"pos=3\\r> "

Protocol reference: Thorlabs, "FW102C/FW212C Motorized Filter Wheel" user manual, Rev H
(2 October 2014), chapter 5 "Software Control", section 5.2 (command line interface,
115.2 kbaud 8N1 no flow control; ``keyword=argument`` commands and ``keyword?`` queries, all
lower case, terminated by CR; an incorrect keyword, format or argument returns an error
string; Enter on an empty line prints ``Command error CMD_NOT_DEFINED`` followed by the ``>``
prompt) and section 5.2.3 (keyword table: ``*idn?``, ``pos=n``/``pos?``,
``pcount=n``/``pcount?``, ``trig=0|1``/``trig?``, ``speed=0|1``/``speed?``,
``sensors=0|1``/``sensors?``, ``baud=0|1``/``baud?``, ``save``). The manual does not spell
out the reply framing byte by byte; the framing used here (echo + CR, answer + CR, prompt
``"> "`` without CR, prompt only after a move completes) is the one that published drivers
for the real device rely on.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator
from typing import ClassVar, Literal

from labkit.errors import ConfigError
from labkit.sim._pty import SliderSimulator
from labkit.sim.serial_protocol import ProtocolHandler, Reply, Wait

__all__ = ["FW102CHandler", "FW102CSimulator"]

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


class FW102CSimulator(SliderSimulator):
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

    def move_time(self, start: int, target: int, speed: int | None = None) -> float:
        """Duration of a move, s (see :meth:`FW102CHandler.move_time`)."""
        return self.handler.move_time(start, target, speed)
