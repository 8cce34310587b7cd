"""The engine that runs a capture plan into a session, and resumes it.

It keeps the plan's *desired* state (scene, slot, light cover) and applies it to the
hardware only before a step that still has frames to capture, so a resumed session
goes straight to its first missing frame. Every action is logged to ``log.jsonl``.
Frames are stored by a :class:`~labkit.session.FrameWriter` on background threads.
"""

from __future__ import annotations

import functools
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Protocol

from labkit.devices.camera import Camera
from labkit.devices.slider import FilterSlider
from labkit.errors import DeviceError, LabkitError
from labkit.frame import Frame
from labkit.io.plain import now_iso
from labkit.protocol.bracketing import run_auto_bracketing
from labkit.protocol.plan import (
    Capture,
    FrameKey,
    Meter,
    Plan,
    build_plan,
    pending_changes,
    update_desired_state,
    validate_plan,
)
from labkit.protocol.stage import Stage
from labkit.rig import Rig
from labkit.session.store import FrameWriter, Session


class Progress(Protocol):
    """Receives progress: the planned total, frames done, the current step.

    Any object with these methods will do; subclasses inherit no-ops for what they skip.
    """

    def set_total(self, total: int, done: int) -> None:
        """The plan now stores `total` frames, `done` of them already stored."""

    def advance(self, frames: int) -> None:
        """`frames` more frames were captured."""

    def set_step(self, text: str) -> None:
        """The step now running, in words."""


class _IgnoreProgress(Progress):
    """The default: progress goes nowhere."""


class CaptureStopped(LabkitError):
    """The capture was asked to stop (Ctrl-C); the session is resumable."""


@dataclass
class CaptureReport:
    """What a run did."""

    status: str
    planned: int
    stored_before: int
    stored_now: int
    recaptured: dict[str, str] = field(default_factory=dict)
    elapsed_s: float = 0.0
    bytes_written: int = 0
    brackets: dict[str, str] = field(default_factory=dict)

    @property
    def frames_per_s(self) -> float:
        """Frames stored per second of this run."""
        return self.stored_now / self.elapsed_s if self.elapsed_s > 0 else 0.0


