"""Any labkit camera as an ophyd-async detector that writes a labkit session.

:class:`SessionDetector` is a :class:`ophyd_async.core.StandardDetector` built from
ophyd-async's three kinds of logic, which together play the roles of a controller (arm,
trigger, disarm) and a writer (store the frames, describe them):

- trigger logic: the exposure time of the next frame (``exposure_s``, or a
  :class:`~ophyd_async.core.TriggerInfo`'s ``livetime``);
- acquire logic: one frame per trigger, grabbed on a worker thread so that the RunEngine's
  event loop stays free while the camera integrates (another device may move meanwhile);
- data logic: each frame checked (:func:`labkit.protocol.check_frame`) and stored in the
  session format, TIFF plus its ``frames.jsonl`` record with its SHA-256, by the same
  :class:`~labkit.session.FrameWriter` and run bookkeeping
  (:class:`~labkit.protocol.capture_run.CaptureRun`) as ``labkit capture``, so the
  session is the one ``labkit capture`` would have written.

What a reading holds: the frame's metadata (``<name>-frame_id``, ``-exposure_s``, …, and
its session ``-key``) as values, and the pixels (``<name>``) as an external ``STREAM:``
key. The pixels travel as a ``stream_resource`` document naming the frame's file in the
session (mimetype ``multipart/related;type=image/tiff``, one file, so ``TiledWriter`` can
register it) and a ``stream_datum`` giving its index; no document carries pixels.

The frame's place in the session is set before each trigger: ``scene`` (``""`` for a
dark frame), ``illumination`` and ``replicate``. Metering frames, which auto-bracketing
looks at but a session does not keep, are taken by the child device ``metering``.
"""

from __future__ import annotations

import asyncio
import dataclasses
import time
from collections.abc import AsyncIterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from bluesky.protocols import Reading, StreamAsset
from event_model import ComposeStreamResource, DataKey
from ophyd_async.core import (
    AsyncStatus,
    DetectorAcquireLogic,
    DetectorDataLogic,
    DetectorTriggerLogic,
    ReadableDataProvider,
    SignalRW,
    StandardDetector,
    StandardReadable,
    StreamableDataProvider,
    TriggerInfo,
    soft_signal_r_and_setter,
    soft_signal_rw,
)

from labkit.devices.camera import Camera
from labkit.errors import ConfigError, DeviceError
from labkit.frame import DARK, Frame, FrameKey
from labkit.protocol.capture_run import CaptureRun, plan_shortfall, resume_hint
from labkit.protocol.steps import check_frame
from labkit.rig import Rig
from labkit.session.store import FrameWriter, Session

TIFF_SEQUENCE = "multipart/related;type=image/tiff"
"""The mimetype of the stream resources: ``TiledWriter`` registers them as TIFF files."""

FRAME_FACTS: dict[str, tuple[str, str]] = {
    "frame_id": ("integer", "<i8"),
    "exposure_s": ("number", "<f8"),
    "exposure_readback_s": ("number", "<f8"),
    "gain_db": ("number", "<f8"),
    "pixel_format": ("string", "|S40"),
    "device_timestamp_ns": ("integer", "<i8"),
    "host_timestamp_s": ("number", "<f8"),
    "status": ("string", "|S40"),
    "key": ("string", "|S40"),
}
"""The frame metadata in each reading of a :class:`SessionDetector`, with their
event-model dtypes: ``<name>-<fact>``; ``key`` is the frame's session key."""


@dataclasses.dataclass(frozen=True)
class SessionTarget:
    """The session a :class:`SessionDetector` stores its frames in.

    Parameters
    ----------
    folder : Path
        The session folder: created, or resumed when it holds a session of `rig`'s plan
        (:meth:`labkit.session.Session.open_for`).
    rig : Rig
        The rig whose plan the session records.
    slider : mapping
        The slider's facts recorded in ``session.yaml`` (``port``, ``identity``).
    writer_workers : int
        Threads storing frames.
    """

    folder: Path
    rig: Rig
    slider: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    writer_workers: int = 2


