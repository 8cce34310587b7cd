"""The reconstruction's size scaling: the target case's settings on textured renders of
256² … 2048² px, each in a fresh process, and the exponent p of time ∝ pixels^p.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from labkit.bench.harness import Measurement, Table, fit_exponent
from labkit.bench.reconstruct_cases import case_bands, run_isolated, simulated_case, to_measurement

SCALING_SIZES = (256, 512, 1024, 2048)
ROUTINE_SCALING_SIZES = (256, 512)
SCALING_EXPONENT_MAX = 1.2
SHORT_S = 30.0


def scaling_cases(rig_path: Path, sizes: tuple[int, ...], *, repeats: int) -> list[Measurement]:
    """The target case's settings on size×size textured renders, each in a fresh process.

    Parameters
    ----------
    rig_path : Path
        Rig YAML (its sensor must be at least as large as the largest size).
    sizes : tuple of int
        Image sides, px (even).
    repeats : int
        Runs of sizes whose first run takes less than :data:`SHORT_S` (median reported).

    Returns
    -------
    list of Measurement
        One per size; ``extra`` holds ``pixels``, ``weight_s`` and ``solve_s`` (median
        times of weight selection and of the patch solves, s) and the errors of
        :func:`errors`.
    """
    cases = []
    for side in sizes:
        case = simulated_case(rig_path, (side, side), "texture")
        result, times, phases, peak = run_isolated(
            case,
            repeats=repeats,
            short_s=SHORT_S,
            bands=case_bands(case, 7),
            dispersion=case["model"],
        )
        measured = to_measurement(
            f"scaling: {side}×{side} texture, 7 bands, EdgeL2, nonneg, Φ, auto:dmc",
            float(np.median(times)),
            times,
            None,
            case,
            result,
            {"image": f"{side}×{side}", "pixels": side * side, "bands": 7},
            peak,
        )
        measured.extra["weight_s"] = float(np.median(phases["weight_s"]))
        measured.extra["solve_s"] = float(np.median(phases["solve_s"]))
        cases.append(measured)
        del case, result
    return cases


def scaling_summary(per_size: list[Measurement]) -> Measurement:
    """The fitted exponents p of time ∝ pixels^p over the scaling cases, held to ≤ 1.2.

    Parameters
    ----------
    per_size : list of Measurement
        :func:`scaling_cases` output (``extra``: ``pixels``, ``solve_s``), ≥ 2 sizes.

    Returns
    -------
    Measurement
        ``seconds``: the sum of the sizes' median times, s; ``times``: those medians;
        ``passed``: both the total-time and the solve-only exponent ≤
        :data:`SCALING_EXPONENT_MAX`; ``extra``: ``exponent``, ``exponent_solve``,
        ``exponent_max``, ``images``, ``seconds``, ``spectral_rmse_rel``.
    """
    pixels = [m.extra["pixels"] for m in per_size]
    seconds = [m.seconds for m in per_size]
    exponent = fit_exponent(pixels, seconds)
    exponent_solve = fit_exponent(pixels, [m.extra["solve_s"] for m in per_size])
    first, last = per_size[0].extra["image"], per_size[-1].extra["image"]
    return Measurement(
        f"scaling: time ∝ pixels^p, {first} … {last}",
        float(sum(seconds)),
        seconds,
        max(m.peak_mib for m in per_size),
        None,
        max(exponent, exponent_solve) <= SCALING_EXPONENT_MAX,
        {
            "exponent": exponent,
            "exponent_solve": exponent_solve,
            "exponent_max": SCALING_EXPONENT_MAX,
            "images": [m.extra["image"] for m in per_size],
            "seconds": seconds,
            "spectral_rmse_rel": [m.extra["spectral_rmse_rel"] for m in per_size],
        },
    )


def scaling_table(per_size: list[Measurement], summary: Measurement) -> Table:
    """The scaling cases as a Markdown table, the fitted exponents in its title line."""
    extra = summary.extra
    verdict = "pass" if summary.passed else "**FAIL**"
    title = (
        f"Time against image size (texture scene, the target case's settings, each size in a "
        f"fresh process): fitted exponent p = {extra['exponent']:.3f} for the total time, "
        f"{extra['exponent_solve']:.3f} for the patch solves alone (least squares in "
        f"log–log, {extra['images'][0]} … {extra['images'][-1]}); "
        f"{verdict} (≤ {extra['exponent_max']:g})."
    )
    rows = [
        [
            m.extra["image"],
            f"{m.extra['pixels']:,}",
            f"{m.seconds:.2f}",
            str(len(m.times)),
            f"{m.extra['weight_s']:.2f}",
            f"{m.extra['solve_s']:.2f}",
            f"{m.peak_mib:.0f}",
            f"{m.extra['spectral_rmse_rel']:.4f}",
            f"{m.extra['patches']} ({m.extra['flat']} flat)",
        ]
        for m in per_size
    ]
    columns = [
        "image",
        "pixels",
        "median time (s)",
        "runs",
        "weights (s)",
        "solve (s)",
        "peak memory (MiB)",
        "spectral RMSE",
        "patches",
    ]
    return Table(title, columns, rows)
