"""The edge-guided L2 prior (``EdgeL2``): its operator, its weights, its problem and its
known answer on a planted edge."""

from __future__ import annotations

import numpy as np
import pytest
from _problems import noisy_step, normalised_colour, rig_corner_formation, smooth_blobs

from labkit.errors import DataError
from reconstruction.model.edge_weights import EDGE_FLOOR, edge_weights
from reconstruction.model.image_formation import ImageFormation
from reconstruction.model.operators import Gradient, WeightedGradient, dot_test
from reconstruction.model.prior_terms import PRIORS, EdgeGuidedTerm, PriorTerm
from reconstruction.model.problem import NEGLIGIBLE_GUIDANCE, SUGGESTED_SMOOTHNESS, Problem
from reconstruction.solve.solvers import solve

SHAPE = (32, 32)


@pytest.mark.parametrize("dtype, tolerance", [(np.float64, 1e-10), (np.float32, 1e-5)])
def test_weighted_gradient_dot_test(dtype, tolerance) -> None:
    rng = np.random.default_rng(1)
    op = WeightedGradient((10, 12, 3), rng.uniform(0.0, 2.0, (10, 12, 2)))
    assert dot_test(op, rng=rng, dtype=dtype).relative_error <= tolerance


def test_weighted_gradient_weighs_each_difference() -> None:
    """‖√w ⊙ ∇u‖² = Σ w |∇u|²; unit weights give the plain gradient; bad weights are refused."""
    rng = np.random.default_rng(2)
    u = rng.standard_normal((6, 8, 2))
    w = rng.uniform(0.1, 1.0, (6, 8, 2))
    g = Gradient((6, 8, 2)).forward(u)
    np.testing.assert_allclose(np.sum(WeightedGradient((6, 8, 2), w).forward(u) ** 2),
                               np.sum(w[:, :, None, :] * g**2))  # fmt: skip
    np.testing.assert_array_equal(WeightedGradient((6, 8, 2), np.ones((6, 8, 2))).forward(u), g)
    with pytest.raises(DataError, match=r"weights of shape \(6, 8, 2\)"):
        WeightedGradient((6, 8, 2), np.ones((6, 8)))
    with pytest.raises(DataError, match="finite and ≥ 0"):
        WeightedGradient((6, 8, 2), -w)


def test_edge_weights_drop_across_an_edge_only() -> None:
    """A vertical step in a grey mosaic: the x-differences that cross it (columns 7→8 of
    the guide) fall to the floor, every difference in the flat parts and along the edge
    stays at 1; the weights do not change with exposure when the level does."""
    raw = np.ones((16, 16))
    raw[:, 8:] = 3.0
    w = edge_weights(raw, cfa="GBRG")
    assert w.shape == (16, 16, 2)
    assert np.all(w[:, 7, 0] < EDGE_FLOOR + 0.01)
    flat_x = np.delete(w[:, :, 0], [7, 15], axis=1)  # 15 wraps around to column 0
    assert flat_x.min() > 0.99 and w[:, :, 1].min() > 0.99
    np.testing.assert_allclose(edge_weights(10 * raw, cfa="GBRG", level=10.0), w, rtol=1e-6)
    with pytest.raises(DataError, match="floor"):
        edge_weights(raw, cfa="GBRG", floor=0.0)
    with pytest.raises(DataError, match="finite"):
        edge_weights(np.full((4, 4), np.nan), cfa="GBRG")


def test_problem_binds_the_guided_term_to_its_patch() -> None:
    """Problem computes the weights from its raw patch unless given, penalises
    Σ w |∇I|², and says it is not circulant (the FFT solve is then only a preconditioner)."""
    rng = np.random.default_rng(3)
    a, truth, raw = noisy_step(SHAPE, rng)
    p = Problem(a, raw, PRIORS["EdgeL2"], (0.5,), True)
    assert isinstance(p.penalties[0][1], EdgeGuidedTerm) and not p.circulant
    np.testing.assert_array_equal(p.edge_weights, edge_weights(raw, cfa="GBRG"))
    gradient = Gradient(truth.shape).forward(truth)
    prior = 0.5 * np.sum(p.edge_weights[:, :, None, :] * gradient**2)
    expected = p.data_misfit(truth) + prior + p.ridge * np.sum(truth**2)
    assert p.objective(truth) == pytest.approx(expected, rel=1e-12)
    assert p.with_weights((0.1,)).edge_weights is p.edge_weights
    assert Problem(a, raw, PRIORS["L2"], (0.5,), True).circulant
    with pytest.raises(DataError, match="no prior term is edge-guided"):
        Problem(a, raw, PRIORS["L2"], (0.5,), True, edge_weights=p.edge_weights)
    with pytest.raises(DataError, match="edge_weights have shape"):
        Problem(a, raw, PRIORS["EdgeL2"], (0.5,), True, edge_weights=np.ones((4, 4, 2)))
    with pytest.raises(DataError, match="only the L2 gradient term"):
        PriorTerm("laplacian", 2, guided=True)