class _Acquisition:
    """What the three logics of one detector share: the camera, the next frame's
    exposure and key, and the frames grabbed."""

    def __init__(self, camera: Camera, exposure_s: SignalRW[float]) -> None:
        self.camera = camera
        self.exposure_s = exposure_s
        self.key: FrameKey | None = None
        self.last_frame: Frame | None = None
        self.stored: list[FrameKey] = []
        self.attempts = 0
        self.grabbed, self.set_grabbed = soft_signal_r_and_setter(int, 0)
        self.shape: tuple[int, int] = (0, 0)
        self.serial = ""

    def restart(self) -> None:
        """A new session run: no frame stored by it yet. The camera's shape and serial are
        read once here, not per frame (each is a device round-trip on a real camera)."""
        self.stored = []
        self.attempts = 0
        self.set_grabbed(0)
        self.shape = self.camera.shape
        self.serial = self.camera.identity.serial

    async def grab(self) -> Frame:
        exposure_s = float(await self.exposure_s.get_value())
        frames = await asyncio.to_thread(self.camera.grab, exposure_s, 1)
        return frames[0]


class _ExposureLogic(DetectorTriggerLogic):
    """Internal triggering, one frame per trigger at ``exposure_s`` (or `livetime`)."""

    def __init__(self, acquisition: _Acquisition) -> None:
        self.acquisition = acquisition

    async def prepare_internal(self, num: int, livetime: float, deadtime: float) -> None:
        if num != 1:
            raise ConfigError(
                f"a labkit detector takes one frame per trigger, not {num}; trigger it "
                "once per frame (each frame has its own key in the session)"
            )
        if livetime:
            await self.acquisition.exposure_s.set(livetime)

    async def default_trigger_info(self) -> TriggerInfo:
        return TriggerInfo()


class _SessionStore:
    """The session being written and its run's bookkeeping (open from prepare to unstage)."""

    def __init__(self, target: SessionTarget, camera: Camera) -> None:
        self.target = target
        self.camera = camera
        self.session: Session | None = None
        self.writer: FrameWriter | None = None
        self.run: CaptureRun | None = None
        self.failure: str | None = None

    def open(self) -> Session:
        if self.session is not None:
            return self.session
        session, _ = Session.open_for(self.target.folder, self.target.rig)
        run = CaptureRun(session, self.camera, self.target.slider)
        run.begin()
        self.session, self.run, self.failure = session, run, None
        self.writer = FrameWriter(session, workers=self.target.writer_workers)
        return session

    def close(self) -> None:
        session, writer, run = self.session, self.writer, self.run
        if session is None or writer is None or run is None:
            return
        self.session = self.writer = self.run = None
        try:
            writer.close()
        except Exception as error:  # the frame that failed to store is missing: resumable
            self.failure = self.failure or f"storing frames failed: {type(error).__name__}: {error}"
        shortfall = plan_shortfall(session)
        if self.failure is None and shortfall is None:
            run.finish("complete", None)
            return
        reason = self.failure or f"the run ended with {shortfall}"
        status = "failed" if self.failure else "stopped"
        run.finish(status, f"{reason}; {resume_hint(session.folder)}")


class _AcquireLogic(DetectorAcquireLogic):
    """A trigger grabs one frame on a worker thread, checks it and queues it for storage."""

    def __init__(self, acquisition: _Acquisition, store: _SessionStore) -> None:
        self.acquisition = acquisition
        self.store = store
        self.task: asyncio.Task[None] | None = None

    async def start_acquiring(self) -> None:
        self.task = asyncio.create_task(self._acquire())

    async def _acquire(self) -> None:
        acquisition, store = self.acquisition, self.store
        key = acquisition.key
        if key is None:
            raise ConfigError("set the detector's scene, illumination and replicate first")
        if store.writer is None:
            raise ConfigError("the detector's session is not open: prepare or trigger it")
        try:
            frame = await acquisition.grab()
            check_frame(frame, key, shape=acquisition.shape, serial=acquisition.serial)
            store.writer.submit(key, frame)
            acquisition.last_frame = frame
            acquisition.stored.append(key)
        finally:
            # counted even when it failed, so the trigger stops waiting and wait_for_idle
            # raises the error (else the trigger would time out with a bare TimeoutError)
            acquisition.attempts += 1
            acquisition.set_grabbed(acquisition.attempts)

    async def wait_for_idle(self) -> None:
        if self.task is not None:
            task, self.task = self.task, None
            await task

    async def ensure_stopped(self) -> None:
        if self.task is not None:
            await asyncio.gather(self.task, return_exceptions=True)
            self.task = None


