"""``labkit capture``: run a rig's capture plan into a crash-safe, resumable session."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from labkit.cli._commands import Commands
from labkit.rig import default_rig_path, load_rig


def register(commands: Commands) -> None:
    """Add ``labkit capture``."""
    parser = commands.add_parser(
        "capture",
        description="Run the rig's capture plan: for every scene, the "
        "open slot and each filter, grab the replicates at every exposure time (or at "
        "auto-bracketed ones), then dark frames for every exposure used. Frames are stored "
        "crash-safely; running the same command on an unfinished session resumes it, "
        "re-capturing only missing or corrupt frames. Ctrl-C stops after the current frame.",
    )
    parser.add_argument("rig", nargs="?", help="rig YAML (default: the simulated rig)")
    parser.add_argument("--session", type=Path, required=True, help="session folder")
    parser.add_argument(
        "--dry-run",
        action="store_true",
        help="print the plan, check it against the devices' bounds, move nothing",
    )
    parser.add_argument(
        "--fast",
        action="store_true",
        help="simulated devices do not wait for exposures and motor moves",
    )
    parser.add_argument(
        "--yes",
        action="store_true",
        help="do not ask the operator to change scenes or cover the light",
    )
    parser.add_argument(
        "--shape",
        type=_shape,
        default=None,
        metavar="ROWSxCOLS",
        help="simulated sensor size (default: the rig's)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.set_defaults(handler=_capture)


def _shape(text: str) -> tuple[int, int]:
    """``--shape ROWSxCOLS``: both even (whole Bayer quads) and at least 8, as a rig's sensor."""
    try:
        rows, cols = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected ROWSxCOLS such as 256x320, got {text!r}"
        ) from None
    for name, value in (("ROWS", rows), ("COLS", cols)):
        if value < 8 or value > 16384 or value % 2:
            raise argparse.ArgumentTypeError(
                f"{text!r}: {name} {value} must be even and 8–16384 (whole 2×2 Bayer quads); "
                "give ROWSxCOLS such as 64x96"
            )
    return rows, cols


class _Bar:
    """tqdm progress: frames done / total, current step, ETA."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self.bar = None  # created when the plan is known, so early errors print no bar

    def set_total(self, total: int, done: int) -> None:
        if self.bar is None:
            from tqdm import tqdm

            self.bar = tqdm(
                total=total,
                unit="frame",
                desc="capture",
                disable=not self.enabled,
                dynamic_ncols=True,
            )
        self.bar.total = total
        self.bar.n = done
        self.bar.refresh()

    def advance(self, frames: int) -> None:
        if self.bar is not None:
            self.bar.update(frames)

    def set_step(self, text: str) -> None:
        if self.bar is not None:
            self.bar.set_postfix_str(text, refresh=False)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _capture(args: argparse.Namespace) -> int:
    from labkit.io.output_folder import writer_lock
    from labkit.protocol import build_plan, validate_plan
    from labkit.protocol.hardware import open_hardware

    rig_path = args.rig or default_rig_path()
    rig = load_rig(rig_path)
    if args.shape and rig.sim is not None:
        rig = rig.with_changes(
            {"sim": {"sensor": {"height": args.shape[0], "width": args.shape[1]}}}
        )
    if args.dry_run:
        return _dry_run(rig, args, build_plan, validate_plan, open_hardware)
    with writer_lock(args.session, command="labkit capture", option="--session"):
        return _capture_session(args, rig)


def _capture_session(args: argparse.Namespace, rig: Any) -> int:
    """Capture (or resume) the session; the caller holds the session's writer lock."""
    from labkit.protocol import Engine, build_plan, validate_plan
    from labkit.protocol.engine import CaptureStopped
    from labkit.protocol.hardware import open_hardware
    from labkit.session import SESSION_FILE, Session

    resumed = (args.session / SESSION_FILE).exists()
    if resumed:  # refuse another plan's session before touching any device
        session, _ = Session.open_for(args.session, rig)
    else:
        Session.check_creatable(args.session)
    if resumed and session.status == "imported":
        print(
            f"session {args.session} was imported ({len(session.records)} frames); capture "
            "does not add frames to an imported session"
        )
        return 0
    if resumed and session.status == "complete":
        todo = _incomplete(session, rig)
        if not todo:
            print(
                f"session {args.session} is already complete ({len(session.records)} frames, "
                "all match their sha256); nothing to do"
            )
            return 0
        print(f"session {args.session} is marked complete but {todo}", file=sys.stderr)
    if resumed:
        print(
            f"resuming session {args.session} ({len(session.records)} frames stored, "
            f"last status {session.status})",
            file=sys.stderr,
        )
    stop = threading.Event()
    previous = signal.getsignal(signal.SIGINT)

    def on_interrupt(signum: int, frame: Any) -> None:
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set()
        print("\nlabkit: stopping after the current frame (Ctrl-C again to abort)", file=sys.stderr)

    signal.signal(signal.SIGINT, on_interrupt)
    bar = _Bar(enabled=not args.no_progress)
    try:
        with open_hardware(rig, fast=args.fast, assume_done=args.yes) as hardware:
            if not resumed:  # created only once the devices opened and accept the plan
                validate_plan(build_plan(rig), hardware.camera, hardware.slider)
                session = Session.create(args.session, rig)
            engine = Engine(
                rig,
                hardware.camera,
                hardware.slider,
                hardware.stage,
                session,
                progress=bar,
                stop=stop,
            )
            report = engine.run()
    except CaptureStopped as stopped:
        bar.close()
        print(f"\nlabkit: {stopped}", file=sys.stderr)
        return 130
    finally:
        bar.close()
        signal.signal(signal.SIGINT, previous)
    mb = report.bytes_written / 1e6
    print(
        f"session {args.session}: complete, {len(session.records)} frames "
        f"({report.stored_now} stored now in {report.elapsed_s:.1f} s, "
        f"{report.frames_per_s:.1f} frames/s, {mb:.0f} MB)"
    )
    for name, text in report.brackets.items():
        print(f"  auto {name}: {text}")
    if report.recaptured:
        print(f"  re-captured {len(report.recaptured)} missing or corrupt frame(s)")
    return 0


