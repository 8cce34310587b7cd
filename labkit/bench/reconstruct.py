"""`labkit bench reconstruct`: spectral reconstruction time against error on the simulated rig.

Target (issue 6): a 344×408 raw image, 7 bands, L2 prior, non-negativity, dispersion-aware,
weights by the demosaicing criterion — ≤ 10 s in total, weight selection included. The raw
images are noise-added renders of the simulated rig (1 nm spectral grid, exact pixel areas,
the lens' true dispersion); the reconstruction model is coarser (band centres, bilinear Φ
from an analytic ``to_reference`` model of the same lens), so there is no inverse crime.

Errors are measured against the rendered truth: the scene's reflectance × light at the band
centres (the light averaged over each band's width, since the lamp has mercury lines that
no band-limited model can hold) in the reference geometry, with vignetting; per-band
registration (4.9) removes the unknown exposure scale. Colour errors compare the raw colour
image with the dispersion-free render.

The main variants (:data:`labkit.bench.real_frames.MAIN_VARIANTS`: the default problem,
σ = 0, the §6.3 reference with and without σ, no non-negativity, VTV with cubic Φ) run on
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
import time
from pathlib import Path
from typing import Any

import numpy as np

from labkit.bench.harness import Measurement, Plot, Table, fit_exponent, peak_rss_mib
from labkit.bench.plots import plot_scaling, plot_time_vs_error
from labkit.bench.real_frames import (
    MAIN_VARIANTS,
    comparison_table,
    patch_cost,
    patch_cost_table,
    real_measurements,
)
from labkit.rig import load_rig

TARGET_S = 10.0
FULL_TARGET_S = 600.0
FULL_MEMORY_MIB = 4096.0
"""Peak memory target of the full-size case (measured in a fresh process, simulation apart)."""
SHAPE = (344, 408)
VARIANT_SHAPE = (172, 204)
NOISE = 0.002
"""Gaussian noise, fraction of the brightest raw value."""
SCALING_SIZES = (256, 512, 1024, 2048)
"""Sides of the square images of the scaling sweep, px (``full`` runs)."""
ROUTINE_SCALING_SIZES = (256, 512)
"""The sweep's sides without ``full``, px."""
SCALING_EXPONENT_MAX = 1.2
"""Largest fitted exponent p of time ∝ pixels^p that passes."""
SHORT_S = 30.0
"""A scaling size whose first run is shorter than this (s) is repeated (median)."""
TIME_ERROR_PNG = "reconstruct_time_vs_error.png"
REAL_TIME_ERROR_PNG = "reconstruct_real_vs_simulated.png"
SCALING_PNG = "reconstruct_scaling.png"


class LensField:
    """The lens' first-order ``to_reference`` field e(q, λ) = −u(q)(s(λ) − s(λ_ref))."""

    kind = "simulated lens (first order)"

    def __init__(self, lens, reference_nm: float) -> None:
        self.lens = lens
        self.reference = float(lens.spectral_factor(reference_nm))

    def evaluate(self, points: np.ndarray) -> np.ndarray:
        ux, uy = self.lens.radial_field(points[:, 0], points[:, 1])
        s = self.lens.spectral_factor(points[:, 2]) - self.reference
        return -np.stack([ux * s, uy * s], axis=1)

    def to_dict(self) -> dict:
        return {"kind": self.kind}


def lens_model(lens, *, reference_nm: float = 600.0):
    """An analytic ``to_reference`` spectral dispersion model of a simulated lens."""
    from calibration.dispersion_model import CalibratedRegion, DispersionModel

    rows, cols = lens.shape
    x, y = np.meshgrid([0.0, cols - 1.0], [0.0, rows - 1.0])
    return DispersionModel(
        type="simulated",
        variables="xylambda",
        direction="to_reference",
        reference=reference_nm,
        image_shape=(rows, cols),
        fields={"spectral": LensField(lens, reference_nm)},
        region=CalibratedRegion.from_points(x, y, np.array([400.0, 700.0])),
    )


