"""labkit: the lab side of a spectral camera toolkit.

Subpackages
-----------
labkit.spectra  spectra, datasets, filters, light sources, colour conversion
labkit.sim      the simulated rig: scenes, lens, sensor, camera, filter-slider simulator
labkit.io       image files (TIFF, PNG previews) and atomic writes
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
