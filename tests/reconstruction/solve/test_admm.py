"""ADMM (thesis Algorithms 5–9) against independent references."""

from __future__ import annotations

import numpy as np
import pytest
from _problems import (
    kkt_violation,
    latent_space,
    noisy_raw,
    noisy_step,
    normalised_colour,
    problem,
    rig_corner_formation,
    smooth_blobs,
    smooth_reference,
)

from labkit.errors import DataError
from reconstruction.model.image_formation import ImageFormation, build_formation
from reconstruction.model.operators import smoothest_metamer
from reconstruction.model.prior_terms import PRIORS, PriorTerm
from reconstruction.model.problem import SUGGESTED_SMOOTHNESS, Problem
from reconstruction.solve.solvers import initial_estimate, solve

SHAPE = (32, 32)


@pytest.mark.parametrize("prior", ["L2", "Lap2", "L2L2"])
@pytest.mark.parametrize("nonneg", [False, True])
def test_l2_priors_reach_the_optimum(prior: str, nonneg: bool) -> None:
    """Default tolerance: objective within 1e-4 (relative) of an L-BFGS-B optimum."""
    p = problem(prior, 0.03, nonneg)
    solution = solve(p)
    reference = smooth_reference(p)
    assert solution.report.converged
    assert (solution.report.objective - reference) / reference < 1e-4
    if nonneg:
        assert solution.latent.min() >= 0
    else:
        assert solution.report.iterations == 1  # a single exact quadratic solve


@pytest.mark.parametrize("prior", ["L1", "Lap1", "L1L1", "L1SpatialLap2", "VTV"])
@pytest.mark.parametrize("nonneg", [False, True])
def test_l1_priors_reach_a_long_solve_with_spectral_smoothness(prior: str, nonneg: bool) -> None:
    """L1 priors with σ = SUGGESTED_SMOOTHNESS: the default solve (ε_rel = SMOOTH_RTOL)
    is within 1e-4 of a long, tight solve (measured 6e-6–2.7e-5; at ε_rel = 1e-4 it stops
    up to 1.5e-3 above)."""
    p = problem(prior, 0.01, nonneg, seed=1, smoothness=SUGGESTED_SMOOTHNESS)
    solution = solve(p)
    reference = solve(p, rtol=1e-9, max_iter=3000)
    gap = (solution.report.objective - reference.report.objective) / reference.report.objective
    assert -1e-6 < gap < 1e-4
    assert solution.report.converged and np.all(np.isfinite(solution.latent))
    if nonneg:
        assert solution.latent.min() >= 0


@pytest.mark.parametrize("prior", ["L1", "Lap1", "VTV"])
@pytest.mark.parametrize("nonneg", [False, True])
def test_l1_priors_without_smoothness_approach_a_long_solve(prior: str, nonneg: bool) -> None:
    """L1 priors without σ (the thesis' problem): the default solve (ε_rel = DEFAULT_RTOL) is
    within 1e-2 of a much tighter, long solve (measured 1e-4–3.6e-3).

    Known gap: the issue asks for 1e-4. Without σ the optimum is a degenerate metamer that
    ADMM approaches slowly (see DEFAULT_RTOL); with σ the test above reaches 1e-4.
    """
    p = problem(prior, 0.01, nonneg, seed=1)
    solution = solve(p)
    reference = solve(p, rtol=1e-7, max_iter=5000)
    gap = (solution.report.objective - reference.report.objective) / reference.report.objective
    assert -1e-6 < gap < 1e-2
    assert np.all(np.isfinite(solution.latent))


def test_vectorial_tv_keeps_a_noisy_step_sharp() -> None:
    """A vertical step between two spectra (grey | yellow) with 1 % noise, 32×32, w = 0.01:
    the L2 prior interpolates the unsampled bands across the step (colour error 0.24 next
    to it); VTV keeps it sharp like L1 (measured 0.015 and 0.006), in fewer ADMM
    iterations than L1 (146 against 239)."""
    colour = normalised_colour()
    a, truth, raw = noisy_step(SHAPE, np.random.default_rng(5))
    worst, iterations = {}, {}
    for prior in ("L2", "L1", "VTV"):
        solution = solve(Problem(a, raw, PRIORS[prior], (0.01,), True), rtol=1e-5, max_iter=5000)
        error = np.abs(solution.latent @ colour.T - (truth @ colour.T))[4:-4]
        worst[prior] = float(error[:, 14:18].max())
        iterations[prior] = solution.report.iterations
        assert np.all(np.isfinite(solution.latent))
    assert worst["L2"] > 0.1
    assert worst["VTV"] < 0.03 and worst["L1"] < 0.03
    assert iterations["VTV"] < iterations["L1"]


