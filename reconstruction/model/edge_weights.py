"""Edge weights of the edge-guided L2 prior ``‖√w ⊙ ∇xy I‖₂²`` (``EdgeL2``, beyond the thesis).

The L2 prior ‖∇xy I‖₂² fills the pixels a Bayer channel does not sample by smoothing
across edges as much as along them: the green channel's one-pixel fringe along every edge
that bilinear demosaicing also has. Directional demosaicing (Menon et al. 2007) avoids it by
interpolating along the edge. This prior does the same inside problem (3.1): each forward
difference of the gradient gets a weight ``w = floor + (1 − floor) / (1 + (ΔL / κ)²)``
from the same difference ΔL of a guide image L, the mean over channels of the raw
patch's Menon demosaic: a difference that crosses an edge of the guide is penalised
``floor`` times as much as one in a flat area, so a pixel takes its value from its
neighbours along the edge. The weights depend on the raw image only, so the problem stays
quadratic: one optimum, solved as fast as L2 (the FFT solvers precondition with the mean
weight; with Φ, conjugate gradients need a few more iterations).

κ is relative to the level of the raw image (the reconstruction's normalised units: its
mean is 1), so the weights do not change with exposure. :data:`EDGE_CONTRAST` and
:data:`EDGE_FLOOR` were chosen on the real ColorChecker frames and on the simulated
ColorChecker together (figures in docs/notes/edge-guided-prior.md and ``labkit bench reconstruct``).
"""

from __future__ import annotations

import numpy as np

from labkit.errors import DataError
from reconstruction.baselines import demosaic_menon
from reconstruction.model.operators import Gradient

EDGE_CONTRAST = 0.05
"""κ: a guide difference of this fraction of the raw level halves a weight's excess over
the floor."""

EDGE_FLOOR = 0.15
"""Smallest weight, at the strongest edges (lower: sharper edges and texture, a larger
per-pixel error on the real chart, and more conjugate-gradient iterations, the matrix being
less well conditioned). Chosen with cubic Φ, the default: with bilinear Φ, whose blur makes
the solver sharpen anyway, 0.2 did as well."""


def edge_weights(
    raw: np.ndarray,
    *,
    cfa: str,
    level: float = 1.0,
    contrast: float = EDGE_CONTRAST,
    floor: float = EDGE_FLOOR,
) -> np.ndarray:
    """Weights (rows, cols, 2) of the gradient's forward differences from a raw mosaic.

    Parameters
    ----------
    raw : ndarray (rows, cols)
        Bayer mosaic, finite, even size (a patch of the normalised raw image).
    cfa : str
        Bayer layout at `raw`'s top-left pixel.
    level : float
        The raw image's level (its mean) in `raw`'s units: 1 for the normalised image.
    contrast : float
        κ, relative to `level` (> 0).
    floor : float
        Smallest weight, in (0, 1].

    Returns
    -------
    ndarray (rows, cols, 2) float64
        ``[y, x, 0]`` weighs ``I[y, x+1] − I[y, x]``, ``[y, x, 1]`` weighs
        ``I[y+1, x] − I[y, x]`` (periodic, as :class:`~reconstruction.model.operators.Gradient`).

    Raises
    ------
    DataError
        Non-finite values, or `level`, `contrast` or `floor` out of range.
    """
    raw = np.asarray(raw, dtype=np.float64)
    if raw.ndim != 2 or not np.all(np.isfinite(raw)):
        raise DataError(f"edge weights need a finite 2-D raw mosaic, got shape {raw.shape}")
    if not (np.isfinite(level) and level > 0):
        raise DataError(f"edge weights need a raw level > 0, got {level}")
    if not (np.isfinite(contrast) and contrast > 0):
        raise DataError(f"edge contrast κ must be > 0, got {contrast}")
    if not (0 < floor <= 1):
        raise DataError(f"edge weight floor must be in (0, 1], got {floor}")
    guide = np.mean(demosaic_menon(raw, cfa), axis=2, keepdims=True, dtype=np.float64)
    # the guide's differences are those the weights multiply: Gradient's, (rows, cols, 2)
    step = Gradient(guide.shape).forward(guide)[:, :, 0, :] / (contrast * level)
    return floor + (1.0 - floor) / (1.0 + step * step)


__all__ = ["EDGE_CONTRAST", "EDGE_FLOOR", "edge_weights"]
