"""The rig's devices as ophyd devices, for a Bluesky RunEngine.

- :class:`LabkitCamera` wraps any labkit :class:`~labkit.devices.camera.Camera` (Aravis,
  GenTL or simulated). Set ``exposure_s``, trigger it, and read the frame and its
  metadata: the fields of a session's ``frames.jsonl`` record.
- :class:`LabkitSlider` wraps a :class:`~labkit.devices.slider.FilterSlider`. ``set(slot)``
  moves it; it reads the slot and the illumination that slot gives.
- :class:`LabkitStage` wraps a :class:`~labkit.protocol.stage.Stage`, the scene and the
  light cover. These are operator actions on a real rig and simulator calls on the
  simulated one.

All three are synchronous: each action is done when its status is returned.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

import numpy as np
from ophyd import Component, Device, Signal
from ophyd.status import Status

from labkit.devices.camera import Camera
from labkit.devices.slider import FilterSlider
from labkit.frame import Frame
from labkit.io.tiff import json_default
from labkit.protocol.stage import Stage

FRAME_FIELDS = (
    "frame_id",
    "exposure_readback_s",
    "gain_db",
    "pixel_format",
    "device_timestamp_ns",
    "host_timestamp_s",
    "status",
)
"""Frame metadata each camera reading carries, beside ``image``, ``exposure_s`` and
``extra`` (the backend's facts as JSON: temperature, levels, simulator truth)."""


def _done() -> Status:
    status = Status()
    status.set_finished()
    return status


class LabkitCamera(Device):
    """A labkit camera as an ophyd device: one frame per trigger.

    Parameters
    ----------
    camera : Camera
        An open camera; the device does not close it.
    name : str
        The device name; reading keys are ``<name>_image``, ``<name>_exposure_s``, …
    """

    exposure_s = Component(Signal, value=0.01, kind="normal")
    image = Component(Signal, value=np.zeros((2, 2), np.uint16), kind="normal")
    frame_id = Component(Signal, value=0, kind="normal")
    exposure_readback_s = Component(Signal, value=0.0, kind="normal")
    gain_db = Component(Signal, value=0.0, kind="normal")
    pixel_format = Component(Signal, value="", kind="normal")
    device_timestamp_ns = Component(Signal, value=0, kind="normal")
    host_timestamp_s = Component(Signal, value=0.0, kind="normal")
    status = Component(Signal, value="", kind="normal")
    extra = Component(Signal, value="{}", kind="normal")

    def __init__(self, camera: Camera, *, name: str = "camera", **kwargs: Any) -> None:
        super().__init__(name=name, **kwargs)
        self.camera = camera
        rows, cols = camera.shape
        self.image.put(np.zeros((rows, cols), np.uint16))

    def trigger(self) -> Status:
        """Grab one frame at ``exposure_s`` and publish it with its metadata."""
        frame = self.camera.grab(float(self.exposure_s.get()), 1)[0]
        self.image.put(frame.image)
        for field in FRAME_FIELDS:
            getattr(self, field).put(getattr(frame, field))
        self.extra.put(json.dumps(frame.extra, default=json_default))
        return _done()


def frame_from_reading(data: Mapping[str, Any], camera_name: str) -> Frame:
    """The :class:`~labkit.frame.Frame` in a reading or event's data of a
    :class:`LabkitCamera` named `camera_name`: values, or ``{"value": …}`` readings."""

    def value(field: str) -> Any:
        item = data[f"{camera_name}_{field}"]
        return item["value"] if isinstance(item, Mapping) else item

    return Frame(
        image=np.asarray(value("image")),
        frame_id=int(value("frame_id")),
        exposure_s=float(value("exposure_s")),
        exposure_readback_s=float(value("exposure_readback_s")),
        gain_db=float(value("gain_db")),
        pixel_format=str(value("pixel_format")),
        device_timestamp_ns=int(value("device_timestamp_ns")),
        host_timestamp_s=float(value("host_timestamp_s")),
        status=str(value("status")),
        extra=json.loads(value("extra")),
    )


class LabkitSlider(Device):
    """A labkit filter slider as an ophyd positioner: ``set(slot)`` moves it.

    Parameters
    ----------
    slider : FilterSlider
        An open slider; the device does not close it.
    positions : mapping slot → illumination name
        What each slot lights the scene with (the rig's ``slider.positions``).
    """

    slot = Component(Signal, value=0, kind="hinted")
    illumination = Component(Signal, value="", kind="normal")

    def __init__(
        self,
        slider: FilterSlider,
        positions: Mapping[int, str],
        *,
        name: str = "slider",
        **kwargs: Any,
    ) -> None:
        super().__init__(name=name, **kwargs)
        self.slider = slider
        self.positions = dict(positions)

    def set(self, slot: int) -> Status:  # type: ignore[override]
        """Move to `slot` (1-based); done when the slider reports the move finished."""
        slot = int(slot)
        self.slider.move(slot)
        self.slot.put(slot)
        self.illumination.put(self.positions.get(slot, ""))
        return _done()


class LabkitStage(Device):
    """Scene and light cover as an ophyd device.

    ``set(("scene", name))``, ``set(("cover", True))`` or ``set(("cover", False))`` acts
    (see :func:`labkit.bluesky.plans.labkit_plan`); it reads the scene and whether the
    light is covered.
    """

    scene = Component(Signal, value="", kind="normal")
    covered = Component(Signal, value=False, kind="normal")

    def __init__(self, stage: Stage, *, name: str = "stage", **kwargs: Any) -> None:
        super().__init__(name=name, **kwargs)
        self.stage = stage

    def set(self, action: tuple[str, Any]) -> Status:  # type: ignore[override]
        """Do one stage action: ``("scene", name)`` or ``("cover", bool)``."""
        what, value = action
        if what == "scene":
            self.stage.set_scene(str(value))
            self.scene.put(str(value))
        elif what == "cover":
            (self.stage.cover_light if value else self.stage.uncover_light)()
            self.covered.put(bool(value))
        else:
            raise ValueError(f"stage action {what!r}: expected 'scene' or 'cover'")
        return _done()
