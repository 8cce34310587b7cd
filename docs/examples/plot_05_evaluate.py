"""
Evaluate against the truth and the baselines
============================================

How much lateral chromatic aberration is left in a colour image, and how close are its
colours and spectra to the truth? :func:`reconstruction.evaluate` scores named estimates
of one raw image side by side (thesis §4.4): the residual aberration in strips inside
the ColorChecker's patch edges, and, where the truth is known, colour and spectral
errors. Here the simulated ColorChecker is reconstructed and compared with the
demosaicing baselines of thesis §4.6 (bilinear, Malvar, Menon), each also followed by
warping Red and Blue onto Green with a calibrated colour-channel model (the
Rudakova–Monasse correction); the simulator gives the dispersion-free truth. This is
what ``labkit evaluate`` and the report of ``labkit demo`` show.
"""

import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from calibration import calibrate_dispersion, filter_bands, load_scene_hdr
from labkit.hdr import run_hdr
from labkit.io import display_on_one_scale, read_raw_exr
from labkit.protocol import Engine
from labkit.protocol.hardware import open_hardware
from labkit.rig import default_rig_path, load_rig
from labkit.session import Session
from labkit.sim import SimulatedRig, colorchecker_patch_boxes, simulated_plans
from labkit.sim.truth import colour_truth, spectral_truth
from reconstruction import baseline_images, evaluate, reconstruct

workspace = tempfile.TemporaryDirectory(prefix="labkit-gallery-")  # removed at the end
out = Path(workspace.name)
rigs = simulated_plans(load_rig(default_rig_path()), (256, 320))  # `labkit demo --quick`'s
world = SimulatedRig(rigs["scenes"])

# %%
# Two dispersion models
# ---------------------
# After capture and HDR (as in the previous examples): a spectral ``to_reference`` model
# for the reconstruction, and a colour-channel model (Red and Blue against Green, from
# the unfiltered disks) for the warping baselines.
for name, rig in rigs.items():
    session, _ = Session.open_for(out / name, rig)
    with open_hardware(rig, fast=True) as hardware:
        Engine(rig, hardware.camera, hardware.slider, hardware.stage, session).run()
run_hdr([out / name for name in rigs], out / "hdr", previews=False)  # one folder, one set
disks = load_scene_hdr(out / "hdr", "disks")
bands = filter_bands(rigs["calibration"], images=disks)
spectral_model = calibrate_dispersion(
    disks, reference="600", bands=bands, direction="to_reference", workers=2
).model
colour_model = calibrate_dispersion(disks, reference="G", workers=2).model

# %%
# The estimates
# -------------
# Every baseline with and without warping, and the reconstruction's aberration-free raw
# colour image; all in the raw image's colour space.
image = read_raw_exr(out / "hdr" / "colorchecker" / "unfiltered.exr")
images, seconds = baseline_images(image.raw, cfa=image.cfa, colour_dispersion=colour_model)
result = reconstruct(image.raw, cfa=image.cfa, response=world.response, dispersion=spectral_model)
images["reconstruction"] = result.raw_colour
seconds["reconstruction"] = result.log["seconds"]
print(list(images))

# %%
# Scores
# ------
# Edge and centre RMSE: the residual aberration in 12 px strips inside the patch edges
# and in the patch centres, against an ideal image made from the raw patch centres;
# colour and spectral errors: against the simulator's dispersion-free truth, each
# channel or band registered by least squares (eq. 4.9). Errors are fractions of the
# mean signal.
boxes = colorchecker_patch_boxes(world.scene("colorchecker"))
evaluation = evaluate(
    image.raw,
    images,
    cfa=image.cfa,
    boxes=boxes,
    truth_colour=colour_truth(world, "colorchecker"),
    spectral={"reconstruction": (result.spectral, result.wavelengths_nm)},
    truth_spectral=lambda bands_nm: spectral_truth(world, "colorchecker", bands_nm),
    seconds=seconds,
)
header, rows = evaluation.table()
widths = [max(len(str(cell)) for cell in column) for column in zip(header, *rows, strict=True)]
for line in [header, *rows]:
    print("  ".join(str(cell).ljust(width) for cell, width in zip(line, widths, strict=True)))

# %%
# The residual aberration per channel: Green is the channel the eye reads edges from.
names = list(evaluation.scores)
edge = np.array([evaluation.scores[name].residual.edge.rmse for name in names])
figure, axis = plt.subplots(figsize=(10, 3.5))
for channel, colour in enumerate(["tab:red", "tab:green", "tab:blue"]):
    axis.bar(np.arange(len(names)) + (channel - 1) * 0.27, edge[:, channel], 0.27, color=colour)
axis.set_xticks(np.arange(len(names)), names, rotation=20, ha="right")
axis.set_ylabel("edge-strip RMSE")
axis.set_title("residual chromatic aberration (R, G, B)")
figure.tight_layout()

# %%
# Crops at the chart's top-left corner, where the lens moves colours the most, on one
# display scale.
display = display_on_one_scale(images, reference="bilinear")
x0, y0 = (int(v) for v in boxes[0][:2])
side = 40
shown = ["bilinear", "menon", "menon + warp", "reconstruction"]
figure, axes = plt.subplots(1, len(shown), figsize=(12, 3.2))
for axis, name in zip(axes, shown, strict=True):
    crop = display[name][max(0, y0 - side // 2) :, max(0, x0 - side // 2) :][:side, :side]
    axis.imshow(crop, interpolation="nearest")
    axis.set_title(name)
    axis.set_axis_off()
figure.tight_layout()

workspace.cleanup()  # the files written above were only for this example