def test_grouped_term_value_and_prox() -> None:
    """‖D I‖₂,₁ sums each pixel's 2-norm over bands and directions; its prox shrinks
    every such vector by the threshold, and zeroes vectors shorter than it."""
    term = PRIORS["VTV"][0]
    d = np.zeros((2, 2, 2, 2))
    d[0, 0] = [[3.0, 0.0], [0.0, 4.0]]  # norm 5
    d[1, 1, 0, 1] = 0.5
    assert term.label == "gradient_L21" and term.value(d) == pytest.approx(5.5)
    p = problem("VTV", 1.0, False)
    p_split = solve(p, max_iter=1)  # one iteration: just to build the split
    assert p_split.report.splits == ["gradient_L21"]
    from reconstruction.solve.solvers.admm import _Split

    split = _Split("g", None, 2.0, 0, 2.0, d, d, grouped=True)  # threshold 1
    shrunk = split.prox(d)
    np.testing.assert_allclose(shrunk[0, 0], d[0, 0] * (1 - 1 / 5))
    assert not shrunk[1, 1].any()
    with pytest.raises(DataError, match="only an L1 term can be grouped"):
        type(term)("gradient", 2, grouped=True)


def test_conjugate_gradients_with_dispersion_converge_quickly() -> None:
    """Simulated rig's lens, a corner patch (2.1 px): PCG needs ≤ 10 iterations per ADMM step."""
    rng = np.random.default_rng(5)
    a = rig_corner_formation((96, 96))
    _, raw = noisy_raw(a, rng)
    p = Problem(a, raw, PRIORS["L2"], (0.03,), True)
    solution = solve(p)
    assert a.dispersion.max_shift_px > 0.5
    assert solution.report.converged
    assert max(solution.report.cg_iterations) <= 10
    assert solution.report.cg_residual <= 1e-5


def test_conjugate_gradients_keep_k_x_for_the_next_solve() -> None:
    """CG returns K x updated alongside x, as accurate as CG's own updated residual (planted
    SPD K of condition 10, no preconditioner: held to 1e-12 of ‖K x‖);
    a solve given it as ``product0`` makes one product fewer and reaches the same x. ADMM's
    quadratic step does this between its iterations (drift measured on the real frames over
    1000 VTV iterations: ≤ 6e-15 of ‖rhs‖)."""
    from reconstruction.solve.solvers.cg import conjugate_gradient

    rng = np.random.default_rng(11)
    q, _ = np.linalg.qr(rng.standard_normal((60, 60)))
    k = (q * np.logspace(0, 1, 60)) @ q.T
    calls = []

    def apply(v: np.ndarray) -> np.ndarray:
        calls.append(1)
        return k @ v

    b1, b2 = rng.standard_normal(60), rng.standard_normal(60)
    # as in ADMM, where each solve starts near its answer: from zeros, then from the last x
    first = conjugate_gradient(apply, b1, rtol=1e-6, track_product=True)
    exact = k @ first.x
    assert np.linalg.norm(first.product - exact) < 1e-12 * np.linalg.norm(exact)
    calls.clear()
    plain = conjugate_gradient(apply, b2, x0=first.x, rtol=1e-10)
    plain_calls = len(calls)
    calls.clear()
    kept = conjugate_gradient(apply, b2, x0=first.x, rtol=1e-10, product0=first.product)
    assert len(calls) == plain_calls - 1
    assert max(kept.iterations, plain.iterations) < 100  # both converged
    np.testing.assert_allclose(kept.x, plain.x, rtol=1e-7)
    assert kept.product is None  # only kept when asked for