def simulated_case(
    rig_path: Path, shape: tuple[int, int], scene: str, *, seed: int = 1, flat_fraction: float = 0
) -> dict[str, Any]:
    """Raw image, dispersion model and ground truth of one simulated scene.

    `flat_fraction` > 0 replaces that fraction of the columns (on the right) by a flat grey
    wall, for the adaptive-skipping comparison.
    """
    from labkit.cfa import mosaic
    from labkit.sim import SimulatedRig
    from labkit.sim.truth import colour_truth, spectral_truth

    rig = load_rig(rig_path)
    world = SimulatedRig(rig, shape=shape)
    colour = colour_truth(world, scene)
    irradiance = world.irradiance(scene, "unfiltered").astype(np.float64)
    wall = np.zeros(shape, dtype=bool)
    if flat_fraction > 0:
        first = round(shape[1] * (1 - flat_fraction) / 2) * 2
        grey = colour[:, first:].mean(axis=(0, 1))
        colour[:, first:] = grey
        irradiance[:, first:] = mosaic(colour[:, first:], rig.cfa)
        wall[:, first:] = True
    exposure = 1.0 / float(irradiance.mean())
    rng = np.random.default_rng(seed)
    raw = irradiance * exposure
    raw = raw + rng.normal(0.0, NOISE * raw.max(), raw.shape)

    def truth(bands_nm: np.ndarray) -> np.ndarray:
        """Reflectance × band-averaged light at `bands_nm` (rows, cols, n), raw units."""
        cube = spectral_truth(world, scene, bands_nm, scale=exposure)
        cube[wall] = np.nan  # the grey wall has no spectral truth
        return cube

    case = {
        "raw": raw,
        "cfa": rig.cfa,
        "response": world.response,
        "model": lens_model(world.lens),
        "colour": colour * exposure,
        "truth": truth,
        "max_shift_px": float(rig.sim.lens.max_shift_px),
    }
    if scene == "colorchecker" and flat_fraction == 0:
        from labkit.sim.scenes import colorchecker_patch_boxes
        from reconstruction.residual_aberration import STRIP_PX

        boxes = colorchecker_patch_boxes(world.scene(scene))
        if np.min(boxes[:, 2:] - boxes[:, :2]) > 2 * STRIP_PX + 2:  # patches have centres
            case["boxes"] = boxes
    return case


def edge_errors(case: dict[str, Any], raw_colour: np.ndarray) -> dict[str, float]:
    """Residual aberration (§4.4.3): RMSE per channel in the ColorChecker's edge strips."""
    from reconstruction import residual_aberration

    measure = residual_aberration(raw_colour, case["raw"], cfa=case["cfa"], boxes=case["boxes"])
    return {f"edge_rmse_{c}": float(v) for c, v in zip("RGB", measure.edge.rmse, strict=True)}


def errors(case: dict[str, Any], result) -> dict[str, float]:
    """Spectral RMSE/MRAE/GOF (registered, 8-px border left out), colour RMSE per channel,
    and on the ColorChecker the edge-strip RMSE per channel (:func:`edge_errors`)."""
    from reconstruction.metrics import colour_errors, spectral_errors

    inner = (slice(8, -8), slice(8, -8))
    truth = case["truth"](result.wavelengths_nm)[inner]
    estimate = result.spectral[inner].astype(np.float64)
    valid = np.all(np.isfinite(truth), axis=-1)
    spectral = spectral_errors(
        np.where(valid[..., None], truth, 0.0), estimate, mask=valid, ssim=False, register=True
    )
    colour = colour_errors(case["colour"][inner], result.raw_colour[inner], ssim=False)
    peak = float(np.max(case["colour"][inner]))
    return {
        "spectral_rmse_rel": spectral.rmse_global / float(np.mean(truth[valid])),
        "spectral_mrae": spectral.mrae,
        "spectral_gof": spectral.gof,
        **{f"colour_rmse_{c}": float(v) / peak for c, v in zip("RGB", colour.rmse, strict=True)},
        **(edge_errors(case, result.raw_colour) if "boxes" in case else {}),
    }


