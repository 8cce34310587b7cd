"""A lens with lateral chromatic aberration, vignetting and defocus blur.

Lateral chromatic aberration is a displacement field that is separable in position and
wavelength::

    d(x, y, λ) = A · g(ρ) · r̂ · s(λ)

where ρ = r / r_corner is the distance from the principal point normalised to 1 at the
image corner, r̂ the unit radial vector, g the radial profile (max abs(g) = 1 on [0, 1]) and
s the spectral profile (s(λ_ref) = 0, max abs(s) = 1 over 400–700 nm). A is therefore the
largest displacement at the image corner, pixels. The spectral profile follows from a
glass dispersion law (Sellmeier, thesis (1.1)–(1.2)): a singlet's magnification scales
with its focal length ∝ 1 / (n(λ) − 1); an achromatic doublet (N-BK7 + F2, corrected at
the F and C lines) leaves the non-monotonic secondary spectrum.

``d`` maps reference-image positions to band positions (``from_reference``): a point
imaged at p at the reference wavelength is imaged at p + d(p, λ) at wavelength λ.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from scipy import ndimage, optimize

from labkit.errors import ConfigError

#: Sellmeier coefficients (B1, B2, B3, C1, C2, C3), λ in µm, from SCHOTT's data sheets.
SELLMEIER = {
    "N-BK7": (1.03961212, 0.231792344, 1.01046945, 0.00600069867, 0.0200179144, 103.560653),
    "F2": (1.34533359, 0.209073176, 0.937357162, 0.00997743871, 0.0470450767, 111.886764),
}

_F_LINE_NM, _C_LINE_NM, _D_LINE_NM = 486.13, 656.27, 587.56


def refractive_index(wavelength_nm: np.ndarray | float, glass: str = "N-BK7") -> np.ndarray:
    """Refractive index from the Sellmeier equation (thesis (1.1)); wavelength in nm."""
    if glass not in SELLMEIER:
        raise ConfigError(f"unknown glass {glass!r}; known: {', '.join(SELLMEIER)}")
    b1, b2, b3, c1, c2, c3 = SELLMEIER[glass]
    um2 = (np.asarray(wavelength_nm, dtype=np.float64) / 1000.0) ** 2
    return np.sqrt(1.0 + b1 * um2 / (um2 - c1) + b2 * um2 / (um2 - c2) + b3 * um2 / (um2 - c3))


def _relative_power(wavelength_nm: np.ndarray, profile: str) -> np.ndarray:
    """Optical power φ(λ) of a thin singlet or achromat, up to a constant factor."""
    if profile == "singlet":
        return refractive_index(wavelength_nm, "N-BK7") - 1.0
    # Thin achromat: K1 (n1 − 1) + K2 (n2 − 1) with equal power at the F and C lines.
    crown = refractive_index(np.array([_F_LINE_NM, _C_LINE_NM]), "N-BK7")
    flint = refractive_index(np.array([_F_LINE_NM, _C_LINE_NM]), "F2")
    k2 = -(crown[0] - crown[1]) / (flint[0] - flint[1])
    return (refractive_index(wavelength_nm, "N-BK7") - 1.0) + k2 * (
        refractive_index(wavelength_nm, "F2") - 1.0
    )


@dataclass(frozen=True)
class Lens:
    """Simulated optics of the rig.

    Attributes
    ----------
    shape : (rows, cols)
        Image size, pixels.
    max_shift_px : float
        A: displacement at the image corner at the worst wavelength in 400–700 nm, px.
        Negative values reverse the direction.
    reference_nm : float
        Wavelength with zero displacement, nm.
    spectral_profile : {"singlet", "achromat"}
        Dispersion law: N-BK7 singlet (monotonic) or N-BK7/F2 achromat (secondary
        spectrum, non-monotonic in λ).
    radial_profile : {"linear", "nonmonotonic"}
        g(ρ) = ρ, or ρ (1 − ρ²/ρ0²) with ρ0 = `reversal_radius`, whose direction reverses
        near the corners like the thesis' measured lens (App. B).
    centre_px : (x, y) or None
        Principal point; None for the image centre.
    vignetting : float
        Relative fall-off at the corner (cos⁴ law), 0 = none.
    blur_sigma_px : float
        Optical blur (defocus, aberrations, the pixel's own spread), standard deviation of
        a Gaussian point spread function, px (0 = none); applied by :meth:`blur`.
    """

    shape: tuple[int, int]
    max_shift_px: float = 2.5
    reference_nm: float = 600.0
    spectral_profile: Literal["singlet", "achromat"] = "singlet"
    radial_profile: Literal["linear", "nonmonotonic"] = "linear"
    reversal_radius: float = 0.95
    centre_px: tuple[float, float] | None = None
    vignetting: float = 0.0
    blur_sigma_px: float = 0.0
    _spectral_norm: float = field(init=False, repr=False, default=1.0)
    _radial_norm: float = field(init=False, repr=False, default=1.0)

    def __post_init__(self) -> None:
        if self.spectral_profile not in ("singlet", "achromat"):
            raise ConfigError(
                f"spectral_profile must be singlet or achromat, not {self.spectral_profile!r}"
            )
        if self.radial_profile not in ("linear", "nonmonotonic"):
            raise ConfigError(
                f"radial_profile must be linear or nonmonotonic, not {self.radial_profile!r}"
            )
        if not 0.0 <= self.vignetting < 1.0:
            raise ConfigError(f"vignetting must be in [0, 1), got {self.vignetting}")
        probe = np.linspace(400.0, 700.0, 301)
        object.__setattr__(self, "_spectral_norm", float(np.abs(self._raw_spectral(probe)).max()))
        rho = np.linspace(0.0, 1.0, 1001)
        object.__setattr__(
            self, "_radial_norm", float(np.abs(rho * self._raw_radial_over_rho(rho**2)).max())
        )

    # -- geometry -------------------------------------------------------------------
    @property
    def centre(self) -> tuple[float, float]:
        """Principal point (x, y), px."""
        if self.centre_px is not None:
            return float(self.centre_px[0]), float(self.centre_px[1])
        rows, cols = self.shape
        return (cols - 1) / 2.0, (rows - 1) / 2.0

    @property
    def corner_radius(self) -> float:
        """Distance from the principal point to the farthest image corner, px."""
        cx, cy = self.centre
        rows, cols = self.shape
        corners = np.array([[0, 0], [cols - 1, 0], [0, rows - 1], [cols - 1, rows - 1]], float)
        return float(np.hypot(corners[:, 0] - cx, corners[:, 1] - cy).max())

    def _raw_spectral(self, wavelength_nm: np.ndarray) -> np.ndarray:
        power = _relative_power(np.asarray(wavelength_nm, dtype=np.float64), self.spectral_profile)
        power_ref = _relative_power(np.array([self.reference_nm]), self.spectral_profile)[0]
        return power_ref / power - 1.0  # relative change of focal length ∝ magnification

    def _raw_radial_over_rho(self, rho2: np.ndarray) -> np.ndarray:
        if self.radial_profile == "linear":
            return np.ones_like(rho2)
        return 1.0 - rho2 / self.reversal_radius**2

    def spectral_factor(self, wavelength_nm: np.ndarray | float) -> np.ndarray:
        """s(λ): 0 at the reference wavelength, max abs(s) = 1 over 400–700 nm."""
        return self._raw_spectral(np.asarray(wavelength_nm, dtype=np.float64)) / self._spectral_norm

    def radial_field(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """u(x, y) = A g(ρ) r̂, px: the displacement per unit of s."""
        cx, cy = self.centre
        scale = self.max_shift_px / (self._radial_norm * self.corner_radius)
        dx = np.asarray(x) - cx
        dy = np.asarray(y) - cy
        rho2 = (dx * dx + dy * dy) / self.corner_radius**2
        factor = scale * self._raw_radial_over_rho(rho2)
        return factor * dx, factor * dy

    def displacement(
        self, x: np.ndarray, y: np.ndarray, wavelength_nm: np.ndarray | float
    ) -> tuple[np.ndarray, np.ndarray]:
        """True dispersion d(x, y, λ) (``from_reference``), px.

        x = column, y = row of a reference-image position; broadcasts over all inputs.
        """
        ux, uy = self.radial_field(x, y)
        s = self.spectral_factor(wavelength_nm)
        return ux * s, uy * s

    def relative_displacement(
        self,
        x: np.ndarray,
        y: np.ndarray,
        wavelength_nm: np.ndarray | float,
        *,
        reference_nm: float,
    ) -> tuple[np.ndarray, np.ndarray]:
        """True dispersion between the images at `reference_nm` and `wavelength_nm`, px.

        A point imaged at (x, y) at `reference_nm` is imaged at (x + dx, y + dy) at
        `wavelength_nm` (``from_reference``): what a calibration against a reference
        band other than the lens' own reference wavelength should find.
        """
        s_ref = float(self.spectral_factor(reference_nm))
        qx, qy = self.to_reference(x, y, s_ref) if s_ref != 0 else (x, y)
        ux, uy = self.radial_field(qx, qy)
        s = self.spectral_factor(wavelength_nm)
        return qx + ux * s - x, qy + uy * s - y

    def to_reference(
        self, x: np.ndarray, y: np.ndarray, s: float, *, iterations: int = 3
    ) -> tuple[np.ndarray, np.ndarray]:
        """Reference-image position imaged at (x, y) for spectral factor `s`, px.

        Solves q + u(q) s = p by fixed-point iteration (‖∇u s‖ ≪ 1, so it converges
        geometrically; three steps leave an error far below 1e-4 px).
        """
        qx, qy = x, y
        for _ in range(iterations):
            ux, uy = self.radial_field(qx, qy)
            qx = x - ux * s
            qy = y - uy * s
        return qx, qy

    def vignetting_map(self) -> np.ndarray:
        """Relative illumination (rows, cols), cos⁴ law, 1 at the principal point."""
        rows, cols = self.shape
        if self.vignetting == 0:
            return np.ones(self.shape, dtype=np.float32)
        cx, cy = self.centre
        cos_corner = (1.0 - self.vignetting) ** 0.25
        focal_px = self.corner_radius * cos_corner / np.sqrt(1.0 - cos_corner**2)
        yy, xx = np.mgrid[0:rows, 0:cols].astype(np.float64)
        r2 = (xx - cx) ** 2 + (yy - cy) ** 2
        return ((focal_px**2 / (focal_px**2 + r2)) ** 2).astype(np.float32)

    def blur(self, image: np.ndarray) -> np.ndarray:
        """`image` (rows, cols, …) blurred by the lens' point spread function, in place.

        The pixel values are convolved along rows and columns with a sampled Gaussian whose
        width is set so that its variance is exactly σ², σ = ``blur_sigma_px`` (a Gaussian
        sampled at σ itself loses variance below about 1 px, and σ = 0.45 px acts as
        0.38 px). Of the discrete kernels tried, this one gives patch edges closest to a
        continuous Gaussian's (:mod:`calibration.edge_blur`) and passes the least detail
        near the Nyquist frequency that a continuous Gaussian would remove. Edges repeat
        the border pixels. With no blur the image is returned as is.
        """
        if self.blur_sigma_px <= 0:
            return image
        kernel = _variance_matched_gaussian(self.blur_sigma_px)
        for axis in (0, 1):
            ndimage.correlate1d(image, kernel, axis=axis, output=image, mode="nearest")
        return image


def _sampled_gaussian(width: float) -> np.ndarray:
    reach = int(np.ceil(4.0 * width)) + 1
    n = np.arange(-reach, reach + 1)
    kernel = np.exp(-0.5 * (n / width) ** 2)
    return kernel / kernel.sum()


def _variance(kernel: np.ndarray) -> float:
    n = np.arange(kernel.size) - kernel.size // 2
    return float(np.sum(kernel * n * n))


@functools.lru_cache(maxsize=16)
def _variance_matched_gaussian(sigma: float) -> np.ndarray:
    """A sampled Gaussian kernel of variance σ² (its width ≥ σ, equal above about 1 px)."""
    width = optimize.brentq(lambda w: _variance(_sampled_gaussian(w)) - sigma**2, 0.05, sigma + 1)
    return _sampled_gaussian(width)
