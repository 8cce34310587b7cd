"""Small problem builders shared by the reconstruction tests: latent spaces, textured
images, planted dispersion fields, small solver problems and their references."""

from __future__ import annotations

from typing import Any

import numpy as np
from _helpers import planted_dispersion_model
from scipy import ndimage
from scipy.optimize import minimize

from labkit.spectra import camera_response
from reconstruction.model.image_formation import ImageFormation, LatentSpace, build_formation
from reconstruction.model.prior_terms import PRIORS
from reconstruction.model.problem import Problem

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


class ConstantField:
    """e = (ex, ey) everywhere, or e scaled by (λ − 600) / 100 with `per_nm`."""

    kind = "test"

    def __init__(self, shift: tuple[float, float], *, per_nm: bool = False) -> None:
        self.shift = np.asarray(shift, dtype=np.float64)
        self.per_nm = per_nm

    def evaluate(self, points: np.ndarray) -> np.ndarray:
        scale = np.ones((points.shape[0], 1))
        if self.per_nm:
            scale = (points[:, 2:3] - 600.0) / 100.0
        return scale * self.shift

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind}


class RadialField:
    """e = m(λ) (p − c) with m linear in λ − 600 nm: a magnification change."""

    kind = "test"

    def __init__(self, magnification: float = 0.03, centre=(30.0, 20.0)) -> None:
        self.magnification = magnification
        self.centre = np.asarray(centre, dtype=np.float64)

    def evaluate(self, points: np.ndarray) -> np.ndarray:
        scale = (points[:, 2:3] - 600.0) / 100.0
        return scale * self.magnification * (points[:, :2] - self.centre)

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind}


def spectral_model(field, shape=(40, 60)):
    """A spectral dispersion model of `field` over 400–700 nm, to the reference."""
    return planted_dispersion_model(
        {"spectral": field}, shape=shape, direction="to_reference", wavelength_span=(400.0, 700.0)
    )


def problem(
    prior: str, weight: float, nonneg: bool, seed: int = 0, smoothness: float = 0.0
) -> Problem:
    """A noisy 32² problem of one prior combination on the normalised colour matrix."""
    rng = np.random.default_rng(seed)
    a = ImageFormation((32, 32), "GBRG", normalised_colour()[None])
    _, raw = noisy_raw(a, rng)
    terms = PRIORS[prior]
    return Problem(a, raw, terms, (weight,) * len(terms), nonneg, smoothness=smoothness)


def smooth_reference(p: Problem) -> float:
    """The optimum of an L2-prior problem by L-BFGS-B (bounds for non-negativity)."""
    a = p.formation

    def f(v):
        x = v.reshape(p.shape)
        r = a.forward(x) - p.raw
        value = np.sum(r * r) + p.ridge * np.sum(x * x)
        grad = 2 * a.adjoint(r) + 2 * p.ridge * x
        for w, _, d in p.penalties:
            g = d.forward(x)
            value += w * np.sum(g * g)
            grad += 2 * w * d.adjoint(g)
        return value, grad.ravel()

    bounds = [(0, None)] * int(np.prod(p.shape)) if p.nonneg else None
    result = minimize(
        f,
        np.zeros(int(np.prod(p.shape))),
        jac=True,
        method="L-BFGS-B",
        bounds=bounds,
        options={"maxiter": 20000, "maxfun": 40000, "ftol": 1e-15, "gtol": 1e-11},
    )
    return float(result.fun)


def kkt_violation(p: Problem, x: np.ndarray) -> float:
    """KKT residual of a non-negative L2-prior problem, relative to ‖2Aᵀy‖: the gradient
    g = Kx − b must vanish where x > 0 and be ≥ 0 where x = 0."""
    a = p.formation
    g = 2 * a.adjoint(a.forward(x) - p.raw) + 2 * p.ridge * x
    for w, _, d in p.penalties:
        g += 2 * w * d.adjoint(d.forward(x))
    violation = np.where(x > 0, np.abs(g), np.maximum(-g, 0.0))
    return float(np.linalg.norm(violation) / np.linalg.norm(2 * a.adjoint(p.raw)))


def shifted_nonneg_problem() -> Problem:
    """32², a planted uniform shift (Φ), L2 + non-negativity: a cold start from zeros takes
    tens of ADMM iterations, whose count followed the BLAS thread count before the library
    fixed it."""
    rng = np.random.default_rng(8)
    model = spectral_model(ConstantField((0.7, -1.3), per_nm=True))
    a = build_formation(latent_space(), (32, 32), "GBRG", model=model, interpolation="bilinear")
    _, raw = noisy_raw(a, rng)
    return Problem(a, raw, PRIORS["L2"], (0.05,), True)
