"""Merging an exposure bracket into one HDR raw mosaic (thesis Algorithm 11, and beyond).

For one (scene, illumination), each exposure's replicates are averaged and the mean dark
frame of the same exposure time is subtracted. Exposures are then visited from the
longest to the shortest: the scaling factor between each consecutive pair is fitted
(:mod:`labkit.hdr.scaling`) and chained, and each exposure is added to a weighted sum
in the units of the longest exposure. At the end the sum is expressed at the shortest
(reference) exposure, as a fraction of the saturation range (1.0 = a saturated pixel).

The merge is a sequence of named steps: each exposure's statistics
(:func:`exposure_sample`), the chain of scaling factors (:class:`FactorChain`), the
weights of one of the methods of :data:`~labkit.hdr.blending.BLENDINGS`, and their
weighted sum (:class:`WeightedSum`). Two weightings (``method``):

``"thesis"``
    Algorithm 11: min(eroded blooming weight (4.1), local weight (4.2)); pixels with
    zero weight at every exposure copy the shortest exposure.
``"noise"``
    Inverse-variance weighting under the Poisson–Gaussian model fitted from the
    replicates and darks (:mod:`labkit.hdr.noise`). A sample is used only if none of
    its replicates reached `high` of the saturation range and neither did its four
    neighbours' (which blooming would have corrupted). The variance is evaluated at a
    pilot estimate (the longest usable exposure), not at each noisy sample, so the
    weights do not favour samples that happen to be low. Writes a ``variance`` channel.

Only a few frame-sized arrays are alive at once, whatever the number of exposures and
replicates.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import ndimage

from labkit.blas_threads import fixed_blas_threads
from labkit.cfa import channel_index, check_layout
from labkit.errors import DataError
from labkit.hdr.blending import BLENDINGS, ExposureSample
from labkit.hdr.levels import DarkFrame, SensorLevels
from labkit.hdr.noise import NoiseModel
from labkit.hdr.scaling import CHANNEL_NAMES, MIN_PAIRS, PairFactor, fit_pair_factor
from labkit.hdr.stack import ExposureInput, FrameStats, accumulate
from labkit.hdr.weights import DISK_1

METHODS = tuple(BLENDINGS)
"""The names of the merge's weightings (:data:`~labkit.hdr.blending.BLENDINGS`)."""

MAX_EXPOSURE_SPAN = 1e15
"""Largest ratio of the longest to the shortest exposure time: signals are chained to the
longest exposure's units in float32 (largest finite 3.4e38; saturation ≤ 2³² DN)."""


FIT_MARGIN_PX = 2
"""Clipping spreads into the pixels around a clipped one (blooming, and on frames that were
demosaiced, resized and mosaiced again, the interpolation kernels), and a spread pixel
below `high` still reads low, which biases a factor fit towards the longer exposure's
deficit. The blend keeps the thesis' radius-1 erosion; the fit, which has pixels to
spare, leaves out a (2·margin + 1)² square around every clipped pixel."""


@dataclass
class ExposureSummary:
    """One row of the Table 4.1 comparison.

    `factor` maps this exposure's signal to the reference (shortest) exposure; `nominal`
    is the exposure-time ratio ``t_ref / t``.
    """

    exposure_s: float
    replicates: int
    darks: int
    nominal: float
    factor: float
    per_channel: dict[str, float | None]

    @property
    def disagreement(self) -> float:
        """Relative difference of the fitted factor from the nominal (0.01 = 1 %)."""
        return self.factor / self.nominal - 1.0


