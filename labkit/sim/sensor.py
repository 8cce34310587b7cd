"""The simulated image sensor: irradiance (e⁻/s) → 12-bit Bayer raw counts.

Per frame and pixel, with exposure t (plus shutter jitter) and light level L::

    mean electrons  μ = irradiance · PRNU · L · t + dark_rate · t
    electrons       e ~ Poisson(μ) + Normal(0, σ_read²)
    full well       charge above `full_well_e` blooms into the column neighbours
    counts          DN = round(e · gain + black_level), clipped to the ADC range

The shot noise is drawn exactly (Poisson) where μ < 30 e⁻ and from the matching Gaussian
Normal(μ, μ) above, where the two are indistinguishable at 12 bits; the variance model
``var(DN) = gain² (μ + σ_read²) + 1/12`` holds in both regimes below saturation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from labkit.cfa import channel_index, check_layout
from labkit.errors import ConfigError

_POISSON_BELOW_E = 30.0


@dataclass(frozen=True)
class SensorModel:
    """Parameters of the simulated sensor (units in the names)."""

    width: int = 2448
    height: int = 2048
    cfa: str = "GBRG"
    adc_bits: int = 12
    full_well_e: float = 10_000.0
    gain_dn_per_e: float = 0.40
    read_noise_e: float = 8.0
    dark_current_e_per_s: float = 5.0
    dark_current_nonuniformity: float = 0.2
    prnu: float = 0.01
    black_level_dn: float = 32.0
    bloom_fraction: float = 0.5
    exposure_jitter_s: float = 2e-5

    def __post_init__(self) -> None:
        check_layout(self.cfa)
        if self.width < 2 or self.height < 2 or self.width % 2 or self.height % 2:
            raise ConfigError(f"sensor size {self.width}×{self.height}: need even sizes ≥ 2")
        positive = {
            "full_well_e": self.full_well_e,
            "gain_dn_per_e": self.gain_dn_per_e,
        }
        for name, value in positive.items():
            if value <= 0:
                raise ConfigError(f"sensor.{name} must be > 0, got {value}")
        non_negative = {
            "read_noise_e": self.read_noise_e,
            "dark_current_e_per_s": self.dark_current_e_per_s,
            "dark_current_nonuniformity": self.dark_current_nonuniformity,
            "prnu": self.prnu,
            "black_level_dn": self.black_level_dn,
            "exposure_jitter_s": self.exposure_jitter_s,
        }
        for name, value in non_negative.items():
            if value < 0:
                raise ConfigError(f"sensor.{name} must be ≥ 0, got {value}")
        if not 0 <= self.bloom_fraction <= 1:
            raise ConfigError(f"sensor.bloom_fraction must be in [0, 1], got {self.bloom_fraction}")
        if self.adc_bits not in (8, 10, 12, 14, 16):
            raise ConfigError(f"sensor.adc_bits must be 8, 10, 12, 14 or 16, got {self.adc_bits}")

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols)."""
        return self.height, self.width

    @property
    def adc_max(self) -> int:
        """Largest ADC count."""
        return 2**self.adc_bits - 1

    def gain_factor(self, gain_db: float) -> float:
        """DN per electron at analogue gain `gain_db` (dB, 20·log10)."""
        return self.gain_dn_per_e * 10.0 ** (gain_db / 20.0)

    def saturation_dn(self, gain_db: float = 0.0) -> float:
        """Counts of a full pixel, black level included (full well or ADC limit, first hit)."""
        full = self.full_well_e * self.gain_factor(gain_db) + self.black_level_dn
        return float(min(np.floor(full + 0.5), self.adc_max))

    def expected_variance_dn(self, mean_e: np.ndarray, gain_db: float = 0.0) -> np.ndarray:
        """Poisson–Gaussian variance of the counts (DN²) for mean electrons `mean_e`."""
        g = self.gain_factor(gain_db)
        return g * g * (np.asarray(mean_e) + self.read_noise_e**2) + 1.0 / 12.0


