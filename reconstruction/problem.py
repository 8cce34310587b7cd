"""One instance of problem (3.1) on a patch: data, forward model, prior terms and weights.

    I* = argmin_I ‖A I − y‖² + Σ_j w_j ‖D_j I‖_p^p + σ‖∇λ I‖² + ε‖I‖²,   I ≥ 0 (optional)

with A from :mod:`reconstruction.image_formation`. Values are *normalised*: the driver
divides the raw image by a global level and the colour matrices by their largest channel
sum (Algorithm 9's q_max), so latent values are O(1) and the weights w_j mean the same for
every image and camera. ε is a tiny ridge (:data:`RIDGE`, relative to the data term) that
picks the smallest of the metameric solutions the data and the spatial priors cannot tell
apart (e.g. the mean spectrum beyond the three colour channels); it changes the objective
by ≈ 1e-9 relative.

σ‖∇λ I‖² (beyond the thesis; off by default) makes the choice among metamers explicit:
the smoothest spectrum rather than the smallest. With the ridge alone the non-negative
optimum is a poor spectrum (the smallest non-negative metamer puts bands at zero), so an
ADMM solve stopped early from the smooth unconstrained start is a better image than the
optimum it approaches, and where the solver stops decides the spectrum. With σ the optimum
is the good image for scenes of smooth spectra, and ADMM reaches it in a few iterations.
The price is a bias against spectra that are not smooth (narrow-band light, bandpass
filters): the raw colour they need is then traded against the penalty.
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

SUGGESTED_SMOOTHNESS = 1e-3
"""σ (normalised units, like the weights) for scenes of smooth reflectances. Measured on the
simulated ColorChecker (344×408, 7 bands, L2, Φ, DMC weights), against σ = 0: spectral
RMSE 0.0951 → 0.0857, colour RMSE R/G/B .0117/.0228/.0238 → .0141/.0163/.0199, and the
exact optimum is within 0.4 % of ADMM's image (σ = 0: 0.175 against 0.095); on the
textured scene (saturated colours) spectral RMSE 0.255 → 0.258, MRAE 0.73 → 0.79; on a flat
synthetic raw colour that no smooth spectrum gives, the raw colour moves by up to 12 %
(1.5 % at σ = 1e-4, 0.15 % at 1e-5; smaller σ loses the gain: 1e-5 gives 0.1015)."""

SMOOTHNESS_TERM = PriorTerm("spectral", 2)
"""‖∇λ I‖²: the term σ weighs."""


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
    smoothness : float
        σ ≥ 0, the weight of ‖∇λ I‖² (0: none, as the thesis); needs ≥ 2 channels.
    penalties : list of (float, PriorTerm, LinearOperator)
        (weight, term, D) of every prior term and then, when σ > 0, of the smoothness term:
        what the solvers minimise besides the data term and the ridge.
    """

    formation: ImageFormation
    raw: np.ndarray
    terms: tuple[PriorTerm, ...]
    weights: tuple[float, ...]
    nonneg: bool = True
    ridge: float | None = None
    smoothness: float = 0.0
    differences: list[LinearOperator] = field(init=False, repr=False)
    penalties: list[tuple[float, PriorTerm, LinearOperator]] = field(init=False, repr=False)

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
        self.smoothness = float(self.smoothness)
        if not (np.isfinite(self.smoothness) and self.smoothness >= 0):
            raise DataError(f"spectral smoothness σ must be finite and ≥ 0, got {self.smoothness}")
        if self.smoothness > 0 and self.shape[2] < 2:
            raise DataError(
                "spectral smoothness needs ≥ 2 latent channels; give smoothness=0 for a "
                "single-channel latent image"
            )
        self.differences = [t.difference(self.shape) for t in self.terms]
        self.penalties = list(zip(self.weights, self.terms, self.differences, strict=True))
        if self.smoothness > 0:
            smoothing = SMOOTHNESS_TERM.difference(self.shape)
            self.penalties.append((self.smoothness, SMOOTHNESS_TERM, smoothing))

    @property
    def shape(self) -> tuple[int, int, int]:
        """Latent image shape (rows, cols, n)."""
        return self.formation.domain_shape

    def with_weights(self, weights: Sequence[float]) -> Problem:
        return Problem(
            self.formation,
            self.raw,
            self.terms,
            tuple(weights),
            self.nonneg,
            self.ridge,
            self.smoothness,
        )

    def data_misfit(self, latent: np.ndarray) -> float:
        """‖A I − y‖²."""
        return float(np.sum((self.formation.forward(latent) - self.raw) ** 2))

    def prior_values(self, latent: np.ndarray) -> list[float]:
        """S_j(I) = ‖D_j I‖_p^p for each prior term (unweighted; σ's term aside)."""
        return [
            t.value(d.forward(latent)) for t, d in zip(self.terms, self.differences, strict=True)
        ]

    def objective(self, latent: np.ndarray) -> float:
        """The full objective at `latent` (∞ if it violates non-negativity)."""
        if self.nonneg and np.any(latent < 0):
            return float("inf")
        priors = sum(w * t.value(d.forward(latent)) for w, t, d in self.penalties)
        return self.data_misfit(latent) + priors + self.ridge * float(np.sum(latent**2))
