"""Small problem builders shared by the reconstruction solver tests."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from labkit.spectra import camera_response
from reconstruction.image_formation import ImageFormation, LatentSpace, build_formation

RESPONSE = "Nikon 5100 (NPL)"


def latent_space() -> LatentSpace:
    return LatentSpace.spectral(camera_response(RESPONSE))


def normalised_colour() -> np.ndarray:
    c = latent_space().colour_matrix()
    return c / c.sum(axis=1).max()


def blobs(shape: tuple[int, int], n: int, rng: np.random.Generator, count: int = 10) -> np.ndarray:
    """A textured latent image: overlapping disks of random spectra, slightly blurred, ≥ 0.05."""
    truth = np.zeros((*shape, n))
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    for _ in range(count):
        cy, cx = rng.uniform(0, shape[0]), rng.uniform(0, shape[1])
        r = rng.uniform(shape[0] / 16, shape[0] / 4)
        truth[(yy - cy) ** 2 + (xx - cx) ** 2 < r * r] = rng.uniform(0, 1, n)
    return ndimage.gaussian_filter(truth, (0.7, 0.7, 0)) + 0.05


def smooth_blobs(shape: tuple[int, int], n: int, rng: np.random.Generator) -> np.ndarray:
    """:func:`blobs` whose spectra are smooth across the bands (Gaussian, σ = 1.5 bands)."""
    return ndimage.gaussian_filter1d(blobs(shape, n, rng), 1.5, axis=2, mode="nearest")


def noisy_raw(
    formation: ImageFormation, rng: np.random.Generator, noise: float = 0.01
) -> tuple[np.ndarray, np.ndarray]:
    """(truth, raw) with relative Gaussian noise on the rendered mosaic."""
    truth = blobs(formation.range_shape, formation.domain_shape[2], rng)
    raw = formation.forward(truth)
    return truth, raw + noise * raw.mean() * rng.standard_normal(raw.shape)


def noisy_step(
    shape: tuple[int, int], rng: np.random.Generator
) -> tuple[ImageFormation, np.ndarray, np.ndarray]:
    """(A, truth, raw): grey left of the middle column, yellow from it on, 1 % noise."""
    colour = normalised_colour()
    a = ImageFormation(shape, "GBRG", colour[None])
    x = np.linspace(0.0, 1.0, colour.shape[1])
    yellow = 0.05 + 0.9 / (1.0 + np.exp(-(x - 0.45) * 20.0))
    truth = np.full((*shape, x.size), 0.1)
    truth[:, shape[1] // 2 :] = yellow
    raw = a.forward(truth)
    return a, truth, raw + 0.01 * raw.mean() * rng.standard_normal(raw.shape)


def rig_lens_model(shape: tuple[int, int] = (2048, 2448)):
    """A to_reference spectral model of the simulated rig's lens at full sensor size.

    First-order inverse of the lens' dispersion relative to 593.06 nm (the effective
    wavelength of the rig's 600 nm band): e(q, λ) = −u(q)(s(λ) − s(λ_ref)).
    """
    from _helpers import planted_dispersion_model

    from labkit.bench.reconstruct_cases import LensField
    from labkit.rig import load_rig
    from labkit.sim.lens import Lens

    rig = load_rig("labkit/rigs/simulated.yaml")
    lens = Lens(shape, **rig.sim.lens.model_dump())
    return planted_dispersion_model(
        {"spectral": LensField(lens, 593.06)},
        shape=shape,
        direction="to_reference",
        wavelength_span=(400.0, 700.0),
    )


def rig_corner_formation(shape: tuple[int, int]) -> ImageFormation:
    """A at the top-left corner of the simulated rig's lens (Φ up to ≈ 2 px), colour scaled
    so the brightest raw channel peaks at 1 — through `colour_gain`, so that A and the FFT
    solver's colour agree (rescaling ``colour_matrices`` afterwards changes only the latter)."""
    a = build_formation(
        latent_space(),
        shape,
        "GBRG",
        model=rig_lens_model(),
        origin=(0, 0),
        interpolation="bilinear",
    )
    gain = 1.0 / a.colour_matrix.sum(axis=1).max()
    return build_formation(
        latent_space(),
        shape,
        "GBRG",
        model=rig_lens_model(),
        origin=(0, 0),
        colour_gain=gain,
        interpolation="bilinear",
    )
