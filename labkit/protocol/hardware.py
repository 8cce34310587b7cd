"""Open a rig's devices: the camera backend, the slider driver and the stage.

For the simulated rig (``camera.backend: sim``) the camera is a
:class:`~labkit.sim.SimCamera`; a slider whose ``port`` is ``sim`` is a protocol
simulator on a pseudo-terminal (FW102C or Elliptec, as the rig's driver names) driven
through the same serial driver as real hardware, and its moves change the simulated
camera's illumination.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from typing import Any

from labkit.devices.camera import Camera
from labkit.devices.elliptec import Elliptec
from labkit.devices.fw102c import FW102C
from labkit.devices.slider import FilterSlider
from labkit.errors import ConfigError
from labkit.protocol.stage import OperatorStage, SimStage, Stage
from labkit.rig import Rig
from labkit.sim.camera import SimCamera
from labkit.sim.elliptec import ElliptecSimulator
from labkit.sim.fw102c import FW102CSimulator
from labkit.sim.world import SimulatedRig


@dataclass
class Hardware:
    """The opened devices of a rig; close with :meth:`close` or a ``with`` block."""

    camera: Camera
    slider: FilterSlider
    stage: Stage
    simulator: Any = None
    _closers: list = field(default_factory=list)

    def close(self) -> None:
        """Close every device (each failure is suppressed so the others still close)."""
        for close in reversed(self._closers):
            with contextlib.suppress(Exception):
                close()
        self._closers.clear()

    def __enter__(self) -> Hardware:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_camera(rig: Rig, *, fast: bool = True, shape: tuple[int, int] | None = None) -> Camera:
    """Open the rig's camera backend.

    The pixel format is left as the device has it: the engine checks the plan against
    the camera (exposure control first) before it configures the format.
    """
    config = rig.camera
    if config.backend == "sim":
        return SimCamera(SimulatedRig(rig, shape=shape), fast=fast)
    if config.backend == "aravis":
        from labkit.devices.aravis import AravisCamera

        return AravisCamera(config.device)
    from labkit.devices.genicam import GenICamCamera

    return GenICamCamera(rig.resolve_path(config.cti or ""), config.device)


def open_slider(rig: Rig, *, port: str | None = None) -> FilterSlider:
    """Open the rig's slider driver on `port` (default: the rig's port).

    The ``sim`` driver speaks the FW102C protocol (to a simulator on a pty).
    """
    config = rig.slider
    port = port or config.port
    timing = {
        "timeout_s": config.timeout_s,
        "move_timeout_s": config.move_timeout_s,
        "retries": config.retries,
    }
    if port == "sim":
        raise ConfigError(
            "slider.port 'sim' names the simulated slider; it is opened by open_hardware"
        )
    if config.driver == "elliptec":
        return Elliptec(port, address=config.address, **timing)
    return FW102C(port, **timing)


def open_hardware(
    rig: Rig,
    *,
    fast: bool = True,
    shape: tuple[int, int] | None = None,
    stage: Stage | None = None,
    assume_done: bool = False,
) -> Hardware:
    """Open camera, slider and stage of a rig (simulated parts included).

    Parameters
    ----------
    fast : bool
        Simulated devices do not wait for exposures, readout or motor moves.
    shape : (rows, cols), optional
        Override the simulated sensor size.
    stage : Stage, optional
        Operator actions; default: the simulated stage for ``sim`` cameras, else
        :class:`OperatorStage` (asks on the terminal unless `assume_done`).
    """
    closers: list = []
    try:
        camera = open_camera(rig, fast=fast, shape=shape)
        closers.append(camera.close)
        simulator = None
        sim_stage = None
        if rig.camera.backend == "sim":
            names = rig.slider.position_names()
            sim_stage = SimStage(camera, names, prerender=rig.illuminations())  # type: ignore[arg-type]
        if rig.slider.port == "sim" or rig.slider.driver == "sim":
            simulator = _start_simulator(rig, fast=fast, on_move=sim_stage and sim_stage.slot_moved)
            closers.append(simulator.stop)
            slider = open_slider(rig, port=simulator.port)
        else:
            slider = open_slider(rig)
        closers.append(slider.close)
        chosen = stage or sim_stage or OperatorStage(assume_done=assume_done)
        return Hardware(camera, slider, chosen, simulator, closers)
    except BaseException:
        for close in reversed(closers):
            with contextlib.suppress(Exception):
                close()
        raise


def _start_simulator(rig: Rig, *, fast: bool, on_move: Any) -> Any:
    slots = max(rig.slider.positions)
    time_scale = 0.0 if fast else 1.0
    first = min(rig.slider.positions)
    if rig.slider.driver == "elliptec":
        model = "ELL6" if slots <= 2 else "ELL9"
        simulator = ElliptecSimulator(
            model=model, address=rig.slider.address, time_scale=time_scale, on_move=on_move
        )
    else:
        simulator = FW102CSimulator(
            positions=6 if slots <= 6 else 12,
            position=first,
            time_scale=time_scale,
            on_move=on_move,
        )
    simulator.start()
    return simulator