def _run(case: dict[str, Any], **options) -> tuple[Any, float]:
    from reconstruction import reconstruct

    start = time.perf_counter()
    result = reconstruct(case["raw"], cfa=case["cfa"], response=case["response"], **options)
    return result, time.perf_counter() - start


def _peak_rss_self_mib() -> float:
    """This process' own peak resident set, MiB.

    ``VmHWM``: ``ru_maxrss`` would include the parent's peak, which the kernel carries over
    into a child that was (v)forked and then exec'd (``spawn``).
    """
    import resource

    try:
        with open("/proc/self/status") as status:
            return next(int(ln.split()[1]) for ln in status if ln.startswith("VmHWM")) / 1024
    except (OSError, StopIteration):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _isolated(
    case: dict[str, Any], options: dict[str, Any], repeats: int, short_s: float
) -> tuple[Any, list[float], dict[str, list[float]], float]:
    """:func:`_run` in this (child) process, repeated if short; see :func:`_run_isolated`."""
    from labkit.bench.harness import repeat_timed

    seconds: list[float] = []
    phases: dict[str, list[float]] = {"weight_s": [], "solve_s": []}

    def once() -> Any:
        result, elapsed = _run(case, **options)
        seconds.append(elapsed)
        phases["weight_s"].append(float(result.log["weights"]["seconds"]))
        phases["solve_s"].append(float(result.log["solve_seconds"]))
        return result

    result, _, _ = repeat_timed(once, repeats=repeats, short_s=short_s)
    return result, seconds, phases, _peak_rss_self_mib()


def _run_isolated(
    case: dict[str, Any], *, repeats: int = 1, short_s: float = 0.0, **options
) -> tuple[Any, list[float], dict[str, list[float]], float]:
    """:func:`_run` in a fresh process, so its peak memory leaves out the simulation's.

    Returns
    -------
    result : Reconstruction
        The first run's.
    times : list of float
        Every run's total time, s: `repeats` runs if the first took less than `short_s`
        seconds, else one.
    phases : dict
        ``weight_s`` and ``solve_s``: every run's time in weight selection and in the
        patch solves, s.
    peak : float
        The process' peak resident set, MiB.
    """
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    inputs = {key: case[key] for key in ("raw", "cfa", "response")}  # the truth won't pickle
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=1, mp_context=context) as pool:
        return pool.submit(_isolated, inputs, options, repeats, short_s).result()


def _bands(case: dict[str, Any], count: int) -> np.ndarray:
    from reconstruction import LatentSpace

    default = LatentSpace.spectral(case["response"]).centres_nm
    return np.linspace(default[0], default[-1], count)


def _measurement(name, seconds, times, target, case, result, extra, peak=None) -> Measurement:
    log = result.log
    peak = peak_rss_mib() if peak is None else peak
    passed = None if target is None else seconds <= target
    if passed is not None and "memory_target_mib" in extra:
        passed = passed and peak <= extra["memory_target_mib"]
    return Measurement(
        name,
        seconds,
        times,
        peak,
        target,
        passed,
        {
            **extra,
            **errors(case, result),
            "weights": [float(w) for w in log["weights"]["values"]],
            "weight_s": float(log["weights"]["seconds"]),
            "patches": log["patches"]["count"],
            "phi_used": log["patches"]["phi_used"],
            "flat": log["patches"]["flat"],
            "iterations_median": log["patches"]["iterations_median"],
            "converged": log["patches"]["converged"],
            "patch_cost": patch_cost(log["patch_records"]),
        },
    )


