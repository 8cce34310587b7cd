"""`labkit demo`: the main job on the simulated rig.

For now (foundation): render the thesis-style frame set — every scene under unfiltered
light and each bandpass filter at a well-chosen exposure, plus matching dark frames —
and write a Markdown report with previews, spectra and the lens' dispersion field.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from labkit.io import raw_preview, write_png, write_raw_tiff, write_text_atomic
from labkit.plots import plot_dispersion, plot_rig_spectra
from labkit.rig import default_rig_path, load_rig
from labkit.sim.world import DARK, SimulatedRig

QUICK_SHAPE = (256, 320)


def choose_exposure(rig: SimulatedRig, irradiance: np.ndarray, candidates: list[float]) -> float:
    """Longest candidate exposure (s) that keeps 99.9 % of pixels below 90 % of full well."""
    bright = float(np.percentile(irradiance, 99.9))
    limit = 0.9 * rig.sensor.model.full_well_e
    fitting = [t for t in sorted(candidates) if bright * t <= limit]
    return fitting[-1] if fitting else min(candidates)


def run_demo(out: str | Path, *, rig_path: str | Path | None = None, quick: bool = False) -> Path:
    """Render the demo frame set into `out` and return the path of ``report.md``."""
    out = Path(out)
    started = time.perf_counter()
    rig_file = Path(rig_path) if rig_path else default_rig_path()
    rig = SimulatedRig(load_rig(rig_file), shape=QUICK_SHAPE if quick else None)
    camera = rig.camera(fast=True)
    model = rig.sensor.model
    rows = []
    darks: set[float] = set()
    illuminations = rig.rig.slider.illumination_names()
    pairs = [(s, i) for s in rig.scene_names() for i in illuminations]
    progress = tqdm(total=len(pairs), desc="demo", unit="frame")
    for scene in rig.scene_names():
        progress.set_description(f"demo: rendering {scene}")
        rig.prerender(scene, illuminations)
        progress.set_description(f"demo: capturing {scene}")
        for illumination in illuminations:
            progress.update()
            candidates = rig.rig.exposures_for(illumination)
            if candidates == "auto":
                candidates = list(np.geomspace(1e-3, 4.0, 13))
            exposure = choose_exposure(rig, rig.irradiance(scene, illumination), candidates)
            darks.add(exposure)
            camera.set_scene(scene)
            camera.set_illumination(illumination)
            frame = camera.grab(exposure)[0]
            name = f"{scene}_{illumination}_{exposure * 1e3:g}ms"
            write_raw_tiff(out / "frames" / f"{name}.tiff", frame.image, _meta(frame))
            write_png(
                out / "previews" / f"{name}.png",
                raw_preview(frame.image, model.cfa, black_level=frame.extra["black_level"],
                            max_side=512),
            )  # fmt: skip
            signal = frame.image.astype(np.float64) - frame.extra["black_level"]
            saturation = model.full_well_e * model.gain_dn_per_e
            rows.append(
                (scene, illumination, exposure, float(np.median(signal)),
                 100 * float(np.mean(signal >= 0.95 * saturation)),
                 100 * float(np.mean((signal > 0.02 * saturation) & (signal < 0.95 * saturation))),
                 f"previews/{name}.png")
            )  # fmt: skip
        rig.clear_cache()
    progress.close()
    camera.set_illumination(DARK)
    for exposure in sorted(darks):
        frame = camera.grab(exposure)[0]
        write_raw_tiff(
            out / "frames" / f"dark_{exposure * 1e3:g}ms.tiff", frame.image, _meta(frame)
        )
    plot_rig_spectra(rig, out / "spectra.png")
    plot_dispersion(rig.lens, [400.0, 450.0, 700.0], out / "dispersion.png")
    elapsed = time.perf_counter() - started
    report = _report(rig, rig_file, rows, sorted(darks), elapsed, len(pairs), quick)
    write_text_atomic(out / "report.md", report)
    return out / "report.md"


def _meta(frame) -> dict:
    return {
        "frame_id": frame.frame_id,
        "exposure_s": frame.exposure_s,
        "gain_db": frame.gain_db,
        "pixel_format": frame.pixel_format,
        "device_timestamp_ns": frame.device_timestamp_ns,
        "host_timestamp_s": frame.host_timestamp_s,
        **frame.extra,
    }


def _report(rig, rig_file, rows, darks, elapsed, n_frames, quick) -> str:
    model = rig.sensor.model
    lens = rig.lens
    lines = [
        f"# labkit demo — {rig.rig.name}",
        "",
        f"Rig file `{rig_file}`{' (quick mode: small sensor)' if quick else ''}. "
        f"Sensor {model.width}×{model.height} {model.cfa}, {model.adc_bits}-bit, full well "
        f"{model.full_well_e:g} e⁻, read noise {model.read_noise_e:g} e⁻, black level "
        f"{model.black_level_dn:g} DN. Lens: {lens.spectral_profile} dispersion, "
        f"{lens.radial_profile} radial profile, {lens.max_shift_px:g} px at the corner, "
        f"reference {lens.reference_nm:g} nm; vignetting {lens.vignetting:g}.",
        "",
        f"{n_frames} frames and {len(darks)} dark frames "
        f"({', '.join(f'{t * 1e3:g} ms' for t in darks)}) in {elapsed:.1f} s. "
        "Exposures: the longest of the plan's list that keeps 99.9 % of pixels below 90 % "
        "of full well. Raw frames are 16-bit TIFF in `frames/`.",
        "",
        "## Rig spectra",
        "",
        "![camera response, lamp and filters](spectra.png)",
        "",
        "## Simulated lateral chromatic aberration",
        "",
        "![dispersion field](dispersion.png)",
        "",
        "## Frames",
        "",
        "| scene | illumination | exposure (ms) | median signal (DN) | saturated (%) "
        "| properly exposed (%) | preview |",
        "|---|---|---:|---:|---:|---:|---|",
    ]
    for scene, illumination, exposure, median, saturated, proper, preview in rows:
        lines.append(
            f"| {scene} | {illumination} | {exposure * 1e3:g} | {median:.0f} | {saturated:.2f} "
            f"| {proper:.1f} | ![{scene} {illumination}]({preview}) |"
        )
    return "\n".join(lines) + "\n"
