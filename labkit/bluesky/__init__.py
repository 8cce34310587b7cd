"""Bluesky integration (``pip install 'labkit[bluesky]'``): the rig's devices as ophyd
devices, thesis Algorithm 10 as a Bluesky plan, and a callback that writes the capture as
a labkit session.

>>> from bluesky import RunEngine
>>> from labkit.bluesky import SessionWriter, labkit_plan, open_devices
>>> RE = RunEngine()
>>> with open_devices(rig) as devices:  # doctest: +SKIP
...     RE.subscribe(SessionWriter("session/"))
...     RE(labkit_plan(devices.camera, devices.slider, rig, stage=devices.stage))
"""

from labkit.bluesky.devices import LabkitCamera, LabkitSlider, LabkitStage, frame_from_reading
from labkit.bluesky.hardware import BlueskyDevices, open_devices
from labkit.bluesky.plans import labkit_plan
from labkit.bluesky.session_writer import SessionWriter

__all__ = [
    "BlueskyDevices",
    "LabkitCamera",
    "LabkitSlider",
    "LabkitStage",
    "SessionWriter",
    "frame_from_reading",
    "labkit_plan",
    "open_devices",
]
