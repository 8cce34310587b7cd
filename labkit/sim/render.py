"""Noise-free sensor irradiance of a scene seen through the lens.

For a pixel p and colour channel c the irradiance is (thesis (3.6) with dispersion)::

    I_c(p) = V(p) Σ_λ w(λ) Q_c(λ) E(λ) Σ_k R_k(λ) a_k(p − d(·, λ))

with trapezoid weights w on the simulation grid (≤ 2 nm), light E, reflectances R_k and
exact pixel-area coverages a_k of each material (see :mod:`labkit.sim.scenes`), then
blurred by the lens' point spread function (:meth:`~labkit.sim.lens.Lens.blur`). Because
d(p, λ) = u(p) s(λ) is separable, the coverage only depends on λ through the scalar
s(λ). The renderer evaluates coverages at a few *levels* s_j, spaced so that adjacent
levels move the image by at most `level_step_px`, and folds the whole spectral sum into
coefficients C[c, k, j] = Σ_λ w Q_c E R_k φ_j(s(λ)) with hat functions φ_j. Hat
interpolation reproduces linear functions of s, so first moments (a disk's centroid)
are exact for any step; the step only bounds the spectral blur's shape error.

Coverages are shared by all illuminations, so rendering several illuminations of one
scene together costs little more than one.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from labkit.sim.lens import Lens
from labkit.sim.scenes import Scene
from labkit.spectra import Spectra, hat_weights, trapezoid_weights


def render_irradiance(
    scene: Scene,
    lens: Lens,
    response: Spectra,
    lights: Mapping[str, np.ndarray],
    wavelengths: np.ndarray,
    *,
    level_step_px: float = 0.25,
    tile_px: int = 256,
    workers: int | None = None,
) -> dict[str, np.ndarray]:
    """Render per-channel irradiance images for several illuminations.

    Parameters
    ----------
    scene, lens : Scene, Lens
        What is imaged and how.
    response : Spectra
        Camera response Q_c, channels R, G, B (resampled onto `wavelengths`, zero outside).
    lights : mapping of str to ndarray (n_λ,)
        Light reaching the scene per illumination, already in the caller's units
        (the result is in those units × response × nm).
    wavelengths : ndarray (n_λ,)
        Simulation grid, nm.
    level_step_px : float
        Largest image motion between adjacent dispersion levels, px.
    tile_px : int
        Tile side; tiles near the principal point need fewer levels.
    workers : int or None
        Threads (default: CPU count).

    Returns
    -------
    dict of str to ndarray (rows, cols, 3), float32
    """
    names = list(lights)
    rows, cols = lens.shape
    q = response.select(["R", "G", "B"]).resample(wavelengths, extrapolate="zero").values
    reflect = scene.materials.resample(wavelengths, extrapolate="constant").values
    tw = trapezoid_weights(wavelengths)
    light = np.stack([np.asarray(lights[n], dtype=np.float64) for n in names])  # (I, n_λ)
    # W[i, c, k, λ] → reshaped to (I*3, K, n_λ)
    weights = light[:, None, None, :] * q.T[None, :, None, :] * reflect.T[None, None] * tw
    weights = weights.reshape(len(names) * 3, scene.n_materials, wavelengths.size)
    active = np.any(weights != 0, axis=(0, 1))
    s = lens.spectral_factor(wavelengths)
    s_lo, s_hi = (float(s[active].min()), float(s[active].max())) if active.any() else (0.0, 0.0)

    out = np.zeros((rows, cols, len(names) * 3), dtype=np.float32)
    tiles = [(r, c) for r in range(0, rows, tile_px) for c in range(0, cols, tile_px)]

    def render_tile(origin: tuple[int, int]) -> None:
        r0, c0 = origin
        r1, c1 = min(r0 + tile_px, rows), min(c0 + tile_px, cols)
        yy, xx = np.mgrid[r0:r1, c0:c1]
        x = xx.ravel().astype(np.float64)
        y = yy.ravel().astype(np.float64)
        probe_y, probe_x = np.meshgrid(np.linspace(r0, r1 - 1, 5), np.linspace(c0, c1 - 1, 5))
        ux, uy = lens.radial_field(probe_x, probe_y)
        motion = float(np.hypot(ux, uy).max()) * (s_hi - s_lo)
        n_levels = max(2, int(np.ceil(motion / level_step_px)) + 1) if motion > 0 else 1
        levels = np.linspace(s_lo, s_hi, n_levels)
        coeff = weights @ hat_weights(s, levels).T  # (I*3, K, J)
        acc = np.zeros((x.size, coeff.shape[0]), dtype=np.float32)
        flat_index = np.arange(x.size)[:, None] * scene.n_materials
        for j, level in enumerate(levels):
            qx, qy = lens.to_reference(x, y, level) if level != 0 else (x, y)
            labels, frac = scene.mixture(qx, qy)
            dense = np.bincount(
                (flat_index + labels).ravel(),
                weights=frac.ravel(),
                minlength=x.size * scene.n_materials,
            ).reshape(x.size, scene.n_materials)
            acc += (dense @ coeff[:, :, j].T).astype(np.float32)
        out[r0:r1, c0:c1] = acc.reshape(r1 - r0, c1 - c0, -1)

    with ThreadPoolExecutor(max_workers=workers or os.cpu_count() or 1) as pool:
        list(pool.map(render_tile, tiles))

    if lens.vignetting > 0:
        out *= lens.vignetting_map()[..., None]
    lens.blur(out)
    return {name: out[..., 3 * i : 3 * i + 3] for i, name in enumerate(names)}
