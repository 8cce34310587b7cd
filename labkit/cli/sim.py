"""``labkit sim render``: render one simulated raw frame to a TIFF file."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from labkit.cfa import pixel_format_for
from labkit.cli._commands import Commands
from labkit.cli._options import non_negative_int
from labkit.errors import ConfigError
from labkit.io import raw_preview, write_png, write_raw_tiff
from labkit.rig import default_rig_path, load_rig
from labkit.sim.camera import SimCamera
from labkit.sim.world import SimulatedRig


def register(commands: Commands) -> None:
    """Add ``labkit sim …``."""
    parser = commands.add_parser("sim")
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    render = actions.add_parser(
        "render",
        help="render one raw frame of a simulated scene",
        description="Render a noisy raw Bayer frame of a simulated scene under one "
        "illumination and exposure, and write it as a 16-bit TIFF (metadata in the "
        "ImageDescription tag).",
    )
    render.add_argument(
        "rig",
        nargs="?",
        default=None,
        help="rig YAML with a sim camera (default: the packaged simulated rig)",
    )
    render.add_argument(
        "--scene", required=True, help="scene name, e.g. disks, colorchecker, texture"
    )
    render.add_argument(
        "--illumination",
        required=True,
        help="slider position name (unfiltered, 400, …, 700) or 'dark'",
    )
    render.add_argument("--exposure", type=float, required=True, help="exposure time, s")
    render.add_argument("--gain", type=float, default=None, help="analogue gain, dB")
    render.add_argument(
        "--bits",
        type=int,
        choices=(8, 12, 16),
        default=None,
        help="output pixel format depth (default: the rig's)",
    )
    render.add_argument("--seed", type=non_negative_int, default=None, help="frame-noise seed, ≥ 0")
    render.add_argument("--frame-id", type=int, default=1, help="frame number (selects the noise)")
    render.add_argument("--preview", type=Path, default=None, help="also write a PNG preview")
    render.add_argument(
        "--out", type=Path, required=True, help="output raw TIFF path (.tif or .tiff)"
    )
    render.set_defaults(handler=_render)  # fmt: skip


def _render(args: argparse.Namespace) -> int:
    from labkit.io.output_folder import check_output_files, staged_output_files

    if args.exposure <= 0 or not math.isfinite(args.exposure):
        raise ConfigError(f"--exposure must be > 0 s (a finite number), got {args.exposure}")
    if args.out.suffix.lower() not in (".tif", ".tiff"):
        given = repr(args.out.suffix) if args.out.suffix else "no suffix"
        raise ConfigError(
            f"--out {args.out}: sim render writes a raw TIFF, so the name must end in .tif or "
            f".tiff (got {given}); e.g. --out {args.out.with_suffix('.tiff')}"
        )
    outputs = [args.out, *([args.preview] if args.preview else [])]
    if args.preview:  # named by its own option where it alone is the problem
        check_output_files([args.preview], option="--preview")
    check_output_files(outputs)
    rig = SimulatedRig(load_rig(args.rig or default_rig_path()))
    camera = SimCamera(rig, fast=True, seed=args.seed)
    camera.set_scene(args.scene)
    camera.set_illumination(args.illumination)
    if args.gain is not None:
        camera.set("Gain", args.gain)
    if args.bits is not None:
        camera.set("PixelFormat", pixel_format_for(rig.rig.cfa, args.bits))
    camera.next_frame_id = args.frame_id
    frame = camera.grab(args.exposure)[0]
    metadata = {
        "scene": args.scene,
        "illumination": args.illumination,
        "exposure_s": args.exposure,
        "gain_db": frame.gain_db,
        "pixel_format": frame.pixel_format,
        "cfa": rig.rig.cfa,
        "frame_id": frame.frame_id,
        "true_exposure_s": frame.extra["true_exposure_s"],
    }
    with staged_output_files(outputs, command="labkit sim render") as staged:
        write_raw_tiff(staged[0], frame.image, metadata)
        if args.preview:
            black = frame.extra["black_level"]
            write_png(staged[1], raw_preview(frame.image, rig.rig.cfa, black_level=black))
    rows, cols = frame.image.shape
    print(
        f"wrote {args.out}: {cols}×{rows} {frame.pixel_format}, {args.scene} under "
        f"{args.illumination}, {args.exposure:g} s, counts {frame.image.min()}–{frame.image.max()}"
    )
    return 0
