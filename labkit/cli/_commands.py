"""The table of ``labkit`` commands: each command's module and its one-line summary.

The summaries live here, not in the modules, so that ``labkit --help`` and
``labkit --version`` list the commands without importing them (and NumPy, SciPy and the
rest behind them): a command's module is imported only when it runs, or when the whole
parser is built (:func:`labkit.cli.build_parser`, for the documentation and the tests).
"""

from __future__ import annotations

import argparse
from typing import Any, NamedTuple


class Command(NamedTuple):
    module: str
    summary: str


COMMANDS: dict[str, Command] = {
    "rig": Command("labkit.cli.rig", "inspect rig description files"),
    "devices": Command(
        "labkit.cli.devices",
        "list cameras (aravis, genicam) and serial ports (with --probe: which slider)",
    ),
    "capture": Command(
        "labkit.cli.capture",
        "run the exposure-bracketing + dark-frame protocol into a session folder",
    ),
    "session": Command("labkit.cli.session", "inspect or import capture sessions"),
    "hdr": Command("labkit.cli.hdr", "merge exposure brackets into HDR raw mosaics"),
    "target": Command(
        "labkit.cli.target", "a printable disk chart for dispersion calibration (SVG + PDF)"
    ),
    "calibrate": Command("labkit.cli.calibrate", "calibrate the camera and lens from HDR images"),
    "synthesize": Command(
        "labkit.cli.synthesize",
        "multispectral + synthetic RGB/raw images from filtered HDR images",
    ),
    "dispersion": Command("labkit.cli.dispersion", "inspect dispersion models"),
    "correct": Command("labkit.cli.correct", "correct images for lateral chromatic aberration"),
    "reconstruct": Command(
        "labkit.cli.reconstruct",
        "spectral image from one Bayer raw image, free of lateral chromatic aberration",
    ),
    "evaluate": Command(
        "labkit.cli.evaluate",
        "score baselines and reconstructions of one raw image (residual aberration, errors)",
    ),
    "export": Command(
        "labkit.cli.export", "convert a spectral image between spectral EXR and ENVI"
    ),
    "serve": Command("labkit.cli.serve", "serve a folder's sessions, EXRs and models with Tiled"),
    "sim": Command("labkit.cli.sim", "the simulated rig"),
    "demo": Command(
        "labkit.cli.demo",
        "run the main job on the simulated rig (or --real frames) and write a report",
    ),
    "bench": Command("labkit.cli.bench", "measure speed and memory (JSON + Markdown report)"),
}


class Commands:
    """What a command module's ``register`` adds its parser to: argparse's subparsers, with
    the command's summary taken from :data:`COMMANDS`."""

    def __init__(self, subparsers: argparse._SubParsersAction) -> None:
        self._subparsers = subparsers

    def add_parser(self, name: str, **options: Any) -> argparse.ArgumentParser:
        """argparse's ``add_parser`` for the command `name` of :data:`COMMANDS`."""
        parser: argparse.ArgumentParser = self._subparsers.add_parser(
            name, help=COMMANDS[name].summary, **options
        )
        return parser
