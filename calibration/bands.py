"""What wavelength a filtered image really shows: effective band wavelengths and purity.

A disk imaged under a bandpass filter is displaced by the dispersion averaged over the
light that reaches the sensor: filter transmission × light source × camera response.
That average sits at the filter's nominal centre only if the band is narrow and clean.
It is not, when

* the light source has emission lines inside the band (a UHP lamp's 405, 436, 546 and
  578 nm mercury lines pull a 10 nm band by several nanometres),
* the filter has a secondary peak (the thesis' 450 nm filter transmits near 390 nm), or
* the camera barely responds in the band, so that the filter's out-of-band leakage
  (optical density 4 over hundreds of nanometres) carries most of the signal: with the
  simulated rig's camera, most of the "400 nm" and "700 nm" images is green light.

A dispersion model labelled with nominal centres is then wrong between bands by a
fraction of a pixel. :func:`filter_bands` returns, per filtered illumination, the
signal-weighted mean wavelength and the signal fraction inside the passband
(``purity``); calibration labels keypoints with the former and, by default, leaves out
bands whose purity is too low to stand for any one wavelength.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from labkit.rig import Rig
from labkit.spectra import camera_response, illuminant, trapezoid_weights, wavelength_grid

#: Transmission above this fraction of the filter's peak counts as in-band.
IN_BAND_FRACTION = 0.01


@dataclass(frozen=True)
class FilterBand:
    """Spectral summary of the light an image taken under one filter records.

    Attributes
    ----------
    illumination : str
        Slider position name.
    nominal_nm : float
        The filter's nominal centre wavelength, nm.
    effective_nm : float
        Mean wavelength of the recorded signal (all colour channels), nm.
    spread_nm : float
        Standard deviation of the recorded signal's wavelength, nm.
    purity : float
        Fraction of the recorded signal transmitted in-band (transmission ≥ 1 % of the
        filter's peak); the rest is out-of-band leakage.
    """

    illumination: str
    nominal_nm: float
    effective_nm: float
    spread_nm: float
    purity: float


def filter_bands(rig: Rig, *, step_nm: float = 1.0) -> dict[str, FilterBand]:
    """Effective wavelength and purity of every filtered illumination of a rig.

    Parameters
    ----------
    rig : Rig
        Supplies the filters, the light source and the camera response.
    step_nm : float
        Integration grid step, nm.

    Returns
    -------
    dict of str to FilterBand, in slider order (open positions are skipped).
    """
    wavelengths = wavelength_grid(350.0, 1000.0, step_nm)
    response = camera_response(rig.response_source()).select(["R", "G", "B"])
    q = response.resample(wavelengths, extrapolate="zero").values.sum(axis=1)
    light = illuminant(rig.light.source, wavelengths).values[:, 0]
    weights = trapezoid_weights(wavelengths)
    bands: dict[str, FilterBand] = {}
    for name in rig.slider.illumination_names():
        band = rig.filter_for(name)
        if band is None:
            continue
        transmission = band.transmission(wavelengths)
        signal = transmission * light * q * weights
        total = float(signal.sum())
        if total <= 0:
            effective, spread, purity = band.centre_nm, 0.0, 0.0
        else:
            effective = float((signal * wavelengths).sum() / total)
            spread = float(np.sqrt((signal * (wavelengths - effective) ** 2).sum() / total))
            in_band = transmission >= IN_BAND_FRACTION * transmission.max()
            purity = float(signal[in_band].sum() / total)
        bands[name] = FilterBand(name, float(band.centre_nm), effective, spread, purity)
    return bands
