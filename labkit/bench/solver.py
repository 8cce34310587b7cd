"""`labkit bench solver`: is ADMM's answer a property of the problem, or of rounding?

Each case is one solve, run three times: with BLAS at 1 and at 2 threads (labkit's own
setting lifted: ``solve.__wrapped__`` under ``threadpool_limits``), and at 1 thread on the
raw image perturbed by :data:`PERTURBATION` relative. Side by side: the objective, its
distance above a tight reference optimum, and the iterations. Targets (issue 32): every
run within the solver's promise of the reference (1e-4 relative at the default tolerance),
the runs within that of each other, iteration counts within 25 % of each other.

The cases are the patch problems of the reconstruction benchmark's scenes (recorded from
:func:`~reconstruction.reconstruct.reconstruct` as it poses them); the solver's tests run
the same measurement on their own problems
(``tests/reconstruction/solve/test_admm_reproducibility.py``).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from labkit.bench.harness import Measurement, Table

PERTURBATION = 1e-15
"""Relative size of the perturbation of the raw image (a few units in the last place)."""
THREAD_COUNTS = (1, 2)
GAP_TARGET = 1e-4
ITERATION_SPREAD_TARGET = 0.25
REFERENCE_RTOL = 1e-10
REFERENCE_ITERATIONS = 3000
PATCHES_PER_SCENE = 3


@dataclasses.dataclass
class Run:
    """One solve: its objective, distance above the reference (relative), iterations, time."""

    label: str
    objective: float
    gap: float
    iterations: int
    seconds: float
    converged: bool


@dataclasses.dataclass
class StabilityRow:
    """The runs of one problem against its reference optimum."""

    name: str
    reference: float
    reference_method: str
    runs: list[Run]

    @property
    def max_gap(self) -> float:
        """Largest distance above the reference over the runs (relative)."""
        return max(r.gap for r in self.runs)

    @property
    def objective_spread(self) -> float:
        """Largest difference between two runs' objectives, relative to the reference."""
        values = [r.objective for r in self.runs]
        return (max(values) - min(values)) / abs(self.reference)

    @property
    def iteration_spread(self) -> float:
        """(most − fewest) / fewest iterations over the runs."""
        counts = [r.iterations for r in self.runs]
        return (max(counts) - min(counts)) / max(min(counts), 1)

    def to_dict(self) -> dict[str, Any]:
        return {
            "reference": self.reference,
            "reference_method": self.reference_method,
            "max_gap": self.max_gap,
            "objective_spread": self.objective_spread,
            "iteration_spread": self.iteration_spread,
            "runs": [dataclasses.asdict(r) for r in self.runs],
        }


def perturbed(problem, *, relative: float = PERTURBATION, seed: int = 0):
    """`problem` with its raw image multiplied by 1 + `relative` · N(0, 1) per pixel."""
    rng = np.random.default_rng(seed)
    raw = problem.raw * (1.0 + relative * rng.standard_normal(problem.raw.shape))
    return dataclasses.replace(problem, raw=raw)


def reference_optimum(problem) -> tuple[float, str]:
    """A tight optimum of `problem` and how it was found.

    Without splits, the exact quadratic solve. Otherwise the best of: the objective a long
    ADMM solve visits (ε_rel = :data:`REFERENCE_RTOL`, at most
    :data:`REFERENCE_ITERATIONS` iterations) and, for non-negative L2-type priors, the
    exact active-set solve (the ``"exact"`` method). Both are needed: where the
    non-negative optimum is degenerate (σ = 0), a KKT residual of 1e-8 still leaves points
    2e-4 above it, so the active-set answer depends on where it starts.
    """
    from reconstruction.solve.solvers import solve

    l2_type = not problem.has_l1_penalty
    if l2_type and not problem.nonneg:
        return solve(problem, cg_rtol=1e-12, cg_max_iter=500).report.objective, "exact"
    long = solve(
        problem,
        rtol=REFERENCE_RTOL,
        max_iter=REFERENCE_ITERATIONS,
        cg_rtol=1e-10,
        track_objective=True,
    )
    candidates = [(float(min(long.report.history)), "long ADMM")]
    if l2_type:
        exact = solve(problem, method="exact", rtol=1e-8, cg_rtol=1e-10)
        if exact.report.polish is not None and exact.report.polish.status == "optimal":
            candidates.append((exact.report.objective, "active set"))
    return min(candidates)