class Sensor:
    """A sensor instance: the model plus its fixed-pattern maps (PRNU, dark current).

    Parameters
    ----------
    model : SensorModel
    seed : int
        Seeds the fixed patterns (a property of the physical sensor).
    """

    def __init__(self, model: SensorModel, *, seed: int = 0) -> None:
        self.model = model
        rng = np.random.default_rng(np.random.SeedSequence([seed, 0x5E50]))
        shape = model.shape
        self.prnu_map = (1.0 + model.prnu * rng.standard_normal(shape)).astype(np.float32)
        spread = model.dark_current_nonuniformity
        log_dark = rng.standard_normal(shape) * spread - 0.5 * spread**2  # mean 1
        self.dark_map = (model.dark_current_e_per_s * np.exp(log_dark)).astype(np.float32)
        self.channels = channel_index(model.cfa, shape)

    def mean_electrons(
        self, irradiance: np.ndarray | None, exposure_s: float, *, light_level: float = 1.0
    ) -> np.ndarray:
        """Expected electrons (rows, cols) for mosaic irradiance in e⁻/s (None = dark)."""
        mean = self.dark_map * np.float32(exposure_s)
        if irradiance is not None:
            mean += irradiance * self.prnu_map * np.float32(exposure_s * light_level)
        return mean

    def expose(
        self,
        irradiance: np.ndarray | None,
        exposure_s: float,
        *,
        rng: np.random.Generator,
        gain_db: float = 0.0,
        light_level: float = 1.0,
    ) -> tuple[np.ndarray, float]:
        """Simulate one frame.

        Parameters
        ----------
        irradiance : ndarray (rows, cols) float32 or None
            Mosaic irradiance, e⁻/s per pixel; None when the light is covered (dark frame).
        exposure_s : float
            Requested exposure, s.
        rng : numpy.random.Generator
            Source of all randomness of this frame.
        gain_db : float
            Analogue gain, dB.
        light_level : float
            Relative light-source output for this frame (drift).

        Returns
        -------
        counts : ndarray (rows, cols) uint16
            ADC counts.
        actual_exposure_s : float
            The exposure the shutter really gave (with jitter), s.
        """
        model = self.model
        if exposure_s <= 0:
            raise ConfigError(f"exposure must be > 0 s, got {exposure_s}")
        jitter = model.exposure_jitter_s * float(rng.standard_normal())
        actual = max(exposure_s + jitter, 0.5 * exposure_s)
        mean = self.mean_electrons(irradiance, actual, light_level=light_level)
        noise = rng.standard_normal(mean.shape, dtype=np.float32)
        electrons = mean + np.sqrt(mean + np.float32(model.read_noise_e**2)) * noise
        low = np.flatnonzero(mean < _POISSON_BELOW_E)
        if low.size:
            shot = rng.poisson(mean.ravel()[low]).astype(np.float32)
            electrons.ravel()[low] = shot + model.read_noise_e * noise.ravel()[low]
        electrons = self._bloom(electrons)
        counts = electrons * np.float32(model.gain_factor(gain_db)) + np.float32(
            model.black_level_dn + 0.5
        )
        np.clip(counts, 0, model.adc_max, out=counts)
        return counts.astype(np.uint16), actual

    def _bloom(self, electrons: np.ndarray) -> np.ndarray:
        """Clip at full well; spill `bloom_fraction` of the excess into the 4 neighbours.

        As in an interline CCD, 80 % of the spilled charge runs along the column.
        """
        full = np.float32(self.model.full_well_e)
        if electrons.max() <= full:
            return electrons
        for _ in range(16):
            excess = electrons - full
            np.maximum(excess, 0, out=excess)
            if not excess.any():
                break
            np.minimum(electrons, full, out=electrons)
            vertical = excess * np.float32(self.model.bloom_fraction * 0.4)
            electrons[1:] += vertical[:-1]
            electrons[:-1] += vertical[1:]
            horizontal = vertical * np.float32(0.25)
            electrons[:, 1:] += horizontal[:, :-1]
            electrons[:, :-1] += horizontal[:, 1:]
        return np.minimum(electrons, full, out=electrons)
