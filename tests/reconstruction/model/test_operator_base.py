"""The operator base: composition, adjoint views, shape checks and the dot test itself."""

from __future__ import annotations

import numpy as np
import pytest

from labkit.errors import DataError
from reconstruction.model.operators import LinearOperator, dot_test


class MatrixOperator(LinearOperator):
    """A dense matrix acting on flattened arrays (reference for the tests)."""

    name = "A"

    def __init__(self, matrix: np.ndarray, domain_shape, range_shape, *, wrong_adjoint=False):
        super().__init__(domain_shape, range_shape)
        self.matrix = matrix
        self.wrong_adjoint = wrong_adjoint

    def _forward(self, x):
        return (self.matrix @ x.ravel()).reshape(self.range_shape)

    def _adjoint(self, y):
        m = self.matrix if self.wrong_adjoint else self.matrix.T
        return (m @ y.ravel()).reshape(self.domain_shape)


def test_dot_test_passes_exact_adjoints_and_catches_wrong_ones(rng):
    a = MatrixOperator(rng.standard_normal((6, 6)), (2, 3), (3, 2))
    assert dot_test(a, rng=rng).relative_error < 1e-13
    assert dot_test(a, rng=rng, dtype=np.float32).relative_error < 1e-5
    wrong = MatrixOperator(rng.standard_normal((6, 6)), (2, 3), (3, 2), wrong_adjoint=True)
    assert dot_test(wrong, rng=rng).relative_error > 1e-3


def test_composition_and_adjoint_view_match_the_matrices(rng):
    first = MatrixOperator(rng.standard_normal((4, 6)), (6,), (4,))
    second = MatrixOperator(rng.standard_normal((3, 4)), (4,), (3,))
    both = second @ first
    x = rng.standard_normal(6)
    assert np.allclose(both.forward(x), second.matrix @ first.matrix @ x, rtol=1e-13)
    y = rng.standard_normal(3)
    assert np.allclose(both.T.forward(y), (second.matrix @ first.matrix).T @ y, rtol=1e-13)
    assert dot_test(both, rng=rng).relative_error < 1e-13
    assert both.name == "A·A" and both.T.name == "A·Aᵀ"


def test_shapes_are_checked(rng):
    a = MatrixOperator(rng.standard_normal((4, 6)), (6,), (4,))
    with pytest.raises(DataError, match=r"expects shape \(6,\)"):
        a.forward(np.zeros(5))
    with pytest.raises(DataError, match="cannot compose"):
        _ = a @ a
