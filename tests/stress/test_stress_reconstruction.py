"""Numerical stress of the reconstruction (issue 7): weights from machine epsilon to 1e10,
raw intensities from 1e-8 to 1e8, float32 against float64 raw images, degenerate and tiny
images, and the solvers (FFT, conjugate gradients, ADMM) at the ends of their ranges.

Known answers used:

* a tiny weight leaves the data term alone: the reconstruction's raw colour, mosaiced,
  reproduces the raw image;
* a huge weight of a spatial prior (whose null space is the constant images) gives a
  spatially constant image whose colour matches the per-channel means of the data the
  patch solve sees (the raw image with its reflected overlap);
* the job normalises the raw image first, so its result scales linearly with the raw
  intensity (to rounding);
* a constant (or saturated) raw image is reproduced; an all-zero one gives zero; with
  non-negativity a negative one gives zero.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from _problems import RESPONSE, blobs, normalised_colour
from _stress import EPS, assert_finite, relative_rms
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from labkit.cfa import channel_index, mosaic
from labkit.errors import DataError
from labkit.spectra import camera_response
from reconstruction.model.image_formation import ImageFormation, LatentSpace, build_formation
from reconstruction.model.operators import dot_test
from reconstruction.model.prior_terms import PRIORS
from reconstruction.model.problem import Problem
from reconstruction.reconstruct import reconstruct
from reconstruction.solve.solvers import FourierSolver, conjugate_gradient, solve

RESPONSE_RGB = camera_response(RESPONSE)
SPACE = LatentSpace.spectral(RESPONSE_RGB)
CFA = "GBRG"
SHAPE = (32, 32)
#: Patch settings for one 32×32 patch (no Dask overhead worth mentioning).
ONE_PATCH = {"patch_px": 32, "pad_px": 8}
#: Every prior of Table 3.1 and its term count.
ALL_PRIORS = sorted(PRIORS)


def textured_raw(shape: tuple[int, int] = SHAPE, seed: int = 0) -> np.ndarray:
    """A noise-free raw mosaic of a textured latent image (blobs of random spectra)."""
    a = build_formation(SPACE, shape, CFA)
    return a.forward(blobs(shape, SPACE.channels, np.random.default_rng(seed)))


def run(raw: np.ndarray, **options: object):
    """:func:`reconstruct` on the shared response and layout; every output checked finite."""
    settings_ = {"cfa": CFA, "response": RESPONSE_RGB, "weights": "fixed:0.01", **ONE_PATCH}
    settings_.update(options)
    result = reconstruct(raw, **settings_)
    assert_finite(result.spectral, result.raw_colour)
    return result


def channel_means(raw: np.ndarray) -> np.ndarray:
    """Mean of each CFA channel (R, G, B) of a mosaic."""
    index = channel_index(CFA, raw.shape)
    return np.array([raw[index == c].mean() for c in range(3)])


RAW = textured_raw()


# -- weights: machine epsilon … 1e10 ------------------------------------------------------
def check_weight_limit(prior: str, weight: float, nonneg: bool) -> None:
    """Known answers at the two ends of the weight range (see the module docstring)."""
    count = len(PRIORS[prior])
    result = run(RAW, prior=prior, weights=[weight] * count, nonneg=nonneg, flat_threshold=None)
    colour = result.raw_colour.astype(np.float64)
    if weight <= 1e-8:
        # the data term alone: the raw image comes back (ADMM tolerance 1e-4)
        assert relative_rms(mosaic(colour, CFA), RAW) < 2e-3
    else:
        # an L1 term's split D I = z is met only to the ADMM tolerance (rtol 1e-4): the
        # Laplacian's weakly penalised low frequencies leave ≈ 0.4 % (0.004 % at rtol 1e-6)
        l1 = any(t.norm == 1 for t in PRIORS[prior])
        tolerance = 5e-3 if l1 else 1e-3
        spread = colour.std(axis=(0, 1)) / colour.mean(axis=(0, 1))
        assert np.all(spread < tolerance), f"not constant: relative spread {spread}"
        # the patch is solved with its reflected overlap: those are the data it fits
        padded = np.pad(RAW, ONE_PATCH["pad_px"], mode="reflect")
        np.testing.assert_allclose(
            colour.mean(axis=(0, 1)), channel_means(padded), rtol=2 * tolerance
        )
    if nonneg:
        assert result.spectral.min() >= 0


@pytest.mark.parametrize("weight", [EPS, 1e10], ids=["eps", "1e10"])
@pytest.mark.parametrize("prior", ["L2", "Lap2", "L1", "L2L2"])
def test_weights_at_both_ends_give_the_known_limits(prior: str, weight: float) -> None:
    check_weight_limit(prior, weight, nonneg=True)


@pytest.mark.slow
@pytest.mark.parametrize("nonneg", [True, False], ids=["nonneg", "free"])
@pytest.mark.parametrize("weight", [EPS, 1e-12, 1e-8, 1e6, 1e8, 1e10])
@pytest.mark.parametrize("prior", ALL_PRIORS)
def test_weight_sweep_all_priors(prior: str, weight: float, nonneg: bool) -> None:
    check_weight_limit(prior, weight, nonneg)


@pytest.mark.slow
@pytest.mark.parametrize("prior", ALL_PRIORS)
def test_intermediate_weights_are_finite_and_between_the_limits(prior: str) -> None:
    """Weights 1e-6 … 1e4 (every decade): finite, and the data misfit grows with the weight."""
    count = len(PRIORS[prior])
    misfits = []
    for weight in 10.0 ** np.arange(-6, 5):
        result = run(RAW, prior=prior, weights=[weight] * count, flat_threshold=None)
        misfits.append(relative_rms(mosaic(result.raw_colour.astype(float), CFA), RAW))
    assert misfits[0] < 0.02
    # monotone up to the solver tolerance
    assert all(b >= a - 2e-3 for a, b in itertools.pairwise(misfits)), misfits


# -- intensities 1e-8 … 1e8 and float32 -----------------------------------------------------
@pytest.fixture(scope="module")
def reference_result():
    """The textured raw image at unit scale, reconstructed with a fixed weight."""
    return run(RAW)


@settings(
    deadline=None,
    max_examples=8,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(exponent=st.floats(min_value=-8.0, max_value=8.0))
def test_reconstruction_scales_linearly_with_intensity(reference_result, exponent: float) -> None:
    scale = 10.0**exponent
    result = run(RAW * scale)
    assert relative_rms(result.raw_colour / scale, reference_result.raw_colour) < 1e-5
    assert relative_rms(result.spectral / scale, reference_result.spectral) < 1e-5


@pytest.mark.parametrize("scale", [1e-8, 1.0, 1e8])
def test_float32_raw_agrees_with_float64(reference_result, scale: float) -> None:
    single = run((RAW * scale).astype(np.float32))
    assert relative_rms(single.raw_colour / scale, reference_result.raw_colour) < 1e-3
    assert relative_rms(single.spectral / scale, reference_result.spectral) < 1e-3


@pytest.mark.slow
@settings(deadline=None, max_examples=12, derandomize=True)
@given(
    exponent=st.floats(min_value=-8.0, max_value=8.0),
    criterion=st.sampled_from(["auto:dmc", "auto:mdc"]),
    single=st.booleans(),
)
def test_automatic_weights_are_scale_invariant(exponent: float, criterion: str, single: bool):
    """Algorithm 3 sees normalised data: the same weight, and a linearly scaled image."""
    base = run(RAW, weights=criterion)
    scale = 10.0**exponent
    raw = RAW * scale
    result = run(raw.astype(np.float32) if single else raw, weights=criterion)
    chosen, reference = result.log["weights"]["values"][0], base.log["weights"]["values"][0]
    assert chosen == pytest.approx(reference, rel=1e-2 if single else 1e-6)
    assert relative_rms(result.raw_colour / scale, base.raw_colour) < 1e-3


# -- degenerate images ---------------------------------------------------------------------
@pytest.mark.parametrize(
    ("name", "raw", "expected"),
    [
        ("all-zero", np.zeros(SHAPE), 0.0),
        ("constant", np.full(SHAPE, 7.0), 7.0),
        ("saturated uint16", np.full(SHAPE, 65535, np.uint16), 65535.0),
        ("negative, non-negativity", np.full(SHAPE, -5.0), 0.0),
        ("tiny constant", np.full(SHAPE, 1e-8), 1e-8),
        ("huge constant", np.full(SHAPE, 1e8, np.float32), 1e8),
    ],
)
def test_flat_images_come_back_flat(name: str, raw: np.ndarray, expected: float) -> None:
    result = run(raw)
    np.testing.assert_allclose(result.raw_colour, expected, rtol=1e-3, atol=1e-11)


def test_automatic_weights_on_a_flat_image_reproduce_it() -> None:
    """DMC on a constant image (no texture to weigh): any weight, the constant back."""
    result = run(np.full(SHAPE, 3.0), weights="auto:dmc")
    assert np.isfinite(result.log["weights"]["values"][0])
    np.testing.assert_allclose(result.raw_colour, 3.0, rtol=1e-3)


def test_partly_saturated_image_is_finite_and_reproduced_where_unclipped() -> None:
    """A textured image clipped at its 80th percentile: clipped pixels come back flat."""
    level = float(np.percentile(RAW, 80))
    raw = np.minimum(RAW, level)
    result = run(raw, weights=[1e-6])
    assert relative_rms(mosaic(result.raw_colour.astype(float), CFA), raw) < 2e-3


@pytest.mark.slow
@pytest.mark.parametrize("criterion", ["auto:dmc", "auto:mdc"])
@pytest.mark.parametrize(
    ("raw", "expected"),
    [
        (np.zeros(SHAPE), 0.0),
        (np.full(SHAPE, 65535, np.uint16), 65535.0),
        (np.full(SHAPE, -5.0), 0.0),
    ],
    ids=["zero", "saturated", "negative"],
)
def test_automatic_weights_on_degenerate_images(raw, expected, criterion: str) -> None:
    result = run(raw, weights=criterion)
    assert np.isfinite(result.log["weights"]["values"][0])
    np.testing.assert_allclose(result.raw_colour, expected, rtol=1e-3)


# -- tiny, odd and malformed images --------------------------------------------------------
@pytest.mark.parametrize(
    ("raw", "message"),
    [
        (np.ones((2, 2)), r"2×2 px\) is too small"),
        (np.ones((3, 5)), r"3×5 px; a Bayer mosaic needs an even number"),
        (np.ones((7, 9)), r"7×9 px; a Bayer mosaic needs an even number"),
        (np.ones((1, 1)), r"even number of rows"),
        (np.ones((6, 6)), r"too small to reconstruct \(≥ 8×8 px\)"),
        (np.ones((0, 0)), r"0×0 px\) is too small"),
        (np.ones((0, 8)), r"too small"),
        (np.ones((8, 8)), r"too small for pad_px=8"),
        (np.ones((8, 40)), r"too small for pad_px=8"),
        (np.ones(64), r"must be a 2-D Bayer mosaic"),
        (np.ones((8, 8, 3)), r"must be a 2-D Bayer mosaic"),
        (np.ones((16, 16), complex), r"must hold real numbers, got dtype complex128"),
        (np.full((16, 16), "1"), r"must hold real numbers, got dtype <U1"),
        (np.full((16, 16), 1e31), r"values up to 1e\+31 .* rescale"),
        (np.full((16, 16), -1e-31), r"values up to 1e-31 .* rescale"),
        (np.where(np.eye(16) > 0, np.inf, 1.0), r"16 NaN/Inf pixel\(s\), first at"),
    ],
    ids=lambda v: "x".join(map(str, v.shape)) + str(v.dtype) if isinstance(v, np.ndarray) else "",
)
def test_unusable_images_get_a_clear_error(raw: np.ndarray, message: str) -> None:
    with pytest.raises(DataError, match=message):
        reconstruct(raw, cfa=CFA, response=RESPONSE_RGB, weights="fixed:0.01")


@pytest.mark.parametrize("shape", [(10, 10), (10, 14), (12, 50), (34, 50)])
@pytest.mark.parametrize("weights", ["fixed:0.01", "auto:dmc"])
def test_small_and_odd_multiple_sizes_work(shape: tuple[int, int], weights: str) -> None:
    """Sizes that are not multiples of the patch or the weight patch: a flat image back."""
    result = run(np.full(shape, 2.5), weights=weights)
    assert result.raw_colour.shape == (*shape, 3)
    np.testing.assert_allclose(result.raw_colour, 2.5, rtol=1e-3)


# -- the solvers and operators -------------------------------------------------------------
COLOUR = normalised_colour()
SOLVER_SHAPE = (16, 24)
SOLVER_A = ImageFormation(SOLVER_SHAPE, CFA, COLOUR[None])


def normal_matrix(x: np.ndarray, terms, identity: float) -> np.ndarray:
    """(2AᵀA + Σ c DᵀD + βI) x computed with the operators (no Fourier transform)."""
    out = 2 * SOLVER_A.adjoint(SOLVER_A.forward(x)) + identity * x
    for coefficient, term in terms:
        d = term.difference(x.shape)
        out += coefficient * d.adjoint(d.forward(x))
    return out


@settings(deadline=None, max_examples=25, derandomize=True)
@given(
    prior=st.sampled_from(["L2", "Lap2", "L2L2"]),
    log_coefficient=st.floats(min_value=np.log10(EPS), max_value=10.0),
    log_identity=st.floats(min_value=-12.0, max_value=10.0),
)
def test_fourier_solver_residual_is_small_over_the_whole_range(
    prior: str, log_coefficient: float, log_identity: float
) -> None:
    """Backward stability: ‖K x̂ − b‖ ≤ 1e-5 ‖b‖ even at condition numbers near 1e17.

    The worst corner (identity 1e-12, prior weights ≤ 1e-13) measured 4.5e-6 on one
    machine and below 1e-6 on another: at that condition the last digits are rounding's;
    everywhere above weights 1e-10 the residual is below 1e-8 on both."""
    terms = [(10.0**log_coefficient, t) for t in PRIORS[prior]]
    identity = 10.0**log_identity
    solver = FourierSolver(SOLVER_SHAPE, CFA, COLOUR, terms=terms, identity=identity)
    x = np.random.default_rng(0).standard_normal(SOLVER_A.domain_shape)
    b = normal_matrix(x, terms, identity)
    solution = solver.solve(b)
    assert_finite(solution)
    assert relative_rms(normal_matrix(solution, terms, identity), b) < 1e-5


@pytest.mark.parametrize("coefficient", [0.0, 1.0, 1e10])
def test_fourier_solver_refuses_a_singular_matrix(coefficient: float) -> None:
    """No identity term: the mosaic leaves components undetermined; said, not garbage."""
    with pytest.raises(DataError, match=r"singular.*give identity > 0"):
        FourierSolver(
            SOLVER_SHAPE, CFA, COLOUR, terms=[(coefficient, PRIORS["L2"][0])], identity=0.0
        )


def test_problem_without_ridge_is_refused_not_solved_into_garbage() -> None:
    """Problem(ridge=0) without splits: the single quadratic solve would be singular."""
    problem = Problem(SOLVER_A, textured_raw(SOLVER_SHAPE), PRIORS["L2"], (0.1,), False, 0.0)
    with pytest.raises(DataError, match="singular"):
        solve(problem)


@pytest.mark.parametrize("log_condition", [0, 4, 8, 10])
def test_conjugate_gradients_report_their_true_residual(log_condition: int) -> None:
    """SPD systems of condition 1 … 1e10: finite, and the reported residual is the real one."""
    rng = np.random.default_rng(log_condition)
    q, _ = np.linalg.qr(rng.standard_normal((40, 40)))
    k = (q * np.logspace(0, log_condition, 40)) @ q.T
    x_true = rng.standard_normal(40)
    b = k @ x_true
    result = conjugate_gradient(lambda v: k @ v, b, rtol=1e-10, max_iter=400)
    assert_finite(result.x)
    actual = float(np.linalg.norm(b - k @ result.x) / np.linalg.norm(b))
    assert actual == pytest.approx(result.relative_residual, rel=1e-3, abs=1e-12)
    if log_condition <= 4:
        assert result.relative_residual <= 1e-10
        np.testing.assert_allclose(result.x, x_true, rtol=0, atol=1e-5)


def test_conjugate_gradients_with_zero_right_hand_side_return_zero() -> None:
    result = conjugate_gradient(lambda v: 3.0 * v, np.zeros(7), x0=np.ones(7))
    assert result.iterations == 0 and np.all(result.x == 0)


@pytest.mark.parametrize("scale", [1e-8, 1.0, 1e8])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_image_formation_passes_the_dot_test_at_any_scale(scale: float, dtype: type) -> None:
    a = build_formation(SPACE, (12, 18), CFA)
    result = dot_test(
        a,
        rng=np.random.default_rng(2),
        dtype=dtype,
        sampler=lambda shape: scale * np.random.default_rng(3).standard_normal(shape),
    )
    assert result.relative_error < (1e-5 if dtype == np.float32 else 1e-12)
    assert np.isfinite(result.forward_inner)


@pytest.mark.parametrize("weight", [EPS, 1e10], ids=["eps", "1e10"])
@pytest.mark.parametrize("prior", ["L2", "L1"])
def test_admm_reports_finite_objective_and_residuals(prior: str, weight: float) -> None:
    raw = textured_raw(SOLVER_SHAPE, seed=4)
    problem = Problem(SOLVER_A, raw, PRIORS[prior], (weight,), True)
    solution = solve(problem)
    report = solution.report
    assert_finite(solution.latent, report.primal_residuals, report.dual_residuals)
    assert np.isfinite(report.objective) and report.converged
    assert solution.latent.min() >= 0
    if weight > 1:  # spatially constant
        spread = solution.latent.std(axis=(0, 1)).max() / solution.latent.mean()
        assert spread < 1e-3
