"""``labkit hdr SESSION [SESSION …] --out DIR``: merge exposure brackets into HDR raw EXRs."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from labkit.cli._commands import Commands


def register(commands: Commands) -> None:
    """Add ``labkit hdr``."""
    parser = commands.add_parser(
        "hdr",
        description="For every scene × illumination of one or more capture sessions: average the "
        "replicates, subtract the mean dark frame of each exposure, fit the scaling factor "
        "between consecutive exposures (first principal component of pixels within 2–95 %% "
        "of saturation in both), blend, and write OUT/<scene>/<illumination>.exr (float32 "
        "'raw' as a fraction of saturation at the shortest exposure; 'variance' with "
        "--method noise), a PNG preview, and OUT/hdr.yaml with the scaling factors against "
        "the exposure-time ratios. The folder is written as one set (OUT/labkit-run.json lists "
        "its files and checksums): an interrupted run leaves the previous folder untouched, "
        "and a second run into the same folder is refused while one is writing. Every frame "
        "is checked against the checksum recorded at capture.",
    )
    parser.add_argument(
        "session",
        type=Path,
        nargs="+",
        help="capture session folder(s), e.g. a calibration session and a session of scenes",
    )
    parser.add_argument(
        "--out",
        type=Path,
        required=True,
        help="output folder: new, empty, or from an earlier labkit run (replaced as a whole)",
    )
    parser.add_argument(
        "--method",
        choices=("thesis", "noise"),
        default="thesis",
        help="thesis: the thesis' weights (eroded blooming weight, local weight); "
        "noise: inverse-variance weights from a Poisson–Gaussian noise model fitted to the "
        "replicates and darks, and a per-pixel variance channel (default: thesis)",
    )
    parser.add_argument(
        "--no-dark",
        action="store_true",
        help="allow exposures without dark frames: subtract the black level only "
        "(dark current then stays in the image); without it, missing darks are an error",
    )
    parser.add_argument("--scene", action="append", help="merge only this scene (repeatable)")
    parser.add_argument(
        "--illumination", action="append", help="merge only this illumination (repeatable)"
    )
    parser.add_argument("--no-preview", action="store_true", help="skip the PNG previews")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument(
        "--factors",
        action="store_true",
        help="also print each image's scaling factors against the exposure-time ratios "
        "(they are in OUT/hdr.yaml in any case)",
    )
    parser.add_argument(
        "--quiet",
        action="store_true",
        help="print only warnings and the closing line, not one line per image",
    )
    parser.set_defaults(handler=_hdr)


def _warn_of_missing_frames(sessions: list[Path]) -> None:
    """One warning line per session that lacks frames of its plan (stopped early, or a
    manifest line lost): the merge goes on with what is there."""
    from labkit.protocol.summary import missing_frames
    from labkit.session import Session

    for folder in sessions:
        session = Session.open(folder)
        missing, planned = missing_frames(session)
        if missing and session.records:  # with none, the merge refuses the session itself
            print(
                f"labkit: warning: session {folder} ({session.info['status']}) lacks {missing} "
                f"of its {planned} planned frames; they are left out of the merge — resume the "
                f"capture (`labkit capture RIG --session {folder}`) to take them",
                file=sys.stderr,
            )


def _hdr(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from labkit.hdr import factor_table, image_summary, plan_sessions, run_hdr
    from labkit.io.output_folder import check_output_folder

    check_output_folder(args.out, command="labkit hdr", inputs=args.session)
    _warn_of_missing_frames(args.session)
    plans = plan_sessions(
        args.session, scenes=args.scene, illuminations=args.illumination, no_dark=args.no_dark
    )
    reports = []

    def report(output) -> None:
        result = output.result
        if args.quiet:
            text = [f"{output.job.name}:"] if result.warnings else []
        else:
            text = [f"{output.job.name}: {image_summary(result)} → {output.exr}"]
        if args.factors:
            text.append(factor_table(result))
            if result.noise is not None:
                text.append(f"gain {result.noise.gain_dn_per_e:.4f} DN/e⁻")
        if not args.quiet:
            text.extend(f"  note: {n}" for n in result.notes)
        text.extend(f"  warning: {w}" for w in result.warnings)
        if text:
            reports.append("\n".join(text))

    with tqdm(
        total=sum(p.frame_count for p in plans), unit="frame", desc="hdr", disable=args.no_progress
    ) as bar:
        run = run_hdr(
            args.session,
            args.out,
            method=args.method,
            no_dark=args.no_dark,
            scenes=args.scene,
            illuminations=args.illumination,
            previews=not args.no_preview,
            on_frame=lambda: bar.update(),
            on_image=lambda output: (bar.set_postfix_str(output.job.name), report(output)),
            on_warning=lambda text: print(f"labkit: warning: {text}", file=sys.stderr),
        )
    if reports:
        print("\n".join(reports))
    warned = sum(bool(o.result.warnings) for o in run.outputs)
    tail = f"; {warned} with warnings (above)" if warned else ""
    print(f"{len(run.outputs)} HDR image(s) and {run.index}{tail}")
    return 0
