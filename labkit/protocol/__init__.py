"""The capture protocol (thesis Algorithm 10): plan, auto-bracketing, stage, the protocol's
steps (:mod:`~labkit.protocol.steps`) and the engine that carries them out."""

from labkit.protocol._generators import drive, drive_within
from labkit.protocol.bracketing import (
    BracketChoice,
    auto_bracketing,
    choose_bracket,
    choose_exposures,
    estimate_rates,
    exposure_ladder,
    frame_levels,
    meter,
    metering,
    run_auto_bracketing,
    usable_in,
)
from labkit.protocol.engine import CaptureReport, CaptureStopped, Engine
from labkit.protocol.plan import (
    DARK,
    Capture,
    CoverLight,
    FrameKey,
    Meter,
    MoveFilter,
    Plan,
    SetScene,
    UncoverLight,
    build_plan,
    exposure_label,
    validate_plan,
)
from labkit.protocol.stage import OperatorStage, SimStage, Stage
from labkit.protocol.steps import check_frame, configure_camera, protocol_steps

__all__ = [
    "DARK",
    "BracketChoice",
    "Capture",
    "CaptureReport",
    "CaptureStopped",
    "CoverLight",
    "Engine",
    "FrameKey",
    "Meter",
    "MoveFilter",
    "OperatorStage",
    "Plan",
    "SetScene",
    "SimStage",
    "Stage",
    "UncoverLight",
    "auto_bracketing",
    "build_plan",
    "check_frame",
    "choose_bracket",
    "choose_exposures",
    "configure_camera",
    "drive",
    "drive_within",
    "estimate_rates",
    "exposure_label",
    "exposure_ladder",
    "frame_levels",
    "meter",
    "metering",
    "protocol_steps",
    "run_auto_bracketing",
    "usable_in",
    "validate_plan",
]
