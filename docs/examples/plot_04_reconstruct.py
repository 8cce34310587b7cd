"""
Reconstruct a spectral image from one raw image
===============================================

:func:`reconstruction.reconstruct` solves the thesis' problem (3.1) patch by patch: the
spectral image whose colour, after the lens' calibrated dispersion and the Bayer mosaic,
matches one raw image, with a spatial prior and non-negativity. Its inputs are the raw
mosaic and its CFA layout, the camera response and a ``to_reference`` dispersion model;
``labkit reconstruct`` is the same job from files. Here the simulated rig captures the
disk pattern (to calibrate) and the ColorChecker (to reconstruct) on a 192 × 256 sensor.
"""

import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from calibration import calibrate_dispersion, filter_bands, load_scene_hdr
from labkit.hdr import run_hdr
from labkit.io import read_raw_exr, spectral_preview
from labkit.protocol import Engine
from labkit.protocol.hardware import open_hardware
from labkit.rig import default_rig_path, load_rig
from labkit.session import Session
from labkit.sim import SimulatedRig, colorchecker_patch_boxes, simulated_plans
from labkit.sim.truth import spectral_truth
from reconstruction import ReconstructOptions, reconstruct

workspace = tempfile.TemporaryDirectory(prefix="labkit-gallery-")  # removed at the end
out = Path(workspace.name)
rigs = simulated_plans(load_rig(default_rig_path()), (192, 256))  # "calibration" and "scenes" plans
world = SimulatedRig(rigs["scenes"])

# %%
# Capture, merge and calibrate
# ----------------------------
# As in the previous examples, but the dispersion model maps each band's positions back
# to the reference band (``direction="to_reference"``), the direction of the image
# formation model.
for name, rig in rigs.items():
    session, _ = Session.open_for(out / name, rig)
    with open_hardware(rig, fast=True) as hardware:
        Engine(rig, hardware.camera, hardware.slider, hardware.stage, session).run()
run_hdr([out / name for name in rigs], out / "hdr", previews=False)  # one folder, one set
disks = load_scene_hdr(out / "hdr", "disks")
bands = filter_bands(rigs["calibration"], images=disks)
model = calibrate_dispersion(
    disks, reference="600", bands=bands, direction="to_reference", workers=2
).model

# %%
# Reconstruct
# -----------
# :class:`~reconstruction.ReconstructOptions` checks every option before any work; the
# defaults are the edge-guided L2 prior (``EdgeL2``: the thesis' L2 prior weighted by
# the raw image's own edges), non-negativity, spectral smoothness and weights chosen by
# the demosaicing criterion (thesis Algorithm 3). The bands default to the response's
# bandlimit.
image = read_raw_exr(out / "hdr" / "colorchecker" / "unfiltered.exr")
options = ReconstructOptions(cfa=image.cfa, response=world.response, dispersion=model)
result = reconstruct(image.raw, options)
result.save(out / "reconstruction")  # spectral.exr, raw_colour.exr, preview.png, log.json
patches = result.log["patches"]
print("bands (nm):", np.round(result.wavelengths_nm, 1))
print("weight:", result.log["weights"]["values"], "| patches:", patches["count"])
print("patches using Φ:", patches["phi_used"], "| flat:", patches["flat"])

# %%
# The raw image and the spectral image
# ------------------------------------
# The spectral image is shown as sRGB (CIE 1931; the simulated lamp is not white and
# nothing is white-balanced), next to the raw mosaic it came from, and three of its bands.
figure, axes = plt.subplots(1, 5, figsize=(14, 2.8))
axes[0].imshow(image.raw, cmap="gray")
axes[0].set_title(f"raw mosaic ({image.cfa})")
axes[1].imshow(spectral_preview(result.spectral, result.wavelengths_nm).image)
axes[1].set_title("reconstruction, sRGB")
for axis, index in zip(axes[2:], [1, len(result.wavelengths_nm) // 2, -2], strict=True):
    axis.imshow(result.spectral[..., index], cmap="gray")
    axis.set_title(f"band {result.wavelengths_nm[index]:.0f} nm")
for axis in axes:
    axis.set_axis_off()
figure.tight_layout()

# %%
# Patch spectra against the truth
# -------------------------------
# The simulator knows each patch's reflectance and the light, so the mean spectrum in a
# patch's centre can be compared with the truth, after one least-squares scale per band
# (the reconstruction's units are not the simulator's; thesis eq. 4.9).
boxes = colorchecker_patch_boxes(world.scene("colorchecker"))
chosen = {"blue sky": 2, "yellow green": 10, "red": 14, "white": 18}
bands_nm = np.asarray(result.wavelengths_nm)
estimate, truth = [], []
for index in chosen.values():
    x0, y0, x1, y1 = boxes[index]
    cy, cx, half = round((y0 + y1) / 2), round((x0 + x1) / 2), max(2, round((x1 - x0) / 4))
    yy, xx = np.mgrid[cy - half : cy + half, cx - half : cx + half]  # the patch's centre
    pixels = (yy.ravel(), xx.ravel())
    estimate.append(result.spectral[pixels].mean(axis=0))
    truth.append(spectral_truth(world, "colorchecker", bands_nm, pixels=pixels).mean(axis=0))
estimate, truth = np.array(estimate), np.array(truth)
scale = (estimate * truth).sum(axis=0) / (estimate * estimate).sum(axis=0)

figure, axes = plt.subplots(1, len(chosen), figsize=(13, 2.8), sharey=True)
for axis, name, e, t in zip(axes, chosen, estimate * scale, truth, strict=True):
    axis.plot(bands_nm, t, "k-", label="truth")
    axis.plot(bands_nm, e, "o-", label="reconstruction")
    axis.set_title(name)
    axis.set_xlabel("wavelength (nm)")
axes[0].set_ylabel("relative radiance")
axes[0].legend(fontsize=8)
figure.tight_layout()

workspace.cleanup()  # the files written above were only for this example
