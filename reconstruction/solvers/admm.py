"""ADMM for problem (3.1) (thesis §3.7, Algorithms 5–9; Boyd et al. 2011).

Splitting (scaled form, one penalty ρ_t per split as in the thesis):

* each L1 term ``w_j‖D_j I‖₁`` gets ``z_j = D_j I``, updated by soft-thresholding at
  ``w_j / ρ_j`` (Algorithm 5, line 8); a grouped term ``w_j‖D_j I‖₂,₁`` (``VTV``) by
  group soft-thresholding, which shrinks each pixel's vector over bands and directions;
* non-negativity gets ``z_0 = I``, updated by projection ``max(0, ·)`` (line 10);
* L2 terms stay in the quadratic step (Algorithm 6, line 4).

The quadratic step solves ``(2AᵀA + Σ_{L2} 2w_j D_jᵀD_j + Σ_t ρ_t G_tᵀG_t + 2ε I) I = rhs``:
exactly by :class:`~reconstruction.solvers.fourier.FourierSolver` without dispersion, and by
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
:data:`ANDERSON_MEMORY`, safeguarded: :mod:`reconstruction.solvers.anderson`), which cuts the
iterations to a tight tolerance
severalfold on textured patches at the small weights the DMC criterion picks.
Without splits (L2 priors, no constraint) the problem is one quadratic solve.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from labkit.blas_threads import fixed_blas_threads
from labkit.errors import DataError
from reconstruction.operators import LinearOperator
from reconstruction.prior_terms import GROUP_AXES
from reconstruction.problem import Problem
from reconstruction.solvers.active_set import KKT_TOLERANCE, PolishReport, polish, solve_periodic
from reconstruction.solvers.anderson import AndersonAcceleration
from reconstruction.solvers.cg import conjugate_gradient
from reconstruction.solvers.fourier import FourierSolver

DEFAULT_RTOL = 1e-4
"""ε_rel of the thesis' problem (σ = 0). Its non-negative optimum is degenerate (the
smallest non-negative metamer, a poorer spectrum than ADMM's early stop) and ADMM
approaches it slowly, so this solve promises no distance to it: every extra iteration moves
the image towards that poorer spectrum (``exact_nonneg`` reaches the optimum; figures in
the docs/notes/solver.md, spectral smoothness)."""

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
SINGLE_PRECISION_IDENTITY = 1e-4
"""The CG preconditioner runs in single precision when the quadratic step's identity
coefficient is at least this times the data term's mean curvature
(:attr:`~reconstruction.problem.Problem.data_curvature`)."""
CG_FORCING = 0.1
"""Each CG solve's residual is at most this times the larger of ADMM's last residuals
(Σ_t ρ_t‖r_t‖ + ‖s_t‖, gradient units) and the smallest dual tolerance: an I-update less
exact than the test that judges it makes that test measure CG's error."""
CG_RTOL_FLOOR = 1e-13
"""Tightest relative CG tolerance asked for (below it, float64 rounding of K x)."""
STALL_WINDOW = 5
"""With spectral smoothness (σ > 0) the residual test must also find the objective settled:
from the first iteration that passes it on, the objective is recorded, and ADMM stops when
the test passes and the last (up to) this many values lie within :data:`STALL_FACTOR` ·
ε_rel of the newest. Small residuals alone let the iterate stop while still drifting along
a flat valley of the objective (docs/notes/solver.md, reproducible solves). Not at
σ = 0, whose early stop is kept on purpose (:data:`DEFAULT_RTOL`), nor in solves with
``settle=False``."""
STALL_FACTOR = 0.5
DIRECT_MAX_ZEROS = 600
"""Largest number of values at or below zero in the unconstrained optimum for which a
direct exact solve without Φ (``direct``) skips ADMM: the dual active-set method
factorises a dense block over its working set, which costs more than ADMM once it numbers
in the thousands. No limit for ``exact_nonneg`` without Φ (an edge-guided prior's weight
search, whose ADMM steps need CG): ADMM there costs more than the rounds, as for
:func:`~reconstruction.solvers.active_set.solve_periodic`. None with Φ either: projected
Newton there masks the values held at zero in its preconditioner (and corrects for at most
:data:`~reconstruction.solvers.active_set.MAX_PINNED` of them without Φ), so its rounds
cost no more with thousands of zeros, and on every row of the validation matrix the
direct solve was faster than ADMM (docs, speed)."""
EXACT_CG_RTOL = 1e-6
"""CG tolerance of the projected-Newton rounds of an exact solve (``exact_nonneg``) that
start from the initial estimate instead of ADMM's result."""
DIRECT_CG_RTOL = 1e-5
"""CG tolerance of the projected-Newton rounds that replace ADMM for a solve with Φ and
spectral smoothness (the KKT test, not this, decides when the optimum is reached)."""
DIRECT_KKT_TOLERANCE = 1e-5
"""KKT residual (relative to ‖2Aᵀy‖) at which those rounds stop. The default solve promises
an objective within 1e-4 of the optimum; at this residual every patch of the real frames'
rows of the validation matrix was within 7e-7 of the optimum at 1e-6 (docs, speed), and
the rounds took a fifth to a quarter fewer CG steps. Solves that ask for the optimum
itself (``exact_nonneg``, the weight search) keep
:data:`~reconstruction.solvers.active_set.KKT_TOLERANCE`."""
_BALANCE, _FACTOR = 10.0, 2.0


