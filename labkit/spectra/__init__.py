"""Spectral core: sampled spectra, datasets, filters, light sources and colour conversion."""

from labkit.spectra.container import Spectra, hat_weights, trapezoid_weights, wavelength_grid
from labkit.spectra.conversion import (
    integration_matrix,
    spectral_to_raw,
    spectral_to_srgb,
    spectral_to_xyz,
    xyz_to_srgb,
)
from labkit.spectra.datasets import (
    COLORCHECKER_PATCHES,
    MEASURED_FILTER_COLUMNS,
    camera_response,
    cie_1931_cmfs,
    colorchecker_reflectances,
    lab_spectra,
    write_response_csv,
)
from labkit.spectra.filters import (
    BandpassFilter,
    filter_spectra,
    measured_transmission,
    parametric_transmission,
)
from labkit.spectra.illuminants import illuminant, uhp_lamp

__all__ = [
    "COLORCHECKER_PATCHES",
    "MEASURED_FILTER_COLUMNS",
    "BandpassFilter",
    "Spectra",
    "camera_response",
    "cie_1931_cmfs",
    "colorchecker_reflectances",
    "filter_spectra",
    "hat_weights",
    "illuminant",
    "integration_matrix",
    "lab_spectra",
    "measured_transmission",
    "parametric_transmission",
    "spectral_to_raw",
    "spectral_to_srgb",
    "spectral_to_xyz",
    "trapezoid_weights",
    "uhp_lamp",
    "wavelength_grid",
    "write_response_csv",
    "xyz_to_srgb",
]
