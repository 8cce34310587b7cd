"""The simulated rig: scenes, lens, sensor, camera and the filter-slider simulators.

Everything renders at finer spatial (exact pixel-area coverage) and spectral (≤ 2 nm)
resolution than any reconstruction model uses, so tests commit no inverse crime.
"""

from labkit.sim._pty import PtySerialSimulator
from labkit.sim.camera import SimCamera
from labkit.sim.elliptec import ElliptecSimulator
from labkit.sim.fw102c import FW102CSimulator
from labkit.sim.lens import SELLMEIER, Lens, refractive_index
from labkit.sim.plans import simulated_plans
from labkit.sim.render import render_irradiance
from labkit.sim.scenes import (
    SCENES,
    CellGrid,
    DiskGrid,
    Scene,
    colorchecker_chart,
    colorchecker_patch_boxes,
    disk_pattern,
    flat_field,
    natural_scene,
    textured_scene,
)
from labkit.sim.sensor import Sensor, SensorModel
from labkit.sim.world import DARK, SimulatedRig

__all__ = [
    "DARK",
    "SCENES",
    "SELLMEIER",
    "CellGrid",
    "DiskGrid",
    "ElliptecSimulator",
    "FW102CSimulator",
    "Lens",
    "PtySerialSimulator",
    "Scene",
    "Sensor",
    "SensorModel",
    "SimCamera",
    "SimulatedRig",
    "colorchecker_chart",
    "colorchecker_patch_boxes",
    "disk_pattern",
    "flat_field",
    "natural_scene",
    "refractive_index",
    "render_irradiance",
    "simulated_plans",
    "textured_scene",
]
