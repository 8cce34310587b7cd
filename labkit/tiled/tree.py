"""A folder of labkit files as a Tiled tree, and a Tiled server for it.

:func:`labkit_tree` walks a folder (a lab's data folder: sessions, ``labkit hdr`` and
``labkit reconstruct`` outputs, dispersion models) and gives the Tiled tree of what labkit
recognises (:func:`labkit.tiled.detect_mimetype`), with the folders between as
containers; files it does not recognise are left out. ``labkit serve FOLDER`` serves it.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

from tiled.adapters.mapping import MapAdapter

from labkit.errors import ConfigError
from labkit.tiled.adapters import ADAPTERS_BY_MIMETYPE, detect_mimetype, nested_containers


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
        node = {folder.name or "data": node}  # the folder is one labkit file (a session)
    return nested_containers(node or {})


def _node(path: Path) -> Any:
    mimetype = detect_mimetype(path)
    if mimetype in ADAPTERS_BY_MIMETYPE:
        return functools.partial(ADAPTERS_BY_MIMETYPE[mimetype].from_uris, path.resolve().as_uri())
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
