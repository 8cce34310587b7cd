"""Auto-bracketing: the fewest exposure times that expose every pixel properly, that the
HDR merge can chain, checked on the camera's own frames.

A pixel is *properly exposed* at exposure t when its dark-subtracted value lies
between ``low`` and ``high`` (2 % and 95 %) of the dark-subtracted saturation level
(thesis §4.2.3). From metering frames we estimate each pixel's rate (counts/s); the
exposures that expose a pixel properly then form an interval [low·S/r, high·S/r]. On a
geometric ladder of the camera's exposure range each pixel admits a contiguous run
of ladder steps, and choosing the fewest steps that hit every run is interval
stabbing, which the greedy "earliest right end first" rule solves exactly. It runs
over the distinct runs (a few hundred), not over pixels. Then (:func:`choose_exposures`):

- an exposure that alone exposes only a handful of pixels is not taken; those pixels are
  reported instead;
- every exposure but the shortest moves down to the shortest its own pixels allow, so that
  the brighter rest of the image is overexposed, and blooms, the least;
- the merge fits the ratio of two consecutive exposures on the pixels properly exposed in
  both and :data:`~labkit.hdr.merge.FIT_MARGIN_PX` pixels away from any clipped one, and
  needs :data:`~labkit.hdr.scaling.MIN_PAIRS` of them: where two consecutive exposures share
  fewer, the ladder step between them that most raises the weaker link is added, until
  every link has enough pixels or no step helps (two light levels farther apart than one
  exposure's range); the links left short are reported.

:func:`auto_bracketing` meters, chooses, and checks each chosen exposure with one frame,
since around pixels overexposed many times over the rates' prediction fails (design note
``docs/notes/auto-bracketing.md``).
"""

from __future__ import annotations

from collections.abc import Callable, Generator, Sequence
from dataclasses import asdict, dataclass, field

import numpy as np
from scipy import ndimage