class _FrameFiles(StreamableDataProvider):
    """Describes the stored frames: one stream resource per file, one datum per frame."""

    def __init__(self, name: str, acquisition: _Acquisition, folder: Path) -> None:
        self.name = name
        self.acquisition = acquisition
        self.collections_written_signal = acquisition.grabbed
        self.folder_uri = folder.resolve().as_uri() + "/"
        self.emitted = 0
        self.compose = ComposeStreamResource()

    async def make_datakeys(self, collections_per_event: int) -> dict[str, DataKey]:
        rows, cols = self.acquisition.shape
        return {
            self.name: DataKey(
                source=self.folder_uri,
                shape=[collections_per_event, rows, cols],
                dtype="array",
                dtype_numpy=np.dtype(np.uint16).str,
                external="STREAM:",
            )
        }

    async def make_stream_docs(
        self, collections_written: int, collections_per_event: int
    ) -> AsyncIterator[StreamAsset]:
        rows, cols = self.acquisition.shape
        while self.emitted < len(self.acquisition.stored):  # failed attempts have no file
            key = self.acquisition.stored[self.emitted]
            bundle = self.compose(
                mimetype=TIFF_SEQUENCE,
                uri=self.folder_uri,
                data_key=self.name,
                parameters={
                    # a template without a field: this one file, whatever the index
                    "template": key.path.replace("{", "{{").replace("}", "}}"),
                    "chunk_shape": (1, rows, cols),
                    "labkit_key": key.id,
                },
            )
            yield "stream_resource", bundle.stream_resource_doc
            yield (
                "stream_datum",
                bundle.compose_stream_datum({"start": self.emitted, "stop": self.emitted + 1}),
            )
            self.emitted += 1


class _FrameFacts(ReadableDataProvider):
    """The metadata of the frame just taken, as readings."""

    def __init__(self, name: str, acquisition: _Acquisition) -> None:
        self.name = name
        self.acquisition = acquisition

    async def make_datakeys(self) -> dict[str, DataKey]:
        return {
            f"{self.name}-{fact}": DataKey(
                source=f"labkit:{self.name}/{fact}", dtype=dtype, shape=[], dtype_numpy=numpy
            )
            for fact, (dtype, numpy) in FRAME_FACTS.items()
        }

    async def make_readings(self) -> dict[str, Reading]:
        frame, key = self.acquisition.last_frame, self.acquisition.key
        if frame is None or key is None:
            raise DeviceError(f"detector {self.name}: read before a frame was taken")
        values = {fact: getattr(frame, fact) for fact in FRAME_FACTS if fact != "key"}
        values["key"] = key.id
        stamp = float(frame.host_timestamp_s) or time.time()
        return {f"{self.name}-{k}": {"value": v, "timestamp": stamp} for k, v in values.items()}


class _SessionDataLogic(DetectorDataLogic):
    """Frames go into the session; their files and metadata are described."""

    def __init__(self, acquisition: _Acquisition, store: _SessionStore) -> None:
        self.acquisition = acquisition
        self.store = store

    async def prepare_unbounded(self, datakey_name: str) -> StreamableDataProvider:
        await asyncio.to_thread(self.store.open)
        self.acquisition.restart()
        return _FrameFiles(datakey_name, self.acquisition, self.store.target.folder)

    def get_hinted_fields(self, datakey_name: str) -> Sequence[str]:
        return [datakey_name]

    async def stop(self) -> None:
        await asyncio.to_thread(self.store.close)


class _FactsDataLogic(DetectorDataLogic):
    datakey_suffix = "-facts"

    def __init__(self, acquisition: _Acquisition) -> None:
        self.acquisition = acquisition

    async def prepare_single(self, datakey_name: str) -> ReadableDataProvider:
        return _FrameFacts(datakey_name.removesuffix(self.datakey_suffix), self.acquisition)


