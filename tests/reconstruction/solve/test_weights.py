"""`reconstruction.solve.weights`: the demosaicing criterion against each reference demosaic."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.interpolate
from _problems import RESPONSE, blobs, normalised_colour

from calibration.multispectral import green_bilinear
from labkit.errors import DataError
from labkit.spectra import camera_response
from reconstruction.baselines import baseline
from reconstruction.model.image_formation import ImageFormation
from reconstruction.model.prior_terms import PRIORS
from reconstruction.model.problem import Problem
from reconstruction.options import parse_weights
from reconstruction.reconstruct import reconstruct
from reconstruction.solve import weights as weights_module
from reconstruction.solve.solvers import solve
from reconstruction.solve.weights import select_weights

CFA = "GBRG"


def textured_problem() -> Problem:
    """A 32² patch of sharp-edged disks (no non-negativity: one exact FFT solve per weight)."""
    rng = np.random.default_rng(5)
    formation = ImageFormation((32, 32), CFA, normalised_colour()[None])
    raw = formation.forward(blobs((32, 32), formation.domain_shape[2], rng, count=8))
    raw = raw + 0.01 * raw.mean() * rng.standard_normal(raw.shape)
    return Problem(formation, raw, PRIORS["L2"], (1.0,), nonneg=False)


def green_distance(problem: Problem, weights: tuple[float, ...], green: np.ndarray) -> float:
    latent = solve(problem.with_weights(weights)).latent
    return float(np.mean(((latent @ problem.formation.colour_matrix.T)[..., 1] - green) ** 2))


@pytest.mark.parametrize("criterion", ["dmc", "dmc-malvar", "dmc-menon"])
def test_each_dmc_scores_against_its_own_demosaic(criterion: str) -> None:
    """The value Algorithm 3 reports for a DMC variant is the mean squared difference between
    the solution's green and that demosaic's green (recomputed here), and the three
    references give different values at the same weight (none silently falls back)."""
    problem = textured_problem()
    selection = select_weights([problem], criterion=criterion)
    method = criterion.partition("-")[2] or "bilinear"
    greens = {
        "bilinear": green_bilinear(problem.raw, CFA),
        "malvar": baseline(problem.raw, "malvar", cfa=CFA)[..., 1],
        "menon": baseline(problem.raw, "menon", cfa=CFA)[..., 1],
    }
    own = green_distance(problem, selection.weights, greens[method])
    assert selection.value == pytest.approx(own, rel=1e-9)
    for other, green in greens.items():
        if other != method:
            assert abs(green_distance(problem, selection.weights, green) - own) > 0.01 * own
    assert 1e-12 < selection.weights[0] < 1.0


def test_an_unknown_demosaic_is_named_in_the_error() -> None:
    with pytest.raises(DataError, match=r"unknown weight criterion 'dmc-ari'.*auto:dmc-menon"):
        parse_weights("auto:dmc-ari", 1)
    with pytest.raises(DataError, match=r"unknown weight criterion 'dmc-ari'.*dmc-menon"):
        select_weights([textured_problem()], criterion="dmc-ari")


def smooth_nonneg_problem() -> Problem:
    """The textured patch, non-negative, with spectral smoothness: an exact optimum exists."""
    problem = textured_problem()
    return Problem(problem.formation, problem.raw, problem.terms, (1.0,), True, smoothness=1e-3)


def test_exact_selection_finds_the_criterion_minimum_of_converged_solves() -> None:
    """With ``exact=True`` the DMC scores exact optima, so the weight chosen is the one whose
    tightly converged ADMM solve (ε_rel 1e-9) scores best: it beats the weights 10 % above
    and below it on such solves, and golden section needs fewer solves than Algorithm 3."""
    problem = smooth_nonneg_problem()
    selection = select_weights([problem], criterion="dmc", exact=True)
    loose = select_weights([problem], criterion="dmc")
    green = green_bilinear(problem.raw, CFA)

    def tight_score(weight: float) -> float:
        latent = solve(problem.with_weights((weight,)), rtol=1e-9, max_iter=20000).latent
        return float(np.mean(((latent @ problem.formation.colour_matrix.T)[..., 1] - green) ** 2))

    chosen = selection.weights[0]
    assert 1e-8 < chosen < 1.0
    at = tight_score(chosen)
    assert at == pytest.approx(selection.value, rel=1e-6)
    assert at < tight_score(1.1 * chosen) and at < tight_score(chosen / 1.1)
    assert selection.solves < loose.solves


def test_exact_search_starts_from_the_nearest_optimum(monkeypatch: pytest.MonkeyPatch) -> None:
    """The edge-guided prior (not circulant: projected Newton, which takes a start): each
    exact solve after the first starts from the nearest weight's optimum, and the search
    chooses the weight it chooses from the initial estimates (1e-3 relative; the optima
    agree to the KKT tolerance), with the same score."""
    problem = textured_problem()
    guided = Problem(
        problem.formation, problem.raw, PRIORS["EdgeL2"], (1.0,), True, smoothness=1e-3
    )
    starts: list[bool] = []
    solve_exact = solve

    def recording(p: Problem, **kwargs: object):
        starts.append(kwargs.get("x0") is not None)
        return solve_exact(p, **kwargs)

    monkeypatch.setattr(weights_module, "solve", recording)
    warm = select_weights([guided], criterion="dmc", exact=True)
    assert starts[0] is False and all(starts[1:]) and len(starts) == warm.solves
    monkeypatch.setattr(weights_module._Evaluator, "_nearest", lambda self, weights: None)
    cold = select_weights([guided], criterion="dmc", exact=True)
    assert warm.weights[0] == pytest.approx(cold.weights[0], rel=1e-3)
    assert warm.value == pytest.approx(cold.value, rel=1e-5)


def test_the_walk_on_two_threads_chooses_what_the_serial_walk_chooses(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """With ``workers=2`` the bracketing walk solves its next two weights at once: the
    search visits the same weights in the same order, scores them alike (exact optima
    reached from other starts) and chooses the same weight; pairs did run on two threads at once,
    and at most one speculative solve per pair is left unused."""
    import threading

    problem = textured_problem()
    guided = Problem(
        problem.formation, problem.raw, PRIORS["EdgeL2"], (1.0,), True, smoothness=1e-3
    )
    serial = select_weights([guided], criterion="dmc", exact=True)
    running, overlapped = set(), []
    lock = threading.Lock()
    solve_exact = weights_module.solve

    def tracking(p: Problem, **kwargs: object):
        with lock:
            running.add(threading.get_ident())
            overlapped.append(len(running) > 1)
        try:
            return solve_exact(p, **kwargs)
        finally:
            with lock:
                running.discard(threading.get_ident())

    monkeypatch.setattr(weights_module, "solve", tracking)
    paired = select_weights([guided], criterion="dmc", exact=True, workers=2)
    assert any(overlapped)
    assert len(paired.path) == len(serial.path)
    for a, b in zip(paired.path, serial.path, strict=True):
        assert a["weights"] == pytest.approx(b["weights"], rel=1e-6)  # measured: 2e-10
        # at the walk's tiny weights only the ridge holds some directions, and the optima
        # reached from other starts differ there within the KKT tolerance (measured 7e-4)
        assert a["value"] == pytest.approx(b["value"], rel=1e-3)
    assert paired.weights == pytest.approx(serial.weights, rel=1e-6)  # measured: 1e-9
    assert paired.value == pytest.approx(serial.value, rel=1e-9)
    assert serial.solves <= paired.solves <= serial.solves + (serial.solves + 1) // 2


@pytest.mark.parametrize("level", [3.0, 65535.0])
def test_mdc_on_a_flat_image_returns_it_flat(level: float) -> None:
    """A flat image fits the data at every weight, so the MDC's misfit range is only the
    loose solves' error; that noise must not pick w = ε, where the data leave the bands
    free and the reconstruction comes back striped (it did: 32398–114950 for 65535)."""
    result = reconstruct(
        np.full((32, 32), level),
        cfa=CFA,
        response=camera_response(RESPONSE),
        weights="auto:mdc",
        patch_px=32,
        pad_px=8,
    )
    assert result.log["weights"]["values"][0] > 1e-6
    np.testing.assert_allclose(result.raw_colour, level, rtol=1e-3)


@pytest.mark.parametrize("criterion", ["dmc", "dmc-menon"])
def test_an_own_start_search_is_brents(criterion: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """A single VTV weight is scored on solves from each weight's own start, a deterministic
    function of the weight, so Brent's method searches it: the weight it picks scores within
    2 % of Algorithm 3's best (measured: 0.5 % and 1e-6) on fewer than 60 % of its solves,
    and the value it reports is that weight's own loose solve scored again."""
    textured = textured_problem()
    problem = Problem(textured.formation, textured.raw, PRIORS["VTV"], (1.0,), True)
    selection = select_weights([problem], criterion=criterion)
    monkeypatch.setattr(
        weights_module,
        "_brent",
        lambda score, count, progress, prefetch=None: weights_module._grid_search(
            score, count, progress
        ),
    )
    grid = select_weights([problem], criterion=criterion)
    assert selection.value <= 1.02 * grid.value
    assert selection.solves < 0.6 * grid.solves
    green = weights_module.reference_green(problem.raw, CFA, criterion)
    latent = solve(
        problem.with_weights(selection.weights), rtol=1e-3, max_iter=300, settle=False
    ).latent
    again = float(np.mean(((latent @ problem.formation.colour_matrix.T)[..., 1] - green) ** 2))
    assert again == pytest.approx(selection.value, rel=1e-12)


