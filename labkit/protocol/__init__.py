"""The capture protocol (thesis Algorithm 10): plan, auto-bracketing, stage and engine."""

from labkit.protocol.bracketing import (
    BracketChoice,
    choose_exposures,
    estimate_rates,
    exposure_ladder,
    frame_levels,
    meter,
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
    "build_plan",
    "choose_exposures",
    "estimate_rates",
    "exposure_label",
    "exposure_ladder",
    "frame_levels",
    "meter",
    "validate_plan",
]