@dataclass
class HDRResult:
    """A merged HDR raw mosaic and how it was made.

    Attributes
    ----------
    raw : ndarray (rows, cols) float32
        Fraction of the saturation range at `reference_exposure_s` (finite everywhere).
    variance : ndarray (rows, cols) float32 or None
        Variance of `raw` (``"noise"`` method); for pixels saturated at every exposure it
        is ``raw²`` (their value is only a lower bound).
    reference_exposure_s : float
        The shortest exposure, s.
    method : str
    exposures : list of ExposureSummary
        Shortest first.
    pairs : list of PairFactor
        Consecutive-exposure fits, longest pair first.
    noise : NoiseModel or None
    saturated_pixels : int
        Pixels clipped (or next to a clipped pixel) at every exposure, the shortest
        included; their values (copied from the shortest exposure) are lower bounds.
    warnings : list of str
        What makes the result less trustworthy than it looks, and what to do about it: an
        exposure that adds nothing, a factor fitted on too few pixels, pixels saturated at
        every exposure.
    dark_pixels : int
        Pixels with no usable sample at any exposure yet unclipped at the shortest: no
        signal above the dark level (thesis weights); their value is the longest
        exposure's, where the dark level is measured best.
    notes : list of str
        What the merge did that follows from the scene, not from a fault: exposures that
        share no properly exposed pixel (their exposure-time ratio is used), dark pixels.
    """

    raw: np.ndarray
    variance: np.ndarray | None
    reference_exposure_s: float
    method: str
    exposures: list[ExposureSummary]
    pairs: list[PairFactor]
    noise: NoiseModel | None
    saturated_pixels: int
    levels: SensorLevels
    warnings: list[str] = field(default_factory=list)
    dark_pixels: int = 0
    notes: list[str] = field(default_factory=list)

    def provenance(self) -> dict[str, Any]:
        """JSON-friendly facts for the EXR header and the run report."""
        return {
            "method": self.method,
            "reference_exposure_s": self.reference_exposure_s,
            "units": "fraction of the saturation range at the reference exposure",
            "saturation_dn": self.levels.saturation_dn,
            "black_level_dn": self.levels.black_level_dn,
            "exposures": [
                {
                    "exposure_s": e.exposure_s,
                    "replicates": e.replicates,
                    "darks": e.darks,
                    "nominal_factor": e.nominal,
                    "factor": e.factor,
                    "disagreement": e.disagreement,
                    "per_channel": e.per_channel,
                }
                for e in self.exposures
            ],
            "pairs": [
                {
                    "longer_s": p.longer_s,
                    "shorter_s": p.shorter_s,
                    "ratio": p.ratio,
                    "nominal": p.nominal,
                    "per_channel": p.per_channel,
                    "pixels": p.pairs,
                    "fallback": p.fallback,
                }
                for p in self.pairs
            ],
            "noise": None if self.noise is None else self.noise.as_dict(),
            "saturated_pixels": self.saturated_pixels,
            "dark_pixels": self.dark_pixels,
            "warnings": self.warnings,
            "notes": self.notes,
        }


DarkSource = Mapping[float, DarkFrame] | Callable[[float], DarkFrame]


def check_bracket(exposures: Sequence[ExposureInput], method: str, fit_margin: int) -> None:
    """Refuse a bracket the merge cannot make sense of, naming what is wrong."""
    if method not in METHODS:
        raise DataError(f"unknown HDR method {method!r}; use one of {', '.join(METHODS)}")
    if not exposures:
        raise DataError("nothing to merge: no exposures")
    times = [e.exposure_s for e in exposures]
    if len(set(times)) != len(times):
        raise DataError(f"exposure times repeat: {sorted(times)}; merge replicates first")
    if any(not np.isfinite(t) or t <= 0 for t in times):
        raise DataError(f"exposure times must be positive seconds, got {times}")
    if not max(times) / min(times) <= MAX_EXPOSURE_SPAN:
        raise DataError(
            f"exposure times span {min(times):g} s … {max(times):g} s, a ratio above "
            f"{MAX_EXPOSURE_SPAN:g}: the float32 merge cannot hold it; check the exposure "
            "times (seconds) or merge the bracket in parts"
        )
    if fit_margin < 0:
        raise DataError(f"fit_margin {fit_margin} must be a non-negative number of pixels")


