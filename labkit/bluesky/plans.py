"""Thesis Algorithm 10 (exposure bracketing, auto-bracketing and dark frames) as a Bluesky
plan: ``RE(labkit_plan(camera, slider, rig, stage=stage))``.

The plan runs the steps of :func:`labkit.protocol.build_plan`, in the same order and with
the same device calls as ``labkit capture``'s engine:

- the stage, the light cover and the slider move only when they must change;
- an ``auto`` illumination is metered, its exposure times chosen and checked with
  :func:`labkit.protocol.auto_bracketing` (the engine's own sequence), and the plan rebuilt;
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
from labkit.errors import ConfigError
from labkit.frame import FrameKey
from labkit.protocol.bracketing import auto_bracketing
from labkit.protocol.engine import check_frame, configure_camera
from labkit.protocol.plan import (
    Capture,
    Meter,
    build_plan,
    pending_changes,
    update_desired_state,
    validate_plan,
)
from labkit.rig import Rig
from labkit.session.store import plan_fingerprint, rig_snapshot

PRIMARY = "primary"
METERING = "labkit_metering"
BRACKETS = "labkit_brackets"
STATISTICS = "labkit_statistics"
"""Names of the event streams :func:`labkit_plan` emits."""


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
    names = {slot: p.name for slot, p in rig.slider.positions.items()}
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
    brackets: dict[tuple[str, str], list[float]] = {}

    def apply(desired: dict[str, Any], state: dict[str, Any]) -> Generator[Any, Any, None]:
        for key, value in pending_changes(desired, state):
            if key == "slot":
                yield from bps.mv(slider, value)
            else:
                yield from bps.mv(stage, ("cover" if key == "covered" else "scene", value))
            state[key] = value

    def read_frame(exposure_s: float, key: FrameKey, stream: str) -> Generator[Any, Any, Any]:
        yield from bps.mv(camera.exposure_s, exposure_s)
        yield from bps.mv(
            label.scene, key.scene or "", label.illumination, key.illumination,
            label.replicate, key.replicate,
        )  # fmt: skip
        reading = yield from bps.trigger_and_read([camera, label, slider, stage], name=stream)
        return frame_from_reading(reading, camera.name)

    def meter(step: Meter) -> Generator[Any, Any, None]:
        auto = rig.plan.auto
        bounds = camera.camera.exposure_bounds()
        steps = auto_bracketing(bounds, auto)
        key = FrameKey(step.scene, step.illumination, 0.0, 0)
        exposure = next(steps)
        try:
            while True:
                frame = yield from read_frame(exposure, key, METERING)
                exposure = steps.send(frame)
        except StopIteration as done:
            choice = done.value
        brackets[step.scene, step.illumination] = list(choice.exposures_s)
        yield from bps.mv(
            note.scene, step.scene, note.illumination, step.illumination,
            note.text, json.dumps(choice.as_dict()),
        )  # fmt: skip
        yield from bps.trigger_and_read([note], name=BRACKETS)

    @bpp.run_decorator(md=metadata)
    def run() -> Generator[Any, Any, None]:
        configure_camera(camera.camera, rig)
        state: dict[str, Any] = {}
        taken: set[FrameKey] = set()
        while True:
            desired: dict[str, Any] = {}
            for step in build_plan(rig, brackets):
                if update_desired_state(desired, step):
                    continue
                if isinstance(step, Meter):
                    yield from apply(desired, state)
                    yield from meter(step)
                    break  # exposures known now: rebuild the plan
                elif isinstance(step, Capture):
                    # the plan is rebuilt after each metering: what was taken stays taken
                    missing = [key for key in step.keys() if key not in taken]
                    if missing:
                        yield from apply(desired, state)
                    for key in missing:
                        frame = yield from read_frame(step.exposure_s, key, PRIMARY)
                        check_frame(frame, key, shape=shape, serial=identity.serial)
                        taken.add(key)
            else:
                break
        statistics = dict(camera.camera.stream_statistics())
        yield from bps.mv(note.scene, "", note.illumination, "", note.text, json.dumps(statistics))
        yield from bps.trigger_and_read([note], name=STATISTICS)

    yield from run()
    return brackets
