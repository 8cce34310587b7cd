"""The kernel of the thin-plate splines (:mod:`calibration.spline_field` evaluates them,
:mod:`calibration.spline` fits them): φ(r) = r² log r in 2-D, −r in 3-D, computed as a
scaled ψ that is cheaper to evaluate.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.distance import cdist

#: φ = PHI_SCALE · ψ, where ψ is what :func:`psi` computes cheaply (r² log r² in 2-D, r in 3-D).
PHI_SCALE = {2: 0.5, 3: -1.0}
_TINY = 1e-300


def psi(
    a: np.ndarray,
    b: np.ndarray,
    dimension: int,
    buffers: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """ψ(|a_i − b_k|) (len(a), len(b)): r² log r² in 2-D, r in 3-D (φ = PHI_SCALE ψ).

    `buffers`, two C-contiguous float64 arrays of shape (len(a), len(b)), are reused
    instead of allocating: allocating megabytes per block costs more than computing them
    (fresh pages are faulted in and zeroed by the kernel).
    """
    if buffers is None:
        r2 = cdist(a, b, "sqeuclidean")
        out = np.empty_like(r2) if dimension == 2 else r2
    else:
        r2, out = buffers
        cdist(a, b, "sqeuclidean", out=r2)
    if dimension == 3:
        return np.sqrt(r2, out=r2)
    np.maximum(r2, _TINY, out=r2)  # r = 0 → r² log r² = 1e-300 · (−690.8) ≈ 0, not NaN
    np.log(r2, out=out)
    out *= r2
    return out
