"""What the serial slider drivers share: the port's lifetime, slot checks, draining, wording."""

from __future__ import annotations

import abc
import contextlib
from typing import Self

import serial

from labkit.errors import DeviceError

#: Most reads of a drain (each waits for the line to be quiet), so that a device that never
#: stops talking cannot hold the driver forever.
MAX_DRAIN_READS = 50


def show_reply(reply: bytes, timeout_s: float) -> str:
    """A reply for an error message: its repr, or that none came."""
    if not reply:
        return f"none within {timeout_s:g} s"
    return repr(reply.decode("latin-1"))


def attempts_text(count: int) -> str:
    """``1 attempt`` / ``N attempts``."""
    return "1 attempt" if count == 1 else f"{count} attempts"


class SerialSlider(abc.ABC):
    """Base of the pyserial slider drivers.

    Subclasses set ``port``, ``timeout_s`` and ``_serial`` (an open :class:`serial.Serial`)
    in their constructor and provide ``slot_count`` and ``_link_hint``.
    """

    port: str
    timeout_s: float
    _serial: serial.Serial | None

    @property
    @abc.abstractmethod
    def slot_count(self) -> int:
        """Number of slots (the driver reads it from the device)."""

    @property
    @abc.abstractmethod
    def _link_hint(self) -> str:
        """What to check when the device does not answer, for error messages."""

    @property
    def _quiet_s(self) -> float:
        """How long the line must stay silent for a drain to end, s."""
        return min(0.05, self.timeout_s / 4)

    @property
    def _where(self) -> str:
        return f"filter slider on {self.port}"

    @property
    def _slot_range_note(self) -> str:
        """Added after the valid slot range in out-of-range errors (e.g. the model)."""
        return ""

    def close(self) -> None:
        """Release the serial port (idempotent)."""
        ser, self._serial = self._serial, None
        if ser is not None:
            with contextlib.suppress(serial.SerialException, OSError):  # already gone: fine
                ser.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _check_slot(self, slot: int) -> int:
        if isinstance(slot, bool) or not isinstance(slot, int):
            raise DeviceError(f"{self._where}: slot must be an integer, got {slot!r}")
        if not 1 <= slot <= self.slot_count:
            raise DeviceError(
                f"{self._where}: slot {slot} is out of range 1..{self.slot_count}"
                f"{self._slot_range_note}; use a position number of the rig file's "
                "slider.positions"
            )
        return slot

    def _serial_port(self) -> serial.Serial:
        if self._serial is None:
            raise DeviceError(
                f"{self._where} is closed; open a new {type(self).__name__} to use it"
            )
        return self._serial

    def _resync(self) -> None:
        """Discard what the device is still sending: drain the input until the line is quiet."""
        ser = self._serial_port()
        try:
            ser.reset_input_buffer()
            ser.timeout = self._quiet_s
            for _ in range(MAX_DRAIN_READS):
                if not ser.read(max(1, ser.in_waiting)):  # returns at the first byte
                    break
        except serial.SerialException as exc:
            raise DeviceError(f"{self._where}: reading failed ({exc}); {self._link_hint}") from exc
