"""Band balance of the L2 priors: each band's spatial smoothing scaled to how well the
camera senses it (beyond the thesis).

The thesis' L2 prior ``w ‖∇xy I‖₂²`` smooths every band alike. A band the camera barely
senses (a small column of the colour matrix C = Ω·B: the ends of the spectrum, or a filter
that passes little light) is then fixed by the prior far more than by the data: its
smoothing length grows like ``√(w / s_b)`` with the band's data strength
``s_b = ‖C_{:, b}‖²``, and its edges smear over many pixels where the other bands' are
sharp (on the simulated ColorChecker, the 700-nm band's edges with the bright background
spread over about ten pixels). The band-balanced prior weighs band b's gradient by

    f_b ∝ max(s_b / mean(s), floor) ** γ,    normalised to mean(f) = 1,

so that γ = 1 would give every band the same smoothing length and γ = 0 is the thesis'
prior. γ = ½ halves the spread of the lengths on the log scale: a weakly sensed band keeps
more of its own edges while the prior still damps its noise, and the spectral smoothness
term ties it to its neighbours. The floor keeps a band the camera does not sense at all
regularised. Band balance needs the spectral smoothness term (σ > 0): at σ = 0 nothing
else holds a weakly sensed band, and on the real ColorChecker frames the DMC weight search
then picks a weight ten times smaller, which leaves those bands noisy (MRAE 0.33 against
0.22), so the options refuse the combination.

:data:`BAND_BALANCE` (γ) and :data:`BAND_BALANCE_FLOOR` were chosen on the real
ColorChecker frames and on the simulated ColorChecker together
(figures in docs/notes/band-balance.md and ``labkit bench reconstruct``). The problem stays
quadratic and its FFT solvers exact
without Φ: the factors enter their channel matrices.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from labkit.errors import DataError
from reconstruction.model.prior_terms import PriorTerm

BAND_BALANCE = 0.5
"""γ of the EdgeL2 prior with σ > 0 unless given (0: every band smoothed alike, the thesis).
The plain L2 prior takes it only when asked: on the real frames its DMC weight then falls
to a quarter and the image gets worse (figures in docs/notes/band-balance.md)."""

BAND_BALANCE_FLOOR = 0.05
"""Smallest relative data strength s_b / mean(s) a band's factor is computed from."""


def band_factors(
    colour_matrix: np.ndarray, *, exponent: float = BAND_BALANCE, floor: float = BAND_BALANCE_FLOOR
) -> np.ndarray:
    """Per-band factors f (n,) of the spatial L2 prior, with mean 1.

    Parameters
    ----------
    colour_matrix : ndarray (3, n)
        C = Ω·B of the latent space (any common scale: only ratios matter).
    exponent : float
        γ in [0, 1]; 0 gives all ones.
    floor : float
        Smallest relative data strength, in (0, 1].

    Raises
    ------
    DataError
        A colour matrix that is not finite or senses nothing, or γ or the floor out of range.
    """
    c = np.asarray(colour_matrix, dtype=np.float64)
    if c.ndim != 2 or not np.all(np.isfinite(c)):
        raise DataError(f"band balance needs a finite (3, n) colour matrix, got shape {c.shape}")
    if not (np.isfinite(exponent) and 0.0 <= exponent <= 1.0):
        raise DataError(f"band balance γ must be in [0, 1], got {exponent}")
    if not (0.0 < floor <= 1.0):
        raise DataError(f"band balance floor must be in (0, 1], got {floor}")
    strength = np.sum(c * c, axis=0)
    if not np.sum(strength) > 0:
        raise DataError("band balance needs a colour matrix that senses some band; it is 0")
    factors = np.maximum(strength / np.mean(strength), floor) ** exponent
    return factors / np.mean(factors)


def balance_terms(terms: Sequence[PriorTerm], factors: np.ndarray) -> tuple[PriorTerm, ...]:
    """`terms` with `factors` on those band balance applies to
    (:attr:`~reconstruction.model.prior_terms.PriorTerm.balanceable`); all-one factors leave the
    terms as they are."""
    factors = np.asarray(factors, dtype=np.float64)
    if np.all(factors == 1.0):
        return tuple(terms)
    values = tuple(float(v) for v in factors)
    return tuple(replace(t, band_factors=values) if t.balanceable else t for t in terms)


__all__ = ["BAND_BALANCE", "BAND_BALANCE_FLOOR", "balance_terms", "band_factors"]
