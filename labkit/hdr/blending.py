"""How each exposure's samples are weighted in the merge, one class per method.

:data:`BLENDINGS` names them (the ``method`` of :func:`~labkit.hdr.merge.merge_exposures`):

``"thesis"`` (:class:`ThesisBlending`)
    Algorithm 11: min(eroded blooming weight (4.1), local weight (4.2)).
``"noise"`` (:class:`NoiseBlending`)
    Inverse-variance weights under the Poisson–Gaussian model fitted from the replicates
    and darks (:mod:`labkit.hdr.noise`), evaluated at a pilot estimate (the longest usable
    exposure) rather than at each noisy sample, so that the weights do not favour samples
    that happen to be low; it also gives the merged image's variance.

Each is given the exposures from the longest to the shortest, one :class:`ExposureSample`
at a time, with the factor that takes the sample to the longest exposure's units.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from labkit.hdr.levels import DarkFrame, SensorLevels
from labkit.hdr.noise import NoiseEstimator, NoiseModel
from labkit.hdr.weights import blend_weight


@dataclass
class ExposureSample:
    """One exposure's replicates, reduced.

    Attributes
    ----------
    exposure_s : float
        Exposure time, s.
    signal : ndarray (rows, cols) float32
        Mean of the replicates minus the dark frame, DN.
    replicate_variance : ndarray (rows, cols) or None
        Variance across the replicates, DN² (None where the method does not need it).
    replicates : int
        Frames averaged.
    usable : ndarray (rows, cols) bool
        Below the clipping level in every replicate, and so are its four neighbours.
    fittable : ndarray (rows, cols) bool
        Below the clipping level, and so is every pixel within the scaling fit's margin.
    dark : DarkFrame
        What was subtracted.
    """

    exposure_s: float
    signal: np.ndarray
    replicate_variance: np.ndarray | None
    replicates: int
    usable: np.ndarray
    fittable: np.ndarray
    dark: DarkFrame


class Blending(Protocol):
    """A weighting of the merge: a weight per sample, then what the weights imply."""

    needs_variance: bool
    """Whether :attr:`ExposureSample.replicate_variance` must be measured."""

    def weight(self, sample: ExposureSample, chain: float, scaled: np.ndarray) -> np.ndarray:
        """Weights of `sample` (float32, ≥ 0), whose signal is `scaled` (= signal × `chain`)
        in the longest exposure's units."""
        ...

    def variance(
        self, weight_sum: np.ndarray, exposures_s: list[float]
    ) -> tuple[np.ndarray | None, NoiseModel | None]:
        """Variance of the weighted mean (longest exposure's units², None if not known)
        and the noise model behind it, once every sample is in."""
        ...


class ThesisBlending:
    """The thesis' weights (Algorithm 11); the merged image has no variance."""

    needs_variance = False

    def __init__(
        self,
        shape: tuple[int, int],
        levels: SensorLevels,
        *,
        low: float,
        weight_unit: np.float32,
        erode: bool = True,
    ) -> None:
        self.saturation_dn = levels.saturation_dn
        self.erode = erode

    def weight(self, sample: ExposureSample, chain: float, scaled: np.ndarray) -> np.ndarray:
        # p = 1 exactly where the mean reached saturation: per-pixel headroom above the dark
        headroom = np.float32(self.saturation_dn) - np.asarray(sample.dark.mean, np.float32)
        return blend_weight(sample.signal / headroom, erode=self.erode)

    def variance(
        self, weight_sum: np.ndarray, exposures_s: list[float]
    ) -> tuple[np.ndarray | None, NoiseModel | None]:
        return None, None


class NoiseBlending:
    """Inverse-variance weights under the noise model fitted as the samples come in.

    Parameters
    ----------
    shape : (rows, cols)
    levels : SensorLevels
    low : float
        Fraction of the saturation range below which samples do not enter the noise fit.
    weight_unit : float32
        A common factor of every weight (the exposure span): it keeps the squared weights
        of the shortest exposure (variance ∝ chain²) from underflowing float32.
    erode : bool
        Unused (the thesis method's erosion).
    """

    needs_variance = True

    def __init__(
        self,
        shape: tuple[int, int],
        levels: SensorLevels,
        *,
        low: float,
        weight_unit: np.float32,
        erode: bool = True,
    ) -> None:
        self.estimator = NoiseEstimator(levels.saturation_range, low=low)
        self.weight_unit = weight_unit
        self.pilot = np.zeros(shape, np.float32)
        self.has_pilot = np.zeros(shape, bool)
        self.shot_part = np.zeros(shape, np.float32)
        self.constant_part = np.zeros(shape, np.float32)

    def weight(self, sample: ExposureSample, chain: float, scaled: np.ndarray) -> np.ndarray:
        estimator, dark = self.estimator, sample.dark
        estimator.add(
            sample.exposure_s,
            sample.signal,
            sample.replicate_variance,
            sample.usable,
            dark_variance=dark.variance_dn2,
        )
        gain = estimator.gain() or 0.0
        if dark.variance_dn2 is not None:
            constant = dark.variance_dn2
        elif estimator.pixels:
            constant = estimator.constant_variance(sample.exposure_s)[0]
        else:
            constant = 0.0
        new = sample.usable & ~self.has_pilot
        self.pilot[new] = scaled[new]
        self.has_pilot |= new
        # shot-noise variance per unit gain, in the longest exposure's units²: the signal
        # the pilot implies at this exposure (pilot / chain, ≥ 0), × chain² / replicates
        shot = np.maximum(self.pilot, 0) * np.float32(chain / sample.replicates)
        dark_mean_var = constant / dark.count if dark.count else 0.0
        const = np.float32(chain * chain * (constant / sample.replicates + dark_mean_var))
        variance = np.float32(gain) * shot + const
        weight = np.zeros(variance.shape, np.float32)
        positive = sample.usable & (variance > 0)
        weight[positive] = self.weight_unit / variance[positive]
        squared = weight * weight
        self.shot_part += squared * shot
        self.constant_part += squared * const
        return weight

    def variance(
        self, weight_sum: np.ndarray, exposures_s: list[float]
    ) -> tuple[np.ndarray | None, NoiseModel | None]:
        model = self.estimator.model(exposures_s)
        variance = np.empty(weight_sum.shape, np.float32)
        safe = np.where(weight_sum <= 0, 1.0, weight_sum)
        variance[:] = (np.float32(model.gain_dn_per_e) * self.shot_part + self.constant_part) / (
            safe * safe
        )
        return variance, model


BLENDINGS: dict[str, type[ThesisBlending] | type[NoiseBlending]] = {
    "thesis": ThesisBlending,
    "noise": NoiseBlending,
}
"""The weightings of the merge by name."""
