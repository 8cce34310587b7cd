"""Full-size (2448×2048) checks of the default simulated rig; slow, run by `make bench`."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from labkit.sim import Lens, Scene, render_irradiance
from labkit.spectra import trapezoid_weights

WINDOW = 24  # centroid half-window: radius 14 px + the largest shift, < half the 64 px pitch


def _centroids(image: np.ndarray, background: np.ndarray, centres: np.ndarray) -> np.ndarray:
    out = []
    for cx, cy in centres:
        ys = slice(round(cy) - WINDOW, round(cy) + WINDOW + 1)
        xs = slice(round(cx) - WINDOW, round(cx) + WINDOW + 1)
        weight = background[ys, xs] - image[ys, xs]
        yy, xx = np.mgrid[ys, xs]
        out.append(((weight * xx).sum() / weight.sum(), (weight * yy).sum() / weight.sum()))
    return np.array(out)


@pytest.mark.slow
def test_every_disk_of_the_default_rig_moves_by_the_true_dispersion(sim_rig_path) -> None:
    """All ~1100 disks, measured 450 nm filter (with its 390 nm side peak), vignetting on."""
    from labkit.rig import load_rig
    from labkit.sim import SimulatedRig

    rig = SimulatedRig(load_rig(sim_rig_path))
    assert rig.shape == (2048, 2448)
    scene = rig.scene("disks")
    centres = scene.disks.centres()
    assert len(centres) >= 800, "the calibration issue needs ≥ 800 disks"
    light = {"450": rig.light("450")}
    still = dataclasses.replace(rig.lens, max_shift_px=0.0)

    def green(scene: Scene, lens: Lens) -> np.ndarray:
        rgb = render_irradiance(scene, lens, rig.response, light, rig.wavelengths)["450"]
        return rgb[..., 1].astype(np.float64)

    paper = green(Scene("paper", scene.materials, scene.grid), still)
    shift = _centroids(green(scene, rig.lens), paper, centres) - _centroids(
        green(scene, still), paper, centres
    )
    q_green = rig.response.resample(rig.wavelengths, extrapolate="zero")["G"]
    reflect = scene.materials.resample(rig.wavelengths, extrapolate="constant").values
    w = (
        q_green
        * light["450"]
        * (reflect[:, 0] - reflect[:, 1])
        * trapezoid_weights(rig.wavelengths)
    )
    dx, dy = rig.lens.displacement(centres[:, :1], centres[:, 1:], rig.wavelengths[None, :])
    expected = np.column_stack([dx @ w, dy @ w]) / w.sum()
    assert np.hypot(*expected.T).max() > 1.0, "corner disks move by more than a pixel"
    error = np.hypot(*(shift - expected).T)
    rms = np.sqrt(np.mean(error**2))
    print(f"{len(centres)} disks, worst error {error.max():.4f} px, RMS {rms:.4f} px")
    assert error.max() < 0.02, f"worst disk off by {error.max():.4f} px (> 0.02 px)"
