"""``labkit calibrate …``: calibrations computed from HDR images.

``labkit calibrate sensitivity HDR_DIR --out DIR``: relative channel sensitivity per
filter band (thesis Algorithm 12), compared with what the rig's camera response predicts.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path


def register(commands: argparse._SubParsersAction) -> None:
    """Add ``labkit calibrate …``."""
    parser = commands.add_parser(
        "calibrate",
        help="calibrate the camera and lens from HDR images",
        description="Calibrations computed from the HDR images written by `labkit hdr`.",
    )
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    sensitivity = actions.add_parser(
        "sensitivity",
        help="R/G and B/G sensitivity ratios per filter band (thesis Algorithm 12)",
        description="Fit the ratios between neighbouring Green–Red and Green–Blue pixels in "
        "textureless, unsaturated regions of every filtered-light HDR image (first principal "
        "component, all scenes of a band pooled). Writes DIR/sensitivity.csv, "
        "DIR/sensitivity.yaml and DIR/sensitivity.png (measured vs the rig's camera response), "
        "and prints a table. Ratios resting on too few pairs or on a channel without signal "
        "are marked unreliable.",
    )
    sensitivity.add_argument(
        "hdr", type=Path, help="HDR folder from `labkit hdr` (DIR/<scene>/<illumination>.exr)"
    )
    sensitivity.add_argument("--out", type=Path, required=True, help="output folder")
    sensitivity.add_argument(
        "--scene",
        action="append",
        metavar="NAME",
        help="use only this scene (repeatable; default: every scene)",
    )
    sensitivity.add_argument(
        "--rig",
        default=None,
        help="rig YAML whose camera response, filters and light give the nominal ratios "
        "(default: the simulated rig)",
    )
    sensitivity.add_argument(
        "--saturation",
        type=float,
        default=0.95,
        help="ignore pixels at or above this fraction of saturation (default 0.95)",
    )
    sensitivity.set_defaults(handler=_sensitivity)


def _sensitivity(args: argparse.Namespace) -> int:
    from calibration import (
        channel_sensitivity,
        load_filtered_hdr,
        nominal_channel_sensitivity,
        plot_channel_sensitivity,
    )
    from labkit.rig import default_rig_path, load_rig

    rig = load_rig(args.rig or default_rig_path())
    scenes = load_filtered_hdr(args.hdr, scenes=args.scene)
    images = [image for group in scenes.values() for image in group]
    measured = channel_sensitivity(images, saturation=args.saturation)
    nominal = nominal_channel_sensitivity(rig)
    args.out.mkdir(parents=True, exist_ok=True)
    paths = [args.out / f"sensitivity.{suffix}" for suffix in ("csv", "yaml", "png")]
    measured.to_csv(paths[0])
    measured.to_yaml(paths[1])
    plot_channel_sensitivity(measured, nominal, paths[2])
    print(f"{len(images)} image(s) of {len(scenes)} scene(s) {sorted(scenes)}; "
          f"nominal ratios from {rig.source or rig.name}")  # fmt: skip
    print(sensitivity_table(measured, nominal))
    print("wrote " + ", ".join(str(path) for path in paths))
    return 0


def sensitivity_table(measured, nominal) -> str:
    """Measured vs nominal ratios per band, as aligned text."""
    header = (
        f"{'band':>8}  {'R/G':>9} {'nominal':>9} {'diff':>8}  "
        f"{'B/G':>9} {'nominal':>9} {'diff':>8}  reliable"
    )
    lines = [header]
    for i, wavelength in enumerate(measured.wavelengths_nm):
        entry = None if nominal is None else nominal.index_of(wavelength)
        cells = []
        for key in ("r", "b"):
            value = float(getattr(measured, f"{key}_over_g")[i])
            expected = math.nan
            if entry is not None:
                expected = float(getattr(nominal, f"{key}_over_g")[entry])
            diff = 100 * (value / expected - 1) if expected > 0 else math.nan
            cells.append(f"{_number(value)} {_number(expected)} {_percent(diff)}")
        reasons = [reason for reason in (measured.reason_r[i], measured.reason_b[i]) if reason]
        reliable = "yes"
        if not measured.reliable[i]:
            reliable = f"no ({'; '.join(reasons)})" if reasons else "no"
        lines.append(f"{wavelength:>5.1f} nm  {cells[0]}  {cells[1]}  {reliable}")
    return "\n".join(lines)


def _number(value: float) -> str:
    return f"{'—':>9}" if not math.isfinite(value) else f"{value:>9.4g}"


def _percent(value: float) -> str:
    return f"{'—':>8}" if not math.isfinite(value) else f"{value:>+7.1f}%"
