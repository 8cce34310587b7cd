"""Device interfaces and drivers.

Interfaces: :class:`Camera` (``camera``) and :class:`FilterSlider` (``slider``).
Camera backends, imported on use because they load system libraries:
``labkit.devices.aravis.AravisCamera`` (GigE Vision through Aravis 0.8) and
``labkit.devices.genicam.GenICamCamera`` (Harvesters + a GenTL producer), which share
their GenICam feature handling (``labkit.devices.genicam_features``); the simulated
camera is :class:`labkit.sim.SimCamera`. Slider drivers (pyserial):
``labkit.devices.fw102c.FW102C`` and ``labkit.devices.elliptec.Elliptec``;
``labkit.devices.serial_ports`` lists and opens serial ports, and
``labkit.devices.slider_probe`` finds which slider answers on one.
"""

from labkit.devices.camera import Bounds, Camera, CameraIdentity, DeviceInfo
from labkit.devices.slider import FilterSlider

__all__ = ["Bounds", "Camera", "CameraIdentity", "DeviceInfo", "FilterSlider"]
