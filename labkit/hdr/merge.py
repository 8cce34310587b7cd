"""Merging an exposure bracket into one HDR raw mosaic (thesis Algorithm 11, and beyond).

For one (scene, illumination), each exposure's replicates are averaged and the mean dark
frame of the same exposure time is subtracted. Exposures are then visited from the
longest to the shortest: the scaling factor between each consecutive pair is fitted
(:mod:`labkit.hdr.scaling`) and chained, and each exposure is added to a weighted sum
in the units of the longest exposure. At the end the sum is expressed at the shortest
(reference) exposure, as a fraction of the saturation range (1.0 = a saturated pixel).

Two weightings (``method``):

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
from labkit.hdr.noise import NoiseEstimator, NoiseModel
from labkit.hdr.scaling import CHANNEL_NAMES, MIN_PAIRS, PairFactor, fit_pair_factor
from labkit.hdr.stack import ExposureInput, accumulate
from labkit.hdr.weights import DISK_1, blend_weight

METHODS = ("thesis", "noise")

MAX_EXPOSURE_SPAN = 1e15
"""Largest ratio of the longest to the shortest exposure time: signals are chained to the
longest exposure's units in float32 (largest finite 3.4e38; saturation ≤ 2³² DN)."""


FIT_MARGIN_PX = 2
"""Clipping spreads into the pixels around a clipped one (blooming, and on frames that were
demosaiced, resized and mosaiced again, the interpolation kernels), and a spread pixel
below `high` still reads low, which biases a factor fit towards the longer exposure's
deficit. The blend keeps the thesis' radius-1 erosion; the fit, which has pixels to
spare, leaves out a (2·margin + 1)² square around every clipped pixel."""


@dataclass(frozen=True)
class SensorLevels:
    """Where the raw counts start and stop.

    Attributes
    ----------
    saturation_dn : float
        Count of a saturated pixel (full well or ADC limit), DN.
    black_level_dn : float
        Count of a dark pixel at zero exposure, DN.
    """

    saturation_dn: float
    black_level_dn: float = 0.0

    @property
    def saturation_range(self) -> float:
        """Signal of a saturated pixel above black, DN."""
        return self.saturation_dn - self.black_level_dn

    def __post_init__(self) -> None:
        if not np.isfinite(self.saturation_dn) or self.saturation_range <= 0:
            raise DataError(
                f"saturation {self.saturation_dn} DN must exceed the black level "
                f"{self.black_level_dn} DN"
            )


