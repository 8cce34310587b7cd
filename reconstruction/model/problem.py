"""One instance of problem (3.1) on a patch: data, forward model, prior terms and weights.

    I* = argmin_I ‖A I − y‖² + Σ_j w_j ‖D_j I‖_p^p + σ‖S I‖² + ε‖I‖²,   I ≥ 0 (optional)

with A from :mod:`reconstruction.model.image_formation`. Values are *normalised*: the driver
divides the raw image by a global level and the colour matrices by their largest channel
sum (Algorithm 9's q_max), so latent values are O(1) and the weights w_j mean the same for
every image and camera. ε is a tiny ridge (:data:`RIDGE`, relative to the data term) that
picks the smallest of the metameric solutions the data and the spatial priors cannot tell
apart (e.g. the mean spectrum beyond the three colour channels); it changes the objective
by ≈ 1e-9 relative.

σ‖S I‖² (beyond the thesis; :class:`~reconstruction.model.operators.SpectralRoughness`) makes
the choice among metamers explicit: the smoothest spectrum rather than the smallest. S is
the spectral difference ∇λ at every spatial frequency but the patch's mean, where only the
part of the mean spectrum its colour does not fix is smoothed, so the term never trades a
patch's mean colour against smoothness (non-negativity still can, see below). With the
ridge alone (σ = 0, the thesis' problem) the non-negative optimum is a poor spectrum (the
smallest non-negative metamer puts bands at zero), so an ADMM solve stopped early from the
smooth unconstrained start is a better image than the optimum it approaches, and where the
solver stops decides the spectrum.
With σ the optimum is the good image for scenes of smooth spectra, and the default solve
reaches it. The price is a bias against spectra that are not smooth (narrow-band light):
where the image varies, and, with non-negativity, in flat patches too (the only
non-negative spectra of such a colour are rough), the raw colour they need is traded
against the penalty. Narrow-band light needs σ = 0.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from labkit.errors import DataError
from reconstruction.model.edge_weights import edge_weights
from reconstruction.model.image_formation import ImageFormation
from reconstruction.model.operators import LinearOperator
from reconstruction.model.prior_terms import EdgeGuidedTerm, PriorTerm, SmoothnessTerm, Term

RIDGE = 1e-9
"""ε of the ridge term, relative to the largest eigenvalue of a pixel's CᵀC."""

NEGLIGIBLE_GUIDANCE = 1e-6
"""An edge-guided term whose weight times its edge weights' spread (times ‖∇ᵀ∇‖ = 8) is at
most this fraction of the data curvature takes its mean edge weight everywhere: its
matrix then differs from the circulant one by less than the solvers' tolerances, and the
exact FFT solvers apply (the tiny weights a weight search tries)."""

SUGGESTED_SMOOTHNESS = 1e-3
"""σ (normalised units, like the weights): the default of
:func:`~reconstruction.reconstruct.reconstruct` for spectral latent images. Against σ = 0
it lowers the simulated ColorChecker's spectral error, its green and blue colour errors and
its green edge error, and costs the textured scene (saturated colours) little. Under
narrow-band light the raw colour is biased: the ColorChecker lit through the rig's 10 nm
filters gets mostly larger raw-colour errors, and a flat patch lit by a single band moves
with non-negativity (more so with σ‖∇λ I‖² at every frequency), exactly kept without.
Figures, with σ = 3e-4 and 3e-3 for comparison, in docs/notes/solver.md (spectral smoothness)."""


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
        σ ≥ 0, the weight of the spectral roughness ‖S I‖² (:class:`SmoothnessTerm`; 0:
        none, as the thesis); needs ≥ 2 channels.
    edge_weights : ndarray (rows, cols, 2), optional
        The weights of an edge-guided term (``EdgeL2``); default
        :func:`~reconstruction.model.edge_weights.edge_weights` of `raw` (normalised units).
        None without such a term.
    penalties : list of (float, PriorTerm or SmoothnessTerm, LinearOperator)
        (weight, term, D) of every prior term (a guided one bound to `edge_weights`) and
        then, when σ > 0, of the smoothness term: what the solvers minimise besides the
        data term and the ridge.
    """

    formation: ImageFormation
    raw: np.ndarray
    terms: tuple[PriorTerm, ...]
    weights: tuple[float, ...]
    nonneg: bool = True
    ridge: float | None = None
    smoothness: float = 0.0
    edge_weights: np.ndarray | None = None
    differences: list[LinearOperator] = field(init=False, repr=False)
    penalties: list[tuple[float, Term, LinearOperator]] = field(init=False, repr=False)

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
        bound = self._bind_edge_weights()
        self.differences = [t.difference(self.shape) for t in bound]
        self.penalties = list(zip(self.weights, bound, self.differences, strict=True))
        if self.smoothness > 0:
            smoothing = SmoothnessTerm(self.formation.colour_matrix)
            self.penalties.append((self.smoothness, smoothing, smoothing.difference(self.shape)))

    def _bind_edge_weights(self) -> list[Term]:
        """The terms, each guided one bound to the edge weights (computed if not given)."""
        if not any(t.guided for t in self.terms):
            if self.edge_weights is not None:
                raise DataError("edge_weights were given, but no prior term is edge-guided")
            return list(self.terms)
        rows, cols = self.raw.shape
        if self.edge_weights is None:
            self.edge_weights = edge_weights(self.raw, cfa=self.formation.cfa)
        self.edge_weights = np.asarray(self.edge_weights, dtype=np.float64)
        if self.edge_weights.shape != (rows, cols, 2):
            raise DataError(
                f"edge_weights have shape {self.edge_weights.shape}; the patch needs "
                f"{(rows, cols, 2)}"
            )
        bound = []
        for weight, term in zip(self.weights, self.terms, strict=True):
            if not term.guided:
                bound.append(term)
                continue
            edges = self.edge_weights
            # ‖∇ᵀ∇‖ = 8: how far the term's matrix is from its mean-weight circulant one
            if weight * 8.0 * float(np.ptp(edges)) <= NEGLIGIBLE_GUIDANCE * self.data_curvature:
                edges = np.full_like(edges, float(np.mean(edges)))
            bound.append(term.bind(edges))
        return bound

    @property
    def circulant(self) -> bool:
        """Whether every penalty is periodic-shift invariant (edge-guided terms only with
        constant weights): then, without Φ, the FFT solver is exact."""
        return not any(
            isinstance(t, EdgeGuidedTerm) and not t.constant for _, t, _ in self.penalties
        )

    @property
    def data_curvature(self) -> float:
        """Mean diagonal of 2AᵀA per latent value (dispersion aside): ADMM's default ρ.

        With the colour matrix C and the Bayer channel fractions f = (¼, ½, ¼) this is
        ``2 Σ_c f_c ‖C_c‖² / n``.
        """
        c = self.formation.colour_matrix
        fractions = np.array([0.25, 0.5, 0.25])
        return float(2.0 * np.sum(fractions * np.sum(c * c, axis=1)) / c.shape[1])

    @property
    def shape(self) -> tuple[int, int, int]:
        """Latent image shape (rows, cols, n)."""
        return self.formation.domain_shape

    @property
    def has_l1_penalty(self) -> bool:
        """Whether some L1-type term has a positive weight (ADMM splits it off)."""
        return any(t.norm == 1 and w > 0 for w, t, _ in self.penalties)

    def with_weights(self, weights: Sequence[float]) -> Problem:
        return Problem(
            self.formation,
            self.raw,
            self.terms,
            tuple(weights),
            self.nonneg,
            self.ridge,
            self.smoothness,
            self.edge_weights,
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
