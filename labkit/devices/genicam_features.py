"""GenICam features, written once for both camera backends (Aravis and GenTL/Harvesters).

Each backend reaches a camera's GenICam node map through its own library, and keeps its
own discovery and streaming. What they share lives here, in :class:`GenICamFeatures`:

* the standard (SFNC) feature names labkit relies on, and their units (exposure in µs on
  the device, s in labkit);
* reading and writing a feature, with its type, access mode, bounds and choices checked
  before the device is asked, so that a bad value fails with one message naming the
  camera, the feature and what it accepts;
* running a command feature;
* the exposure and gain features and their bounds, the pixel formats the camera offers,
  the CFA layout of its pixel format, and the image size;
* what a bracketed capture needs from the camera: continuous acquisition, a frame-start
  software trigger, exposure and gain under manual control, and an exposure time set to
  the nearest step the camera allows.

A backend subclasses :class:`GenICamFeatures` and provides the node-map primitives (its
abstract methods): what kind of node a feature is, its access mode, reading, writing,
bounds, increment, choices and running a command, a context that turns the library's
errors into :class:`~labkit.errors.DeviceError`, and how to stop a running acquisition
before a setting that needs it stopped.
"""

from __future__ import annotations

import abc
import difflib
import math
from collections.abc import Iterable
from contextlib import AbstractContextManager
from typing import Any

from labkit.cfa import layout_from_pixel_format
from labkit.devices.camera import Bounds
from labkit.errors import DataError, DeviceError

__all__ = [
    "ACCESS_NAMES",
    "EXPOSURE_FEATURES",
    "EXPOSURE_UNIT_S",
    "GAIN_FEATURES",
    "TRIGGER_FEATURES",
    "VALUE_KINDS",
    "GenICamFeatures",
]

#: Exposure-time features, preferred first (GenICam SFNC, then the older GigE name).
EXPOSURE_FEATURES = ("ExposureTime", "ExposureTimeAbs")
#: Seconds per unit of the exposure features (they are in µs).
EXPOSURE_UNIT_S = 1e-6
#: Gain features, preferred first: ``Gain`` is in dB, ``GainRaw`` in device units.
GAIN_FEATURES = ("Gain", "GainRaw")
#: The features a software trigger needs.
TRIGGER_FEATURES = ("TriggerMode", "TriggerSource", "TriggerSoftware")
#: Node kinds that hold a value (others: ``command``, ``register``, ``category``…).
VALUE_KINDS = frozenset({"enumeration", "boolean", "float", "integer", "string"})
#: GenApi access modes, as the primitives report them.
ACCESS_NAMES = {
    "NI": "not implemented",
    "NA": "not available",
    "WO": "write-only",
    "RO": "read-only",
    "RW": "read-write",
}
#: Increments below this are continuous features (some devices report 1e-300 for none).
_TINY_INCREMENT = 1e-12


