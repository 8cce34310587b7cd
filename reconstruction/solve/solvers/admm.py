"""ADMM for problem (3.1) (thesis §3.7, Algorithms 5–9; Boyd et al. 2011).

:class:`ADMM` is the solver (``setup`` / ``step`` / ``run`` / ``finalize``) and
:func:`solve_admm` its functional form, one of the methods of
:func:`reconstruction.solve.solvers.solve`.

Splitting (scaled form, one penalty ρ_t per split as in the thesis):

* each L1 term ``w_j‖D_j I‖₁`` gets ``z_j = D_j I``, updated by soft-thresholding at
  ``w_j / ρ_j`` (Algorithm 5, line 8); a grouped term ``w_j‖D_j I‖₂,₁`` (``VTV``) by
  group soft-thresholding, which shrinks each pixel's vector over bands and directions;
* non-negativity gets ``z_0 = I``, updated by projection ``max(0, ·)`` (line 10);
* L2 terms stay in the quadratic step (Algorithm 6, line 4).

The quadratic step (:class:`~reconstruction.solve.solvers.quadratic.QuadraticStep`) solves
``(2AᵀA + Σ_{L2} 2w_j D_jᵀD_j + Σ_t ρ_t G_tᵀG_t + 2ε I) I = rhs``:
exactly by :class:`~reconstruction.solve.solvers.fourier.FourierSolver` without dispersion, and by
conjugate gradients warm-started at the previous iterate and preconditioned by the same
FFT solver (dispersion approximated by per-sample mean translations) with dispersion. Each
CG solve stops at ``cg_rtol`` or at :data:`CG_FORCING` times ADMM's latest residuals
(gradient units) and dual tolerance, whichever is tighter: a fixed CG tolerance left an
error in every I-update larger than the convergence test's thresholds near the end, so
the test measured CG's error, and when it fired depended on rounding.

Convergence is Algorithms 7–8 (primal and dual residual of every split against
``ε_abs √M + ε_rel ·`` the matching norm), with ε_abs from Algorithm 9
(``ε_rel · median(y) / q_max``; q_max = 1 after normalisation), and with spectral
smoothness an objective that has settled over the last iterations (:data:`STALL_WINDOW`).
Additions to the thesis, both from Boyd et al. §3.4: over-relaxation (α = 1.6) and
residual balancing (ρ_t is doubled or halved when one residual exceeds the other ten-fold;
each change costs a re-inversion of the FFT blocks, so at most :data:`MAX_PENALTY_UPDATES`
are made). A third addition: type-II Anderson acceleration of the (z, u) iteration (memory
:data:`ANDERSON_MEMORY`, safeguarded: :mod:`reconstruction.solve.solvers.anderson`), which cuts the
iterations to a tight tolerance
severalfold on textured patches at the small weights the DMC criterion picks.
Without splits (L2 priors, no constraint) the problem is one quadratic solve.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from labkit.blas_threads import fixed_blas_threads
from labkit.errors import DataError
from reconstruction.model.operators import LinearOperator
from reconstruction.model.prior_terms import GROUP_AXES
from reconstruction.model.problem import Problem
from reconstruction.solve.solvers.anderson import AndersonAcceleration
from reconstruction.solve.solvers.quadratic import QuadraticStep, initial_estimate
from reconstruction.solve.solvers.report import Solution, SolveReport, check_start, finished

DEFAULT_RTOL = 1e-4
"""ε_rel of the thesis' problem (σ = 0). Its non-negative optimum is degenerate (the
smallest non-negative metamer, a poorer spectrum than ADMM's early stop) and ADMM
approaches it slowly, so this solve promises no distance to it: every extra iteration moves
the image towards that poorer spectrum (the ``exact`` method reaches the optimum; figures
in the docs/notes/solver.md, spectral smoothness)."""

SMOOTH_RTOL = 1e-5
"""ε_rel with spectral smoothness (σ > 0, the default of
:func:`~reconstruction.reconstruct.reconstruct`): the optimum is then well defined, and
the default solve (with :data:`STALL_WINDOW`) comes within 1e-4 of it (relative objective;
measured by ``labkit bench solver`` and docs/notes/solver.md)."""


def default_rtol(smoothness: float = 0.0) -> float:
    """ε_rel of the default solve: :data:`SMOOTH_RTOL` with spectral smoothness σ > 0,
    else :data:`DEFAULT_RTOL`."""
    return SMOOTH_RTOL if smoothness > 0 else DEFAULT_RTOL


MAX_PENALTY_UPDATES = 8
OVER_RELAXATION = 1.6
ANDERSON_MEMORY = 5
"""Anderson acceleration memory of the ADMM iteration (0: plain ADMM)."""
CG_FORCING = 0.1
"""Each CG solve's residual is at most this times the larger of ADMM's last residuals
(Σ_t ρ_t‖r_t‖ + ‖s_t‖, gradient units) and the smallest dual tolerance: an I-update less
exact than the test that judges it makes that test measure CG's error."""
STALL_WINDOW = 5
"""With spectral smoothness (σ > 0) the residual test must also find the objective settled:
from the first iteration that passes it on, the objective is recorded, and ADMM stops when
the test passes and the last (up to) this many values lie within :data:`STALL_FACTOR` ·
ε_rel of the newest. Small residuals alone let the iterate stop while still drifting along
a flat valley of the objective (docs/notes/solver.md, reproducible solves). Not at
σ = 0, whose early stop is kept on purpose (:data:`DEFAULT_RTOL`), nor in solves with
``settle=False``."""
STALL_FACTOR = 0.5
_BALANCE, _FACTOR = 10.0, 2.0


