"""Preconditioned conjugate gradients for the ADMM quadratic step with dispersion."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class CGResult:
    """Solution, iterations taken and the final relative residual ‖b − K x‖ / ‖b‖."""

    x: np.ndarray
    iterations: int
    relative_residual: float


def conjugate_gradient(
    apply: Callable[[np.ndarray], np.ndarray],
    b: np.ndarray,
    *,
    x0: np.ndarray | None = None,
    preconditioner: Callable[[np.ndarray], np.ndarray] | None = None,
    rtol: float = 1e-6,
    max_iter: int = 100,
) -> CGResult:
    """Solve K x = b for symmetric positive-definite K given as `apply` (arrays any shape).

    Parameters
    ----------
    apply : callable
        x ↦ K x.
    b : ndarray
    x0 : ndarray, optional
        Warm start (the previous ADMM iterate); zeros by default.
    preconditioner : callable, optional
        r ↦ P⁻¹ r with P ≈ K symmetric positive definite.
    rtol : float
        Stop when ‖b − K x‖ ≤ rtol ‖b‖.
    max_iter : int
        Iteration limit (the result then carries its residual; no error is raised).
    """
    b_norm = float(np.linalg.norm(b))
    x = np.zeros_like(b) if x0 is None else x0.copy()
    if b_norm == 0.0:
        return CGResult(np.zeros_like(b), 0, 0.0)
    r = b - apply(x) if x0 is not None else b.copy()
    residual = float(np.linalg.norm(r)) / b_norm
    if residual <= rtol:
        return CGResult(x, 0, residual)
    z = preconditioner(r) if preconditioner else r
    p = z.copy()
    rz = float(np.vdot(r, z))
    for iteration in range(1, max_iter + 1):
        kp = apply(p)
        curvature = float(np.vdot(p, kp))
        if curvature <= 0:  # K not positive definite along p: stop with what we have
            return CGResult(x, iteration - 1, residual)
        step = rz / curvature
        x += step * p
        r -= step * kp
        residual = float(np.linalg.norm(r)) / b_norm
        if residual <= rtol:
            return CGResult(x, iteration, residual)
        z = preconditioner(r) if preconditioner else r
        rz_next = float(np.vdot(r, z))
        p = z + (rz_next / rz) * p
        rz = rz_next
    return CGResult(x, max_iter, residual)
