"""``labkit synthesize HDR_DIR --sensitivity FILE --out DIR``: thesis Algorithm 13."""

from __future__ import annotations

import argparse
from pathlib import Path

from labkit.cli._commands import Commands


def register(commands: Commands) -> None:
    """Add ``labkit synthesize``."""
    parser = commands.add_parser(
        "synthesize",
        description="For each scene: interpolate the Green channel of every filtered-light "
        "HDR image (divided by its exposure) into a multispectral image, collapse it to RGB "
        "with the calibrated R/G and B/G ratios, and sample that with the CFA. Writes "
        "DIR/<scene>-multispectral.exr, DIR/<scene>-synthetic-raw.exr and "
        "DIR/<scene>-synthetic-rgb.png; values are fractions of saturation per second.",
    )
    parser.add_argument(
        "hdr", type=Path, help="HDR folder from `labkit hdr` (DIR/<scene>/<illumination>.exr)"
    )
    parser.add_argument(
        "--sensitivity",
        type=Path,
        required=True,
        help="sensitivity.csv or sensitivity.yaml from `labkit calibrate sensitivity`",
    )
    parser.add_argument(
        "--scene",
        action="append",
        metavar="NAME",
        help="synthesize only this scene (repeatable; default: every scene with filtered images)",
    )
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.set_defaults(handler=_synthesize)


def _synthesize(args: argparse.Namespace) -> int:
    from calibration import (
        ChannelSensitivity,
        load_filtered_hdr,
        synthesize_multispectral,
        write_synthesis,
    )
    from labkit.io.output_folder import check_output_folder, staged_output_folder

    inputs = [args.hdr, args.sensitivity]
    check_output_folder(args.out, command="labkit synthesize", inputs=inputs)
    sensitivity = ChannelSensitivity.from_file(args.sensitivity)
    scenes = load_filtered_hdr(args.hdr, scenes=args.scene)
    lines = []
    with staged_output_folder(args.out, command="labkit synthesize", inputs=inputs) as stage:
        for scene, images in scenes.items():
            synthesis = synthesize_multispectral(images, sensitivity)
            paths = write_synthesis(synthesis, stage, scene)
            bands = ", ".join(f"{w:g}" for w in synthesis.multispectral.wavelengths_nm)
            unreliable = synthesis.raw.labkit["unreliable_bands"]
            note = f" (unreliable ratios at {unreliable} nm)" if unreliable else ""
            lines.append(f"{scene}: {len(images)} bands [{bands}] nm{note} → "
                         + ", ".join(path.name for path in paths.values()))  # fmt: skip
    print("\n".join(lines))
    print(f"wrote {len(scenes)} scene(s) to {args.out}")
    return 0
