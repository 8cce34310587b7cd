"""labkit's files served by Tiled (``pip install 'labkit[tiled]'``): adapters for session
folders, HDR raw and spectral EXRs and dispersion models (:mod:`labkit.tiled.adapters`),
registered under labkit's mimetypes, and a folder of them as a Tiled tree
(:func:`labkit_tree`), which ``labkit serve FOLDER`` serves. In a Tiled catalog, the
adapters serve files registered with :func:`detect_mimetype` as the mimetype hook
(``tiled serve directory DATA --mimetype-hook labkit.tiled:detect_mimetype --adapter
MIMETYPE=labkit.tiled:ADAPTER …``, one ``--adapter`` per entry of
:data:`ADAPTERS_BY_MIMETYPE`).

>>> from tiled.client.constructors import from_app  # doctest: +SKIP
>>> from tiled.server.app import build_app  # doctest: +SKIP
>>> client = from_app(build_app(labkit_tree("data/")))  # doctest: +SKIP
"""

from labkit.tiled.adapters import (
    ADAPTERS_BY_MIMETYPE,
    DISPERSION_MODEL,
    RAW_EXR,
    SESSION,
    SPECTRAL_EXR,
    DispersionModelAdapter,
    RawExrAdapter,
    SessionAdapter,
    SpectralExrAdapter,
    detect_mimetype,
)
from labkit.tiled.tree import labkit_tree

__all__ = [
    "ADAPTERS_BY_MIMETYPE",
    "DISPERSION_MODEL",
    "RAW_EXR",
    "SESSION",
    "SPECTRAL_EXR",
    "DispersionModelAdapter",
    "RawExrAdapter",
    "SessionAdapter",
    "SpectralExrAdapter",
    "detect_mimetype",
    "labkit_tree",
]
