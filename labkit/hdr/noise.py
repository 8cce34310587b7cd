"""The sensor's Poisson–Gaussian noise, estimated from the replicates and darks themselves.

Below saturation a dark-subtracted signal ``s`` (DN) has temporal variance
``var = g · s + σ²(t)`` where ``g`` is the conversion gain (DN per electron: shot noise)
and ``σ²(t)`` the read, dark-current and quantisation noise of exposure ``t`` (DN²),
measured from the dark frames of that exposure.

Replicates also differ by effects common to a whole frame (shutter jitter, lamp
flicker): they add ``κ(t) · s²`` to the variance across replicates but not to the
merged image, because the fitted exposure scaling factors absorb them. So ``g`` is the
common slope of a fit ``var = c(t) + g · s + κ(t) · s²`` over all exposures, with its own
``c`` and ``κ`` per exposure (signals normalised by the saturation range first). Where
darks are missing, the fitted ``c(t)`` stands in for ``σ²(t)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from labkit.errors import DataError


@dataclass
class _Sums:
    """Weighted moments of (u, v) for one exposure: u = signal / saturation, v = variance."""

    samples: int
    count: float  # Σ w
    u: float
    u2: float
    u3: float
    u4: float
    v: float
    uv: float
    u2v: float

    @classmethod
    def of(cls, u: np.ndarray, v: np.ndarray) -> _Sums:
        """Weighted moments; weights ≈ 1 / var² so bright, noisy variances do not dominate.

        Computed a chunk at a time in float64, so no full-size float64 copies are made.
        """
        totals = np.zeros(8)
        for start in range(0, u.size, _CHUNK):
            a = u[start : start + _CHUNK].astype(np.float64)
            b = v[start : start + _CHUNK].astype(np.float64)
            w = 1.0 / (a + _CROSSOVER) ** 2
            wu = w * a
            wu2 = wu * a
            totals += (
                w.sum(),
                wu.sum(),
                wu2.sum(),
                wu2 @ a,
                (wu2 * a) @ a,
                w @ b,
                wu @ b,
                wu2 @ b,
            )
        return cls(int(u.size), *(float(t) for t in totals))


_CHUNK = 1 << 18

#: Signal (fraction of saturation) where shot noise starts to dominate a sample variance;
#: weights are ∝ 1 / (u + crossover)², i.e. ∝ 1 / variance² up to a constant.
_CROSSOVER = 0.01
_MIN_SAMPLES = 20


@dataclass
class NoiseModel:
    """Fitted noise: conversion gain and per-exposure constant variance.

    Attributes
    ----------
    gain_dn_per_e : float
        Variance added per DN of signal (= DN per electron), DN.
    constant_variance_dn2 : dict
        Exposure time (s) → read + dark + quantisation variance of one frame, DN².
    source : dict
        Exposure time (s) → ``"darks"`` or ``"fit"`` (where the constant came from).
    pixels : int
        Pixel samples in the gain fit.
    """

    gain_dn_per_e: float
    constant_variance_dn2: dict[float, float] = field(default_factory=dict)
    source: dict[float, str] = field(default_factory=dict)
    pixels: int = 0

    def as_dict(self) -> dict:
        """JSON/YAML-friendly form."""
        return {
            "gain_dn_per_e": self.gain_dn_per_e,
            "pixels": self.pixels,
            "constant_variance_dn2": {
                f"{t:g}": {"value": v, "from": self.source.get(t)}
                for t, v in sorted(self.constant_variance_dn2.items())
            },
        }


class NoiseEstimator:
    """Accumulates (signal, variance) samples exposure by exposure; fits the model.

    Parameters
    ----------
    saturation_range : float
        Signal of a saturated pixel, DN.
    low, high : float
        Only pixels with signal in this fraction of `saturation_range` are used.
    """

    def __init__(self, saturation_range: float, *, low: float = 0.02, high: float = 0.9) -> None:
        self.saturation_range = float(saturation_range)
        self.low = low
        self.high = high
        self._sums: dict[float, _Sums] = {}
        self._dark: dict[float, float] = {}
        self._fit: tuple[float, dict[float, float]] | None = None

    def add(
        self,
        exposure_s: float,
        signal: np.ndarray,
        variance: np.ndarray | None,
        usable: np.ndarray,
        *,
        dark_variance: float | None,
    ) -> None:
        """Add one exposure: mean signal and replicate variance (DN, DN²) of usable pixels."""
        if dark_variance is not None:
            self._dark[exposure_s] = float(dark_variance)
        if variance is None:
            return
        lo, hi = self.low * self.saturation_range, self.high * self.saturation_range
        select = usable & (signal >= lo) & (signal <= hi)
        if np.count_nonzero(select) < _MIN_SAMPLES:
            return
        u = signal[select]
        u /= np.float32(self.saturation_range)
        self._sums[exposure_s] = _Sums.of(u, variance[select])
        self._fit = None

    @property
    def pixels(self) -> int:
        """Pixel samples collected so far."""
        return sum(sums.samples for sums in self._sums.values())

    def _solve(self) -> tuple[float, dict[float, float]] | None:
        """Least squares for (g, c(t)) with κ(t) terms, falling back to κ = 0."""
        if self._fit is not None:
            return self._fit
        keys = list(self._sums)
        if not keys:
            return None
        for quadratic in (True, False):
            size = 1 + len(keys) * (2 if quadratic else 1)
            normal = np.zeros((size, size))
            rhs = np.zeros(size)
            for k, key in enumerate(keys):
                m = self._sums[key]
                c = 1 + k
                normal[0, 0] += m.u2
                normal[0, c] = normal[c, 0] = m.u
                normal[c, c] = m.count
                rhs[0] += m.uv
                rhs[c] = m.v
                if quadratic:
                    q = 1 + len(keys) + k
                    normal[0, q] = normal[q, 0] = m.u3
                    normal[c, q] = normal[q, c] = m.u2
                    normal[q, q] = m.u4
                    rhs[q] = m.u2v
            scale = np.sqrt(np.diag(normal))
            if np.any(scale == 0):
                continue
            scaled = normal / np.outer(scale, scale)
            if np.linalg.cond(scaled) > 1e10:
                continue
            theta = np.linalg.solve(scaled, rhs / scale) / scale
            gain = theta[0] / self.saturation_range
            if gain > 0:
                self._fit = (gain, {key: float(theta[1 + k]) for k, key in enumerate(keys)})
                return self._fit
        return None

    def gain(self) -> float | None:
        """Conversion gain, DN per e⁻ (None until measurable)."""
        fit = self._solve()
        return None if fit is None else fit[0]

    def constant_variance(self, exposure_s: float, gain: float | None = None) -> tuple[float, str]:
        """σ²(t) of one frame, DN²: from the darks, else the fit's intercept."""
        if exposure_s in self._dark:
            return self._dark[exposure_s], "darks"
        fit = self._solve()
        if fit is None:
            raise DataError("cannot estimate the read noise: no darks and no usable replicates")
        intercepts = fit[1]
        value = intercepts.get(exposure_s)
        if value is None:
            value = float(np.median(list(intercepts.values())))
        return max(value, 0.0), "fit"

    def model(self, exposures_s: list[float]) -> NoiseModel:
        """The fitted model for the given exposures."""
        gain = self.gain()
        if gain is None and self._sums:
            raise DataError(
                f"cannot estimate the sensor gain from {self.pixels} pixel samples between "
                f"{self.low:.0%} and {self.high:.0%} of saturation: within each exposure "
                "their signals barely vary (a flat scene), so the replicate variances do not "
                "separate shot from read noise; use a scene with a range of intensities, or "
                "the thesis method"
            )
        if gain is None:
            raise DataError(
                "cannot estimate the sensor gain: no exposure has ≥ 2 replicates with pixels "
                f"between {self.low:.0%} and {self.high:.0%} of saturation; the noise method "
                "needs replicates (--method thesis merges one frame per exposure)"
            )
        result = NoiseModel(gain, pixels=self.pixels)
        for exposure in exposures_s:
            value, source = self.constant_variance(exposure)
            result.constant_variance_dn2[exposure] = value
            result.source[exposure] = source
        return result
