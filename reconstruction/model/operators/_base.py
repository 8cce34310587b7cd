"""Linear operators on image-shaped arrays, with adjoints and the dot test (PyLops style).

Every operator of problem (3.1) — mosaicing M, spectral-to-colour Ω, dispersion Φ, the
spectral basis B and the priors' difference operators — maps an array of
``domain_shape`` to one of ``range_shape`` and knows its adjoint. Composition (``A @ B``)
and the dot test live here so each operator module holds only its own algebra.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from labkit.errors import DataError


class LinearOperator(ABC):
    """A linear map between arrays of fixed shapes.

    Subclasses implement :meth:`_forward` and :meth:`_adjoint` on arrays already checked
    for shape; both must be linear and exact adjoints of each other (⟨A x, y⟩ = ⟨x, Aᵀ y⟩).

    Attributes
    ----------
    domain_shape, range_shape : tuple of int
        Shapes of the input and output arrays.
    name : str
        Short label for messages and logs (``"M"``, ``"Ω"``, …).
    """

    name = "A"

    def __init__(self, domain_shape: tuple[int, ...], range_shape: tuple[int, ...]) -> None:
        self.domain_shape = tuple(int(n) for n in domain_shape)
        self.range_shape = tuple(int(n) for n in range_shape)

    def __repr__(self) -> str:
        return f"{self.name}: {self.domain_shape} → {self.range_shape}"

    def forward(self, x: np.ndarray) -> np.ndarray:
        """A x for an array `x` of :attr:`domain_shape`."""
        return self._forward(self._checked(x, self.domain_shape, "forward"))

    def adjoint(self, y: np.ndarray) -> np.ndarray:
        """Aᵀ y for an array `y` of :attr:`range_shape`."""
        return self._adjoint(self._checked(y, self.range_shape, "adjoint"))

    @abstractmethod
    def _forward(self, x: np.ndarray) -> np.ndarray:
        """A x on an array already checked to be of :attr:`domain_shape`."""

    @abstractmethod
    def _adjoint(self, y: np.ndarray) -> np.ndarray:
        """Aᵀ y on an array already checked to be of :attr:`range_shape`."""

    def _checked(self, array: np.ndarray, shape: tuple[int, ...], what: str) -> np.ndarray:
        array = np.asarray(array)
        if array.shape != shape:
            raise DataError(
                f"operator {self.name} ({what}) expects shape {shape}, got {array.shape}"
            )
        return array

    def __matmul__(self, other: LinearOperator) -> LinearOperator:
        return Composition(self, other)

    @property
    def T(self) -> LinearOperator:
        """The adjoint as an operator."""
        return Adjoint(self)


class Composition(LinearOperator):
    """``outer @ inner``: x ↦ outer(inner(x))."""

    def __init__(self, outer: LinearOperator, inner: LinearOperator) -> None:
        if outer.domain_shape != inner.range_shape:
            raise DataError(
                f"cannot compose {outer.name} {outer.domain_shape} with {inner.name} "
                f"{inner.range_shape}"
            )
        super().__init__(inner.domain_shape, outer.range_shape)
        self.outer, self.inner = outer, inner
        self.name = f"{outer.name}·{inner.name}"

    def _forward(self, x: np.ndarray) -> np.ndarray:
        return self.outer.forward(self.inner.forward(x))

    def _adjoint(self, y: np.ndarray) -> np.ndarray:
        return self.inner.adjoint(self.outer.adjoint(y))


class Adjoint(LinearOperator):
    """The adjoint of an operator as an operator of its own."""

    def __init__(self, op: LinearOperator) -> None:
        super().__init__(op.range_shape, op.domain_shape)
        self.op = op
        self.name = f"{op.name}ᵀ"

    def _forward(self, x: np.ndarray) -> np.ndarray:
        return self.op.adjoint(x)

    def _adjoint(self, y: np.ndarray) -> np.ndarray:
        return self.op.forward(y)


@dataclass(frozen=True)
class DotTest:
    """Result of :func:`dot_test`: ⟨A x, y⟩ and ⟨x, Aᵀ y⟩ for random x, y."""

    forward_inner: float
    adjoint_inner: float

    @property
    def relative_error(self) -> float:
        scale = max(abs(self.forward_inner), abs(self.adjoint_inner), 1e-300)
        return abs(self.forward_inner - self.adjoint_inner) / scale


def dot_test(
    op: LinearOperator,
    *,
    rng: np.random.Generator,
    dtype: type = np.float64,
    sampler: Callable[[tuple[int, ...]], np.ndarray] | None = None,
) -> DotTest:
    """The adjoint (dot) test of `op` with random standard-normal inputs.

    Returns both inner products; an exact adjoint gives a relative error at rounding
    level (≈ 1e-15 in float64, ≈ 1e-6 in float32).
    """
    draw: Callable[[tuple[int, ...]], np.ndarray] = sampler or rng.standard_normal
    x: np.ndarray = draw(op.domain_shape).astype(dtype)
    y: np.ndarray = draw(op.range_shape).astype(dtype)
    ax = op.forward(x)
    aty = op.adjoint(y)
    return DotTest(
        float(np.vdot(ax.astype(np.float64), y.astype(np.float64))),
        float(np.vdot(x.astype(np.float64), aty.astype(np.float64))),
    )
