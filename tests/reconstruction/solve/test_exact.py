"""The exact non-negative solvers (:mod:`reconstruction.solve.solvers.exact` and the active-set
methods it uses) against independent references."""

from __future__ import annotations

import numpy as np
import pytest
from _problems import (
    kkt_violation,
    noisy_raw,
    normalised_colour,
    problem,
    rig_corner_formation,
    smooth_reference,
)

from reconstruction.model.image_formation import ImageFormation
from reconstruction.model.prior_terms import PRIORS
from reconstruction.model.problem import SUGGESTED_SMOOTHNESS, Problem
from reconstruction.solve.solvers import initial_estimate, quadratic_system, solve
from reconstruction.solve.solvers.active_set import polish, solve_periodic


@pytest.mark.parametrize("prior", ["L2", "Lap2", "L2L2"])
def test_exact_solve_reaches_the_optimum_at_small_weights(prior: str) -> None:
    """128×128 simulated patch at the weight the DMC picked on the rig without spectral
    smoothness (4.7e-4), with non-negativity, σ = 0. Measured (L2 / Lap2 / L2L2): ADMM at
    the default tolerance from zeros stops 3.9e-2 / 5.3e-3 / 1.8e-2 above the optimum; the
    dual active-set solve (9 / 45 / 8 rounds, no ADMM) has a KKT residual ≤ 4e-8, is at
    most 4.5e-7 below ADMM plus the projected-Newton finish (which stops at a KKT residual
    of 1e-6), and a 20× longer ADMM solve at rtol 1e-7 is still 4–5e-5 above it."""
    rng = np.random.default_rng(3)
    a = ImageFormation((128, 128), "GBRG", normalised_colour()[None])
    _, raw = noisy_raw(a, rng, noise=0.002)
    terms = PRIORS[prior]
    p = Problem(a, raw, terms, (4.7e-4,) * len(terms), True)
    zeros = np.zeros(p.shape)  # the thesis' start
    plain = solve(p, x0=zeros)
    exact = solve(p, method="exact")
    long = solve(p, x0=zeros, rtol=1e-7, max_iter=20 * plain.report.iterations)
    assert exact.report.polish.status == "optimal" and exact.report.converged
    assert exact.report.iterations == 0  # no ADMM: the dual active-set method settled
    assert exact.latent.min() >= 0 and np.all(np.isfinite(exact.latent))
    assert kkt_violation(p, exact.latent) < 1e-6
    optimum = exact.report.objective
    assert long.report.objective >= optimum * (1 - 1e-9)
    assert (plain.report.objective - optimum) / optimum > 1e-3  # why the exact solve exists
    apply, solver = quadratic_system(p)
    finished, report = polish(p, plain.latent, apply, solver)
    assert report.status == "optimal"
    assert optimum <= p.objective(finished) * (1 + 1e-12)
    assert (p.objective(finished) - optimum) / optimum < 1e-6


@pytest.mark.parametrize("weight", [1e-6, 1e-3])
def test_dual_active_set_solve_against_l_bfgs_b(weight: float) -> None:
    """32×32 patch, L2 prior, non-negativity, at a weight far below the DMC's (1e-6: the
    null space of the mosaic is barely held, K⁻¹ spans ≈ 1e6) and near it (1e-3):
    the dual active-set solve settles (KKT ≤ 1e-6) and its objective is not above an
    independent L-BFGS-B optimum (to 1e-7)."""
    p = problem("L2", weight, True, seed=2)
    x, report = solve_periodic(p, quadratic_system(p)[1])
    assert report.status == "optimal" and report.active > 0
    assert x.min() >= 0 and kkt_violation(p, x) < 1e-6
    reference = smooth_reference(p)
    assert p.objective(x) <= reference * (1 + 1e-7)


