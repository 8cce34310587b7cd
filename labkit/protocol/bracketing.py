"""Auto-bracketing: the fewest exposure times that expose every pixel properly.

A pixel is *properly exposed* at exposure t when its dark-subtracted value lies
between ``low`` and ``high`` (2 % and 95 %) of the dark-subtracted saturation level
(thesis §4.2.3). From metering frames we estimate each pixel's rate (counts/s); the
exposures that expose a pixel properly then form an interval [low·S/r, high·S/r]. On a
geometric ladder of the camera's exposure range each pixel admits a contiguous run
of ladder steps, and choosing the fewest steps that hit every run is interval
stabbing, which the greedy "earliest right end first" rule solves exactly. It runs
over the distinct runs (a few hundred), not over pixels.
"""

from __future__ import annotations

from collections.abc import Generator, Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

from labkit.cfa import pixel_format_bits
from labkit.devices.camera import Bounds, Camera
from labkit.errors import DataError
from labkit.frame import Frame
from labkit.rig import AutoExposureConfig

#: Metering goes up or down the exposure range by this factor per frame.
METERING_STEP = 8.0
#: At most this many metering frames per illumination.
MAX_METERING_FRAMES = 8


@dataclass
class BracketChoice:
    """The outcome of auto-bracketing one illumination.

    Attributes
    ----------
    exposures_s : list of float
        Chosen exposure times, s, ascending.
    skipped_s : list of float
        Ladder exposures that would expose some pixels properly but add none that the
        chosen ones miss (so they are not captured).
    metering_s : list of float
        Exposures of the metering frames, s.
    pixels : int
        Pixels considered.
    covered : int
        Pixels predicted properly exposed by at least one chosen exposure.
    too_dark : int
        Pixels below the low threshold even at the longest allowed exposure.
    too_bright : int
        Pixels above the high threshold even at the shortest exposure.
    """

    exposures_s: list[float]
    skipped_s: list[float] = field(default_factory=list)
    metering_s: list[float] = field(default_factory=list)
    pixels: int = 0
    covered: int = 0
    too_dark: int = 0
    too_bright: int = 0

    def as_dict(self) -> dict:
        """Plain mapping for the session file."""
        return asdict(self)

    def summary(self) -> str:
        """One line for logs and progress output."""
        times = ", ".join(f"{t:.4g}" for t in self.exposures_s) or "none"
        text = f"{len(self.exposures_s)} exposure(s) [{times}] s"
        if self.skipped_s:
            text += f", {len(self.skipped_s)} ladder step(s) skipped as adding nothing"
        if self.too_dark or self.too_bright:
            text += (
                f"; {self.too_dark} pixel(s) too dark and {self.too_bright} too bright "
                "for any allowed exposure"
            )
        return text


def exposure_ladder(
    bounds: Bounds, *, maximum_s: float | None = None, steps_per_octave: int = 4
) -> np.ndarray:
    """Geometric ladder of exposure times inside the camera's range, s.

    The ladder runs down from ``min(bounds.maximum, maximum_s)`` in steps of
    ``2**(1/steps_per_octave)`` to ``bounds.minimum``, quantised to the increment.
    """
    top = min(bounds.maximum, maximum_s) if maximum_s else bounds.maximum
    if top < bounds.minimum:
        raise DataError(
            f"auto-bracketing: the longest allowed exposure {top:g} s is below the camera's "
            f"minimum {bounds.minimum:g} s; raise plan.auto.max_exposure_s"
        )
    octaves = np.log2(top / bounds.minimum)
    count = int(np.floor(octaves * steps_per_octave + 1e-9)) + 1
    ladder = top * 2.0 ** (-np.arange(count) / steps_per_octave)
    if bounds.increment > 0:
        steps = np.maximum(np.round((ladder - bounds.minimum) / bounds.increment), 0)
        ladder = bounds.minimum + steps * bounds.increment
    return np.unique(ladder)


