"""The filter slider, the scene and the light cover as ophyd-async movables.

Each ``set`` runs the device call on a worker thread and returns an
:class:`~ophyd_async.core.AsyncStatus`, so a RunEngine can move one while the camera
integrates. Positions have names: the slider takes a slot number or the name of the
illumination a slot gives (``"550"``), the scene a scene name, the cover ``True``
(covered) or ``False``.
"""

from __future__ import annotations

import asyncio
from collections.abc import Mapping

from ophyd_async.core import AsyncStatus, StandardReadable, soft_signal_r_and_setter
from ophyd_async.core import StandardReadableFormat as Format

from labkit.devices.slider import FilterSlider
from labkit.errors import ConfigError
from labkit.protocol.stage import Stage


class SliderPositioner(StandardReadable):
    """The filter slider: ``set(3)`` (a slot) or ``set("550")`` (the illumination a slot
    gives) moves it.

    Parameters
    ----------
    slider : FilterSlider
        An open slider; the device does not close it.
    positions : mapping slot → illumination name
        What each slot lights the scene with (the rig's ``slider.positions``).
    """

    def __init__(self, slider: FilterSlider, positions: Mapping[int, str], name: str = "") -> None:
        self.slider = slider
        self.positions = dict(positions)
        with self.add_children_as_readables(Format.HINTED_SIGNAL):
            self.slot, self._set_slot = soft_signal_r_and_setter(int, 0)
        with self.add_children_as_readables():
            self.illumination, self._set_illumination = soft_signal_r_and_setter(str, "")
        super().__init__(name=name)

    def slot_of(self, position: int | str) -> int:
        """The slot of `position`: a slot number (int), or the illumination a slot gives
        (str, e.g. ``"unfiltered"`` or ``"450"``)."""
        if isinstance(position, str):
            slots = [slot for slot, name in self.positions.items() if name == position]
            if not slots:
                raise ConfigError(
                    f"slider {self.name!r} has no slot giving {position!r}; its slots give "
                    f"{sorted(set(self.positions.values()))} (or pass a slot number)"
                )
            return slots[0]
        slot = int(position)
        if slot not in self.positions:
            raise ConfigError(
                f"slider {self.name!r} has no slot {slot}; its slots are {sorted(self.positions)}"
            )
        return slot

    @AsyncStatus.wrap
    async def set(self, value: int | str) -> None:
        """Move to a slot (number or illumination name); done when the move is."""
        slot = self.slot_of(value)
        await asyncio.to_thread(self.slider.move, slot)
        self._set_slot(slot)
        self._set_illumination(self.positions[slot])


class ScenePositioner(StandardReadable):
    """The scene before the camera: ``set("colorchecker")`` puts it there (an operator
    action on a real rig, a simulator call on the simulated one)."""

    def __init__(self, stage: Stage, scenes: list[str], name: str = "") -> None:
        self._stage = stage
        self.scenes = list(scenes)
        with self.add_children_as_readables(Format.HINTED_SIGNAL):
            self.scene, self._set_scene = soft_signal_r_and_setter(str, "")
        super().__init__(name=name)

    @AsyncStatus.wrap
    async def set(self, value: str) -> None:
        """Set the scene `value`, one of the rig's."""
        if value not in self.scenes:
            raise ConfigError(f"scene {value!r} is not one of the rig's: {self.scenes}")
        await asyncio.to_thread(self._stage.set_scene, value)
        self._set_scene(value)


class LightCover(StandardReadable):
    """The light cover for dark frames: ``set(True)`` covers the light, ``set(False)``
    uncovers it."""

    def __init__(self, stage: Stage, name: str = "") -> None:
        self._stage = stage
        with self.add_children_as_readables(Format.HINTED_SIGNAL):
            self.covered, self._set_covered = soft_signal_r_and_setter(bool, False)
        super().__init__(name=name)

    @AsyncStatus.wrap
    async def set(self, value: bool) -> None:
        """Cover (True) or uncover (False) the light."""
        action = self._stage.cover_light if value else self._stage.uncover_light
        await asyncio.to_thread(action)
        self._set_covered(bool(value))
