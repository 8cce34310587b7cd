"""Figures of the benchmark report: time against error, and time against image size."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

#: One point of a time-against-error series: (time in s, error, label or "").
Point = tuple[float, float, str]


def plot_time_vs_error(
    series: Mapping[str, Sequence[Point]],
    path: str | Path,
    *,
    title: str,
    error_label: str,
    connect: bool = False,
    reference: tuple[str, float] | None = None,
    log_error: bool = False,
) -> None:
    """Scatter of run time (log axis) against error, one colour per series; PNG, atomic.

    Parameters
    ----------
    series : mapping of str to sequence of (float, float, str)
        Legend label → points (time in s, error in `error_label`'s unit, annotation).
    path : str or Path
        PNG file to write (atomically).
    title, error_label : str
        Axes title and y-axis label (with unit).
    connect : bool
        Join each series' points in the given order (a knob swept within a series).
    reference : (str, float), optional
        A horizontal line (label, error), e.g. a lower bound.
    log_error : bool
        Logarithmic error axis.
    """
    import matplotlib.pyplot as plt

    from labkit.plots import save_figure

    figure, axis = plt.subplots(figsize=(7, 4.5))
    for label, points in series.items():
        if not points:
            continue
        t = np.array([p[0] for p in points], dtype=np.float64)
        e = np.array([p[1] for p in points], dtype=np.float64)
        axis.plot(t, e, "o-" if connect else "o", label=label)
        for x, y, note in points:
            if note:
                axis.annotate(note, (x, y), fontsize=6, xytext=(3, 3), textcoords="offset points")
    if reference is not None:
        axis.axhline(reference[1], color="grey", linestyle="--", label=reference[0])
    axis.set_xscale("log")
    if log_error:
        axis.set_yscale("log")
    axis.set_xlabel("time (s)")
    axis.set_ylabel(error_label)
    axis.set_title(title)
    axis.legend(fontsize=7)
    figure.tight_layout()
    save_figure(figure, path)


def plot_scaling(
    pixels: Sequence[float],
    series: Mapping[str, tuple[Sequence[float], float]],
    path: str | Path,
    *,
    title: str,
) -> None:
    """Log–log plot of time against pixel count with each series' fitted power law; PNG.

    Parameters
    ----------
    pixels : sequence of float
        Image sizes, pixels.
    series : mapping of str to (sequence of float, float)
        Legend label → (times in s, one per size; fitted exponent p).
    path : str or Path
        PNG file to write (atomically).
    title : str
        Axes title.
    """
    import matplotlib.pyplot as plt

    from labkit.plots import save_figure

    n = np.asarray(pixels, dtype=np.float64)
    figure, axis = plt.subplots(figsize=(6, 4.5))
    for label, (seconds, exponent) in series.items():
        t = np.asarray(seconds, dtype=np.float64)
        (line,) = axis.loglog(n, t, "o", label=f"{label}: p = {exponent:.2f}")
        # the least-squares line passes through the centroid in log–log space
        scale = np.exp(np.mean(np.log(t)) - exponent * np.mean(np.log(n)))
        axis.loglog(n, scale * n**exponent, "-", color=line.get_color(), linewidth=1)
    t0 = np.asarray(next(iter(series.values()))[0], dtype=np.float64)
    axis.loglog(n, t0[0] * n / n[0], ":", color="grey", label="p = 1 (linear)")
    axis.set_xlabel("image size (pixels)")
    axis.set_ylabel("time (s)")
    axis.set_title(title)
    axis.legend(fontsize=7)
    figure.tight_layout()
    save_figure(figure, path)
