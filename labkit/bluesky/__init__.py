"""Bluesky integration (``pip install 'labkit[bluesky]'``).

Recommended: the rig's devices as **ophyd-async** devices whose camera writes a labkit
session as it captures (:class:`SessionDetector`; its documents point at the frames'
files), and thesis Algorithm 10 as plans, whole (:func:`capture_protocol`) or in parts
(:func:`session_run`, :func:`bracket`, :func:`dark_series`):

>>> from bluesky import RunEngine
>>> from labkit.bluesky import capture_protocol, open_session_devices
>>> RE = RunEngine()
>>> with open_session_devices(rig, "session/") as d:  # doctest: +SKIP
...     RE(capture_protocol(d.detector, d.slider, d.scene, d.cover))

Also kept, for ophyd v1 set-ups: :class:`LabkitCamera`, :class:`LabkitSlider` and
:class:`LabkitStage` (synchronous; every frame's pixels travel inside its event),
:func:`labkit_plan` and the :class:`SessionWriter` callback that turns its documents into
a session.
"""

from labkit.bluesky.capture_plans import (
    acquire_frame,
    bracket,
    capture_protocol,
    dark_series,
    meter_frame,
    session_run,
)
from labkit.bluesky.detector import FRAME_FACTS, MeteringCamera, SessionDetector, SessionTarget
from labkit.bluesky.devices import LabkitCamera, LabkitSlider, LabkitStage, frame_from_reading
from labkit.bluesky.hardware import (
    BlueskyDevices,
    SessionDevices,
    open_devices,
    open_session_devices,
    session_devices,
)
from labkit.bluesky.movables import LightCover, ScenePositioner, SliderPositioner
from labkit.bluesky.plans import labkit_plan
from labkit.bluesky.session_writer import SessionWriter
from labkit.bluesky.streams import BRACKETS, METERING, PRIMARY, STATISTICS

__all__ = [
    "BRACKETS",
    "FRAME_FACTS",
    "METERING",
    "PRIMARY",
    "STATISTICS",
    "BlueskyDevices",
    "LabkitCamera",
    "LabkitSlider",
    "LabkitStage",
    "LightCover",
    "MeteringCamera",
    "ScenePositioner",
    "SessionDetector",
    "SessionDevices",
    "SessionTarget",
    "SessionWriter",
    "SliderPositioner",
    "acquire_frame",
    "bracket",
    "capture_protocol",
    "dark_series",
    "frame_from_reading",
    "labkit_plan",
    "meter_frame",
    "open_devices",
    "open_session_devices",
    "session_devices",
    "session_run",
]
