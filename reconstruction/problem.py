"""One instance of problem (3.1) on a patch: data, forward model, prior terms and weights.

    I* = argmin_I ‖A I − y‖² + Σ_j w_j ‖D_j I‖_p^p + ε‖I‖²,   I ≥ 0 (optional)

with A from :mod:`reconstruction.image_formation`. Values are *normalised*: the driver
divides the raw image by a global level and the colour matrices by their largest channel
sum (Algorithm 9's q_max), so latent values are O(1) and the weights w_j mean the same for
every image and camera. ε is a tiny ridge (:data:`RIDGE`, relative to the data term) that
picks the smallest of the metameric solutions the data and the spatial priors cannot tell
apart (e.g. the mean spectrum beyond the three colour channels); it changes the objective
by ≈ 1e-9 relative.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from labkit.errors import DataError
from reconstruction.image_formation import ImageFormation
from reconstruction.operators import LinearOperator
from reconstruction.prior_terms import PriorTerm

RIDGE = 1e-9
"""ε of the ridge term, relative to the largest eigenvalue of a pixel's CᵀC."""


@dataclass(eq=False)
class Problem:
    """Problem (3.1) on one patch.

    Attributes
    ----------
    formation : ImageFormation
        A (normalised colour matrices).
    raw : ndarray (rows, cols)
        Normalised raw patch y.
    terms : tuple of PriorTerm
    weights : tuple of float
        w_j ≥ 0, one per term.
    nonneg : bool
        Constrain I ≥ 0.
    ridge : float
        ε (absolute, set from :data:`RIDGE` unless given).
    """

    formation: ImageFormation
    raw: np.ndarray
    terms: tuple[PriorTerm, ...]
    weights: tuple[float, ...]
    nonneg: bool = True
    ridge: float | None = None
    differences: list[LinearOperator] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.raw = np.asarray(self.raw, dtype=np.float64)
        if self.raw.shape != self.formation.range_shape:
            raise DataError(
                f"raw patch {self.raw.shape} does not match the forward model "
                f"{self.formation.range_shape}"
            )
        self.terms = tuple(self.terms)
        self.weights = tuple(float(w) for w in self.weights)
        if len(self.weights) != len(self.terms):
            raise DataError(
                f"{len(self.terms)} prior terms need {len(self.terms)} weights, got "
                f"{len(self.weights)}"
            )
        if any(not np.isfinite(w) or w < 0 for w in self.weights):
            raise DataError(f"weights must be finite and ≥ 0, got {self.weights}")
        if self.ridge is None:
            c = self.formation.colour_matrix
            self.ridge = RIDGE * float(np.linalg.eigvalsh(c.T @ c).max())
        self.differences = [t.difference(self.shape) for t in self.terms]

    @property
    def shape(self) -> tuple[int, int, int]:
        """Latent image shape (rows, cols, n)."""
        return self.formation.domain_shape

    def with_weights(self, weights: Sequence[float]) -> Problem:
        return Problem(
            self.formation, self.raw, self.terms, tuple(weights), self.nonneg, self.ridge
        )

    def data_misfit(self, latent: np.ndarray) -> float:
        """‖A I − y‖²."""
        return float(np.sum((self.formation.forward(latent) - self.raw) ** 2))

    def prior_values(self, latent: np.ndarray) -> list[float]:
        """S_j(I) = ‖D_j I‖_p^p for each term (unweighted)."""
        return [
            t.value(d.forward(latent)) for t, d in zip(self.terms, self.differences, strict=True)
        ]

    def objective(self, latent: np.ndarray) -> float:
        """The full objective at `latent` (∞ if it violates non-negativity)."""
        if self.nonneg and np.any(latent < 0):
            return float("inf")
        priors = self.prior_values(latent)
        return (
            self.data_misfit(latent)
            + sum(w * s for w, s in zip(self.weights, priors, strict=True))
            + self.ridge * float(np.sum(latent**2))
        )
