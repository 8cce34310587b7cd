"""SimCamera: a simulated GenICam-style colour camera looking at a simulated rig.

It exposes GenICam feature names and units (``ExposureTime`` in µs, ``Gain`` in dB,
``PixelFormat`` Bayer*8/12/16, ``Width``/``Height``, ``AcquisitionMode``, ``TriggerMode``/
``TriggerSource``/``TriggerSoftware``, device identity) and an acquisition engine with
software triggering, frame ids and device/host timestamps. Frames are deterministic given
the seed and the frame id. In ``fast`` mode nothing sleeps: the device clock still
advances by exposure + readout, but the host does not wait for it.
"""

from __future__ import annotations

import collections
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from labkit.cfa import layout_from_pixel_format, pixel_format_bits, pixel_format_for
from labkit.devices.camera import Bounds, CameraIdentity
from labkit.errors import DeviceError
from labkit.frame import Frame
from labkit.sim.world import DARK, SimulatedRig


@dataclass
class Feature:
    """A GenICam-style feature: value, type, access mode and bounds."""

    value: Any
    kind: str  # "float" | "int" | "enum" | "string" | "command"
    access: str = "RW"  # "RW" | "RO"
    minimum: float | None = None
    maximum: float | None = None
    increment: float | None = None
    choices: tuple[str, ...] = ()
    unit: str = ""
    locked_while_acquiring: bool = False


@dataclass(frozen=True)
class _Trigger:
    frame_id: int
    exposure_s: float
    gain_db: float
    pixel_format: str
    scene: str
    illumination: str
    device_time_ns: int


