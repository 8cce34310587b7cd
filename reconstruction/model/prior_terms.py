"""The regularisation terms of problem (3.1) and the combinations of Table 3.1 (thesis §3.5).

A prior is a sum ``Σ_j w_j S_j(I)`` with ``S_j(I) = ‖D_j I‖_p^p``, where ``D_j`` is one of
the difference operators of :mod:`reconstruction.model.operators.priors` and p ∈ {1, 2}:

==================  ===========================================================
name                terms
==================  ===========================================================
``L1``              ‖∇xy I‖₁
``L2``              ‖∇xy I‖₂²
``Lap1``            ‖∇²xy I‖₁
``Lap2``            ‖∇²xy I‖₂²
``L1L1``            ‖∇xy I‖₁ + ‖∇λ∇xy I‖₁
``L2L2``            ‖∇xy I‖₂² + ‖∇λ∇xy I‖₂²
``L1SpatialLap2``   ‖∇xy I‖₁ + ‖∇²xy I‖₂²
``L1SpectralLap2``  ‖∇λ∇xy I‖₁ + ‖∇²xy I‖₂²
``VTV``             ‖∇xy I‖₂,₁ (beyond the thesis, see below)
``EdgeL2``          ‖√w ⊙ ∇xy I‖₂² (beyond the thesis, see below)
==================  ===========================================================

Each combination may be used with or without non-negativity (a separate option).

``VTV`` is vectorial total variation (Blomgren & Chan 1998): the sum over pixels of
``√(Σ_bands Σ_directions (∇xy I)²)``. Like ``L1`` it keeps edges sharp where the
quadratic priors interpolate the unsampled bands across them (bilinear demosaicing's
one-pixel fringe); unlike ``L1``, whose per-band sparsity also flattens spectra band by
band, an edge costs once however many bands it crosses, so spectra keep their shape.
On the simulated rig's ColorChecker with cubic Φ its green edge error is below Menon
demosaicing's and L2's at the DMC weight, its spectral error far below L1's, in a fraction
of L1's time. Automatic weights (:mod:`reconstruction.solve.weights`, each weight's solve from
its own initial estimate): the weight the MSE criterion picks on the textured scene keeps
the ColorChecker's green edge error below Menon's; the DMC on the ColorChecker picks a
smaller weight whose green edge error is above Menon's; the DMC against Menon's demosaic
(``auto:dmc-menon``) picks one with a lower spectral error and a green edge error below
Menon's (figures in docs/notes/larger-sigma.md, colour fringes along edges).

``EdgeL2`` is the L2 prior with a weight per pixel and direction taken from the raw image's
own edges (:mod:`reconstruction.model.edge_weights`): differences across an edge cost less, so
unsampled pixels are filled along edges, as directional demosaicing does, while the problem
stays quadratic (one optimum, L2's solvers and cost). A
:class:`~reconstruction.model.problem.Problem` binds the declared term to its raw patch's
weights (:class:`EdgeGuidedTerm`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from labkit.errors import DataError
from reconstruction.model.operators import (
    Gradient,
    Laplacian,
    LinearOperator,
    SpectralDifference,
    SpectralGradient,
    SpectralRoughness,
    WeightedGradient,
)

#: "spectral" (∇λ alone, at every spatial frequency) is no prior of Table 3.1; the spectral
#: smoothness term of :mod:`reconstruction.model.problem` is :class:`SmoothnessTerm` instead.
Difference = Literal["gradient", "spectral_gradient", "laplacian", "spectral"]


@dataclass(frozen=True)
class PriorTerm:
    """One penalty ``‖D I‖_p^p``: `operator` names D, `norm` is p (1 or 2).

    With `grouped` (p = 1 only) the penalty is the mixed norm ``‖D I‖₂,₁``: the 2-norm of
    each pixel's values over bands and directions, summed over pixels.

    With `guided` (the L2 gradient only) the penalty is ``‖√w ⊙ ∇xy I‖₂²`` with edge
    weights w of the problem's raw patch: :meth:`bind` makes the term of one patch. Unbound,
    the term stands for all weights 1 (plain L2).

    With `band_factors` f (the L2 gradient only, guided or not) band b's gradient is
    weighed by f_b: ``Σ_b f_b ‖∇xy I_b‖₂²`` (:mod:`reconstruction.model.band_balance`).
    """

    operator: Difference
    norm: Literal[1, 2]
    grouped: bool = False
    guided: bool = False
    band_factors: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        if self.grouped and self.norm != 1:
            raise DataError("only an L1 term can be grouped (the mixed norm ‖·‖₂,₁)")
        if self.guided and (self.operator != "gradient" or self.norm != 2):
            raise DataError("only the L2 gradient term can be edge-guided")
        if self.band_factors is not None:
            if not self.balanceable:
                raise DataError("only the L2 gradient term can be band-balanced")
            factors = np.asarray(self.band_factors, dtype=np.float64)
            if factors.ndim != 1 or not np.all(np.isfinite(factors)) or np.any(factors < 0):
                raise DataError(f"band factors must be finite and ≥ 0, got {self.band_factors}")

    @property
    def balanceable(self) -> bool:
        """Whether band factors apply (:mod:`reconstruction.model.band_balance`): the quadratic
        spatial gradient (L2, EdgeL2)."""
        return self.operator == "gradient" and self.norm == 2 and not self.grouped

    @property
    def label(self) -> str:
        if self.guided:
            return "edge_gradient_L2"
        return f"{self.operator}_L{'21' if self.grouped else self.norm}"

    def bind(self, weights: np.ndarray) -> EdgeGuidedTerm:
        """The guided term of one patch, with its edge weights (rows, cols, 2)."""
        if not self.guided:
            raise DataError(f"the {self.label} term takes no edge weights")
        return EdgeGuidedTerm(np.asarray(weights, dtype=np.float64), self.band_factors)

    def difference(self, shape: tuple[int, int, int]) -> LinearOperator:
        """D on images of `shape` (rows, cols, channels), periodic boundary."""
        if self.band_factors is not None:
            return WeightedGradient(shape, band_factors=_factors(self.band_factors, shape[2]))
        if self.operator == "gradient":
            return Gradient(shape)
        if self.operator == "spectral_gradient":
            return SpectralGradient(shape)
        if self.operator == "spectral":
            return SpectralDifference(shape)
        return Laplacian(shape)

    def spatial_symbol(self, shape: tuple[int, int]) -> np.ndarray:
        """Real multiplier (rows, cols) of DᵀD per spatial frequency (the spectral part aside)."""
        if self.operator == "spectral":
            return np.ones(shape)
        # ∇ᵀ∇ and the Laplacian share one symbol; DᵀD of the Laplacian is its square
        laplacian = Laplacian((*shape, 1)).fourier_symbol()
        return laplacian**2 if self.operator == "laplacian" else laplacian

    def spectral_matrix(self, channels: int) -> np.ndarray:
        """The channel factor (channels × channels) of DᵀD: I (diag(f) with band factors),
        or D_λᵀD_λ for ∇λ∇xy."""
        if self.band_factors is not None:
            return np.diag(_factors(self.band_factors, channels))
        if self.operator not in ("spectral_gradient", "spectral"):
            return np.eye(channels)
        d = SpectralGradient((1, 1, channels)).spectral_matrix
        return d.T @ d

    def fourier_pieces(
        self, shape: tuple[int, int], channels: int
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        """DᵀD as (spatial symbol (rows, cols), channel matrix) pairs, for the FFT solver."""
        return [(self.spatial_symbol(shape), self.spectral_matrix(channels))]

    def quadratic(self) -> PriorTerm:
        """The same operator with p = 2 (an L1 or grouped term made quadratic)."""
        return self if self.norm == 2 else PriorTerm(self.operator, 2)

    def value(self, d_image: np.ndarray) -> float:
        """S(I) = ‖D I‖_p^p (or ‖D I‖₂,₁) from D I."""
        if self.grouped:
            return float(np.sum(np.sqrt(np.sum(d_image**2, axis=GROUP_AXES))))
        return float(np.sum(np.abs(d_image))) if self.norm == 1 else float(np.sum(d_image**2))


#: Axes of D I (rows, cols, channels, directions) a grouped term takes the 2-norm over.
GROUP_AXES = (2, 3)


@dataclass(frozen=True, eq=False)
class EdgeGuidedTerm:
    """``‖√w ⊙ ∇xy I‖₂²`` with the edge weights `weights` (rows, cols, 2) of one patch
    (:func:`~reconstruction.model.edge_weights.edge_weights`): the bound form of a guided
    :class:`PriorTerm`, with the same interface. Not circulant: its Fourier pieces, for the
    FFT solvers (a preconditioner here), are L2's times the mean weight.
    """

    weights: np.ndarray
    band_factors: tuple[float, ...] | None = None
    operator: str = "gradient"
    norm: Literal[2] = 2
    grouped: bool = False
    guided: bool = True

    @property
    def label(self) -> str:
        return "edge_gradient_L2"

    @property
    def mean_weight(self) -> float:
        return float(np.mean(self.weights))

    @property
    def constant(self) -> bool:
        """Whether every edge weight is the same (the term is then circulant)."""
        return bool(np.all(self.weights == self.weights.flat[0]))

    def __repr__(self) -> str:  # what FFT solvers' caches key on: the mean alone enters
        return (
            f"EdgeGuidedTerm(mean_weight={self.mean_weight!r}, band_factors={self.band_factors!r})"
        )

    def difference(self, shape: tuple[int, int, int]) -> WeightedGradient:
        factors = None if self.band_factors is None else _factors(self.band_factors, shape[2])
        return WeightedGradient(shape, self.weights, factors)

    def fourier_pieces(
        self, shape: tuple[int, int], channels: int
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        # the (band-balanced) L2 gradient term's, scaled by the mean weight
        plain = PriorTerm("gradient", 2, band_factors=self.band_factors)
        return [(self.mean_weight * s, m) for s, m in plain.fourier_pieces(shape, channels)]

    def quadratic(self) -> EdgeGuidedTerm:
        return self

    def value(self, d_image: np.ndarray) -> float:
        return float(np.sum(d_image**2))


@dataclass(frozen=True, eq=False)
class SmoothnessTerm:
    """``‖S I‖²`` with S the :class:`~reconstruction.model.operators.SpectralRoughness` of the
    colour matrix `colour` (channels × k): the spectral smoothness term of
    :mod:`reconstruction.model.problem` (beyond the thesis, no prior of Table 3.1). Same interface
    as :class:`PriorTerm`.
    """

    colour: np.ndarray
    operator: str = "spectral_roughness"
    norm: Literal[2] = 2
    grouped: bool = False

    @property
    def label(self) -> str:
        return "spectral_roughness_L2"

    def difference(self, shape: tuple[int, int, int]) -> SpectralRoughness:
        return SpectralRoughness(shape, self.colour)

    def fourier_pieces(
        self, shape: tuple[int, int], channels: int
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        return self.difference((*shape, channels)).fourier_pieces(shape)

    def quadratic(self) -> SmoothnessTerm:
        return self

    def value(self, d_image: np.ndarray) -> float:
        return float(np.sum(d_image**2))


def _factors(band_factors: tuple[float, ...], channels: int) -> np.ndarray:
    """Band factors as an array, checked against the image's channels."""
    if len(band_factors) != channels:
        raise DataError(
            f"{len(band_factors)} band factors do not fit an image of {channels} channels"
        )
    return np.asarray(band_factors, dtype=np.float64)


#: Any penalty a :class:`~reconstruction.model.problem.Problem` holds.
Term = PriorTerm | SmoothnessTerm | EdgeGuidedTerm

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
    "VTV": (PriorTerm("gradient", 1, grouped=True),),
    "EdgeL2": (PriorTerm("gradient", 2, guided=True),),
}


def prior_terms(name: str, *, channels: int | None = None) -> tuple[PriorTerm, ...]:
    """The terms of prior `name` (Table 3.1), checked against the number of channels.

    Raises
    ------
    DataError
        Unknown name, or a spectral-gradient term on an image with one channel.
    """
    if name not in PRIORS:
        raise DataError(f"unknown prior {name!r}; use one of {', '.join(PRIORS)}")
    terms = PRIORS[name]
    if (
        channels is not None
        and channels < 2
        and any(t.operator == "spectral_gradient" for t in terms)
    ):
        raise DataError(f"prior {name!r} has a spectral-gradient term and needs ≥ 2 channels")
    return terms