def test_initial_estimate_is_the_quadratic_optimum_it_promises() -> None:
    """Under a uniform periodic shift (up to 2.7 px), Ã = A: the start is the exact
    unconstrained L2 optimum of the Φ problem (for an L1 prior, of its quadratic
    stand-in), clipped at zero for a non-negative problem. What ADMM makes of it, warm
    against cold: test_admm_reproducibility."""
    from test_dispersion_operator import ConstantField
    from test_image_formation import spectral_model

    rng = np.random.default_rng(8)
    model = spectral_model(ConstantField((0.7, -1.3), per_nm=True))
    a = build_formation(latent_space(), (32, 32), "GBRG", model=model, interpolation="bilinear")
    _, raw = noisy_raw(a, rng)
    free = Problem(a, raw, PRIORS["L2"], (0.05,), False)
    single = solve(free, cg_rtol=1e-10)
    # regression: with the ridge alone in the identity, a float32 preconditioner left CG at
    # a residual of 0.73 after 500 iterations; in float64 the exact one needs 1–2
    assert single.report.cg_iterations[0] <= 3
    exact = single.latent
    start = initial_estimate(free)
    assert np.linalg.norm(start - exact) < 1e-6 * np.linalg.norm(exact)
    nonneg = Problem(a, raw, PRIORS["L2"], (0.05,), True)
    np.testing.assert_array_equal(initial_estimate(nonneg), np.maximum(start, 0.0))
    assert exact.min() < 0  # so the clipping is tested
    l1 = Problem(a, raw, PRIORS["L1"], (0.05,), False)
    np.testing.assert_allclose(initial_estimate(l1), start, rtol=1e-12, atol=1e-12)


def test_unconstrained_l2_solution_has_zero_gradient() -> None:
    """KKT: the gradient of the objective vanishes at the single-solve L2 solution."""
    p = problem("L2", 0.05, False)
    x = solve(p).latent
    a, d = p.formation, p.differences[0]
    grad = (
        2 * a.adjoint(a.forward(x) - p.raw) + 2 * 0.05 * d.adjoint(d.forward(x)) + 2 * p.ridge * x
    )
    assert np.linalg.norm(grad) < 1e-8 * np.linalg.norm(2 * a.adjoint(p.raw))


def test_bad_settings_are_refused() -> None:
    p = problem("L2", 0.05, True)
    with pytest.raises(DataError, match="rtol"):
        solve(p, rtol=2.0)
    with pytest.raises(DataError, match="x0"):
        solve(p, x0=np.zeros((3, 3, 3)))
    with pytest.raises(DataError, match="weights"):
        Problem(p.formation, p.raw, p.terms, (-1.0,), True)


@pytest.mark.parametrize("weight", [4.7e-4, 6.3e-3])
@pytest.mark.parametrize("prior", ["L2", "Lap2"])
@pytest.mark.parametrize("nonneg", [True, False])
def test_default_solve_reaches_the_optimum_with_spectral_smoothness(
    weight: float, prior: str, nonneg: bool
) -> None:
    """The issue's optimality check on a 128×128 simulated patch, as the pipeline poses it:
    σ = SUGGESTED_SMOOTHNESS, at the DMC's picks on the rig without σ (4.7e-4) and with it
    (6.3e-3). The default solve (from the initial estimate, ε_rel = SMOOTH_RTOL) ends within
    1e-4 of the exact optimum (measured with non-negativity: L2 2.1e-6 / 8.7e-7, Lap2 7.1e-6
    / 4.3e-6; at σ = 0 and ε_rel = DEFAULT_RTOL it stops 5.5e-4 / 9.7e-4 above it at
    4.7e-4)."""
    rng = np.random.default_rng(3)
    a = ImageFormation((128, 128), "GBRG", normalised_colour()[None])
    _, raw = noisy_raw(a, rng, noise=0.002)
    terms = PRIORS[prior]
    p = Problem(a, raw, terms, (weight,) * len(terms), nonneg, smoothness=SUGGESTED_SMOOTHNESS)
    default = solve(p)
    if nonneg:
        optimum = solve(p, method="exact")
        assert optimum.report.iterations == 0 and optimum.report.polish.status == "optimal"
        assert kkt_violation(p, optimum.latent) < 1e-6
        gap = (default.report.objective - optimum.report.objective) / optimum.report.objective
        assert -1e-9 < gap < 1e-4
        assert default.report.converged and default.latent.min() >= 0
    else:  # one exact FFT solve: the gradient vanishes
        assert default.report.iterations == 1
        assert kkt_violation(p, default.latent) < 1e-8