def _incomplete(session: Any, rig: Any) -> str:
    """What a session marked complete still lacks (planned frames without a record,
    recorded frames missing or corrupt on disk), or ``""``."""
    from labkit.protocol import build_plan

    plan = build_plan(rig, session.brackets)
    unrecorded = sum(not session.has(key) for key in plan.keys())
    damaged = session.verify()
    parts = []
    if unrecorded:
        parts.append(f"{unrecorded} planned frame(s) have no record in frames.jsonl")
    if plan.pending_meters:
        parts.append(f"{plan.pending_meters} illumination(s) are not yet metered")
    if damaged:
        parts.append(f"{len(damaged)} recorded frame file(s) are missing or corrupt")
    return " and ".join(parts) + ("; re-capturing them" if parts else "")


def _dry_run(rig, args, build_plan, validate_plan, open_hardware) -> int:
    from labkit.session import SESSION_FILE, Session

    brackets = {}
    stored: set[str] = set()
    if (args.session / SESSION_FILE).exists():
        session, _ = Session.open_for(args.session, rig, repair=False)  # a dry run writes nothing
        brackets, stored = session.brackets, set(session.records)
        if session.status == "imported":
            print(f"session {args.session} was imported; a capture would not add frames to it")
        stored -= set(session.verify(hashes=False))  # a real run also checks each sha256
    else:  # the checks of a real run, before anything is captured
        Session.check_creatable(args.session)
    plan = build_plan(rig, brackets)
    print(plan.describe())
    if (args.session / SESSION_FILE).exists():
        todo = sum(key.id not in stored for key in plan.keys())
        print(f"session {args.session}: {len(stored)} frames stored, {todo} still to capture")
    with open_hardware(rig, fast=True, assume_done=True) as hardware:
        validate_plan(plan, hardware.camera, hardware.slider)
        bounds = hardware.camera.exposure_bounds()
        print(
            f"checked against {hardware.camera.identity} (exposure "
            f"{bounds.minimum:g}–{bounds.maximum:g} s) and the slider on {hardware.slider.port} "
            f"({hardware.slider.slot_count} slots): OK"
        )
    return 0
