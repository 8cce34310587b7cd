"""Thesis Algorithm 10 (exposure bracketing, auto-bracketing and dark frames) as a Bluesky
plan: ``RE(labkit_plan(camera, slider, rig, stage=stage))``.

The plan carries out the requests of :func:`labkit.protocol.steps.protocol_steps`, the one
description of the protocol that ``labkit capture``'s engine carries out too, so it makes
the same device calls in the same order:

- the stage, the light cover and the slider move only when they must change;
- an ``auto`` illumination is metered, its exposure times chosen and checked with
  :func:`labkit.protocol.auto_bracketing`, and the plan rebuilt;
- every frame is checked as the engine checks it.

The documents it emits:

- ``start``: under ``labkit``, the rig snapshot, its plan fingerprint, the camera's and the
  slider's identity and the names of the devices;
- stream ``primary``: one event per stored frame (the frame, its metadata and its key:
  scene, illumination, exposure, replicate);
- stream ``labkit_metering``: the metering frames;
- stream ``labkit_brackets``: each auto-bracketing choice;
- stream ``labkit_statistics``: the camera's stream counters at the end.

:class:`labkit.bluesky.SessionWriter` turns them into a labkit session.
"""

from __future__ import annotations

import json
from collections.abc import Generator
from typing import Any

import bluesky.plan_stubs as bps
import bluesky.preprocessors as bpp
from ophyd import Component, Device, Signal

import labkit
from labkit.bluesky.devices import LabkitCamera, LabkitSlider, LabkitStage, frame_from_reading
from labkit.bluesky.streams import BRACKETS, METERING, PRIMARY, STATISTICS
from labkit.errors import ConfigError
from labkit.frame import Frame, FrameKey
from labkit.protocol import drive_within
from labkit.protocol.plan import build_plan, validate_plan
from labkit.protocol.steps import (
    Acquire,
    BracketChosen,
    Move,
    Record,
    Request,
    configure_camera,
    protocol_steps,
)
from labkit.rig import Rig
from labkit.session.store import plan_fingerprint, rig_snapshot


class FrameLabel(Device):
    """The key of the frame being read: scene (``""`` for darks), illumination, replicate."""

    scene = Component(Signal, value="", kind="normal")
    illumination = Component(Signal, value="", kind="normal")
    replicate = Component(Signal, value=0, kind="normal")


class RunNote(Device):
    """A JSON note about the run (an auto-bracketing choice, the stream counters)."""

    scene = Component(Signal, value="", kind="normal")
    illumination = Component(Signal, value="", kind="normal")
    text = Component(Signal, value="{}", kind="normal")


def labkit_plan(
    camera: LabkitCamera,
    slider: LabkitSlider,
    rig: Rig,
    *,
    stage: LabkitStage,
    md: dict[str, Any] | None = None,
) -> Generator[Any, Any, dict[tuple[str, str], list[float]]]:
    """Capture `rig`'s plan (thesis Algorithm 10) with a Bluesky RunEngine.

    Parameters
    ----------
    camera, slider, stage : LabkitCamera, LabkitSlider, LabkitStage
        The rig's devices (:func:`labkit.bluesky.open_devices` opens them from a rig).
    rig : Rig
        Scenes, illuminations, exposure times (fixed or ``auto``), replicates, darks.
    md : dict, optional
        Extra start-document metadata.

    Returns
    -------
    dict
        The auto-bracketed exposure times, s, by (scene, illumination).

    Raises
    ------
    ConfigError
        A plan the camera or slider cannot run (checked before anything moves).
    DeviceError
        A frame that fails the engine's checks (bad buffer, shape or exposure).
    """
    snapshot = rig_snapshot(rig)
    validate_plan(build_plan(rig), camera.camera, slider.slider)
    identity = camera.camera.identity
    shape = camera.camera.shape
    label = FrameLabel(name="frame")
    note = RunNote(name="note")
    names = rig.slider.position_names()
    if names != slider.positions:
        raise ConfigError(
            f"slider device {slider.name!r} has positions {slider.positions}, the rig "
            f"{names}; build it from the same rig (labkit.bluesky.open_devices)"
        )
    metadata = {
        "plan_name": "labkit_plan",
        "labkit": {
            "kind": "labkit-capture",
            "version": labkit.__version__,
            "rig": snapshot,
            "rig_source": rig.source,
            "plan_fingerprint": plan_fingerprint(snapshot),
            "camera": identity.as_dict(),
            "slider": {"port": slider.slider.port, "identity": slider.slider.identity},
            "devices": {"camera": camera.name, "label": label.name, "note": note.name},
        },
        **(md or {}),
    }
    taken: set[FrameKey] = set()

    def read_frame(exposure_s: float, key: FrameKey, stream: str) -> Generator[Any, Any, Any]:
        yield from bps.mv(camera.exposure_s, exposure_s)
        yield from bps.mv(
            label.scene, key.scene or "", label.illumination, key.illumination,
            label.replicate, key.replicate,
        )  # fmt: skip
        reading = yield from bps.trigger_and_read([camera, label, slider, stage], name=stream)
        return frame_from_reading(reading, camera.name)

    def carry_out(request: Request) -> Generator[Any, Any, Frame | None]:
        match request:
            case Move("slot", value):
                yield from bps.mv(slider, value)
            case Move(what, value):
                yield from bps.mv(stage, ("cover" if what == "covered" else "scene", value))
            case Acquire(exposure_s, key, metering):
                stream = METERING if metering else PRIMARY
                return (yield from read_frame(exposure_s, key, stream))
            case BracketChosen(step, choice):
                yield from bps.mv(
                    note.scene, step.scene, note.illumination, step.illumination,
                    note.text, json.dumps(choice.as_dict()),
                )  # fmt: skip
                yield from bps.trigger_and_read([note], name=BRACKETS)
            case Record(key, _):
                taken.add(key)  # the event is the record
        return None

    @bpp.run_decorator(md=metadata)
    def run() -> Generator[Any, Any, dict[tuple[str, str], list[float]]]:
        configure_camera(camera.camera, rig)
        steps = protocol_steps(
            rig,
            brackets={},
            done=taken.__contains__,
            exposure_bounds=camera.camera.exposure_bounds,
            shape=shape,
            serial=identity.serial,
        )
        brackets = yield from drive_within(steps, carry_out)
        statistics = dict(camera.camera.stream_statistics())
        yield from bps.mv(note.scene, "", note.illumination, "", note.text, json.dumps(statistics))
        yield from bps.trigger_and_read([note], name=STATISTICS)
        return brackets

    return (yield from run())
