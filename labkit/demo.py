"""`labkit demo`: the main job on the simulated rig, end to end, with an HTML report.

1. **Capture** with the thesis protocol (auto-bracketed exposures, dark frames): the disk
   pattern under every illumination (for calibration), the ColorChecker and the textured
   scene unfiltered (to reconstruct).
2. **HDR**: merge every bracket (thesis Algorithm 11).
3. **Calibrate** lateral chromatic aberration from the disks: a spectral ``to_reference``
   model for reconstruction and a colour-channel ``from_reference`` model for the warping
   baselines; both compared with the simulated lens.
4. **Reconstruct** the ColorChecker (plain, the §6.3 mean-colour variant and the §3.9.2
   variant that warps after a dispersion-free solve) and the textured scene.
5. **Evaluate** against the simulator's ground truth and the baselines (bilinear, Malvar,
   Menon, each with and without channel warping): residual aberration (§4.4.3), colour
   and spectral errors.
6. **Report**: ``report.html`` and ``report.md`` with previews, plots, crops and tables;
   ``results.json`` with every figure.

The sensor is cropped to :data:`DEMO_SHAPE` (:data:`QUICK_SHAPE` with ``quick``) so that
the whole job runs on a laptop (each stage's time is in the report).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from labkit.demo_steps import (
    DispersionModels,
    SavedReconstruction,
    Stages,
    method_figures,
    reconstruct_and_save,
    reconstruction_notes,
    save_models,
    stage_table,
)
from labkit.io import write_text_atomic
from labkit.io.tiff import json_default
from labkit.plots import (
    plot_dispersion,
    plot_patch_spectra,
    plot_rig_spectra,
)
from labkit.report import Report
from labkit.rig import Rig, default_rig_path, load_rig
from labkit.sim.plans import simulated_plans

if TYPE_CHECKING:
    from reconstruction import Evaluation

DEMO_SHAPE = (768, 1024)
"""Sensor size of the demo, (rows, cols) px."""
QUICK_SHAPE = (256, 320)
"""Sensor size of ``--quick``, (rows, cols) px."""
RECONSTRUCTED = ("colorchecker", "texture")
SPECTRA_PATCHES = (0, 6, 11, 13, 14, 18)
"""ColorChecker patches whose spectra are plotted (chart order)."""
PATCH_NAMES = (
    "dark skin", "light skin", "blue sky", "foliage", "blue flower", "bluish green",
    "orange", "purplish blue", "moderate red", "purple", "yellow green", "orange yellow",
    "blue", "green", "red", "yellow", "magenta", "cyan",
    "white", "neutral 8", "neutral 6.5", "neutral 5", "neutral 3.5", "black",
)  # fmt: skip


def run_demo(out: str | Path, *, rig_path: str | Path | None = None, quick: bool = False) -> Path:
    """Run the whole job on the simulated rig into `out`; return the path of ``report.html``.

    Parameters
    ----------
    out : str or Path
        Output folder (created; existing demo outputs in it are replaced).
    rig_path : str or Path, optional
        A simulated rig YAML (default: the embedded ``rigs/simulated.yaml``).
    quick : bool
        A small sensor (:data:`QUICK_SHAPE`) for a fast check.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rig_file = Path(rig_path) if rig_path else default_rig_path()
    shape = QUICK_SHAPE if quick else DEMO_SHAPE
    rigs = simulated_plans(load_rig(rig_file), shape, scenes=RECONSTRUCTED)
    results: dict[str, Any] = {"shape": list(shape), "rig": str(rig_file), "quick": quick}
    report = Report(f"labkit demo — {rigs['calibration'].name}")
    stage = Stages(5, "demo")
    captures = stage("capture", lambda: _capture(rigs, out))
    stage("hdr", lambda: _hdr(out))
    models = stage("calibrate", lambda: _calibrate(rigs["calibration"], out))
    recons = stage("reconstruct", lambda: _reconstruct(rigs["calibration"], out, models))
    evaluations = stage(
        "evaluate", lambda: _evaluate(rigs["calibration"], out, models, recons, results)
    )
    stage.close()
    times = stage.seconds
    results["seconds"] = times
    results["capture"] = {name: capture.as_dict() for name, capture in captures.items()}
    results["calibration"] = models.summary
    results["reconstruction"] = {name: r.saved.summary for name, r in recons.items()}
    from labkit.sim import SimulatedRig

    world = SimulatedRig(rigs["calibration"])
    plot_rig_spectra(world, out / "rig_spectra.png")
    plot_dispersion(world.lens, [450.0, 500.0, 650.0], out / "lens_dispersion.png")
    _write_report(report, rigs, rig_file, shape, times, captures, models, recons, evaluations)
    write_text_atomic(
        out / "results.json", json.dumps(results, indent=1, default=json_default) + "\n"
    )
    _, page = report.write(out)
    return page