from labkit.cfa import pixel_format_bits
from labkit.devices.camera import Bounds, Camera
from labkit.errors import DataError
from labkit.frame import Frame
from labkit.hdr.merge import FIT_MARGIN_PX
from labkit.hdr.scaling import MIN_PAIRS
from labkit.protocol._generators import drive
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
    flooded : int
        Pixels that a check frame found spoilt at the exposure they need: the charge of
        overexposed pixels around them spills into them (blooming) or clips a neighbour.
    left_out : int
        Pixels that only exposures exposing fewer than `min_pixels` pixels of their own
        would have exposed properly: too few to be worth an exposure.
    checked_s : list of float
        Exposures of the check frames, s (:func:`auto_bracketing`).
    linking_s : list of float
        Exposures among `exposures_s` added only so that consecutive exposures share
        enough properly exposed pixels for the merge to fit their ratio.
    unlinked_s : list of [float, float]
        Consecutive chosen exposures that still share fewer than `min_overlap` pixels
        (no ladder step between them helps): the merge will use their exposure-time ratio.
    min_overlap : int
        Pixels two consecutive exposures must share.
    """

    exposures_s: list[float]
    skipped_s: list[float] = field(default_factory=list)
    metering_s: list[float] = field(default_factory=list)
    pixels: int = 0
    covered: int = 0
    too_dark: int = 0
    too_bright: int = 0
    flooded: int = 0
    left_out: int = 0
    checked_s: list[float] = field(default_factory=list)
    linking_s: list[float] = field(default_factory=list)
    unlinked_s: list[list[float]] = field(default_factory=list)
    min_overlap: int = 0

    def as_dict(self) -> dict:
        """Plain mapping for the session file."""
        return asdict(self)

    def summary(self) -> str:
        """One line for logs and progress output."""
        times = ", ".join(f"{t:.4g}" for t in self.exposures_s) or "none"
        text = f"{len(self.exposures_s)} exposure(s) [{times}] s"
        if self.skipped_s:
            text += f", {len(self.skipped_s)} ladder step(s) skipped as adding nothing"
        if self.linking_s:
            text += (
                f", {len(self.linking_s)} of them added so that consecutive exposures share "
                f"≥ {self.min_overlap} properly exposed pixels"
            )
        for shorter, longer in self.unlinked_s:
            text += (
                f"; {shorter:.4g} s and {longer:.4g} s share fewer than {self.min_overlap} "
                "properly exposed pixels (the merge uses their exposure-time ratio)"
            )
        if self.too_dark or self.too_bright:
            text += (
                f"; {self.too_dark} pixel(s) too dark and {self.too_bright} too bright "
                "for any allowed exposure"
            )
        if self.left_out:
            text += f"; {self.left_out} pixel(s) too few to be worth an exposure of their own"
        if self.flooded:
            text += (
                f"; {self.flooded} pixel(s) flooded by the overexposed pixels around them at "
                "the exposure they need"
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
    min_overlap: int = MIN_PAIRS,
    longest: np.ndarray | None = None,
    min_pixels: int | None = None,
) -> BracketChoice:
    """The fewest ladder exposures exposing every reachable pixel properly, linked so that
    the HDR merge can fit each consecutive pair's ratio.

    Parameters
    ----------
    rate : ndarray (rows, cols) or (pixels,)
        Per-pixel rate from :func:`estimate_rates` (negative = saturated at the
        shortest metering exposure, a lower bound). In a 2-D image the links between
        exposures count only pixels away from clipping, as the merge's fit does; a 1-D
        array of independent pixels has no neighbours.
    ladder : ndarray
        Allowed exposure times, s, ascending.
    low, high : float
        Proper-exposure window, fractions of the saturation range.
    margin : float
        The predicted window is narrowed to [low·margin, high/margin].
    min_overlap : int
        Properly exposed pixels two consecutive chosen exposures must share (0: none,
        the plain interval stabbing).
    longest : ndarray of int, optional
        Per pixel, the last ladder step at which a check frame found it usable (same shape
        as `rate`): a cap on what its rate predicts (:func:`auto_bracketing`).
    min_pixels : int, optional
        Fewest pixels an exposure must expose properly that no other chosen exposure does;
        pixels left to exposures below it are reported (`left_out`), not chased. Default:
        0.1 % of the pixels, at most :data:`~labkit.hdr.scaling.MIN_PAIRS`.
    """
    ladder = np.asarray(ladder, dtype=np.float64)
    if ladder.ndim != 1 or ladder.size == 0 or np.any(np.diff(ladder) <= 0):
        raise DataError("auto-bracketing: the exposure ladder must be a non-empty ascending list")
    rate = np.asarray(rate, dtype=np.float64)
    first, last = _runs(rate, ladder, low=low, high=high, margin=margin, longest=longest)
    flooded = np.zeros(rate.shape, bool)
    if longest is not None:
        flooded = (last < first) & (longest < first) & (first < ladder.size)
    fit_last = last
    if rate.ndim == 2:  # fitted away from clipping
        fit_last = ndimage.minimum_filter(last, size=2 * FIT_MARGIN_PX + 1, mode="nearest")
    first, last, fit_last = first.ravel(), last.ravel(), fit_last.ravel()
    flooded = flooded.ravel()
    too_dark = first >= ladder.size
    too_bright = (last < 0) & ~flooded
    reachable = ~too_dark & ~too_bright & (first <= last)
    runs = np.unique(np.stack([last[reachable], first[reachable]], axis=1), axis=0)
    stabs: list[int] = []
    for end, start in runs:  # sorted by right end: stab each unhit run at its right end
        if not stabs or start > stabs[-1]:
            stabs.append(int(end))
    if min_pixels is None:
        min_pixels = _fewest_worth(first.size)
    stabs = _worthwhile(stabs, first[reachable], last[reachable], min_pixels)
    stabs = _shortest(stabs, first[reachable], last[reachable])
    chosen, unlinked = _linked(stabs, first, fit_last, ladder.size, min_overlap)
    chosen_steps = np.array(chosen, dtype=np.int64)
    hit = np.zeros(first.size, dtype=bool)
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
        pixels=int(first.size),
        covered=int(np.count_nonzero(hit & reachable)),
        too_dark=int(np.count_nonzero(too_dark)),
        too_bright=int(np.count_nonzero(too_bright & ~too_dark)),
        flooded=int(np.count_nonzero(flooded)),
        left_out=int(np.count_nonzero(reachable & ~hit)),
        linking_s=[float(ladder[i]) for i in sorted(set(chosen) - set(stabs))],
        unlinked_s=[[float(ladder[a]), float(ladder[b])] for a, b in unlinked],
        min_overlap=min_overlap,
    )


def _fewest_worth(pixels: int) -> int:
    """Fewest pixels of its own an exposure must expose: 0.1 % of them, at most MIN_PAIRS."""
    return min(MIN_PAIRS, max(1, pixels // 1000))


def _runs(
    rate: np.ndarray,
    ladder: np.ndarray,
    *,
    low: float,
    high: float,
    margin: float,
    longest: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, the first and last ladder steps that expose it properly by its rate (the
    window narrowed by `margin`), the last capped at `longest`."""
    saturated = rate < 0
    magnitude = np.abs(rate)
    with np.errstate(divide="ignore"):
        t_low = np.where(magnitude > 0, low * margin / magnitude, np.inf)  # shortest allowed
        t_high = np.where(magnitude > 0, high / margin / magnitude, np.inf)  # longest allowed
    first = np.searchsorted(ladder, t_low, side="left")  # first step ≥ t_low
    last = np.searchsorted(ladder, t_high, side="right") - 1  # last step ≤ t_high
    last = np.where(saturated, np.minimum(last, first), last)  # only an upper bound known
    if longest is not None:
        last = np.minimum(last, longest)
    return first, last


