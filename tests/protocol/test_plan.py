"""The capture plan (thesis Algorithm 10): counts, dark frames, keys, validation."""

from __future__ import annotations

from pathlib import Path

import pytest

from labkit.errors import ConfigError
from labkit.protocol import Capture, CoverLight, Meter, build_plan, validate_plan
from labkit.rig import load_rig
from labkit.sim import SimCamera, SimulatedRig


def test_thesis_plan_counts_and_dark_frames(thesis_rig_path: Path) -> None:
    plan = build_plan(load_rig(thesis_rig_path))
    # 2 scenes × (3 × 15 + 7 filters × 7 × 5) + darks (3 × 15 + 7 × 5)
    assert plan.frame_count == 660 and plan.pending_meters == 0
    keys = plan.keys()
    assert len({k.id for k in keys}) == 660 and len({k.path for k in keys}) == 660
    darks = {c.exposure_s: c.replicates for c in plan.captures() if c.scene is None}
    assert darks == {0.003: 15, 0.006: 15, 0.012: 15, 0.025: 5, 0.05: 5, 0.1: 5, 0.25: 5,
                     0.5: 5, 2.0: 5, 3.916: 5}  # fmt: skip
    first_dark = next(i for i, s in enumerate(plan.steps) if isinstance(s, CoverLight))
    assert all(c.scene is None for c in plan.steps[first_dark:] if isinstance(c, Capture))


def test_auto_illuminations_meter_first_then_use_their_bracket(make_rig) -> None:
    rig = load_rig(
        make_rig(
            **{
                "plan.exposures_s": {"unfiltered": [0.003, 0.006, 0.012], "filtered": "auto"},
                "plan.scenes": ["disks"],
            }
        )
    )
    plan = build_plan(rig)
    assert plan.pending_meters == 7 and plan.frame_count == 3 * 15 + 3 * 15
    for_450 = [s for s in plan.steps if isinstance(s, Meter | Capture) and s.illumination == "450"]
    assert len(for_450) == 1 and isinstance(for_450[0], Meter)
    brackets = {("disks", name): [0.2] for name in rig.illuminations() if name != "unfiltered"}
    done = build_plan(rig, brackets)
    assert done.pending_meters == 0 and done.frame_count == 3 * 15 + 7 * 5 + (3 * 15 + 5)


class _Slider:
    port = "/dev/ttyFAKE"
    slot_count = 6


def test_validation_rejects_missing_slots_and_out_of_range_exposures(
    sim_rig_path: Path, make_rig
) -> None:
    camera = SimCamera(SimulatedRig(load_rig(sim_rig_path), shape=(8, 8)))
    with pytest.raises(ConfigError, match=r"slider positions \[7, 8\] do not exist .*ttyFAKE"):
        validate_plan(build_plan(load_rig(sim_rig_path)), camera, _Slider())
    short = load_rig(make_rig(**{"plan.exposures_s.unfiltered": [1e-6, 0.01]}))
    with pytest.raises(ConfigError, match=r"1e-06 s \(for dark, unfiltered\) are outside"):
        validate_plan(build_plan(short), camera)