@dataclass(frozen=True)
class CaptureSummary:
    """One plan's capture.

    Attributes
    ----------
    frames, dark_frames : int
        Frames recorded, dark frames among them.
    seconds : float
        The capture's wall time, s.
    exposures_s : dict of str to list of float
        The bracket auto-bracketing chose for each ``scene / illumination``, s.
    """

    frames: int
    dark_frames: int
    seconds: float
    exposures_s: dict[str, list[float]]

    def as_dict(self) -> dict[str, Any]:
        """The fields as a JSON-ready dictionary."""
        return asdict(self)


@dataclass(frozen=True)
class SceneReconstruction:
    """One reconstruction of a scene's raw image, saved."""

    scene: str
    raw: np.ndarray
    cfa: str
    saved: SavedReconstruction


@dataclass(frozen=True)
class SceneEvaluation:
    """One scene's scoreboard and the report's figures of it."""

    evaluation: Evaluation
    figures: dict[str, Any]


def _capture(rigs: dict[str, Rig], out: Path) -> dict[str, CaptureSummary]:
    from labkit.protocol import Engine
    from labkit.protocol.hardware import open_hardware
    from labkit.session import Session

    summary = {}
    for name, rig in rigs.items():
        session, _ = Session.open_for(out / "sessions" / name, rig)
        with open_hardware(rig, fast=True) as hw:
            report = Engine(rig, hw.camera, hw.slider, hw.stage, session).run()
        records = list(Session.open(out / "sessions" / name).records.values())
        exposures: dict[str, list[float]] = {}
        for record in records:
            if not record["dark"]:
                key = f"{record['scene']} / {record['illumination']}"
                exposures.setdefault(key, []).append(record["exposure_s"])
        summary[name] = CaptureSummary(
            frames=len(records),
            dark_frames=sum(bool(r["dark"]) for r in records),
            seconds=report.elapsed_s,
            exposures_s={k: sorted(set(v)) for k, v in exposures.items()},
        )
    return summary


def _hdr(out: Path) -> None:
    from labkit.hdr import run_hdr

    sessions = [out / "sessions" / name for name in ("calibration", "scenes")]
    run_hdr(sessions, out / "hdr", previews=True)


def _calibrate(rig: Rig, out: Path) -> DispersionModels:
    from calibration import load_scene_hdr
    from calibration.bands import filter_bands
    from calibration.dispersion_calibration import calibrate_dispersion
    from labkit.sim import SimulatedRig
    from labkit.sim.truth import model_error

    images = load_scene_hdr(out / "hdr", "disks")
    bands = filter_bands(rig, images=images)
    spectral = calibrate_dispersion(
        images, reference="600", bands=bands, direction="to_reference", workers=2
    )
    colour = calibrate_dispersion(images, reference="G", bands=bands, workers=2)
    summary = save_models(spectral, colour, out / "calibration")
    lens = SimulatedRig(rig).lens
    used = summary["spectral"]["bands_used_nm"]
    grid = sorted({*used, *np.arange(np.ceil(used[0] / 5) * 5, used[-1], 5.0).tolist()})
    error = model_error(spectral.model, lens, float(spectral.model.reference), grid)
    summary["spectral"]["error_vs_lens_px"] = error
    return DispersionModels(spectral.model, colour.model, summary)


def _reconstruct(rig: Rig, out: Path, models: DispersionModels) -> dict[str, SceneReconstruction]:
    from labkit.io import read_raw_exr
    from labkit.sim import SimulatedRig

    response = SimulatedRig(rig).response
    jobs = [(scene, scene, scene, {}) for scene in RECONSTRUCTED] + [
        (
            "colorchecker",
            "colorchecker (reference spectrum from the mean colour)",
            "colorchecker_mean_colour",
            {"reference": "mean-colour"},
        ),
        (
            "colorchecker",
            "colorchecker (solved without the dispersion, then warped)",
            "colorchecker_warp",
            {"correction": "warp"},
        ),
    ]
    hdr = out / "hdr"
    images = {scene: read_raw_exr(hdr / scene / "unfiltered.exr") for scene in RECONSTRUCTED}
    results = {}
    for scene, name, slug, variant in jobs:
        image = images[scene]
        saved = reconstruct_and_save(
            image.raw,
            out / "reconstruction" / slug,
            name=name,
            cfa=image.cfa,
            response=response,
            dispersion=models.spectral,
            **variant,
        )
        results[name] = SceneReconstruction(scene, image.raw, image.cfa, saved)
    return results


