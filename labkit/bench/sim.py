"""`labkit bench sim`: simulator speed (issue targets: render ≤ 15 s, frame ≤ 0.3 s)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from labkit.bench.harness import Measurement, measure
from labkit.rig import load_rig
from labkit.sim.camera import SimCamera
from labkit.sim.world import SimulatedRig

RENDER_TARGET_S = 15.0
FRAME_TARGET_S = 0.3


def bench_sim(rig_path: str | Path, *, repeats: int = 3) -> tuple[list[Measurement], list[str]]:
    """Time full-size irradiance renders per scene and per-frame sensor simulation."""
    rig = SimulatedRig(load_rig(rig_path))
    rows, cols = rig.shape
    cases: list[Measurement] = []
    for scene in rig.scene_names():
        case = measure(
            f"render {scene} (1 illumination)",
            lambda scene=scene: rig.prerender(scene, ["unfiltered"]),
            setup=rig.clear_cache,
            repeats=repeats,
            target_s=RENDER_TARGET_S,
        )
        case.extra = {"size": f"{cols}x{rows}", "materials": rig.scene(scene).n_materials}
        cases.append(case)
    illuminations = rig.rig.slider.illumination_names()
    batch = measure(
        f"render colorchecker ({len(illuminations)} illuminations together)",
        lambda: rig.prerender("colorchecker", illuminations),
        setup=rig.clear_cache,
        repeats=1,
    )
    batch.extra = {"per_illumination_s": batch.seconds / len(illuminations)}
    cases.append(batch)

    camera = SimCamera(rig, fast=True)
    camera.set_scene("colorchecker")
    camera.set_illumination("unfiltered")
    camera.grab(0.006)  # irradiance is cached from here on
    frame = measure(
        "frame (exposure, noise, saturation, quantisation)",
        lambda: camera.grab(0.006),
        repeats=max(10, repeats),
        target_s=FRAME_TARGET_S,
    )
    image = camera.grab(0.012)[0].image
    frame.extra = {"saturated_fraction": float(np.mean(image >= image.max()))}
    cases.append(frame)
    notes = [
        f"Irradiance renders are cold (cache cleared before each repeat) at {cols}x{rows}, "
        f"spectral step {rig.rig.sim.spectral_step_nm} nm, dispersion level step "
        f"{rig.rig.sim.level_step_px} px, lens max shift {rig.lens.max_shift_px} px.",
    ]
    return cases, notes