def smooth_spectra_raw(
    shape: tuple[int, int], seed: int
) -> tuple[ImageFormation, np.ndarray, np.ndarray]:
    """(A, truth, raw): blobs whose spectra are smooth across the bands (Gaussian, σ = 1.5
    bands), 0.5 % noise."""
    rng = np.random.default_rng(seed)
    a = ImageFormation(shape, "GBRG", normalised_colour()[None])
    truth = smooth_blobs(shape, a.domain_shape[2], rng)
    raw = a.forward(truth)
    return a, truth, raw + 0.005 * raw.mean() * rng.standard_normal(raw.shape)


@pytest.mark.parametrize("weight", [1e-3, 6.3e-3])
def test_spectral_smoothness_makes_the_optimum_the_better_spectrum(weight: float) -> None:
    """Planted smooth spectra, 32×32, L2 prior, non-negativity. Without σ the exact optimum
    picks the smallest non-negative metamer (spectral error 0.26 / 0.31), and ADMM from the
    unconstrained start stops elsewhere again (0.34): where the solver stops decides the
    spectrum. With σ = SUGGESTED_SMOOTHNESS the optimum is the smoothest metamer (0.14 /
    0.16) and the default solve lands on it (to 1e-3 in the image, 1e-4 in the objective)."""
    a, truth, raw = smooth_spectra_raw((32, 32), seed=4)

    def error(x: np.ndarray) -> float:
        return float(np.linalg.norm(x - truth) / np.linalg.norm(truth))

    plain = Problem(a, raw, PRIORS["L2"], (weight,), True)
    smooth = Problem(a, raw, PRIORS["L2"], (weight,), True, smoothness=SUGGESTED_SMOOTHNESS)
    plain_optimum = solve(plain, method="exact")
    smooth_optimum = solve(smooth, method="exact")
    smooth_default = solve(smooth)
    assert error(smooth_optimum.latent) < 0.6 * error(plain_optimum.latent)
    assert error(smooth_optimum.latent) < 0.6 * error(solve(plain).latent)
    drift = np.linalg.norm(smooth_default.latent - smooth_optimum.latent)
    assert drift < 1e-2 * np.linalg.norm(smooth_optimum.latent)
    optimum = smooth_optimum.report.objective
    assert (smooth_default.report.objective - optimum) / optimum < 1e-4
    # the colour the camera saw is fitted equally well either way
    colour = np.linalg.norm(a.forward(smooth_optimum.latent) - raw) / np.linalg.norm(raw)
    assert colour < 2 * np.linalg.norm(a.forward(plain_optimum.latent) - raw) / np.linalg.norm(raw)


def test_spectral_smoothness_is_validated() -> None:
    p = problem("L2", 0.05, True)
    for bad in (-1e-3, float("nan")):
        with pytest.raises(DataError, match="smoothness"):
            Problem(p.formation, p.raw, p.terms, p.weights, True, smoothness=bad)
    grey = ImageFormation(SHAPE, "GBRG", np.ones((1, 3, 1)))
    with pytest.raises(DataError, match="≥ 2 latent channels"):
        Problem(grey, p.raw, p.terms, p.weights, True, smoothness=1e-3)
    # the objective carries σ‖S I‖² = σ(‖∇λ(I − Ī)‖² + N‖∇λ P Ī‖²), P = I − R C
    x = np.random.default_rng(0).uniform(size=p.shape)
    with_sigma = Problem(p.formation, p.raw, p.terms, p.weights, True, smoothness=0.5)
    mean = x.mean(axis=(0, 1))
    unseen = mean - smoothest_metamer(p.formation.colour_matrix) @ mean
    roughness = np.sum(np.diff(x - mean, axis=2) ** 2) + x[..., 0].size * np.sum(
        np.diff(unseen) ** 2
    )
    expected = p.objective(x) + 0.5 * float(roughness)
    assert with_sigma.objective(x) == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("band", [3, 0])  # 550 nm (green), 400 nm (violet)