def _evaluate(
    rig: Rig,
    out: Path,
    models: DispersionModels,
    recons: dict[str, SceneReconstruction],
    results: dict[str, Any],
) -> dict[str, SceneEvaluation]:
    from labkit.sim import SimulatedRig, colorchecker_patch_boxes
    from labkit.sim.truth import colour_truth, spectral_truth
    from reconstruction import baseline_images, evaluate

    world = SimulatedRig(rig)
    evaluations = {}
    results["evaluation"] = {}
    for scene in RECONSTRUCTED:
        of_scene = {n: r for n, r in recons.items() if r.scene == scene}
        first = next(iter(of_scene.values()))
        raw, cfa = first.raw, first.cfa
        ours = {n: r.saved for n, r in of_scene.items()}
        images, seconds = baseline_images(raw, cfa=cfa, colour_dispersion=models.colour)
        for name, r in ours.items():
            images[f"spectral: {name}"] = r.result.raw_colour
            seconds[f"spectral: {name}"] = r.summary["seconds"]
        spectral = {
            f"spectral: {n}": (r.result.spectral, r.result.wavelengths_nm) for n, r in ours.items()
        }
        boxes = colorchecker_patch_boxes(world.scene(scene)) if scene == "colorchecker" else None
        evaluation = evaluate(
            raw,
            images,
            cfa=cfa,
            boxes=boxes,
            truth_colour=colour_truth(world, scene),
            spectral=spectral,
            truth_spectral=lambda bands, scene=scene: spectral_truth(world, scene, bands),
            seconds=seconds,
        )
        results["evaluation"][scene] = evaluation.as_dict()
        figures = _scene_figures(out, scene, raw, images, evaluation, boxes)
        if boxes is not None:
            figures["spectra"] = _patch_spectra(out, world, scene, boxes, ours)
        evaluations[scene] = SceneEvaluation(evaluation, figures)
    return evaluations


