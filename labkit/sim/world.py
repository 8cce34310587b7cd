"""The simulated rig: what the camera sees, built from a rig description.

:class:`SimulatedRig` owns the lens, the sensor, the scenes and the light, and caches the
noise-free mosaic irradiance of each (scene, illumination) so that every further frame
only applies exposure, noise, saturation and quantisation.
"""

from __future__ import annotations

import math
import threading

import numpy as np

from labkit.cfa import mosaic
from labkit.errors import ConfigError
from labkit.rig import Rig, SimSceneConfig
from labkit.sim.lens import Lens
from labkit.sim.render import render_irradiance
from labkit.sim.scenes import SCENES, Scene, flat_field
from labkit.sim.sensor import Sensor, SensorModel
from labkit.spectra import camera_response, illuminant, trapezoid_weights, wavelength_grid

DARK = "dark"


class SimulatedRig:
    """The physics of a simulated rig.

    Parameters
    ----------
    rig : Rig
        A validated rig whose camera backend is ``sim``.
    shape : (rows, cols) or None
        Override the sensor size (e.g. a small sensor for quick tests).
    """

    def __init__(self, rig: Rig, *, shape: tuple[int, int] | None = None) -> None:
        if rig.sim is None:
            raise ConfigError(f"rig {rig.source or rig.name} has no `sim` section")
        self.rig = rig
        sim = rig.sim
        sensor_cfg = sim.sensor.model_dump()
        if shape is not None:
            sensor_cfg["height"], sensor_cfg["width"] = shape
        self.sensor = Sensor(SensorModel(cfa=rig.cfa, **sensor_cfg), seed=sim.seed)
        self.shape = self.sensor.model.shape
        self.lens = Lens(self.shape, **sim.lens.model_dump())
        self.wavelengths = wavelength_grid(380.0, 780.0, sim.spectral_step_nm)
        self.response = camera_response(rig.response_source())
        self.lamp = illuminant(rig.light.source, self.wavelengths).values[:, 0]
        self._scale = self._electron_scale()
        self._scenes: dict[str, Scene] = {}
        self._cache: dict[tuple[str, str], np.ndarray] = {}
        self._lock = threading.Lock()

    # -- light ----------------------------------------------------------------------
    def _electron_scale(self) -> float:
        q = self.response.select(["R", "G", "B"]).resample(self.wavelengths).values
        white = (q * (self.lamp * trapezoid_weights(self.wavelengths))[:, None]).sum(axis=0)
        return self.rig.sim.light.white_rate_e_per_s / float(white.max())

    def illuminations(self) -> list[str]:
        """All illumination names: the slider positions, then ``"dark"``."""
        return [*self.rig.slider.illumination_names(), DARK]

    def light(self, illumination: str) -> np.ndarray | None:
        """Light reaching the scene, electron-scaled, on :attr:`wavelengths` (None = dark)."""
        if illumination == DARK:
            return None
        filt = self.rig.filter_for(illumination)
        spectrum = self.lamp * self._scale
        return spectrum if filt is None else spectrum * filt.transmission(self.wavelengths)

    def light_level(self, device_time_s: float, rng: np.random.Generator) -> float:
        """Relative lamp output at a device time (slow drift and frame-to-frame flicker)."""
        cfg = self.rig.sim.light
        drift = cfg.drift_amplitude * math.sin(2 * math.pi * device_time_s / cfg.drift_period_s)
        return max(1.0 + drift + cfg.flicker * float(rng.standard_normal()), 0.0)

    # -- scenes ---------------------------------------------------------------------
    def scene_names(self) -> list[str]:
        """Names of the scenes this rig can show."""
        return list(self.rig.sim.scenes)

    def scene(self, name: str) -> Scene:
        """The named scene, built on first use."""
        if name not in self._scenes:
            if name not in self.rig.sim.scenes:
                raise ConfigError(
                    f"rig {self.rig.source or self.rig.name} defines no scene {name!r}; "
                    f"use one of {self.scene_names()}"
                )
            self._scenes[name] = _build_scene(self.rig.sim.scenes[name], self.shape)
        return self._scenes[name]

    # -- irradiance ----------------------------------------------------------------------
    def irradiance(self, scene: str, illumination: str) -> np.ndarray | None:
        """Noise-free mosaic irradiance (rows, cols), e⁻/s per pixel; None for dark."""
        if illumination == DARK:
            return None
        key = (scene, illumination)
        if key not in self._cache:
            self.prerender(scene, [illumination])
        return self._cache[key]

    def prerender(self, scene: str, illuminations: list[str]) -> None:
        """Render and cache several illuminations of a scene together (cheaper than apart)."""
        with self._lock:
            todo = [i for i in illuminations if i != DARK and (scene, i) not in self._cache]
            if not todo:
                return
            images = self.render_rgb(scene, todo)
            for name, rgb in images.items():
                self._cache[(scene, name)] = np.ascontiguousarray(mosaic(rgb, self.rig.cfa))

    def render_rgb(self, scene: str, illuminations: list[str]) -> dict[str, np.ndarray]:
        """Noise-free irradiance of every channel (rows, cols, 3), e⁻/s (not cached)."""
        lights = {name: self.light(name) for name in illuminations}
        if any(light is None for light in lights.values()):
            raise ConfigError("'dark' has no irradiance to render")
        return render_irradiance(
            self.scene(scene),
            self.lens,
            self.response,
            lights,
            self.wavelengths,
            level_step_px=self.rig.sim.level_step_px,
        )

    def exposure_fraction(
        self, scene: str | None, illumination: str, exposure_s: float, *, gain_db: float = 0.0
    ) -> np.ndarray:
        """Ground truth: noise-free dark-subtracted signal as a fraction of the saturation range.

        Returns (rows, cols); 1.0 is a full pixel (full well or ADC limit). Shutter
        jitter, flicker and blooming are left out.
        """
        model = self.sensor.model
        irradiance = None if scene is None else self.irradiance(scene, illumination)
        electrons = self.sensor.mean_electrons(irradiance, exposure_s)
        gain = model.gain_factor(gain_db)
        full = min(model.full_well_e * gain, model.adc_max - model.black_level_dn)
        return electrons * np.float32(gain / full)

    def clear_cache(self) -> None:
        """Forget cached irradiance (frees memory)."""
        with self._lock:
            self._cache.clear()


_SCENE_BUILDERS = {**SCENES, "flat": flat_field}


def _build_scene(cfg: SimSceneConfig, shape: tuple[int, int]) -> Scene:
    return _SCENE_BUILDERS[cfg.type](shape, **cfg.options())
