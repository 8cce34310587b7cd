"""The camera interface every backend implements (aravis, genicam, sim).

The protocol runner only ever talks to a :class:`Camera`; backends translate it into
their library's calls. Units: seconds for exposure in this API (µs only at the GenICam
feature boundary), dB for gain.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Protocol, runtime_checkable

from labkit.frame import Frame


@dataclass(frozen=True)
class CameraIdentity:
    """Who a camera is: vendor, model, serial number and firmware version."""

    vendor: str
    model: str
    serial: str
    firmware: str

    def as_dict(self) -> dict[str, str]:
        """The identity as a plain mapping (for session files)."""
        return asdict(self)

    def __str__(self) -> str:
        return f"{self.vendor} {self.model} (serial {self.serial}, firmware {self.firmware})"


@dataclass(frozen=True)
class Bounds:
    """Allowed range of a numeric setting and its step (0 = continuous)."""

    minimum: float
    maximum: float
    increment: float = 0.0

    def contains(self, value: float) -> bool:
        """Whether `value` lies within [minimum, maximum] (a relative 1e-9 slack)."""
        slack = 1e-9 * max(abs(self.minimum), abs(self.maximum), 1.0)
        return self.minimum - slack <= value <= self.maximum + slack


@dataclass(frozen=True)
class DeviceInfo:
    """A camera found by a backend's discovery (``labkit devices``)."""

    backend: str
    device_id: str
    vendor: str = ""
    model: str = ""
    serial: str = ""
    address: str = ""


@runtime_checkable
class Camera(Protocol):
    """A colour camera delivering raw Bayer frames.

    Backends open the device in their constructor (or a ``open`` classmethod) and
    release it in :meth:`close`; they are context managers.
    """

    backend: str

    @property
    def identity(self) -> CameraIdentity:
        """Vendor, model, serial and firmware."""
        ...

    @property
    def pixel_format(self) -> str:
        """Current GenICam pixel format, e.g. ``BayerGB12``."""
        ...

    @property
    def cfa(self) -> str:
        """CFA layout of the current pixel format, e.g. ``GBRG``."""
        ...

    @property
    def shape(self) -> tuple[int, int]:
        """Image (rows, cols)."""
        ...

    def feature_names(self) -> list[str]:
        """Names of the device's features."""
        ...

    def get(self, name: str) -> Any:
        """Read a feature (GenICam units)."""
        ...

    def set(self, name: str, value: Any) -> None:
        """Write a feature (GenICam units)."""
        ...

    def exposure_bounds(self) -> Bounds:
        """Exposure time range and increment, s.

        Raises DeviceError naming the missing feature when the camera has no
        controllable exposure time.
        """
        ...

    def gain_bounds(self) -> Bounds:
        """Gain range and increment, dB."""
        ...

    def set_pixel_format(self, pixel_format: str) -> None:
        """Choose the pixel format (e.g. ``BayerGB12``, ``BayerRG12p``)."""
        ...

    def grab(self, exposure_s: float, n: int = 1) -> list[Frame]:
        """Capture `n` frames each exposed for `exposure_s` seconds.

        Every returned frame was exposed after the exposure change (software
        triggered, newer frame id, host time after the change), has status
        ``"SUCCESS"`` and a uint16 (or uint8) mosaic of :attr:`shape`. Failed
        buffers are retried a bounded number of times; a DeviceError is raised when
        the retries are exhausted.
        """
        ...

    def stream_statistics(self) -> dict[str, int]:
        """Counters of the stream: completed and failed buffers, missing packets, resends…"""
        ...

    def close(self) -> None:
        """Stop any acquisition and release the device."""
        ...

    def __enter__(self) -> Camera: ...

    def __exit__(self, *exc: object) -> None: ...
