"""From HDR images of a calibration scene to a dispersion model (thesis §3.2, Appendix B).

:func:`calibrate_dispersion` runs the whole chain behind ``labkit calibrate dispersion``:

1. choose the bands — each filtered image is labelled with its effective wavelength
   (:mod:`calibration.bands`) and bands dominated by out-of-band leakage are left out;
2. optionally correct each image for vignetting (§3.2.2), fitted on the background of
   the disk pattern;
3. keypoints — disk centres (§3.2.1) or patch-wise registration (§3.2.3);
4. a polynomial (Algorithm 1) or thin-plate spline (Algorithm 2) model (§3.2.4).

With ``reference="G"`` it calibrates colour-channel dispersion (R and B relative to G)
from one unfiltered image instead, as Rudakova and Monasse do.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np

from calibration._hdr_inputs import source_of
from calibration.bands import FilterBand
from calibration.disks import background_mask, channel_disk_keypoints, disk_keypoints
from calibration.dispersion_model import DispersionModel
from calibration.keypoints import DispersionKeypoints
from calibration.polynomial import fit_polynomial_model
from calibration.registration import channel_registration_keypoints, registration_keypoints
from calibration.spline import fit_spline_model
from calibration.vignetting import fit_vignetting
from labkit.blas_threads import fixed_blas_threads
from labkit.errors import DataError
from labkit.io.exr import RawImage

#: Bands whose recorded signal is less in-band than this are left out by default. Chosen
#: between the leak-dominated and the clean bands of both the simulated rig and the real
#: frames, with their measured purities (docs/data.md, "Band selection") on either side.
MIN_PURITY = 0.8
CHANNELS = ("R", "G", "B")

ModelType = Literal["polynomial", "spline"]
KeypointMethod = Literal["disks", "registration"]


@dataclass(frozen=True)
class BandUse:
    """How one image entered the calibration."""

    illumination: str
    file: str
    nominal_nm: float | None
    wavelength_nm: float | None
    purity: float | None
    used: bool
    reason: str = ""


@dataclass
class DispersionCalibration:
    """Result of :func:`calibrate_dispersion`."""

    model: DispersionModel
    keypoints: DispersionKeypoints
    bands: list[BandUse]
    warnings: list[str] = field(default_factory=list)


@fixed_blas_threads
def calibrate_dispersion(
    images: Sequence[RawImage],
    *,
    reference: str | float,
    model: ModelType = "polynomial",
    keypoints: KeypointMethod = "disks",
    direction: str = "from_reference",
    bands: Mapping[str, FilterBand] | None = None,
    min_purity: float = MIN_PURITY,
    vignetting: Literal["none", "auto"] = "none",
    rng: np.random.Generator | None = None,
    workers: int | None = None,
    progress: Callable[[str], None] | None = None,
) -> DispersionCalibration:
    """Calibrate a dispersion model from HDR images of one scene.

    Parameters
    ----------
    images : sequence of RawImage
        Filtered images of the scene (spectral model), or images including exactly one
        unfiltered image when `reference` is a colour channel.
    reference : str or float
        Reference band: an illumination name (``"600"``), a nominal wavelength in nm
        (600), or ``"G"`` for a colour-channel model from the unfiltered image.
    model : {"polynomial", "spline"}
    keypoints : {"disks", "registration"}
    direction : {"from_reference", "to_reference"}
    bands : mapping of illumination to FilterBand, optional
        Effective wavelengths and purities (from the rig, :func:`filter_bands`). Without
        them keypoints are labelled with the images' nominal wavelengths.
    min_purity : float
        Leave out bands whose in-band signal fraction is lower (0 keeps every band).
    vignetting : {"none", "auto"}
        ``"auto"`` fits a vignetting model to each image's background (disk scenes) or
        to the whole image (other scenes) and divides it out before finding keypoints.
    rng : numpy.random.Generator, optional
        Cross-validation folds (default: seeded 2019).
    workers : int, optional
        Processes for the disk fits (default: CPU count).
    progress : callable, optional
        Called with a short message before each step.

    Returns
    -------
    DispersionCalibration

    Raises
    ------
    DataError
        No usable images, an unknown or impure reference band, too few bands, or any
        error of the keypoint and model steps (they name the image or band).
    """
    if not images:
        raise DataError("no HDR images to calibrate from")
    rng = rng if rng is not None else np.random.default_rng(2019)
    say = progress or (lambda message: None)
    if model not in ("polynomial", "spline"):
        raise DataError(f"model must be polynomial or spline, not {model!r}")
    if keypoints not in ("disks", "registration"):
        raise DataError(f"keypoints must be disks or registration, not {keypoints!r}")
    colour = isinstance(reference, str) and reference.upper() in CHANNELS
    warnings: list[str] = []
    if colour:
        chosen, table = _unfiltered_image(images, str(reference).upper())
        chosen = [_corrected(image, vignetting, say) for image in chosen]
        say(f"{keypoints} keypoints between colour channels of {source_of(chosen[0])}")
        points = _channel_keypoints(chosen[0], keypoints, workers)
    else:
        chosen, table, reference_nm, wavelengths = _filtered_images(
            images, reference, bands, min_purity, warnings
        )
        chosen = [_corrected(image, vignetting, say) for image in chosen]
        say(f"{keypoints} keypoints in {len(chosen)} bands, reference {reference_nm:.1f} nm")
        points = _spectral_keypoints(chosen, keypoints, reference_nm, wavelengths, workers)
    say(f"fitting a {model} model to {len(points)} keypoints")
    if model == "polynomial":
        fitted = fit_polynomial_model(points, direction=direction, rng=rng)
    else:
        fitted = fit_spline_model(points, direction=direction, rng=rng)
    provenance = dict(fitted.provenance)
    provenance.update(
        {
            "keypoint_method": keypoints,
            "vignetting": vignetting,
            "bands_table": [band.__dict__ for band in table],
            "warnings": warnings,
        }
    )
    fitted = replace(fitted, provenance=provenance)
    return DispersionCalibration(fitted, points, table, warnings)


def _unfiltered_image(
    images: Sequence[RawImage], channel: str
) -> tuple[list[RawImage], list[BandUse]]:
    if channel != "G":
        raise DataError(
            f"the colour-channel reference must be G (the densest channel), not {channel}"
        )
    open_images = [image for image in images if image.wavelength_nm is None]
    if len(open_images) != 1:
        names = [source_of(image) for image in open_images] or ["none"]
        raise DataError(
            f"a colour-channel model needs exactly one unfiltered image of the scene; found "
            f"{len(open_images)}: {', '.join(names)}"
        )
    image = open_images[0]
    use = BandUse(image.illumination, source_of(image), None, None, None, True)
    return [image], [use]


def _filtered_images(
    images: Sequence[RawImage],
    reference: str | float,
    bands: Mapping[str, FilterBand] | None,
    min_purity: float,
    warnings: list[str],
) -> tuple[list[RawImage], list[BandUse], float, dict[str, float]]:
    filtered = [image for image in images if image.wavelength_nm is not None]
    if not filtered:
        raise DataError(
            "no filtered images to calibrate spectral dispersion from; capture the disk scene "
            "under the bandpass filters, or use --reference G for a colour-channel model"
        )
    ref_image = _find_reference(filtered, reference)
    table: list[BandUse] = []
    chosen: list[RawImage] = []
    wavelengths: dict[str, float] = {}
    for image in filtered:
        band = bands.get(image.illumination) if bands is not None else None
        wavelength = band.effective_nm if band is not None else float(image.wavelength_nm)
        purity = band.purity if band is not None else None
        reason = ""
        if band is None and bands is not None:
            reason = "not in the rig; labelled with its nominal wavelength"
        used = purity is None or purity >= min_purity
        if band is not None and used:
            reason = band.explain()
        if not used:
            reason = (
                f"only {band.explain()} (effective {wavelength:.1f} nm); out-of-band leakage "
                f"dominates"
            )
            if image is ref_image:
                raise DataError(
                    f"reference band {image.illumination} ({source_of(image)}): {reason}; "
                    "choose another --reference or lower --min-purity"
                )
            warnings.append(f"band {image.illumination} left out: {reason}")
        table.append(
            BandUse(
                image.illumination,
                source_of(image),
                float(image.wavelength_nm),
                wavelength,
                purity,
                used,
                reason,
            )
        )
        if used:
            chosen.append(image)
            wavelengths[image.illumination] = wavelength
    if len(chosen) < 2:
        raise DataError(
            f"only {len(chosen)} usable filtered band(s); a spectral model needs the reference "
            "and at least one more band (three or more for a polynomial in wavelength)"
        )
    return chosen, table, wavelengths[ref_image.illumination], wavelengths


def _find_reference(filtered: Sequence[RawImage], reference: str | float) -> RawImage:
    for image in filtered:
        if isinstance(reference, str) and image.illumination == reference:
            return image
    try:
        target = float(reference)
    except (TypeError, ValueError):
        target = None
    if target is not None:
        matches = [image for image in filtered if abs(image.wavelength_nm - target) <= 0.5]
        if len(matches) == 1:
            return matches[0]
    available = ", ".join(
        f"{image.illumination} ({image.wavelength_nm:g} nm)" for image in filtered
    )
    raise DataError(f"reference band {reference!r} not found; available: {available}")


def _corrected(image: RawImage, vignetting: str, say: Callable[[str], None]) -> RawImage:
    if vignetting == "none":
        return image
    if vignetting != "auto":
        raise DataError(f"vignetting must be none or auto, not {vignetting!r}")
    name = source_of(image)
    say(f"vignetting correction of {name}")
    try:
        mask = background_mask(image.raw, cfa=image.cfa)
    except DataError:
        mask = None  # not a disk scene: fit the whole image
    fitted = fit_vignetting(image.raw, cfa=image.cfa, mask=mask, name=name)
    return replace(image, raw=fitted.correct(image.raw).astype(np.float32))


def _spectral_keypoints(
    images: Sequence[RawImage],
    method: str,
    reference_nm: float,
    wavelengths: Mapping[str, float],
    workers: int | None,
) -> DispersionKeypoints:
    if method == "disks":
        return disk_keypoints(
            images, reference_nm=reference_nm, wavelengths=wavelengths, workers=workers
        )
    return registration_keypoints(images, reference_nm=reference_nm, wavelengths=wavelengths)


def _channel_keypoints(image: RawImage, method: str, workers: int | None) -> DispersionKeypoints:
    if method == "disks":
        return channel_disk_keypoints(image, workers=workers)
    return channel_registration_keypoints(image)


def band_table(calibration: DispersionCalibration) -> str:
    """The bands of a calibration as aligned text (for the command line)."""
    lines = [f"{'band':>10} {'nominal':>9} {'effective':>10} {'purity':>7}  used"]
    for band in calibration.bands:
        nominal = "—" if band.nominal_nm is None else f"{band.nominal_nm:g}"
        effective = "—" if band.wavelength_nm is None else f"{band.wavelength_nm:.1f}"
        purity = "—" if band.purity is None else f"{band.purity:.1%}"
        used = ("yes" if band.used else "no") + (f": {band.reason}" if band.reason else "")
        lines.append(f"{band.illumination:>10} {nominal:>9} {effective:>10} {purity:>7}  {used}")
    return "\n".join(lines)


def summary(calibration: DispersionCalibration) -> dict[str, Any]:
    """Short model-selection summary for printing."""
    selection = calibration.model.selection
    keys = ("method", "degree_xy", "degree_lambda", "degree", "smoothing", "condition_number")
    return {key: selection[key] for key in keys if key in selection}