class _Identity(LinearOperator):
    name = "I"

    def __init__(self, shape: tuple[int, ...]) -> None:
        super().__init__(shape, shape)

    def _forward(self, x: np.ndarray) -> np.ndarray:
        return x

    def _adjoint(self, y: np.ndarray) -> np.ndarray:
        return y


@dataclass(eq=False)
class _Split:
    name: str
    operator: LinearOperator
    threshold_weight: float | None  # w_j of an L1 term; None: projection onto I ≥ 0
    term_index: int | None
    rho: float
    z: np.ndarray
    u: np.ndarray
    z_next: np.ndarray = field(default_factory=lambda: np.empty(0))  # this iteration's
    u_next: np.ndarray = field(default_factory=lambda: np.empty(0))
    grouped: bool = False

    def prox(self, v: np.ndarray) -> np.ndarray:
        if self.threshold_weight is None:
            return np.maximum(v, 0.0)
        t = self.threshold_weight / self.rho
        if self.grouped:
            norm = np.sqrt(np.sum(v * v, axis=GROUP_AXES, keepdims=True))
            return v * np.maximum(1.0 - t / np.maximum(norm, np.finfo(np.float64).tiny), 0.0)
        return np.sign(v) * np.maximum(np.abs(v) - t, 0.0)


def absolute_tolerance(raw: np.ndarray, rtol: float, q_max: float = 1.0) -> float:
    """ε_abs of Algorithm 9: ``rtol · median(raw) / q_max`` (a floor of 1e-12 · rtol)."""
    return float(rtol * max(float(np.median(raw)), 1e-12) / q_max)