# the DMC of the real frames' selection patch at σ = 5e-3 (exact optima), log10 w -12 … 0
REAL_DMC_LOGS = np.arange(-12.0, 0.01, 0.5)
REAL_DMC = [0.01303] * 5 + [
    0.01126, 0.008765, 0.007763, 0.007615, 0.007589, 0.007577, 0.007567, 0.007549, 0.007502,
    0.007239, 0.006539, 0.00509, 0.003179, 0.001694, 0.0009784, 0.0007397, 0.0008347,
    0.002012, 0.008058, 0.02902,
]  # fmt: skip


def search(criterion) -> tuple[float, int]:
    """The single-weight search on `criterion(log10 w)`: (log10 of the pick, evaluations)."""
    solves, (weight,), value = weights_module._brent(
        lambda w: criterion(float(np.log10(w[0]))), 1, None
    )
    assert value == pytest.approx(criterion(float(np.log10(weight))), rel=1e-12)
    return float(np.log10(weight)), solves


def real_dmc(log_weight: float) -> float:
    shape = scipy.interpolate.PchipInterpolator(REAL_DMC_LOGS, np.log(REAL_DMC))
    return float(np.exp(shape(np.clip(log_weight, -12.0, 0.0))))


def test_the_search_passes_over_a_dip_on_the_plateau_of_tiny_weights() -> None:
    """On the real frames at σ = 5e-3 the exact solves' criterion is flat below w ≈ 1e-5
    up to dips of ~0.5 % (the solves' own error there), and Brent's method over [ε, 1e10]
    stopped in one next to its first golden point, w = 1.3e-6 (MRAE 0.51 instead of 0.20).
    With such a dip, the walk from 1e-5 finds the criterion's minimum near 1e-2 instead."""

    def dipped(log_weight: float) -> float:
        return real_dmc(log_weight) * (0.99 if abs(log_weight + 5.9) < 0.1 else 1.0)

    truth = -2.0  # the minimum of the interpolated values (PCHIP keeps the sample's)
    found, solves = search(dipped)
    assert abs(found - truth) < 0.05
    assert solves <= 20


def test_the_search_walks_down_to_a_minimum_below_its_start() -> None:
    """A criterion already rising at the walk's start: it walks down to the minimum."""
    found, _ = search(lambda x: (x + 8.3) ** 2 + 1.0)
    assert abs(found + 8.3) < 0.05


def test_the_search_stops_at_a_bound_where_the_criterion_falls_to_it() -> None:
    found, _ = search(lambda x: -x)
    assert found > 9.9
    found, _ = search(lambda x: x)
    assert found < np.log10(weights_module.LOWEST) + 0.1


def test_of_two_minima_the_search_keeps_the_one_nearest_its_start() -> None:
    """As on the textured scene: a shallow minimum and, 1.6 decades above it, a lower one
    where the image is about as blurred as the bilinear reference; the walk keeps the first,
    as Brent's method over the whole range did there (the better image)."""

    def two(x: float) -> float:
        return min(1.0 + 0.05 * (x + 2.8) ** 2, 0.9 + 0.5 * (x + 1.2) ** 2)

    found, _ = search(two)
    assert abs(found + 2.8) < 0.05