def stability_row(name: str, problem, *, method: str = "admm", **options: Any) -> StabilityRow:
    """Solve `problem` at each of :data:`THREAD_COUNTS` BLAS threads and once perturbed.

    Parameters
    ----------
    name : str
        Row label.
    problem : Problem
    method : str
        The solver (:data:`~reconstruction.solve.solvers.SOLVE_METHODS`).
    **options
        Its keyword options (rtol, x0, …).
    """
    from reconstruction.solve.solvers import SOLVE_METHODS

    reference, reference_method = reference_optimum(problem)
    unpinned: Callable = SOLVE_METHODS[method].__wrapped__  # type: ignore[attr-defined]
    runs = []
    cases = [(f"{n} thread{'s' if n > 1 else ''}", n, problem) for n in THREAD_COUNTS]
    cases.append((f"perturbed {PERTURBATION:g}", THREAD_COUNTS[0], perturbed(problem)))
    for label, threads, posed in cases:
        with threadpool_limits(threads, user_api="blas"):
            start = time.perf_counter()
            solution = unpinned(posed, **options)
            seconds = time.perf_counter() - start
        objective = solution.report.objective
        runs.append(
            Run(
                label,
                objective,
                (objective - reference) / abs(reference),
                solution.report.iterations,
                seconds,
                solution.report.converged,
            )
        )
    return StabilityRow(name, reference, reference_method, runs)


def stability_table(rows: list[StabilityRow], *, title: str) -> Table:
    """The rows as a Markdown table: objective, gap and iterations per run."""
    labels = [r.label for r in rows[0].runs] if rows else []
    columns = ["case", "reference"]
    for label in labels:
        columns += [f"objective ({label})", "gap", "iterations"]
    columns += ["spread", "iterations ±"]
    cells = []
    for row in rows:
        line = [row.name, f"{row.reference:.7g} ({row.reference_method})"]
        for run in row.runs:
            line += [f"{run.objective:.7g}", f"{run.gap:.1e}", str(run.iterations)]
        line += [f"{row.objective_spread:.1e}", f"{100 * row.iteration_spread:.0f} %"]
        cells.append(line)
    return Table(title, columns, cells)


def recorded_patch_problems(case: dict[str, Any], **options: Any) -> list[tuple[Any, dict]]:
    """(problem, solve options) of every patch solve :func:`reconstruct` makes for `case`."""
    import reconstruction.solve.patches as patches
    from labkit.bench.reconstruct_cases import run_case

    recorded: list[tuple[Any, dict]] = []
    solve = patches.solve

    def recording(problem, **kwargs):
        solution = solve(problem, **kwargs)
        recorded.append((problem, {**kwargs, "iterations": solution.report.iterations}))
        return solution

    patches.solve = recording
    try:
        run_case(case, scheduler="sync", **options)
    finally:
        patches.solve = solve
    return recorded