class ADMM:
    """ADMM on `problem`: :meth:`setup` from a start, :meth:`step` one iteration at a
    time or :meth:`run` to convergence, :meth:`finalize` into a :class:`Solution`. Each
    runs its BLAS work at labkit's fixed thread count (:mod:`labkit.blas_threads`).

    Parameters
    ----------
    problem : Problem
    rtol : float, optional
        ε_rel of the convergence test (thesis: 1e-3); default :func:`default_rtol`, with
        σ > 0 tight enough that the objective comes within 1e-4 of the optimum.
    atol : float, optional
        ε_abs; default Algorithm 9 on the patch (the driver passes the whole image's).
    max_iter : int
        Iteration limit k_max of :meth:`run`.
    cg_rtol, cg_max_iter : float, int
        Loosest tolerance (relative to the right-hand side) and iteration limit of each
        conjugate-gradient solve (with dispersion); near convergence the tolerance follows
        ADMM's residuals down (:data:`CG_FORCING`).
    penalty : float, optional
        Initial ρ for every split; default the data term's mean curvature.
    track_objective : bool
        Record the objective after each iteration in ``report.history`` (costly).
    settle : bool
        With spectral smoothness (σ > 0), stop only once the objective has also settled
        (:data:`STALL_WINDOW`). Off for solves that promise no optimum, such as weight
        selection's at the thesis' loose tolerance.
    """

    def __init__(
        self,
        problem: Problem,
        *,
        rtol: float | None = None,
        atol: float | None = None,
        max_iter: int = 1000,
        cg_rtol: float = 1e-5,
        cg_max_iter: int = 100,
        penalty: float | None = None,
        track_objective: bool = False,
        settle: bool = True,
    ) -> None:
        self.problem = problem
        self.rtol = default_rtol(problem.smoothness) if rtol is None else float(rtol)
        if not (0 < self.rtol < 1):
            raise DataError(f"rtol must be in (0, 1), got {self.rtol}")
        self.atol = absolute_tolerance(problem.raw, self.rtol) if atol is None else float(atol)
        self.max_iter = max_iter
        self.cg_rtol, self.cg_max_iter = cg_rtol, cg_max_iter
        self.penalty = penalty
        self.track_objective = track_objective
        self.stall_window = STALL_WINDOW if settle and problem.smoothness > 0 else 0
        self.report = SolveReport()

    @fixed_blas_threads
    def setup(self, x0: np.ndarray | None = None) -> None:
        """Start from `x0` (splits at ``z = G x0``); default :func:`initial_estimate` when
        anything is split (the thesis starts from zeros: pass ``np.zeros(shape)`` for that),
        zeros for a single quadratic solve (CG's start with Φ)."""
        problem = self.problem
        check_start(problem, x0)
        if x0 is not None:
            x = np.array(x0, dtype=np.float64)
        elif problem.nonneg or problem.has_l1_penalty:
            x = initial_estimate(problem)
        else:
            x = np.zeros(problem.shape)
        # on textured patches ADMM reaches the optimum in far fewer iterations with ρ near
        # the data curvature than with ρ ten times larger (figures in docs/notes/solver.md)
        rho0 = float(self.penalty) if self.penalty is not None else problem.data_curvature
        splits: list[_Split] = []
        for j, (weight, term, difference) in enumerate(problem.penalties):
            if term.norm == 1 and weight > 0:
                gx = difference.forward(x)
                splits.append(
                    _Split(
                        term.label,
                        difference,
                        weight,
                        j,
                        rho0,
                        gx,
                        np.zeros_like(gx),
                        grouped=term.grouped,
                    )
                )
        if problem.nonneg:
            splits.append(
                _Split(
                    "nonneg",
                    _Identity(problem.shape),
                    None,
                    None,
                    rho0,
                    np.maximum(x, 0),
                    np.zeros(problem.shape),
                )
            )
        self.x = x
        self.splits = splits
        self.report.splits = [s.name for s in splits]
        self.quadratic = QuadraticStep(problem, splits, self.cg_rtol, self.cg_max_iter)
        self.data_rhs = 2.0 * problem.formation.adjoint(problem.raw)
        self.iteration = 0
        self._sqrt_m = np.sqrt(x.size)
        self._recent: list[float] = []
        self._cg_atol = np.inf
        self._updates = 0
        self._anderson = AndersonAcceleration(ANDERSON_MEMORY)
        self._projected = splits[-1].z if problem.nonneg else x  # x ≥ 0: the last split's z

    @fixed_blas_threads
    def step(self) -> bool:
        """One iteration: the I-update, the splits' updates and the convergence test
        (Algorithms 5–8); when not converged, the next (z, u) (Anderson-extrapolated) and
        the penalties rebalanced. Returns whether the test passed."""
        problem, splits, report = self.problem, self.splits, self.report
        self.iteration += 1
        rhs = self.data_rhs.copy()
        for s in splits:
            rhs += s.rho * s.operator.adjoint(s.z - s.u)
        x = self.x = self.quadratic.solve(rhs, self.x, self._cg_atol)
        converged = True
        gradient_scale, dual_floor = 0.0, np.inf
        primal, dual = [], []
        for s in splits:
            gx = s.operator.forward(x)
            relaxed = OVER_RELAXATION * gx + (1.0 - OVER_RELAXATION) * s.z
            z_old = s.z
            s.z_next = s.prox(relaxed + s.u)
            s.u_next = s.u + relaxed - s.z_next
            r = float(np.linalg.norm(gx - s.z_next))
            d = float(s.rho * np.linalg.norm(s.operator.adjoint(s.z_next - z_old)))
            eps_pri = self.atol * self._sqrt_m + self.rtol * max(
                float(np.linalg.norm(gx)), float(np.linalg.norm(s.z_next))
            )
            eps_dual = self.atol * self._sqrt_m + self.rtol * float(
                s.rho * np.linalg.norm(s.operator.adjoint(s.u_next))
            )
            converged &= r < eps_pri and d < eps_dual
            gradient_scale += d + s.rho * r
            dual_floor = min(dual_floor, eps_dual)
            primal.append(r)
            dual.append(d)
        self._cg_atol = CG_FORCING * max(dual_floor, gradient_scale)
        if problem.nonneg:
            self._projected = splits[-1].z_next
        recent = self._recent
        settling = bool(self.stall_window) and (converged or bool(recent))
        if self.track_objective or settling:
            objective = problem.objective(self._projected if problem.nonneg else x)
            if self.track_objective:
                report.history.append(objective)
        report.iterations = self.iteration
        report.primal_residuals, report.dual_residuals = primal, dual
        if settling:
            recent.append(objective)
            window = recent[-self.stall_window :]
            converged = converged and (
                len(window) >= 2
                and max(window) - min(window) <= STALL_FACTOR * self.rtol * abs(window[-1])
            )
        if converged:
            report.converged = True
            return True
        self._next_state()
        self._balance_penalties(primal, dual)
        return False

    def _next_state(self) -> None:
        """The next (z, u): ADMM's own step, extrapolated by Anderson acceleration."""
        splits = self.splits
        state = np.concatenate([v.ravel() for s in splits for v in (s.z, s.u)])
        mapped = np.concatenate([v.ravel() for s in splits for v in (s.z_next, s.u_next)])
        vector = self._anderson.step(state, mapped)
        self.report.accelerated += self._anderson.accepted
        at = 0
        for s in splits:
            size = s.z.size
            s.z = vector[at : at + size].reshape(s.z.shape)
            s.u = vector[at + size : at + 2 * size].reshape(s.u.shape)
            at += 2 * size

    def _balance_penalties(self, primal: list[float], dual: list[float]) -> None:
        """Residual balancing (Boyd et al. §3.4.1), at most :data:`MAX_PENALTY_UPDATES` times."""
        if self._updates >= MAX_PENALTY_UPDATES:
            return
        changed = False
        for s, rp, rd in zip(self.splits, primal, dual, strict=True):
            if rp > _BALANCE * rd:
                s.rho *= _FACTOR
                s.u /= _FACTOR
                changed = True
            elif rd > _BALANCE * rp:
                s.rho /= _FACTOR
                s.u *= _FACTOR
                changed = True
        if changed:
            self._updates += 1
            self._anderson.reset()
            self.quadratic.refresh()

    @fixed_blas_threads
    def run(self) -> np.ndarray:
        """Iterate (on from any :meth:`step` already taken) until the test passes or
        `max_iter`; the image reached (≥ 0 for a non-negative problem). Without splits, one
        quadratic solve."""
        if not self.splits:
            self.x = self.quadratic.solve(self.data_rhs, self.x)
            self.report.iterations, self.report.converged = 1, True
            return self.x
        while not self.report.converged and self.iteration < self.max_iter:
            self.step()
        self.report.penalties = [s.rho for s in self.splits]
        return self._projected.copy() if self.problem.nonneg else self.x

    @fixed_blas_threads
    def finalize(self, latent: np.ndarray) -> Solution:
        """The solution at `latent` (what :meth:`run` returned, or a finish of it)."""
        return finished(
            self.problem,
            latent,
            self.report,
            cg_iterations=self.quadratic.cg_iterations,
            cg_residual=self.quadratic.cg_residual,
        )


@fixed_blas_threads
def solve_admm(problem: Problem, *, x0: np.ndarray | None = None, **options: Any) -> Solution:
    """Minimise `problem` by ADMM (or one quadratic solve when nothing needs splitting).

    The options are :class:`ADMM`'s; `x0` is the start (:meth:`ADMM.setup`).
    """
    admm = ADMM(problem, **options)
    admm.setup(x0)
    return admm.finalize(admm.run())
