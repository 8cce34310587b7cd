"""Solvers of problem (3.1): ADMM (Algorithms 5–9), the exact FFT quadratic step, PCG."""

from reconstruction.solvers.admm import (
    DEFAULT_RTOL,
    SMOOTH_RTOL,
    Solution,
    SolveReport,
    absolute_tolerance,
    solve,
)
from reconstruction.solvers.cg import CGResult, conjugate_gradient
from reconstruction.solvers.fourier import FourierSolver, mask_coefficients

__all__ = [
    "DEFAULT_RTOL",
    "SMOOTH_RTOL",
    "CGResult",
    "FourierSolver",
    "Solution",
    "SolveReport",
    "absolute_tolerance",
    "conjugate_gradient",
    "mask_coefficients",
    "solve",
]
