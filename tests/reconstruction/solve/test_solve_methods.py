"""The solvers by name (:data:`reconstruction.solve.solvers.SOLVE_METHODS`) and ADMM as a solver
object (setup / step / run / finalize)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from _problems import noisy_raw, problem, rig_corner_formation

from labkit.errors import ConfigError
from reconstruction.choices import _solver
from reconstruction.model.prior_terms import PRIORS
from reconstruction.model.problem import Problem
from reconstruction.solve.solvers import ADMM, SOLVE_METHODS, solve, solve_admm


def test_every_solver_the_choices_can_pick_is_a_method() -> None:
    picked = {
        _solver(SimpleNamespace(exact=exact, nonneg=nonneg), smoothness, l1).value
        for exact in (None, True, False)
        for nonneg in (True, False)
        for smoothness in (0.0, 1e-3)
        for l1 in (True, False)
    }
    assert picked == set(SOLVE_METHODS) == {"admm", "exact", "direct-or-admm"}


def test_an_unknown_method_is_refused_with_the_names() -> None:
    with pytest.raises(ConfigError, match=r"'newton'.*admm, exact, direct-or-admm"):
        solve(problem("L2", 0.03, True), method="newton")


def dispersed_problem() -> Problem:
    """Φ of the rig's corner (CG I-updates), L2, non-negative, σ = 0: 6 ADMM iterations."""
    a = rig_corner_formation((48, 48))
    _, raw = noisy_raw(a, np.random.default_rng(6), noise=0.002)
    return Problem(a, raw, PRIORS["L2"], (4.7e-4,), True)


@pytest.mark.parametrize("case", ["L1", "VTV signed", "L2 with Φ"])
def test_admm_stepped_by_hand_then_run_is_the_one_call_solve(case: str) -> None:
    """Three steps by hand, then run(): bit for bit the image and report of solve_admm."""
    p = {
        "L1": lambda: problem("L1", 0.01, True),
        "VTV signed": lambda: problem("VTV", 0.01, False),
        "L2 with Φ": dispersed_problem,
    }[case]()
    reference = solve_admm(p)
    admm = ADMM(p)
    admm.setup()
    assert not any(admm.step() for _ in range(3))
    assert admm.iteration == 3
    solution = admm.finalize(admm.run())
    np.testing.assert_array_equal(solution.latent, reference.latent)
    assert solution.report == reference.report
    assert reference.report.iterations > 3


def test_methods_agree_where_nothing_is_split() -> None:
    """A signed L2 problem is one quadratic solve whatever the method."""
    p = problem("L2", 0.03, False)
    images = [solve(p, method=m).latent for m in SOLVE_METHODS]
    for image in images[1:]:
        np.testing.assert_array_equal(image, images[0])
