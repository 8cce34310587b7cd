"""`labkit bench reconstruct`: spectral reconstruction time against error on the simulated rig.

Targets (issue 53, replacing issue 6's 10 s and the full-size case's 600 s and 4 GiB): a
344×408 raw image, 7 bands, the default options (EdgeL2 prior, non-negativity,
dispersion-aware, weights by the demosaicing criterion) — :data:`TARGET_S` in total,
weight selection included; the full 2448×2048 8-band raw (``full`` only) in
:data:`FULL_TARGET_S` and :data:`FULL_MEMORY_MIB`. The raw
images are noise-added renders of the simulated rig (1 nm spectral grid, exact pixel areas,
the lens' true dispersion); the reconstruction model is coarser (band centres, Φ sampled
from an analytic ``to_reference`` model of the same lens), so there is no inverse crime.

Errors are measured against the rendered truth: the scene's reflectance × light at the band
centres (the light averaged over each band's width, since the lamp has mercury lines that
no band-limited model can hold) in the reference geometry, with vignetting; per-band
registration (4.9) removes the unknown exposure scale. Colour errors compare the raw colour
image with the dispersion-free render.

The main variants (:data:`labkit.bench.real_frames.MAIN_VARIANTS`: the default problem,
σ = 0, the §6.3 reference with and without σ, no non-negativity, the thesis' L2 prior,
the thesis' bilinear Φ, VTV) run on
the simulated ColorChecker and on the real ColorChecker frames of the thesis' lab
(:mod:`labkit.bench.real_frames`), tabulated and plotted side by side.

Besides the target case: solver knobs (prior, band count, tolerance, patch size, with and
without Φ) on one small textured image, plotted as time against error; an 80 %-flat scene
with and without adaptive skipping; and the target case's settings on textured images of
256², 512² (and, with ``full``, 1024² and 2048²) pixels, each in a fresh process, with the
exponent p of time ∝ pixels^p fitted in log–log (issue 7: close to 1, held to ≤ 1.2).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from labkit.bench.harness import Measurement, Plot, Table
from labkit.bench.plots import plot_scaling, plot_time_vs_error
from labkit.bench.real_frames import (
    MAIN_VARIANTS,
    comparison_table,
    patch_cost_table,
    real_measurements,
)
from labkit.bench.reconstruct_cases import (
    NOISE,
    SHAPE,
    VARIANT_SHAPE,
    case_bands,
    edge_errors,
    run_case,
    run_isolated,
    simulated_case,
    to_measurement,
)
from labkit.bench.reconstruct_scaling import (
    ROUTINE_SCALING_SIZES,
    SCALING_SIZES,
    scaling_cases,
    scaling_summary,
    scaling_table,
)

TARGET_S = 3.5
"""Wall time of the 344×408 7-band case with default options on 2 cores, s (issue 53)."""
FULL_TARGET_S = 60.0
"""Wall time of the full 2448×2048 8-band case with default options, s (issue 53)."""
FULL_MEMORY_MIB = 2048.0
"""Peak resident memory of the full-size case's process, MiB (issue 53)."""
TIME_ERROR_PNG = "reconstruct_time_vs_error.png"
REAL_TIME_ERROR_PNG = "reconstruct_real_vs_simulated.png"
REAL_TIME_RMSE_PNG = "reconstruct_real_vs_simulated_rmse.png"
SCALING_PNG = "reconstruct_scaling.png"


def full_run(full: bool | None = None) -> bool:
    """Whether the slow cases run: `full` if given, else ``LABKIT_BENCH_FULL=1``."""
    return os.environ.get("LABKIT_BENCH_FULL") == "1" if full is None else bool(full)


#: The target case's image (rows, cols) and scene, and its name in the bench tables.
MAIN_IMAGE = "344×408 ColorChecker, 7 bands"