def exposure_sample(
    stats: FrameStats,
    dark: DarkFrame,
    exposure_s: float,
    *,
    levels: SensorLevels,
    high: float,
    fit_margin: int,
) -> ExposureSample:
    """One exposure's replicate statistics made a sample of the merge: dark-subtracted,
    usable where it and its four neighbours stayed below `high` of the saturation range,
    fittable where every pixel within `fit_margin` did."""
    if isinstance(dark.mean, np.ndarray) and dark.mean.shape != stats.mean.shape:
        raise DataError(
            f"dark frames at {exposure_s:g} s are {dark.mean.shape} but the "
            f"images are {stats.mean.shape}"
        )
    signal = stats.mean - np.asarray(dark.mean, dtype=np.float32)
    unclipped = stats.maximum < levels.black_level_dn + high * levels.saturation_range
    usable = ndimage.binary_erosion(unclipped, structure=DISK_1, border_value=1)
    margin = np.ones((2 * fit_margin + 1,) * 2, bool)
    fittable = ndimage.binary_erosion(unclipped, structure=margin, border_value=1)
    return ExposureSample(exposure_s, signal, stats.variance, stats.count, usable, fittable, dark)


def properly_exposed(sample: ExposureSample, levels: SensorLevels, low: float, high: float) -> int:
    """Pixels of `sample` usable and between `low` and `high` of the saturation range."""
    s, full = sample.signal, levels.saturation_range
    return int(np.count_nonzero(sample.usable & (s >= low * full) & (s <= high * full)))


class FactorChain:
    """The scaling factors of consecutive exposures, fitted and chained to the longest
    exposure's units (exposures given from the longest to the shortest).

    Parameters
    ----------
    channels : ndarray (rows, cols)
        CFA channel index of each pixel.
    levels : SensorLevels
    low, high, min_pairs
        As for :func:`merge_exposures`.
    """

    def __init__(
        self,
        channels: np.ndarray,
        levels: SensorLevels,
        *,
        low: float,
        high: float,
        min_pairs: int,
    ) -> None:
        self.channels, self.levels = channels, levels
        self.low, self.high, self.min_pairs = low, high, min_pairs
        self.chain = 1.0  # from the current exposure's signal to the longest one's
        self.chains: dict[float, float] = {}
        self.channel_chains: dict[float, dict[str, float | None]] = {}
        self.pairs: list[PairFactor] = []
        self.proper: dict[float, int] = {}
        self.warnings: list[str] = []
        self.notes: list[str] = []
        self._previous: ExposureSample | None = None

    def add(self, sample: ExposureSample) -> float:
        """Chain `sample` (the next shorter exposure) on; returns its factor to the longest
        exposure's units."""
        t = sample.exposure_s
        proper = self.proper[t] = properly_exposed(sample, self.levels, self.low, self.high)
        if not proper:
            self.warnings.append(
                f"no pixel is properly exposed at {t:g} s (each is clipped, "
                f"next to a clipped pixel, or below {self.low:.0%} of saturation): this "
                "exposure adds nothing; leave it out of the plan's exposures, or let `auto` "
                "choose them"
            )
        if self._previous is None:
            channel_chain: dict[str, float | None] = dict.fromkeys(CHANNEL_NAMES, 1.0)
        else:
            longer = self._previous
            longer_s = longer.exposure_s
            pair = fit_pair_factor(
                longer.signal,
                sample.signal,
                longer.fittable & sample.fittable,
                self.channels,
                longer_s=longer_s,
                shorter_s=t,
                saturation_range=self.levels.saturation_range,
                low=self.low,
                high=self.high,
                min_pairs=self.min_pairs,
            )
            if pair.fallback:
                _report_fallback(
                    pair, pair.fallback, self.proper, self.min_pairs, self.warnings, self.notes
                )
            self.pairs.append(pair)
            self.chain *= pair.ratio
            last = self.channel_chains[longer_s]
            channel_chain = {
                name: None
                if last[name] is None or pair.per_channel[name] is None
                else last[name] * pair.per_channel[name]
                for name in CHANNEL_NAMES
            }
        self.chains[t] = self.chain
        self.channel_chains[t] = channel_chain
        self._previous = sample
        return self.chain

    def summaries(self, counts: list[tuple[float, int, int]]) -> list[ExposureSummary]:
        """Table 4.1's rows, shortest exposure first, factors to the shortest (reference)
        exposure; `counts`: (exposure s, replicates, darks) of each exposure."""
        reference = min(self.chains)
        ref_chain, ref_channels = self.chains[reference], self.channel_chains[reference]
        return [
            ExposureSummary(
                exposure_s=t,
                replicates=n,
                darks=d,
                nominal=reference / t,
                factor=self.chains[t] / ref_chain,
                per_channel={
                    name: None
                    if self.channel_chains[t][name] is None or ref_channels[name] is None
                    else self.channel_chains[t][name] / ref_channels[name]
                    for name in CHANNEL_NAMES
                },
            )
            for t, n, d in sorted(counts)
        ]


