"""Ground truth of the simulated rig: scenes for evaluating reconstructions (thesis §4.4),
and the lens' dispersion for judging calibrated models (:func:`model_error`).

The truth is the scene without the lens' dispersion: reflectance × light in the reference
geometry, with vignetting and the lens' blur (what a lens of the same sharpness but no
chromatic aberration would give: a reconstruction removes dispersion, not defocus), at the
simulator's exact pixel-area coverage. The colour truth
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
    coverage = world.lens.blur(scene_obj.coverage_image(world.shape).astype(np.float64))
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


def model_error(model, lens, reference_nm: float, wavelengths_nm, *, step_px: int = 16) -> dict:
    """RMS and max ‖model − the lens' displacement‖ (px) on a grid in the calibrated region.

    A ``to_reference`` model at a band position q is compared with minus the lens'
    displacement at q (exact to first order: the field varies by < 0.3 % of itself over
    the few pixels it moves). `step_px` is the grid spacing, px.
    """
    rows, cols = lens.shape
    yy, xx = np.mgrid[0:rows:step_px, 0:cols:step_px].astype(np.float64)
    inside = model.region.contains(xx, yy)
    x, y = xx[inside], yy[inside]
    sign = -1.0 if model.direction == "to_reference" else 1.0
    errors = {}
    for wavelength in wavelengths_nm:
        if model.variables == "xylambda":
            mx, my = model.displacement(x, y, wavelength)
        else:
            mx, my = model.displacement(x, y, channel=wavelength)
        tx, ty = lens.relative_displacement(x, y, wavelength, reference_nm=reference_nm)
        errors[float(wavelength)] = np.hypot(mx - sign * tx, my - sign * ty)
    everything = np.concatenate(list(errors.values()))
    return {
        "rms_px": float(np.sqrt(np.mean(everything**2))),
        "max_px": float(everything.max()),
        "worst_band_rms_px": max(float(np.sqrt(np.mean(e**2))) for e in errors.values()),
    }