#: Solver knobs, each run once on the small textured image at the weight the target case
#: chose (so that they compare solver settings, not weight selection): (label, options,
#: number of bands).
SOLVER_VARIANTS: tuple[tuple[str, dict[str, Any], int], ...] = (
    ("L2, 7 bands, rtol 1e-5 (default tolerance)", {"prior": "L2"}, 7),
    ("L2, 7 bands, rtol 1e-4", {"prior": "L2", "rtol": 1e-4}, 7),
    ("L2, 7 bands, rtol 1e-3", {"prior": "L2", "rtol": 1e-3}, 7),
    ("L2, 5 bands", {"prior": "L2"}, 5),
    ("L2, 9 bands", {"prior": "L2"}, 9),
    ("Lap2, 7 bands", {"prior": "Lap2"}, 7),
    ("L1, 7 bands", {"prior": "L1"}, 7),
    ("L2, 7 bands, no Φ", {"prior": "L2", "dispersion": None}, 7),
    ("L2, 7 bands, solved without Φ, then warped", {"prior": "L2", "correction": "warp"}, 7),
    ("L2, 7 bands, exact (active-set finish)", {"prior": "L2", "exact": True}, 7),
    ("L2, 7 bands, bilinear Φ", {"prior": "L2", "interpolation": "bilinear"}, 7),
    ("L2, 7 bands, σ = 0 (thesis)", {"prior": "L2", "spectral_smoothness": 0.0}, 7),
    ("L2, 7 bands, σ = 0, exact", {"prior": "L2", "spectral_smoothness": 0.0, "exact": True}, 7),
    (
        "VTV (w 0.02), 7 bands, cubic Φ",
        {"prior": "VTV", "interpolation": "cubic", "weights": "fixed:0.02"},
        7,
    ),
    ("L2, 7 bands, patch 128", {"prior": "L2", "patch_px": 128, "pad_px": 16}, 7),
)

#: Adaptive skipping of flat patches, on 344×408 textured scenes at the target case's
#: weight: (label, fraction of the image left flat, options).
SKIPPING_SCENES: tuple[tuple[str, float, dict[str, Any]], ...] = (
    ("fully textured", 0.0, {}),
    ("80 % flat", 0.8, {}),
    ("80 % flat, no skipping", 0.8, {"flat_threshold": None}),
)


def bench_reconstruct(
    rig_path: Path, *, repeats: int = 1, out: Path | None = None, full: bool | None = None
) -> tuple[list[Measurement], list[str | Plot | Table]]:
    """The issue's target case, time-versus-error variants, skipping, and size scaling.

    Parameters
    ----------
    rig_path : Path
        Rig YAML of the simulated rig.
    repeats : int
        Runs of the target case and of short scaling sizes (median reported).
    out : Path, optional
        Report folder: the plots are written there.
    full : bool, optional
        Also run the full-size case and the 1024² and 2048² scaling sizes (minutes);
        default from ``LABKIT_BENCH_FULL=1``.

    Returns
    -------
    cases : list of Measurement
    notes : list of str, Plot and Table
        Shown under the stage's heading.
    """
    full = full_run(full)
    main_case = simulated_case(rig_path, SHAPE, "colorchecker")
    simulated_main = _main_variants(main_case, repeats)
    weights = f"fixed:{simulated_main[0].extra['weights'][0]:.6g}"
    real_main, real_baselines = real_measurements()
    variant_results = _solver_variants(rig_path, weights)
    skipping_results = _skipping_scenes(rig_path, weights, case_bands(main_case, 7))
    full_results = [_full_size_case(rig_path)] if full else []
    per_size = scaling_cases(
        rig_path, SCALING_SIZES if full else ROUTINE_SCALING_SIZES, repeats=repeats
    )
    summary = scaling_summary(per_size)
    results = [
        *simulated_main,
        *real_main,
        *variant_results,
        *skipping_results,
        *full_results,
        *per_size,
        summary,
    ]
    notes = _notes(
        main_case, weights, skipping_results, real_main, simulated_main, real_baselines, full
    )
    notes.append(scaling_table(per_size, summary))
    if out is not None:
        notes += _plots(Path(out), variant_results, real_main, simulated_main, per_size, summary)
    return results, notes


def _case_measurement(
    case: dict[str, Any], name: str, extra: dict[str, Any], **options: Any
) -> Measurement:
    """One run of `case` with `options`, measured without a target."""
    result, seconds = run_case(case, **options)
    return to_measurement(name, seconds, [seconds], None, case, result, extra)


