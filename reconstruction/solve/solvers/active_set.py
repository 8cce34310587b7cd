"""Exact optimum of the non-negative quadratic problems by a projected-Newton active-set method.

With L2-type priors (L2, Lap1, Lap2, L2L2) and non-negativity, problem (3.1) is the bound
constrained quadratic programme ``min ½ xᵀKx − bᵀx, x ≥ 0`` with
``K = 2AᵀA + Σ_j 2w_j D_jᵀD_j + 2εI`` and ``b = 2Aᵀy``. Its KKT conditions are
``Kx − b = μ, x ≥ 0, μ ≥ 0, xᵀμ = 0``. ADMM's residual test stops while directions curved
only by a small prior are still far off (well above the optimum at the small weights the
DMC picks; figures in docs/notes/solver.md), so :func:`polish` finishes its result
with Bertsekas' projected Newton method: the active set S holds the values at zero whose
gradient pushes outwards; the problem with ``x_S = 0`` is solved on the free values, and
the step towards that solution is projected onto x ≥ 0 and shortened until the objective
falls enough (Armijo). It stops when the KKT residual is below :data:`KKT_TOLERANCE`.
The rounds locate S with a loose solve tolerance and switch to a tight one once S repeats
(or a loose solve has nothing left to do).
Warm-started from ADMM, a few rounds suffice (figures in docs/notes/solver.md).

Each round solves ``K_FF x_F = b_F`` on the free set F by conjugate gradients
preconditioned with the FFT solver K̃ (exact without Φ; Φ by mean translations) restricted
to F by a capacitance correction: with ``G̃ = K̃⁻¹`` and ``z = K̃⁻¹ r``,
``(K̃_FF)⁻¹ r = [z − K̃⁻¹ E_S (G̃_SS)⁻¹ z_S]_F``. K̃ is periodic with the 2×2 Bayer
period, so every column of G̃ is a rolled copy of one of 4n impulse responses and the
(k × k) matrix ``G̃_SS`` of the k active values costs a gather and a Cholesky
factorisation. Without Φ the preconditioner is the exact inverse and CG takes one or two
steps; with Φ it is as good as the FFT preconditioner of the unconstrained step.

Without Φ, :func:`solve_periodic` needs no ADMM start: K⁻¹ is exact by FFT, so it works in
the dual. With ``x̂ = K⁻¹b`` and multipliers μ on a working set W of values held at zero,
``x = x̂ + K⁻¹ E_W μ_W`` with ``G̃_WW μ_W = −x̂_W`` (a dense Cholesky solve; G̃_WW gathered
from the impulse responses as above). A primal-dual active-set update keeps the values of
W whose multiplier is positive and adds the most negative values of x outside it (at most
:data:`ADD_BATCH` per round, so that W cannot balloon as a full primal-dual active-set
step does); when W repeats, x ≥ 0, μ ≥ 0 and ``Kx − b = E_W μ`` are the KKT conditions.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from labkit.blas_threads import fixed_blas_threads
from reconstruction.model.problem import Problem
from reconstruction.solve.solvers.cg import conjugate_gradient
from reconstruction.solve.solvers.fourier import FourierSolver

MAX_ACTIVE = 2000
"""Largest working set of :func:`solve_periodic` (dense k × k matrix: 32 MB, one Cholesky
factorisation per round; its time is in docs/notes/solver.md)."""

MAX_PINNED = 500
"""Most values held at zero that :func:`polish`'s preconditioner corrects for exactly (the
most strongly held ones; the rest are only masked). The k × k gather and Cholesky factor
cost O(k²) and O(k³) per round, and beyond a few hundred values they cost more than the
CG steps a fuller correction saves (measured where thousands of values are held, the real
frames under the G = 1 sensor map: docs, speed)."""

MAX_ROUNDS = 30
"""Newton rounds before giving up (the last iterate, never worse than the start, is kept)."""

CG_RTOL = 1e-7
"""Relative residual of the restricted solves once the active set has settled."""

KKT_TOLERANCE = 1e-6
"""KKT residual at the optimum: ‖gradient on positive values, and its negative part on
zeros‖ relative to ‖2Aᵀy‖ (objective then within ≪ 1e-6 of the optimum)."""

_ARMIJO = 1e-4

ROUND_RTOL = 1e-4
"""Relative residual of the rounds before the active set settles (they only locate it)."""

_ACTIVE_TOLERANCE = 1e-10
"""Values within this fraction of the largest value count as zero."""

ADD_BATCH = 300
"""Most values :func:`solve_periodic` adds to its working set per round."""

MAX_PERIODIC_ROUNDS = 100
"""Rounds of :func:`solve_periodic` before it gives up: above the counts observed on 64²
and 128² patches over a wide range of weights (figures in docs/notes/solver.md)."""


@dataclass
class PolishReport:
    """What :func:`polish` did (JSON-friendly).

    Attributes
    ----------
    status : str
        ``"optimal"`` (KKT residual ≤ :data:`KKT_TOLERANCE`), ``"rounds"``
        (:data:`MAX_ROUNDS` reached),
        ``"stalled"`` (no decrease along the projected step) or ``"singular"``;
        :func:`solve_periodic` adds ``"cycled"``, ``"large"`` and ``"inexact"``.
    rounds : int
        Newton rounds (restricted solves), or working-set rounds of :func:`solve_periodic`.
    active : int
        Size of the final active set.
    cg_iterations : list of int
        CG iterations of each restricted solve.
    """

    status: str = "optimal"
    rounds: int = 0
    active: int = 0
    cg_iterations: list[int] = field(default_factory=list)


def inverse_block(
    impulses: np.ndarray, index: tuple[np.ndarray, ...], shape: tuple[int, int]
) -> np.ndarray:
    """The (k × k) block of K̃⁻¹ at k values (``index`` = their rows, cols, bands).

    `impulses` are :meth:`FourierSolver.impulse_responses`; the column of the value at
    (r, c, j) is the impulse response of (r % 2, c % 2, j) rolled by the even part of (r, c).
    """
    rows, cols = shape
    n = impulses.shape[2]
    r, c, j = (v.astype(np.intp) for v in index)
    p, q = r % 2, c % 2
    # flat offsets into the contiguous (2, 2, n, rows, cols, n) array: one take, not a
    # six-way fancy index
    column = ((2 * p + q) * n + j) * (rows * cols * n)
    pixel = ((r[:, None] - r[None, :] + p[None, :]) % rows) * cols
    pixel += (c[:, None] - c[None, :] + q[None, :]) % cols
    pixel *= n
    pixel += j[:, None] + column[None, :]
    block = np.take(np.ascontiguousarray(impulses).ravel(), pixel)
    return 0.5 * (block + block.T)


class _Capacitance:
    """Preconditioner ``(K̃_FF)⁻¹`` for an active set S, from K̃'s impulse responses.

    The correction uses the `pinned` subset of S (all of it up to :data:`MAX_PINNED`):
    that is the inverse of a larger principal block of K̃, restricted to F, so still
    symmetric positive definite, only a rougher preconditioner.
    """

    def __init__(
        self,
        solver: FourierSolver,
        impulses: np.ndarray | None,
        pinned: np.ndarray,
        active: np.ndarray,
    ) -> None:
        self.solver = solver
        self.free = ~active
        self.active_index = np.nonzero(active)
        self.index = np.nonzero(pinned)
        self.factor: tuple[np.ndarray, bool] | None = None
        if self.index[0].size:
            if impulses is None:
                raise ValueError("pinned values need the impulse responses")
            block = inverse_block(impulses, self.index, active.shape[:2])
            self.factor = scipy.linalg.cho_factor(block, check_finite=False)

    def __call__(self, residual: np.ndarray) -> np.ndarray:
        z = self.solver.solve(residual * self.free, refine=False)
        if self.factor is not None:
            nu = np.zeros_like(z)
            nu[self.index] = scipy.linalg.cho_solve(self.factor, z[self.index], check_finite=False)
            z -= self.solver.solve(nu, refine=False)
        z[self.active_index] = 0.0
        return z


def _restricted(
    apply: Callable[[np.ndarray], np.ndarray], free: np.ndarray, v: np.ndarray
) -> np.ndarray:
    """K restricted to the free values: ``v ↦ F K F v`` (F: the free values' mask)."""
    return apply(v * free) * free


@fixed_blas_threads
def polish(
    problem: Problem,
    x_start: np.ndarray,
    apply: Callable[[np.ndarray], np.ndarray],
    solver: FourierSolver,
    *,
    cg_rtol: float | None = None,
    cg_max_iter: int = 200,
    max_rounds: int = MAX_ROUNDS,
    correct_active: bool | None = None,
    kkt_tolerance: float = KKT_TOLERANCE,
) -> tuple[np.ndarray, PolishReport]:
    """The exact non-negative optimum of `problem`, warm-started at `x_start` (≥ 0).

    Parameters
    ----------
    problem : Problem
        Non-negative, with L2-type priors only (nothing but the constraint to split).
    x_start : ndarray
        A feasible estimate (ADMM's projected iterate).
    apply : callable
        x ↦ K x with the true A (and Φ).
    solver : FourierSolver
        K̃: K itself without dispersion, its mean-translation approximation with.
    cg_rtol, cg_max_iter : float, int
        Each restricted solve's tolerance (default :data:`CG_RTOL`) and limit.
    max_rounds : int
        Newton rounds allowed.
    correct_active : bool, optional
        Restrict the preconditioner to the free values exactly (the capacitance
        correction, a Cholesky factorisation of the active set's block of K̃⁻¹ per round
        and a second FFT solve per CG step), or only mask it. Default: correct where K̃
        is K itself (no Φ, so CG takes one or two steps); with Φ, K̃ is an
        approximation anyway and the correction costs more than the CG steps it saves
        (figures in docs/notes/solver.md).
    kkt_tolerance : float
        The KKT residual at which it stops, relative to ‖2Aᵀy‖ (:func:`_satisfies_kkt`).

    Returns
    -------
    x : ndarray
        The last iterate: feasible, and its objective never above `x_start`'s.
    report : PolishReport
    """
    report = PolishReport()
    cg_rtol = CG_RTOL if cg_rtol is None else cg_rtol
    tolerance = max(cg_rtol, ROUND_RTOL)
    b = 2.0 * problem.formation.adjoint(problem.raw)
    scale_b = float(np.linalg.norm(b)) or 1.0
    x = np.maximum(x_start, 0.0)
    value = problem.objective(x)
    gradient = apply(x) - b
    impulses = None
    previous = None
    correct_active = not solver.dispersive if correct_active is None else correct_active
    for _ in range(max_rounds):
        # ε-active set (Bertsekas' projected Newton): at zero and pushed outwards
        active = (x <= _ACTIVE_TOLERANCE * (float(x.max()) or 1.0)) & (gradient > 0)
        report.active = int(active.sum())
        if previous is not None and np.array_equal(active, previous):
            tolerance = cg_rtol
        pinned = np.zeros_like(active)  # masked only, unless corrected for
        if correct_active and report.active:
            if impulses is None:
                # consistent with the unrefined solves of the preconditioner (_Capacitance)
                impulses = solver.impulse_responses(refine=False)
            if report.active <= MAX_PINNED:
                pinned = active
            else:  # correct for the most strongly held values only
                order = np.argsort(np.where(active, gradient, -np.inf), axis=None)
                pinned.ravel()[order[-MAX_PINNED:]] = True
        try:
            precondition = _Capacitance(solver, impulses, pinned, active)
        except (np.linalg.LinAlgError, ValueError):
            report.status = "singular"
            return x, report
        free = ~active
        start = x * free
        while True:
            result = conjugate_gradient(
                functools.partial(_restricted, apply, free),
                b * free,
                x0=start,
                preconditioner=precondition,
                rtol=tolerance,
                max_iter=cg_max_iter,
            )
            if result.iterations or tolerance <= cg_rtol:
                break
            # the loose solve had nothing to do: the set is likely settled, so solve it
            # tightly now rather than spend a round (factor, arc search) on a null step
            tolerance, start = cg_rtol, result.x
        report.rounds += 1
        report.cg_iterations.append(result.iterations)
        direction = result.x * free - x
        # projected arc search: x(t) = max(x + t d, 0), Armijo on the actual decrease
        step = 1.0
        for _ in range(30):
            trial = np.maximum(x + step * direction, 0.0)
            trial_value = problem.objective(trial)
            if trial_value <= value + _ARMIJO * float(np.vdot(gradient, trial - x)):
                break
            step *= 0.5
        else:
            report.status = "stalled"
            return x, report
        clipped = bool(np.any(x + step * direction < 0))
        x, value = trial, trial_value
        gradient = apply(x) - b
        if _satisfies_kkt(x, gradient, scale_b, kkt_tolerance) and not clipped:
            report.status = "optimal"
            return x, report
        if result.iterations == 0:  # the solve had nothing left at this tolerance
            tolerance = max(0.1 * tolerance, 1e-12)
        previous = active
    report.status = "rounds"
    return x, report


def _satisfies_kkt(
    x: np.ndarray, gradient: np.ndarray, scale_b: float, tolerance: float = KKT_TOLERANCE
) -> bool:
    """Whether x ≥ 0 with gradient ``Kx − b`` is optimal to `tolerance` · `scale_b`: the
    gradient vanishes on positive values and pushes outwards on zeros."""
    violation = np.where(x > 0, np.abs(gradient), np.maximum(-gradient, 0.0))
    return float(np.linalg.norm(violation)) <= tolerance * scale_b


def _most_negative(x: np.ndarray, candidates: np.ndarray, count: int) -> np.ndarray:
    """The `count` most negative values of x among `candidates` (a boolean mask)."""
    if int(candidates.sum()) <= count:
        return candidates
    flat = np.where(candidates, x, np.inf).ravel()
    chosen = np.zeros(x.size, bool)
    chosen[np.argpartition(flat, count)[:count]] = True
    return chosen.reshape(x.shape)


@fixed_blas_threads
def solve_periodic(
    problem: Problem,
    solver: FourierSolver,
    *,
    max_rounds: int = MAX_PERIODIC_ROUNDS,
    max_zeros: int | None = None,
) -> tuple[np.ndarray, PolishReport]:
    """The exact non-negative optimum of a problem without Φ, by active sets in the dual.

    Parameters
    ----------
    problem : Problem
        Non-negative, L2-type priors only, no dispersion (K periodic).
    solver : FourierSolver
        K itself (its inverse is exact).
    max_rounds : int
        Working-set rounds allowed.
    max_zeros : int, optional
        Give up at once (status ``"large"``) when more values of the unconstrained optimum
        x̂ than this are ≤ 0.

    Returns
    -------
    x : ndarray
        ``max(x̂ + K⁻¹E_W μ_W, 0)`` of the last round: the optimum when the report's status
        is ``"optimal"``.
    report : PolishReport
        Status ``"optimal"`` (KKT residual ≤ :data:`KKT_TOLERANCE`, checked with K), ``"cycled"``
        (a working set came back), ``"large"`` (it grew past :data:`MAX_ACTIVE`, or x̂ has more
        than `max_zeros` values ≤ 0), ``"rounds"``
        or ``"singular"``; on any of these the caller should fall back to ADMM and
        :func:`polish`. ``cg_iterations`` stays empty.
    """
    report = PolishReport()
    b = 2.0 * problem.formation.adjoint(problem.raw)
    unconstrained = solver.solve(b)
    if max_zeros is not None and int(np.count_nonzero(unconstrained <= 0)) > max_zeros:
        report.status = "large"
        return np.maximum(unconstrained, 0.0), report
    tolerance = _ACTIVE_TOLERANCE * (float(np.abs(unconstrained).max()) or 1.0)
    working = _most_negative(unconstrained, unconstrained < -tolerance, ADD_BATCH)
    x = unconstrained
    impulses = None
    seen: set[bytes] = set()
    report.status = "rounds"
    for _ in range(max_rounds):
        report.rounds += 1
        report.active = int(working.sum())
        if report.active > MAX_ACTIVE:
            report.status = "large"
            return np.maximum(x, 0.0), report
        multipliers = np.zeros(problem.shape)
        if report.active:
            if impulses is None:
                impulses = solver.impulse_responses()
            index = np.nonzero(working)
            try:
                factor = scipy.linalg.cho_factor(
                    inverse_block(impulses, index, problem.shape[:2]), check_finite=False
                )
            except (np.linalg.LinAlgError, ValueError):
                report.status = "singular"
                return np.maximum(x, 0.0), report
            multipliers[index] = scipy.linalg.cho_solve(
                factor, -unconstrained[index], check_finite=False
            )
            x = unconstrained + solver.solve(multipliers)
            x[index] = 0.0  # zero by construction, up to round-off
        else:
            x = unconstrained
        violated = (x < -tolerance) & ~working
        following = (multipliers > 0) | _most_negative(x, violated, ADD_BATCH)
        if np.array_equal(following, working):
            report.status = "settled"
            break
        key = np.packbits(following).tobytes()
        if key in seen:
            report.status = "cycled"
            return np.maximum(x, 0.0), report
        seen.add(key)
        working = following
    x = np.maximum(x, 0.0)
    if report.status == "settled":
        optimal = _satisfies_kkt(x, solver.apply(x) - b, float(np.linalg.norm(b)) or 1.0)
        report.status = "optimal" if optimal else "inexact"
    return x, report
