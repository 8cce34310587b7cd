"""
Calibrate lateral chromatic aberration
======================================

A pattern of disks is captured under every bandpass filter of the simulated rig and
merged into HDR raw images. :func:`calibration.calibrate_dispersion` finds the disk
centres in each band (keypoints), measures how far each moves against the reference
band, and fits a polynomial model of the displacement d(x, y, λ) (thesis Algorithm 1),
as ``labkit calibrate dispersion`` does. The simulated lens knows the true displacement,
so the model can be checked.
"""

import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from calibration import calibrate_dispersion, filter_bands, load_scene_hdr
from labkit.hdr import run_hdr
from labkit.protocol import Engine
from labkit.protocol.hardware import open_hardware
from labkit.rig import default_rig_path, load_rig
from labkit.session import Session
from labkit.sim import SimulatedRig, simulated_plans
from labkit.sim.truth import model_error

workspace = tempfile.TemporaryDirectory(prefix="labkit-gallery-")  # removed at the end
out = Path(workspace.name)
plans = simulated_plans(load_rig(default_rig_path()), (192, 256))
rig = plans["calibration"]  # disks, every filter

# %%
# Capture and merge
# -----------------
# The calibration plan: the disk pattern under every slider position, auto-bracketed,
# with dark frames; then one HDR raw image per filter.
session, _ = Session.open_for(out / "session", rig)
with open_hardware(rig, fast=True) as hardware:
    Engine(rig, hardware.camera, hardware.slider, hardware.stage, session).run()
run_hdr(out / "session", out / "hdr", previews=False)
images = load_scene_hdr(out / "hdr", "disks")
print([image.illumination for image in images])

# %%
# Which bands can be trusted
# --------------------------
# A filtered image records filter × lamp × camera. Where the camera barely sees the
# passband, the filter's out-of-band leakage carries most of the light, and the image
# does not stand for the filter's wavelength. :func:`calibration.filter_bands` measures
# each band's in-band fraction (purity) from the images and its effective wavelength.
bands = filter_bands(rig, images=images)
for name, band in bands.items():
    print(f"{name:>4} nm filter: effective {band.effective_nm:6.1f} nm, purity {band.purity:4.0%}")

# %%
# Calibrate
# ---------
# Disk keypoints in every band against the 600 nm band, a polynomial in (x, y, λ) with
# its degrees chosen by cross-validation. Bands below 80 % purity are left out.
result = calibrate_dispersion(images, reference="600", bands=bands, workers=2)
model = result.model
for use in result.bands:
    print(f"{use.illumination:>10}: {'used' if use.used else 'left out'} {use.reason or ''}")
print(model.selection["degree_xy"], model.selection["degree_lambda"], len(result.keypoints))
model.save(out / "dispersion.yaml")  # what `labkit reconstruct --dispersion` reads

# %%
# The keypoints and the model
# ---------------------------
# The arrows are the measured displacements (scaled up 30×); the colour is the model's
# displacement length at the band's effective wavelength.
keypoints = result.keypoints
rows, cols = model.image_shape
yy, xx = np.mgrid[0:rows:4, 0:cols:4].astype(float)
used = [b for b in result.bands if b.used and b.wavelength_nm != model.reference]
shown = [used[0], used[-1]]
figure, axes = plt.subplots(1, len(shown), figsize=(11, 3.8))
for axis, band in zip(axes, shown, strict=True):
    dx, dy = model.displacement(xx, yy, band.wavelength_nm)
    image = axis.imshow(np.hypot(dx, dy), extent=(0, cols, rows, 0), cmap="viridis")
    mine = np.isclose(keypoints.wavelength_nm, band.wavelength_nm)
    axis.quiver(
        keypoints.x[mine], keypoints.y[mine], keypoints.dx[mine], keypoints.dy[mine],
        color="white", angles="xy", scale_units="xy", scale=1 / 30,
    )  # fmt: skip
    axis.set_title(f"{band.illumination} nm filter ({band.wavelength_nm:.1f} nm)")
    figure.colorbar(image, ax=axis, label="‖d‖ (px)", shrink=0.8)
figure.tight_layout()

# %%
# Against the simulated lens
# --------------------------
# The model's displacement against the lens' true one, between the used bands.
lens = SimulatedRig(rig).lens
wavelengths = np.arange(450.0, 641.0, 10.0)
error = model_error(model, lens, float(model.reference), wavelengths, step_px=8)
print({name: round(value, 4) for name, value in error.items()})

x = np.full(wavelengths.size, cols - 20.0)
y = np.full(wavelengths.size, rows - 20.0)
true_dx, _ = lens.relative_displacement(x, y, wavelengths, reference_nm=float(model.reference))
model_dx, _ = model.displacement(x, y, wavelengths)
figure, axis = plt.subplots(figsize=(6, 3.5))
axis.plot(wavelengths, true_dx, "k-", label="simulated lens")
axis.plot(wavelengths, model_dx, "o", label="calibrated model")
axis.set_xlabel("wavelength (nm)")
axis.set_ylabel("dx near the corner (px)")
axis.legend()
figure.tight_layout()

workspace.cleanup()  # the files written above were only for this example
