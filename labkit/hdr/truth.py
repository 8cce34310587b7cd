"""Ground truth for exposure brackets merged from the simulated rig.

The simulated camera records each frame's true exposure and lamp level (``sim`` in
``frames.jsonl``), so the noise-free signal at the reference exposure and the
Cramér–Rao bound of a merge are known exactly. Used by ``labkit bench hdr`` and the tests.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from labkit.hdr.weights import DISK_1
from labkit.io.exr import RawImage
from labkit.sim.sensor import Sensor


@dataclass
class MergeTruth:
    """What a perfect merge of a bracket would give, and how well any merge can do.

    Attributes
    ----------
    signal : ndarray (rows, cols)
        Noise-free signal at the reference (shortest) exposure, fraction of saturation.
    bound : ndarray (rows, cols)
        Cramér–Rao variance of `signal` (0 outside `region`).
    region : ndarray of bool (rows, cols)
        Properly exposed pixels: some exposure puts them within [low, high] of saturation.
    """

    signal: np.ndarray
    bound: np.ndarray
    region: np.ndarray

    def relative_rms_bound(self) -> float:
        """The bound on the relative RMS error over `region` (dimensionless)."""
        region = self.region
        return float(np.sqrt(np.mean(self.bound[region] / self.signal[region] ** 2)))


def effective_exposures(
    records: Iterable[Mapping], *, illumination: str | None = None
) -> dict[float, float]:
    """Exposure (s) → mean of true exposure × lamp level over its lit frames, s.

    `records` are session manifest records of simulated frames; darks are skipped.
    """
    values: dict[float, list[float]] = {}
    for record in records:
        if record["dark"] or (illumination is not None and record["illumination"] != illumination):
            continue
        sim = record["sim"]
        values.setdefault(float(record["exposure_s"]), []).append(
            sim["true_exposure_s"] * sim["light_level"]
        )
    return {t: float(np.mean(v)) for t, v in values.items()}


def merge_truth(
    sensor: Sensor,
    rate: np.ndarray,
    effective: Mapping[float, float],
    *,
    replicates: int,
    darks: int,
    saturation_range: float,
    low: float = 0.02,
    high: float = 0.95,
) -> MergeTruth:
    """Noise-free signal and Cramér–Rao bound of a bracket merged at 0 dB gain.

    Parameters
    ----------
    sensor : Sensor
        The simulated sensor (its dark-current map and noise model).
    rate : ndarray (rows, cols)
        Signal electrons per second of every pixel, PRNU included, e⁻/s.
    effective : mapping
        Nominal exposure (s) → effective exposure (true exposure × lamp level), s.
    replicates, darks : int
        Lit and dark frames averaged per exposure.
    saturation_range : float
        Signal of a saturated pixel above black, DN.
    low, high : float
        Fractions of saturation bounding properly exposed samples.

    Notes
    -----
    The bound is that of the dark-subtracted replicate means (Gaussian, with the sensor
    model's Poisson–Gaussian variance and the dark-frame average's own noise), counting
    only samples below `high` of saturation that are not next to one above it.
    """
    model = sensor.model
    gain = model.gain_factor(0.0)
    reference = min(effective)
    truth = rate * np.float32(effective[reference] * gain / saturation_range)
    information = np.zeros(rate.shape, np.float64)
    proper = np.zeros(rate.shape, bool)
    for t, lit in sorted(effective.items()):
        signal = rate * np.float32(lit * gain)  # DN
        dark = sensor.dark_map * np.float32(t * gain)
        near = ndimage.binary_dilation(signal + dark >= high * saturation_range, DISK_1)
        constant = gain * gain * (sensor.dark_map * t + model.read_noise_e**2) + 1 / 12
        variance = (gain * signal + constant) / replicates + constant / darks
        factor = lit / effective[reference]
        information += np.where(near, 0.0, factor**2 * saturation_range**2 / variance)
        fraction = signal / saturation_range
        proper |= (fraction >= low) & (fraction <= high)
    region = proper & (information > 0)
    bound = np.zeros(rate.shape, np.float64)
    bound[region] = 1.0 / information[region]
    return MergeTruth(truth, bound, region)


def simulated_hdr_images(
    rig,
    scene: str,
    illuminations: Sequence[str],
    *,
    rng: np.random.Generator,
    replicates: int | None = None,
    darks: int = 5,
    exposures_s: Sequence[float] | None = None,
) -> list[RawImage]:
    """HDR images of a simulated scene without capturing: the truth plus merge-level noise.

    Each illumination's noise-free signal (at the rig plan's shortest exposure for that
    illumination, fraction of saturation) gets Gaussian noise with the Cramér–Rao
    variance of merging the plan's bracket (:func:`merge_truth`): what a good merge of
    a real capture delivers, in a fraction of the time. Used where a full capture would
    cost minutes (``labkit bench calibrate``).

    Parameters
    ----------
    rig : SimulatedRig
    scene : str
    illuminations : sequence of str
    rng : numpy.random.Generator
    replicates : int, optional
        Replicates per exposure (default: the rig's plan).
    darks : int
        Dark frames per exposure.
    exposures_s : sequence of float, optional
        Exposure times of every illumination's bracket, s (default: the rig plan's, which
        must then be explicit lists rather than ``auto``).

    Returns
    -------
    list of RawImage, one per illumination, labelled like ``labkit hdr`` output.
    """
    sensor = rig.sensor
    model = sensor.model
    saturation_range = model.saturation_dn() - model.black_level_dn
    rig.prerender(scene, list(illuminations))
    images = []
    for name in illuminations:
        exposures = rig.rig.exposures_for(name) if exposures_s is None else list(exposures_s)
        if exposures == "auto":
            raise ValueError(
                f"the rig plan auto-brackets {name!r}: give simulated_hdr_images the "
                "exposures_s of the bracket to simulate"
            )
        count = replicates or rig.rig.replicates_for(name)
        rate = rig.irradiance(scene, name) * sensor.prnu_map
        truth = merge_truth(
            sensor,
            rate,
            {float(t): float(t) for t in exposures},
            replicates=count,
            darks=darks,
            saturation_range=saturation_range,
        )
        noise = rng.standard_normal(rate.shape).astype(np.float32)
        # outside the region (saturated or unlit at every exposure) a merge copies the
        # shortest exposure, which clips at saturation
        raw = np.where(
            truth.region,
            truth.signal + np.sqrt(truth.bound).astype(np.float32) * noise,
            np.minimum(truth.signal, 1.0),
        )
        band = rig.rig.filter_for(name)
        images.append(
            RawImage(
                raw=raw.astype(np.float32),
                cfa=model.cfa,
                exposure_s=float(min(exposures)),
                illumination=name,
                wavelength_nm=None if band is None else float(band.centre_nm),
                variance=truth.bound.astype(np.float32),
                labkit={"scene": scene, "simulated": "merge_truth", "source_file": f"<{name}>"},
            )
        )
    return images