class GenICamFeatures(abc.ABC):
    """Feature access on a GenICam node map, with its checks and messages (see the module)."""

    #: What a caller can do about a camera without exposure control (backend-specific).
    no_exposure_hint = (
        "labkit cannot control it on this camera: check its features with feature_names() "
        "or use a camera that has one"
    )

    # -- what a backend provides --------------------------------------------------------------
    @property
    @abc.abstractmethod
    def _where(self) -> str:
        """The camera as messages name it, e.g. ``camera LK01``."""

    @abc.abstractmethod
    def _usable(self) -> None:
        """Raise DeviceError if the camera is closed (reconnect first where the backend can)."""

    @abc.abstractmethod
    def _kind(self, name: str) -> str | None:
        """The node kind of feature `name` (lower-case GenApi interface: ``integer``,
        ``float``, ``enumeration``, ``boolean``, ``string``, ``command``…); None if absent."""

    def _access(self, name: str) -> str | None:
        """The access mode of `name` (a key of :data:`ACCESS_NAMES`); None when unknown."""
        return None

    @abc.abstractmethod
    def _read(self, name: str, kind: str) -> Any:
        """The value of a value feature of `kind` (device units)."""

    @abc.abstractmethod
    def _write(self, name: str, kind: str, value: Any) -> None:
        """Write a value already checked against the feature's kind, bounds and choices."""

    @abc.abstractmethod
    def _limits(self, name: str, kind: str) -> tuple[float, float]:
        """(minimum, maximum) of a numeric feature, device units."""

    @abc.abstractmethod
    def _increment(self, name: str, kind: str) -> float:
        """Step of a numeric feature, device units (0 or less: none)."""

    @abc.abstractmethod
    def _choices(self, name: str) -> list[str]:
        """The symbols an enumeration feature offers now."""

    @abc.abstractmethod
    def _run(self, name: str) -> None:
        """Execute a command feature."""

    def _unit(self, name: str) -> str:
        """The unit the device gives for `name` ('' when it gives none)."""
        return ""

    @abc.abstractmethod
    def _device_call(self, action: str) -> AbstractContextManager[None]:
        """A context turning the library's errors into one DeviceError naming `action`."""

    @abc.abstractmethod
    def feature_names(self) -> list[str]:
        """Names of the device's features (categories left out)."""

    @property
    @abc.abstractmethod
    def pixel_format(self) -> str:
        """The current GenICam pixel format, e.g. ``BayerRG12p``."""

    @abc.abstractmethod
    def _stop_for_change(self) -> None:
        """Stop a running acquisition (the trigger settings are locked while it runs)."""

    # -- features --------------------------------------------------------------------------------
    def has_feature(self, name: str) -> bool:
        """Whether the device implements feature `name` and it is available now."""
        self._usable()
        return self._available(name)

    def _available(self, name: str) -> bool:
        """:meth:`has_feature` without the open check, for callers that have made it."""
        return self._kind(name) is not None and self._access(name) not in ("NI", "NA")

    def _feature_kind(self, name: str) -> str:
        """The kind of feature `name`; DeviceError naming similar features if it is absent."""
        self._usable()
        kind = self._kind(name)
        if kind is None:
            names = self.feature_names()
            similar = difflib.get_close_matches(name, names, n=5)
            hint = (
                f"similar: {', '.join(similar)}"
                if similar
                else f"see feature_names() for the {len(names)} it has"
            )
            raise DeviceError(f"{self._where}: no feature {name!r}; {hint}")
        return kind

    def get(self, name: str) -> Any:
        """Read a feature (GenICam units: µs, dB, enumeration symbol…).

        Raises
        ------
        DeviceError
            When the feature is missing, not readable now, or holds no value (a command,
            a register).
        """
        kind = self._feature_kind(name)
        if kind not in VALUE_KINDS:
            raise DeviceError(
                f"{self._where}: {name} is a {kind}, not a value; commands run with execute()"
            )
        access = self._access(name)
        if access is not None and access not in ("RO", "RW"):
            raise DeviceError(
                f"{self._where}: feature {name} is {ACCESS_NAMES.get(access, access)} and "
                "cannot be read now (another setting may disable it)"
            )
        with self._device_call(f"reading {name}"):
            return self._read(name, kind)

    def set(self, name: str, value: Any) -> None:
        """Write a feature (GenICam units).

        Raises
        ------
        DeviceError
            When the feature is missing, not writable now, holds no value (a command), or
            the value is not a number within its bounds, not an integer for an integer
            feature, or not one of an enumeration's choices.
        """
        self._write_feature(name, value)

    def _write_feature(self, name: str, value: Any) -> Any:
        """Check `value` against the feature and write it; returns what was written."""
        kind = self._feature_kind(name)
        if kind not in VALUE_KINDS:
            use = f"use execute({name!r})" if kind == "command" else "it holds no value"
            raise DeviceError(f"{self._where}: {name} is a {kind}, not a writable value; {use}")
        access = self._access(name)
        if access is not None and access not in ("WO", "RW"):
            hint = (
                " (stop the acquisition or change the controlling setting first)"
                if access == "RO"
                else ""
            )
            raise DeviceError(
                f"{self._where}: feature {name} is {ACCESS_NAMES.get(access, access)} and "
                f"cannot be written{hint}"
            )
        value = self._checked_value(name, kind, value)
        with self._device_call(f"writing {name}={value!r}"):
            self._write(name, kind, value)
        return value

    def _checked_value(self, name: str, kind: str, value: Any) -> Any:
        where = f"{self._where}: {name}"
        if kind == "enumeration":
            with self._device_call(f"listing the choices of {name}"):
                choices = self._choices(name)
            if str(value) not in choices:
                raise DeviceError(f"{where}={value!r} is not one of {choices}; pick one of those")
            return str(value)
        if kind == "boolean":
            return bool(value)
        if kind == "string":
            return str(value)
        try:
            number = float(value)
        except (TypeError, ValueError):
            raise DeviceError(f"{where} takes a number, not {value!r}") from None
        if not math.isfinite(number):
            raise DeviceError(f"{where} takes a finite number, not {value!r}")
        if kind == "integer" and number != int(number):
            raise DeviceError(f"{where} takes an integer, not {value!r}")
        with self._device_call(f"reading the bounds of {name}"):
            low, high = self._limits(name, kind)
        if not low <= number <= high:
            unit = self._unit(name)
            raise DeviceError(
                f"{where}={number:g} is outside [{low:g}, {high:g}]" + (f" {unit}" if unit else "")
            )
        return int(number) if kind == "integer" else number

    def execute(self, name: str) -> None:
        """Run a command feature (e.g. ``TriggerSoftware``)."""
        if self._feature_kind(name) != "command":
            raise DeviceError(f"{self._where}: {name} is not a command; use set() or get()")
        with self._device_call(f"executing {name}"):
            self._run(name)

    def _first_feature(self, candidates: Iterable[str]) -> str | None:
        """The first of `candidates` the device has, or None."""
        self._usable()
        return self._present(candidates)

    def _present(self, candidates: Iterable[str]) -> str | None:
        """:meth:`_first_feature` without the open check, which may reconnect: for code
        that runs while a frame is being handled."""
        return next((name for name in candidates if self._available(name)), None)

    def _feature_bounds(self, name: str, scale: float) -> Bounds:
        """Range and increment of numeric feature `name`, times `scale`."""
        kind = self._feature_kind(name)
        with self._device_call(f"reading the bounds of {name}"):
            low, high = self._limits(name, kind)
            increment = float(self._increment(name, kind))
        if not (math.isfinite(increment) and increment > _TINY_INCREMENT):
            increment = 0.0
        return Bounds(float(low) * scale, float(high) * scale, increment * scale)

    # -- exposure and gain -----------------------------------------------------------------------
    def _exposure_feature(self) -> str:
        """``ExposureTime`` or ``ExposureTimeAbs``, whichever the camera has."""
        name = self._first_feature(EXPOSURE_FEATURES)
        if name is None:
            raise DeviceError(
                f"{self._where} has no exposure-time feature (neither "
                f"{' nor '.join(EXPOSURE_FEATURES)}), so labkit cannot set its exposure time; "
                f"{self.no_exposure_hint}"
            )
        return name

    def exposure_bounds(self) -> Bounds:
        """Exposure time range and increment, s (0 increment: continuous).

        Raises
        ------
        DeviceError
            Naming the missing feature when the camera has neither ``ExposureTime`` nor
            ``ExposureTimeAbs``.
        """
        return self._feature_bounds(self._exposure_feature(), EXPOSURE_UNIT_S)

    def _check_exposure(self, exposure_s: float) -> Bounds:
        """Exposure bounds, s, after checking that `exposure_s` lies within them."""
        bounds = self.exposure_bounds()  # raises the missing-feature error first
        if not (math.isfinite(exposure_s) and exposure_s > 0 and bounds.contains(exposure_s)):
            raise DeviceError(
                f"{self._where}: exposure {exposure_s:g} s is outside the camera's range "
                f"[{bounds.minimum:g}, {bounds.maximum:g}] s; choose an exposure within it"
            )
        return bounds

    def gain_bounds(self) -> Bounds:
        """Gain range and increment: dB from ``Gain``, device units from ``GainRaw``.

        Raises
        ------
        DeviceError
            When the camera has neither feature.
        """
        name = self._first_feature(GAIN_FEATURES)
        if name is None:
            raise DeviceError(
                f"{self._where} has no gain feature (neither {' nor '.join(GAIN_FEATURES)}); "
                "its gain cannot be read or set: leave the rig's camera.gain_db at 0"
            )
        return self._feature_bounds(name, 1.0)

    # -- image format ----------------------------------------------------------------------------
    def pixel_formats(self) -> list[str]:
        """The pixel formats the device offers now."""
        self._feature_kind("PixelFormat")
        with self._device_call("listing its pixel formats"):
            return list(self._choices("PixelFormat"))

    def _check_offered(self, pixel_format: str) -> list[str]:
        """The offered pixel formats, after checking that `pixel_format` is one of them."""
        offered = self.pixel_formats()
        if pixel_format not in offered:
            raise DeviceError(
                f"{self._where}: pixel format {pixel_format!r} is not offered; it offers "
                f"{', '.join(offered)}"
            )
        return offered

    @property
    def cfa(self) -> str:
        """CFA layout of the current pixel format, e.g. ``RGGB`` for ``BayerRG8``.

        Raises
        ------
        DeviceError
            When the current pixel format is not a Bayer format.
        """
        pixel_format = self.pixel_format
        try:
            return layout_from_pixel_format(pixel_format)
        except DataError:
            bayer = [name for name in self.pixel_formats() if name.startswith("Bayer")]
            hint = (
                f"select one of its Bayer formats {bayer} with set_pixel_format()"
                if bayer
                else "it offers no Bayer format, so it cannot capture raw colour mosaics"
            )
            raise DeviceError(
                f"{self._where} delivers {pixel_format}, not a Bayer format, so it has no CFA "
                f"layout; {hint}"
            ) from None

    @property
    def shape(self) -> tuple[int, int]:
        """Image (rows, cols) = (``Height``, ``Width``) of the current region of interest."""
        return int(self.get("Height")), int(self.get("Width"))

    # -- what a bracketed capture needs ----------------------------------------------------------
    def _set_if_offered(self, name: str, value: str) -> None:
        """Set enumeration `name` to `value` where the camera has it and offers `value`."""
        if self.has_feature(name) and value in self._choices(name) and self.get(name) != value:
            self._write_feature(name, value)

    def _continuous_acquisition(self) -> None:
        """``AcquisitionMode`` = ``Continuous`` where the camera offers it."""
        self._set_if_offered("AcquisitionMode", "Continuous")

    def _manual_exposure_and_gain(self) -> None:
        """``ExposureAuto`` and ``GainAuto`` off: bracketing needs the values it asks for."""
        self._set_if_offered("ExposureAuto", "Off")
        self._set_if_offered("GainAuto", "Off")

    def _software_trigger_available(self) -> bool:
        """Whether frames can be software-triggered (selecting the ``FrameStart`` trigger)."""
        if not all(self.has_feature(name) for name in TRIGGER_FEATURES):
            return False
        self._set_if_offered("TriggerSelector", "FrameStart")
        return "Software" in self._choices("TriggerSource")

    def _use_software_trigger(self, on: bool) -> None:
        """Software-triggered frames (`on`) or free running; stops the acquisition to change."""
        if on:
            if self.get("TriggerSource") != "Software" or self.get("TriggerMode") != "On":
                self._stop_for_change()
                self._write_feature("TriggerSource", "Software")
                self._write_feature("TriggerMode", "On")
        elif self.has_feature("TriggerMode") and self.get("TriggerMode") != "Off":
            self._stop_for_change()
            self._write_feature("TriggerMode", "Off")

    def _set_exposure(self, exposure_s: float) -> None:
        """Exposure time `exposure_s` (s), at the nearest step the camera allows, with
        automatic exposure and gain off."""
        bounds = self._check_exposure(exposure_s)
        name = self._exposure_feature()
        self._manual_exposure_and_gain()
        scale = 1.0 / EXPOSURE_UNIT_S
        low, high = bounds.minimum * scale, bounds.maximum * scale
        step = bounds.increment * scale
        value = min(max(exposure_s * scale, low), high)
        if step > 0:
            value = min(low + round((value - low) / step) * step, high)
        self._write_feature(name, value)

    def _exposure_readback_s(self) -> float:
        """The exposure feature read back, s (NaN without one)."""
        name = self._first_feature(EXPOSURE_FEATURES)
        return math.nan if name is None else float(self.get(name)) * EXPOSURE_UNIT_S