@dataclass
class SolveReport:
    """What one solve did (JSON-friendly).

    Attributes
    ----------
    iterations : int
        ADMM iterations (1 for a single quadratic solve).
    converged : bool
        Whether the tolerance was met before `max_iter`.
    objective : float
        Objective at the returned image.
    primal_residuals, dual_residuals : list of float
        Final ‖G_t I − z_t‖ and ρ_t‖G_tᵀ(z_t − z_t⁻)‖ per split.
    penalties : list of float
        Final ρ_t per split.
    cg_iterations : list of int
        Conjugate-gradient iterations of each quadratic step (empty when solved exactly).
    cg_residual : float
        Largest final relative residual of those CG solves.
    splits : list of str
        Names of the splits (``nonneg``, ``gradient_L1``, …).
    history : list of float
        Objective after each iteration (with ``track_objective``).
    accelerated : int
        Iterations whose next (z, u) came from Anderson extrapolation.
    polish : PolishReport or None
        The active-set finish of a non-negative L2-type problem (None: not run).
    """

    iterations: int = 0
    converged: bool = False
    objective: float = float("nan")
    primal_residuals: list[float] = field(default_factory=list)
    dual_residuals: list[float] = field(default_factory=list)
    penalties: list[float] = field(default_factory=list)
    cg_iterations: list[int] = field(default_factory=list)
    cg_residual: float = 0.0
    splits: list[str] = field(default_factory=list)
    history: list[float] = field(default_factory=list)
    accelerated: int = 0
    polish: PolishReport | None = None

    def summary(self) -> dict[str, Any]:
        """A compact dict for logs."""
        cg = self.cg_iterations
        return {
            "iterations": self.iterations,
            "converged": self.converged,
            "objective": self.objective,
            "cg_iterations_max": max(cg) if cg else 0,
            "cg_iterations_mean": float(np.mean(cg)) if cg else 0.0,
            "polish": None if self.polish is None else self.polish.status,
            "polish_rounds": 0 if self.polish is None else self.polish.rounds,
        }


@dataclass
class Solution:
    """The latent image (rows, cols, n) and the report of its solve."""

    latent: np.ndarray
    report: SolveReport


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


class _QuadraticStep:
    """Solver of the I-update for the current penalties."""

    def __init__(self, problem: Problem, splits: list[_Split], cg_rtol: float, cg_max_iter: int):
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
        identity = 2.0 * _ridge(p)
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
    step = _QuadraticStep(problem, [], 1e-5, 100)
    return step.apply, step.solver


def _ridge(problem: Problem) -> float:
    """ε of `problem` (set when the Problem is built)."""
    if problem.ridge is None:
        raise DataError("the problem has no ridge ε; build it with Problem(…), which sets one")
    return problem.ridge


def absolute_tolerance(raw: np.ndarray, rtol: float, q_max: float = 1.0) -> float:
    """ε_abs of Algorithm 9: ``rtol · median(raw) / q_max`` (a floor of 1e-12 · rtol)."""
    return float(rtol * max(float(np.median(raw)), 1e-12) / q_max)


