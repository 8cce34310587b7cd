"""``labkit demo``: run the main job on the simulated rig (or on real frames) and write a report."""

from __future__ import annotations

import argparse
from pathlib import Path

from labkit.cli._commands import Commands


def register(commands: Commands) -> None:
    """Add ``labkit demo``."""
    parser = commands.add_parser(
        "demo",
        description="The whole job on the simulated rig: capture (auto-bracketing, dark "
        "frames) → HDR → dispersion calibration → reconstruction of the ColorChecker and "
        "textured scenes → evaluation against the simulator's truth and the baselines → "
        "DIR/report.html and report.md (previews, dispersion plots, crops, spectra, tables, "
        "timings) and DIR/results.json; --quick: a smaller sensor. "
        "With --real, the job on real frames of a ColorChecker from the thesis' lab (the "
        "vendored set, or --data DIR laid out the same way): import → HDR → sensor map → "
        "multispectral and synthetic raw images → dispersion calibration → reconstruction → "
        "patch spectra against the chart's spectrometer reflectances and residual aberration "
        "against the demosaicing baselines.",
    )
    parser.add_argument("--out", type=Path, default=Path("demo-out"), help="output folder")
    parser.add_argument("--rig", type=Path, default=None, help="rig YAML (default: simulated rig; "
                        "with --real, rigs/example-flea3.yaml)")  # fmt: skip
    parser.add_argument("--quick", action="store_true", help="a 320×256 sensor, for a fast check")
    parser.add_argument(
        "--real", action="store_true", help="run on real frames instead of the simulated rig"
    )
    parser.add_argument(
        "--data",
        type=Path,
        default=None,
        help="with --real: folder with frames/, darks/ and labels.png named like the vendored "
        "set (default: labkit's own real ColorChecker frames)",
    )
    parser.add_argument(
        "--pattern",
        action="append",
        metavar="PATTERN",
        help="with --real: file-name pattern of the frames and darks, as for `labkit session "
        "import` (repeatable; default: the vendored set's)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    parser.set_defaults(handler=_demo)


def _demo(args: argparse.Namespace) -> int:
    from labkit.errors import ConfigError

    if not args.real and (args.data is not None or args.pattern):
        raise ConfigError("--data and --pattern name real captures; add --real")
    if args.real and args.quick:
        raise ConfigError(
            "--quick applies to the simulated demo; --real always runs the whole vendored set"
        )
    from labkit.io.output_folder import output_folder_in_place

    command = "labkit demo --real" if args.real else "labkit demo"
    with output_folder_in_place(args.out, command=command) as out:
        if args.real:
            from labkit.demo_real import run_real_demo

            report = run_real_demo(
                out,
                data=args.data,
                rig_path=args.rig,
                patterns=args.pattern,
                progress=False if args.no_progress else None,
            )
        else:
            from labkit.demo import run_demo

            report = run_demo(out, rig_path=args.rig, quick=args.quick)
    print(f"wrote {report} (and report.md, results.json)")
    return 0
