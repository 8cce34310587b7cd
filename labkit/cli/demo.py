"""``labkit demo``: run the main job on the simulated rig and write a report."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(commands: argparse._SubParsersAction) -> None:
    """Add ``labkit demo``."""
    parser = commands.add_parser(
        "demo",
        help="run the main job on the simulated rig and write a report",
        description="The whole job on the simulated rig: capture (auto-bracketing, dark "
        "frames) → HDR → dispersion calibration → reconstruction of the ColorChecker and "
        "textured scenes → evaluation against the simulator's truth and the baselines → "
        "DIR/report.html and report.md (previews, dispersion plots, crops, spectra, tables, "
        "timings) and DIR/results.json. About 5 minutes on 2 cores; --quick: under 2.",
    )
    parser.add_argument("--out", type=Path, default=Path("demo-out"), help="output folder")
    parser.add_argument("--rig", type=Path, default=None, help="rig YAML (default: simulated rig)")
    parser.add_argument("--quick", action="store_true", help="a 320×256 sensor, for a fast check")
    parser.set_defaults(handler=_demo)


def _demo(args: argparse.Namespace) -> int:
    from labkit.demo import run_demo

    report = run_demo(args.out, rig_path=args.rig, quick=args.quick)
    print(f"wrote {report} (and report.md, results.json)")
    return 0