class MeteringCamera(StandardReadable):
    """The detector's camera for metering: a trigger grabs one frame at ``exposure_s``
    that is kept in memory (:attr:`last_frame`) for auto-bracketing, never stored; a
    reading holds its metadata and its mean and maximum, DN."""

    def __init__(self, acquisition: _Acquisition, name: str = "") -> None:
        self._acquisition = acquisition
        self.last_frame: Frame | None = None
        with self.add_children_as_readables():
            self.frame_id, self._set_frame_id = soft_signal_r_and_setter(int, 0)
            self.exposure_readback_s, self._set_readback = soft_signal_r_and_setter(float, 0.0)
            self.mean_dn, self._set_mean = soft_signal_r_and_setter(float, 0.0)
            self.max_dn, self._set_max = soft_signal_r_and_setter(float, 0.0)
        super().__init__(name=name)

    @AsyncStatus.wrap
    async def trigger(self) -> None:
        """Grab one metering frame (on a worker thread)."""
        frame = await self._acquisition.grab()
        self.last_frame = frame
        self._set_frame_id(int(frame.frame_id))
        self._set_readback(float(frame.exposure_readback_s))
        self._set_mean(float(frame.image.mean()))
        self._set_max(float(frame.image.max()))


class SessionDetector(StandardDetector):
    """A labkit camera as an ophyd-async detector whose frames go into a labkit session.

    Set ``exposure_s`` and the next frame's place (``scene``, ``illumination``,
    ``replicate``) before each trigger; plans do this
    (:func:`labkit.bluesky.acquire_frame`). See the module for what is read and written.

    Parameters
    ----------
    camera : Camera
        An open camera (Aravis, GenTL or simulated); the detector does not close it.
    target : SessionTarget
        The session (folder and rig) its frames are stored in.
    name : str
        The device name, the data key of its frames.
    """

    def __init__(self, camera: Camera, target: SessionTarget, *, name: str = "camera") -> None:
        self.camera = camera
        self.target = target
        self.exposure_s = soft_signal_rw(float, 0.01, units="s")
        self.scene = soft_signal_rw(str, "")
        self.illumination = soft_signal_rw(str, "")
        self.replicate = soft_signal_rw(int, 0)
        self._acquisition = _Acquisition(camera, self.exposure_s)
        self._store = _SessionStore(target, camera)
        self.metering = MeteringCamera(self._acquisition)
        self.add_detector_logics(
            _ExposureLogic(self._acquisition),
            _AcquireLogic(self._acquisition, self._store),
            _SessionDataLogic(self._acquisition, self._store),
            _FactsDataLogic(self._acquisition),
        )
        super().__init__(name=name)

    @property
    def session(self) -> Session | None:
        """The session being written (between prepare, or the first trigger, and unstage)."""
        return self._store.session

    @property
    def last_frame(self) -> Frame | None:
        """The frame the last trigger stored."""
        return self._acquisition.last_frame

    def taken(self, key: FrameKey) -> bool:
        """Whether `key`'s frame is stored, or queued to be, in the open session."""
        writer = self._store.writer
        return writer is not None and writer.has(key)

    def record_failure(self, reason: str) -> None:
        """Close the session, at unstage, as ``failed`` with `reason` (a plan's error)."""
        self._store.failure = reason

    async def _set_key(self) -> None:
        scene, illumination, replicate, exposure_s = await asyncio.gather(
            self.scene.get_value(),
            self.illumination.get_value(),
            self.replicate.get_value(),
            self.exposure_s.get_value(),
        )
        if not scene and illumination != DARK:
            raise ConfigError(
                f"detector {self.name}: a frame without a scene must be a dark frame "
                f"(illumination {DARK!r}), not {illumination!r}"
            )
        self._acquisition.key = FrameKey(scene or None, illumination, exposure_s, replicate)

    @AsyncStatus.wrap
    async def trigger(self) -> None:  # type: ignore[override]
        """Grab one frame and store it in the session under the key set beforehand."""
        await self._set_key()
        await super().trigger()
