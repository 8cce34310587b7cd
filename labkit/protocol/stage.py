"""What the engine cannot motorise: the scene in front of the camera and the light cover.

On a real rig an operator does these (:class:`OperatorStage` asks on the terminal); on
the simulated rig :class:`SimStage` tells the simulated camera directly. The slider's
moves reach the simulated camera through :meth:`SimStage.slot_moved`.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Mapping
from typing import Protocol, TextIO

from labkit.errors import DeviceError
from labkit.sim.camera import SimCamera
from labkit.sim.world import DARK


class Stage(Protocol):
    """Scene changes and the light cover."""

    def set_scene(self, scene: str) -> None:
        """Put `scene` in front of the camera."""
        ...

    def cover_light(self) -> None:
        """Block the light (dark frames)."""
        ...

    def uncover_light(self) -> None:
        """Unblock the light."""
        ...


class OperatorStage:
    """Asks the operator to act and waits for Enter.

    Parameters
    ----------
    ask : callable, optional
        ``ask(prompt) -> str``; default reads the terminal. With ``assume_done=True``
        nothing is asked (the operator prepared the rig, e.g. a one-scene plan).
    """

    def __init__(
        self,
        *,
        ask: Callable[[str], str] | None = None,
        out: TextIO | None = None,
        assume_done: bool = False,
    ) -> None:
        self._ask = ask or input
        self._out = out or sys.stderr
        self.assume_done = assume_done

    def _request(self, action: str) -> None:
        if self.assume_done:
            print(f"labkit: assuming done: {action}", file=self._out)
            return
        try:
            self._ask(f"\n>>> {action}, then press Enter: ")
        except EOFError:
            raise DeviceError(
                f"operator action needed ({action}) but there is no terminal to ask; "
                "run interactively, or pass --yes if the rig is already prepared"
            ) from None

    def set_scene(self, scene: str) -> None:
        self._request(f"Place scene {scene!r} in front of the camera")

    def cover_light(self) -> None:
        self._request("Cover the light source (dark frames)")

    def uncover_light(self) -> None:
        self._request("Uncover the light source")


class SimStage:
    """Scene and light cover of the simulated rig, applied to a :class:`SimCamera`.

    Parameters
    ----------
    camera : SimCamera
    slot_names : mapping slot → illumination name
        What each slider slot lights the scene with.
    prerender : list of str, optional
        Illuminations to render together when a scene is set (faster than one by one).
    """

    def __init__(
        self,
        camera: SimCamera,
        slot_names: Mapping[int, str],
        *,
        prerender: list[str] | None = None,
    ) -> None:
        self.camera = camera
        self.slot_names = dict(slot_names)
        self.prerender = list(prerender or [])
        self.covered = False
        self.illumination = camera.illumination

    def set_scene(self, scene: str) -> None:
        self.camera.set_scene(scene)
        if self.prerender:
            self.camera.rig.prerender(scene, self.prerender)

    def cover_light(self) -> None:
        self.covered = True
        self.camera.set_illumination(DARK)

    def uncover_light(self) -> None:
        self.covered = False
        self.camera.set_illumination(self.illumination)

    def slot_moved(self, slot: int) -> None:
        """Slider callback: the light now passes through `slot`."""
        self.illumination = self.slot_names.get(slot, self.illumination)
        if not self.covered:
            self.camera.set_illumination(self.illumination)
