"""The printable disk chart for disk-keypoint calibration (thesis §3.2.1, §4.2.1).

Black disks on white paper on a square grid, sized so that, photographed at the working
distance through the rig's lens, each disk spans the radius in pixels the detector and the
disk fit work best with and neighbouring disks stand a pitch apart. The size on paper
follows from the thin-lens magnification ``m = f / (D − f)`` (focal length f, distance D
from the lens to the paper): one sensor pixel of pitch p sees ``p / m`` of paper.

:func:`design_disk_chart` lays the chart out; :func:`write_chart_svg` and
:func:`write_chart_pdf` write it at its physical size (print at 100 %, no scaling), with a
scale bar to check the print and the parameters printed in the margin;
:func:`write_chart_yaml` records the design, which ``labkit calibrate dispersion
--target`` compares with the disks it finds.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from calibration.disks.detect import detect_disks
from labkit.errors import ConfigError
from labkit.io.atomic import atomic_write, write_text_atomic

#: Paper sizes, mm (width, height), portrait.
PAPER_MM = {"A4": (210.0, 297.0), "A3": (297.0, 420.0), "letter": (215.9, 279.4)}
#: Disk radius and pitch the detector and the fit work with comfortably, px: a 14 px disk
#: keeps its centre's fit well conditioned under several px of blur and aberration, and a
#: 64 px pitch leaves each disk's fitting window free of its neighbours (the simulated
#: rig's chart).
RADIUS_PX = 14.0
PITCH_PX = 64.0
#: Margin kept free of disks on every side, mm (printers do not print to the edge; the
#: bottom margin holds the scale bar and the parameters).
MARGIN_MM = 15.0
BOTTOM_MM = 30.0


@dataclass(frozen=True)
class DiskChart:
    """A disk chart's layout on paper.

    Attributes
    ----------
    paper_mm : (float, float)
        Page width and height, mm.
    radius_mm, pitch_mm : float
        Disk radius and centre-to-centre spacing, mm.
    centres_mm : ndarray (n, 2)
        Disk centres (x from the left edge, y from the top edge), mm.
    radius_px, pitch_px : float
        What the disks measure in the camera's image at the working distance, px.
    mm_per_px : float
        Paper seen by one sensor pixel at the working distance, mm.
    camera : dict
        The camera and lens the chart was made for (pixel pitch, focal length, distance).
    """

    paper_mm: tuple[float, float]
    radius_mm: float
    pitch_mm: float
    centres_mm: np.ndarray
    radius_px: float
    pitch_px: float
    mm_per_px: float
    camera: dict[str, float]

    def describe(self) -> list[str]:
        """Lines for the margin and the terminal: the design, then how to print it."""
        cam = self.camera
        return [
            f"labkit disk chart: {len(self.centres_mm)} disks {2 * self.radius_mm:.2f} mm "
            f"across, {self.pitch_mm:.2f} mm apart",
            f"for {cam['pixel_um']:g} µm pixels, f = {cam['focal_mm']:g} mm, "
            f"{cam['distance_m']:g} m from the lens: radius {self.radius_px:g} px, pitch "
            f"{self.pitch_px:g} px",
            "print at 100 % (no scaling) on matte paper; the scale bar must measure "
            f"{_scale_bar(self)[2]:g} mm",
        ]


def paper_size(name: str, *, landscape: bool = False) -> tuple[float, float]:
    """A paper name (``A4``, ``A3``, ``letter``) or ``WxH`` in mm → (width, height), mm."""
    size = PAPER_MM.get(name) or PAPER_MM.get(name.upper())
    if size is None:
        try:
            width, height = (float(part) for part in name.lower().split("x"))
        except ValueError:
            raise ConfigError(
                f"--paper {name!r}: give {', '.join(PAPER_MM)} or WIDTHxHEIGHT in mm (e.g. 300x200)"
            ) from None
        if not (width > 0 and height > 0):
            raise ConfigError(f"--paper {name!r}: width and height must be positive mm")
        size = (width, height)
    return (size[1], size[0]) if landscape else size


def design_disk_chart(
    paper_mm: tuple[float, float],
    *,
    pixel_um: float,
    focal_mm: float,
    distance_m: float,
    radius_px: float = RADIUS_PX,
    pitch_px: float = PITCH_PX,
) -> DiskChart:
    """Lay out a disk chart for a camera and lens at a working distance.

    Parameters
    ----------
    paper_mm : (float, float)
        Page width and height, mm.
    pixel_um : float
        The sensor's pixel pitch, µm.
    focal_mm : float
        The lens' focal length, mm.
    distance_m : float
        Distance from the lens to the chart, m.
    radius_px, pitch_px : float
        Disk radius and spacing wanted in the image, px.

    Raises
    ------
    ConfigError
        Values that cannot describe a chart (non-positive, the chart inside the focal
        length, disks that touch) or a page too small for a 2 × 2 grid of disks.
    """
    for name, value in (
        ("pixel_um", pixel_um),
        ("focal_mm", focal_mm),
        ("distance_m", distance_m),
        ("radius_px", radius_px),
        ("pitch_px", pitch_px),
    ):
        if not (np.isfinite(value) and value > 0):
            raise ConfigError(f"--{name.replace('_', '-')} {value!r} must be a positive number")
    distance_mm = distance_m * 1000.0
    if distance_mm <= focal_mm:
        raise ConfigError(
            f"--distance-m {distance_m:g} is not beyond the focal length {focal_mm:g} mm: the "
            "lens cannot focus on the chart"
        )
    if pitch_px < 3 * radius_px:
        raise ConfigError(
            f"--pitch-px {pitch_px:g} leaves disks of radius {radius_px:g} px too close: the "
            f"fit needs a pitch of at least 3 radii ({3 * radius_px:g} px)"
        )
    magnification = focal_mm / (distance_mm - focal_mm)
    mm_per_px = pixel_um / 1000.0 / magnification
    radius_mm, pitch_mm = radius_px * mm_per_px, pitch_px * mm_per_px
    width, height = paper_mm
    usable_x = width - 2 * MARGIN_MM - 2 * radius_mm
    usable_y = height - MARGIN_MM - BOTTOM_MM - 2 * radius_mm
    columns = int(np.floor(usable_x / pitch_mm + 1e-9)) + 1 if usable_x >= 0 else 0
    rows = int(np.floor(usable_y / pitch_mm + 1e-9)) + 1 if usable_y >= 0 else 0
    if columns < 2 or rows < 2:
        raise ConfigError(
            f"a {width:g}×{height:g} mm page holds {max(columns, 0)}×{max(rows, 0)} disks of "
            f"{2 * radius_mm:.1f} mm at a {pitch_mm:.1f} mm pitch; use larger paper (--paper), "
            "a shorter distance or smaller --radius-px/--pitch-px"
        )
    x0 = (width - (columns - 1) * pitch_mm) / 2
    y0 = MARGIN_MM + (height - MARGIN_MM - BOTTOM_MM - (rows - 1) * pitch_mm) / 2
    yy, xx = np.mgrid[:rows, :columns]
    centres = np.column_stack([x0 + xx.ravel() * pitch_mm, y0 + yy.ravel() * pitch_mm])
    camera = {"pixel_um": pixel_um, "focal_mm": focal_mm, "distance_m": distance_m}
    return DiskChart(
        (width, height), radius_mm, pitch_mm, centres, radius_px, pitch_px, mm_per_px, camera
    )


def _scale_bar(chart: DiskChart) -> tuple[float, float, float]:
    """(x, y, length) of the 100 mm scale bar in the bottom margin, mm."""
    width, height = chart.paper_mm
    length = 100.0 if width - 2 * MARGIN_MM >= 100 else 50.0
    return MARGIN_MM, height - BOTTOM_MM + 8.0, length


def write_chart_svg(chart: DiskChart, path: str | Path) -> Path:
    """Write the chart as SVG at its physical size (mm units), atomically."""
    width, height = chart.paper_mm
    x, y, length = _scale_bar(chart)
    circles = "\n".join(
        f'  <circle cx="{cx:.4f}" cy="{cy:.4f}" r="{chart.radius_mm:.4f}"/>'
        for cx, cy in chart.centres_mm
    )
    lines = "\n".join(
        f'<text x="{x:.4f}" y="{y + 8 + 4 * k:.4f}" font-family="sans-serif" '
        f'font-size="2.8">{line.replace("&", "&amp;").replace("<", "&lt;")}</text>'
        for k, line in enumerate(chart.describe())
    )
    svg = f"""<?xml version="1.0" encoding="UTF-8"?>
