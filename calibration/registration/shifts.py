"""Sub-pixel shifts of image patches: the batched, windowed, low-passed phase correlation
with one refinement (the estimator of :mod:`calibration.registration`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import fft as sp_fft
from scipy import ndimage

from calibration.registration._grid import patch_grid
from labkit.blas_threads import fixed_blas_threads
from labkit.errors import DataError

#: Default ceiling of the per-patch registration error (translation-invariant normalised
#: RMS error of the aligned, windowed, low-passed patches; 0 = identical up to shift).
MAX_ERROR = 0.1
#: Default floor of the patch texture (RMS gradient along the weakest direction over the
#: mean intensity, 1/px): textured scenes give 0.05–0.15, a patch centred on a disk of the
#: calibration pattern ≈ 0.1, a patch with only disk edges in its window's tails ≈ 0.01.
MIN_TEXTURE = 0.03
#: Patches processed together (bounds memory: ~40 MB per chunk at 64 px).
_CHUNK = 256
#: Coarse refinement grid of the upsampled DFT: ± this many px around the integer peak.
_COARSE_HALF_PX = 0.8
#: Spectral weights below this are left out of the DFT refinement.
_NEGLIGIBLE_WEIGHT = 1e-6
#: Threads of the batched FFTs.
_WORKERS = -1


@dataclass(frozen=True)
class PatchShifts:
    """Per-patch translations between two images (result of :func:`patch_shifts`).

    Attributes
    ----------
    x, y : ndarray (n,) float64
        Patch centres in the reference image, px (x = column, y = row).
    dx, dy : ndarray (n,) float64
        Displacement reference → moving, px: the feature at (x, y) in the reference is
        at (x + dx, y + dy) in the moving image (``from_reference`` sign).
    error : ndarray (n,) float64
        Translation-invariant normalised RMS error of the aligned patches, 0–1
        (scikit-image's ``error``, computed on the windowed, low-passed patches).
    texture : ndarray (n,) float64
        RMS gradient of the windowed, low-passed patch along its weakest direction
        over its mean intensity, 1/px (the smaller of the two images'); 0 for flat
        patches, small for a single straight edge.
    accepted : ndarray (n,) bool
        Patches that passed the error, texture and search-limit tests.
    """

    x: np.ndarray
    y: np.ndarray
    dx: np.ndarray
    dy: np.ndarray
    error: np.ndarray
    texture: np.ndarray
    accepted: np.ndarray

    def __len__(self) -> int:
        return int(self.x.size)

    @property
    def n_accepted(self) -> int:
        """Number of accepted patches."""
        return int(np.count_nonzero(self.accepted))

    @property
    def n_rejected(self) -> int:
        """Number of rejected patches."""
        return len(self) - self.n_accepted


@fixed_blas_threads
def patch_shifts(
    reference: np.ndarray,
    moving: np.ndarray,
    *,
    patch_px: int = 64,
    step_px: int = 32,
    upsample: int = 100,
    max_error: float = MAX_ERROR,
    min_texture: float = MIN_TEXTURE,
    max_shift_px: float = 8.0,
    window: bool = True,
    lowpass: float | None = 0.06,
    normalization: str | None = None,
    iterations: int = 1,
) -> PatchShifts:
    """Sub-pixel translation of every patch of `moving` relative to `reference`.

    Parameters
    ----------
    reference, moving : ndarray (rows, cols)
        Two images of one scene (any linear units; their scales may differ).
    patch_px : int
        Patch side, px (thesis: 64).
    step_px : int
        Distance between neighbouring patch centres, px (thesis: 32). The patch grid is
        centred in the image.
    upsample : int
        Upsampling factor of the DFT refinement: shifts are resolved to 1/`upsample` px.
    max_error : float
        Reject patches whose registration error (0–1) exceeds this.
    min_texture : float
        Reject patches whose texture (see :class:`PatchShifts`, 1/px) is below this.
    max_shift_px : float
        Search range, px; patches whose shift reaches it in x or y are rejected.
    window : bool
        Apply a Hann window to each (mean-subtracted) patch.
    lowpass : float or None
        Standard deviation of the Gaussian weight on the cross-power spectrum,
        cycles/px (None: no weighting, as scikit-image).
    normalization : {None, "phase"}
        ``"phase"`` whitens the cross-power spectrum (phase correlation) before the
        low-pass weight; None keeps it (cross-correlation, scikit-image's
        ``normalization=None``), which was the more accurate on Bayer images.
    iterations : int
        Refinement passes after the first estimate (0 = a single pass).

    Returns
    -------
    PatchShifts
        Rejected patches keep their (unreliable) estimates; nothing is NaN.

    Raises
    ------
    DataError
        Images of different shape, smaller than one patch, or holding NaN/Inf.
    """
    reference = np.asarray(reference, dtype=np.float64)
    moving = np.asarray(moving, dtype=np.float64)
    _check_pair(reference, moving, patch_px, step_px, upsample, max_shift_px, normalization)
    r0, c0 = patch_grid(reference.shape, patch_px, step_px)
    n = r0.size
    weight = _spectral_weight(patch_px, lowpass)
    taper = _hann(patch_px) if window else np.ones((patch_px, patch_px))
    margin = int(np.ceil(max_shift_px)) + 4
    coefficients = None
    if iterations > 0:
        padded = np.pad(moving, margin, mode="reflect")
        coefficients = ndimage.spline_filter(padded, order=3, mode="mirror")
    ref_windows = np.lib.stride_tricks.sliding_window_view(reference, (patch_px, patch_px))
    mov_windows = np.lib.stride_tricks.sliding_window_view(moving, (patch_px, patch_px))
    dx, dy, error, texture = np.zeros(n), np.zeros(n), np.ones(n), np.zeros(n)
    at_limit = np.zeros(n, dtype=bool)
    for start in range(0, n, _CHUNK):
        part = slice(start, min(start + _CHUNK, n))
        rows, cols = r0[part], c0[part]
        ref_spectrum, ref_level = _spectrum(ref_windows[rows, cols], taper)
        texture[part] = _texture(ref_spectrum, ref_level, weight, taper)
        shift = np.zeros((rows.size, 2))  # (dy, dx)
        for step in range(iterations + 1):
            if step == 0:
                mov_patches = mov_windows[rows, cols]
                search = max_shift_px + 1.0
            else:
                # patches beyond the search range are rejected; keep them inside the padding
                inside = np.clip(shift, 3 - margin, margin - 3)
                mov_patches = _shifted_patches(coefficients, rows, cols, inside, patch_px, margin)
                search = 2.0
            mov_spectrum, mov_level = _spectrum(mov_patches, taper)
            if step == 0:
                texture[part] = np.minimum(
                    texture[part], _texture(mov_spectrum, mov_level, weight, taper)
                )
            cross = np.conj(ref_spectrum) * mov_spectrum
            weighted = cross
            if normalization == "phase":
                weighted = cross / np.maximum(np.abs(cross), np.finfo(np.float64).tiny)
            if weight is not None:
                weighted = weighted * weight
            residual = _correlation_peak(weighted, search, upsample, _support(weight))
            shift = shift + residual
            if step == 0:
                at_limit[part] = np.any(np.abs(residual) > max_shift_px, axis=1)
        error[part] = _registration_error(cross, ref_spectrum, mov_spectrum, weight, residual)
        flat = texture[part] == 0
        shift[flat] = 0.0  # no signal: report no displacement rather than noise
        dy[part], dx[part] = shift[:, 0], shift[:, 1]
    at_limit |= np.maximum(np.abs(dx), np.abs(dy)) > max_shift_px
    accepted = (error <= max_error) & (texture >= min_texture) & ~at_limit
    half = (patch_px - 1) / 2.0
    return PatchShifts(
        x=c0 + half,
        y=r0 + half,
        dx=dx,
        dy=dy,
        error=error,
        texture=texture,
        accepted=accepted,
    )


# -- the batched estimator ------------------------------------------------------------


def _check_pair(
    reference: np.ndarray,
    moving: np.ndarray,
    patch_px: int,
    step_px: int,
    upsample: int,
    max_shift_px: float,
    normalization: str | None,
) -> None:
    if reference.ndim != 2 or reference.shape != moving.shape:
        raise DataError(
            f"patch_shifts needs two 2-D images of one shape, got {reference.shape} "
            f"and {moving.shape}"
        )
    if patch_px < 8 or step_px < 1 or upsample < 1:
        raise DataError(
            f"patch_px ≥ 8, step_px ≥ 1 and upsample ≥ 1 required, got {patch_px}, "
            f"{step_px}, {upsample}"
        )
    if min(reference.shape) < patch_px:
        raise DataError(
            f"images of {reference.shape[1]}×{reference.shape[0]} px are smaller than one "
            f"{patch_px} px patch; use a smaller patch_px"
        )
    if not 0 < max_shift_px < patch_px / 4:
        raise DataError(
            f"max_shift_px must be in (0, {patch_px / 4:g}) for {patch_px} px patches, "
            f"got {max_shift_px}"
        )
    if normalization not in (None, "phase"):
        raise DataError(f"normalization must be None or 'phase', not {normalization!r}")
    for name, image in (("reference", reference), ("moving", moving)):
        if not np.all(np.isfinite(image)):
            raise DataError(f"the {name} image holds NaN or Inf pixels")


def _hann(size: int) -> np.ndarray:
    """Separable Hann window (size, size) without zero end points."""
    w = np.hanning(size + 2)[1:-1]
    return np.outer(w, w)


def _spectral_weight(size: int, sigma: float | None) -> np.ndarray | None:
    """Gaussian weight (size, size) on the FFT grid, σ in cycles/px (None: no weight)."""
    if sigma is None:
        return None
    if sigma <= 0:
        raise DataError(f"lowpass must be a positive number of cycles/px, got {sigma}")
    f = np.fft.fftfreq(size)
    return np.exp(-(f[:, None] ** 2 + f[None, :] ** 2) / (2.0 * sigma * sigma))


def _support(weight: np.ndarray | None) -> np.ndarray | None:
    """FFT indices (one axis) where the separable spectral weight is not negligible."""
    if weight is None:
        return None
    return np.flatnonzero(weight[0] > _NEGLIGIBLE_WEIGHT)


def _spectrum(patches: np.ndarray, taper: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """FFT (n, p, p) of the mean-subtracted, windowed patches and their windowed means."""
    level = np.einsum("nij,ij->n", patches, taper) / taper.sum()
    centred = (patches - level[:, None, None]) * taper
    return sp_fft.fft2(centred, workers=_WORKERS), level


def _texture(
    spectrum: np.ndarray, level: np.ndarray, weight: np.ndarray | None, taper: np.ndarray
) -> np.ndarray:
    """Texture of each patch: RMS gradient along its weakest direction over its mean, 1/px.

    The gradient structure tensor J = mean(∇I ∇Iᵀ) of the windowed, low-passed patch is
    computed from its spectrum (Parseval); sqrt of its smaller eigenvalue is 0 for flat
    patches and for patches holding a single straight edge (the aperture problem), which
    constrain the shift in at most one direction. 0 where the mean is not positive.
    """
    size = spectrum.shape[1]
    f = 2.0 * np.pi * np.fft.fftfreq(size)
    power = np.abs(spectrum) ** 2
    if weight is not None:
        power = power * weight
    scale = size * size * np.sum(taper * taper)
    jyy = np.einsum("nij,i->n", power, f * f) / scale
    jxx = np.einsum("nij,j->n", power, f * f) / scale
    jxy = np.einsum("nij,i,j->n", power, f, f) / scale
    smallest = 0.5 * (jxx + jyy) - np.sqrt(0.25 * (jxx - jyy) ** 2 + jxy * jxy)
    rms = np.sqrt(np.maximum(smallest, 0.0))
    return np.divide(rms, level, out=np.zeros_like(rms), where=level > 0)


def _correlation_peak(
    cross: np.ndarray, search_px: float, upsample: int, support: np.ndarray | None
) -> np.ndarray:
    """Location (n, 2) = (dy, dx) of the maximum of the correlation ``ifft2(cross)``.

    The whole-pixel maximum within ±`search_px` is refined by matrix-multiply DFTs
    (Guizar-Sicairos et al. 2008, as scikit-image): first on a 0.1 px grid over
    ±0.8 px, then on a 1/`upsample` px grid over ±0.1 px. `support` restricts the DFTs
    to the frequencies (per axis) that carry weight.
    """
    n, size, _ = cross.shape
    surface = sp_fft.ifft2(cross, workers=_WORKERS).real
    offsets = np.fft.fftfreq(size, 1.0 / size)  # 0, 1, …, −1
    outside = np.abs(offsets) > search_px
    surface[:, outside, :] = -np.inf
    surface[:, :, outside] = -np.inf
    flat = np.argmax(surface.reshape(n, -1), axis=1)
    peak = np.column_stack([offsets[flat // size], offsets[flat % size]])
    if upsample == 1:
        return peak
    freq = np.fft.fftfreq(size)
    if support is not None:
        cross = cross[:, support][:, :, support]
        freq = freq[support]
    coarse_step = 1.0 / min(upsample, 10)
    for step, half in ((coarse_step, _COARSE_HALF_PX), (1.0 / upsample, coarse_step)):
        if step >= half:
            continue
        grid = step * np.arange(-round(half / step), round(half / step) + 1)
        peak = _refine(cross, freq, peak, grid)
    return peak


def _refine(
    cross: np.ndarray, freq: np.ndarray, centre: np.ndarray, grid: np.ndarray
) -> np.ndarray:
    """Maximum of the correlation sampled at `centre` + `grid` × `grid`, (n, 2) px.

    The DFT kernel factorises, exp(2πi f (c + g)) = exp(2πi f c) exp(2πi f g): each
    spectrum is phase-shifted to its centre, then all patches share two matrix
    products with the grid kernel (two large GEMMs instead of 2n small ones).
    """
    n, m, _ = cross.shape
    k = grid.size
    row = np.exp(2j * np.pi * centre[:, 0:1] * freq[None, :])  # (n, m)
    col = np.exp(2j * np.pi * centre[:, 1:2] * freq[None, :])
    shifted = row[:, :, None] * cross * col[:, None, :]  # (n, m, m)
    kernel = np.exp(2j * np.pi * grid[:, None] * freq[None, :])  # (k, m)
    left = kernel @ shifted.transpose(1, 0, 2).reshape(m, n * m)  # (k, n·m)
    samples = (left.reshape(k * n, m) @ kernel.T).reshape(k, n, k).real  # (k_y, n, k_x)
    flat = np.argmax(samples.transpose(1, 0, 2).reshape(n, -1), axis=1)
    return centre + np.column_stack([grid[flat // k], grid[flat % k]])


def _registration_error(
    cross: np.ndarray,
    ref_spectrum: np.ndarray,
    mov_spectrum: np.ndarray,
    weight: np.ndarray | None,
    shift: np.ndarray,
) -> np.ndarray:
    """Translation-invariant normalised RMS error of the patches at `shift` (n, 2).

    ``sqrt(1 − c² / (E_ref E_mov))`` with c the weighted cross-correlation at the
    shift found in the last pass and E the weighted energies (scikit-image's ``error``
    of the unnormalised correlation); 1 where a patch has no energy or c < 0.
    """
    size = cross.shape[1]
    freq = np.fft.fftfreq(size)
    w = 1.0 if weight is None else weight
    row = np.exp(2j * np.pi * shift[:, 0:1] * freq[None, :])  # (n, p)
    col = np.exp(2j * np.pi * shift[:, 1:2] * freq[None, :])
    peak = np.einsum("ni,nij,nj->n", row, cross * w, col).real
    energy = np.sum(np.abs(ref_spectrum) ** 2 * w, axis=(1, 2)) * np.sum(
        np.abs(mov_spectrum) ** 2 * w, axis=(1, 2)
    )
    ratio = np.divide(peak * peak, energy, out=np.zeros_like(peak), where=energy > 0)
    ratio[peak < 0] = 0.0
    return np.sqrt(np.clip(1.0 - ratio, 0.0, 1.0))


def _bspline_weights(fraction: np.ndarray) -> np.ndarray:
    """Cubic B-spline weights (n, 4) of the samples at −1, 0, 1, 2 for offsets in [0, 1)."""
    t = np.abs(fraction[:, None] - np.arange(-1, 3)[None, :])
    inner = 2.0 / 3.0 - t * t + 0.5 * t**3
    outer = np.maximum(2.0 - t, 0.0) ** 3 / 6.0
    return np.where(t < 1.0, inner, outer)


def _shifted_patches(
    coefficients: np.ndarray,
    r0: np.ndarray,
    c0: np.ndarray,
    shift: np.ndarray,
    patch_px: int,
    margin: int,
) -> np.ndarray:
    """Patches of the moving image sampled at (r0 + i + dy, c0 + j + dx) (cubic B-spline).

    `coefficients` are the B-spline coefficients of the moving image padded by `margin`.
    """
    whole = np.floor(shift).astype(np.int64)
    frac = shift - whole
    top = r0 + whole[:, 0] + margin - 1
    left = c0 + whole[:, 1] + margin - 1
    windows = np.lib.stride_tricks.sliding_window_view(coefficients, (patch_px + 3, patch_px + 3))
    block = windows[top, left]  # (n, p + 3, p + 3)
    wy = _bspline_weights(frac[:, 0])
    wx = _bspline_weights(frac[:, 1])
    cols = sum(wx[:, m, None, None] * block[:, :, m : m + patch_px] for m in range(4))
    return sum(wy[:, m, None, None] * cols[:, m : m + patch_px, :] for m in range(4))
