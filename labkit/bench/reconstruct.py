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
"""

from __future__ import annotations

import io
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from labkit.bench.harness import Measurement, peak_rss_mib
from labkit.rig import load_rig

TARGET_S = 10.0
FULL_TARGET_S = 600.0
FULL_MEMORY_MIB = 4096.0
"""Peak memory target of the full-size case (measured in a fresh process, simulation apart)."""
SHAPE = (344, 408)
VARIANT_SHAPE = (172, 204)
NOISE = 0.002
"""Gaussian noise, fraction of the brightest raw value."""


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

    rig = load_rig(rig_path)
    world = SimulatedRig(rig, shape=shape)
    scene_obj = world.scene(scene)
    light = world.light("unfiltered")
    wavelengths = world.wavelengths
    reflect = scene_obj.materials.resample(wavelengths, extrapolate="constant").values  # (f, K)
    coverage = scene_obj.coverage_image(shape).astype(np.float64)  # (rows, cols, K)
    vignetting = world.lens.vignetting_map()[..., None]
    q = world.response.select(["R", "G", "B"]).resample(wavelengths).values  # (f, 3)
    step = np.gradient(wavelengths)
    colour = (coverage @ ((reflect * (light * step)[:, None]).T @ q)) * vignetting
    irradiance = world.irradiance(scene, "unfiltered").astype(np.float64)
    if flat_fraction > 0:
        first = round(shape[1] * (1 - flat_fraction) / 2) * 2
        grey = colour[:, first:].mean(axis=(0, 1))
        colour[:, first:] = grey
        irradiance[:, first:] = mosaic(colour[:, first:], rig.cfa)
        coverage[:, first:] = np.nan  # marks the wall for the spectral truth
    exposure = 1.0 / float(irradiance.mean())
    rng = np.random.default_rng(seed)
    raw = irradiance * exposure
    raw = raw + rng.normal(0.0, NOISE * raw.max(), raw.shape)

    def truth(bands_nm: np.ndarray) -> np.ndarray:
        """Reflectance × band-averaged light at `bands_nm` (rows, cols, n), raw units."""
        half = 0.5 * float(np.mean(np.diff(bands_nm)))
        light_at = np.array(
            [light[(wavelengths >= b - half) & (wavelengths <= b + half)].mean() for b in bands_nm]
        )
        spectra = np.stack([np.interp(bands_nm, wavelengths, r) for r in reflect.T])  # (K, n)
        cube = np.nan_to_num(coverage) @ (spectra * light_at)
        cube[np.isnan(coverage[..., 0])] = np.nan  # the grey wall has no spectral truth
        return cube * vignetting * exposure

    return {
        "raw": raw,
        "cfa": rig.cfa,
        "response": world.response,
        "model": lens_model(world.lens),
        "colour": colour * exposure,
        "truth": truth,
        "max_shift_px": float(rig.sim.lens.max_shift_px),
    }


def errors(case: dict[str, Any], result) -> dict[str, float]:
    """Spectral RMSE/MRAE/GOF (registered, 8-px border left out) and colour RMSE per channel."""
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
    }


def _run(case: dict[str, Any], **options) -> tuple[Any, float]:
    from reconstruction import reconstruct

    start = time.perf_counter()
    result = reconstruct(case["raw"], cfa=case["cfa"], response=case["response"], **options)
    return result, time.perf_counter() - start


def _isolated(case: dict[str, Any], options: dict[str, Any]) -> tuple[Any, float, float]:
    """:func:`_run` in this (child) process, plus this process' peak RSS, MiB."""
    import resource

    result, seconds = _run(case, **options)
    return result, seconds, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _run_isolated(case: dict[str, Any], **options) -> tuple[Any, float, float]:
    """:func:`_run` in a fresh process, so its peak memory leaves out the simulation's."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    inputs = {key: case[key] for key in ("raw", "cfa", "response")}  # the truth won't pickle
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=1, mp_context=context) as pool:
        return pool.submit(_isolated, inputs, options).result()


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
        },
    )


def bench_reconstruct(
    rig_path: Path, *, repeats: int = 1, out: Path | None = None
) -> tuple[list[Measurement], list[str]]:
    """The issue's target case, time-versus-error variants, and flat-versus-textured scenes."""
    results: list[Measurement] = []
    main_case = simulated_case(rig_path, SHAPE, "colorchecker")
    bands7 = _bands(main_case, 7)
    main_options = {"bands": bands7, "dispersion": main_case["model"], "prior": "L2"}
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
            {"image": "408×344", "bands": 7},
        )
    )
    weights = f"fixed:{result.log['weights']['values'][0]:.6g}"

    variant_case = simulated_case(rig_path, VARIANT_SHAPE, "texture")
    variants = [
        ("L2, 7 bands, rtol 1e-4", {"prior": "L2"}, 7),
        ("L2, 7 bands, rtol 1e-3", {"prior": "L2", "rtol": 1e-3}, 7),
        ("L2, 7 bands, rtol 1e-5", {"prior": "L2", "rtol": 1e-5}, 7),
        ("L2, 5 bands", {"prior": "L2"}, 5),
        ("L2, 9 bands", {"prior": "L2"}, 9),
        ("Lap2, 7 bands", {"prior": "Lap2"}, 7),
        ("L1, 7 bands", {"prior": "L1"}, 7),
        ("L2, 7 bands, no Φ", {"prior": "L2", "dispersion": None}, 7),
        ("L2, 7 bands, patch 128", {"prior": "L2", "patch_px": 128, "pad_px": 16}, 7),
    ]
    for name, options, count in variants:
        options = {"dispersion": variant_case["model"], "weights": weights, **options}
        result, seconds = _run(variant_case, bands=_bands(variant_case, count), **options)
        results.append(
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

    if os.environ.get("LABKIT_BENCH_FULL") == "1":
        full = simulated_case(rig_path, (2048, 2448), "colorchecker")
        result, seconds, peak = _run_isolated(full, bands=_bands(full, 8), dispersion=full["model"])
        results.append(
            _measurement(
                "2448×2048 ColorChecker, 8 bands, L2, nonneg, Φ, auto:dmc",
                seconds,
                [seconds],
                FULL_TARGET_S,
                full,
                result,
                {"image": "2448×2048", "bands": 8, "memory_target_mib": FULL_MEMORY_MIB},
                peak,
            )
        )
    notes = [
        "Reconstruction inputs: simulated renders (1 nm grid, exact pixel areas, true lens "
        f"dispersion up to {main_case['max_shift_px']:g} px) plus Gaussian noise of "
        f"{NOISE:g} × the brightest raw value; Φ from an analytic to_reference model of the "
        "same lens. Spectral errors are registered per band (4.9) and relative to the mean "
        "truth; colour RMSE is relative to the brightest true raw colour.",
        f"Variants reuse the weight the target case chose ({weights}) so that they compare "
        "solver settings, not weight selection.",
    ]
    if os.environ.get("LABKIT_BENCH_FULL") != "1":
        notes.append(
            "The full-size 2448×2048 case runs only with LABKIT_BENCH_FULL=1 (about 10 minutes)."
        )
    if out is not None:
        notes.append(f"Time against error: {_plot(results, Path(out))}")
    return results, notes


def _plot(results: list[Measurement], out: Path) -> str:
    """Scatter of time against spectral error; returns the file name."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from labkit.io.atomic import atomic_write

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for m in results:
        ax.scatter(m.seconds, m.extra["spectral_rmse_rel"])
        ax.annotate(m.name, (m.seconds, m.extra["spectral_rmse_rel"]), fontsize=6)
    ax.set_xscale("log")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("spectral RMSE / mean truth")
    ax.set_title("labkit reconstruct: time against error")
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=120)
    plt.close(fig)
    with atomic_write(out / "reconstruct_time_vs_error.png") as handle:
        handle.write(buffer.getvalue())
    return "reconstruct_time_vs_error.png"