class SimCamera:
    """A simulated camera.

    Parameters
    ----------
    rig : SimulatedRig
        The simulated world (scene, light, lens, sensor).
    fast : bool
        Do not sleep for exposure and readout.
    seed : int or None
        Frame-noise seed (default: the rig's seed).
    """

    backend = "sim"
    vendor = "labkit"
    firmware = "sim-1.0"

    def __init__(self, rig: SimulatedRig, *, fast: bool = True, seed: int | None = None) -> None:
        self.rig = rig
        self.fast = fast
        self.seed = rig.rig.sim.seed if seed is None else seed
        model = rig.sensor.model
        layout = model.cfa
        formats = tuple(pixel_format_for(layout, bits) for bits in (8, 12, 16))
        rows, cols = model.shape
        self.serial = rig.rig.camera.device or "sim-0"
        self._features: dict[str, Feature] = {
            "DeviceVendorName": Feature(self.vendor, "string", "RO"),
            "DeviceModelName": Feature(f"SimCam-{cols}x{rows}", "string", "RO"),
            "DeviceSerialNumber": Feature(self.serial, "string", "RO"),
            "DeviceFirmwareVersion": Feature(self.firmware, "string", "RO"),
            "DeviceTemperature": Feature(35.0, "float", "RO", unit="C"),
            "SensorWidth": Feature(cols, "int", "RO"),
            "SensorHeight": Feature(rows, "int", "RO"),
            "Width": Feature(cols, "int", "RO"),
            "Height": Feature(rows, "int", "RO"),
            "PixelFormat": Feature(
                pixel_format_for(layout, 12) if model.adc_bits >= 12 else formats[0],
                "enum", choices=formats, locked_while_acquiring=True,
            ),
            "ExposureTime": Feature(10_000.0, "float", minimum=10.0, maximum=32_000_000.0,
                                    increment=1.0, unit="us"),
            "Gain": Feature(rig.rig.camera.gain_db, "float", minimum=0.0, maximum=24.0,
                            increment=0.1, unit="dB"),
            "AcquisitionMode": Feature("Continuous", "enum",
                                       choices=("Continuous", "SingleFrame", "MultiFrame"),
                                       locked_while_acquiring=True),
            "AcquisitionFrameCount": Feature(1, "int", minimum=1, maximum=65535, increment=1),
            "TriggerMode": Feature("Off", "enum", choices=("Off", "On")),
            "TriggerSource": Feature("Software", "enum", choices=("Software",)),
            "TriggerSoftware": Feature(None, "command"),
            "AcquisitionStart": Feature(None, "command"),
            "AcquisitionStop": Feature(None, "command"),
        }  # fmt: skip
        self.scene = rig.scene_names()[0]
        self.illumination = rig.illuminations()[0]
        self._acquiring = False
        self._pending: collections.deque[_Trigger] = collections.deque()
        self._next_frame_id = 1
        self._frames_left: int | None = None
        self._device_ns = 0
        self._delivered = 0
        self._open = True

    # -- identity and features -----------------------------------------------------------
    @property
    def identity(self) -> CameraIdentity:
        """Vendor, model, serial and firmware strings."""
        return CameraIdentity(
            vendor=self.get("DeviceVendorName"),
            model=self.get("DeviceModelName"),
            serial=self.get("DeviceSerialNumber"),
            firmware=self.get("DeviceFirmwareVersion"),
        )

    @property
    def pixel_format(self) -> str:
        """Current pixel format, e.g. ``BayerGB12``."""
        return self.get("PixelFormat")

    def set_pixel_format(self, pixel_format: str) -> None:
        """Choose the pixel format (Bayer 8/12/16 in the sensor's layout)."""
        self.set("PixelFormat", pixel_format)

    @property
    def cfa(self) -> str:
        """CFA layout of the current pixel format."""
        return layout_from_pixel_format(self.pixel_format)

    @property
    def shape(self) -> tuple[int, int]:
        """Image (rows, cols)."""
        return int(self.get("Height")), int(self.get("Width"))

    def exposure_bounds(self) -> Bounds:
        """Exposure time range and step, s."""
        return self._bounds("ExposureTime", 1e-6)

    def gain_bounds(self) -> Bounds:
        """Gain range and step, dB."""
        return self._bounds("Gain", 1.0)

    def _bounds(self, name: str, scale: float) -> Bounds:
        feat = self.feature(name)
        return Bounds(feat.minimum * scale, feat.maximum * scale, (feat.increment or 0) * scale)

    def stream_statistics(self) -> dict[str, int]:
        """Frames delivered (a simulated stream never loses one)."""
        return {"completed": self._delivered, "failed": 0, "retries": 0}

    def feature_names(self) -> list[str]:
        """All feature names."""
        return list(self._features)

    def feature(self, name: str) -> Feature:
        """The feature record (value, bounds, access) named `name`."""
        self._check_open()
        try:
            return self._features[name]
        except KeyError:
            raise DeviceError(
                f"camera {self.serial}: no feature {name!r}; it has {sorted(self._features)}"
            ) from None

    def get(self, name: str) -> Any:
        """Read a feature value (GenICam units)."""
        return self.feature(name).value

    def set(self, name: str, value: Any) -> None:
        """Write a feature value (GenICam units); bounds and access are enforced."""
        feat = self.feature(name)
        if feat.access != "RW" or feat.kind == "command":
            raise DeviceError(f"camera {self.serial}: feature {name} is not writable")
        if feat.locked_while_acquiring and self._acquiring:
            raise DeviceError(
                f"camera {self.serial}: {name} cannot change during acquisition; stop it first"
            )
        if feat.kind == "enum":
            if value not in feat.choices:
                raise DeviceError(
                    f"camera {self.serial}: {name}={value!r} is not one of {list(feat.choices)}"
                )
            feat.value = value
            return
        number = float(value)
        if not np.isfinite(number) or not feat.minimum <= number <= feat.maximum:
            raise DeviceError(
                f"camera {self.serial}: {name}={number:g} {feat.unit} is outside "
                f"[{feat.minimum:g}, {feat.maximum:g}] {feat.unit}"
            )
        if feat.increment:
            number = feat.minimum + round((number - feat.minimum) / feat.increment) * feat.increment
        feat.value = int(number) if feat.kind == "int" else number

    def execute(self, name: str) -> None:
        """Run a command feature (TriggerSoftware, AcquisitionStart, AcquisitionStop)."""
        if self.feature(name).kind != "command":
            raise DeviceError(f"camera {self.serial}: {name} is not a command")
        {
            "TriggerSoftware": self.software_trigger,
            "AcquisitionStart": self.start_acquisition,
            "AcquisitionStop": self.stop_acquisition,
        }[name]()

    # -- the simulated world -----------------------------------------------------------
    def set_scene(self, scene: str) -> None:
        """Put a scene in front of the camera."""
        self.rig.scene(scene)  # validates the name
        self.scene = scene

    def set_illumination(self, illumination: str) -> None:
        """Light the scene with a slider position's light, or ``"dark"`` (light covered)."""
        if illumination not in self.rig.illuminations():
            raise DeviceError(
                f"no illumination {illumination!r}; use one of {self.rig.illuminations()}"
            )
        self.illumination = illumination

    # -- acquisition ---------------------------------------------------------------------
    def start_acquisition(self) -> None:
        """Start acquiring (free-running, or waiting for triggers if TriggerMode is On)."""
        self._check_open()
        mode = self.get("AcquisitionMode")
        self._frames_left = {"Continuous": None, "SingleFrame": 1}.get(
            mode, self.get("AcquisitionFrameCount")
        )
        self._pending.clear()
        self._acquiring = True

    def stop_acquisition(self) -> None:
        """Stop acquiring and drop frames not yet fetched."""
        self._acquiring = False
        self._pending.clear()

    @property
    def next_frame_id(self) -> int:
        """Id of the next frame; setting it replays the noise of earlier frames."""
        return self._next_frame_id

    @next_frame_id.setter
    def next_frame_id(self, value: int) -> None:
        if value < 1:
            raise DeviceError(f"camera {self.serial}: frame ids start at 1, got {value}")
        self._next_frame_id = int(value)

    @property
    def acquiring(self) -> bool:
        """Whether an acquisition is running."""
        return self._acquiring

    def software_trigger(self) -> None:
        """Expose one frame with the current settings (TriggerMode On)."""
        if not self._acquiring:
            raise DeviceError(f"camera {self.serial}: trigger before AcquisitionStart")
        if self.get("TriggerMode") != "On":
            raise DeviceError(f"camera {self.serial}: TriggerSoftware needs TriggerMode=On")
        self._queue_frame()

    def _queue_frame(self) -> None:
        if self._frames_left is not None:
            if self._frames_left <= 0:
                raise DeviceError(f"camera {self.serial}: acquisition frame count reached")
            self._frames_left -= 1
        exposure_s = self.get("ExposureTime") * 1e-6
        trigger = _Trigger(
            self._next_frame_id, exposure_s, self.get("Gain"), self.get("PixelFormat"),
            self.scene, self.illumination, self._device_ns,
        )  # fmt: skip
        self._next_frame_id += 1
        self._device_ns += round((exposure_s + self.rig.rig.sim.readout_s) * 1e9)
        self._pending.append(trigger)

    def fetch(self, timeout_s: float = 5.0) -> Frame:
        """Return the next frame (free-running mode exposes one on demand)."""
        self._check_open()
        if not self._acquiring:
            raise DeviceError(f"camera {self.serial}: fetch without a running acquisition")
        if not self._pending:
            if self.get("TriggerMode") == "On":
                raise DeviceError(
                    f"camera {self.serial}: no frame within {timeout_s} s (no trigger was sent)"
                )
            self._queue_frame()
        trigger = self._pending.popleft()
        if not self.fast:
            time.sleep(trigger.exposure_s + self.rig.rig.sim.readout_s)
        frame = self._render(trigger)
        self._delivered += 1
        if self._frames_left == 0 and not self._pending:
            self._acquiring = False
        return frame

    def grab(self, exposure_s: float, n: int = 1) -> list[Frame]:
        """Capture `n` software-triggered frames at `exposure_s` seconds."""
        bounds = self.exposure_bounds()
        if not bounds.contains(exposure_s):
            raise DeviceError(
                f"camera {self.serial}: exposure {exposure_s:g} s is outside "
                f"[{bounds.minimum:g}, {bounds.maximum:g}] s"
            )
        self.set("ExposureTime", exposure_s * 1e6)
        self.set("TriggerMode", "On")
        if not self._acquiring:
            self.set("AcquisitionMode", "Continuous")
            self.start_acquisition()
        frames = []
        for _ in range(n):
            self.software_trigger()
            frames.append(self.fetch())
        return frames

    def close(self) -> None:
        """Stop and release the camera."""
        self.stop_acquisition()
        self._open = False

    def __enter__(self) -> SimCamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _check_open(self) -> None:
        if not self._open:
            raise DeviceError(f"camera {self.serial} is closed")

    def _saturation_dn(self, gain_db: float) -> float:
        """Counts of a full pixel (full well or ADC limit, whichever comes first)."""
        return self.rig.sensor.model.saturation_dn(gain_db)

    def _render(self, trigger: _Trigger) -> Frame:
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, trigger.frame_id]))
        irradiance = self.rig.irradiance(trigger.scene, trigger.illumination)
        level = self.rig.light_level(trigger.device_time_ns * 1e-9, rng)
        model = self.rig.sensor.model
        counts, actual = self.rig.sensor.expose(
            irradiance, trigger.exposure_s, rng=rng, gain_db=trigger.gain_db, light_level=level
        )
        bits = pixel_format_bits(trigger.pixel_format)
        shift = bits - model.adc_bits  # counts are MSB-aligned in the output format
        image = counts << shift if shift >= 0 else counts >> -shift
        if bits == 8:
            image = image.astype(np.uint8)
        return Frame(
            image=image,
            frame_id=trigger.frame_id,
            exposure_s=trigger.exposure_s,
            exposure_readback_s=trigger.exposure_s,
            gain_db=trigger.gain_db,
            pixel_format=trigger.pixel_format,
            device_timestamp_ns=trigger.device_time_ns,
            host_timestamp_s=time.time(),
            extra={
                "scene": trigger.scene,
                "illumination": trigger.illumination,
                "true_exposure_s": actual,
                "light_level": level,
                "temperature_c": self.get("DeviceTemperature"),
                "black_level": model.black_level_dn * 2.0**shift,  # in delivered counts
                "saturation_dn": self._saturation_dn(trigger.gain_db) * 2.0**shift,
                "dark": trigger.illumination == DARK,
            },
        )