<svg xmlns="http://www.w3.org/2000/svg" width="{width:g}mm" height="{height:g}mm"
     viewBox="0 0 {width:g} {height:g}">
<title>labkit disk chart</title>
<rect x="0" y="0" width="{width:g}" height="{height:g}" fill="white"/>
<g fill="black">
{circles}
</g>
<g fill="black" stroke="none">
  <rect x="{x:.4f}" y="{y:.4f}" width="{length:g}" height="1.5"/>
  <rect x="{x:.4f}" y="{y - 2:.4f}" width="0.4" height="5.5"/>
  <rect x="{x + length - 0.4:.4f}" y="{y - 2:.4f}" width="0.4" height="5.5"/>
</g>
<text x="{x + length + 4:.4f}" y="{y + 1.5:.4f}" font-family="sans-serif"
      font-size="3.5">{length:g} mm</text>
{lines}
</svg>
"""
    write_text_atomic(Path(path), svg)
    return Path(path)


def write_chart_pdf(chart: DiskChart, path: str | Path) -> Path:
    """Write the chart as a one-page vector PDF at its physical size, atomically."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle, Rectangle

    width, height = chart.paper_mm
    figure = Figure(figsize=(width / 25.4, height / 25.4))
    axes = figure.add_axes((0, 0, 1, 1))
    axes.set_xlim(0, width)
    axes.set_ylim(height, 0)  # y from the top edge, as in the SVG
    axes.set_axis_off()
    for cx, cy in chart.centres_mm:
        axes.add_patch(Circle((cx, cy), chart.radius_mm, facecolor="black", edgecolor="none"))
    x, y, length = _scale_bar(chart)
    axes.add_patch(Rectangle((x, y), length, 1.5, facecolor="black", edgecolor="none"))
    for end in (x, x + length - 0.4):
        axes.add_patch(Rectangle((end, y - 2), 0.4, 5.5, facecolor="black", edgecolor="none"))
    points = 72 / 25.4  # font sizes in mm → points
    axes.text(x + length + 4, y + 1.5, f"{length:g} mm", fontsize=3.5 * points, va="baseline")
    for k, line in enumerate(chart.describe()):
        axes.text(x, y + 8 + 4 * k, line, fontsize=2.8 * points, va="baseline")
    with atomic_write(Path(path)) as handle:
        figure.savefig(handle, format="pdf", metadata={"Title": "labkit disk chart"})
    return Path(path)


