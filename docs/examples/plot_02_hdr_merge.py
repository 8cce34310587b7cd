"""
Merge an exposure bracket into an HDR raw image
===============================================

One exposure cannot hold the whole ColorChecker: long exposures clip the white patch,
short ones bury the black patch in read noise. Here a bracket of the simulated
ColorChecker (four exposures, five replicates each, with dark frames) is merged by
:func:`labkit.hdr.merge_exposures` with the thesis' weights (Algorithm 11) and with the
noise-aware weights, and the result is compared with the simulator's noise-free
irradiance. ``labkit hdr`` (:func:`labkit.hdr.run_hdr`) does the same for every scene and
illumination of a session and writes raw EXRs.
"""

import matplotlib.pyplot as plt
import numpy as np

from labkit.hdr import DarkFrame, ExposureInput, SensorLevels, merge_exposures
from labkit.rig import default_rig_path, load_rig
from labkit.sim import SimCamera, SimulatedRig

world = SimulatedRig(load_rig(default_rig_path()), shape=(128, 160))
camera = SimCamera(world, fast=True)
camera.set_scene("colorchecker")
EXPOSURES = [0.002, 0.008, 0.032, 0.128]  # s, a factor of 4 apart
REPLICATES = 5

# %%
# The bracket and its dark frames
# -------------------------------
# Every frame carries its sensor levels; the dark frames (light covered) are averaged per
# exposure into :class:`~labkit.hdr.DarkFrame` objects.
lit, dark = {}, {}
camera.set_illumination("unfiltered")
for t in EXPOSURES:
    lit[t] = camera.grab(t, n=REPLICATES)
camera.set_illumination("dark")
for t in EXPOSURES:
    dark[t] = camera.grab(t, n=REPLICATES)
first = lit[EXPOSURES[0]][0]
levels = SensorLevels(first.extra["saturation_dn"], first.extra["black_level"])
print(levels, world.rig.cfa)

bracket = [ExposureInput.from_arrays(t, [f.image for f in lit[t]]) for t in EXPOSURES]
darks = {
    t: DarkFrame.from_frames(ExposureInput.from_arrays(t, [f.image for f in dark[t]]))
    for t in EXPOSURES
}

figure, axes = plt.subplots(1, len(EXPOSURES), figsize=(12, 2.8))
for axis, t in zip(axes, EXPOSURES, strict=True):
    image = lit[t][0].image
    axis.imshow(image, cmap="gray", vmin=0, vmax=levels.saturation_dn)
    axis.set_title(f"{t * 1e3:g} ms: {np.mean(image >= levels.saturation_dn):.0%} clipped")
    axis.set_axis_off()
figure.tight_layout()

# %%
# Merge
# -----
# The merged mosaic is in units of the saturation range at the shortest exposure. The
# scaling factor of each exposure is fitted from the pixels that two exposures both
# expose properly (thesis Table 4.1); the simulated shutter jitters, so the fitted
# factors differ a little from the exposure-time ratios.
results = {
    method: merge_exposures(bracket, darks, cfa=world.rig.cfa, levels=levels, method=method)
    for method in ("thesis", "noise")
}
for e in results["noise"].exposures:
    print(
        f"{e.exposure_s * 1e3:6.1f} ms  nominal {e.nominal:.5f}  fitted {e.factor:.5f} "
        f"({e.disagreement:+.2%})"
    )

# %%
# Against the truth
# -----------------
# The simulator knows each pixel's noise-free irradiance (electrons per second). The
# merged value over the irradiance is one constant wherever the merge is right; its
# spread is the merge's relative noise, far below that of the one exposure that clips
# nothing (the shortest), most of all in the dark patches.
truth = world.irradiance("colorchecker", "unfiltered")
lit_pixels = truth > 0.02 * truth.max()
shortest = EXPOSURES[0]
single = (lit[shortest][0].image - darks[shortest].mean) / levels.saturation_range

figure, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
merged = results["noise"].raw
shown = left.imshow(np.log10(np.maximum(merged, 1e-4)), cmap="magma")
left.set_title("merged HDR raw (noise-aware), log10")
left.set_axis_off()
figure.colorbar(shown, ax=left, shrink=0.8)
for name, values, mask in [
    (f"one {shortest * 1e3:g} ms frame", single, lit_pixels),
    ("merged, thesis weights", results["thesis"].raw, lit_pixels),
    ("merged, noise-aware", merged, lit_pixels),
]:
    ratio = values[mask] / truth[mask]
    ratio /= np.median(ratio)
    spread = np.std(ratio)
    right.loglog(truth[mask], ratio, ".", markersize=2, alpha=0.4, label=f"{name} (σ {spread:.3f})")
right.set_xlabel("true irradiance (e⁻/s)")
right.set_ylabel("merged / truth (normalised)")
right.set_ylim(0.6, 1.6)
right.legend(fontsize=8, markerscale=4)
figure.tight_layout()