class WeightedSum:
    """Σ w·s and Σ w of the samples in the longest exposure's units, and the merged image
    they give."""

    def __init__(self, shape: tuple[int, int]) -> None:
        self.total = np.zeros(shape, np.float32)
        self.weight_sum = np.zeros(shape, np.float32)

    def add(self, weight: np.ndarray, scaled: np.ndarray) -> None:
        self.total += weight * scaled
        self.weight_sum += weight

    def merged(
        self,
        shortest: ExposureSample,
        shortest_chain: float,
        longest_signal: np.ndarray,
    ) -> tuple[np.ndarray, int, int]:
        """The weighted mean (longest exposure's units), with the pixels no sample weighs
        filled: those clipped (or next to a clipped pixel) at the shortest exposure take
        its value (a lower bound), the others, never above the dark level, the longest
        exposure's. Returns the image and how many pixels of each kind it filled
        (saturated, unlit)."""
        no_weight = self.weight_sum <= 0
        merged = np.empty(self.total.shape, np.float32)
        np.divide(self.total, self.weight_sum, out=merged, where=~no_weight)
        clipped = ~shortest.usable
        saturated = no_weight & clipped
        unlit = no_weight & ~clipped
        merged[saturated] = shortest.signal[saturated] * np.float32(shortest_chain)
        merged[unlit] = longest_signal[unlit]  # the longest exposure's units: chain 1
        return merged, int(np.count_nonzero(saturated)), int(np.count_nonzero(unlit))


@fixed_blas_threads
def merge_exposures(
    exposures: Sequence[ExposureInput],
    darks: DarkSource,
    *,
    cfa: str,
    levels: SensorLevels,
    method: str = "thesis",
    low: float = 0.02,
    high: float = 0.95,
    min_pairs: int = MIN_PAIRS,
    fit_margin: int = FIT_MARGIN_PX,
    erode: bool = True,
    on_frame: Callable[[], None] | None = None,
) -> HDRResult:
    """Merge the exposures of one (scene, illumination) into an HDR raw mosaic.

    Parameters
    ----------
    exposures : sequence of ExposureInput
        One entry per exposure time (any order), each with its replicate frames.
    darks : mapping or callable
        Exposure time (s) → :class:`DarkFrame`; a callable is asked once per exposure
        (so darks can be read lazily and shared between merges).
    cfa : str
        Bayer layout of the frames.
    levels : SensorLevels
        Saturation and black level of the raw counts, DN.
    method : {"thesis", "noise"}
        Blending weights (:data:`~labkit.hdr.blending.BLENDINGS`).
    low, high : float
        Fractions of the saturation range bounding "properly exposed" pixels (thesis:
        2 % and 95 %).
    min_pairs : int
        Fewest pixel pairs for fitting a scaling factor (else the nominal ratio is used).
    fit_margin : int
        Pixels within this many pixels (in rows and in columns) of one at or above
        `high` in either exposure of a pair are left out of its factor fit (see
        :data:`FIT_MARGIN_PX`).
    erode : bool
        Erode the blooming weight (thesis method); False only for demonstrations.
    on_frame : callable or None
        Called after each frame is read (progress).

    Returns
    -------
    HDRResult
    """
    check_bracket(exposures, method, fit_margin)
    layout = check_layout(cfa)
    get_dark = darks.__getitem__ if isinstance(darks, Mapping) else darks
    times = [e.exposure_s for e in exposures]
    weight_unit = np.float32(max(times) / min(times))  # noise weights: any common factor
    blending_class = BLENDINGS[method]
    order = sorted(exposures, key=lambda e: e.exposure_s, reverse=True)
    counts: list[tuple[float, int, int]] = []
    shape: tuple[int, int] | None = None
    for exposure in order:
        stats = accumulate(
            exposure, shape=shape, with_variance=blending_class.needs_variance, on_frame=on_frame
        )
        sample = exposure_sample(
            stats,
            get_dark(exposure.exposure_s),
            exposure.exposure_s,
            levels=levels,
            high=high,
            fit_margin=fit_margin,
        )
        del stats
        if shape is None:  # the longest exposure: the first read
            shape = sample.signal.shape
            factors = FactorChain(
                channel_index(layout, shape), levels, low=low, high=high, min_pairs=min_pairs
            )
            blending = blending_class(shape, levels, low=low, weight_unit=weight_unit, erode=erode)
            weighted = WeightedSum(shape)
            longest_signal = sample.signal.copy()  # the best estimate of pixels that stay dark
        chain = factors.add(sample)
        counts.append((exposure.exposure_s, sample.replicates, sample.dark.count))
        scaled = sample.signal * np.float32(chain)
        weighted.add(blending.weight(sample, chain, scaled), scaled)
        sample.replicate_variance = None  # free it before the next exposure is read
        del scaled

    reference = order[-1].exposure_s
    merged, saturated, unlit = weighted.merged(sample, chain, longest_signal)
    del longest_signal
    to_output = np.float32(1.0 / (chain * levels.saturation_range))
    merged *= to_output
    variance, noise_model = blending.variance(weighted.weight_sum, times)
    if variance is not None:
        no_weight = weighted.weight_sum <= 0
        variance *= to_output * to_output
        variance[no_weight] = np.maximum(merged[no_weight] ** 2, np.float32(1e-12))
    _report_unweighted(
        saturated, unlit, reference, order[0].exposure_s, factors.warnings, factors.notes
    )
    _check_finite(merged, "raw")
    if variance is not None:
        _check_finite(variance, "variance")
    return HDRResult(
        raw=merged,
        variance=variance,
        reference_exposure_s=reference,
        method=method,
        exposures=factors.summaries(counts),
        pairs=factors.pairs,
        noise=noise_model,
        saturated_pixels=saturated,
        levels=levels,
        dark_pixels=unlit,
        warnings=factors.warnings,
        notes=factors.notes,
    )


