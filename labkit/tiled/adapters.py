"""Tiled adapters for labkit's files (``pip install 'labkit[tiled]'``).

Each adapter is built from one file or folder (``from_uris``, as Tiled builds adapters)
and is served by Tiled as:

========================  =============================================================
what                      served as
========================  =============================================================
session folder            a container (metadata: ``session.yaml``) holding ``frames``:
                          one ``uint16`` array per frame, nested as the frames' files
                          are (scene / illumination / exposure / replicate), each with
                          its ``frames.jsonl`` record as metadata; read when asked for
HDR raw EXR               an xarray dataset: ``raw`` (and ``variance``) over ``y``,
                          ``x``; attributes (metadata ``attrs``): CFA, exposure,
                          illumination, provenance
spectral EXR              an xarray dataset: ``spectral`` over ``y``, ``x``,
                          ``wavelength`` with the band centres (nm) as the
                          ``wavelength`` coordinate; attributes ``wavelengths_nm``
dispersion model (YAML)   a container with the model as metadata (its kind, direction,
                          domain, fit statistics); no data
========================  =============================================================

The values are labkit's own readers' (:func:`labkit.io.read_raw_exr`,
:func:`labkit.io.read_spectral_exr`, :func:`labkit.io.read_raw_tiff`), bit for bit.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import dask
import dask.array
import numpy as np
import xarray
from tiled.adapters.array import ArrayAdapter
from tiled.adapters.mapping import MapAdapter
from tiled.adapters.xarray import DatasetAdapter
from tiled.structures.core import Spec
from tiled.utils import path_from_uri

from calibration.dispersion_model import KIND as MODEL_KIND
from calibration.dispersion_model import load_dispersion_model
from labkit.io import read_raw_exr, read_raw_tiff, read_spectral_exr
from labkit.io.exr import is_spectral_layout, read_exr_header
from labkit.session import Session

SESSION = "application/x-labkit-session"
RAW_EXR = "image/x-labkit-raw-exr"
SPECTRAL_EXR = "image/x-labkit-spectral-exr"
DISPERSION_MODEL = "application/x-labkit-dispersion-model"
"""The mimetypes labkit's adapters are registered under."""


def _json(value: Any) -> Any:
    """`value` as plain JSON types (dates and numpy numbers as Tiled can send them)."""
    return json.loads(json.dumps(value, default=_plain))


def _plain(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)


def _path(data_uri: str) -> Path:
    return Path(path_from_uri(data_uri)) if "://" in data_uri else Path(data_uri)


class _FromFile:
    """Built from its one file (or folder), also when a Tiled catalog asks."""

    @classmethod
    def from_catalog(cls, data_source: Any, node: Any, /, **kwargs: Any) -> Any:
        """The adapter of a node registered in a Tiled catalog (``tiled register``, ``tiled
        serve directory``): read from its file again."""
        (asset,) = [a for a in data_source.assets if a.parameter == "data_uri"]
        return cls.from_uris(asset.data_uri)  # type: ignore[attr-defined]


def _frame_adapter(folder: Path, record: dict[str, Any]) -> ArrayAdapter:
    path = folder / record["file"]
    shape = tuple(int(n) for n in record["shape"])
    pixels = dask.array.from_delayed(
        dask.delayed(lambda: read_raw_tiff(path)[0])(), shape=shape, dtype=np.uint16
    )
    return ArrayAdapter.from_array(
        pixels, dims=("y", "x"), metadata=_json(record), specs=[Spec("labkit_frame")]
    )


class SessionAdapter(_FromFile, MapAdapter):
    """A capture session: ``frames`` (nested like the frames' files) with each frame's
    record, and ``session.yaml`` as metadata."""

    @classmethod
    def from_uris(cls, data_uri: str, **kwargs: Any) -> SessionAdapter:
        """The session in the folder `data_uri` (a path or ``file://`` URI)."""
        session = Session.open(_path(data_uri))
        tree: dict[str, Any] = {}
        for record in sorted(session.records.values(), key=lambda r: r["file"]):
            parts = Path(record["file"]).with_suffix("").parts[1:]  # below frames/
            node = tree
            for part in parts[:-1]:
                node = node.setdefault(part, {})
            node[parts[-1]] = _frame_adapter(session.folder, record)
        return cls(
            {"frames": nested_containers(tree)},
            metadata=_json(session.info),
            specs=[Spec("labkit_session")],
        )


def nested_containers(tree: Mapping[str, Any]) -> MapAdapter:
    """A Tiled container of `tree`: a nested mapping becomes a container, a function (of
    no arguments) is called for its adapter when a client first asks for that node, and an
    adapter is served as it is."""
    return MapAdapter(_OnDemand(tree))