class Engine:
    """Runs `rig`'s plan with the given devices into `session`.

    Parameters
    ----------
    rig : Rig
    camera : Camera
    slider : FilterSlider
    stage : Stage
        Scene changes and light cover.
    session : Session
    progress : Progress, optional
    stop : threading.Event, optional
        Set it (e.g. from a SIGINT handler) to stop after the current frame.
    writer_workers : int
        Threads storing frames.
    """

    def __init__(
        self,
        rig: Rig,
        camera: Camera,
        slider: FilterSlider,
        stage: Stage,
        session: Session,
        *,
        progress: Progress | None = None,
        stop: threading.Event | None = None,
        writer_workers: int = 2,
    ) -> None:
        self.rig = rig
        self.camera = camera
        self.slider = slider
        self.stage = stage
        self.session = session
        self.progress = progress or _IgnoreProgress()
        self.stop = stop or threading.Event()
        self.writer_workers = writer_workers
        self._state: dict[str, Any] = {}  # what the hardware is known to be doing

    def plan(self) -> Plan:
        """The plan with the exposures chosen so far."""
        return build_plan(self.rig, self.session.brackets)

    def run(self) -> CaptureReport:
        """Capture every missing frame; returns a report. Raises CaptureStopped on stop."""
        session = self.session
        started = time.perf_counter()
        plan = self.plan()
        validate_plan(plan, self.camera, self.slider)
        configure_camera(self.camera, self.rig)
        self._shape = self.camera.shape  # read once: a device round-trip on real cameras
        self._serial = self.camera.identity.serial
        session.remove_leftovers()
        problems = session.verify()
        if problems:
            session.forget(problems)
            session.log("recapture", frames=problems)
        stored_before = len(session.records)
        self._bytes_before = session.stored_bytes()
        session.info["camera"] = self.camera.identity.as_dict()
        session.info["slider"] = {"port": self.slider.port, "identity": self.slider.identity}
        session.info.setdefault("runs", []).append(
            {"started": now_iso(), "resumed_with": stored_before}
        )
        session.set_status("running")
        self._continue_frame_ids()
        report = CaptureReport("running", plan.frame_count, stored_before, 0, recaptured=problems)
        try:
            with FrameWriter(session, workers=self.writer_workers) as writer:
                self._run_plan(writer, report)
        except CaptureStopped as stop:
            self._finish(report, "stopped", str(stop), started)
            raise
        except LabkitError as error:
            self._finish(report, "failed", str(error), started)
            raise
        except BaseException as error:
            self._finish(report, "failed", f"{type(error).__name__}: {error}", started)
            raise
        self._finish(report, "complete", None, started)
        return report

    # -- the loop -----------------------------------------------------------------------------
    def _run_plan(self, writer: FrameWriter, report: CaptureReport) -> None:
        while True:
            plan = self.plan()
            report.planned = plan.frame_count
            self.progress.set_total(plan.frame_count, sum(writer.has(k) for k in plan.keys()))
            desired: dict[str, Any] = {}
            for step in plan:
                if update_desired_state(desired, step):
                    continue
                if isinstance(step, Meter):
                    self._apply(desired)
                    self._meter(step, report)
                    break  # exposures known now: rebuild the plan
                elif isinstance(step, Capture):
                    # queued frames count: the plan is rebuilt while writes are pending
                    missing = [k for k in step.keys() if not writer.has(k)]
                    if missing:
                        self._apply(desired)
                        self._capture(step, missing, writer)
            else:
                return

    def _apply(self, desired: dict[str, Any]) -> None:
        for key, value in pending_changes(desired, self._state):
            if key == "covered":
                action = self.stage.cover_light if value else self.stage.uncover_light
                self._act(action, "cover" if value else "uncover")
            elif key == "scene":
                self._act(functools.partial(self.stage.set_scene, value), "scene", value)
            else:
                self._act(functools.partial(self.slider.move, value), "move", value)
            self._state[key] = value

    def _act(self, action: Any, event: str, value: Any = None) -> None:
        self._check_stop()
        self.progress.set_step(f"{event} {value}" if value is not None else event)
        action()
        self.session.log(event, value=value)

    def _capture(self, step: Capture, missing: list[FrameKey], writer: FrameWriter) -> None:
        self.progress.set_step(step.describe())
        self.session.log("capture", step=step.describe(), missing=len(missing))
        for key in missing:
            self._check_stop()
            frame = self.camera.grab(step.exposure_s, 1)[0]
            self._check_frame(frame, key)
            writer.submit(key, frame)
            self.progress.advance(1)

    def _check_frame(self, frame: Frame, key: FrameKey) -> None:
        check_frame(frame, key, shape=self._shape, serial=self._serial)

    def _meter(self, step: Meter, report: CaptureReport) -> None:
        auto = self.rig.plan.auto
        self.progress.set_step(f"meter {step.scene}/{step.illumination}")
        bounds = self.camera.exposure_bounds()
        choice = run_auto_bracketing(self.camera, bounds=bounds, auto=auto)
        fixed = self.rig.replicates_for(step.illumination)
        self.session.save_bracket(step.scene, step.illumination, choice.as_dict())
        self.session.log(
            "meter",
            scene=step.scene,
            illumination=step.illumination,
            choice=choice.summary(),
            replicates=fixed,
        )
        report.brackets[f"{step.scene}/{step.illumination}"] = choice.summary()

    # -- set-up and finish ---------------------------------------------------------------------
    def _continue_frame_ids(self) -> None:
        """A simulated camera draws noise by frame id: never reuse one within a session."""
        if hasattr(self.camera, "next_frame_id") and self.session.records:
            last = max(int(r.get("frame_id") or 0) for r in self.session.records.values())
            self.camera.next_frame_id = max(self.camera.next_frame_id, last + 1)

    def _check_stop(self) -> None:
        if self.stop.is_set():
            raise CaptureStopped(
                f"capture stopped on request after {len(self.session.records)} stored frames; "
                f"run the same command again to resume session {self.session.folder}"
            )

    def _finish(self, report: CaptureReport, status: str, reason: str | None, t0: float) -> None:
        report.status = status
        report.elapsed_s = time.perf_counter() - t0
        report.stored_now = len(self.session.records) - report.stored_before
        report.bytes_written = self.session.stored_bytes() - self._bytes_before
        session = self.session
        session.info["stream_statistics"] = dict(self.camera.stream_statistics())
        session.info["runs"][-1].update(
            {"stopped": now_iso(), "status": status, "stored": report.stored_now}
        )
        session.log("finish", status=status, reason=reason, stored=report.stored_now)
        session.set_status(status, reason)


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
