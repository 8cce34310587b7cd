"""The spectral basis B of problem (3.1) and the choice of its bands (thesis §3.3.2–3.3.3).

Band selection (§3.3.2, :func:`choose_bands`)
---------------------------------------------
* **Support.** The interval from the first to the last response sample at which *any*
  channel reaches ``support_fraction`` (5 %) of its own peak ``|Q_c|``. The ends are
  sample wavelengths of the response grid (no sub-sample interpolation).
* **Bandlimit.** For each channel, the power spectrum ``|DFT(Q_c)|²`` of the response on
  its (uniform) measurement grid, zero frequency excluded (thesis Figure 3.7); the
  bandlimit is the first DFT frequency ``k / (n Δλ)`` at which the cumulative one-sided
  power reaches ``power_fraction`` (95 %) of the total. The largest over the channels is
  used. It is therefore quantised to the DFT bin width ``1 / (n Δλ)``. A non-uniform
  response grid is first resampled linearly onto a uniform grid at its median step.
* **Centres.** Spacing ``Δv = 1 / (2 f_B)`` (Nyquist), count ``floor(width / Δv) + 1``,
  centred within the support (as in the author's code), so the outer centres lie inside
  the support by up to half a spacing. The thesis reports 35.5 nm and 8 bands in
  418–667 nm for its copy of the Nikon D5100 data; colour-science's "Nikon 5100 (NPL)"
  (380–780 nm, 5 nm) gives a support of 415–670 nm, a bandlimit of 6/405 cycles/nm
  (33.75 nm spacing) and 8 bands at 424.4–660.6 nm.

The operator B (§3.3.3, :class:`SpectralBasis`)
-----------------------------------------------
Coefficients ``I_i`` at uniformly spaced centres ``v_i`` (spacing ``Δv``) give the
spectrum ``S(s_j) = Σ_i K(s_j − v_i) I_i`` (3.9), i.e. ``B_ji = K(s_j − v_i)`` (3.10).

* **Kernel.** The Gaussian (3.12) with σ chosen so that 95 % of the kernel's *power*
  spectrum ``|K̂(f)|² ∝ exp(−4π²σ²f²)`` lies within the Nyquist frequency ``1/(2Δv)`` of
  the centres: ``erf(2πσ/(2Δv)) = 0.95`` ⇒ ``σ = erfinv(0.95) Δv / π ≈ 0.4411 Δv``.
  *Choice:* the kernel is (3.12) multiplied by the constant ``Δv`` (area ``Δv`` instead
  of 1), so coefficients carry the units of the spectrum and a constant coefficient
  vector gives that constant back up to the Gaussian's Poisson ripple
  ``±2 exp(−2π²σ²/Δv²) ≈ ±4.3 %`` (period Δv). This rescaling does not change the set of
  representable spectra, but the ripple limits how well B reproduces smooth spectra
  (figures in docs/notes/solver.md). ``kernel="sinc"`` uses
  ``sinc((s − v)/Δv)`` instead (ideal bandlimited interpolation; may go negative, which
  is why the thesis prefers the Gaussian).
* **B close to identity.** With ``sample_nm == centres_nm`` the Gaussian B is the
  symmetric Toeplitz matrix ``B_ik = (Δv/(σ√2π)) exp(−(i−k)²Δv²/(2σ²))`` (plus the
  extrapolation weights in the first and last columns): diagonal 0.9044, first
  off-diagonals 0.0693, second 3.1e-5; the corner entries are 0.9736 because they also
  carry the extrapolation weights. With ``kernel="sinc"`` it is the identity to rounding.
* **Constant extrapolation.** As the thesis prescribes, B is computed as though the
  coefficient vector were padded on both sides with copies of its end values; the
  padding reaches 12 σ (Gaussian) or 2000 spacings (sinc) beyond the farthest sample,
  and the padded kernel weights are summed into the first/last columns. The truncated
  sinc tail is accurate to ≈ 1e-4 relative (it decays only like 1/n); the Gaussian one
  to rounding. So B equals (3.10) applied to the explicitly padded coefficients, and far
  outside the centres (≳ 9 σ) the spectrum depends only on the nearest end coefficient
  (times the Δv-periodic ripple above: the thesis' "approximately constant").
* **Downsampling (3.11).** If the samples are uniform with a spacing ``Δs > Δv``,
  ``B = B_{b→N} B_{b→b}``: ``B_{b→b}`` is the kernel matrix at the centres and ``B_{b→N}``
  is the sinc low-pass at the samples' Nyquist frequency,
  ``(Δv/Δs) sinc((s_j − v_i)/Δs)``, again with constant padding.
* **Sensible samples.** Sample wavelengths must be positive, finite, strictly increasing
  and no more than :data:`MAX_EXTRAPOLATION_NM` beyond the outer centres.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.special import erfinv

from labkit.errors import DataError
from labkit.spectra import Spectra
from reconstruction.model.operators._base import LinearOperator

KERNELS = ("gaussian", "sinc")
"""Kernels of the spectral basis B."""

MAX_EXTRAPOLATION_NM = 500.0
"""Farthest a sample wavelength may lie beyond the outer band centres, nm."""

KERNEL_POWER_FRACTION = 0.95
"""Fraction of the Gaussian kernel's power within the centres' Nyquist frequency (§3.3.3)."""

_GAUSSIAN_REACH_SIGMAS = 12.0
_SINC_PADDING = 2000
_UNIFORM_RTOL = 1e-6


@dataclass(frozen=True, eq=False)
class BandSelection:
    """Spectral sampling chosen from a camera response (thesis §3.3.2).

    Attributes
    ----------
    support_nm : tuple of float
        First and last response wavelength (nm) where any channel reaches the support
        fraction (5 %) of its own peak.
    bandlimit_cycles_per_nm : float
        The largest channel bandlimit: the frequency (cycles/nm) up to which the
        cumulative power spectrum (zero frequency excluded) reaches the power fraction
        (95 %).
    centres_nm : ndarray, shape (n_bands,)
        Uniform band centres (nm) at the Nyquist spacing ``1 / (2 bandlimit)``, centred
        within the support.
    """

    support_nm: tuple[float, float]
    bandlimit_cycles_per_nm: float
    centres_nm: np.ndarray

    @property
    def spacing_nm(self) -> float:
        """Nyquist sample spacing ``1 / (2 bandlimit)``, nm."""
        return 0.5 / self.bandlimit_cycles_per_nm

    @property
    def n_bands(self) -> int:
        """Number of band centres."""
        return int(self.centres_nm.size)


def _uniform_response(response: Spectra) -> tuple[np.ndarray, np.ndarray, float]:
    """Wavelengths, values and step of `response` on a uniform grid (resampled if needed)."""
    w = response.wavelengths
    steps = np.diff(w)
    step = float(np.median(steps))
    if np.allclose(steps, step, rtol=_UNIFORM_RTOL, atol=0.0):
        return w, response.values, step
    count = int(np.floor((w[-1] - w[0]) / step + 1e-9)) + 1
    grid = w[0] + step * np.arange(count)
    return grid, response.resample(grid, extrapolate="constant").values, step


def _bandlimit(values: np.ndarray, step_nm: float, power_fraction: float) -> float:
    """Largest per-channel 95 %-power frequency (cycles/nm) of `values` (n, channels)."""
    n = values.shape[0]
    power = np.abs(np.fft.rfft(values, axis=0)) ** 2
    power = power[1:]  # exclude the zero frequency (thesis Figure 3.7)
    cumulative = np.cumsum(power, axis=0)
    total = cumulative[-1]
    if np.any(total <= 0):
        raise DataError(
            "a camera response channel is constant over its grid, so it has no bandlimit; "
            "supply the measured response including its fall-off"
        )
    reached = cumulative >= power_fraction * total * (1 - 1e-12)
    first = np.argmax(reached, axis=0) + 1  # DFT bin index k ≥ 1
    return float(first.max() / (n * step_nm))


def choose_bands(
    response: Spectra, *, support_fraction: float = 0.05, power_fraction: float = 0.95
) -> BandSelection:
    """Choose the spectral bands of the estimated image from a camera response (§3.3.2).

    Parameters
    ----------
    response : Spectra
        Channel spectral responses ``Q_c(λ)`` (relative units), wavelengths in nm; at
        least 4 samples and one channel, each channel with a nonzero response.
    support_fraction : float, optional
        Fraction of each channel's peak absolute response counted as sensitive (default 0.05).
    power_fraction : float, optional
        Fraction of the power spectrum (zero frequency excluded) defining the bandlimit
        (default 0.95).

    Returns
    -------
    BandSelection
        Support (nm), bandlimit (cycles/nm) and uniform band centres (nm).

    Raises
    ------
    DataError
        On an empty or all-zero response, a channel without response, or fractions
        outside (0, 1) / (0, 1].
    """
    if not 0.0 < support_fraction < 1.0:
        raise DataError(f"support_fraction must lie in (0, 1), got {support_fraction}")
    if not 0.0 < power_fraction <= 1.0:
        raise DataError(f"power_fraction must lie in (0, 1], got {power_fraction}")
    if response.values.size == 0 or response.values.shape[1] == 0:
        raise DataError("camera response is empty: it has no channels")
    if response.wavelengths.size < 4:
        raise DataError(
            f"camera response has {response.wavelengths.size} samples; need ≥ 4 to estimate "
            "its bandlimit"
        )
    lo, hi = sensitive_range(response, support_fraction=support_fraction)
    _, values, step = _uniform_response(response)
    bandlimit = _bandlimit(values, step, power_fraction)
    spacing = 0.5 / bandlimit
    n_bands = int(np.floor((hi - lo) / spacing + 1e-9)) + 1
    start = 0.5 * (lo + hi - (n_bands - 1) * spacing)
    centres = start + spacing * np.arange(n_bands, dtype=np.float64)
    if n_bands < 2:
        raise DataError(
            f"the response's sensitive range {lo:g}–{hi:g} nm is narrower than one band "
            f"spacing ({spacing:.3g} nm); the camera cannot support a spectral basis"
        )
    return BandSelection((lo, hi), bandlimit, centres)


def sensitive_range(response: Spectra, *, support_fraction: float = 0.05) -> tuple[float, float]:
    """First and last wavelength (nm) where some channel reaches `support_fraction` of its peak.

    Raises
    ------
    DataError
        A channel is zero everywhere.
    """
    magnitude = np.abs(response.values)
    peaks = magnitude.max(axis=0)
    if np.any(peaks <= 0):
        dead = [label for label, p in zip(response.labels, peaks, strict=True) if p <= 0]
        raise DataError(
            f"camera response channel(s) {dead} are zero everywhere; drop them with "
            ".select([...]) before choosing bands"
        )
    sensitive = np.any(magnitude >= support_fraction * peaks, axis=1)
    indices = np.flatnonzero(sensitive)
    return float(response.wavelengths[indices[0]]), float(response.wavelengths[indices[-1]])


def gaussian_sigma_nm(spacing_nm: float, power_fraction: float = KERNEL_POWER_FRACTION) -> float:
    """σ (nm) of the Gaussian whose power within ``1/(2 spacing)`` is `power_fraction`.

    ``|K̂(f)|² ∝ exp(−4π²σ²f²)`` puts ``erf(2πσ f)`` of its power within ``|f| ≤ f``; with
    ``f = 1/(2 spacing)`` this gives ``σ = erfinv(power_fraction) · spacing / π``.
    """
    return float(erfinv(power_fraction) * spacing_nm / np.pi)


def _checked_grid(values: np.ndarray, what: str, minimum_size: int) -> np.ndarray:
    grid = np.asarray(values, dtype=np.float64)
    if grid.ndim != 1 or grid.size < minimum_size:
        raise DataError(f"{what} must be a 1-D array of ≥ {minimum_size} wavelengths (nm)")
    if not np.all(np.isfinite(grid)):
        raise DataError(f"{what} contains NaN or Inf")
    if np.any(np.diff(grid) <= 0):
        raise DataError(f"{what} must be strictly increasing (nm)")
    if grid[0] <= 0:
        raise DataError(f"{what} must be positive wavelengths in nm, got {grid[0]:g}")
    return grid


def _uniform_spacing(grid: np.ndarray) -> float | None:
    """The common spacing of `grid`, or None when it is not uniform."""
    if grid.size < 2:
        return None
    steps = np.diff(grid)
    step = float(steps.mean())
    return step if np.allclose(steps, step, rtol=_UNIFORM_RTOL, atol=0.0) else None


def _padded_weights(
    targets: np.ndarray,
    centres: np.ndarray,
    spacing: float,
    kernel: Callable[[np.ndarray], np.ndarray],
    reach_nm: float,
) -> np.ndarray:
    """``K(t − v)`` over `centres` padded with copies of the end values (constant extension).

    The padding extends `reach_nm` beyond the farthest target; its weights are summed into
    the first and last columns.
    """
    below = max(0.0, centres[0] - targets.min()) + reach_nm
    above = max(0.0, targets.max() - centres[-1]) + reach_nm
    n_lo = int(np.ceil(below / spacing))
    n_hi = int(np.ceil(above / spacing))
    pad_lo = centres[0] - spacing * np.arange(n_lo, 0, -1)
    pad_hi = centres[-1] + spacing * np.arange(1, n_hi + 1)
    weights = np.empty((targets.size, centres.size))
    weights[:] = kernel(targets[:, None] - centres[None, :])
    weights[:, 0] += kernel(targets[:, None] - pad_lo[None, :]).sum(axis=1)
    weights[:, -1] += kernel(targets[:, None] - pad_hi[None, :]).sum(axis=1)
    return weights


class SpectralBasis(LinearOperator):
    """B: band coefficients (rows, cols, n_bands) → spectrum samples (rows, cols, n_samples).

    Parameters
    ----------
    shape : tuple of int
        Image size (rows, cols), pixels.
    centres_nm : ndarray, shape (n_bands,)
        Uniformly spaced, strictly increasing band centres ``v_i``, nm (≥ 2).
    sample_nm : ndarray, shape (n_samples,)
        Strictly increasing wavelengths ``s_j`` (nm) at which the spectrum is evaluated,
        e.g. the dispersion or colour-integration grid; at most
        :data:`MAX_EXTRAPOLATION_NM` beyond the outer centres.
    kernel : {"gaussian", "sinc"}, optional
        Interpolation kernel K (default the thesis' Gaussian (3.12), scaled by ``Δv``).

    Notes
    -----
    See the module docstring for the construction, (3.8)–(3.12). Float32 input gives
    float32 output; anything else is computed in float64.
    """

    name = "B"

    def __init__(
        self,
        shape: tuple[int, int],
        centres_nm: np.ndarray,
        sample_nm: np.ndarray,
        *,
        kernel: str = "gaussian",
    ) -> None:
        if len(shape) != 2 or min(shape) < 1:
            raise DataError(f"B needs an image shape (rows, cols) ≥ 1, got {shape}")
        if kernel not in KERNELS:
            raise DataError(f"unknown kernel {kernel!r}; use 'gaussian' or 'sinc'")
        centres = _checked_grid(centres_nm, "band centres", 2)
        samples = _checked_grid(sample_nm, "sample wavelengths", 1)
        spacing = _uniform_spacing(centres)
        if spacing is None:
            raise DataError(
                "band centres must be equally spaced (the spectral basis is a shifted kernel)"
            )
        low, high = centres[0] - MAX_EXTRAPOLATION_NM, centres[-1] + MAX_EXTRAPOLATION_NM
        if samples[0] < low or samples[-1] > high:
            raise DataError(
                f"sample wavelengths {samples[0]:g}–{samples[-1]:g} nm reach more than "
                f"{MAX_EXTRAPOLATION_NM:g} nm beyond the band centres "
                f"{centres[0]:g}–{centres[-1]:g} nm; restrict the samples"
            )
        super().__init__(
            (int(shape[0]), int(shape[1]), centres.size),
            (int(shape[0]), int(shape[1]), samples.size),
        )
        self.centres_nm = centres
        self.sample_nm = samples
        self.kernel = kernel
        self.spacing_nm = spacing
        self.sigma_nm = gaussian_sigma_nm(spacing) if kernel == "gaussian" else None
        self._matrix = self._build()
        self._matrix32 = self._matrix.astype(np.float32)

    def _kernel(self) -> tuple[Callable[[np.ndarray], np.ndarray], float]:
        spacing = self.spacing_nm
        if self.kernel == "gaussian":
            sigma = gaussian_sigma_nm(spacing)
            scale = spacing / (sigma * np.sqrt(2.0 * np.pi))
            reach = _GAUSSIAN_REACH_SIGMAS * sigma

            def gaussian(x: np.ndarray) -> np.ndarray:
                return scale * np.exp(-0.5 * (x / sigma) ** 2)

            return gaussian, reach

        def sinc(x: np.ndarray) -> np.ndarray:
            return np.sinc(x / spacing)

        return sinc, _SINC_PADDING * spacing

    def _build(self) -> np.ndarray:
        kernel, reach = self._kernel()
        centres, samples, spacing = self.centres_nm, self.sample_nm, self.spacing_nm
        sample_spacing = _uniform_spacing(samples)
        if sample_spacing is None or sample_spacing <= spacing * (1 + _UNIFORM_RTOL):
            return _padded_weights(samples, centres, spacing, kernel, reach)
        # (3.11): values at the centres, then a sinc low-pass at the samples' Nyquist rate.
        at_centres = _padded_weights(centres, centres, spacing, kernel, reach)

        def lowpass(x: np.ndarray) -> np.ndarray:
            return (spacing / sample_spacing) * np.sinc(x / sample_spacing)

        down = _padded_weights(samples, centres, spacing, lowpass, _SINC_PADDING * spacing)
        return down @ at_centres

    @property
    def matrix(self) -> np.ndarray:
        """B as a dense matrix, shape (n_samples, n_bands); ``B[j, i] = K(s_j − v_i)``."""
        return self._matrix.copy()

    def _for(self, array: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if array.dtype == np.float32:
            return array, self._matrix32
        return array.astype(np.float64, copy=False), self._matrix

    def _forward(self, x: np.ndarray) -> np.ndarray:
        x, m = self._for(x)
        return x @ m.T

    def _adjoint(self, y: np.ndarray) -> np.ndarray:
        y, m = self._for(y)
        return y @ m
