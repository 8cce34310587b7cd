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

Both rest on the camera response, and a rig may name a stand-in for a sensor whose
response is unknown. Given the filtered images themselves, :func:`filter_bands` therefore
measures the purity: the leakage a band's image should hold is predicted from the rig
(it spans hundreds of nanometres, so the stand-in's broad shape suffices), put in the
images' units by the median ratio of measured to predicted brightness over the bands,
and compared with the brightness the image actually has. A band the real camera sees
much better than the stand-in says is then brighter than predicted, and its leakage a
small fraction of its signal: it is kept, and the table says why.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from calibration.sensitivity import load_response
from labkit.cfa import channel_index
from labkit.io.exr import RawImage
from labkit.rig import Rig
from labkit.spectra import illuminant, trapezoid_weights, wavelength_grid

#: Transmission above this fraction of the filter's peak counts as in-band.
IN_BAND_FRACTION = 0.01

#: Fewest filtered images whose median brightness ratio can calibrate the leakage.
MIN_EVIDENCE_BANDS = 3


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
        filter's peak); the rest is out-of-band leakage. Measured from the images when
        `source` is ``"images"``, else predicted by the camera response.
    response_purity : float
        The purity the rig's camera response predicts.
    brightness : float or None
        The image's brightness relative to the rig's prediction, in units of the
        median over the bands (1: as predicted); None without images.
    source : str
        ``"images"`` or ``"response"``: where `purity` and `effective_nm` come from.
    """

    illumination: str
    nominal_nm: float
    effective_nm: float
    spread_nm: float
    purity: float
    response_purity: float | None = None
    brightness: float | None = None
    source: str = "response"

    def explain(self) -> str:
        """Why the purity is what it is, in words (for band tables)."""
        if self.source != "images":
            return f"{self.purity:.0%} in-band by the camera response"
        predicted = self.response_purity if self.response_purity is not None else self.purity
        text = f"{self.purity:.0%} in-band by the images (the camera response predicts "
        text += f"{predicted:.0%}"
        if self.brightness is not None and not 0.5 <= self.brightness <= 2:
            text += f"; the image is {self.brightness:.2g}× as bright as predicted"
        return text + ")"


def filter_bands(
    rig: Rig, *, images: Sequence[RawImage] | None = None, step_nm: float = 1.0
) -> dict[str, FilterBand]:
    """Effective wavelength and purity of every filtered illumination of a rig.

    Parameters
    ----------
    rig : Rig
        Supplies the filters, the light source and the camera response.
    images : sequence of RawImage, optional
        HDR images of one scene under the filters (values: fraction of saturation at
        `exposure_s`). With at least :data:`MIN_EVIDENCE_BANDS` of them, the purity and
        effective wavelength of their bands are measured (see the module docstring);
        bands without an image keep the response's prediction.
    step_nm : float
        Integration grid step, nm.

    Returns
    -------
    dict of str to FilterBand, in slider order (open positions are skipped).
    """
    wavelengths = wavelength_grid(350.0, 1000.0, step_nm)
    response = load_response(rig.response_source()).select(["R", "G", "B"])
    q = response.resample(wavelengths, extrapolate="zero").values
    light = illuminant(rig.light.source, wavelengths).values[:, 0]
    weights = trapezoid_weights(wavelengths)
    bands: dict[str, FilterBand] = {}
    parts: dict[str, _Parts] = {}
    for name in rig.slider.illumination_names():
        band = rig.filter_for(name)
        if band is None:
            continue
        transmission = band.transmission(wavelengths)
        per_channel = (transmission * light * weights)[:, None] * q
        signal = per_channel.sum(axis=1)
        total = float(signal.sum())
        if total <= 0:
            effective, spread, purity = band.centre_nm, 0.0, 0.0
        else:
            effective = float((signal * wavelengths).sum() / total)
            spread = float(np.sqrt((signal * (wavelengths - effective) ** 2).sum() / total))
            in_band = transmission >= IN_BAND_FRACTION * transmission.max()
            purity = float(signal[in_band].sum() / total)
            mosaic = per_channel @ _MOSAIC_SHARE  # what a mean over the mosaic adds up
            parts[name] = _Parts(
                float(mosaic[in_band].sum()),
                float(mosaic[~in_band].sum()),
                _mean(wavelengths[in_band], signal[in_band], band.centre_nm),
                _mean(wavelengths[~in_band], signal[~in_band], effective),
            )
        bands[name] = FilterBand(
            name, float(band.centre_nm), effective, spread, purity, response_purity=purity
        )
    if images:
        bands.update(_measured(bands, parts, images))
    return bands


#: Share of each colour channel (R, G, B) in a Bayer mosaic.
_MOSAIC_SHARE = np.array([0.25, 0.5, 0.25])


@dataclass(frozen=True)
class _Parts:
    inside: float  # predicted in-band signal, relative units (mosaic mean)
    leak: float  # predicted out-of-band signal, same units
    inside_nm: float  # signal-weighted mean wavelength of each part, nm
    leak_nm: float


def _mean(wavelengths: np.ndarray, weights: np.ndarray, default: float) -> float:
    total = float(weights.sum())
    return float((weights * wavelengths).sum() / total) if total > 0 else float(default)


def _measured(
    bands: dict[str, FilterBand],
    parts: dict[str, _Parts],
    images: Sequence[RawImage],
) -> dict[str, FilterBand]:
    rates = {}
    for image in images:
        if image.illumination not in parts or not image.exposure_s:
            continue
        channels = channel_index(image.cfa, image.raw.shape)
        means = [float(np.mean(image.raw[channels == c])) for c in range(3)]
        rates[image.illumination] = float(np.dot(means, _MOSAIC_SHARE)) / image.exposure_s
    ratios = {
        name: rate / (parts[name].inside + parts[name].leak)
        for name, rate in rates.items()
        if rate > 0
    }
    if len(ratios) < MIN_EVIDENCE_BANDS:
        return {}
    scale = float(np.median(list(ratios.values())))
    measured = {}
    for name, ratio in ratios.items():
        part, band = parts[name], bands[name]
        purity = float(np.clip(1.0 - scale * part.leak / rates[name], 0.0, 1.0))
        effective = purity * part.inside_nm + (1.0 - purity) * part.leak_nm
        measured[name] = replace(
            band,
            purity=purity,
            effective_nm=float(effective),
            brightness=ratio / scale,
            source="images",
        )
    return measured