def full_run(full: bool | None = None) -> bool:
    """Whether the slow cases run: `full` if given, else ``LABKIT_BENCH_FULL=1``."""
    return os.environ.get("LABKIT_BENCH_FULL") == "1" if full is None else bool(full)


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
    results: list[Measurement] = []
    main_case = simulated_case(rig_path, SHAPE, "colorchecker")
    bands7 = _bands(main_case, 7)
    main_options = {"bands": bands7, "dispersion": main_case["model"], "prior": "L2"}
    # the default problem, then the main variants on this image and on the real frames
    times, result = [], None
    for _ in range(max(1, repeats)):
        result, seconds = _run(main_case, **main_options)
        times.append(seconds)
    results.append(
        _measurement(
            "344×408 ColorChecker, 7 bands, L2, nonneg, Φ, auto:dmc",
            float(np.median(times)),
            times,
            TARGET_S,
            main_case,
            result,
            {"image": "408×344", "bands": 7, "variant": MAIN_VARIANTS[0][0]},
        )
    )
    weights = f"fixed:{result.log['weights']['values'][0]:.6g}"
    simulated_main = [results[-1]]
    for label, extra in MAIN_VARIANTS[1:]:
        variant, seconds = _run(main_case, **{**main_options, **extra})
        simulated_main.append(
            _measurement(
                f"344×408 ColorChecker, 7 bands, {label}",
                seconds,
                [seconds],
                None,
                main_case,
                variant,
                {"image": "408×344", "bands": 7, "variant": label},
            )
        )
    results += simulated_main[1:]
    real_main, real_baselines = real_measurements()
    results += real_main

    variant_case = simulated_case(rig_path, VARIANT_SHAPE, "texture")
    variants = [
        ("L2, 7 bands, rtol 1e-5 (default)", {"prior": "L2"}, 7),
        ("L2, 7 bands, rtol 1e-4", {"prior": "L2", "rtol": 1e-4}, 7),
        ("L2, 7 bands, rtol 1e-3", {"prior": "L2", "rtol": 1e-3}, 7),
        ("L2, 5 bands", {"prior": "L2"}, 5),
        ("L2, 9 bands", {"prior": "L2"}, 9),
        ("Lap2, 7 bands", {"prior": "Lap2"}, 7),
        ("L1, 7 bands", {"prior": "L1"}, 7),
        ("L2, 7 bands, no Φ", {"prior": "L2", "dispersion": None}, 7),
        ("L2, 7 bands, Φ-free then warp (§3.9.2)", {"prior": "L2", "correction": "warp"}, 7),
        ("L2, 7 bands, exact (active-set finish)", {"prior": "L2", "exact": True}, 7),
        ("L2, 7 bands, cubic Φ", {"prior": "L2", "interpolation": "cubic"}, 7),
        ("L2, 7 bands, σ = 0 (thesis)", {"prior": "L2", "spectral_smoothness": 0.0}, 7),
        (
            "L2, 7 bands, σ = 0, exact",
            {"prior": "L2", "spectral_smoothness": 0.0, "exact": True},
            7,
        ),
        (
            "VTV (w 0.02), 7 bands, cubic Φ",
            {"prior": "VTV", "interpolation": "cubic", "weights": "fixed:0.02"},
            7,
        ),
        ("L2, 7 bands, patch 128", {"prior": "L2", "patch_px": 128, "pad_px": 16}, 7),
    ]
    variant_results: list[Measurement] = []
    for name, options, count in variants:
        options = {"dispersion": variant_case["model"], "weights": weights, **options}
        result, seconds = _run(variant_case, bands=_bands(variant_case, count), **options)
        variant_results.append(
            _measurement(
                f"204×172 texture, {name}",
                seconds,
                [seconds],
                None,
                variant_case,
                result,
                {"image": "204×172", "bands": count},
            )
        )
    results += variant_results

    scenes = (
        ("fully textured", 0.0, {}),
        ("80 % flat", 0.8, {}),
        ("80 % flat, no skipping", 0.8, {"flat_threshold": None}),
    )
    for label, fraction, skipping in scenes:
        case = simulated_case(rig_path, SHAPE, "texture", flat_fraction=fraction)
        result, seconds = _run(
            case, bands=bands7, dispersion=case["model"], weights=weights, prior="L2", **skipping
        )
        results.append(
            _measurement(
                f"344×408 texture, {label}",
                seconds,
                [seconds],
                None,
                case,
                result,
                {"image": "408×344", "flat_fraction": fraction},
            )
        )
    skipping = skipping_line(results[-2], results[-1])

    if full:
        full_case = simulated_case(rig_path, (2048, 2448), "colorchecker")
        result, times, _, peak = _run_isolated(
            full_case, bands=_bands(full_case, 8), dispersion=full_case["model"]
        )
        results.append(
            _measurement(
                "2448×2048 ColorChecker, 8 bands, L2, nonneg, Φ, auto:dmc",
                times[0],
                times,
                FULL_TARGET_S,
                full_case,
                result,
                {"image": "2448×2048", "bands": 8, "memory_target_mib": FULL_MEMORY_MIB},
                peak,
            )
        )
        del full_case

    sizes = SCALING_SIZES if full else ROUTINE_SCALING_SIZES
    per_size = scaling_cases(rig_path, sizes, repeats=repeats)
    summary = scaling_summary(per_size)
    results += [*per_size, summary]

    from reconstruction.evaluation import baseline_images

    baselines, _ = baseline_images(main_case["raw"], cfa=main_case["cfa"])
    notes: list[str | Plot | Table] = [
        "Reconstruction inputs: simulated renders (1 nm grid, exact pixel areas, true lens "
        f"dispersion up to {main_case['max_shift_px']:g} px) plus Gaussian noise of "
        f"{NOISE:g} × the brightest raw value; Φ from an analytic to_reference model of the "
        "same lens. Spectral errors are registered per band (4.9) and relative to the mean "
        "truth; colour RMSE is relative to the brightest true raw colour.",
        f"Variants reuse the weight the target case chose ({weights}) so that they compare "
        "solver settings, not weight selection.",
        skipping,
        "Residual aberration (§4.4.3, edge-strip RMSE R/G/B, ColorChecker rows) of the "
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
    notes.append(scaling_table(per_size, summary))
    if out is not None:
        out = Path(out)
        plot_time_vs_error(
            {"204×172 texture, weight fixed": [_point(m) for m in variant_results]},
            out / TIME_ERROR_PNG,
            title="labkit reconstruct: time against error (prior, bands, rtol, patch, Φ)",
            error_label="spectral RMSE / mean truth",
        )
        notes.append(Plot("Reconstruction: time against spectral error", TIME_ERROR_PNG))
        plot_time_vs_error(
            {
                "real ColorChecker: patch-centre MRAE (ASD)": [
                    (m.seconds, m.extra["mrae"], m.extra["variant"]) for m in real_main
                ],
                "simulated ColorChecker: MRAE per pixel": [
                    (m.seconds, m.extra["spectral_mrae"], m.extra["variant"])
                    for m in simulated_main
                ],
            },
            out / REAL_TIME_ERROR_PNG,
            title="labkit reconstruct: the main variants on real and simulated data",
            error_label="MRAE",
        )
        notes.append(
            Plot("Main variants: time against MRAE, real and simulated", REAL_TIME_ERROR_PNG)
        )
        pixels = [m.extra["pixels"] for m in per_size]
        plot_scaling(
            pixels,
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
        notes.append(Plot("Reconstruction: time against image size (log–log)", SCALING_PNG))
    return results, notes


def _point(m: Measurement) -> tuple[float, float, str]:
    name = m.name.split(", ", 1)[-1]
    return m.seconds, m.extra["spectral_rmse_rel"], name


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
        result, times, phases, peak = _run_isolated(
            case,
            repeats=repeats,
            short_s=SHORT_S,
            bands=_bands(case, 7),
            dispersion=case["model"],
            prior="L2",
        )
        measurement = _measurement(
            f"scaling: {side}×{side} texture, 7 bands, L2, nonneg, Φ, auto:dmc",
            float(np.median(times)),
            times,
            None,
            case,
            result,
            {"image": f"{side}×{side}", "pixels": side * side, "bands": 7},
            peak,
        )
        measurement.extra["weight_s"] = float(np.median(phases["weight_s"]))
        measurement.extra["solve_s"] = float(np.median(phases["solve_s"]))
        cases.append(measurement)
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
