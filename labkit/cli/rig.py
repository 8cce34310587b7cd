"""``labkit rig check RIG.yaml``: validate a rig file and summarise it."""

from __future__ import annotations

import argparse
from pathlib import Path

from labkit.cli._commands import Commands
from labkit.protocol.plan import build_plan
from labkit.rig import Rig, load_rig


def register(commands: Commands) -> None:
    """Add ``labkit rig …``."""
    parser = commands.add_parser("rig")
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    check = actions.add_parser(
        "check",
        help="validate a rig YAML file and print what it describes",
        description="Validate a rig file against the schema; on error, print one line naming "
        "the file, the key, the bad value and what is expected.",
    )
    check.add_argument("rig", help="rig YAML file, e.g. rigs/simulated.yaml")
    check.set_defaults(handler=_check)


def plan_frame_count(rig: Rig) -> int:
    """Frames the rig's plan stores (-1 when auto-bracketing decides at run time)."""
    plan = build_plan(rig)
    return -1 if plan.pending_meters else plan.frame_count


def _check(args: argparse.Namespace) -> int:
    rig = load_rig(args.rig)
    _check_response(rig, args.rig)
    camera = rig.camera
    print(f"{args.rig}: valid rig '{rig.name}' (format {rig.format})")
    print(f"  camera  {camera.backend} device={camera.device or '(first found)'} "
          f"{camera.pixel_format} → CFA {rig.cfa}, response {camera.response}")  # fmt: skip
    print(f"  slider  {rig.slider.driver} on {rig.slider.port}:")
    for slot, position in sorted(rig.slider.positions.items()):
        filt = position.filter
        what = "open" if filt is None else (
            f"{filt.centre_nm:g} nm, FWHM {filt.fwhm_nm:g} nm, OD {filt.optical_density:g}"
            + (f", measured '{filt.measured}'" if filt.measured else "")
        )  # fmt: skip
        print(f"    {slot:>2}  {position.name:<12} {what}")
    frames = plan_frame_count(rig)
    count = "auto-bracketed" if frames < 0 else f"{frames} frames"
    print(f"  plan    scenes {rig.plan.scenes}, {len(rig.illuminations())} illuminations, {count}")
    if rig.sim is not None and camera.backend == "sim":
        s, lens = rig.sim.sensor, rig.sim.lens
        print(f"  sim     {s.width}×{s.height}, {s.adc_bits}-bit, full well {s.full_well_e:g} e⁻; "
              f"lens {lens.spectral_profile}/{lens.radial_profile} {lens.max_shift_px:g} px; "
              f"scenes {sorted(rig.sim.scenes)}")  # fmt: skip
    return 0


def _check_response(rig: Rig, path: Path) -> None:
    """The camera response loads (a dataset name that exists, a file that parses)."""
    from calibration.sensitivity import load_response
    from labkit.errors import ConfigError, DataError

    try:
        load_response(rig.response_source())
    except DataError as error:
        raise ConfigError(f"{path}: camera.response: {error}") from None
