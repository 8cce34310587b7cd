"""Safeguarded Anderson acceleration of a fixed-point iteration (ADMM's (z, u) map)."""

from __future__ import annotations

import numpy as np

ANDERSON_SAFEGUARD = 10.0
"""An extrapolation whose residual exceeds this many times the best residual so far is
undone (:class:`AndersonAcceleration`)."""


class AndersonAcceleration:
    """Type-II Anderson acceleration of a fixed-point map y ↦ g(y) (Walker & Ni 2011).

    With memory m the next iterate is ``g(y) − ΔG γ``, γ the least-squares fit of the
    newest residual f = g(y) − y by the last m residual differences ΔF, and ΔG the
    matching differences of g (ΔY + ΔF). An extrapolation whose residual comes out more
    than :data:`ANDERSON_SAFEGUARD`-fold above the best so far is rejected: the iteration
    goes on from the plain step of the point it was extrapolated from, and the memory
    restarts. (Keeping it instead, where the residual differences had become nearly
    collinear near convergence, threw the objective up by orders of magnitude and cost
    ADMM many iterations to recover; figures in docs/notes/solver.md.)

    Parameters
    ----------
    memory : int
        How many residual differences it keeps (0: no acceleration, the plain step).
    """

    def __init__(self, memory: int) -> None:
        self.memory = memory
        self._d_mapped = np.empty((memory, 0))  # (memory, size) ring buffers of ΔG, ΔF
        self._d_residuals = np.empty((memory, 0))
        self._gram = np.zeros((memory, memory))  # ΔFᵀΔF, updated one column at a time
        self.reset()

    def reset(self) -> None:
        self.count = 0  # stored differences
        self.slot = 0  # where the next one goes
        self.last: tuple[np.ndarray, np.ndarray] | None = None  # the last (g(y), f)
        self.best = np.inf
        self.accepted = 0
        self.fallback: np.ndarray | None = None  # the plain step an extrapolation replaced

    def _store(
        self, mapped: np.ndarray, residual: np.ndarray, last: tuple[np.ndarray, np.ndarray]
    ) -> None:
        if self._d_mapped.shape[1] != mapped.size:
            self._d_mapped = np.empty((self.memory, mapped.size))
            self._d_residuals = np.empty((self.memory, mapped.size))
        slot = self.slot
        np.subtract(mapped, last[0], out=self._d_mapped[slot])
        d_residual = np.subtract(residual, last[1], out=self._d_residuals[slot])
        self.count = min(self.count + 1, self.memory)
        products = self._d_residuals[: self.count] @ d_residual
        self._gram[slot, : self.count] = products
        self._gram[: self.count, slot] = products
        self.slot = (slot + 1) % self.memory

    def step(self, state: np.ndarray, mapped: np.ndarray) -> np.ndarray:
        self.accepted = 0
        if self.memory == 0:
            return mapped
        residual = mapped - state
        norm = float(np.linalg.norm(residual))
        if norm > ANDERSON_SAFEGUARD * self.best:
            fallback = self.fallback
            self.reset()
            if fallback is not None:  # `state` was a bad extrapolation: undo it
                return fallback
        self.best = min(self.best, norm)
        if self.last is not None:
            self._store(mapped, residual, self.last)
        self.last = (mapped, residual)
        if self.count == 0:
            return mapped
        m = self.count
        gram = self._gram[:m, :m]
        scale = np.sqrt(np.diag(gram))
        if not np.all(scale > 0):
            self.reset()
            return mapped
        normalised = gram / np.outer(scale, scale) + 1e-10 * np.eye(m)
        gamma = np.linalg.solve(normalised, (self._d_residuals[:m] @ residual) / scale) / scale
        self.accepted = 1
        self.fallback = mapped
        return mapped - gamma @ self._d_mapped[:m]
