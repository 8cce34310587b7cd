"""`labkit bench solver`: recording the reconstruction's patch problems and comparing runs."""

from __future__ import annotations

import numpy as np

from labkit.bench.reconstruct_cases import case_bands, simulated_case
from labkit.bench.solver import (
    PERTURBATION,
    perturbed,
    pick_patches,
    recorded_patch_problems,
    stability_row,
    stability_table,
)
from labkit.rig import default_rig_path


def test_patch_problems_are_recorded_as_reconstruct_poses_them() -> None:
    """A 96×112 crop with Φ: one record per patch solve (3 × 3 patches at weights fixed, so
    no weight-selection solves), each with its options; re-solving a recorded problem with
    them gives the iterations reconstruct() saw."""
    case = simulated_case(default_rig_path(), (96, 112), "texture")
    options = {"bands": case_bands(case, 5), "dispersion": case["model"], "weights": "fixed:0.005"}
    recorded = recorded_patch_problems(case, prior="L2", patch_px=32, pad_px=8, **options)
    assert len(recorded) == 3 * 4
    problem, kwargs = recorded[0]
    assert problem.nonneg and all(40 <= n <= 48 for n in problem.raw.shape)  # 32 px + pads
    assert problem.formation.dispersion is not None  # Φ used at the corner
    from reconstruction.solve.solvers import solve

    again = solve(problem, **{k: v for k, v in kwargs.items() if k != "iterations"})
    assert again.report.iterations == kwargs["iterations"]


def test_runs_are_compared_against_a_tight_reference() -> None:
    case = simulated_case(default_rig_path(), (64, 64), "texture")
    options = {"bands": case_bands(case, 5), "dispersion": case["model"], "weights": "fixed:0.005"}
    recorded = recorded_patch_problems(case, prior="L2", patch_px=32, pad_px=8, **options)
    problem, _ = recorded[0]
    changed = perturbed(problem)
    relative = np.abs(changed.raw - problem.raw) / np.abs(problem.raw)
    assert 0 < relative.max() < 10 * PERTURBATION
    row = stability_row("corner", problem, rtol=1e-6)
    assert row.reference_method in ("active set", "long ADMM")
    assert [r.label for r in row.runs] == ["1 thread", "2 threads", "perturbed 1e-15"]
    assert all(-1e-9 < r.gap < 1e-3 for r in row.runs)
    assert row.objective_spread < 1e-4 and row.iteration_spread <= 0.25
    table = stability_table([row], title="t")
    assert len(table.rows[0]) == len(table.columns) == 2 + 3 * 3 + 2


def test_patches_are_picked_corner_most_and_median() -> None:
    records = [(f"p{i}", {"iterations": n}) for i, n in enumerate([1, 30, 90, 10, 50, 1])]
    picked = [index for index, _, _ in pick_patches(records, 3)]
    assert picked == [1, 2, 4]  # first with ADMM iterations, most, median of {10, 30, 50, 90}
    assert [i for i, _, _ in pick_patches(records, 1)] == [1]
    assert pick_patches([("p", {"iterations": 1})], 3) == []
