"""The direct solve (:mod:`reconstruction.solve.solvers.direct`): the optimum without ADMM
where that is cheap, ADMM's own result otherwise."""

from __future__ import annotations

import numpy as np
import pytest
from _problems import kkt_violation, noisy_raw, normalised_colour, rig_corner_formation

from reconstruction.model.image_formation import ImageFormation
from reconstruction.model.prior_terms import PRIORS
from reconstruction.model.problem import SUGGESTED_SMOOTHNESS, Problem
from reconstruction.solve.solvers import solve


def test_direct_exact_solve_with_dispersion_and_smoothness(monkeypatch: pytest.MonkeyPatch) -> None:
    """Φ (the rig's corner, up to 2 px) and σ = 1e-3: the direct method reaches the KKT point by
    projected Newton from the initial estimate without any ADMM iteration, within 1e-6 of a
    tight ADMM solve's objective (ε_rel 1e-9, 69 iterations; it stops at the KKT residual
    :data:`DIRECT_KKT_TOLERANCE`, 1e-5) and below the default solve's;
    where the rounds do not settle it is plain ADMM again. However many values start at
    zero: the limit on them (:data:`DIRECT_MAX_ZEROS`) is the dual method's, without Φ."""
    import reconstruction.solve.solvers.direct as direct_module
    import reconstruction.solve.solvers.exact as exact_module

    rng = np.random.default_rng(6)
    a = rig_corner_formation((64, 64))
    _, raw = noisy_raw(a, rng, noise=0.002)
    p = Problem(a, raw, PRIORS["L2"], (4.7e-4,), True, smoothness=SUGGESTED_SMOOTHNESS)
    default = solve(p)
    monkeypatch.setattr(direct_module, "DIRECT_MAX_ZEROS", -1)
    direct = solve(p, method="direct-or-admm")
    tight = solve(p, rtol=1e-9, max_iter=5000)
    assert a.dispersion.max_shift_px > 0.5 and default.report.iterations > 5
    assert direct.report.iterations == 0 and direct.report.polish.status == "optimal"
    assert direct.report.converged and direct.latent.min() >= 0
    assert kkt_violation(p, direct.latent) < 1e-5
    assert direct.report.objective <= tight.report.objective * (1 + 1e-6)  # measured 2.4e-7
    assert direct.report.objective < default.report.objective
    polish = exact_module.polish
    monkeypatch.setattr(exact_module, "polish", lambda *a, **k: polish(*a, **k, max_rounds=1))
    fallback = solve(p, method="direct-or-admm")
    assert fallback.report.polish is None
    assert fallback.report.iterations == default.report.iterations
    assert fallback.report.objective == default.report.objective


def test_direct_exact_solve_without_dispersion(monkeypatch: pytest.MonkeyPatch) -> None:
    """No Φ (a flat or undispersed patch) and σ = 1e-3: the direct method is the dual
    active-set method, with no ADMM iteration, the same image as the exact method, and
    no worse than a tight ADMM solve; with more zeros in the start than
    :data:`DIRECT_MAX_ZEROS` it is plain ADMM again."""
    import reconstruction.solve.solvers.direct as direct_module

    rng = np.random.default_rng(8)
    a = ImageFormation((64, 64), "GBRG", normalised_colour()[None])
    _, raw = noisy_raw(a, rng, noise=0.002)
    p = Problem(a, raw, PRIORS["L2"], (4.7e-4,), True, smoothness=SUGGESTED_SMOOTHNESS)
    direct = solve(p, method="direct-or-admm")
    exact = solve(p, method="exact")
    tight = solve(p, rtol=1e-9, max_iter=5000)
    assert direct.report.iterations == 0 and direct.report.polish.status == "optimal"
    assert direct.latent.min() >= 0 and kkt_violation(p, direct.latent) < 1e-5
    np.testing.assert_array_equal(direct.latent, exact.latent)
    assert direct.report.objective <= tight.report.objective * (1 + 1e-8)
    monkeypatch.setattr(direct_module, "DIRECT_MAX_ZEROS", -1)
    fallback = solve(p, method="direct-or-admm")
    assert fallback.report.polish is None and fallback.report.iterations > 0
    assert fallback.report.objective == solve(p).report.objective
