"""Preconditioned conjugate gradients for the ADMM quadratic step with dispersion."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class CGResult:
    """Solution, iterations taken and the final relative residual ‖b − K x‖ / ‖b‖, and
    (when asked for with ``track_product``) K x, updated alongside x."""

    x: np.ndarray
    iterations: int
    relative_residual: float
    product: np.ndarray | None = None


def conjugate_gradient(
    apply: Callable[[np.ndarray], np.ndarray],
    b: np.ndarray,
    *,
    x0: np.ndarray | None = None,
    preconditioner: Callable[[np.ndarray], np.ndarray] | None = None,
    rtol: float = 1e-6,
    max_iter: int = 100,
    product0: np.ndarray | None = None,
    track_product: bool = False,
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
    product0 : ndarray, optional
        K x0, if known (a previous result's ``product``): saves the product that the
        initial residual would otherwise cost.
    track_product : bool
        Update K x alongside x (one vector update per iteration, no product) and return it
        as ``product``, for the next solve with the same K started from this x.
    """
    b_norm = float(np.linalg.norm(b))
    x = np.zeros_like(b) if x0 is None else x0.copy()
    if b_norm == 0.0:
        return CGResult(np.zeros_like(b), 0, 0.0, np.zeros_like(b) if track_product else None)
    if x0 is None:
        kx = np.zeros_like(b)
    else:
        kx = apply(x) if product0 is None else product0.copy()
    r = b - kx
    residual = float(np.linalg.norm(r)) / b_norm
    product = kx if track_product else None
    if residual <= rtol:
        return CGResult(x, 0, residual, product)
    z = preconditioner(r) if preconditioner else r
    p = z.copy()
    rz = float(np.vdot(r, z))
    for iteration in range(1, max_iter + 1):
        kp = apply(p)
        curvature = float(np.vdot(p, kp))
        if curvature <= 0:  # K not positive definite along p: stop with what we have
            return CGResult(x, iteration - 1, residual, product)
        step = rz / curvature
        x += step * p
        r -= step * kp
        if product is not None:  # track_product
            product += step * kp
        residual = float(np.linalg.norm(r)) / b_norm
        if residual <= rtol:
            return CGResult(x, iteration, residual, product)
        z = preconditioner(r) if preconditioner else r
        rz_next = float(np.vdot(r, z))
        p = z + (rz_next / rz) * p
        rz = rz_next
    return CGResult(x, max_iter, residual, product)