@dataclass
class DarkFrame:
    """What to subtract from an exposure: the mean dark frame, or a constant black level.

    Attributes
    ----------
    exposure_s : float
        Exposure time, s.
    mean : ndarray (rows, cols) float32 or float
        Mean dark counts, DN.
    variance_dn2 : float or None
        Temporal variance of one dark frame averaged over pixels, DN² (None: unknown).
    count : int
        Dark frames averaged (0 for a constant black level).
    """

    exposure_s: float
    mean: np.ndarray | float
    variance_dn2: float | None
    count: int

    @classmethod
    def from_frames(
        cls,
        exposure: ExposureInput,
        *,
        shape: tuple[int, int] | None = None,
        on_frame: Callable[[], None] | None = None,
    ) -> DarkFrame:
        """Average dark frames (streaming)."""
        stats = accumulate(exposure, shape=shape, with_variance=True, on_frame=on_frame)
        variance = (
            None if stats.variance is None else float(np.mean(stats.variance, dtype=np.float64))
        )
        return cls(exposure.exposure_s, stats.mean, variance, stats.count)

    @classmethod
    def black_level(cls, exposure_s: float, black_level_dn: float) -> DarkFrame:
        """No dark frames: subtract a constant (dark current stays in the image)."""
        return cls(exposure_s, float(black_level_dn), None, 0)


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
        Blending weights (see the module docstring).
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
    layout = check_layout(cfa)
    get_dark = darks.__getitem__ if isinstance(darks, Mapping) else darks
    noise_aware = method == "noise"
    saturation_range = levels.saturation_range
    clip_level = levels.black_level_dn + high * saturation_range
    weight_unit = np.float32(max(times) / min(times))  # noise weights: any common factor

    order = sorted(exposures, key=lambda e: e.exposure_s, reverse=True)
    shape: tuple[int, int] | None = None
    channels = None
    estimator = NoiseEstimator(saturation_range, low=low) if noise_aware else None
    chain = 1.0  # factor from the current exposure's signal to the longest one's
    chains: dict[float, float] = {}
    channel_chains: dict[float, dict[str, float | None]] = {}
    pairs: list[PairFactor] = []
    summaries_in: list[tuple[float, int, int]] = []
    warnings: list[str] = []
    notes: list[str] = []
    longest_signal = None
    proper_count: dict[float, int] = {}
    total = weight_sum = None
    pilot = has_pilot = shot_part = constant_part = None
    previous: tuple[np.ndarray, np.ndarray, float, np.ndarray] | None = None
    if fit_margin < 0:
        raise DataError(f"fit_margin {fit_margin} must be a non-negative number of pixels")
    margin = np.ones((2 * fit_margin + 1,) * 2, bool)
    signal = None

    for exposure in order:
        stats = accumulate(exposure, shape=shape, with_variance=noise_aware, on_frame=on_frame)
        if shape is None:
            shape = stats.mean.shape
            channels = channel_index(layout, shape)
            total = np.zeros(shape, np.float32)
            weight_sum = np.zeros(shape, np.float32)
            if noise_aware:
                pilot = np.zeros(shape, np.float32)
                has_pilot = np.zeros(shape, bool)
                shot_part = np.zeros(shape, np.float32)
                constant_part = np.zeros(shape, np.float32)
        dark = get_dark(exposure.exposure_s)
        if isinstance(dark.mean, np.ndarray) and dark.mean.shape != shape:
            raise DataError(
                f"dark frames at {exposure.exposure_s:g} s are {dark.mean.shape} but the "
                f"images are {shape}"
            )
        signal = stats.mean - np.asarray(dark.mean, dtype=np.float32)
        unclipped = stats.maximum < clip_level
        usable = ndimage.binary_erosion(unclipped, structure=DISK_1, border_value=1)
        fittable = ndimage.binary_erosion(unclipped, structure=margin, border_value=1)
        proper = usable & (signal >= low * saturation_range) & (signal <= high * saturation_range)
        proper_count[exposure.exposure_s] = int(np.count_nonzero(proper))
        del proper
        if not proper_count[exposure.exposure_s]:
            warnings.append(
                f"no pixel is properly exposed at {exposure.exposure_s:g} s (each is clipped, "
                f"next to a clipped pixel, or below {low:.0%} of saturation): this exposure "
                "adds nothing; leave it out of the plan's exposures, or let `auto` choose them"
            )
        if longest_signal is None:
            longest_signal = signal.copy()  # the best estimate of pixels that stay dark
        if previous is None:
            channel_chain: dict[str, float | None] = dict.fromkeys(CHANNEL_NAMES, 1.0)
        else:
            longer, _, longer_s, longer_fittable = previous
            pair = fit_pair_factor(
                longer,
                signal,
                longer_fittable & fittable,
                channels,
                longer_s=longer_s,
                shorter_s=exposure.exposure_s,
                saturation_range=saturation_range,
                low=low,
                high=high,
                min_pairs=min_pairs,
            )
            if pair.fallback:
                _report_fallback(pair, pair.fallback, proper_count, min_pairs, warnings, notes)
            pairs.append(pair)
            chain *= pair.ratio
            last = channel_chains[longer_s]
            channel_chain = {
                name: None
                if last[name] is None or pair.per_channel[name] is None
                else last[name] * pair.per_channel[name]
                for name in CHANNEL_NAMES
            }
        chains[exposure.exposure_s] = chain
        channel_chains[exposure.exposure_s] = channel_chain
        summaries_in.append((exposure.exposure_s, stats.count, dark.count))
        scaled = signal * np.float32(chain)

        if noise_aware:
            estimator.add(
                exposure.exposure_s,
                signal,
                stats.variance,
                usable,
                dark_variance=dark.variance_dn2,
            )
            gain = estimator.gain() or 0.0
            if dark.variance_dn2 is not None:
                constant = dark.variance_dn2
            elif estimator.pixels:
                constant = estimator.constant_variance(exposure.exposure_s)[0]
            else:
                constant = 0.0
            new = usable & ~has_pilot
            pilot[new] = scaled[new]
            has_pilot |= new
            # shot-noise variance per unit gain, in the longest exposure's units²: the signal
            # the pilot implies at this exposure (pilot / chain, ≥ 0), × chain² / replicates
            shot = np.maximum(pilot, 0) * np.float32(chain / stats.count)
            dark_mean_var = constant / dark.count if dark.count else 0.0
            const = np.float32(chain * chain * (constant / stats.count + dark_mean_var))
            variance = np.float32(gain) * shot + const
            weight = np.zeros(shape, np.float32)
            positive = usable & (variance > 0)
            # ∝ 1 / variance, times a constant (the exposure span) that keeps the squared
            # weights of the shortest exposure (variance ∝ chain²) from underflowing float32
            weight[positive] = weight_unit / variance[positive]
            squared = weight * weight
            shot_part += squared * shot
            constant_part += squared * const
        else:
            # p = 1 exactly where the mean reached saturation: per-pixel headroom above the dark
            headroom = np.float32(levels.saturation_dn) - np.asarray(dark.mean, np.float32)
            weight = blend_weight(signal / headroom, erode=erode)
        total += weight * scaled
        weight_sum += weight
        previous = (signal, usable, exposure.exposure_s, fittable)
        # free this exposure's frame-sized temporaries before the next one is read
        del stats, dark, scaled, weight, unclipped
        if noise_aware:
            del shot, variance, positive, squared

    reference = order[-1].exposure_s
    reference_chain = chains[reference]
    no_weight = weight_sum <= 0
    merged = np.empty(shape, np.float32)
    np.divide(total, weight_sum, out=merged, where=~no_weight)
    # no weight anywhere: clipped (or next to a clipped pixel) at the shortest exposure, or
    # else never above the dark level (thesis weights are 0 at p ≤ 0)
    clipped = ~previous[1]
    saturated_mask = no_weight & clipped
    unlit_mask = no_weight & ~clipped
    merged[saturated_mask] = signal[saturated_mask] * np.float32(reference_chain)  # shortest
    merged[unlit_mask] = longest_signal[unlit_mask]  # the longest exposure's units: chain 1
    to_output = np.float32(1.0 / (reference_chain * saturation_range))
    merged *= to_output
    saturated = int(np.count_nonzero(saturated_mask))
    unlit = int(np.count_nonzero(unlit_mask))
    del longest_signal, saturated_mask, unlit_mask

    noise_model = None
    variance_out = None
    if noise_aware:
        noise_model = estimator.model([e.exposure_s for e in exposures])
        variance_out = np.empty(shape, np.float32)
        safe = np.where(no_weight, 1.0, weight_sum)
        variance_out[:] = (np.float32(noise_model.gain_dn_per_e) * shot_part + constant_part) / (
            safe * safe
        )
        variance_out *= to_output * to_output
        variance_out[no_weight] = np.maximum(merged[no_weight] ** 2, np.float32(1e-12))
    if saturated:
        warnings.append(
            f"{saturated} pixels are saturated (or next to saturation) even at the shortest "
            f"exposure {reference:g} s; their values are lower bounds"
        )
    if unlit:
        notes.append(
            f"{unlit} pixel(s) show no signal above the dark level at any exposure (up to "
            f"{order[0].exposure_s:g} s); their values are the longest exposure's"
        )
    summaries = [
        ExposureSummary(
            exposure_s=t,
            replicates=n,
            darks=d,
            nominal=reference / t,
            factor=chains[t] / reference_chain,
            per_channel={
                name: None
                if channel_chains[t][name] is None or channel_chains[reference][name] is None
                else channel_chains[t][name] / channel_chains[reference][name]
                for name in CHANNEL_NAMES
            },
        )
        for t, n, d in sorted(summaries_in)
    ]
    _check_finite(merged, "raw")
    if variance_out is not None:
        _check_finite(variance_out, "variance")
    return HDRResult(
        raw=merged,
        variance=variance_out,
        reference_exposure_s=reference,
        method=method,
        exposures=summaries,
        pairs=pairs,
        noise=noise_model,
        saturated_pixels=saturated,
        levels=levels,
        dark_pixels=unlit,
        warnings=warnings,
        notes=notes,
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
