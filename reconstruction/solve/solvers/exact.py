"""The exact non-negative optimum of an L2-type problem (non-negativity its only split).

At σ = 0 ADMM's residual test stops short of the optimum at the small weights the DMC
criterion picks, so the weight search and ``--exact`` ask for the optimum itself:

* without Φ, the dual active-set method
  (:func:`~reconstruction.solve.solvers.active_set.solve_periodic`) from one FFT solve, with no
  ADMM at all;
* with Φ and spectral smoothness (a unique optimum), projected Newton
  (:func:`~reconstruction.solve.solvers.active_set.polish`) straight from the initial estimate;
* otherwise, or where those do not settle, ADMM's result finished by projected Newton, at
  several times the cost of the ADMM solve.

Problems with an L1 prior or without the constraint are solved by ADMM alone.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from labkit.blas_threads import fixed_blas_threads
from reconstruction.model.problem import Problem
from reconstruction.solve.solvers.active_set import (
    KKT_TOLERANCE,
    PolishReport,
    polish,
    solve_periodic,
)
from reconstruction.solve.solvers.admm import ADMM
from reconstruction.solve.solvers.quadratic import QuadraticStep, initial_estimate
from reconstruction.solve.solvers.report import Solution, SolveReport, check_start, finished

EXACT_CG_RTOL = 1e-6
"""CG tolerance of the projected-Newton rounds of an exact solve that start from the
initial estimate instead of ADMM's result."""


class ExactAttempt(NamedTuple):
    """What an attempt at the optimum without ADMM gave."""

    latent: np.ndarray | None
    """The optimum, or None where the attempt did not settle or was not made."""
    report: PolishReport | None
    start: np.ndarray | None
    """The initial estimate it started from (None: none was made), ADMM's start next."""
    step: QuadraticStep
    """K's quadratic step (no penalty), whose matrix and FFT solver the rounds use."""


def exact_applies(problem: Problem) -> bool:
    """Whether `problem` is non-negative with L2-type priors only (nothing else to split)."""
    return problem.nonneg and not problem.has_l1_penalty


def attempt_optimum(
    problem: Problem,
    x0: np.ndarray | None,
    *,
    cg_rtol: float,
    cg_max_iter: int,
    max_zeros: int | None,
    newton: bool,
    newton_cg_rtol: float,
    kkt_tolerance: float,
) -> ExactAttempt:
    """The exact optimum without ADMM, where a method for it applies.

    Without Φ the dual active-set method (giving up at once beyond `max_zeros` values at or
    below zero in the unconstrained optimum); with Φ, when `newton`, projected Newton from
    `x0` or the initial estimate, to `kkt_tolerance` with CG at `newton_cg_rtol`.
    """
    step = QuadraticStep(problem, [], cg_rtol, cg_max_iter)
    report: PolishReport | None = None
    start = None
    if step.exact:
        x, report = solve_periodic(problem, step.solver, max_zeros=max_zeros)
    elif newton:
        start = x0 if x0 is not None else initial_estimate(problem, solver=step.solver)
        x, report = polish(
            problem,
            start,
            step.apply,
            step.solver,
            cg_rtol=newton_cg_rtol,
            kkt_tolerance=kkt_tolerance,
        )
    if report is not None and report.status == "optimal":
        return ExactAttempt(x, report, start, step)
    return ExactAttempt(None, None, start, step)


def exact_solution(problem: Problem, attempt: ExactAttempt) -> Solution:
    """The solution of an attempt that reached the optimum (no ADMM iteration)."""
    assert attempt.latent is not None and attempt.report is not None
    return finished(
        problem,
        attempt.latent,
        SolveReport(converged=True, splits=["nonneg"], polish=attempt.report),
        cg_iterations=attempt.step.cg_iterations,
        cg_residual=attempt.step.cg_residual,
    )


@fixed_blas_threads
def solve_exact(problem: Problem, *, x0: np.ndarray | None = None, **options: Any) -> Solution:
    """The exact optimum of a non-negative L2-type problem (ADMM for any other).

    The options are :class:`~reconstruction.solve.solvers.admm.ADMM`'s, for its solve where the
    optimum needs one (``report.iterations`` = 0 where it did not).
    """
    admm = ADMM(problem, **options)
    check_start(problem, x0)
    if not exact_applies(problem):
        admm.setup(x0)
        return admm.finalize(admm.run())
    attempt = attempt_optimum(
        problem,
        x0,
        cg_rtol=admm.cg_rtol,
        cg_max_iter=admm.cg_max_iter,
        max_zeros=None,
        newton=problem.smoothness > 0,
        newton_cg_rtol=EXACT_CG_RTOL,
        kkt_tolerance=KKT_TOLERANCE,
    )
    if attempt.latent is not None:
        return exact_solution(problem, attempt)
    admm.setup(x0 if x0 is not None else attempt.start)
    x = admm.run()
    x, admm.report.polish = polish(problem, x, attempt.step.apply, attempt.step.solver)
    admm.report.converged = admm.report.polish.status == "optimal" or admm.report.converged
    return admm.finalize(x)
