"""The quadratic step shared by every solver of problem (3.1), and the start it gives.

The quadratic part of the objective has the Hessian K = 2AᵀA + Σ_{L2} 2w_j D_jᵀD_j + 2εI.
ADMM adds its penalties ρ_t G_tᵀG_t to it in each I-update; the exact methods solve with
K itself. Without Φ the matrix is block-circulant and one FFT solve
(:class:`~reconstruction.solve.solvers.fourier.FourierSolver`) inverts it exactly; with Φ it is
solved by conjugate gradients, preconditioned by the FFT solver of Φ's mean translations.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Protocol

import numpy as np

from labkit.blas_threads import fixed_blas_threads
from labkit.errors import DataError
from reconstruction.model.problem import Problem
from reconstruction.solve.solvers.cg import conjugate_gradient
from reconstruction.solve.solvers.fourier import FourierSolver

SINGLE_PRECISION_IDENTITY = 1e-4
"""The CG preconditioner runs in single precision when the quadratic step's identity
coefficient is at least this times the data term's mean curvature
(:attr:`~reconstruction.model.problem.Problem.data_curvature`)."""
CG_RTOL_FLOOR = 1e-13
"""Tightest relative CG tolerance asked for (below it, float64 rounding of K x)."""


class Penalised(Protocol):
    """A split of ADMM as the quadratic step sees it: its penalty ρ and the prior term
    it splits (None: the identity, non-negativity's split)."""

    rho: float
    term_index: int | None


class QuadraticStep:
    """Solver of ``(K + Σ_t ρ_t G_tᵀG_t) x = rhs`` for the current penalties of `splits`.

    Parameters
    ----------
    problem : Problem
    splits : list
        ADMM's splits (their ρ and prior term); empty for K itself.
    cg_rtol, cg_max_iter : float, int
        Loosest tolerance (relative to the right-hand side) and iteration limit of each
        CG solve (with Φ).
    """

    def __init__(
        self,
        problem: Problem,
        splits: Sequence[Penalised],
        cg_rtol: float,
        cg_max_iter: int,
    ) -> None:
        self.problem = problem
        self.splits = splits
        self.cg_rtol, self.cg_max_iter = cg_rtol, cg_max_iter
        self.formation = problem.formation
        self.exact = self.formation.dispersion is None and problem.circulant
        self._curvature = problem.data_curvature
        self.cg_iterations: list[int] = []
        self.cg_residual = 0.0
        self._last: tuple[np.ndarray, np.ndarray] | None = None  # (x, K x) of the last CG solve
        self._build()

    def _coefficients(self) -> tuple[list[tuple[float, int]], float]:
        """(coefficient, term index) of every DᵀD in the matrix, and the identity's coefficient."""
        p = self.problem
        terms = [(2.0 * w, j) for j, (w, t, _) in enumerate(p.penalties) if t.norm == 2 and w > 0]
        identity = 2.0 * ridge(p)
        for s in self.splits:
            if s.term_index is None:
                identity += s.rho
            else:
                terms.append((s.rho, s.term_index))
        return terms, identity

    def _build(self) -> None:
        self.terms, self.identity = self._coefficients()
        self.solver = FourierSolver(
            self.formation.range_shape,
            self.formation.cfa,
            self.formation.fourier_colour(),
            terms=[(c, self.problem.penalties[j][1]) for c, j in self.terms],
            identity=self.identity,
        )

    def refresh(self) -> None:
        """Re-invert after a penalty change."""
        self._last = None  # K changed
        terms, identity = self._coefficients()
        if terms != self.terms:
            self._build()
        else:
            self.solver.set_identity(identity)
            self.identity = identity

    def apply(self, x: np.ndarray) -> np.ndarray:
        """The quadratic step's matrix times x, with the true A (and Φ)."""
        a = self.formation
        out = 2.0 * a.adjoint(a.forward(x)) + self.identity * x
        for coefficient, j in self.terms:
            d = self.problem.penalties[j][2]
            out += coefficient * d.adjoint(d.forward(x))
        return out

    def _precondition(self, r: np.ndarray) -> np.ndarray:
        # float32 blocks carry a relative error ≈ 6e-8 × their condition number: fine once
        # ADMM's penalty is in the identity, useless with the ridge alone (cond ≈ 1e10)
        if self.identity >= SINGLE_PRECISION_IDENTITY * self._curvature:
            return self.solver.solve_single(r)
        return self.solver.solve(r, refine=False)

    def solve(self, rhs: np.ndarray, x0: np.ndarray, atol: float = np.inf) -> np.ndarray:
        """The I-update: exact without Φ; with Φ, CG to ‖rhs − K x‖ ≤ min(cg_rtol ‖rhs‖, atol)."""
        if self.exact:
            return self.solver.solve(rhs)
        rhs_norm = float(np.linalg.norm(rhs))
        rtol = self.cg_rtol
        if rhs_norm > 0:
            rtol = max(min(rtol, atol / rhs_norm), CG_RTOL_FLOOR)
        # ADMM starts each solve from the last one's x, whose K x CG has kept up to date
        last = self._last
        known = last[1] if last is not None and x0 is last[0] else None
        result = conjugate_gradient(
            self.apply,
            rhs,
            x0=x0,
            preconditioner=self._precondition,
            rtol=rtol,
            max_iter=self.cg_max_iter,
            product0=known,
            track_product=True,
        )
        self._last = None if result.product is None else (result.x, result.product)
        self.cg_iterations.append(result.iterations)
        self.cg_residual = max(self.cg_residual, result.relative_residual)
        return result.x


def quadratic_system(problem: Problem) -> tuple[Callable[[np.ndarray], np.ndarray], FourierSolver]:
    """K, the Hessian of the problem's quadratic part (2AᵀA + Σ 2w_j D_jᵀD_j over the L2
    terms + 2εI), as ``x ↦ K x`` with the true A (and Φ), and its FFT solver: K itself
    without Φ, the mean-translation approximation with (the active-set finish's inputs)."""
    step = QuadraticStep(problem, [], 1e-5, 100)
    return step.apply, step.solver


def ridge(problem: Problem) -> float:
    """ε of `problem` (set when the Problem is built)."""
    if problem.ridge is None:
        raise DataError("the problem has no ridge ε; build it with Problem(…), which sets one")
    return problem.ridge


@fixed_blas_threads
def initial_estimate(problem: Problem, *, solver: FourierSolver | None = None) -> np.ndarray:
    """A start for the solvers: one FFT solve with Φ as mean translations, priors made
    quadratic.

    ``(2ÃᵀÃ + Σ_j 2w_j D_jᵀD_j + 2εI) x = 2Ãᵀy`` where Ã is A with each Φ sample replaced
    by its mean translation over the patch (A itself without Φ), in the matrix and the
    right-hand side alike: were they to disagree, the directions only the ridge ε holds
    would amplify the mismatch. Clipped at zero for a non-negative problem. ADMM
    starts here unless given x0 (the thesis starts from zeros), which saves iterations of
    ADMM and of each CG solve (docs/notes/solver.md).

    `solver` is an FFT solver of that matrix to use instead of building one: for L2-type
    priors, the split-free quadratic step's (:func:`quadratic_system`).
    """
    formation = problem.formation
    if solver is None:
        quadratic = [(2.0 * w, t.quadratic()) for w, t, _ in problem.penalties if w > 0]
        solver = FourierSolver(
            formation.range_shape,
            formation.cfa,
            formation.fourier_colour(),
            terms=quadratic,
            identity=2.0 * ridge(problem),
        )
    x = solver.solve(2.0 * formation.translation_adjoint(problem.raw))
    return np.maximum(x, 0.0) if problem.nonneg else x
