"""What a solve returns: the latent image and the report of how it was reached."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from labkit.errors import DataError
from reconstruction.model.problem import Problem
from reconstruction.solve.solvers.active_set import PolishReport


@dataclass
class SolveReport:
    """What one solve did (JSON-friendly).

    Attributes
    ----------
    iterations : int
        ADMM iterations (1 for a single quadratic solve, 0 when an exact method replaced
        ADMM).
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


def check_start(problem: Problem, x0: np.ndarray | None) -> None:
    """Refuse a starting image whose shape is not the problem's latent image's."""
    if x0 is not None and np.shape(x0) != problem.shape:
        raise DataError(f"x0 has shape {np.shape(x0)}, the problem's latent image {problem.shape}")


def finished(
    problem: Problem,
    latent: np.ndarray,
    report: SolveReport,
    *,
    cg_iterations: list[int],
    cg_residual: float,
) -> Solution:
    """The solution with its objective and CG counts recorded; an error if it is not finite."""
    report.objective = problem.objective(latent)
    report.cg_iterations = cg_iterations
    report.cg_residual = cg_residual
    if not np.all(np.isfinite(latent)):
        raise DataError(
            "the solver produced NaN or Inf; check the raw image and the weights "
            f"(weights {problem.weights})"
        )
    return Solution(latent, report)
