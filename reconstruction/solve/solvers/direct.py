"""The direct solve: the exact non-negative optimum with no ADMM where that is cheaper.

For a non-negative L2-type problem it tries the optimum straight away, without Φ by the
dual active-set method when at most :data:`DIRECT_MAX_ZEROS` values of the unconstrained
optimum are ≤ 0, with Φ by projected Newton from the initial estimate; where that does not
settle, or the problem is of another kind, ADMM's own result stands (no finish, unlike
:mod:`~reconstruction.solve.solvers.exact`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from labkit.blas_threads import fixed_blas_threads
from reconstruction.model.problem import Problem
from reconstruction.solve.solvers.admm import ADMM
from reconstruction.solve.solvers.exact import attempt_optimum, exact_applies, exact_solution
from reconstruction.solve.solvers.report import Solution, check_start

DIRECT_MAX_ZEROS = 600
"""Largest number of values at or below zero in the unconstrained optimum for which a
direct solve without Φ skips ADMM: the dual active-set method factorises a dense block
over its working set, which costs more than ADMM once it numbers in the thousands. No limit
for the ``exact`` method without Φ (an edge-guided prior's weight search, whose ADMM steps
need CG): ADMM there costs more than the rounds, as for
:func:`~reconstruction.solve.solvers.active_set.solve_periodic`. None with Φ either: projected
Newton there masks the values held at zero in its preconditioner (and corrects for at most
:data:`~reconstruction.solve.solvers.active_set.MAX_PINNED` of them without Φ), so its rounds
cost no more with thousands of zeros, and on every row of the validation matrix the
direct solve was faster than ADMM (docs, speed)."""
DIRECT_CG_RTOL = 1e-5
"""CG tolerance of the projected-Newton rounds that replace ADMM for a solve with Φ
(the KKT test, not this, decides when the optimum is reached)."""
DIRECT_KKT_TOLERANCE = 1e-5
"""KKT residual (relative to ‖2Aᵀy‖) at which those rounds stop. The default solve promises
an objective within 1e-4 of the optimum; at this residual every patch of the real frames'
rows of the validation matrix was within 7e-7 of the optimum at 1e-6 (docs, speed), and
the rounds took a fifth to a quarter fewer CG steps. Solves that ask for the optimum
itself (the ``exact`` method, the weight search) keep
:data:`~reconstruction.solve.solvers.active_set.KKT_TOLERANCE`."""


@fixed_blas_threads
def solve_direct(problem: Problem, *, x0: np.ndarray | None = None, **options: Any) -> Solution:
    """The exact optimum without ADMM where it applies and is cheap, else ADMM.

    The options are :class:`~reconstruction.solve.solvers.admm.ADMM`'s, for its solve where one
    is needed (``report.iterations`` = 0 where none was).
    """
    admm = ADMM(problem, **options)
    check_start(problem, x0)
    start = x0
    if exact_applies(problem):
        attempt = attempt_optimum(
            problem,
            x0,
            cg_rtol=admm.cg_rtol,
            cg_max_iter=admm.cg_max_iter,
            max_zeros=DIRECT_MAX_ZEROS,
            newton=True,
            newton_cg_rtol=DIRECT_CG_RTOL,
            kkt_tolerance=DIRECT_KKT_TOLERANCE,
        )
        if attempt.latent is not None:
            return exact_solution(problem, attempt)
        start = x0 if x0 is not None else attempt.start
    admm.setup(start)
    return admm.finalize(admm.run())