def _main_variants(main_case: dict[str, Any], repeats: int) -> list[Measurement]:
    """The target case (median of `repeats` runs), then the other main variants."""
    options = {"bands": case_bands(main_case, 7), "dispersion": main_case["model"]}
    image = {"image": "408×344", "bands": 7}
    times, result = [], None
    for _ in range(max(1, repeats)):
        result, seconds = run_case(main_case, **options)
        times.append(seconds)
    label = MAIN_VARIANTS[0][0]
    measured = [
        to_measurement(
            f"{MAIN_IMAGE}, EdgeL2, nonneg, Φ, auto:dmc",
            float(np.median(times)),
            times,
            TARGET_S,
            main_case,
            result,
            {**image, "variant": label},
        )
    ]
    for label, extra in MAIN_VARIANTS[1:]:
        measured.append(
            _case_measurement(
                main_case,
                f"{MAIN_IMAGE}, {label}",
                {**image, "variant": label},
                **{**options, **extra},
            )
        )
    return measured


def _solver_variants(rig_path: Path, weights: str) -> list[Measurement]:
    """:data:`SOLVER_VARIANTS` on the small textured image."""
    case = simulated_case(rig_path, VARIANT_SHAPE, "texture")
    return [
        _case_measurement(
            case,
            f"204×172 texture, {name}",
            {"image": "204×172", "bands": count},
            bands=case_bands(case, count),
            **{"dispersion": case["model"], "weights": weights, **options},
        )
        for name, options, count in SOLVER_VARIANTS
    ]


def _skipping_scenes(rig_path: Path, weights: str, bands: np.ndarray) -> list[Measurement]:
    """:data:`SKIPPING_SCENES`, with the target case's bands and weight."""
    measured = []
    for label, fraction, skipping in SKIPPING_SCENES:
        case = simulated_case(rig_path, SHAPE, "texture", flat_fraction=fraction)
        measured.append(
            _case_measurement(
                case,
                f"344×408 texture, {label}",
                {"image": "408×344", "flat_fraction": fraction},
                bands=bands,
                dispersion=case["model"],
                weights=weights,
                prior="L2",
                **skipping,
            )
        )
    return measured


def _full_size_case(rig_path: Path) -> Measurement:
    """The full 2448×2048 ColorChecker with default options, in a fresh process."""
    case = simulated_case(rig_path, (2048, 2448), "colorchecker")
    result, times, _, peak = run_isolated(case, bands=case_bands(case, 8), dispersion=case["model"])
    return to_measurement(
        "2448×2048 ColorChecker, 8 bands, EdgeL2, nonneg, Φ, auto:dmc",
        times[0],
        times,
        FULL_TARGET_S,
        case,
        result,
        {"image": "2448×2048", "bands": 8, "memory_target_mib": FULL_MEMORY_MIB},
        peak,
    )


def _notes(
    main_case: dict[str, Any],
    weights: str,
    skipping_results: list[Measurement],
    real_main: list[Measurement],
    simulated_main: list[Measurement],
    real_baselines: dict[str, Any],
    full: bool,
) -> list[str | Plot | Table]:
    """What the stage's report says under its heading (the scaling table apart)."""
    from reconstruction.evaluate.evaluation import baseline_images

    baselines, _ = baseline_images(main_case["raw"], cfa=main_case["cfa"])
    notes: list[str | Plot | Table] = [
        "Reconstruction inputs: simulated renders (1 nm grid, exact pixel areas, true lens "
        f"dispersion up to {main_case['max_shift_px']:g} px, a lens blur of "
        f"σ = {main_case['blur_px']:g} px; the default rig's is measured on the real frames' "
        "patch edges) plus Gaussian noise of "
        f"{NOISE:g} × the brightest raw value; Φ from an analytic to_reference model of the "
        "same lens. Spectral errors are registered per band and relative to the mean "
        "truth; colour RMSE is relative to the brightest true raw colour.",
        f"Variants reuse the weight the target case chose ({weights}) so that they compare "
        "solver settings, not weight selection.",
        skipping_line(skipping_results[-2], skipping_results[-1]),
        "Residual aberration (edge-strip RMSE R/G/B, ColorChecker rows) of the "
        "demosaicing baselines: "
        + "; ".join(
            f"{method} " + "/".join(f"{v:.4f}" for v in edge_errors(main_case, image).values())
            for method, image in baselines.items()
        )
        + ".",
        "Residual aberration of the baselines on the real frames (the synthetic raw image, "
        "fractions of the raw mean): "
        + "; ".join(
            f"{method} " + "/".join(f"{v:.4f}" for v in values)
            for method, values in real_baselines.items()
        )
        + ".",
        comparison_table(real_main, simulated_main),
        patch_cost_table(real_main, simulated_main),
        "Peak memory: the largest resident set so far of this process or a finished child; "
        "for the full-size case and the scaling sizes, that of the fresh process the "
        "reconstruction ran in (VmHWM), the simulation left out.",
    ]
    if not full:
        notes.append(
            "The full-size 2448×2048 case and the 1024² and 2048² scaling sizes run only with "
            "`labkit bench all`, `--full` or LABKIT_BENCH_FULL=1 (about 6 minutes more on 2 "
            "quiet cores)."
        )
    return notes


