"""Open a rig's devices (real or simulated) as Bluesky devices: ophyd-async
(:func:`open_session_devices`, recommended) or ophyd v1 (:func:`open_devices`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Self

from labkit.bluesky.detector import SessionDetector, SessionTarget
from labkit.bluesky.devices import LabkitCamera, LabkitSlider, LabkitStage
from labkit.bluesky.movables import LightCover, ScenePositioner, SliderPositioner
from labkit.protocol.hardware import Hardware, open_hardware
from labkit.rig import Rig


class _OpenHardware:
    """Devices over an opened rig's hardware; close with :meth:`close` or a ``with`` block."""

    hardware: Hardware

    def close(self) -> None:
        """Close the camera, the slider and any simulator."""
        self.hardware.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass
class BlueskyDevices(_OpenHardware):
    """The ophyd devices of an opened rig; close with :meth:`close` or a ``with`` block."""

    camera: LabkitCamera
    slider: LabkitSlider
    stage: LabkitStage
    hardware: Hardware


def open_devices(
    rig: Rig,
    *,
    fast: bool = True,
    shape: tuple[int, int] | None = None,
    assume_done: bool = False,
) -> BlueskyDevices:
    """Open `rig`'s camera, slider and stage (:func:`labkit.protocol.hardware.open_hardware`)
    and wrap them as ophyd devices named ``camera``, ``slider`` and ``stage``.

    Parameters
    ----------
    fast : bool
        Simulated devices do not wait for exposures, readout or motor moves.
    shape : (rows, cols), optional
        Override the simulated sensor size.
    assume_done : bool
        On a real rig, do not ask the operator to change scenes or cover the light.
    """
    hardware = open_hardware(rig, fast=fast, shape=shape, assume_done=assume_done)
    try:
        return BlueskyDevices(
            LabkitCamera(hardware.camera, name="camera"),
            LabkitSlider(hardware.slider, rig.slider.position_names(), name="slider"),
            LabkitStage(hardware.stage, name="stage"),
            hardware,
        )
    except BaseException:
        hardware.close()
        raise


@dataclass
class SessionDevices(_OpenHardware):
    """The ophyd-async devices of an opened rig; close with :meth:`close` or a ``with``
    block."""

    detector: SessionDetector
    slider: SliderPositioner
    scene: ScenePositioner
    cover: LightCover
    hardware: Hardware


def open_session_devices(
    rig: Rig,
    session: str | Path,
    *,
    fast: bool = True,
    shape: tuple[int, int] | None = None,
    assume_done: bool = False,
    writer_workers: int = 2,
) -> SessionDevices:
    """Open `rig`'s camera, slider and stage (:func:`labkit.protocol.hardware.open_hardware`)
    as ophyd-async devices named ``camera``, ``slider``, ``scene`` and ``cover``, the
    camera's frames going into the session folder `session` (created, or resumed when it
    holds this rig's session).

    Parameters
    ----------
    fast : bool
        Simulated devices do not wait for exposures, readout or motor moves.
    shape : (rows, cols), optional
        Override the simulated sensor size.
    assume_done : bool
        On a real rig, do not ask the operator to change scenes or cover the light.
    writer_workers : int
        Threads storing frames.
    """
    hardware = open_hardware(rig, fast=fast, shape=shape, assume_done=assume_done)
    try:
        return session_devices(rig, session, hardware, writer_workers=writer_workers)
    except BaseException:
        hardware.close()
        raise


def session_devices(
    rig: Rig, session: str | Path, hardware: Hardware, *, writer_workers: int = 2
) -> SessionDevices:
    """`hardware`, already open (a camera, slider and stage of your own, say), as the
    ophyd-async devices :func:`open_session_devices` gives; closing them closes
    `hardware`."""
    slider_facts = {"port": hardware.slider.port, "identity": hardware.slider.identity}
    target = SessionTarget(Path(session), rig, slider_facts, writer_workers)
    return SessionDevices(
        SessionDetector(hardware.camera, target, name="camera"),
        SliderPositioner(hardware.slider, rig.slider.position_names(), name="slider"),
        ScenePositioner(hardware.stage, list(rig.plan.scenes), name="scene"),
        LightCover(hardware.stage, name="cover"),
        hardware,
    )