def _report_unweighted(
    saturated: int,
    unlit: int,
    shortest_s: float,
    longest_s: float,
    warnings: list[str],
    notes: list[str],
) -> None:
    """Say which pixels no exposure weighed: saturated ones (a warning: lower bounds) and
    unlit ones (a note)."""
    if saturated:
        warnings.append(
            f"{saturated} pixels are saturated (or next to saturation) even at the shortest "
            f"exposure {shortest_s:g} s; their values are lower bounds"
        )
    if unlit:
        notes.append(
            f"{unlit} pixel(s) show no signal above the dark level at any exposure (up to "
            f"{longest_s:g} s); their values are the longest exposure's"
        )


def _report_fallback(
    pair: PairFactor,
    fallback: str,
    proper_count: dict[float, int],
    min_pairs: int,
    warnings: list[str],
    notes: list[str],
) -> None:
    """Say why a pair's exposure-time ratio was used (`fallback`, the fit's reason): a note
    when the scene has no light level both exposures see properly (nothing could be
    measured; each exposure adds pixels of its own), a warning when the fit had some pixels
    but too few, or failed."""
    both_useful = proper_count[pair.longer_s] > 0 and proper_count[pair.shorter_s] > 0
    if pair.pairs == 0 and both_useful:
        notes.append(
            f"no pixel is properly exposed at both {pair.longer_s:g} s and {pair.shorter_s:g} s "
            "(the scene's light levels lie farther apart than one exposure's range): their "
            "exposure-time ratio is used"
        )
    elif pair.pairs == 0:
        return  # the exposure that adds nothing has its own warning
    elif pair.pairs < min_pairs:
        warnings.append(f"{fallback}; an exposure between them would let the merge measure it")
    else:
        warnings.append(fallback)


def _check_finite(image: np.ndarray, name: str) -> None:
    bad = int(np.count_nonzero(~np.isfinite(image)))
    if bad:  # a bug, not bad input: say so rather than write NaN
        raise DataError(f"HDR merge produced {bad} non-finite {name} values; please report this")
