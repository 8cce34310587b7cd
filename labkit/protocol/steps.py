"""Thesis Algorithm 10 once: the capture protocol as one generator of requests.

:func:`protocol_steps` walks a rig's plan and says what to do next, one request at a
time; a driver carries each out and sends back what it asks for. ``labkit capture``'s
:class:`~labkit.protocol.engine.Engine` drives it with the devices themselves, the
Bluesky plan (:func:`labkit.bluesky.labkit_plan`) with a RunEngine's messages, so the two
make the same moves, meterings, choices, checks and frames in the same order.

The requests, in the order a plan makes them:

:class:`PlanReady`
    The plan (re)built: with every exposure time known so far.
:class:`Move`
    Bring the stage, the light cover or the filter slider to a state, only when it must
    change.
:class:`StartMeter`, then :class:`Acquire` (``metering``), then :class:`BracketChosen`
    An ``auto`` illumination metered, its exposure times chosen and checked on the
    camera's frames (:func:`~labkit.protocol.bracketing.auto_bracketing`); the plan is
    then rebuilt.
:class:`StartCapture`, then :class:`Acquire` and :class:`Record` per missing frame
    A step's frames grabbed, each checked (:func:`check_frame`) before it is recorded.

An :class:`Acquire` is answered with the :class:`~labkit.frame.Frame` captured; every
other request with nothing; :func:`labkit.protocol.drive` carries them out with a
function that does so.
"""

from __future__ import annotations

from collections.abc import Callable, Generator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from labkit.devices.camera import Bounds, Camera
from labkit.errors import DeviceError
from labkit.frame import Frame, FrameKey
from labkit.protocol.bracketing import BracketChoice, auto_bracketing
from labkit.protocol.plan import (
    Capture,
    Meter,
    Plan,
    build_plan,
    pending_changes,
    update_desired_state,
)
from labkit.rig import AutoExposureConfig, Rig


@dataclass(frozen=True)
class PlanReady:
    """The plan, built with the exposure times chosen so far."""

    plan: Plan


@dataclass(frozen=True)
class Move:
    """Set `what` (``"scene"``, ``"covered"`` or ``"slot"``) to `value`."""

    what: str
    value: Any


@dataclass(frozen=True)
class StartMeter:
    """Metering of an ``auto`` illumination begins."""

    step: Meter


@dataclass(frozen=True)
class Acquire:
    """Grab one frame of `key` at `exposure_s`; answer with the :class:`Frame`.

    `metering`: a metering or checking frame of auto-bracketing (its key's exposure is 0),
    not a frame of the plan.
    """

    exposure_s: float
    key: FrameKey
    metering: bool


@dataclass(frozen=True)
class BracketChosen:
    """The exposure times chosen for an ``auto`` illumination."""

    step: Meter
    choice: BracketChoice


@dataclass(frozen=True)
class StartCapture:
    """A capture step with frames still `missing` begins."""

    step: Capture
    missing: tuple[FrameKey, ...]


@dataclass(frozen=True)
class Record:
    """A checked frame of the plan: store it."""

    key: FrameKey
    frame: Frame


Request = PlanReady | Move | StartMeter | Acquire | BracketChosen | StartCapture | Record