def write_chart_yaml(chart: DiskChart, path: str | Path) -> Path:
    """Record the chart's design (what ``calibrate dispersion --target`` checks against)."""
    record: dict[str, Any] = {
        "kind": "labkit.disk_chart",
        "format": 1,
        **{k: v for k, v in asdict(chart).items() if k != "centres_mm"},
        "paper_mm": list(chart.paper_mm),
        "disks": len(chart.centres_mm),
    }
    write_text_atomic(Path(path), yaml.safe_dump(record, sort_keys=False))
    return Path(path)


def load_chart_yaml(path: str | Path) -> dict[str, Any]:
    """A chart design written by :func:`write_chart_yaml`."""
    path = Path(path)
    try:
        record = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as error:
        raise ConfigError(f"{path}: cannot read a chart design ({error})") from None
    if not isinstance(record, dict) or record.get("kind") != "labkit.disk_chart":
        raise ConfigError(f"{path} is not a chart design written by `labkit target`")
    return record


#: How far the disks of a shot may measure from the chart's design before the calibration
#: says so (relative, radius or pitch).
SHOT_TOLERANCE = 0.2


@dataclass(frozen=True)
class ShotCheck:
    """How the disks of a shot of the chart measure against the chart's design.

    Attributes
    ----------
    radius_px, pitch_px : float
        Median disk radius and median distance to the nearest disk in the shot, px.
    design_radius_px, design_pitch_px : float
        What the chart was made for, px.
    problem : str or None
        What is wrong and what to do, where the shot is more than :data:`SHOT_TOLERANCE`
        off the design.
    """

    radius_px: float
    pitch_px: float
    design_radius_px: float
    design_pitch_px: float
    problem: str | None

    def describe(self) -> str:
        """One line for the terminal."""
        return (
            f"disks in the shot: radius {self.radius_px:.1f} px, pitch {self.pitch_px:.1f} px "
            f"(the chart was made for {self.design_radius_px:g} px and {self.design_pitch_px:g} px)"
        )


def check_shot(raw: np.ndarray, design: dict[str, Any], *, cfa: str, name: str) -> ShotCheck:
    """Compare the disks of a shot (a raw mosaic of the chart) with the chart's design
    (:func:`load_chart_yaml`): their median radius and nearest-neighbour pitch, px."""
    found = detect_disks(raw, cfa=cfa, name=name)
    radius = float(np.median(np.sqrt(found.area_px / np.pi)))
    distances = np.linalg.norm(found.centres[:, None] - found.centres[None], axis=2)
    np.fill_diagonal(distances, np.inf)
    pitch = float(np.median(distances.min(axis=1)))
    want_radius, want_pitch = float(design["radius_px"]), float(design["pitch_px"])
    problem = None
    scale = pitch / want_pitch
    if abs(scale - 1) > SHOT_TOLERANCE or abs(radius / want_radius - 1) > SHOT_TOLERANCE:
        where = "farther from" if scale < 1 else "closer to"
        problem = (
            f"{name}: the disks measure {radius:.1f} px in radius and {pitch:.1f} px apart, but "
            f"the chart was made for {want_radius:g} px and {want_pitch:g} px: the camera "
            f"stands {max(scale, 1 / scale):.2f}× {where} the chart than it was made for "
            "(or the lens differs). Move the camera, or make a chart for this distance "
            "(labkit target) and shoot it again"
        )
    return ShotCheck(radius, pitch, want_radius, want_pitch, problem)
