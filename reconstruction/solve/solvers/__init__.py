"""Solvers of problem (3.1), chosen by name.

:func:`solve` dispatches through :data:`SOLVE_METHODS`:

``"admm"``
    ADMM (thesis Algorithms 5–9, :mod:`~reconstruction.solve.solvers.admm`), or one quadratic
    solve when nothing needs splitting.
``"exact"``
    The exact non-negative optimum of an L2-type problem
    (:mod:`~reconstruction.solve.solvers.exact`).
``"direct-or-admm"``
    That optimum with no ADMM where it is cheap, else ADMM
    (:mod:`~reconstruction.solve.solvers.direct`).

``"auto"`` is not a method here: :func:`reconstruction.choices.resolve_choices` picks one
with the other automatic choices of a reconstruction. Their building blocks: the FFT
quadratic step (:mod:`~reconstruction.solve.solvers.fourier`), preconditioned CG
(:mod:`~reconstruction.solve.solvers.cg`), the active-set methods
(:mod:`~reconstruction.solve.solvers.active_set`) and Anderson acceleration
(:mod:`~reconstruction.solve.solvers.anderson`).
"""

from collections.abc import Callable
from typing import Any

from labkit.errors import ConfigError
from reconstruction.model.problem import Problem
from reconstruction.solve.solvers.admm import (
    ADMM,
    DEFAULT_RTOL,
    SMOOTH_RTOL,
    absolute_tolerance,
    default_rtol,
    solve_admm,
)
from reconstruction.solve.solvers.cg import CGResult, conjugate_gradient
from reconstruction.solve.solvers.direct import solve_direct
from reconstruction.solve.solvers.exact import solve_exact
from reconstruction.solve.solvers.fourier import FourierSolver, mask_coefficients
from reconstruction.solve.solvers.quadratic import initial_estimate, quadratic_system
from reconstruction.solve.solvers.report import Solution, SolveReport

SOLVE_METHODS: dict[str, Callable[..., Solution]] = {
    "admm": solve_admm,
    "exact": solve_exact,
    "direct-or-admm": solve_direct,
}
"""The solvers by name; each takes the problem and the same keyword options."""


def solve(problem: Problem, *, method: str = "admm", **options: Any) -> Solution:
    """Minimise `problem` by the solver named `method` (a key of :data:`SOLVE_METHODS`).

    Parameters
    ----------
    problem : Problem
    method : str
        ``"admm"``, ``"exact"`` or ``"direct-or-admm"``.
    **options
        The solvers' common options: ``x0``, ``rtol``, ``atol``, ``max_iter``,
        ``cg_rtol``, ``cg_max_iter``, ``penalty``, ``track_objective``, ``settle``
        (:class:`~reconstruction.solve.solvers.admm.ADMM`).
    """
    try:
        function = SOLVE_METHODS[method]
    except KeyError:
        raise ConfigError(
            f"unknown solve method {method!r}; choose one of {', '.join(SOLVE_METHODS)}"
        ) from None
    return function(problem, **options)


__all__ = [
    "ADMM",
    "DEFAULT_RTOL",
    "SMOOTH_RTOL",
    "SOLVE_METHODS",
    "CGResult",
    "FourierSolver",
    "Solution",
    "SolveReport",
    "absolute_tolerance",
    "conjugate_gradient",
    "default_rtol",
    "initial_estimate",
    "mask_coefficients",
    "quadratic_system",
    "solve",
    "solve_admm",
    "solve_direct",
    "solve_exact",
]
