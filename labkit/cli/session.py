"""``labkit session show|import``: inspect sessions, build one from other software's frames."""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

from labkit.cli._commands import Commands
from labkit.errors import ConfigError
from labkit.rig import default_rig_path, load_rig


def register(commands: Commands) -> None:
    """Add ``labkit session …``."""
    parser = commands.add_parser("session")
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    show = actions.add_parser(
        "show",
        help="summarise a session: status, devices, frames per scene/illumination/exposure",
        description="Print what a session holds and how far its plan got. With --verify, "
        "re-hash every frame and report missing or corrupt ones (a resume re-captures them).",
    )
    show.add_argument("session", type=Path, help="session folder")
    show.add_argument("--verify", action="store_true", help="check every frame's sha256")
    show.set_defaults(handler=_show)
    imp = actions.add_parser(
        "import",
        help="build a session from TIFF frames or camera raw files (DNG, NEF, CR2, …)",
        description="Match the TIFF and camera raw files (DNG, NEF, CR2, CR3, ARW, … read "
        "by LibRaw) of FOLDER against --pattern (fields {scene}, {illumination}, {exposure} "
        "with unit, {replicate}; other {names} and * match anything) and store them as a "
        "labkit session. Example for FlyCapture-style names "
        "d1_disks32cmV2_450nm_100ms_2019-02-08-174831-0004.tif: --pattern "
        "'d1_{scene}_{illumination}_{exposure}_{date}-{replicate}.tif' --pattern "
        "'d1_dark_{exposure}_{date}-{replicate}.tif'. A TIFF frame's bit depth, "
        "justification and saturation level are read from its data and the rig's pixel "
        "format (8-bit files: 255; 16-bit files: N-bit data right- or left-justified); "
        "--bits, --saturation and --black-level override them. A camera raw file brings "
        "its black and white levels (checked against its data) and its exposure time, so "
        "its pattern may leave {exposure} out, e.g. --pattern '{scene}_{illumination}_*.NEF' "
        "--pattern 'dark_*.NEF'; its CFA layout must be the rig's. The levels are recorded "
        "in the manifest.",
    )
    imp.add_argument("session", type=Path, help="new session folder")
    imp.add_argument(
        "--from",
        dest="source",
        type=Path,
        action="append",
        required=True,
        help="folder of TIFF or camera raw files (repeatable, e.g. the frames and the darks)",
    )
    imp.add_argument(
        "--pattern",
        action="append",
        required=True,
        help="file-name pattern (repeatable; the first that matches wins)",
    )
    imp.add_argument(
        "--rig", default=None, help="rig YAML the frames came from (default: simulated)"
    )
    imp.add_argument(
        "--map",
        action="append",
        default=[],
        metavar="TEXT=SLOT",
        help="map an illumination text in file names to a rig slot name",
    )
    levels = imp.add_mutually_exclusive_group()
    levels.add_argument(
        "--bits",
        type=int,
        help="the files hold right-justified data of this many bits (saturation 2^bits − 1)",
    )
    levels.add_argument(
        "--saturation",
        type=float,
        metavar="DN",
        help="saturation level in the files' counts (e.g. 65520 for left-justified 12-bit)",
    )
    imp.add_argument(
        "--black-level", type=float, metavar="DN", help="black level in the files' counts (0)"
    )
    imp.add_argument("--no-progress", action="store_true", help="no progress bar")
    imp.set_defaults(handler=_import)


def _show(args: argparse.Namespace) -> int:
    from labkit.protocol.summary import summarise
    from labkit.session import Session

    session = Session.open(args.session)
    problems = session.verify() if args.verify else None
    print(summarise(session, problems=problems))
    return 1 if problems else 0


def _import(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from labkit.session.importer import import_session

    mapping = {}
    for item in args.map:
        text, sep, slot = item.partition("=")
        if not sep or not text or not slot:
            raise ConfigError(f"--map {item!r}: expected TEXT=SLOT, e.g. 450nm=450")
        mapping[text] = slot
    rig = load_rig(args.rig or default_rig_path())
    # disable=None: no bar when stderr is not a terminal (logs, pipes), so errors stay one line
    with tqdm(unit="frame", desc="import", disable=True if args.no_progress else None) as bar:
        session, unmatched = import_session(
            args.session,
            args.source,
            args.pattern,
            rig,
            mapping=mapping,
            bits=args.bits,
            saturation=args.saturation,
            black_level=args.black_level,
            progress=bar.update,
        )
    print(f"imported {len(session.records)} frames into {args.session}")
    levels = Counter(
        (r["levels_from"], r["saturation_dn"], r["black_level"]) for r in session.records.values()
    )
    for (reason, saturation, black), count in sorted(levels.items()):
        print(
            f"levels: {reason}: saturation {saturation:g} DN, black {black:g} DN ({count} frames)"
        )
    if unmatched:
        names = ", ".join(p.name for p in unmatched[:5])
        print(
            f"skipped {len(unmatched)} file(s) matching no pattern: {names}"
            + (" …" if len(unmatched) > 5 else "")
        )
    return 0