def frame_levels(frame: Frame) -> tuple[float, float]:
    """(black level, saturation level) of a frame in its counts.

    Uses the backend's ``extra["black_level"]`` and ``extra["saturation_dn"]`` when it
    reports them, else 0 and the largest count of the pixel format.
    """
    black = float(frame.extra.get("black_level", 0.0))
    full_scale = 2.0 ** pixel_format_bits(frame.pixel_format) - 1.0
    saturation = float(frame.extra.get("saturation_dn", full_scale))
    if saturation <= black:
        raise DataError(
            f"frame {frame.frame_id}: saturation level {saturation:g} is not above the black "
            f"level {black:g}"
        )
    return black, saturation


def _near_saturation(normalised: np.ndarray, high: float) -> np.ndarray:
    """Saturated pixels and their 4-neighbours (blooming spills into them)."""
    full = normalised >= high
    near = full.copy()
    near[1:, :] |= full[:-1, :]
    near[:-1, :] |= full[1:, :]
    near[:, 1:] |= full[:, :-1]
    near[:, :-1] |= full[:, 1:]
    return near


def estimate_rates(frames: Sequence[Frame], *, high: float = 0.95) -> np.ndarray:
    """Per-pixel rate, fraction of the saturation range per second.

    Each pixel uses the longest metering frame in which neither it nor a neighbour is
    near saturation; pixels saturated in every frame get the lower bound implied by the
    shortest one (``high / t_min``), marked by the sign: they are returned negative.
    """
    if not frames:
        raise DataError("auto-bracketing needs at least one metering frame")
    order = sorted(frames, key=lambda f: f.exposure_s)
    rate = np.full(order[0].image.shape, np.nan, dtype=np.float64)
    for frame in order:  # shortest first; longer unsaturated frames overwrite (better SNR)
        black, saturation = frame_levels(frame)
        normalised = (frame.image.astype(np.float64) - black) / (saturation - black)
        usable = ~_near_saturation(normalised, high)
        rate[usable] = np.maximum(normalised[usable], 0.0) / frame.exposure_s
    unknown = np.isnan(rate)
    rate[unknown] = -high / order[0].exposure_s
    return rate


def choose_exposures(
    rate: np.ndarray,
    ladder: np.ndarray,
    *,
    low: float = 0.02,
    high: float = 0.95,
    margin: float = 1.15,
) -> BracketChoice:
    """The fewest ladder exposures exposing every reachable pixel properly.

    Parameters
    ----------
    rate : ndarray
        Per-pixel rate from :func:`estimate_rates` (negative = saturated at the
        shortest metering exposure, a lower bound).
    ladder : ndarray
        Allowed exposure times, s, ascending.
    low, high : float
        Proper-exposure window, fractions of the saturation range.
    margin : float
        The predicted window is narrowed to [low·margin, high/margin].
    """
    ladder = np.asarray(ladder, dtype=np.float64)
    if ladder.ndim != 1 or ladder.size == 0 or np.any(np.diff(ladder) <= 0):
        raise DataError("auto-bracketing: the exposure ladder must be a non-empty ascending list")
    flat = rate.ravel()
    saturated = flat < 0
    magnitude = np.abs(flat)
    with np.errstate(divide="ignore"):
        t_low = np.where(magnitude > 0, low * margin / magnitude, np.inf)  # shortest allowed
        t_high = np.where(magnitude > 0, high / margin / magnitude, np.inf)  # longest allowed
    first = np.searchsorted(ladder, t_low, side="left")  # first step ≥ t_low
    last = np.searchsorted(ladder, t_high, side="right") - 1  # last step ≤ t_high
    last = np.where(saturated, np.minimum(last, first), last)  # only an upper bound known
    too_dark = first >= ladder.size
    too_bright = last < 0
    reachable = ~too_dark & ~too_bright & (first <= last)
    runs = np.unique(np.stack([last[reachable], first[reachable]], axis=1), axis=0)
    chosen: list[int] = []
    for end, start in runs:  # sorted by right end: stab each unhit run at its right end
        if not chosen or start > chosen[-1]:
            chosen.append(int(end))
    chosen_steps = np.array(chosen, dtype=np.int64)
    hit = np.zeros(flat.size, dtype=bool)
    if chosen_steps.size:
        position = np.searchsorted(chosen_steps, first)
        inside = position < chosen_steps.size
        hit[inside] = chosen_steps[position[inside]] <= last[inside]
    useful = np.unique(np.concatenate([first[reachable], last[reachable]]))
    skipped = (
        sorted(set(range(int(useful.min()), int(useful.max()) + 1)) - set(chosen))
        if (useful.size)
        else []
    )
    return BracketChoice(
        exposures_s=[float(ladder[i]) for i in chosen_steps],
        skipped_s=[float(ladder[i]) for i in skipped],
        pixels=int(flat.size),
        covered=int(np.count_nonzero(hit & reachable)),
        too_dark=int(np.count_nonzero(too_dark)),
        too_bright=int(np.count_nonzero(too_bright & ~too_dark)),
    )


