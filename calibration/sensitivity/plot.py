"""Figure 4.12: measured against nominal channel sensitivities."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calibration.sensitivity.table import ChannelSensitivity


def plot_channel_sensitivity(
    measured: ChannelSensitivity, nominal: ChannelSensitivity | None, path: str | Path
) -> None:
    """Measured (solid, markers) vs nominal (dotted) R/G and B/G against wavelength.

    The thesis' Figure 4.12. Ratios span decades, so the y axis is logarithmic;
    unreliable measured ratios are drawn as open markers. Written as PNG, atomically.
    """
    import matplotlib.pyplot as plt

    from labkit.plots import save_figure

    figure, axis = plt.subplots(figsize=(7, 4.5))
    for key, colour, label in (("r", "tab:red", "R/G"), ("b", "tab:blue", "B/G")):
        w = measured.wavelengths_nm
        ratio = getattr(measured, f"{key}_over_g")
        reliable = getattr(measured, f"reliable_{key}")
        shown = np.isfinite(ratio) & (ratio > 0)
        axis.plot(w[shown], ratio[shown], "-o", color=colour, label=f"{label} measured",
                  markevery=reliable[shown].tolist())  # fmt: skip
        bad = shown & ~reliable
        if bad.any():
            axis.plot(w[bad], ratio[bad], "o", mfc="none", color=colour,
                      label=f"{label} unreliable")  # fmt: skip
        if nominal is not None:
            ratio = getattr(nominal, f"{key}_over_g")
            shown = np.isfinite(ratio) & (ratio > 0)
            axis.plot(nominal.wavelengths_nm[shown], ratio[shown], ":", color=colour,
                      label=f"{label} nominal")  # fmt: skip
    axis.set_yscale("log")
    axis.set_xlabel("filter centre wavelength (nm)")
    axis.set_ylabel("sensitivity relative to Green")
    axis.set_title("relative channel sensitivity per filter band")
    axis.grid(True, which="both", alpha=0.3)
    axis.legend(fontsize=8)
    save_figure(figure, path)