def _worthwhile(stabs: list[int], first: np.ndarray, last: np.ndarray, least: int) -> list[int]:
    """`stabs` without the steps that alone expose fewer than `least` pixels (runs
    ``[first, last]``), the weakest dropped first; the last step is always kept."""
    chosen = list(stabs)
    while len(chosen) > 1:
        hit = np.stack([(first <= step) & (step <= last) for step in chosen])
        alone = np.count_nonzero(hit & (hit.sum(axis=0) == 1), axis=1)
        weakest = int(np.argmin(alone))
        if alone[weakest] >= least:
            break
        del chosen[weakest]
    return chosen


def _hit_counts(first: np.ndarray, last: np.ndarray, steps: Sequence[int]) -> np.ndarray:
    """Per pixel, how many of the ladder `steps` fall in its run ``[first, last]``."""
    hits = np.zeros(first.shape, np.int16)
    for step in steps:
        hits += (first <= step) & (step <= last)
    return hits


def _shortest(stabs: list[int], first: np.ndarray, last: np.ndarray) -> list[int]:
    """The same number of steps as `stabs`, each but the shortest moved down to the shortest
    exposure that still hits every run no other step hits (runs ``[first, last]``).

    Greedy stabbing puts each step at the right end of a run: the longest exposure its
    pixels allow, which overexposes the brighter rest of the image the most. Sensors spill
    the charge of overexposed pixels into their neighbours (blooming), so far that dark
    regions next to bright ones can be flooded, so every step is made as short as its own
    pixels allow. The shortest step overexposes only pixels too bright for any exposure and
    stays where its pixels are exposed best. A step moved down stays above the one below it:
    a run it alone hits starts above that.
    """
    chosen = list(stabs)
    hits = _hit_counts(first, last, chosen)
    for k, step in enumerate(chosen):
        if k == 0:
            continue
        own = (first <= step) & (step <= last)
        alone = own & (hits == 1)
        if alone.any():
            chosen[k] = int(first[alone].max())
            hits += ((first <= chosen[k]) & (chosen[k] <= last)).astype(np.int16) - own
    return chosen


def _linked(
    stabs: list[int], first: np.ndarray, fit_last: np.ndarray, steps: int, min_overlap: int
) -> tuple[list[int], list[tuple[int, int]]]:
    """`stabs` (ascending ladder steps) with steps added between consecutive ones until each
    pair shares `min_overlap` fittable pixels or no step raises the weaker link; returns the
    steps and the pairs left short.

    Pixels shared by steps a < b: properly exposed at both, ``first ≤ a`` and
    ``b ≤ fit_last`` (a pixel's run is contiguous). They are counted from one 2-D table
    over (first, fit_last), cumulated from the corner: ``shared[a, b]``.
    """
    if min_overlap <= 0 or len(stabs) < 2:
        return list(stabs), []
    valid = (first < steps) & (fit_last >= 0) & (first <= fit_last)
    table = np.zeros((steps, steps), np.int64)
    np.add.at(table, (first[valid], fit_last[valid]), 1)
    shared = table.cumsum(axis=0)[:, ::-1].cumsum(axis=1)[:, ::-1]  # Σ first ≤ a, last ≥ b
    chosen = list(stabs)
    short: list[tuple[int, int]] = []
    k = 0
    while k < len(chosen) - 1:
        a, b = chosen[k], chosen[k + 1]
        if shared[a, b] >= min_overlap:
            k += 1
            continue
        middle = np.arange(a + 1, b)
        weaker = np.minimum(shared[a, middle], shared[middle, b]) if middle.size else middle
        if middle.size and weaker.max() > shared[a, b]:
            chosen.insert(k + 1, int(middle[np.argmax(weaker)]))  # re-check a → the new step
        else:
            short.append((a, b))
            k += 1
    return chosen, short


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

    shortest = _normalised(frames[0])
    exposure = start
    while np.any(shortest >= high) and exposure > bounds.minimum * 1.0001:
        if len(frames) >= MAX_METERING_FRAMES:
            return frames
        exposure = max(exposure / METERING_STEP, bounds.minimum)
        frames.append((yield exposure))
        shortest = _normalised(frames[-1])
    longest = _normalised(frames[0])
    exposure = start
    while np.any(longest < low * 2) and exposure < top * 0.9999:
        if len(frames) >= MAX_METERING_FRAMES:
            break
        exposure = min(exposure * METERING_STEP, top)
        frames.append((yield exposure))
        longest = _normalised(frames[-1])
    return frames


