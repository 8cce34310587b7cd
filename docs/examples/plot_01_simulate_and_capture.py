"""
Simulate a rig and capture a session
====================================

The simulated rig renders a scene through the lens (lateral chromatic aberration,
vignetting, blur), a bandpass filter and the camera's response onto a noisy Bayer sensor.
Here it is shrunk to a 128 × 160 px sensor, its scenes are rendered, one frame is grabbed
from its GenICam-style camera, and the rig's capture plan (thesis Algorithm 10:
auto-bracketed exposures, then dark frames) is run into a session folder by
:class:`labkit.protocol.Engine`, as ``labkit capture`` does.
"""

import tempfile
from collections import defaultdict
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from labkit.io.tiff import read_raw_tiff
from labkit.protocol import Engine, build_plan
from labkit.protocol.hardware import open_hardware
from labkit.rig import default_rig_path, load_rig
from labkit.session import Session
from labkit.sim import SimCamera, SimulatedRig, simulated_plans

SHAPE = (128, 160)  # sensor rows, cols (the real simulated sensor is 2048 × 2448)

# %%
# The rig and its scenes
# ----------------------
# :func:`labkit.sim.simulated_plans` makes two capture plans of ``rigs/simulated.yaml``
# with the sensor cropped to `SHAPE`: the disk pattern under every filter (for
# calibration) and the ColorChecker and a textured scene unfiltered (to reconstruct). The noise-free
# irradiance of a scene is :meth:`SimulatedRig.irradiance <labkit.sim.SimulatedRig.irradiance>`,
# a Bayer mosaic in electrons per second.
rigs = simulated_plans(load_rig(default_rig_path()), SHAPE)
rig = rigs["scenes"]
world = SimulatedRig(rig)
print(rig.name, "—", world.rig.cfa, "sensor", world.shape)

figure, axes = plt.subplots(1, 3, figsize=(10, 3))
for axis, scene in zip(axes, ["disks", "colorchecker", "texture"], strict=True):
    axis.imshow(world.irradiance(scene, "unfiltered"), cmap="gray")
    axis.set_title(f"{scene} (irradiance, e⁻/s)")
    axis.set_axis_off()
figure.tight_layout()

# %%
# One frame from the simulated camera
# -----------------------------------
# :class:`labkit.sim.SimCamera` implements the same :class:`~labkit.devices.camera.Camera`
# protocol as the GigE Vision and GenICam backends: exposure in seconds, frames with
# their metadata. ``fast=True`` skips the real exposure waits.
camera = SimCamera(world, fast=True)
camera.set_scene("colorchecker")
figure, axes = plt.subplots(1, 2, figsize=(10, 3.6))
for axis, (illumination, exposure_s) in zip(
    axes, [("unfiltered", 0.005), ("550", 0.02)], strict=True
):
    camera.set_illumination(illumination)
    frame = camera.grab(exposure_s, n=1)[0]  # a list of n Frames
    print(illumination, frame.image.dtype, frame.image.shape, "max", frame.image.max(), "DN")
    shown = axis.imshow(frame.image, cmap="gray")
    axis.set_title(f"{illumination}, {exposure_s * 1e3:g} ms (raw DN)")
    axis.set_axis_off()
    figure.colorbar(shown, ax=axis, shrink=0.8)

# %%
# The capture plan
# ----------------
# With ``exposures_s: auto`` each scene and illumination starts with a metering step;
# its exposures are chosen from metering frames while the plan runs.
print(build_plan(rig).describe())

# %%
# Capture into a session
# ----------------------
# A session is a folder: ``session.yaml`` (rig snapshot, plan, status, the chosen
# brackets), ``frames.jsonl`` (one record per stored frame) and the frames as TIFFs,
# written crash-safely; an unfinished session resumes where it stopped.
workspace = tempfile.TemporaryDirectory(prefix="labkit-gallery-")  # removed at the end
folder = Path(workspace.name) / "session"
session, resumed = Session.open_for(folder, rig)
with open_hardware(rig, fast=True) as hardware:  # camera, slider (on a pty), stage
    report = Engine(rig, hardware.camera, hardware.slider, hardware.stage, session).run()
print(report.status, report.stored_now, "frames in", f"{report.elapsed_s:.1f} s")

records = list(Session.open(folder).records.values())
exposures = defaultdict(set)
for record in records:
    label = "dark" if record["dark"] else f"{record['scene']} / {record['illumination']}"
    exposures[label].add(record["exposure_s"])
for label, times in exposures.items():
    print(f"{label:24s}", ", ".join(f"{t * 1e3:.3g} ms" for t in sorted(times)))

# %%
# The stored frames of the ColorChecker, one per exposure of its bracket: the
# auto-bracketing picks the fewest exposures that expose every pixel properly, here a
# short one for the white patch and the paper and a long one for the black patch.
chart = sorted(
    (r for r in records if r["scene"] == "colorchecker" and r["replicate"] == 0),
    key=lambda r: r["exposure_s"],
)
figure, axes = plt.subplots(1, len(chart), figsize=(3.2 * len(chart), 3), squeeze=False)
for axis, record in zip(axes[0], chart, strict=True):
    pixels, _ = read_raw_tiff(folder / record["file"])
    saturated = np.mean(pixels >= record["saturation_dn"])
    axis.imshow(pixels, cmap="gray")
    axis.set_title(f"{record['exposure_s'] * 1e3:.3g} ms, {saturated:.0%} saturated")
    axis.set_axis_off()
figure.tight_layout()

workspace.cleanup()  # the files written above were only for this example
