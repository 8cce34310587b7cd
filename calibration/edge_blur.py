"""The optical blur of a camera, measured on the straight patch edges of a chart.

Across an edge, the raw image's Green samples follow a step blurred by the lens' point
spread function and integrated over each pixel's area. :func:`edge_blur` fits that model,
``a + b · E((x − x₀) / σ)`` with E a unit step convolved with a Gaussian of standard
deviation σ and a 1-px box, to short profiles across every patch edge (two neighbouring
rows or columns together, so that the Bayer pattern's Green samples cover every position)
and reports the median σ over the profiles that show a clear step.

The fit is a grid search over (x₀, σ) with (a, b) solved by least squares at every grid
point, for all profiles at once. It measures the blur of the image as it is, whatever its
cause (defocus, aberrations, resampling of the frames), which is what the simulated rig's
``blur_sigma_px`` must reproduce for simulated and real images to agree
(docs/notes/blur.md).
Green is used because it is sampled twice as densely as Red and Blue; a band whose Green
response is weak gives a noisier, lower estimate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr

from labkit.cfa import channel_index
from labkit.errors import DataError

HALF_WIDTH_PX = 4
"""Samples each side of an edge in a profile (the gaps between a chart's patches are wider)."""
MIN_CONTRAST = 0.1
"""Smallest step, relative to the brighter side, that a profile must show to be used."""
_OFFSETS = np.arange(-2.0, 2.0001, 0.02)  # x₀, px from the marked edge
_SIGMAS = np.arange(0.02, 2.0001, 0.01)  # σ, px


@dataclass(frozen=True)
class EdgeBlur:
    """Result of :func:`edge_blur`.

    Attributes
    ----------
    sigma_px : float
        Median Gaussian standard deviation of the blur over the profiles, px.
    quartiles_px : (float, float)
        25th and 75th percentile of the profiles' σ, px.
    profiles : int
        Profiles with a clear step that were fitted.
    """

    sigma_px: float
    quartiles_px: tuple[float, float]
    profiles: int


def _step(x: np.ndarray, offset: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """A unit step at `offset`, blurred by a Gaussian of `sigma` and averaged over each
    1-px pixel centred on `x`: ∫ Φ((t − x₀)/σ) dt over [x − ½, x + ½]."""

    def antiderivative(u: np.ndarray) -> np.ndarray:
        z = u / sigma
        return u * ndtr(z) + sigma * np.exp(-0.5 * z * z) / np.sqrt(2.0 * np.pi)

    return antiderivative(x - offset + 0.5) - antiderivative(x - offset - 0.5)


def _profiles(raw: np.ndarray, green: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Green profiles (count, 2 · HALF_WIDTH_PX) across the left and right edges of every
    labelled patch, two rows at a time, in the middle 60 % of each patch's rows; the
    marked edge lies between samples HALF_WIDTH_PX − 1 and HALF_WIDTH_PX."""
    out = []
    half = HALF_WIDTH_PX
    for label in np.unique(labels[labels > 0]):
        rows = np.flatnonzero((labels == label).any(axis=1))
        inset = int(0.2 * rows.size)
        for r in rows[inset : rows.size - inset - 1 : 2]:
            inside = np.flatnonzero(labels[r] == label)
            for edge in (inside[0], inside[-1] + 1):
                if edge - half < 0 or edge + half > raw.shape[1]:
                    continue
                window = np.s_[r : r + 2, edge - half : edge + half]
                counts = green[window].sum(axis=0)
                if np.any(counts == 0):
                    continue
                out.append(np.where(green[window], raw[window], 0.0).sum(axis=0) / counts)
    return np.array(out).reshape(-1, 2 * half)


def edge_blur(
    raw: np.ndarray, *, cfa: str, labels: np.ndarray, saturation: float | None = None
) -> EdgeBlur:
    """Measure the blur of a raw image on the straight edges of a chart's patches.

    Parameters
    ----------
    raw : ndarray (rows, cols)
        Bayer raw image, linear (dark-subtracted), any units.
    cfa : str
        Bayer layout of `raw` (RGGB, GRBG, GBRG, BGGR).
    labels : ndarray of int (rows, cols)
        Patch index per pixel, 0 outside the patches (a ColorChecker label image; for
        rectangles,
        :func:`reconstruction.evaluate.residual_aberration.labels_from_boxes`). Edges are
        taken from each patch's first and last pixel in a row and, through the transpose,
        in a column; a marked edge may be up to 2 px off the true one.
    saturation : float, optional
        Raw value at and above which a pixel is clipped: profiles holding one are left out
        (a clipped step looks sharper than it is).

    Returns
    -------
    EdgeBlur
        σ in px of the raw image's pixel grid.

    Raises
    ------
    DataError
        Shapes differ, the image is not finite, or no edge shows a clear step.
    """
    raw = np.asarray(raw, dtype=np.float64)
    labels = np.asarray(labels)
    if raw.ndim != 2 or labels.shape != raw.shape:
        raise DataError(
            f"edge_blur needs a raw image and a label image of one shape, got {raw.shape} "
            f"and {labels.shape}"
        )
    if not np.all(np.isfinite(raw)):
        raise DataError("edge_blur: the raw image holds NaN or Inf")
    green = channel_index(cfa, raw.shape) == 1
    profiles = np.concatenate([_profiles(raw, green, labels), _profiles(raw.T, green.T, labels.T)])
    x = np.arange(-HALF_WIDTH_PX, HALF_WIDTH_PX) + 0.5  # the marked edge at 0
    offset, sigma = np.meshgrid(_OFFSETS, _SIGMAS, indexing="ij")
    steps = _step(x, offset.ravel()[:, None], sigma.ravel()[:, None])  # (candidates, samples)
    # least squares in (a, b) per candidate: project the centred profile on the centred step
    steps_c = steps - steps.mean(axis=1, keepdims=True)
    norms = np.sum(steps_c**2, axis=1)
    profiles_c = profiles - profiles.mean(axis=1, keepdims=True)
    explained = (profiles_c @ steps_c.T) ** 2 / norms  # (profiles, candidates)
    best = np.argmax(explained, axis=1)
    b = (profiles_c * steps_c[best]).sum(axis=1) / norms[best]
    a = profiles.mean(axis=1) - b * steps[best].mean(axis=1)
    level = np.maximum(np.abs(a), np.abs(a + b))
    fitted_offset = offset.ravel()[best]
    clear = (np.abs(b) >= MIN_CONTRAST * level) & (np.abs(fitted_offset) < _OFFSETS[-1] - 0.01)
    if saturation is not None:
        clear &= profiles.max(axis=1) < saturation
    if not np.any(clear):
        raise DataError(
            "edge_blur: no patch edge shows a clear, unclipped step; check that the label "
            "image matches the raw image, that the patches differ in brightness and that "
            "the image is not saturated"
        )
    sigmas = sigma.ravel()[best][clear]
    q1, median, q3 = np.percentile(sigmas, [25, 50, 75])
    return EdgeBlur(float(median), (float(q1), float(q3)), int(sigmas.size))
