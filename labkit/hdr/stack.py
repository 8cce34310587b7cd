"""Streaming statistics of the replicate frames of one exposure (and of dark frames).

Frames are read one at a time (the next one is loaded on a helper thread while the
current one is summed), so memory stays a few frames whatever the replicate count.
Sums are taken of each frame's difference from the first frame, which keeps the float32
variance free of the cancellation that sums of squared raw counts would suffer.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from labkit.errors import DataError

FrameLoader = Callable[[], np.ndarray]


@dataclass(frozen=True)
class FrameSource:
    """One raw frame to be read on demand.

    Attributes
    ----------
    name : str
        What error messages call the frame (e.g. its session key and file).
    load : callable
        Returns the (rows, cols) integer mosaic; raises DataError when unreadable.
    """

    name: str
    load: FrameLoader


@dataclass
class ExposureInput:
    """The replicate frames of one exposure time of one (scene, illumination)."""

    exposure_s: float
    frames: list[FrameSource]

    @classmethod
    def from_arrays(
        cls, exposure_s: float, arrays: Sequence[np.ndarray], *, name: str = "frame"
    ) -> ExposureInput:
        """Wrap in-memory frames (tests, notebooks)."""
        sources = [
            FrameSource(f"{name} {exposure_s:g} s #{index}", lambda array=array: array)
            for index, array in enumerate(arrays)
        ]
        return cls(float(exposure_s), sources)


@dataclass
class FrameStats:
    """Per-pixel statistics of the replicates of one exposure.

    Attributes
    ----------
    exposure_s : float
        Exposure time, s.
    count : int
        Number of replicates.
    mean : ndarray (rows, cols) float32
        Mean counts, DN.
    maximum : ndarray (rows, cols), the frames' integer dtype
        Largest replicate value, DN (detects clipping in any replicate).
    variance : ndarray (rows, cols) float32 or None
        Unbiased sample variance across replicates, DN² (None unless asked for and
        count ≥ 2).
    """

    exposure_s: float
    count: int
    mean: np.ndarray
    maximum: np.ndarray
    variance: np.ndarray | None


def iter_frames(
    sources: Sequence[FrameSource],
    *,
    shape: tuple[int, int] | None = None,
    on_frame: Callable[[], None] | None = None,
) -> Iterator[tuple[FrameSource, np.ndarray]]:
    """Yield (source, image) in order, reading the next frame while the caller works.

    Every image is checked to be a 2-D integer mosaic of `shape` (when given).
    """
    if not sources:
        return
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="labkit-read") as reader:
        pending = reader.submit(sources[0].load)
        for index, source in enumerate(sources):
            image = pending.result()
            if index + 1 < len(sources):
                pending = reader.submit(sources[index + 1].load)
            image = _checked(source, image, shape)
            shape = image.shape  # every later frame must match the first
            yield source, image
            if on_frame is not None:
                on_frame()


def accumulate(
    exposure: ExposureInput,
    *,
    shape: tuple[int, int] | None = None,
    with_variance: bool = False,
    on_frame: Callable[[], None] | None = None,
) -> FrameStats:
    """Mean, maximum and (optionally) variance of an exposure's replicates, streaming.

    Parameters
    ----------
    exposure : ExposureInput
    shape : (rows, cols) or None
        Required frame shape; a frame of another size raises DataError naming it.
    with_variance : bool
        Also compute the per-pixel sample variance (needs ≥ 2 replicates).
    on_frame : callable or None
        Called after each frame (progress bars).
    """
    if not exposure.frames:
        raise DataError(f"exposure {exposure.exposure_s:g} s has no frames")
    first = total = squares = maximum = None
    for _, image in iter_frames(exposure.frames, shape=shape, on_frame=on_frame):
        if first is None:
            first = image.astype(np.float32)
            total = np.zeros_like(first)
            squares = np.zeros_like(first) if with_variance else None
            maximum = image.copy()  # integer counts: half the memory of float32
            continue
        np.maximum(maximum, image, out=maximum)
        frame = image.astype(np.float32)
        frame -= first
        total += frame
        if squares is not None:
            frame *= frame
            squares += frame
    count = len(exposure.frames)
    mean = total / np.float32(count)
    variance = None
    if squares is not None and count >= 2:
        variance = (squares - total * mean) / np.float32(count - 1)
        np.maximum(variance, 0, out=variance)
    mean += first
    return FrameStats(exposure.exposure_s, count, mean, maximum, variance)


def _checked(source: FrameSource, image: np.ndarray, shape: tuple[int, int] | None) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 2 or not np.issubdtype(image.dtype, np.integer):
        raise DataError(
            f"{source.name}: expected a 2-D integer raw mosaic, got {image.dtype} {image.shape}"
        )
    if shape is not None and image.shape != tuple(shape):
        raise DataError(
            f"{source.name}: frame is {image.shape[0]}×{image.shape[1]} but the other frames "
            f"are {shape[0]}×{shape[1]}; frames of different sizes cannot be merged"
        )
    return image
