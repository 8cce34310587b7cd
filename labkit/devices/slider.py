"""The filter-slider interface every driver implements (fw102c, elliptec, sim)."""

from __future__ import annotations

from typing import Protocol, runtime_checkable


@runtime_checkable
class FilterSlider(Protocol):
    """A motorised filter wheel or slider with numbered slots.

    Slots are numbered as the device numbers them (FW102C: 1..N; Elliptec: 1..N from
    the home end). :meth:`move` blocks until the move is done and the read-back
    position equals the target, retrying a bounded number of times; it raises
    DeviceError naming the port, the command and the last reply otherwise.
    """

    port: str

    @property
    def identity(self) -> str:
        """The device's identification string."""
        ...

    @property
    def slot_count(self) -> int:
        """Number of slots."""
        ...

    def position(self) -> int:
        """The current slot, read from the device."""
        ...

    def move(self, slot: int) -> None:
        """Move to `slot` and verify it by reading the position back."""
        ...

    def close(self) -> None:
        """Release the serial port."""
        ...

    def __enter__(self) -> FilterSlider: ...

    def __exit__(self, *exc: object) -> None: ...
