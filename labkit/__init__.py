"""labkit: the lab side of a spectral camera toolkit.

The main entry points are importable from here (``from labkit import load_rig,
SimulatedRig, run_hdr``); each loads its module on first use, so ``import labkit`` stays
cheap. The spectral reconstruction and the calibrations are the packages
:mod:`reconstruction` and :mod:`calibration`.

Subpackages
-----------
labkit.spectra  spectra, datasets, filters, light sources, colour conversion
labkit.sim      the simulated rig: scenes, lens, sensor, camera, filter-slider simulator
labkit.devices  camera and filter-slider drivers
labkit.protocol the capture plan (thesis Algorithm 10), auto-bracketing, the engine
labkit.session  the session folder: frames, manifest, import from other software
labkit.hdr      HDR merging (thesis Algorithm 11)
labkit.io       image files (raw TIFF and EXR, spectral EXR, ENVI, PNG previews)
labkit.cli      the ``labkit`` command
labkit.bench    the benchmark harness (``labkit bench``)

Modules
-------
labkit.cfa      Bayer colour-filter-array layouts
labkit.rig      rig description files (``rigs/*.yaml``): schema and loader
labkit.errors   the error hierarchy
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("labkit")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

#: Name → the module that defines it; loaded on first use (PEP 562).
_EXPORTS = {
    "ConfigError": "labkit.errors",
    "DataError": "labkit.errors",
    "DeviceError": "labkit.errors",
    "Engine": "labkit.protocol",
    "LabkitError": "labkit.errors",
    "RawImage": "labkit.io",
    "Rig": "labkit.rig",
    "Session": "labkit.session",
    "SimCamera": "labkit.sim",
    "SimulatedRig": "labkit.sim",
    "Spectra": "labkit.spectra",
    "SpectralImage": "labkit.io",
    "build_plan": "labkit.protocol",
    "camera_response": "labkit.spectra",
    "load_rig": "labkit.rig",
    "merge_exposures": "labkit.hdr",
    "open_hardware": "labkit.protocol.hardware",
    "read_mosaic": "labkit.io",
    "read_raw_exr": "labkit.io",
    "read_spectral_exr": "labkit.io",
    "run_hdr": "labkit.hdr",
    "write_envi": "labkit.io",
    "write_spectral_exr": "labkit.io",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> object:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'labkit' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