class _OnDemand(Mapping[str, Any]):
    """The children of :func:`nested_containers`, each built once, when first asked for."""

    def __init__(self, tree: Mapping[str, Any]) -> None:
        self._tree = tree
        self._built: dict[str, Any] = {}

    def __getitem__(self, key: str) -> Any:
        if key not in self._built:
            value = self._tree[key]
            if isinstance(value, Mapping):
                value = nested_containers(value)
            elif callable(value):
                value = value()
            self._built[key] = value
        return self._built[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._tree)

    def __len__(self) -> int:
        return len(self._tree)


class RawExrAdapter(_FromFile, DatasetAdapter):
    """An HDR raw (or raw) EXR: ``raw`` and, when stored, ``variance``."""

    @classmethod
    def from_uris(cls, data_uri: str, **kwargs: Any) -> RawExrAdapter:
        """The raw EXR at `data_uri` (a path or ``file://`` URI)."""
        image = read_raw_exr(_path(data_uri))
        variables = {"raw": (("y", "x"), image.raw)}
        if image.variance is not None:
            variables["variance"] = (("y", "x"), image.variance)
        metadata = {
            "cfa": image.cfa,
            "exposure_s": image.exposure_s,
            "illumination": image.illumination,
            "wavelength_nm": image.wavelength_nm,
            "labkit": image.labkit,
        }
        dataset = xarray.Dataset(variables, attrs=_json(metadata))
        return cls.from_dataset(dataset, specs=[Spec("labkit_raw_exr")])  # type: ignore[return-value]


class SpectralExrAdapter(_FromFile, DatasetAdapter):
    """A spectral EXR: ``spectral`` over ``y``, ``x``, ``wavelength`` (nm)."""

    @classmethod
    def from_uris(cls, data_uri: str, **kwargs: Any) -> SpectralExrAdapter:
        """The spectral EXR at `data_uri` (a path or ``file://`` URI)."""
        image = read_spectral_exr(_path(data_uri))
        metadata = {
            "wavelengths_nm": [float(w) for w in image.wavelengths_nm],
            "wavelength_units": "nm",
            "labkit": image.labkit,
        }
        dataset = xarray.Dataset(
            {"spectral": (("y", "x", "wavelength"), image.cube)},
            coords={"wavelength": ("wavelength", np.asarray(image.wavelengths_nm))},
            attrs=_json(metadata),
        )
        return cls.from_dataset(dataset, specs=[Spec("labkit_spectral_exr")])  # type: ignore[return-value]


class DispersionModelAdapter(_FromFile, MapAdapter):
    """A dispersion model file: the model (as written) as metadata."""

    @classmethod
    def from_uris(cls, data_uri: str, **kwargs: Any) -> DispersionModelAdapter:
        """The dispersion model YAML at `data_uri` (a path or ``file://`` URI)."""
        model = load_dispersion_model(_path(data_uri))
        return cls({}, metadata=_json(model.to_dict()), specs=[Spec("labkit_dispersion_model")])


ADAPTERS_BY_MIMETYPE: dict[str, type] = {
    SESSION: SessionAdapter,
    RAW_EXR: RawExrAdapter,
    SPECTRAL_EXR: SpectralExrAdapter,
    DISPERSION_MODEL: DispersionModelAdapter,
}
"""labkit's adapters by mimetype, for Tiled's ``adapters_by_mimetype``."""


def detect_mimetype(path: str | Path, mimetype: str | None = None) -> str | None:
    """labkit's mimetype of `path`, else `mimetype` (what Tiled guessed): a session folder
    (it holds ``session.yaml``), a raw or spectral EXR (by its channels), a dispersion
    model (a YAML file whose ``kind`` says so). Usable as Tiled's mimetype detection hook."""
    path = Path(path)
    if path.is_dir():
        return SESSION if (path / "session.yaml").is_file() else mimetype
    suffix = path.suffix.lower()
    if suffix == ".exr":
        try:
            header = read_exr_header(path)
        except Exception:  # not an EXR labkit can read: leave it to Tiled
            return mimetype
        names = [channel.name for channel in header.get("channels", [])]
        if "raw" in names and "cfa" in header:
            return RAW_EXR
        if is_spectral_layout(header, names) or "wavelengths_nm" in header:
            return SPECTRAL_EXR
        return mimetype
    if suffix in (".yaml", ".yml"):
        with open(path, encoding="utf-8", errors="replace") as handle:
            head = [handle.readline().strip() for _ in range(8)]
        if f"kind: {MODEL_KIND}" in head:
            return DISPERSION_MODEL
    return mimetype
