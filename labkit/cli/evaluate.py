"""``labkit evaluate RAW --out DIR``: baselines and reconstructions scored side by side."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from labkit.cli._commands import Commands
from labkit.cli._options import add_cfa_option, add_extrapolation_option, model_domain

DESCRIPTION = """\
Score colour images of one raw image. RAW is a raw Bayer mosaic: a raw
EXR (from `labkit hdr`, or from other software: channel 'raw' or the only channel), a
single-channel uint8/uint16/float TIFF or PNG (integers scaled by the container's maximum)
or a camera raw file read by LibRaw (DNG, NEF, CR2, CR3, ARW, ORF, RW2, PEF, …; black level
subtracted; Bayer sensors only); --cfa gives the Bayer layout of a file that does not record
it. Runs the demosaicing baselines
(bilinear, Malvar 2004, Menon 2007; with --colour-dispersion each also followed by warping
Red and Blue onto Green), adds the images given with --image (e.g. the raw_colour.exr of
`labkit reconstruct`), and measures:

  - residual chromatic aberration in 12-px strips inside the patch edges of a
    ColorChecker-like chart, given its geometry: --labels (a label image, 0 = background,
    k = patch k) or --scene NAME of a simulated rig (--rig);
  - colour errors against --truth-colour (an RGB EXR of the aberration-free image) and,
    for a simulated scene, against the simulator's truth (--scene with --truth).

Writes DIR/evaluation.json, DIR/evaluation.md and .html (a table and previews on one
display scale) and DIR/<method>.png. Errors are fractions of the raw image's mean.
"""


def register(commands: Commands) -> None:
    """Add ``labkit evaluate``."""
    from reconstruction.baselines import BASELINES

    parser = commands.add_parser(
        "evaluate",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "raw",
        type=Path,
        help="raw Bayer mosaic: raw (HDR) EXR, single-channel TIFF/PNG (with --cfa) or camera "
        "raw file (DNG, NEF, CR2, ARW, …)",
    )
    add_cfa_option(parser)
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument(
        "--baselines",
        default=",".join(BASELINES),
        help=f"comma-separated demosaicers, or 'none' (default {','.join(BASELINES)})",
    )
    parser.add_argument(
        "--colour-dispersion",
        type=Path,
        help="colour-channel model YAML (either direction): adds '<method> + warp' baselines",
    )
    parser.add_argument(
        "--image",
        action="append",
        default=[],
        metavar="NAME=RGB.exr",
        help="another colour estimate in raw colour, e.g. ours=recon/raw_colour.exr (repeatable)",
    )
    geometry = parser.add_mutually_exclusive_group()
    geometry.add_argument("--labels", type=Path, help="patch label image (PNG/TIFF/NPY)")
    geometry.add_argument("--scene", help="simulated scene whose chart geometry to use")
    parser.add_argument("--rig", type=Path, help="simulated rig YAML for --scene (default: sim)")
    parser.add_argument("--truth-colour", type=Path, help="aberration-free RGB EXR to compare with")
    parser.add_argument(
        "--truth",
        action="store_true",
        help="with --scene: compare with the simulator's dispersion-free raw-colour truth",
    )
    add_extrapolation_option(parser, model="--colour-dispersion's model")
    parser.set_defaults(handler=_evaluate)


def _evaluate(args: argparse.Namespace) -> int:
    from labkit.errors import DataError
    from labkit.io import read_mosaic
    from labkit.io.output_folder import (
        check_output_folder,
        staged_output_folder,
        verify_output_file,
    )
    from reconstruction import baseline_images, evaluate

    check_output_folder(args.out, command="labkit evaluate", inputs=[args.raw])
    if args.raw.is_file():
        verify_output_file(args.raw, what="raw image")
    raw = read_mosaic(args.raw, cfa=args.cfa)
    images_in = dict(_named_image(spec, raw.raw.shape) for spec in args.image)
    notes: list[str] = []
    methods = [] if args.baselines == "none" else [m.strip() for m in args.baselines.split(",")]
    model = None
    if args.colour_dispersion is not None:
        from calibration.dispersion_model import load_dispersion_model

        model = load_dispersion_model(args.colour_dispersion)
        if model.variables != "xy":
            raise DataError(
                f"--colour-dispersion {args.colour_dispersion} is a spectral (x, y, λ) model "
                "between filter bands, but evaluate warps the colour channels of its "
                "baselines: give a colour-channel model (`labkit calibrate dispersion HDR "
                "--reference G`); a spectral model warps spectral images (`labkit correct warp`)"
            )
        model, _, message = model_domain(
            model, args, shape=raw.raw.shape, what=f"--colour-dispersion {args.colour_dispersion}"
        )
        if message:
            notes.append(f"warning: {message}")
    boxes = labels = truth = None
    if args.labels is not None:
        from labkit.io.plane import read_labels

        labels = read_labels(args.labels, raw.raw.shape)
    if args.scene is not None:
        world = _world(args.rig, raw.raw.shape)
        if args.truth:
            from labkit.sim.truth import colour_truth

            truth = colour_truth(world, args.scene)
        if _is_chart(world, args.scene):
            from labkit.sim import colorchecker_patch_boxes

            boxes = colorchecker_patch_boxes(world.scene(args.scene))
    elif args.truth:
        raise DataError("--truth needs --scene (the simulator's truth of that scene)")
    if args.truth_colour is not None:
        truth = _read_rgb(args.truth_colour, raw.raw.shape, option="--truth-colour")
    _check_geometry(args, raw.raw.shape, boxes, labels)
    if args.scene is not None and boxes is None:
        no_score = (
            f"--scene {args.scene} is not a colour chart, so there is no residual-aberration "
            "score (it needs a chart's patches: a colorchecker scene, or --labels)"
        )
        if truth is None:
            raise DataError(
                f"{no_score}, and nothing else to score; add --truth (the simulator's "
                "truth of this scene) or --truth-colour, or evaluate an image of a chart"
            )
        notes.append(f"warning: {no_score}; scoring colour errors only")
    if not methods and not images_in:
        raise DataError("nothing to evaluate: give --baselines or at least one --image")
    images, seconds = baseline_images(raw.raw, cfa=raw.cfa, methods=methods,
                                      colour_dispersion=model)  # fmt: skip
    images.update(images_in)
    result = evaluate(raw.raw, images, cfa=raw.cfa, boxes=boxes, labels=labels,
                      truth_colour=truth, seconds=seconds)  # fmt: skip
    with staged_output_folder(args.out, command="labkit evaluate", inputs=[args.raw]) as stage:
        header, rows = _write_evaluation(args, raw, images, result, stage, notes)
    for note in notes:
        print(f"labkit: {note}", file=sys.stderr)
    for row in rows:
        print("  ".join(f"{h}: {v}" for h, v in zip(header, row, strict=True)))
    print(f"wrote {args.out / 'evaluation.json'}, evaluation.md, evaluation.html")
    return 0


def _write_evaluation(
    args: argparse.Namespace, raw, images: dict, result, stage: Path, notes: list[str]
):
    """The report, figures and JSON of an evaluation, into the staging folder; returns the
    table (header, rows). `notes` are the command's own warnings, added to the report."""
    from labkit.io import display_on_one_scale, write_png, write_text_atomic
    from labkit.report import Report, file_stem

    report = Report(f"labkit evaluate — {args.raw.name}")
    report.paragraph(
        f"Raw image `{args.raw}` ({raw.raw.shape[1]}×{raw.raw.shape[0]}, {raw.cfa}). "
        + " ".join([*result.notes, *(note[0].upper() + note[1:] + "." for note in notes)])
    )
    header, rows = result.table()
    report.table(header, rows)
    figures = []
    for name, image in display_on_one_scale(images).items():
        path = stage / f"{file_stem(name)}.png"
        write_png(path, image)
        figures.append((path.name, name))
    report.figures(figures, width_px=320)
    plain = {"raw": str(args.raw), **result.as_dict(), "warnings": list(notes)}
    write_text_atomic(stage / "evaluation.json", json.dumps(plain, indent=1) + "\n")
    report.write(stage, "evaluation")
    return header, rows


def _named_image(spec: str, shape: tuple[int, int]):
    from labkit.errors import DataError

    name, sep, path = spec.partition("=")
    if not sep or not name or not path:
        raise DataError(f"--image {spec!r}: expected NAME=PATH.exr, e.g. ours=recon/raw_colour.exr")
    return name, _read_rgb(Path(path), shape, option=f"--image {spec}")


def _read_rgb(path: Path, shape: tuple[int, int], *, option: str):
    """An RGB EXR in raw camera colour (a spectral EXR is refused), named by `option`."""
    from labkit.errors import DataError
    from labkit.io import read_rgb_exr

    try:
        rgb = read_rgb_exr(path)
    except DataError as error:
        raise DataError(f"{option}: {error}") from None
    if rgb.shape[:2] != tuple(shape):
        raise DataError(
            f"{path} is {rgb.shape[1]}×{rgb.shape[0]} px but the raw image is "
            f"{shape[1]}×{shape[0]} px; give images of the same raw image"
        )
    return rgb


def _check_geometry(args: argparse.Namespace, shape: tuple[int, int], boxes, labels) -> None:
    """The chart's patches fit the image's edge strips (before any work), naming the option
    that gave them."""
    if boxes is None and labels is None:
        return
    from labkit.errors import DataError
    from reconstruction.evaluate.residual_aberration import patch_regions

    try:
        patch_regions(shape, boxes=boxes, labels=labels)
    except DataError as error:
        where = f"--scene {args.scene}" if boxes is not None else f"--labels {args.labels}"
        raise DataError(f"{where} in {args.raw} ({shape[1]}×{shape[0]} px): {error}") from None


def _world(rig_path: Path | None, shape: tuple[int, int]):
    from labkit.errors import ConfigError
    from labkit.rig import default_rig_path, load_rig
    from labkit.sim import SimulatedRig

    rig = load_rig(rig_path or default_rig_path())
    if rig.sim is None:
        raise ConfigError(f"{rig_path}: --scene needs a simulated rig (a 'sim' section)")
    return SimulatedRig(rig, shape=shape)


def _is_chart(world, scene: str) -> bool:
    from labkit.errors import DataError

    scenes = world.rig.sim.scenes
    if scene not in scenes:
        raise DataError(f"--scene {scene!r} is not in the rig; its scenes: {sorted(scenes)}")
    return scenes[scene].type == "colorchecker"