@pytest.mark.parametrize("nonneg", [False, True])
def test_spectral_smoothness_bias_on_a_flat_narrow_band_patch(band: int, nonneg: bool) -> None:
    """A flat 32×32 patch lit by one band (the most narrow-band light the basis holds; 0.2 %
    noise), L2 prior, exact optimum, raw-colour error relative to the brightest channel.
    σ = 0 (the thesis): ≤ 4.5e-3. σ‖S I‖² leaves the mean colour free: without
    non-negativity the colour comes back as at σ = 0 (measured 1–2e-4), where σ‖∇λ I‖² at
    every frequency pulls it 19 % towards a smooth spectrum's colour. With non-negativity
    the only non-negative spectrum of such a colour is rough, so both terms bias it
    (measured green 10 % against 19 %, violet 25 % against 30 %): narrow-band light needs
    σ = 0."""
    rng = np.random.default_rng(5)
    a = ImageFormation(SHAPE, "GBRG", normalised_colour()[None])
    spectrum = np.zeros(a.domain_shape[2])
    spectrum[band] = 1.0
    clean = a.forward(np.broadcast_to(spectrum, a.domain_shape))
    raw = clean + 0.002 * clean.max() * rng.standard_normal(clean.shape)
    l2 = PRIORS["L2"]
    colour = a.colour_matrix
    target = colour @ spectrum

    def error(p: Problem) -> float:
        mean_colour = solve(p, method="exact").latent.mean(axis=(0, 1)) @ colour.T
        return float(np.abs(mean_colour - target).max() / target.max())

    thesis = error(Problem(a, raw, l2, (1e-3,), nonneg))
    ours = error(Problem(a, raw, l2, (1e-3,), nonneg, smoothness=SUGGESTED_SMOOTHNESS))
    terms = (*l2, PriorTerm("spectral", 2))
    every = error(Problem(a, raw, terms, (1e-3, SUGGESTED_SMOOTHNESS), nonneg))
    assert thesis < 5e-3 and every > 0.15
    if nonneg:
        assert 0.05 < ours < 0.9 * every
    else:
        assert ours < 1e-3


@pytest.mark.slow
@pytest.mark.parametrize("prior", ["L1", "Lap1"])
@pytest.mark.parametrize("nonneg", [True, False])
def test_l1_default_solve_reaches_the_optimum_on_128px(prior: str, nonneg: bool) -> None:
    """The issue's optimality check for L1 and Laplacian-L1 priors on a 128×128 simulated
    patch, σ = SUGGESTED_SMOOTHNESS, at the DMC's pick with σ (6.3e-3): the default solve is
    within 1e-4 of the best objective a 1500-iteration solve at ε_rel = 1e-12 visits
    (measured 5.3e-5–6.5e-5, 440–600 iterations, 9–40 s each)."""
    rng = np.random.default_rng(3)
    a = ImageFormation((128, 128), "GBRG", normalised_colour()[None])
    _, raw = noisy_raw(a, rng, noise=0.002)
    terms = PRIORS[prior]
    p = Problem(a, raw, terms, (6.3e-3,) * len(terms), nonneg, smoothness=SUGGESTED_SMOOTHNESS)
    reference = solve(p, rtol=1e-12, max_iter=1500, track_objective=True)
    best = min(reference.report.history)
    default = solve(p)
    assert default.report.converged
    assert -1e-6 < (default.report.objective - best) / best < 1e-4


def test_anderson_rejects_an_extrapolation_that_blows_up() -> None:
    """On y ↦ y/2 + 1 (fixed point 2) Anderson's second step extrapolates to the fixed
    point; when the map's residual there comes out 1e6 (far above 10× the best so far),
    the point is rejected and the iteration resumes from the plain step it replaced."""
    from reconstruction.solve.solvers.anderson import AndersonAcceleration

    def g(y):
        return 0.5 * y + 1.0

    anderson = AndersonAcceleration(3)
    first = anderson.step(np.zeros(4), g(np.zeros(4)))  # no memory yet: the plain step
    np.testing.assert_array_equal(first, np.ones(4))
    second = anderson.step(first, g(first))
    assert anderson.accepted == 1
    np.testing.assert_allclose(second, 2.0, rtol=1e-8)  # exact for a linear map
    resumed = anderson.step(second, second + 1e6)
    assert anderson.accepted == 0
    np.testing.assert_array_equal(resumed, g(first))
