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
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from tqdm import tqdm

from labkit.io import display_on_one_scale, write_png, write_text_atomic
from labkit.io.tiff import json_default
from labkit.plots import (
    plot_channel_errors,
    plot_crops,
    plot_dispersion,
    plot_patch_spectra,
    plot_rig_spectra,
)
from labkit.report import Report, file_stem
from labkit.rig import Rig, default_rig_path, rig_from_dict

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
    rigs = demo_rigs(rig_file, shape)
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
    results["capture"] = captures
    results["calibration"] = models["summary"]
    results["reconstruction"] = {name: r["summary"] for name, r in recons.items()}
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


class Stages:
    """Runs the named stages of a job under one progress bar and records their wall time.

    ``stages(name, function)`` runs `function` and returns its value; :attr:`seconds` maps
    each stage's name to its wall time, s, in order.
    """

    def __init__(self, total: int, description: str, *, disable: bool | None = False) -> None:
        self.description = description
        self.seconds: dict[str, float] = {}
        self.bar = tqdm(total=total, desc=description, unit="stage", disable=disable)

    def __call__(self, name: str, function: Callable[[], Any]) -> Any:
        self.bar.set_description(f"{self.description}: {name}")
        start = time.perf_counter()
        value = function()
        self.seconds[name] = time.perf_counter() - start
        self.bar.update()
        return value

    def close(self) -> None:
        self.bar.close()


def stage_table(report: Report, seconds: dict[str, float]) -> None:
    """Add the time of every stage, and their total, to `report` as a table."""
    report.table(
        ["stage", "time (s)"],
        [[name, f"{value:.1f}"] for name, value in seconds.items()]
        + [["total", f"{sum(seconds.values()):.1f}"]],
    )