#: Rounds of check frames: choose, check each new exposure with one frame, choose again.
MAX_CHECK_ROUNDS = 4


def usable_in(frame: Frame, *, low: float = 0.02, high: float = 0.95) -> np.ndarray:
    """Pixels of one frame the HDR merge can use: dark-subtracted value in [low, high] of
    the saturation range, and neither the pixel nor a 4-neighbour at or above `high`."""
    normalised = _normalised(frame)
    return (normalised >= low) & ~_near_saturation(normalised, high)


def _normalised(frame: Frame) -> np.ndarray:
    """Dark-subtracted fraction of the saturation range, float32."""
    black, saturation = frame_levels(frame)
    return (frame.image.astype(np.float32) - black) / np.float32(saturation - black)


def auto_bracketing(
    bounds: Bounds, auto: AutoExposureConfig, *, start_s: float | None = None
) -> Generator[float, Frame, BracketChoice]:
    """Auto-bracketing of one illumination, checked on the camera's own frames, as a
    generator: it yields the next exposure time, s, is sent the frame captured at it, and
    returns the :class:`BracketChoice`.

    It meters (:func:`metering`) and chooses (:func:`choose_exposures`) from the pixels'
    rates, which assume every pixel integrates its own light. Around pixels overexposed
    many times over that fails: their charge spills into their neighbours (blooming), and
    a dark region next to a bright one can read saturated at the exposure its rate asks
    for. So every chosen exposure is checked with one frame: the pixels it shows unusable
    (clipped, or next to a clipped pixel) are capped below it — all the pixels an exposure
    alone was chosen for when too few of them are usable — and the choice is made again,
    the check frames serving as metering frames too, for up to :data:`MAX_CHECK_ROUNDS`
    rounds. Pixels left without any usable exposure are reported as flooded.

    :func:`run_auto_bracketing` drives it with a camera; the Bluesky plan
    (:mod:`labkit.bluesky`) drives the same sequence through its RunEngine.
    """
    low, high = auto.low_fraction, auto.high_fraction
    frames = yield from metering(
        bounds, maximum_s=auto.max_exposure_s, low=low, high=high, start_s=start_s
    )
    ladder = exposure_ladder(
        bounds, maximum_s=auto.max_exposure_s, steps_per_octave=auto.steps_per_octave
    )
    shape = frames[0].image.shape
    least = _fewest_worth(shape[0] * shape[1])
    longest = np.full(shape, ladder.size - 1, np.int64)
    checked: dict[float, Frame] = {}
    for round_ in range(MAX_CHECK_ROUNDS + 1):
        rate = estimate_rates([*frames, *checked.values()], high=high)  # checks meter too
        choice = choose_exposures(
            rate, ladder, low=low, high=high, margin=auto.margin, longest=longest
        )
        new = [t for t in choice.exposures_s if t not in checked]
        if not new or round_ == MAX_CHECK_ROUNDS:
            break
        first, last = _runs(rate, ladder, low=low, high=high, margin=auto.margin, longest=longest)
        hits = _hit_counts(first, last, np.searchsorted(ladder, choice.exposures_s))
        for exposure in new:
            frame = yield exposure
            checked[exposure] = frame
            step = int(np.searchsorted(ladder, exposure))
            spoilt = _near_saturation(_normalised(frame), high)  # clipped or next to it
            alone = (first <= step) & (step <= last) & (hits == 1)
            if np.count_nonzero(alone & ~spoilt) < least:  # the exposure is lost to flooding:
                longest[alone] = np.minimum(longest[alone], first[alone] - 1)  # its pixels too
            longest[spoilt] = np.minimum(longest[spoilt], step - 1)
    choice.metering_s = [float(f.exposure_s) for f in frames]
    choice.checked_s = sorted(checked)
    return choice


def run_auto_bracketing(
    camera: Camera, *, bounds: Bounds, auto: AutoExposureConfig, start_s: float | None = None
) -> BracketChoice:
    """:func:`auto_bracketing` driven with frames grabbed from `camera`."""
    return drive(auto_bracketing(bounds, auto, start_s=start_s), _grabber(camera))


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
    return drive(
        metering(bounds, maximum_s=maximum_s, low=low, high=high, start_s=start_s),
        _grabber(camera),
    )


def _grabber(camera: Camera) -> Callable[[float], Frame]:
    """One frame grabbed from `camera` at each exposure, s, asked for."""
    return lambda exposure_s: camera.grab(exposure_s, 1)[0]


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
