"""The two capture plans of a job on the simulated rig: a calibration plan and a scene plan."""

from __future__ import annotations

from collections.abc import Sequence

from labkit.errors import ConfigError
from labkit.rig import Rig

SCENES = ("colorchecker", "texture")
"""Scenes of the scene plan by default."""


def simulated_plans(
    rig: Rig, shape: tuple[int, int], *, scenes: Sequence[str] = SCENES
) -> dict[str, Rig]:
    """The calibration and scene plans of `rig` (a simulated rig) on a sensor of `shape`.

    Both auto-bracket every exposure and take dark frames. ``"calibration"`` shoots a disk
    chart (disk radius a quarter of the pitch, 32 px pitch below 512 px, else 64 px) under
    every illumination; ``"scenes"`` shoots `scenes` (a texture scene is added to the rig
    if it has none) under the open slot. The demo and the gallery use them.

    Parameters
    ----------
    rig : Rig
        A rig with ``camera.backend: sim``.
    shape : (rows, cols)
        Sensor size, px.
    scenes : sequence of str
        Scenes of the scene plan.

    Raises
    ------
    ConfigError
        `rig` is not simulated, or a plan is not a valid rig (the message names the key).
    """
    if rig.camera.backend != "sim" or rig.sim is None:
        raise ConfigError(
            f"{rig.source or rig.name}: the simulated plans need a simulated rig "
            "(camera.backend: sim)"
        )
    pitch = 32 if min(shape) < 512 else 64
    added = {"disks": {"type": "disks", "radius_px": pitch // 4, "pitch_px": pitch}}
    if "texture" not in rig.sim.scenes:
        added["texture"] = {"type": "texture", "seed": 7}
    base = rig.with_changes(
        {
            "sim": {"sensor": {"width": shape[1], "height": shape[0]}, "scenes": added},
            "plan": {
                "exposures_s": {"unfiltered": "auto", "filtered": "auto"},
                "dark_frames": True,
            },
        }
    )
    return {
        "calibration": base.with_changes({"plan": {"scenes": ["disks"], "illuminations": "all"}}),
        "scenes": base.with_changes(
            {"plan": {"scenes": list(scenes), "illuminations": ["unfiltered"]}}
        ),
    }