def demo_rigs(rig_file: Path, shape: tuple[int, int]) -> dict[str, Rig]:
    """The two capture plans of the demo on a sensor of `shape`: calibration and scenes."""
    data = yaml.safe_load(Path(rig_file).read_text())
    if data.get("camera", {}).get("backend") != "sim":
        from labkit.errors import ConfigError

        raise ConfigError(f"{rig_file}: the demo needs a simulated rig (camera.backend: sim)")
    data["sim"]["sensor"].update(width=shape[1], height=shape[0])
    pitch = 32 if min(shape) < 512 else 64
    data["sim"]["scenes"]["disks"] = {"type": "disks", "radius_px": pitch // 4, "pitch_px": pitch}
    data["sim"]["scenes"].setdefault("texture", {"type": "texture", "seed": 7})
    plan = data.setdefault("plan", {})
    plan["exposures_s"] = {"unfiltered": "auto", "filtered": "auto"}
    plan["dark_frames"] = True
    calibration = {**data, "plan": {**plan, "scenes": ["disks"], "illuminations": "all"}}
    scenes = {
        **data,
        "plan": {**plan, "scenes": list(RECONSTRUCTED), "illuminations": ["unfiltered"]},
    }
    return {
        "calibration": rig_from_dict(calibration, source=f"{rig_file} (demo calibration plan)"),
        "scenes": rig_from_dict(scenes, source=f"{rig_file} (demo scene plan)"),
    }


def _capture(rigs: dict[str, Rig], out: Path) -> dict[str, Any]:
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
        summary[name] = {
            "frames": len(records),
            "dark_frames": sum(bool(r["dark"]) for r in records),
            "seconds": report.elapsed_s,
            "exposures_s": {k: sorted(set(v)) for k, v in exposures.items()},
        }
    return summary


def _hdr(out: Path) -> None:
    from labkit.hdr import run_hdr

    sessions = [out / "sessions" / name for name in ("calibration", "scenes")]
    run_hdr(sessions, out / "hdr", previews=True)


def _calibrate(rig: Rig, out: Path) -> dict[str, Any]:
    from calibration._hdr_inputs import load_scene_hdr
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
    return {"spectral": spectral.model, "colour": colour.model, "summary": summary}


def save_models(spectral: Any, colour: Any, folder: Path) -> dict[str, Any]:
    """Save a spectral and a colour-channel dispersion calibration with their plots.

    Writes ``spectral_to_reference.yaml``, ``colour_from_reference.yaml`` and a PNG of
    each into `folder`; returns their summary for the report.
    """
    from calibration.plots import plot_model

    spectral.model.save(folder / "spectral_to_reference.yaml")
    colour.model.save(folder / "colour_from_reference.yaml")
    plot_model(spectral.model, folder / "spectral_model.png")
    plot_model(colour.model, folder / "colour_model.png")
    selection = spectral.model.selection
    return {
        "spectral": {
            "bands_used_nm": sorted(b.wavelength_nm for b in spectral.bands if b.used),
            "reference_nm": float(spectral.model.reference),
            "keypoints": len(spectral.keypoints),
            "degree_xy": selection.get("degree_xy"),
            "degree_lambda": selection.get("degree_lambda"),
            "condition_number": selection.get("condition_number"),
            "warnings": list(spectral.warnings),
        },
        "colour": {
            "keypoints": len(colour.keypoints),
            "degree_xy": colour.model.selection.get("degree_xy"),
            "warnings": list(colour.warnings),
        },
    }


def _reconstruct(rig: Rig, out: Path, models: dict[str, Any]) -> dict[str, Any]:
    from labkit.io import read_raw_exr
    from labkit.sim import SimulatedRig

    response = SimulatedRig(rig).response
    jobs = [(scene, scene, scene, {}) for scene in RECONSTRUCTED] + [
        (
            "colorchecker",
            "colorchecker (§6.3 mean-colour)",
            "colorchecker_mean_colour",
            {"reference": "mean-colour"},
        ),
        ("colorchecker", "colorchecker (§3.9.2 warp)", "colorchecker_warp", {"correction": "warp"}),
    ]
    results = {}
    for scene, name, slug, variant in jobs:
        image = read_raw_exr(out / "hdr" / scene / "unfiltered.exr")
        result, summary = reconstruct_and_save(
            image.raw,
            out / "reconstruction" / slug,
            name=name,
            cfa=image.cfa,
            response=response,
            dispersion=models["spectral"],
            **variant,
        )
        results[name] = {
            "scene": scene,
            "slug": slug,
            "result": result,
            "raw": image.raw,
            "cfa": image.cfa,
            "summary": summary,
        }
    return results


def reconstruct_and_save(
    raw: np.ndarray,
    folder: Path,
    *,
    name: str,
    command: str = "labkit demo",
    disable_progress: bool | None = False,
    **options: Any,
) -> tuple[Any, dict[str, Any]]:
    """Reconstruct `raw` with a progress bar and save it into `folder`
    (:meth:`reconstruction.Reconstruction.save`).

    Returns the :class:`reconstruction.Reconstruction` and a summary for the report
    (seconds, bands, weight, patch counts, median ADMM iterations).
    """
    from reconstruction import reconstruct

    bar = tqdm(desc=f"reconstruct {name}", unit="patch", leave=False, disable=disable_progress)

    def progress(done: int, total: int) -> None:
        bar.total = total
        bar.n = done
        bar.refresh()

    start = time.perf_counter()
    result = reconstruct(raw, progress=progress, **options)
    seconds = time.perf_counter() - start
    bar.close()
    result.save(folder, provenance={"command": command})
    patches = result.log["patches"]
    summary = {
        "seconds": seconds,
        "bands_nm": [float(b) for b in result.wavelengths_nm],
        "weights": result.log["weights"]["values"],
        "patches": patches["count"],
        "phi_used": patches["phi_used"],
        "flat": patches["flat"],
        "median_iterations": patches["iterations_median"],
        "exact": patches["exact"],
        "warnings": list(result.log.get("warnings", [])),
        "choices": result.log.get("choices", {}),
    }
    return result, summary


def reconstruction_notes(report: Any, summaries: dict[str, dict[str, Any]]) -> None:
    """Add the reconstructions' warnings (their logs' ``warnings``), if any, and the
    choices labkit made for each (their logs' ``choices``: value, how, why) to `report`."""
    notices = [f"{name}: {w}" for name, s in summaries.items() for w in s.get("warnings", [])]
    if notices:
        report.bullets(notices)
    rows = [
        [name, option, _choice_value(c["value"]), c["source"], c["reason"]]
        for name, s in summaries.items()
        for option, c in s.get("choices", {}).items()
        if c["source"] != "given"
    ]
    if rows:
        report.paragraph(
            "Choices labkit made (each can be given as an option instead; `log.json`'s "
            "`choices` records them with their evidence):"
        )
        report.table(["image", "option", "value", "how", "why"], rows)


def _choice_value(value: Any) -> str:
    if isinstance(value, list) and value and all(isinstance(v, (int, float)) for v in value):
        return f"{len(value)} values, {value[0]:g}–{value[-1]:g}"
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def _evaluate(
    rig: Rig,
    out: Path,
    models: dict[str, Any],
    recons: dict[str, Any],
    results: dict[str, Any],
) -> dict[str, Any]:
    from labkit.sim import SimulatedRig, colorchecker_patch_boxes
    from labkit.sim.truth import colour_truth, spectral_truth
    from reconstruction import baseline_images, evaluate

    world = SimulatedRig(rig)
    evaluations = {}
    results["evaluation"] = {}
    for scene in RECONSTRUCTED:
        ours = {n: r for n, r in recons.items() if r["scene"] == scene}
        first = next(iter(ours.values()))
        raw, cfa = first["raw"], first["cfa"]
        images, seconds = baseline_images(raw, cfa=cfa, colour_dispersion=models["colour"])
        for name, r in ours.items():
            images[f"spectral: {name}"] = r["result"].raw_colour
            seconds[f"spectral: {name}"] = r["summary"]["seconds"]
        spectral = {
            f"spectral: {n}": (r["result"].spectral, r["result"].wavelengths_nm)
            for n, r in ours.items()
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
        evaluations[scene] = {"evaluation": evaluation, "figures": figures}
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


def method_figures(
    out: Path,
    folder: Path,
    images: dict[str, np.ndarray],
    evaluation: Any,
    centres: list[tuple[int, int]],
    side: int,
    *,
    edge: bool,
) -> dict[str, Any]:
    """Every method's image on one display scale, zoomed crops and the edge-error chart.

    Parameters
    ----------
    out : Path
        The report's folder (figure paths are returned relative to it).
    folder : Path
        Where the PNGs go.
    images : dict of str to ndarray (rows, cols, 3)
        Colour images by method (``"bilinear"`` among them: the display scale's reference).
    evaluation : reconstruction.Evaluation
        Their scores (the edge chart needs residual aberration).
    centres : list of (row, col)
        Centres of the zoomed crops, px.
    side : int
        Crop side, px.
    edge : bool
        Draw the edge-strip RMSE chart.
    """
    display = display_on_one_scale(images, reference="bilinear")
    previews = []
    for name, image in display.items():
        path = folder / f"{file_stem(name)}.png"
        write_png(path, image)
        previews.append((str(path.relative_to(out)), name))
    rows, cols = next(iter(images.values())).shape[:2]
    windows = [
        (int(np.clip(r - side // 2, 0, rows - side)), int(np.clip(c - side // 2, 0, cols - side)),
         side)
        for r, c in centres
    ]  # fmt: skip
    chosen = ["bilinear", "malvar + warp", "menon", "menon + warp"]
    chosen += [n for n in display if n.startswith("spectral")]
    plot_crops({n: display[n] for n in chosen if n in display}, windows, folder / "crops.png")
    figures = {"previews": previews, "crops": str((folder / "crops.png").relative_to(out))}
    if edge:
        rmse = {n: s.residual.edge.rmse for n, s in evaluation.scores.items() if s.residual}
        plot_channel_errors(
            rmse, folder / "edge_rmse.png", ylabel="edge-strip RMSE (fraction of raw mean)"
        )
        figures["edge"] = str((folder / "edge_rmse.png").relative_to(out))
    return figures


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
        bands = np.asarray(r["result"].wavelengths_nm)
        target = np.stack([spectral_truth(world, scene, bands, pixels=p).mean(0) for p in pixels])
        means = np.stack([r["result"].spectral[p].mean(axis=0) for p in pixels])
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
    for name, summary in captures.items():
        for key, exposures in summary["exposures_s"].items():
            rows.append([name, key, ", ".join(f"{t * 1e3:.4g}" for t in exposures)])
    report.paragraph(
        "Exposures chosen by auto-bracketing (metering, then the shortest set that exposes "
        "every pixel properly); dark frames at every exposure. "
        + "; ".join(
            f"{n}: {s['frames']} frames ({s['dark_frames']} dark) in {s['seconds']:.1f} s"
            for n, s in captures.items()
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
    calibration = models["summary"]
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
        "Problem (3.1): the edge-guided L2 prior (EdgeL2), non-negativity, the calibrated "
        "dispersion model, weights by the demosaicing criterion; patch-wise on Dask with "
        "flat patches and negligible dispersion skipped. The §6.3 variant reconstructs "
        "relative to a smooth spectrum fitted to the image's mean colour; the §3.9.2 variant "
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
            for name, s in ((n, r["summary"]) for n, r in recons.items())
        ],
    )  # fmt: skip
    reconstruction_notes(report, {n: r["summary"] for n, r in recons.items()})
    report.figures(
        [(f"reconstruction/{r['slug']}/preview.png", f"{n}: sRGB") for n, r in recons.items()],
        width_px=340,
    )
    for scene, item in evaluations.items():
        evaluation, figures = item["evaluation"], item["figures"]
        report.heading(f"Evaluation: {scene}")
        report.paragraph(
            "Errors are fractions of the mean signal. Edge/centre RMSE: residual "
            "chromatic aberration in 12-px strips inside the patch edges and in the patch "
            "centres against an ideal image synthesised from the raw patch centres (§4.4.3). "
            "Colour and spectral RMSE: against the simulator's dispersion-free truth, "
            "registered per channel/band (4.9)."
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
