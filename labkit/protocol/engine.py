"""The engine that runs a capture plan into a session, and resumes it.

It carries out the requests of Algorithm 10 (:func:`~labkit.protocol.steps.protocol_steps`)
on the devices: the stage, light cover and slider move only before a step that still has
frames to capture, so a resumed session goes straight to its first missing frame. Every
action is logged to ``log.jsonl``. Frames are stored by a
:class:`~labkit.session.FrameWriter` on background threads.
"""

from __future__ import annotations

import functools
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Protocol

from labkit.devices.camera import Camera
from labkit.devices.slider import FilterSlider
from labkit.errors import LabkitError
from labkit.frame import Frame
from labkit.protocol._generators import drive
from labkit.protocol.bracketing import BracketChoice
from labkit.protocol.capture_run import CaptureRun
from labkit.protocol.plan import Meter, Plan, build_plan, validate_plan
from labkit.protocol.stage import Stage
from labkit.protocol.steps import (
    Acquire,
    BracketChosen,
    Move,
    PlanReady,
    Record,
    Request,
    StartCapture,
    StartMeter,
    configure_camera,
    protocol_steps,
)
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

    def plan(self) -> Plan:
        """The plan with the exposures chosen so far."""
        return build_plan(self.rig, self.session.brackets)

    def run(self) -> CaptureReport:
        """Capture every missing frame; returns a report. Raises CaptureStopped on stop."""
        started = time.perf_counter()
        plan = self.plan()
        validate_plan(plan, self.camera, self.slider)
        configure_camera(self.camera, self.rig)
        self._shape = self.camera.shape  # read once: a device round-trip on real cameras
        self._serial = self.camera.identity.serial
        run = CaptureRun(
            self.session,
            self.camera,
            {"port": self.slider.port, "identity": self.slider.identity},
        )
        problems = run.begin()
        report = CaptureReport(
            "running", plan.frame_count, run.stored_before, 0, recaptured=problems
        )
        try:
            with FrameWriter(self.session, workers=self.writer_workers) as writer:
                self._run_plan(writer, report)
        except CaptureStopped as stop:
            self._finish(run, report, "stopped", str(stop), started)
            raise
        except LabkitError as error:
            self._finish(run, report, "failed", str(error), started)
            raise
        except BaseException as error:
            self._finish(run, report, "failed", f"{type(error).__name__}: {error}", started)
            raise
        self._finish(run, report, "complete", None, started)
        return report

    # -- the loop: Algorithm 10's requests, carried out on the devices ------------------------
    def _run_plan(self, writer: FrameWriter, report: CaptureReport) -> None:
        steps = protocol_steps(
            self.rig,
            brackets=self.session.brackets,
            done=writer.has,  # queued frames count: the plan is rebuilt while writes are pending
            exposure_bounds=self.camera.exposure_bounds,
            shape=self._shape,
            serial=self._serial,
        )
        drive(steps, functools.partial(self._carry_out, writer=writer, report=report))

    def _carry_out(
        self, request: Request, *, writer: FrameWriter, report: CaptureReport
    ) -> Frame | None:
        match request:
            case PlanReady(plan):
                report.planned = plan.frame_count
                self.progress.set_total(plan.frame_count, sum(writer.has(k) for k in plan.keys()))
            case Move(what, value):
                self._move(what, value)
            case StartMeter(step):
                self.progress.set_step(f"meter {step.scene}/{step.illumination}")
            case Acquire(exposure_s, _, metering):
                if not metering:
                    self._check_stop()
                return self.camera.grab(exposure_s, 1)[0]
            case BracketChosen(step, choice):
                self._record_bracket(step, choice, report)
            case StartCapture(step, missing):
                self.progress.set_step(step.describe())
                self.session.log("capture", step=step.describe(), missing=len(missing))
            case Record(key, frame):
                writer.submit(key, frame)
                self.progress.advance(1)
        return None

    def _move(self, what: str, value: Any) -> None:
        if what == "covered":
            action = self.stage.cover_light if value else self.stage.uncover_light
            self._act(action, "cover" if value else "uncover")
        elif what == "scene":
            self._act(functools.partial(self.stage.set_scene, value), "scene", value)
        else:
            self._act(functools.partial(self.slider.move, value), "move", value)

    def _act(self, action: Any, event: str, value: Any = None) -> None:
        self._check_stop()
        self.progress.set_step(f"{event} {value}" if value is not None else event)
        action()
        self.session.log(event, value=value)

    def _record_bracket(self, step: Meter, choice: BracketChoice, report: CaptureReport) -> None:
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

    # -- finish ------------------------------------------------------------------------------
    def _check_stop(self) -> None:
        if self.stop.is_set():
            raise CaptureStopped(
                f"capture stopped on request after {len(self.session.records)} stored frames; "
                f"run the same command again to resume session {self.session.folder}"
            )

    def _finish(
        self, run: CaptureRun, report: CaptureReport, status: str, reason: str | None, t0: float
    ) -> None:
        run.finish(status, reason)
        report.status = status
        report.elapsed_s = time.perf_counter() - t0
        report.stored_now = run.stored_now
        report.bytes_written = run.bytes_written
