"""Thesis Algorithm 10 as Bluesky plans for the ophyd-async devices, whole and in parts.

- :func:`capture_protocol`: the whole protocol on a rig (metering and auto-bracketing,
  brackets, replicates, dark frames), carrying out the requests of
  :func:`labkit.protocol.protocol_steps`, as ``labkit capture``'s engine does, so the two
  make the same moves, meterings, frames and checks in the same order and write the same
  session. Run it again on the same session folder (Bluesky or ``labkit capture``) and it
  resumes at the first missing frame.
- Building blocks for plans of your own, inside :func:`session_run`: :func:`bracket` (one
  exposure bracket of a scene under an illumination), :func:`dark_series` (dark frames),
  :func:`acquire_frame` and :func:`meter_frame` (one frame).

The streams: ``primary``, one event per stored frame (its metadata, its file as a
``stream_resource``/``stream_datum`` pair, the slider, scene and cover); ``labkit_metering``
(the metering frames' levels); ``labkit_brackets`` (each auto-bracketing choice).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Generator, Iterable, Sequence
from typing import Any

import bluesky.plan_stubs as bps
import bluesky.preprocessors as bpp
from bluesky.utils import FailedStatus
from ophyd_async.core import StandardReadable, TriggerInfo, soft_signal_rw
from ophyd_async.plan_stubs import ensure_connected

import labkit
from labkit.bluesky.detector import SessionDetector
from labkit.bluesky.movables import LightCover, ScenePositioner, SliderPositioner
from labkit.bluesky.streams import BRACKETS, METERING, PRIMARY
from labkit.errors import ConfigError, LabkitError
from labkit.frame import DARK, Frame, FrameKey
from labkit.protocol import drive_within
from labkit.protocol.plan import build_plan, validate_plan
from labkit.protocol.steps import (
    Acquire,
    BracketChosen,
    Move,
    Request,
    StartCapture,
    configure_camera,
    protocol_steps,
)
from labkit.rig import Rig
from labkit.session.store import Session, plan_fingerprint, rig_snapshot

Plan = Generator[Any, Any, Any]


class BracketNote(StandardReadable):
    """An auto-bracketing choice, read into the ``labkit_brackets`` stream."""

    def __init__(self, name: str = "") -> None:
        with self.add_children_as_readables():
            self.scene = soft_signal_rw(str, "")
            self.illumination = soft_signal_rw(str, "")
            self.choice = soft_signal_rw(str, "{}")
        super().__init__(name=name)


def acquire_frame(
    detector: SessionDetector,
    exposure_s: float,
    key: FrameKey,
    *,
    readables: Sequence[Any] = (),
    stream: str = PRIMARY,
) -> Generator[Any, Any, Frame]:
    """Take and store the frame `key` at `exposure_s`, read with `readables`; returns it."""
    yield from bps.mv(
        detector.exposure_s, exposure_s, detector.scene, key.scene or "",
        detector.illumination, key.illumination, detector.replicate, key.replicate,
    )  # fmt: skip
    yield from bps.trigger_and_read([detector, *readables], name=stream)
    frame = detector.last_frame
    assert frame is not None, "a triggered detector has a frame"
    return frame


def meter_frame(detector: SessionDetector, exposure_s: float) -> Generator[Any, Any, Frame]:
    """Take a metering frame at `exposure_s` (kept in memory, not stored); returns it."""
    yield from bps.mv(detector.exposure_s, exposure_s)
    yield from bps.trigger_and_read([detector.metering], name=METERING)
    frame = detector.metering.last_frame
    assert frame is not None, "a triggered metering camera has a frame"
    return frame


def bracket(
    detector: SessionDetector,
    exposures_s: Iterable[float],
    *,
    scene: str | None,
    illumination: str,
    replicates: int = 1,
    readables: Sequence[Any] = (),
) -> Plan:
    """One exposure bracket: `replicates` frames of `scene` under `illumination` at each
    exposure time, s, skipping frames the session already holds. Inside
    :func:`session_run`; move the scene, slider and cover first."""
    for exposure_s in exposures_s:
        for replicate in range(replicates):
            key = FrameKey(scene, illumination, float(exposure_s), replicate)
            if not detector.taken(key):
                yield from acquire_frame(detector, float(exposure_s), key, readables=readables)


def dark_series(
    detector: SessionDetector,
    cover: LightCover,
    exposures_s: Iterable[float],
    *,
    replicates: int = 1,
    readables: Sequence[Any] = (),
) -> Plan:
    """Dark frames: the light covered, `replicates` frames at each exposure time, s, then
    the light uncovered. Inside :func:`session_run`."""
    yield from bps.mv(cover, True)
    yield from bracket(
        detector, exposures_s, scene=None, illumination=DARK, replicates=replicates,
        readables=readables,
    )  # fmt: skip
    yield from bps.mv(cover, False)


def session_run(
    detector: SessionDetector,
    body: Callable[[Session], Plan],
    *,
    devices: Sequence[Any] = (),
    md: dict[str, Any] | None = None,
) -> Plan:
    """Open a run that captures into the detector's session, and run ``body(session)``.

    The devices are connected, the detector staged and prepared (its session created, or
    opened to resume), `body` run, and the detector unstaged, which waits for every frame
    to be durable and closes the session: ``complete`` when the rig's plan is, ``failed``
    (with the error) when `body` raised, ``stopped`` otherwise. The start document carries
    the rig snapshot and plan fingerprint under ``labkit``.
    """
    rig = detector.target.rig
    snapshot = rig_snapshot(rig)
    metadata = {
        "plan_name": getattr(body, "__name__", "session_run"),
        "labkit": {
            "kind": "labkit-session-capture",
            "version": labkit.__version__,
            "session": str(detector.target.folder),
            "rig": snapshot,
            "rig_source": rig.source,
            "plan_fingerprint": plan_fingerprint(snapshot),
            "camera": detector.camera.identity.as_dict(),
            "devices": {"detector": detector.name, **{d.name: type(d).__name__ for d in devices}},
        },
        **(md or {}),
    }

    def record_failure(error: BaseException) -> Plan:
        while isinstance(error, FailedStatus) and error.__cause__ is not None:
            error = error.__cause__  # a device's status failed: say why
        detector.record_failure(
            str(error) if isinstance(error, LabkitError) else f"{type(error).__name__}: {error}"
        )
        yield from bps.null()

    def inside() -> Plan:
        yield from bps.prepare(detector, TriggerInfo(), wait=True)
        session = detector.session
        assert session is not None, "a prepared detector has its session open"
        return (yield from body(session))

    yield from ensure_connected(detector, *devices)
    return (
        yield from bpp.run_wrapper(
            bpp.stage_wrapper(
                bpp.contingency_wrapper(inside(), except_plan=record_failure),
                [detector],
            ),
            md=metadata,
        )
    )


def capture_protocol(
    detector: SessionDetector,
    slider: SliderPositioner,
    scene: ScenePositioner,
    cover: LightCover,
    *,
    md: dict[str, Any] | None = None,
) -> Generator[Any, Any, dict[tuple[str, str], list[float]]]:
    """Capture the detector's rig's plan (thesis Algorithm 10) into its session.

    Parameters
    ----------
    detector, slider, scene, cover
        The rig's devices (:func:`labkit.bluesky.open_session_devices` opens them).
    md : dict, optional
        Extra start-document metadata.

    Returns
    -------
    dict
        Every auto-bracketed exposure time, s, by (scene, illumination).

    Raises
    ------
    ConfigError
        A plan the camera or slider cannot run (checked before anything moves), or
        devices of another rig.
    DeviceError
        A frame that fails the checks (bad buffer, shape or exposure); the session is
        left ``failed`` and resumable.
    """
    rig = detector.target.rig
    _check_devices(rig, slider, scene)
    camera = detector.camera
    validate_plan(build_plan(rig), camera, slider.slider)
    note = BracketNote(name="bracket")
    readables = [slider, scene, cover]

    def carry_out(request: Request, session: Session) -> Generator[Any, Any, Frame | None]:
        match request:
            case Move("slot", value):
                yield from bps.mv(slider, value)
                session.log("move", value=value)
            case Move("scene", value):
                yield from bps.mv(scene, value)
                session.log("scene", value=value)
            case Move("covered", value):
                yield from bps.mv(cover, value)
                session.log("cover" if value else "uncover", value=None)
            case Acquire(exposure_s, key, metering):
                if metering:
                    return (yield from meter_frame(detector, exposure_s))
                return (yield from acquire_frame(detector, exposure_s, key, readables=readables))
            case BracketChosen(step, choice):
                session.save_bracket(step.scene, step.illumination, choice.as_dict())
                session.log(
                    "meter", scene=step.scene, illumination=step.illumination,
                    choice=choice.summary(), replicates=rig.replicates_for(step.illumination),
                )  # fmt: skip
                yield from bps.mv(
                    note.scene, step.scene, note.illumination, step.illumination,
                    note.choice, json.dumps(choice.as_dict()),
                )  # fmt: skip
                yield from bps.trigger_and_read([note], name=BRACKETS)
            case StartCapture(step, missing):
                session.log("capture", step=step.describe(), missing=len(missing))
        return None

    def protocol(session: Session) -> Generator[Any, Any, dict[tuple[str, str], list[float]]]:
        configure_camera(camera, rig)
        steps = protocol_steps(
            rig,
            brackets=session.brackets,
            done=detector.taken,
            exposure_bounds=camera.exposure_bounds,
            shape=camera.shape,
            serial=camera.identity.serial,
        )
        return (yield from drive_within(steps, lambda request: carry_out(request, session)))

    return (
        yield from session_run(
            detector,
            protocol,
            devices=[slider, scene, cover, note],
            md={"plan_name": "capture_protocol", **(md or {})},
        )
    )


def _check_devices(rig: Rig, slider: SliderPositioner, scene: ScenePositioner) -> None:
    names = rig.slider.position_names()
    if names != slider.positions:
        raise ConfigError(
            f"slider device {slider.name!r} has positions {slider.positions}, the rig "
            f"{names}; open the devices from the same rig (labkit.bluesky.open_session_devices)"
        )
    if set(rig.plan.scenes) - set(scene.scenes):
        raise ConfigError(
            f"scene device {scene.name!r} knows the scenes {scene.scenes}, the rig plans "
            f"{list(rig.plan.scenes)}; open the devices from the same rig"
        )
