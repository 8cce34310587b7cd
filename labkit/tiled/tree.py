"""A folder of labkit files as a Tiled tree, and a Tiled server for it.

:func:`labkit_tree` walks a folder (a lab's data folder: sessions, ``labkit hdr`` and
``labkit reconstruct`` outputs, dispersion models) and gives the Tiled tree of what labkit
recognises (:func:`labkit.tiled.detect_mimetype`), with the folders between as
containers; files it does not recognise are left out. ``labkit serve FOLDER`` serves it.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from tiled.adapters.mapping import MapAdapter

from labkit.errors import ConfigError
from labkit.tiled.adapters import ADAPTERS_BY_MIMETYPE, detect_mimetype


def labkit_tree(folder: str | Path) -> MapAdapter:
    """The Tiled tree of the labkit files under `folder`.

    Keys are file and folder names without their suffix (with it where two would clash).
    A session folder is one node (:class:`labkit.tiled.SessionAdapter`); the files are
    read when a client asks for them, the sessions' frames when their pixels are asked for.

    Raises
    ------
    ConfigError
        `folder` is not a folder.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ConfigError(f"{folder} is not a folder; serve the folder that holds your data")
    node = _node(folder)
    if node is not None and not isinstance(node, dict):
        return MapAdapter({folder.name or "data": node})
    return _containers(node or {})


def _node(path: Path) -> Any:
    mimetype = detect_mimetype(path)
    if mimetype in ADAPTERS_BY_MIMETYPE:
        return _Lazy(ADAPTERS_BY_MIMETYPE[mimetype], path)
    if not path.is_dir():
        return None
    children: dict[str, Any] = {}
    entries = sorted(p for p in path.iterdir() if not p.name.startswith("."))
    stems = [p.stem if p.is_file() else p.name for p in entries]
    for entry, stem in zip(entries, stems, strict=True):
        child = _node(entry)
        if child is None or child == {}:
            continue
        children[stem if stems.count(stem) == 1 else entry.name] = child
    return children


class _Lazy:
    """A file's adapter, built when first asked for."""

    def __init__(self, adapter_class: type, path: Path) -> None:
        self.adapter_class = adapter_class
        self.path = path


class _LazyMapping(Mapping[str, Any]):
    """Children built (and kept) when a client first asks for them."""

    def __init__(self, tree: dict[str, Any]) -> None:
        self._tree = tree
        self._built: dict[str, Any] = {}

    def __getitem__(self, key: str) -> Any:
        if key not in self._built:
            value = self._tree[key]
            self._built[key] = (
                _containers(value)
                if isinstance(value, dict)
                else value.adapter_class.from_uris(value.path.resolve().as_uri())
            )
        return self._built[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._tree)

    def __len__(self) -> int:
        return len(self._tree)


def _containers(tree: dict[str, Any]) -> MapAdapter:
    return MapAdapter(_LazyMapping(tree))