@fixed_blas_threads
def initial_estimate(problem: Problem, *, solver: FourierSolver | None = None) -> np.ndarray:
    """A start for ADMM: one FFT solve with Φ as mean translations, priors made quadratic.

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
            identity=2.0 * _ridge(problem),
        )
    x = solver.solve(2.0 * formation.translation_adjoint(problem.raw))
    return np.maximum(x, 0.0) if problem.nonneg else x


@fixed_blas_threads
def solve(
    problem: Problem,
    *,
    rtol: float | None = None,
    atol: float | None = None,
    max_iter: int = 1000,
    x0: np.ndarray | None = None,
    cg_rtol: float = 1e-5,
    cg_max_iter: int = 100,
    penalty: float | None = None,
    track_objective: bool = False,
    exact_nonneg: bool = False,
    direct: bool = False,
    settle: bool = True,
) -> Solution:
    """Minimise `problem` by ADMM (or one quadratic solve when nothing needs splitting).

    Parameters
    ----------
    problem : Problem
    rtol : float, optional
        ε_rel of the convergence test (thesis: 1e-3); default :func:`default_rtol`, with
        σ > 0 tight enough that the objective comes within 1e-4 of the optimum.
    atol : float, optional
        ε_abs; default Algorithm 9 on the patch (the driver passes the whole image's).
    max_iter : int
        ADMM iteration limit k_max.
    x0 : ndarray, optional
        Starting image; splits start at ``z = G x0``. Default :func:`initial_estimate`
        when ADMM runs (the thesis starts from zeros: pass ``np.zeros(shape)`` for that),
        zeros for a single quadratic solve (CG's start with Φ).
    cg_rtol, cg_max_iter : float, int
        Loosest tolerance (relative to the right-hand side) and iteration limit of each
        conjugate-gradient solve (with dispersion); near convergence the tolerance follows
        ADMM's residuals down (:data:`CG_FORCING`).
    penalty : float, optional
        Initial ρ for every split; default from the data term's scale.
    track_objective : bool
        Record the objective after each iteration in ``report.history`` (costly).
    exact_nonneg : bool
        Solve a problem whose only split is non-negativity (L2-type priors) exactly
        (:mod:`~reconstruction.solvers.active_set`); at σ = 0 ADMM's residual test alone
        stops short of the optimum at the small weights the DMC picks. Without Φ, a dual
        active-set method replaces ADMM (``report.iterations`` = 0); if it does not
        settle, and always with Φ, ADMM's result is finished by projected Newton, at
        several times the cost of the ADMM solve.
    direct : bool
        For a non-negative L2-type problem, try the exact optimum with no ADMM: without Φ
        by the dual active-set method (as ``exact_nonneg``) when at most
        :data:`DIRECT_MAX_ZEROS` values of the unconstrained optimum are ≤ 0, with Φ by
        projected Newton straight from the start (the initial estimate); ADMM as usual
        otherwise, or if the rounds do not settle. ``exact_nonneg`` does the same with σ > 0.
    settle : bool
        With spectral smoothness (σ > 0), stop only once the objective has also settled
        (:data:`STALL_WINDOW`). Off for solves that promise no optimum, such as weight
        selection's at the thesis' loose tolerance.
    """
    shape = problem.shape
    l1_splits = problem.has_l1_penalty
    rtol = default_rtol(problem.smoothness) if rtol is None else float(rtol)
    if not (0 < rtol < 1):
        raise DataError(f"rtol must be in (0, 1), got {rtol}")
    atol = absolute_tolerance(problem.raw, rtol) if atol is None else float(atol)
    if x0 is not None and np.shape(x0) != shape:
        raise DataError(f"x0 has shape {np.shape(x0)}, the problem's latent image {shape}")
    report = SolveReport()
    # the exact solve needs K itself (no ADMM penalty): without Φ it may replace ADMM
    exact = None
    start = None  # the initial estimate, once the direct attempt has made it
    if (exact_nonneg or direct) and problem.nonneg and not l1_splits:
        exact = _QuadraticStep(problem, [], cg_rtol, cg_max_iter)
        if exact.exact:  # no Φ: the dual active-set method, from one FFT solve; a direct
            # solve gives up where its dense working set would cost more than ADMM
            limit = None if exact_nonneg else DIRECT_MAX_ZEROS
            x_exact, report.polish = solve_periodic(problem, exact.solver, max_zeros=limit)
        elif problem.smoothness > 0 or direct:
            # a unique optimum: projected Newton straight from the initial estimate, whose
            # matrix K̃ is here, priors being quadratic
            start = x0 if x0 is not None else initial_estimate(problem, solver=exact.solver)
            x_exact, report.polish = polish(
                problem,
                start,
                exact.apply,
                exact.solver,
                cg_rtol=EXACT_CG_RTOL if exact_nonneg else DIRECT_CG_RTOL,
                kkt_tolerance=KKT_TOLERANCE if exact_nonneg else DIRECT_KKT_TOLERANCE,
            )
        if report.polish is not None and report.polish.status == "optimal":
            report.converged, report.splits = True, ["nonneg"]
            return _finish(problem, x_exact, report, exact)
        report.polish = None
        if not exact_nonneg:
            exact = None  # ADMM's own result stands
    if x0 is not None:
        x = np.array(x0, dtype=np.float64)
    elif start is not None:
        x = start
    elif problem.nonneg or l1_splits:
        x = initial_estimate(problem)
    else:
        x = np.zeros(shape)
    # on textured patches ADMM reaches the optimum in far fewer iterations with ρ near the
    # data curvature than with ρ ten times larger (figures in docs/notes/solver.md)
    rho0 = float(penalty) if penalty is not None else problem.data_curvature

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
        identity = _Identity(shape)
        splits.append(
            _Split("nonneg", identity, None, None, rho0, np.maximum(x, 0), np.zeros(shape))
        )

    report.splits = [s.name for s in splits]
    step = _QuadraticStep(problem, splits, cg_rtol, cg_max_iter)
    data_rhs = 2.0 * problem.formation.adjoint(problem.raw)
    if not splits:
        x = step.solve(data_rhs, x)
        report.iterations, report.converged = 1, True
        return _finish(problem, x, report, step)

    sqrt_m = np.sqrt(x.size)
    stall_window = STALL_WINDOW if settle and problem.smoothness > 0 else 0
    recent: list[float] = []
    cg_atol = np.inf
    updates = 0
    anderson = AndersonAcceleration(ANDERSON_MEMORY)
    projected = splits[-1].z if problem.nonneg else x  # x ≥ 0: the last split's z
    for k in range(1, max_iter + 1):
        rhs = data_rhs.copy()
        for s in splits:
            rhs += s.rho * s.operator.adjoint(s.z - s.u)
        x = step.solve(rhs, x, cg_atol)
        converged = True
        gradient_scale, dual_floor = 0.0, np.inf
        primal, dual = [], []
        imbalance = []
        for s in splits:
            gx = s.operator.forward(x)
            relaxed = OVER_RELAXATION * gx + (1.0 - OVER_RELAXATION) * s.z
            z_old = s.z
            s.z_next = s.prox(relaxed + s.u)
            s.u_next = s.u + relaxed - s.z_next
            r = float(np.linalg.norm(gx - s.z_next))
            d = float(s.rho * np.linalg.norm(s.operator.adjoint(s.z_next - z_old)))
            eps_pri = atol * sqrt_m + rtol * max(
                float(np.linalg.norm(gx)), float(np.linalg.norm(s.z_next))
            )
            eps_dual = atol * sqrt_m + rtol * float(
                s.rho * np.linalg.norm(s.operator.adjoint(s.u_next))
            )
            converged &= r < eps_pri and d < eps_dual
            gradient_scale += d + s.rho * r
            dual_floor = min(dual_floor, eps_dual)
            primal.append(r)
            dual.append(d)
            imbalance.append((r, d))
        cg_atol = CG_FORCING * max(dual_floor, gradient_scale)
        if problem.nonneg:
            projected = splits[-1].z_next
        settling = bool(stall_window) and (converged or bool(recent))
        if track_objective or settling:
            objective = problem.objective(projected if problem.nonneg else x)
            if track_objective:
                report.history.append(objective)
        report.iterations = k
        report.primal_residuals, report.dual_residuals = primal, dual
        if settling:
            recent.append(objective)
            window = recent[-stall_window:]
            converged = converged and (
                len(window) >= 2
                and max(window) - min(window) <= STALL_FACTOR * rtol * abs(window[-1])
            )
        if converged:
            report.converged = True
            break
        # the next (z, u): ADMM's own step, extrapolated by Anderson acceleration
        state = np.concatenate([v.ravel() for s in splits for v in (s.z, s.u)])
        mapped = np.concatenate([v.ravel() for s in splits for v in (s.z_next, s.u_next)])
        _unpack(anderson.step(state, mapped), splits)
        report.accelerated += anderson.accepted
        if updates < MAX_PENALTY_UPDATES:
            changed = False
            for s, (rp, rd) in zip(splits, imbalance, strict=True):
                if rp > _BALANCE * rd:
                    s.rho *= _FACTOR
                    s.u /= _FACTOR
                    changed = True
                elif rd > _BALANCE * rp:
                    s.rho /= _FACTOR
                    s.u *= _FACTOR
                    changed = True
            if changed:
                updates += 1
                anderson.reset()
                step.refresh()
    report.penalties = [s.rho for s in splits]
    x = projected.copy() if problem.nonneg else x
    if exact is not None:
        x, report.polish = polish(problem, x, exact.apply, exact.solver)
        report.converged = report.polish.status == "optimal" or report.converged
    return _finish(problem, x, report, step)


def _unpack(vector: np.ndarray, splits: list[_Split]) -> None:
    at = 0
    for s in splits:
        size = s.z.size
        s.z = vector[at : at + size].reshape(s.z.shape)
        s.u = vector[at + size : at + 2 * size].reshape(s.u.shape)
        at += 2 * size


def _finish(problem: Problem, x: np.ndarray, report: SolveReport, step: _QuadraticStep) -> Solution:
    report.objective = problem.objective(x)
    report.cg_iterations = step.cg_iterations
    report.cg_residual = step.cg_residual
    if not np.all(np.isfinite(x)):
        raise DataError(
            "the solver produced NaN or Inf; check the raw image and the weights "
            f"(weights {problem.weights})"
        )
    return Solution(x, report)
