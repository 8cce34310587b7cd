"""The simulated rig's two capture plans (:func:`labkit.sim.simulated_plans`)."""

from __future__ import annotations

import pytest

from labkit.errors import ConfigError
from labkit.rig import default_rig_path, load_rig
from labkit.sim import simulated_plans


@pytest.mark.parametrize(("shape", "pitch"), [((192, 256), 32), ((768, 1024), 64)])
def test_the_plans_crop_the_sensor_and_split_calibration_from_scenes(shape, pitch) -> None:
    rig = load_rig(default_rig_path())
    plans = simulated_plans(rig, shape, scenes=("colorchecker", "texture"))
    for plan in plans.values():
        sensor = plan.sim.sensor
        assert (sensor.height, sensor.width) == shape
        assert plan.exposures_for("unfiltered") == "auto" and plan.plan.dark_frames
        assert plan.sim.scenes["disks"].pitch_px == pitch
        assert plan.sim.scenes["disks"].radius_px == pitch // 4
    calibration, scenes = plans["calibration"], plans["scenes"]
    assert calibration.plan.scenes == ["disks"]
    assert calibration.illuminations() == rig.illuminations()  # every filter
    assert scenes.plan.scenes == ["colorchecker", "texture"]
    assert scenes.illuminations() == ["unfiltered"]
    assert rig.sim.sensor.width != shape[1]  # the rig itself is left as it was


def test_a_real_rig_has_no_simulated_plans(repo_root) -> None:
    rig = load_rig(repo_root / "rigs" / "example-flea3.yaml")
    with pytest.raises(ConfigError, match="simulated rig"):
        simulated_plans(rig, (192, 256))
