"""Simulated reconstruction cases for the benchmarks: render a scene, reconstruct it, score it.

The raw images are noise-added renders of the simulated rig (1 nm spectral grid, exact
pixel areas, the lens' true dispersion); the reconstruction model is coarser (band
centres, bilinear Φ from an analytic ``to_reference`` model of the same lens), so there is
no inverse crime. Errors are measured against the rendered truth (see :func:`errors`).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from labkit.bench.harness import Measurement, peak_rss_mib
from labkit.bench.real_frames import (
    patch_cost,
)
from labkit.rig import SCENE_OPTIONS, load_rig

SHAPE = (344, 408)
VARIANT_SHAPE = (172, 204)
NOISE = 0.002


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
    rig_path: Path,
    shape: tuple[int, int],
    scene: str,
    *,
    seed: int = 1,
    flat_fraction: float = 0,
    illumination: str = "unfiltered",
    max_shift_px: float | None = None,
) -> dict[str, Any]:
    """Raw image, dispersion model and ground truth of one simulated scene.

    `scene` names one of the rig's scenes, or a scene type it does not define (e.g.
    ``"natural"``), built with its defaults. `flat_fraction` > 0 replaces that fraction
    of the columns (on the right) by a flat grey wall, for the adaptive-skipping
    comparison. `illumination` names the light (a filter
    of the rig's slider for narrow-band light); `max_shift_px` replaces the lens' largest
    lateral chromatic aberration (px, corners, 400–700 nm).
    """
    from labkit.cfa import mosaic
    from labkit.sim import SimulatedRig
    from labkit.sim.truth import colour_truth, spectral_truth

    rig = load_rig(rig_path)
    if scene not in rig.sim.scenes and scene in SCENE_OPTIONS:  # a scene type the rig lacks
        rig = rig.with_changes({"sim": {"scenes": {scene: {"type": scene}}}})
    if max_shift_px is not None:
        rig = rig.with_changes({"sim": {"lens": {"max_shift_px": float(max_shift_px)}}})
    world = SimulatedRig(rig, shape=shape)
    colour = colour_truth(world, scene, illumination=illumination)
    irradiance = world.irradiance(scene, illumination).astype(np.float64)
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
        cube = spectral_truth(world, scene, bands_nm, illumination=illumination, scale=exposure)
        cube[wall] = np.nan  # the grey wall has no spectral truth
        return cube

    case = {
        "scene": scene,
        "illumination": illumination,
        "raw": raw,
        "cfa": rig.cfa,
        "response": world.response,
        "model": lens_model(world.lens),
        "colour": colour * exposure,
        "truth": truth,
        "max_shift_px": float(rig.sim.lens.max_shift_px),
        "blur_px": float(rig.sim.lens.blur_sigma_px),
        "colour_model": lambda: channel_model(world, illumination),
    }
    if scene == "colorchecker" and flat_fraction == 0:
        from labkit.sim.scenes import colorchecker_patch_boxes
        from reconstruction.evaluate.residual_aberration import STRIP_PX

        boxes = colorchecker_patch_boxes(world.scene(scene))
        if np.min(boxes[:, 2:] - boxes[:, :2]) > 2 * STRIP_PX + 2:  # patches have centres
            case["boxes"] = boxes
    return case


#: Pitch of the exact keypoints :func:`channel_model` fits, px.
CHANNEL_KEYPOINT_PITCH_PX = 8


def channel_model(world: Any, illumination: str) -> Any:
    """The colour-channel dispersion model (R and B relative to G, ``from_reference``) a
    calibration of the simulated lens would find at best: each channel's displacement is
    the lens' averaged over the light that channel records from a grey scene (camera
    sensitivity × `illumination`'s light), computed exactly on a grid of
    :data:`CHANNEL_KEYPOINT_PITCH_PX` and fitted as a calibration fits one (degree by
    cross-validation). The warping baselines get it: a colour-channel calibration on the
    small simulated rows' own images finds too few keypoints."""
    from calibration.keypoints import DispersionKeypoints
    from calibration.polynomial import fit_polynomial_model
    from labkit.spectra.container import trapezoid_weights

    lens, wavelengths = world.lens, world.wavelengths
    rows, cols = lens.shape
    pitch = CHANNEL_KEYPOINT_PITCH_PX
    gy, gx = np.mgrid[pitch / 2 : rows : pitch, pitch / 2 : cols : pitch]
    x, y = gx.ravel(), gy.ravel()
    sensitivity = world.response.select(["R", "G", "B"]).resample(wavelengths).values
    light = world.light(illumination) * trapezoid_weights(wavelengths)
    weights = sensitivity * light[:, None]
    weights /= weights.sum(axis=0)
    dx, dy = lens.displacement(x[:, None], y[:, None], wavelengths[None, :])
    mean = {c: (dx @ weights[:, i], dy @ weights[:, i]) for i, c in enumerate("RGB")}
    parts = [
        (x, y, mean[c][0] - mean["G"][0], mean[c][1] - mean["G"][1], np.full(x.shape, c))
        for c in "RB"
    ]
    px, py, pdx, pdy, channel = (np.concatenate(v) for v in zip(*parts, strict=True))
    keypoints = DispersionKeypoints(
        px, py, pdx, pdy, reference="G", image_shape=(rows, cols), channel=channel
    )
    return fit_polynomial_model(keypoints, rng=np.random.default_rng(0))


def edge_errors(case: dict[str, Any], raw_colour: np.ndarray) -> dict[str, float]:
    """Residual aberration (§4.4.3): RMSE per channel in the ColorChecker's edge strips."""
    from reconstruction import residual_aberration

    measure = residual_aberration(raw_colour, case["raw"], cfa=case["cfa"], boxes=case["boxes"])
    return {f"edge_rmse_{c}": float(v) for c, v in zip("RGB", measure.edge.rmse, strict=True)}


def strip_errors(
    case: dict[str, Any], result, *, truth: np.ndarray | None = None
) -> dict[str, float]:
    """Spectral RMSE in the ColorChecker's edge strips, centres and surround, relative to
    the mean truth (:func:`reconstruction.spectral_strip_errors`; 8-px border left out and
    registered as in :func:`errors`, whose global RMSE it splits). `truth`: the case's
    truth at the result's bands, if already rendered."""
    from reconstruction import spectral_strip_errors

    if truth is None:
        truth = case["truth"](result.wavelengths_nm)
    keep = np.zeros(truth.shape[:2], bool)
    keep[8:-8, 8:-8] = True
    keep &= np.all(np.isfinite(truth), axis=-1)
    split = spectral_strip_errors(
        np.where(keep[..., None], truth, 0.0), result.spectral, boxes=case["boxes"], mask=keep
    )
    return {
        "spectral_rmse_strips": split.strips,
        "spectral_rmse_centres": split.centres,
        "spectral_rmse_surround": split.surround,
    }


def errors(case: dict[str, Any], result) -> dict[str, float]:
    """Spectral RMSE/MRAE/GOF (registered, 8-px border left out), colour RMSE per channel,
    and on the ColorChecker the edge-strip RMSE per channel (:func:`edge_errors`) and the
    spectral RMSE in the strips, centres and surround (:func:`strip_errors`)."""
    from reconstruction.evaluate.metrics import colour_errors, spectral_errors

    inner = (slice(8, -8), slice(8, -8))
    rendered = case["truth"](result.wavelengths_nm)
    truth = rendered[inner]
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
        **(strip_errors(case, result, truth=rendered) if "boxes" in case else {}),
    }