def _plots(
    out: Path,
    variant_results: list[Measurement],
    real_main: list[Measurement],
    simulated_main: list[Measurement],
    per_size: list[Measurement],
    summary: Measurement,
) -> list[str | Plot | Table]:
    """The stage's four plots, written into `out`."""
    plot_time_vs_error(
        {"204×172 texture, weight fixed": [_point(m) for m in variant_results]},
        out / TIME_ERROR_PNG,
        title="labkit reconstruct: time against error (prior, bands, rtol, patch, Φ)",
        error_label="spectral RMSE / mean truth",
    )
    plot_time_vs_error(
        {
            "real ColorChecker: patch-centre MRAE (ASD)": [
                (m.seconds, m.extra["mrae"], m.extra["variant"]) for m in real_main
            ],
            "simulated ColorChecker: MRAE per pixel": [
                (m.seconds, m.extra["spectral_mrae"], m.extra["variant"]) for m in simulated_main
            ],
        },
        out / REAL_TIME_ERROR_PNG,
        title="labkit reconstruct: the main variants on real and simulated data",
        error_label="MRAE",
    )
    plot_time_vs_error(
        {
            "real ColorChecker: chart, against the multispectral image": [
                (m.seconds, m.extra["spectral_rmse"], m.extra["variant"]) for m in real_main
            ],
            "simulated ColorChecker: image, against the truth": [
                (m.seconds, m.extra["spectral_rmse_rel"], m.extra["variant"])
                for m in simulated_main
            ],
        },
        out / REAL_TIME_RMSE_PNG,
        title="labkit reconstruct: the main variants, per-pixel spectral error",
        error_label="spectral RMSE / mean truth",
    )
    plot_scaling(
        [m.extra["pixels"] for m in per_size],
        {
            "total (weights included)": (
                [m.seconds for m in per_size],
                summary.extra["exponent"],
            ),
            "patch solves only": (
                [m.extra["solve_s"] for m in per_size],
                summary.extra["exponent_solve"],
            ),
        },
        out / SCALING_PNG,
        title="labkit reconstruct: time against image size (texture, 7 bands)",
    )
    return [
        Plot("Reconstruction: time against spectral error", TIME_ERROR_PNG),
        Plot("Main variants: time against MRAE, real and simulated", REAL_TIME_ERROR_PNG),
        Plot(
            "Main variants: time against per-pixel spectral RMSE, real and simulated",
            REAL_TIME_RMSE_PNG,
        ),
        Plot("Reconstruction: time against image size (log–log)", SCALING_PNG),
    ]


def _point(m: Measurement) -> tuple[float, float, str]:
    name = m.name.split(", ", 1)[-1]
    return m.seconds, m.extra["spectral_rmse_rel"], name


def skipping_line(with_skipping: Measurement, without: Measurement) -> str:
    """One sentence: what adaptive skipping saved on the same scene (time, patches, error).

    Parameters
    ----------
    with_skipping, without : Measurement
        The same scene reconstructed with and without skipping flat patches (``extra``:
        ``patches``, ``flat``, ``spectral_rmse_rel``, ``flat_fraction``).

    Returns
    -------
    str
    """
    saved = 1 - with_skipping.seconds / without.seconds
    e_with = with_skipping.extra["spectral_rmse_rel"]
    e_without = without.extra["spectral_rmse_rel"]
    change = abs(e_with - e_without) / e_without
    return (
        f"Adaptive skipping saved {saved:.0%} of the time on the "
        f"{with_skipping.extra['flat_fraction']:.0%}-flat scene: "
        f"{with_skipping.seconds:.2f} s with skipping, {without.seconds:.2f} s without; "
        f"{with_skipping.extra['flat']} of {with_skipping.extra['patches']} patches skipped "
        f"as flat; spectral RMSE {e_with:.4f} with, {e_without:.4f} without "
        f"({'equal within 1 %' if change <= 0.01 else f'{change:.1%} apart'})."
    )