def test_dual_active_set_solve_falls_back_to_admm(monkeypatch: pytest.MonkeyPatch) -> None:
    """When the working set outgrows the dense block (here capped at 5 values), solve()
    falls back to ADMM and the projected-Newton finish, and still reaches the optimum."""
    import reconstruction.solve.solvers.active_set as active_set

    p = problem("L2", 1e-6, True, seed=2)
    direct = solve(p, method="exact")
    monkeypatch.setattr(active_set, "ADD_BATCH", 3)
    monkeypatch.setattr(active_set, "MAX_ACTIVE", 5)
    _, report = solve_periodic(p, quadratic_system(p)[1])
    assert report.status == "large"
    # from zeros: ADMM from the initial estimate stops after 5 iterations at this weight,
    # 1e-6, and the finish then runs out of rounds (30) before the active set settles
    fallback = solve(p, x0=np.zeros(p.shape), method="exact")
    assert fallback.report.iterations > 0 and fallback.report.polish.status == "optimal"
    assert fallback.report.objective == pytest.approx(direct.report.objective, rel=1e-7)


def test_finish_corrects_for_the_most_strongly_held_values(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Without Φ the finish corrects its preconditioner for at most :data:`MAX_PINNED`
    values held at zero (here 3, of more than 3 held): it still reaches a KKT point, at
    the objective of the fully corrected finish (both stop at the KKT tolerance: within
    2e-5 at this tiny weight, measured), in more CG steps (the cap is honoured)."""
    import reconstruction.solve.solvers.active_set as active_set

    p = problem("L2", 1e-6, True, seed=2)
    apply, solver = quadratic_system(p)
    start = initial_estimate(p, solver=solver)
    full, full_report = polish(p, start, apply, solver)
    assert full_report.status == "optimal" and full_report.active > 3
    monkeypatch.setattr(active_set, "MAX_PINNED", 3)
    capped, capped_report = polish(p, start, apply, solver)
    assert capped_report.status == "optimal" and kkt_violation(p, capped) < 1e-5
    assert p.objective(capped) == pytest.approx(p.objective(full), rel=1e-4)
    assert sum(capped_report.cg_iterations) > sum(full_report.cg_iterations)


def test_exact_finish_with_dispersion() -> None:
    """Simulated rig's lens, corner patch (Φ up to 2 px): the active-set finish with the
    FFT preconditioner satisfies KKT to 1e-5 in ≤ 30 rounds."""
    rng = np.random.default_rng(6)
    a = rig_corner_formation((64, 64))
    _, raw = noisy_raw(a, rng, noise=0.002)
    p = Problem(a, raw, PRIORS["L2"], (4.7e-4,), True)
    plain = solve(p)
    exact = solve(p, method="exact")
    report = exact.report.polish
    assert a.dispersion.max_shift_px > 0.5
    assert report.status == "optimal" and report.rounds <= 30
    assert kkt_violation(p, exact.latent) < 1e-5
    assert exact.report.objective <= plain.report.objective


def test_finish_with_dispersion_masks_the_preconditioner(monkeypatch: pytest.MonkeyPatch) -> None:
    """With Φ the finish masks the FFT preconditioner to the free values instead of
    correcting it for the active set (no impulse responses, no Cholesky factor), and
    reaches the same optimum as the corrected one: both optimal, objectives within 1e-9,
    iterates within the KKT tolerance's reach (1e-4 of the largest value)."""
    from reconstruction.solve.solvers.fourier import FourierSolver

    rng = np.random.default_rng(6)
    a = rig_corner_formation((64, 64))
    _, raw = noisy_raw(a, rng, noise=0.002)
    p = Problem(a, raw, PRIORS["L2"], (4.7e-4,), True, smoothness=SUGGESTED_SMOOTHNESS)
    apply, solver = quadratic_system(p)
    assert solver.dispersive
    start = initial_estimate(p, solver=solver)
    corrected, corrected_report = polish(p, start, apply, solver, correct_active=True)
    assert corrected_report.active > 0  # there is an active set to correct for

    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("the masked preconditioner needs no impulse responses")

    monkeypatch.setattr(FourierSolver, "impulse_responses", refuse)
    masked, masked_report = polish(p, start, apply, solver)
    assert corrected_report.status == masked_report.status == "optimal"
    assert p.objective(masked) == pytest.approx(p.objective(corrected), rel=1e-9)
    assert np.max(np.abs(masked - corrected)) < 1e-4 * corrected.max()