def test_edge_guided_prior_keeps_a_planted_edge() -> None:
    """The step edge of the VTV test (``noisy_step``), L2 and EdgeL2 at the same weight:
    L2 smears the unsampled values across the edge (worst raw-colour error in columns 14–17 measured
    0.24), the guided prior fills them along it (measured 0.10) and fits the flat part as
    well (RMSE 0.0017 both)."""
    rng = np.random.default_rng(5)
    a, truth, raw = noisy_step(SHAPE, rng)
    colour = normalised_colour()
    worst, far = {}, {}
    for prior in ("L2", "EdgeL2"):
        solution = solve(Problem(a, raw, PRIORS[prior], (0.01,), True))
        assert solution.report.converged and np.all(np.isfinite(solution.latent))
        error = np.abs((solution.latent - truth) @ colour.T)[4:-4]
        worst[prior] = float(error[:, 14:18].max())
        far[prior] = float(np.sqrt(np.mean(error[:, 4:10] ** 2)))
    assert worst["L2"] > 0.2
    assert worst["EdgeL2"] < 0.55 * worst["L2"], worst
    assert far["EdgeL2"] < 1.5 * far["L2"] + 1e-3, far


@pytest.mark.parametrize("with_phi", [False, True])
def test_edge_guided_solve_reaches_the_optimum(with_phi: bool) -> None:
    """The default solve (σ = 1e-3) of a textured patch, with and without Φ (the corner of
    the simulated rig's lens), comes within 1e-4 of a tight reference solve's objective
    (relative), like L2's (measured 7e-7 and 4e-7); without Φ by CG and projected Newton,
    the FFT solve being inexact here."""
    rng = np.random.default_rng(6)
    if with_phi:
        a = rig_corner_formation((48, 48))
        assert a.dispersion.max_shift_px > 0.5
    else:
        a = ImageFormation((48, 48), "GBRG", normalised_colour()[None])
    truth = smooth_blobs((48, 48), a.domain_shape[2], rng)
    raw = a.forward(truth)
    raw = raw + 0.01 * raw.mean() * rng.standard_normal(raw.shape)
    p = Problem(a, raw, PRIORS["EdgeL2"], (0.01,), True, smoothness=SUGGESTED_SMOOTHNESS)
    default = solve(p)
    reference = solve(p, rtol=1e-9, method="exact", cg_rtol=1e-10, max_iter=5000)
    gap = (default.report.objective - reference.report.objective) / reference.report.objective
    assert default.report.converged
    assert gap < 1e-4, gap


def test_constant_or_negligible_guidance_keeps_the_problem_circulant() -> None:
    """Unit weights (a flat patch) make the problem L2's, solved exactly by FFT; a weight so
    small that the edge weights' spread moves the matrix by less than NEGLIGIBLE_GUIDANCE
    of the data curvature (a weight search's tiny weights) takes the mean edge weight."""
    rng = np.random.default_rng(7)
    a, _, raw = noisy_step(SHAPE, rng)
    flat = Problem(a, raw, PRIORS["EdgeL2"], (0.05,), True, edge_weights=np.ones((*SHAPE, 2)))
    plain = Problem(a, raw, PRIORS["L2"], (0.05,), True)
    assert flat.circulant
    assert solve(flat).report.objective == pytest.approx(solve(plain).report.objective, rel=1e-9)
    edges = edge_weights(raw, cfa="GBRG")
    spread = float(np.ptp(edges))
    tiny = 0.5 * NEGLIGIBLE_GUIDANCE * plain.data_curvature / (8.0 * spread)
    bound = Problem(a, raw, PRIORS["EdgeL2"], (tiny,), True).penalties[0][1]
    assert bound.constant and bound.mean_weight == pytest.approx(float(np.mean(edges)))
    assert Problem(a, raw, PRIORS["EdgeL2"], (tiny,), True).circulant
    assert not Problem(a, raw, PRIORS["EdgeL2"], (4 * tiny,), True).circulant
