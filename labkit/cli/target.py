"""``labkit target --out DIR``: the printable disk chart for dispersion calibration."""

from __future__ import annotations

import argparse
from pathlib import Path

from labkit.cli._commands import Commands


def register(commands: Commands) -> None:
    """Add ``labkit target``."""
    parser = commands.add_parser(
        "target",
        description="Lay out the disk chart that `labkit calibrate dispersion` photographs "
        "(black disks on white paper), sized for your camera and lens: at "
        "the working distance each disk must span --radius-px and neighbours stand "
        "--pitch-px apart in the image (thin-lens magnification f / (D − f)). Writes "
        "DIR/chart.svg and DIR/chart.pdf at the paper's physical size, with a scale bar and "
        "the parameters printed in the margin (print at 100 %, no scaling; measure the bar), "
        "and DIR/chart.yaml, the design that `calibrate dispersion --target` checks the "
        "shot against.",
    )
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument(
        "--paper", default="A4", help="A4, A3, letter or WIDTHxHEIGHT in mm (default: A4)"
    )
    parser.add_argument("--landscape", action="store_true", help="turn the page sideways")
    parser.add_argument(
        "--pixel-um", type=float, required=True, help="the sensor's pixel pitch, µm (e.g. 3.45)"
    )
    parser.add_argument("--focal-mm", type=float, required=True, help="the lens' focal length, mm")
    parser.add_argument(
        "--distance-m",
        type=float,
        required=True,
        help="distance from the lens to the chart, m",
    )
    parser.add_argument(
        "--radius-px",
        type=float,
        default=None,
        help="disk radius wanted in the image, px (default: 14, what the disk fit works best with)",
    )
    parser.add_argument(
        "--pitch-px",
        type=float,
        default=None,
        help="disk spacing wanted in the image, px, at least 3 radii (default: 64)",
    )
    parser.set_defaults(handler=_target)


def _target(args: argparse.Namespace) -> int:
    from calibration.disks.chart import (
        PITCH_PX,
        RADIUS_PX,
        design_disk_chart,
        paper_size,
        write_chart_pdf,
        write_chart_svg,
        write_chart_yaml,
    )
    from labkit.io.output_folder import check_output_folder, staged_output_folder

    chart = design_disk_chart(
        paper_size(args.paper, landscape=args.landscape),
        pixel_um=args.pixel_um,
        focal_mm=args.focal_mm,
        distance_m=args.distance_m,
        radius_px=RADIUS_PX if args.radius_px is None else args.radius_px,
        pitch_px=PITCH_PX if args.pitch_px is None else args.pitch_px,
    )
    check_output_folder(args.out, command="labkit target")
    with staged_output_folder(args.out, command="labkit target") as stage:
        write_chart_svg(chart, stage / "chart.svg")
        write_chart_pdf(chart, stage / "chart.pdf")
        write_chart_yaml(chart, stage / "chart.yaml")
    for line in chart.describe():
        print(line)
    print(f"wrote {args.out / 'chart.svg'}, chart.pdf, chart.yaml")
    return 0
