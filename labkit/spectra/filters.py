"""Bandpass filters: measured (thesis lab data) and parametric interference filters."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from labkit.errors import DataError
from labkit.spectra.container import Spectra
from labkit.spectra.datasets import MEASURED_FILTER_COLUMNS, lab_spectra


@dataclass(frozen=True)
class BandpassFilter:
    """An optical bandpass filter.

    Attributes
    ----------
    centre_nm, fwhm_nm : float
        Nominal centre wavelength and full width at half maximum, nm.
    optical_density : float
        Out-of-band blocking, OD (transmission floor 10**-OD).
    peak_transmission : float
        In-band transmission, 0–1 (parametric filters only).
    measured : str or None
        Column of the lab file to use instead of the parametric shape.
    """

    centre_nm: float
    fwhm_nm: float = 10.0
    optical_density: float = 4.0
    peak_transmission: float = 0.85
    measured: str | None = None

    def transmission(self, wavelengths: np.ndarray) -> np.ndarray:
        """Transmission (0–1) at `wavelengths` (nm)."""
        if self.measured is not None:
            return measured_transmission(
                self.measured, wavelengths, optical_density=self.optical_density
            )
        return parametric_transmission(
            wavelengths,
            centre_nm=self.centre_nm,
            fwhm_nm=self.fwhm_nm,
            optical_density=self.optical_density,
            peak=self.peak_transmission,
        )


def parametric_transmission(
    wavelengths: np.ndarray,
    *,
    centre_nm: float,
    fwhm_nm: float,
    optical_density: float = 4.0,
    peak: float = 0.85,
) -> np.ndarray:
    """A flat-topped (4th-order super-Gaussian) interference-filter passband.

    Returns transmission on `wavelengths` (nm); the out-of-band floor is 10**-OD.
    """
    if fwhm_nm <= 0 or not 0 < peak <= 1 or optical_density < 0:
        raise DataError(
            f"filter at {centre_nm} nm: need FWHM > 0 nm, 0 < peak ≤ 1 and OD ≥ 0 "
            f"(got FWHM {fwhm_nm}, peak {peak}, OD {optical_density})"
        )
    w = np.asarray(wavelengths, dtype=np.float64)
    shape = np.exp(-np.log(2.0) * np.abs(2.0 * (w - centre_nm) / fwhm_nm) ** 4)
    return np.maximum(peak * shape, 10.0**-optical_density)


def measured_transmission(
    column: str,
    wavelengths: np.ndarray,
    *,
    optical_density: float = 4.0,
    noise_floor: float = 0.05,
) -> np.ndarray:
    """Transmission of a filter measured in the thesis' lab (relative to the lamp).

    The spectrometer readings far from the passband are noise (0.1–9 % of the peak,
    rising where the lamp is dim), so values below `noise_floor` × peak are replaced by
    the filter's blocking level 10**-OD, and so are runs above that floor whose maximum
    stays under 2 × `noise_floor` × peak (noise, e.g. the 700 nm filter's readings near
    780 nm). Real secondary peaks, such as the 450 nm filter's near 390 nm (≈ 20 % of
    its peak), are kept.
    """
    if column not in MEASURED_FILTER_COLUMNS:
        raise DataError(
            f"no measured filter {column!r}; the lab file has {list(MEASURED_FILTER_COLUMNS)}"
        )
    data = lab_spectra().select([column]).resample(wavelengths, extrapolate="zero")
    values = np.clip(data.values[:, 0], 0.0, None)
    floor = 10.0**-optical_density
    peak = values.max()
    runs, count = ndimage.label(values >= noise_floor * peak)
    run_max = ndimage.maximum(values, runs, index=np.arange(1, count + 1))
    keep = np.isin(runs, 1 + np.flatnonzero(np.asarray(run_max) >= 2 * noise_floor * peak))
    values[~keep] = floor
    return np.maximum(values, floor)


def filter_spectra(filters: dict[str, BandpassFilter], wavelengths: np.ndarray) -> Spectra:
    """Transmissions of several named filters on one grid (nm)."""
    values = np.column_stack([f.transmission(wavelengths) for f in filters.values()])
    return Spectra(np.asarray(wavelengths, dtype=np.float64), values, tuple(filters))