def metering(
    bounds: Bounds,
    *,
    maximum_s: float,
    low: float = 0.02,
    high: float = 0.95,
    start_s: float | None = None,
) -> Generator[float, Frame, list[Frame]]:
    """The metering sequence as a generator: it yields the next exposure time, s, and is
    sent the frame captured at it; it returns the frames when metering is done.

    Start at `start_s` (default: the geometric middle of the allowed range). Step down
    while pixels saturate, then up from the start while some are dark. Stop when the
    shortest frame has no saturated pixel (or is at the camera minimum) and the longest
    has every pixel above `low` (or is at `maximum_s`), after at most
    :data:`MAX_METERING_FRAMES` frames. :func:`meter` drives it with a camera; a Bluesky
    plan (:mod:`labkit.bluesky`) drives the same sequence through its RunEngine.
    """
    top = min(bounds.maximum, maximum_s)
    start = start_s or float(np.sqrt(max(bounds.minimum, 1e-6) * top))
    frames = [(yield start)]

    def levels(frame: Frame) -> np.ndarray:
        black, saturation = frame_levels(frame)
        return (frame.image.astype(np.float32) - black) / np.float32(saturation - black)

    shortest = levels(frames[0])
    exposure = start
    while np.any(shortest >= high) and exposure > bounds.minimum * 1.0001:
        if len(frames) >= MAX_METERING_FRAMES:
            return frames
        exposure = max(exposure / METERING_STEP, bounds.minimum)
        frames.append((yield exposure))
        shortest = levels(frames[-1])
    longest = levels(frames[0])
    exposure = start
    while np.any(longest < low * 2) and exposure < top * 0.9999:
        if len(frames) >= MAX_METERING_FRAMES:
            break
        exposure = min(exposure * METERING_STEP, top)
        frames.append((yield exposure))
        longest = levels(frames[-1])
    return frames


def meter(
    camera: Camera,
    *,
    bounds: Bounds,
    maximum_s: float,
    low: float = 0.02,
    high: float = 0.95,
    start_s: float | None = None,
) -> list[Frame]:
    """Metering frames grabbed from `camera` (the sequence of :func:`metering`)."""
    steps = metering(bounds, maximum_s=maximum_s, low=low, high=high, start_s=start_s)
    exposure = next(steps)
    try:
        while True:
            exposure = steps.send(camera.grab(exposure, 1)[0])
    except StopIteration as done:
        return done.value


def choose_bracket(
    frames: Sequence[Frame], bounds: Bounds, auto: AutoExposureConfig
) -> BracketChoice:
    """The exposure times of one illumination from its metering frames (the rig's
    ``plan.auto`` settings): rates, the ladder, then :func:`choose_exposures`."""
    rate = estimate_rates(frames, high=auto.high_fraction)
    ladder = exposure_ladder(
        bounds, maximum_s=auto.max_exposure_s, steps_per_octave=auto.steps_per_octave
    )
    choice = choose_exposures(
        rate, ladder, low=auto.low_fraction, high=auto.high_fraction, margin=auto.margin
    )
    choice.metering_s = [float(f.exposure_s) for f in frames]
    return choice
