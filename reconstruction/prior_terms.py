"""The regularisation terms of problem (3.1) and the combinations of Table 3.1 (thesis §3.5).

A prior is a sum ``Σ_j w_j S_j(I)`` with ``S_j(I) = ‖D_j I‖_p^p``, where ``D_j`` is one of
the difference operators of :mod:`reconstruction.operators.priors` and p ∈ {1, 2}:

=================  ===========================================================
name               terms
=================  ===========================================================
``L1``             ‖∇xy I‖₁
``L2``             ‖∇xy I‖₂²
``Lap1``           ‖∇²xy I‖₁
``Lap2``           ‖∇²xy I‖₂²
``L1L1``           ‖∇xy I‖₁ + ‖∇λ∇xy I‖₁
``L2L2``           ‖∇xy I‖₂² + ‖∇λ∇xy I‖₂²
``L1SpatialLap2``  ‖∇xy I‖₁ + ‖∇²xy I‖₂²
``L1SpectralLap2`` ‖∇λ∇xy I‖₁ + ‖∇²xy I‖₂²
=================  ===========================================================

Each combination may be used with or without non-negativity (a separate option).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from labkit.errors import DataError
from reconstruction.operators import Gradient, Laplacian, LinearOperator, SpectralGradient

Difference = Literal["gradient", "spectral_gradient", "laplacian"]


@dataclass(frozen=True)
class PriorTerm:
    """One penalty ``‖D I‖_p^p``: `operator` names D, `norm` is p (1 or 2)."""

    operator: Difference
    norm: Literal[1, 2]

    @property
    def label(self) -> str:
        return f"{self.operator}_L{self.norm}"

    def difference(self, shape: tuple[int, int, int]) -> LinearOperator:
        """D on images of `shape` (rows, cols, channels), periodic boundary."""
        if self.operator == "gradient":
            return Gradient(shape)
        if self.operator == "spectral_gradient":
            return SpectralGradient(shape)
        return Laplacian(shape)

    def spatial_symbol(self, shape: tuple[int, int]) -> np.ndarray:
        """Real multiplier (rows, cols) of DᵀD per spatial frequency (the spectral part aside)."""
        # ∇ᵀ∇ and the Laplacian share one symbol; DᵀD of the Laplacian is its square
        laplacian = Laplacian((*shape, 1)).fourier_symbol()
        return laplacian**2 if self.operator == "laplacian" else laplacian

    def spectral_matrix(self, channels: int) -> np.ndarray:
        """The channel factor (channels × channels) of DᵀD: I, or D_λᵀD_λ for ∇λ∇xy."""
        if self.operator != "spectral_gradient":
            return np.eye(channels)
        d = SpectralGradient((1, 1, channels)).spectral_matrix
        return d.T @ d

    def value(self, d_image: np.ndarray) -> float:
        """S(I) = ‖D I‖_p^p from D I."""
        return float(np.sum(np.abs(d_image))) if self.norm == 1 else float(np.sum(d_image**2))


_G1, _G2 = PriorTerm("gradient", 1), PriorTerm("gradient", 2)
_S1, _S2 = PriorTerm("spectral_gradient", 1), PriorTerm("spectral_gradient", 2)
_L1, _L2 = PriorTerm("laplacian", 1), PriorTerm("laplacian", 2)

#: Table 3.1: prior name → its terms, in the order of their weights.
PRIORS: dict[str, tuple[PriorTerm, ...]] = {
    "L1": (_G1,),
    "L2": (_G2,),
    "Lap1": (_L1,),
    "Lap2": (_L2,),
    "L1L1": (_G1, _S1),
    "L2L2": (_G2, _S2),
    "L1SpatialLap2": (_G1, _L2),
    "L1SpectralLap2": (_S1, _L2),
}


def prior_terms(name: str, *, channels: int | None = None) -> tuple[PriorTerm, ...]:
    """The terms of prior `name` (Table 3.1), checked against the number of channels.

    Raises
    ------
    DataError
        Unknown name, or a spectral-gradient term on an image with one channel.
    """
    if name not in PRIORS:
        raise DataError(
            f"unknown prior {name!r}; use one of {', '.join(PRIORS)} (thesis Table 3.1)"
        )
    terms = PRIORS[name]
    if (
        channels is not None
        and channels < 2
        and any(t.operator == "spectral_gradient" for t in terms)
    ):
        raise DataError(f"prior {name!r} has a spectral-gradient term and needs ≥ 2 channels")
    return terms