def _scene_figures(out, scene, raw, images, evaluation, boxes) -> dict[str, Any]:
    """Display images on one common scale, zoomed crops, and the edge-error chart."""
    rows, cols = raw.shape
    if boxes is not None:  # patch corners far from the centre fringe the most
        x0, y0 = boxes[0][:2]
        x1, y1 = boxes[-1][2:]
        centres = [(y0, x0), (y0, x1), (y1, x1)]
    else:
        centres = [(rows // 8, cols // 8), (rows // 2, cols // 2), (rows - rows // 8, cols // 8)]
    side = max(32, min(rows, cols) // 8)
    return method_figures(
        out, out / "evaluation" / scene, images, evaluation, centres, side, edge=boxes is not None
    )


def _patch_spectra(out, world, scene, boxes, ours) -> str:
    """Mean spectra of a few patch centres against the truth.

    Each estimate is registered per band (4.9) over these patches, the truth being in
    the simulator's units; the truth is drawn on a 2 nm grid and as band averages.
    """
    from labkit.sim.truth import spectral_truth

    half = 3
    pixels = []
    for index in SPECTRA_PATCHES:
        x0, y0, x1, y1 = boxes[index]
        cy, cx = round((y0 + y1) / 2), round((x0 + x1) / 2)
        yy, xx = np.mgrid[cy - half : cy + half, cx - half : cx + half]
        pixels.append((yy.ravel(), xx.ravel()))
    fine = np.arange(400.0, 701.0, 2.0)
    truth = np.stack([spectral_truth(world, scene, fine, pixels=p).mean(axis=0) for p in pixels])
    estimates = {}
    for name, r in ours.items():
        bands = np.asarray(r.result.wavelengths_nm)
        target = np.stack([spectral_truth(world, scene, bands, pixels=p).mean(0) for p in pixels])
        means = np.stack([r.result.spectral[p].mean(axis=0) for p in pixels])
        scale = (target * means).sum(axis=0) / np.maximum((means * means).sum(axis=0), 1e-300)
        estimates.setdefault("truth, band average", (bands, target))
        estimates[name] = (bands, means * scale)
    path = out / "evaluation" / scene / "patch_spectra.png"
    plot_patch_spectra((fine, truth), estimates, [PATCH_NAMES[i] for i in SPECTRA_PATCHES], path)
    return str(path.relative_to(out))


def _write_report(report, rigs, rig_file, shape, times, captures, models, recons, evaluations):
    rig = rigs["calibration"]
    sim = rig.sim
    report.paragraph(
        f"The whole job on the simulated rig `{rig_file}`, sensor cropped to {shape[1]}×"
        f"{shape[0]} px ({rig.cfa}), lens {sim.lens.spectral_profile} with "
        f"{sim.lens.max_shift_px:g} px of lateral chromatic aberration at the corner "
        f"(reference {sim.lens.reference_nm:g} nm). Total {sum(times.values()):.0f} s."
    )
    stage_table(report, times)
    report.heading("Rig")
    report.figures([("rig_spectra.png", "camera response, lamp and filter transmissions")])
    report.heading("Capture and HDR")
    rows = []
    for name, capture in captures.items():
        for key, exposures in capture.exposures_s.items():
            rows.append([name, key, ", ".join(f"{t * 1e3:.4g}" for t in exposures)])
    report.paragraph(
        "Exposures chosen by auto-bracketing (metering, then the shortest set that exposes "
        "every pixel properly); dark frames at every exposure. "
        + "; ".join(
            f"{n}: {c.frames} frames ({c.dark_frames} dark) in {c.seconds:.1f} s"
            for n, c in captures.items()
        )
        + "."
    )
    report.table(["plan", "scene / illumination", "exposures (ms)"], rows)
    report.figures(
        [
            ("hdr/disks/unfiltered.png", "disks, unfiltered (HDR)"),
            ("hdr/disks/450.png", "disks, 450 nm filter"),
            ("hdr/disks/650.png", "disks, 650 nm filter"),
            ("hdr/colorchecker/unfiltered.png", "ColorChecker (HDR)"),
            ("hdr/texture/unfiltered.png", "textured scene (HDR)"),
        ],
        width_px=300,
    )
    calibration = models.summary
    spectral = calibration["spectral"]
    report.heading("Dispersion calibration")
    report.paragraph(
        f"Disk keypoints in {len(spectral['bands_used_nm'])} bands "
        f"({', '.join(f'{b:.0f}' for b in spectral['bands_used_nm'])} nm), "
        f"{spectral['keypoints']} keypoints; polynomial degree {spectral['degree_xy']} in x, y "
        f"and {spectral['degree_lambda']} in λ chosen by cross-validation (condition number "
        f"{spectral['condition_number']:.3g}). Against the simulated lens: RMS "
        f"**{spectral['error_vs_lens_px']['rms_px']:.3f} px**, max "
        f"{spectral['error_vs_lens_px']['max_px']:.3f} px. The colour-channel model (R and B "
        f"onto G, {calibration['colour']['keypoints']} keypoints) drives the warping "
        "baselines."
    )
    report.figures(
        [
            ("lens_dispersion.png", "the simulated lens' true dispersion"),
            ("calibration/spectral_model.png", "spectral model (to_reference), per band"),
            ("calibration/colour_model.png", "colour-channel model (from_reference)"),
        ]
    )
    report.heading("Reconstruction")
    report.paragraph(
        "The spectral reconstruction: the edge-guided L2 prior (EdgeL2), non-negativity, the "
        "calibrated dispersion model, weights by the demosaicing criterion; patch-wise on "
        "Dask with flat patches and negligible dispersion skipped. The mean-colour variant "
        "reconstructs relative to a smooth spectrum fitted to the image's mean colour; the "
        "warp variant "
        "solves without Φ and then warps every band onto the 600 nm geometry with the same "
        "(inverted) model."
    )
    report.table(
        ["image", "time (s)", "bands (nm)", "weight", "patches", "Φ used", "flat",
         "exact", "median ADMM iterations"],
        [
            [name, f"{s['seconds']:.1f}", f"{s['bands_nm'][0]:.0f}–{s['bands_nm'][-1]:.0f} "
             f"({len(s['bands_nm'])})", f"{s['weights'][0]:.2g}", str(s["patches"]),
             str(s["phi_used"]), str(s["flat"]), str(s["exact"]), f"{s['median_iterations']:.0f}"]
            for name, s in ((n, r.saved.summary) for n, r in recons.items())
        ],
    )  # fmt: skip
    reconstruction_notes(report, {n: r.saved.summary for n, r in recons.items()})
    report.figures(
        [
            (f"reconstruction/{r.saved.folder.name}/preview.png", f"{n}: sRGB")
            for n, r in recons.items()
        ],
        width_px=340,
    )
    for scene, item in evaluations.items():
        evaluation, figures = item.evaluation, item.figures
        report.heading(f"Evaluation: {scene}")
        report.paragraph(
            "Errors are fractions of the mean signal. Edge/centre RMSE: residual "
            "chromatic aberration in 12-px strips inside the patch edges and in the patch "
            "centres against an ideal image synthesised from the raw patch centres. "
            "Colour and spectral RMSE: against the simulator's dispersion-free truth, "
            "registered per channel/band."
        )
        header, rows = evaluation.table()
        report.table(header, rows)
        if "edge" in figures:
            report.figures([(figures["edge"], "edge-strip RMSE per channel")])
        report.heading("Images (one display scale for all)", 3)
        report.figures(figures["previews"], width_px=300)
        report.heading("Zoomed crops", 3)
        report.figures([(figures["crops"], "crops near the corners, nearest-neighbour zoom")])
        if "spectra" in figures:
            report.heading("Patch spectra", 3)
            caption = "patch-centre spectra against the truth (registered per band)"
            report.figures([(figures["spectra"], caption)])
