"""
Real frames: the thesis' ColorChecker
=====================================

labkit ships real captures from the thesis' lab (:func:`labkit.data.real_colorchecker`):
a ColorChecker under seven bandpass filters at seven exposures and dark frames, from a
FLIR Flea3 (8-bit, 342 × 408, GBRG), with the chart's patches labelled. The lab has no
raw image of this chart whose truth is known, so, as in thesis §4.2.4, the filtered
images make one: :func:`labkit.real_chart.prepare_real_inputs` imports the frames into a
session (their levels read from the files), merges them into HDR images, measures the
sensor map (the camera's R/G and B/G per band, Algorithm 12), synthesises a
multispectral and a raw image from them (Algorithm 13) and calibrates the dispersion
from the filtered images. The synthetic raw image is then reconstructed with the sensor
map as the camera response and scored against the chart's spectrometer readings, as
``labkit demo --real`` does.
"""

import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from labkit.data import real_colorchecker
from labkit.io import display_on_one_scale, spectral_preview
from labkit.real_chart import prepare_real_inputs
from reconstruction import reconstruct

workspace = tempfile.TemporaryDirectory(prefix="labkit-gallery-")  # removed at the end
out = Path(workspace.name)
print(real_colorchecker())

# %%
# From frames to the synthetic raw image
# --------------------------------------
# Stages 1–5 of the real demo; the summaries say what each found.
real = prepare_real_inputs(out)
print(real.imported)
for band, merge in real.hdr.items():
    fitted = ", ".join(f"{f:.4f}" for f in merge.fitted)
    print(f"{band} nm: exposure factors {fitted}")

# %%
# The sensor map: how strongly Red and Blue respond against Green in each band, measured
# from the filtered images, against the rig's stand-in camera response.
sensitivity = real.sensor.sensitivity
nominal = {row["wavelength_nm"]: row for row in real.sensor.summary["bands"]}
figure, axis = plt.subplots(figsize=(6, 3.5))
wavelengths = sensitivity.wavelengths_nm
axis.semilogy(wavelengths, sensitivity.r_over_g, "o-", color="tab:red", label="R/G measured")
axis.semilogy(wavelengths, sensitivity.b_over_g, "o-", color="tab:blue", label="B/G measured")
for key, colour in [("nominal_r_over_g", "tab:red"), ("nominal_b_over_g", "tab:blue")]:
    values = [nominal[float(w)][key] for w in wavelengths]
    axis.semilogy(wavelengths, [np.nan if v is None else v for v in values], ":", color=colour)
axis.set_xlabel("band (nm)")
axis.set_ylabel("ratio to Green")
axis.set_title("sensor map (dotted: stand-in response)")
axis.legend(fontsize=8)
figure.tight_layout()

# %%
# Reconstruct
# -----------
# :meth:`~labkit.real_chart.RealInputs.reconstruct_options` gives the CFA layout, the sensor
# map as the response, its bands and the spectral dispersion model; the rest are the
# defaults. Its :attr:`~labkit.real_chart.RealInputs.scorer` scores the result against the
# chart (:class:`reconstruction.evaluate.chart_scores.ChartScorer`).
result = reconstruct(real.synthesis.raw.raw, **real.reconstruct_options())
score = real.scorer.score(result)
print({name: round(value, 4) for name, value in score.items()})

multispectral = real.synthesis.multispectral
figure, axes = plt.subplots(1, 3, figsize=(12, 3.4))
axes[0].imshow(real.synthesis.raw.raw, cmap="gray")
axes[0].set_title("synthetic raw image")
axes[1].imshow(display_on_one_scale({"rgb": real.synthesis.rgb})["rgb"])
axes[1].set_title("synthetic colour image (Alg. 13)")
axes[2].imshow(spectral_preview(result.spectral, result.wavelengths_nm).image)
axes[2].set_title("reconstruction, sRGB")
for axis in axes:
    axis.set_axis_off()
figure.tight_layout()

# %%
# Against the spectrometer
# ------------------------
# Mean spectra of the patch centres against the chart's ASD reflectances, each band
# scaled by least squares over the 24 patches (eq. 4.9). MRAE is the mean relative
# absolute error over patches and bands (the thesis' best reconstruction at full
# resolution: 0.258).
reflectances = real.scorer.reflectances
errors = {
    "multispectral": real.scorer.patch_errors(multispectral.cube, multispectral.wavelengths_nm),
    "reconstruction": real.scorer.patch_errors(result.spectral, result.wavelengths_nm),
}
for name, e in errors.items():
    print(f"{name:15s} MRAE {e['mrae']:.3f}  RMSE {e['rmse']:.4f}")

patches = {"dark skin": 0, "blue sky": 2, "orange": 6, "yellow": 15, "red": 14, "white": 18}
fine = np.arange(400.0, 701.0, 5.0)
truth = reflectances.resample(fine).values.T
figure, axes = plt.subplots(1, len(patches), figsize=(14, 2.8), sharey=True)
for axis, (name, index) in zip(axes, patches.items(), strict=True):
    axis.plot(fine, truth[index], "k-", label="ASD")
    axis.plot(multispectral.wavelengths_nm, errors["multispectral"]["estimate"][index], "s--",
              label="multispectral")  # fmt: skip
    axis.plot(result.wavelengths_nm, errors["reconstruction"]["estimate"][index], "o-",
              label="reconstruction")  # fmt: skip
    axis.set_title(name)
    axis.set_xlabel("nm")
axes[0].set_ylabel("reflectance")
axes[0].legend(fontsize=7)
figure.tight_layout()

workspace.cleanup()  # the files written above were only for this example