def run_case(case: dict[str, Any], **options: Any) -> tuple[Any, float]:
    """Reconstruct `case`'s raw image with `options`; the result and the wall time, s."""
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
    """:func:`run_case` in this (child) process, repeated if short; see :func:`run_isolated`."""
    from labkit.bench.harness import repeat_timed

    seconds: list[float] = []
    phases: dict[str, list[float]] = {"weight_s": [], "solve_s": []}

    def once() -> Any:
        result, elapsed = run_case(case, **options)
        seconds.append(elapsed)
        phases["weight_s"].append(float(result.log["weights"]["seconds"]))
        phases["solve_s"].append(float(result.log["solve_seconds"]))
        return result

    result, _, _ = repeat_timed(once, repeats=repeats, short_s=short_s)
    return result, seconds, phases, _peak_rss_self_mib()


def run_isolated(
    case: dict[str, Any], *, repeats: int = 1, short_s: float = 0.0, **options
) -> tuple[Any, list[float], dict[str, list[float]], float]:
    """:func:`run_case` in a fresh process, so its peak memory leaves out the simulation's.

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


def case_bands(case: dict[str, Any], count: int) -> np.ndarray:
    """`count` band centres, nm, evenly spread over the default ones of `case`'s response."""
    from reconstruction import LatentSpace

    default = LatentSpace.spectral(case["response"]).centres_nm
    return np.linspace(default[0], default[-1], count)


def to_measurement(
    name: str,
    seconds: float,
    times: list[float],
    target: float | None,
    case: dict[str, Any],
    result: Any,
    extra: dict[str, Any],
    peak: float | None = None,
) -> Measurement:
    """A bench row for a reconstruction of `case`: time, memory, errors and the solve's log.

    `target` (s) is the time to reach, None for none; ``extra["memory_target_mib"]``, if
    given, must be met too. `peak` (MiB) defaults to this process' peak so far.
    """
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
