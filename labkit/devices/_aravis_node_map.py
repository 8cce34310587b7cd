"""The GenICam node map of an Aravis camera: the primitives of
:class:`~labkit.devices.genicam_features.GenICamFeatures` on Aravis' device features.

:class:`AravisNodeMap` reads and writes features through ``Aravis.Device``, reports their
kinds, bounds, increments and choices, runs commands, reads the identity and the gain, and
turns Aravis' GErrors into one-line :class:`~labkit.errors.DeviceError` messages. It is the
lowest layer of :class:`labkit.devices.aravis.AravisCamera`, which opens the camera and
owns the state declared here.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator
from typing import Any

from labkit.devices._aravis_gi import Aravis, GLib
from labkit.devices.camera import CameraIdentity
from labkit.devices.genicam_features import GAIN_FEATURES, GenICamFeatures
from labkit.errors import DeviceError

__all__ = ["AravisNodeMap"]


class AravisNodeMap(GenICamFeatures):
    """Feature access on an Aravis camera's node map (see the module)."""

    # the camera's state these methods use, set by AravisCamera (its __init__ and _open)
    device_id: str
    # Aravis' GObjects (PyGObject ships no types); None while disconnected
    _cam: Any
    _dev: Any
    _control_lost: threading.Event

    @contextlib.contextmanager
    def _gerror(self, action: str) -> Iterator[None]:
        """Turn an Aravis GError into a one-line DeviceError naming the camera and action."""
        try:
            yield
        except GLib.GError as error:
            if error.matches(Aravis.device_error_quark(), Aravis.DeviceError.TIMEOUT):
                self._control_lost.set()  # the next operation re-opens the camera
                hint = (
                    "the camera does not answer: check its power and network link; the next "
                    "call tries to reconnect"
                )
            else:
                hint = "check the feature names, values and access modes (feature_names(), get())"
            raise DeviceError(
                f"camera {self.device_id}: {action} failed: {error.message}; {hint}"
            ) from error

    def _read_identity(self) -> CameraIdentity:
        with self._gerror("reading its identity"):
            firmware = ""
            for name in ("DeviceFirmwareVersion", "DeviceVersion"):
                if self._dev.get_feature(name) is not None:
                    firmware = self._dev.get_string_feature_value(name) or ""
                    break
            return CameraIdentity(
                vendor=self._cam.get_vendor_name() or "",
                model=self._cam.get_model_name() or "",
                serial=self._cam.get_device_serial_number() or "",
                firmware=firmware,
            )

    # -- the node-map primitives of GenICamFeatures ---------------------------------------------
    @property
    def _where(self) -> str:
        return f"camera {self.device_id}"

    def _kind(self, name: str) -> str | None:
        node = self._dev.get_feature(name)
        if node is None:
            return None
        # interfaces, not classes: a Converter node is a GcFloat, an enumeration a GcInteger
        for interface, kind in (
            (Aravis.GcEnumeration, "enumeration"),
            (Aravis.GcBoolean, "boolean"),
            (Aravis.GcFloat, "float"),
            (Aravis.GcInteger, "integer"),
            (Aravis.GcString, "string"),
            (Aravis.GcCommand, "command"),
        ):
            if isinstance(node, interface):
                return kind
        return type(node).__name__.removeprefix("Gc").lower()  # a register, a category…

    def _read(self, name: str, kind: str) -> Any:
        dev = self._dev
        if kind == "boolean":
            return bool(dev.get_boolean_feature_value(name))
        if kind == "float":
            return float(dev.get_float_feature_value(name))
        if kind == "integer":
            return int(dev.get_integer_feature_value(name))
        return dev.get_string_feature_value(name)  # enumerations and strings

    def _write(self, name: str, kind: str, value: Any) -> None:
        dev = self._dev
        if kind == "boolean":
            dev.set_boolean_feature_value(name, value)
        elif kind == "float":
            dev.set_float_feature_value(name, value)
        elif kind == "integer":
            dev.set_integer_feature_value(name, value)
        else:
            dev.set_string_feature_value(name, value)

    def _limits(self, name: str, kind: str) -> tuple[float, float]:
        if kind == "float":
            low, high = self._dev.get_float_feature_bounds(name)
        else:
            low, high = self._dev.get_integer_feature_bounds(name)
        return float(low), float(high)

    def _increment(self, name: str, kind: str) -> float:
        if kind == "float":
            return float(self._cam.get_float_increment(name))
        return float(self._cam.get_integer_increment(name))

    def _choices(self, name: str) -> list[str]:
        return list(self._dev.dup_available_enumeration_feature_values_as_strings(name) or [])

    def _run(self, name: str) -> None:
        self._dev.execute_command(name)

    def _device_call(self, action: str) -> contextlib.AbstractContextManager[None]:
        return self._gerror(action)

    def _read_gain(self) -> float | None:
        if self._present(GAIN_FEATURES) is None:
            return None
        with self._gerror("reading the gain"):
            return float(self._cam.get_gain())