def protocol_steps(
    rig: Rig,
    *,
    brackets: Mapping[tuple[str, str], Sequence[float]],
    done: Callable[[FrameKey], bool],
    exposure_bounds: Callable[[], Bounds],
    shape: tuple[int, int],
    serial: str,
) -> Generator[Request, Frame | None, dict[tuple[str, str], list[float]]]:
    """Algorithm 10 on `rig`'s plan, as requests (see the module).

    Parameters
    ----------
    rig : Rig
    brackets : mapping
        Exposure times already chosen, s, by (scene, illumination) (a resumed session's).
    done : callable
        Whether a frame is already stored (or queued): it is not captured again.
    exposure_bounds : callable
        The camera's exposure range, asked at each metering.
    shape, serial : tuple, str
        The camera's image shape and serial number, which frames are checked against.

    Returns
    -------
    dict
        Every exposure time chosen, s, by (scene, illumination).
    """
    chosen = {key: list(times) for key, times in brackets.items()}
    state: dict[str, Any] = {}  # what the hardware is known to be doing
    while True:
        plan = build_plan(rig, chosen)
        yield PlanReady(plan)
        desired: dict[str, Any] = {}
        for step in plan:
            if update_desired_state(desired, step):
                continue
            if isinstance(step, Meter):
                yield from _moves(desired, state)
                yield StartMeter(step)
                choice = yield from _meter(step, rig.plan.auto, exposure_bounds())
                chosen[step.scene, step.illumination] = list(choice.exposures_s)
                yield BracketChosen(step, choice)
                break  # exposures known now: rebuild the plan
            if isinstance(step, Capture):
                missing = tuple(k for k in step.keys() if not done(k))
                if not missing:
                    continue
                yield from _moves(desired, state)
                yield StartCapture(step, missing)
                for key in missing:
                    frame = yield Acquire(step.exposure_s, key, metering=False)
                    assert frame is not None, "an Acquire request is answered with a frame"
                    check_frame(frame, key, shape=shape, serial=serial)
                    yield Record(key, frame)
        else:
            return chosen


def _moves(desired: dict[str, Any], state: dict[str, Any]) -> Generator[Move, Any, None]:
    for what, value in pending_changes(desired, state):
        yield Move(what, value)
        state[what] = value


def _meter(
    step: Meter, auto: AutoExposureConfig, bounds: Bounds
) -> Generator[Acquire, Frame | None, BracketChoice]:
    """Auto-bracketing of `step`'s illumination, one metering frame per request."""
    sequence = auto_bracketing(bounds, auto)
    key = FrameKey(step.scene, step.illumination, 0.0, 0)
    exposure = next(sequence)
    try:
        while True:
            frame = yield Acquire(exposure, key, metering=True)
            assert frame is not None, "an Acquire request is answered with a frame"
            exposure = sequence.send(frame)
    except StopIteration as finished:
        return finished.value


def configure_camera(camera: Camera, rig: Rig) -> None:
    """Set the rig's pixel format and gain on `camera`, checking the gain first.

    Raises
    ------
    DeviceError
        A gain outside the camera's range, or a non-zero gain on a camera without a
        ``Gain`` feature in dB.
    """
    config = rig.camera
    if camera.pixel_format != config.pixel_format:
        camera.set_pixel_format(config.pixel_format)
    serial = camera.identity.serial
    if "Gain" not in camera.feature_names():
        if config.gain_db:
            raise DeviceError(
                f"camera {serial} has no Gain feature in dB, so camera.gain_db "
                f"{config.gain_db:g} cannot be applied; set camera.gain_db to 0"
            )
        return
    gain = camera.gain_bounds()
    if not gain.contains(config.gain_db):
        raise DeviceError(
            f"camera {serial}: gain {config.gain_db:g} dB is outside "
            f"[{gain.minimum:g}, {gain.maximum:g}] dB; change camera.gain_db in the rig file"
        )
    camera.set("Gain", config.gain_db)


def check_frame(frame: Frame, key: FrameKey, *, shape: tuple[int, int], serial: str) -> None:
    """Raise DeviceError unless `frame` is a good capture of `key`: a ``SUCCESS`` buffer of
    `shape` exposed for the planned time (within 1e-9 relative)."""
    if frame.status != "SUCCESS":
        problem = f"buffer status {frame.status}; the session can be resumed"
    elif frame.image.shape != shape:
        problem = f"image shape {frame.image.shape} ≠ {shape}"
    elif abs(frame.exposure_s - key.exposure_s) > 1e-9 * max(1.0, key.exposure_s):
        problem = f"exposure {frame.exposure_s} s ≠ planned {key.exposure_s} s"
    else:
        return
    raise DeviceError(f"camera {serial}, frame {frame.frame_id} for {key.id}: {problem}")