def pick_patches(recorded: list[tuple[Any, dict]], count: int) -> list[tuple[int, Any, dict]]:
    """The first patch (top-left: the largest Φ), then those with the most and the median
    ADMM iterations (single quadratic solves left out), up to `count`."""
    indexed = [(i, p, o) for i, (p, o) in enumerate(recorded) if o["iterations"] > 1]
    if not indexed:
        return []
    by_iterations = sorted(indexed, key=lambda item: item[2]["iterations"])
    chosen: list[tuple[int, Any, dict]] = []
    for item in (indexed[0], by_iterations[-1], by_iterations[len(by_iterations) // 2]):
        if all(item[0] != c[0] for c in chosen) and len(chosen) < count:
            chosen.append(item)
    return chosen


def bench_solver(
    rig_path: Path, *, repeats: int = 1
) -> tuple[list[Measurement], list[str | Table]]:
    """Reproducibility of the reconstruction benchmark's patch solves (see the module).

    Parameters
    ----------
    rig_path : Path
        Rig YAML of the simulated rig.
    repeats : int
        Unused: each run is one solve (its time is reported).
    """
    from labkit.bench.reconstruct_cases import (
        SHAPE,
        VARIANT_SHAPE,
        case_bands,
        run_case,
        simulated_case,
    )

    colorchecker = simulated_case(rig_path, SHAPE, "colorchecker")
    texture = simulated_case(rig_path, VARIANT_SHAPE, "texture")
    # (label, case, options, gap target): σ = 0 promises no optimum (DEFAULT_RTOL)
    scenes = [
        (
            "344×408 ColorChecker, EdgeL2 (default), Φ, auto:dmc",
            colorchecker,
            {"prior": "EdgeL2", "weights": "auto:dmc"},
            GAP_TARGET,
        ),
        ("344×408 ColorChecker, L2, Φ, auto:dmc", colorchecker, {"prior": "L2"}, GAP_TARGET),
        (
            "204×172 texture, L2, σ = 0",
            texture,
            {"prior": "L2", "spectral_smoothness": 0.0},
            None,
        ),
        ("204×172 texture, Lap2", texture, {"prior": "Lap2"}, GAP_TARGET),
        ("204×172 texture, L1", texture, {"prior": "L1"}, GAP_TARGET),
        (
            "204×172 texture, VTV (w 0.02), cubic Φ",
            texture,
            {"prior": "VTV", "interpolation": "cubic", "weights": "fixed:0.02"},
            GAP_TARGET,
        ),
    ]
    main, _ = run_case(
        colorchecker,
        bands=case_bands(colorchecker, 7),
        dispersion=colorchecker["model"],
        prior="L2",
    )
    weights = f"fixed:{main.log['weights']['values'][0]:.6g}"
    cases: list[Measurement] = []
    rows: list[StabilityRow] = []
    for label, case, options, gap_target in scenes:
        options = {
            "bands": case_bands(case, 7),
            "dispersion": case["model"],
            "weights": weights,
            **options,
        }
        recorded = recorded_patch_problems(case, **options)
        for index, problem, solve_options in pick_patches(recorded, PATCHES_PER_SCENE):
            solve_options = {k: v for k, v in solve_options.items() if k != "iterations"}
            row = stability_row(f"{label}, patch {index}", problem, **solve_options)
            rows.append(row)
            seconds = [r.seconds for r in row.runs]
            extra = {**row.to_dict(), "gap_target": gap_target}
            measurement = Measurement(
                row.name, float(np.median(seconds)), seconds, 0.0, extra=extra
            )
            measurement.passed = (
                (gap_target is None or row.max_gap < gap_target)
                and row.objective_spread < GAP_TARGET
                and row.iteration_spread <= ITERATION_SPREAD_TARGET
            )
            cases.append(measurement)
    notes: list[str | Table] = [
        f"Each patch problem is solved with BLAS at 1 and 2 threads and at 1 thread on its raw "
        f"patch perturbed by {PERTURBATION:g} relative; weights fixed at the ColorChecker's L2 "
        f"DMC pick ({weights}; the EdgeL2 row chooses its own). Targets: gap to the reference "
        f"below {GAP_TARGET:g}, the runs "
        f"within {GAP_TARGET:g} of each other, iterations within "
        f"{100 * ITERATION_SPREAD_TARGET:.0f} %. `passed` in the JSON says whether they "
        "hold. σ = 0 (the thesis' problem) is held to the last two only: its non-negative "
        "optimum is degenerate and its default solve stops early on purpose (DEFAULT_RTOL).",
        stability_table(rows, title="ADMM reproducibility on the benchmark's patch problems"),
    ]
    return cases, notes
