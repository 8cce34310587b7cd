"""Ground truth of simulated scenes for evaluating reconstructions (thesis §4.4).

The truth is the scene without the lens' dispersion: reflectance × light in the reference
geometry, with vignetting, at the simulator's exact pixel-area coverage. The colour truth
integrates over the simulator's fine spectral grid; the spectral truth averages the light
over each band's width (the lamp has mercury lines that no band-limited model can hold)
and samples the reflectances at the band centres. Units: the simulator's irradiance units
(e⁻/s on a perfect white reflector's scale) times `scale`.
"""

from __future__ import annotations

import numpy as np

from labkit.errors import DataError
from labkit.sim.world import SimulatedRig


def _scene_parts(world: SimulatedRig, scene: str, illumination: str, pixels=None):
    light = world.light(illumination)
    if light is None:
        raise DataError(f"illumination {illumination!r} has no light; use a lit illumination")
    scene_obj = world.scene(scene)
    wavelengths = world.wavelengths
    reflect = scene_obj.materials.resample(wavelengths, extrapolate="constant").values  # (f, K)
    coverage = scene_obj.coverage_image(world.shape).astype(np.float64)  # (rows, cols, K)
    vignetting = world.lens.vignetting_map()[..., None]
    if pixels is not None:
        coverage, vignetting = coverage[pixels], vignetting[pixels]
    return light, wavelengths, reflect, coverage, vignetting


def colour_truth(
    world: SimulatedRig, scene: str, *, illumination: str = "unfiltered", scale: float = 1.0
) -> np.ndarray:
    """Dispersion-free raw-colour image (rows, cols, 3) of a simulated scene, float64."""
    light, wavelengths, reflect, coverage, vignetting = _scene_parts(world, scene, illumination)
    q = world.response.select(["R", "G", "B"]).resample(wavelengths).values  # (f, 3)
    step = np.gradient(wavelengths)
    return (coverage @ ((reflect * (light * step)[:, None]).T @ q)) * vignetting * scale


def spectral_truth(
    world: SimulatedRig,
    scene: str,
    bands_nm: np.ndarray,
    *,
    illumination: str = "unfiltered",
    scale: float = 1.0,
    pixels: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Reflectance × band-averaged light at `bands_nm` (rows, cols, n), float64.

    Each band averages the light over ± half the mean band spacing (bands equally
    spaced, nm). With `pixels` (row and column indices), only those pixels: (k, n).
    """
    bands_nm = np.asarray(bands_nm, dtype=np.float64)
    light, wavelengths, reflect, coverage, vignetting = _scene_parts(
        world, scene, illumination, pixels
    )
    half = 0.5 * float(np.mean(np.diff(bands_nm))) if bands_nm.size > 1 else 5.0
    inside = np.abs(wavelengths[None, :] - bands_nm[:, None]) <= half  # (n, f)
    light_at = (inside * light).sum(axis=1) / np.maximum(inside.sum(axis=1), 1)
    spectra = np.stack([np.interp(bands_nm, wavelengths, r) for r in reflect.T])  # (K, n)
    return coverage @ (spectra * light_at) * vignetting * scale
