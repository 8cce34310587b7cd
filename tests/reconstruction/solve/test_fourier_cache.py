"""FourierSolver's block cache: solvers of the same matrix share one inversion, and only
those (without dispersion every patch of an image has the same matrix)."""

from __future__ import annotations

import numpy as np
import pytest
from _problems import normalised_colour

from reconstruction.model.prior_terms import PRIORS
from reconstruction.solve.solvers import fourier
from reconstruction.solve.solvers.fourier import FourierSolver

SHAPE = (16, 16)


@pytest.fixture(autouse=True)
def empty_cache():
    fourier._BLOCKS.clear()
    yield
    fourier._BLOCKS.clear()


def _solver(colour=None, cfa="GBRG", weight=0.1, identity=1e-3, shape=SHAPE) -> FourierSolver:
    colour = normalised_colour() if colour is None else colour
    return FourierSolver(shape, cfa, colour, terms=[(weight, PRIORS["L2"][0])], identity=identity)


def test_the_same_matrix_is_inverted_once_and_solves_alike() -> None:
    first, second = _solver(), _solver()
    assert second._inverse is first._inverse
    b = np.random.default_rng(0).standard_normal((*SHAPE, first.channels))
    fourier._BLOCKS.clear()
    fresh = _solver()
    assert fresh._inverse is not first._inverse
    assert second._refine == fresh._refine  # the cache keeps whether solves refine
    np.testing.assert_array_equal(second.solve(b), fresh.solve(b))
    for identity in (1e-12, 1.0):  # refining and not
        fourier._BLOCKS.clear()
        fresh, cached = _solver(identity=identity), _solver(identity=identity)
        assert cached._inverse is fresh._inverse and cached._refine == fresh._refine
    assert fresh._refine != _solver(identity=1e-12)._refine


@pytest.mark.parametrize(
    "change",
    [
        {"cfa": "RGGB"},
        {"weight": 0.2},
        {"identity": 2e-3},
        {"shape": (16, 20)},
        {"colour": 1.5 * normalised_colour()},
    ],
    ids=lambda c: next(iter(c)),
)
def test_a_different_matrix_is_not_shared(change: dict) -> None:
    base = _solver()
    other = _solver(**change)
    assert other._inverse is not base._inverse
    assert (
        not np.array_equal(other._matrix, base._matrix) or other._matrix.shape != base._matrix.shape
    )


def test_a_penalty_update_leaves_the_other_solvers_alone() -> None:
    first, second = _solver(), _solver()
    before = first._inverse.copy()
    second.set_identity(5e-3)  # ADMM's penalty update on one patch
    np.testing.assert_array_equal(first._inverse, before)
    assert first.identity == 1e-3 and second.identity == 5e-3
    with pytest.raises(ValueError, match="read-only"):
        first._inverse[0, 0, 0] = 0.0


def test_solvers_with_dispersion_are_not_cached() -> None:
    colour = normalised_colour()
    per_frequency = np.broadcast_to(colour.astype(complex), (*SHAPE, *colour.shape)).copy()
    a = _solver(colour=per_frequency)
    b = _solver(colour=per_frequency)
    assert a._key is None and len(fourier._BLOCKS._entries) == 0
    assert b._dense_blocks()[1] is not a._dense_blocks()[1]
    # each solves its own (equal) matrix alike: to the same bits, and to K x = b
    x = np.random.default_rng(1).standard_normal((*SHAPE, a.channels))
    np.testing.assert_array_equal(a.solve(x), b.solve(x))
    np.testing.assert_allclose(a.apply(a.solve(x)), x, rtol=0, atol=1e-9 * np.abs(x).max())
