"""Linear operators of problem (3.1): M, Ω, Φ, B and the priors' differences (thesis §3.2–3.5).

Contents
--------
:class:`LinearOperator`, :func:`dot_test`
    The base class (forward, adjoint, composition with ``@``, ``.T``) and the dot test.
:class:`Mosaic` (M, §3.4)
    Colour image → Bayer mosaic, any of the four layouts.
:class:`SpectralToColour` (Ω, §3.3.1, (3.6))
    Spectral bands → raw colour channels by the trapezoid rule over the camera response.
:class:`SpectralBasis`, :func:`choose_bands` (B, §3.3.2–3.3.3, (3.8)–(3.12))
    Band centres from the response's support and bandlimit; Gaussian (or sinc) kernels.
:class:`Dispersion`, :func:`dispersion_samples` (Φ, §3.2.5)
    Bilinear warping by a ``to_reference`` model, per patch; spectral sampling that keeps
    consecutive bands ≤ 0.1 px apart.
:class:`Gradient`, :class:`SpectralGradient`, :class:`Laplacian` (§3.5, (3.15)–(3.20))
    Periodic (default) or Neumann differences with their Fourier symbols.
:class:`WeightedGradient`
    ∇xy weighted per pixel and direction (the edge-guided L2 prior).
:class:`SpectralDifference`, :class:`SpectralRoughness`, :func:`smoothest_metamer`
    Per-pixel spectral roughness (the spectral smoothness term beyond the thesis); the
    latter never pulls the patch's mean colour.
"""

from reconstruction.model.operators._base import (
    Adjoint,
    Composition,
    DotTest,
    LinearOperator,
    dot_test,
)
from reconstruction.model.operators.basis import BandSelection, SpectralBasis, choose_bands
from reconstruction.model.operators.colour import SpectralToColour
from reconstruction.model.operators.dispersion import Dispersion, dispersion_samples
from reconstruction.model.operators.mosaic import Mosaic
from reconstruction.model.operators.priors import (
    Gradient,
    Laplacian,
    SpectralDifference,
    SpectralGradient,
    SpectralRoughness,
    WeightedGradient,
    smoothest_metamer,
)

__all__ = [
    "Adjoint",
    "BandSelection",
    "Composition",
    "Dispersion",
    "DotTest",
    "Gradient",
    "Laplacian",
    "LinearOperator",
    "Mosaic",
    "SpectralBasis",
    "SpectralDifference",
    "SpectralGradient",
    "SpectralRoughness",
    "SpectralToColour",
    "WeightedGradient",
    "choose_bands",
    "dispersion_samples",
    "dot_test",
    "smoothest_metamer",
]
