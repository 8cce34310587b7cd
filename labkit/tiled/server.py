"""A Tiled server for a folder of labkit files, on this machine: :func:`serving` runs it
on a background thread (scripts, notebooks, tests), :func:`serve` in the foreground
(``labkit serve``)."""

from __future__ import annotations

import secrets
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import uvicorn
from tiled.config import Authentication
from tiled.server.app import build_app
from tiled.server.simple import ThreadedServer

from labkit.tiled.tree import labkit_tree


def tiled_app(folder: str | Path, *, api_key: str | None = None) -> Any:
    """The Tiled web application serving `folder`'s labkit files; with `api_key`, clients
    must give it, else anyone who reaches the port may read."""
    authentication = (
        Authentication(single_user_api_key=api_key)
        if api_key
        else Authentication(allow_anonymous_access=True)
    )
    return build_app(labkit_tree(folder), authentication=authentication)


@contextmanager
def serving(
    folder: str | Path, *, host: str = "127.0.0.1", port: int = 0, api_key: str | None = None
) -> Iterator[tuple[str, str]]:
    """Serve `folder` on a background thread while the ``with`` block runs; yields the
    server's URI and its API key (one is made when `api_key` is not given)."""
    api_key = api_key or secrets.token_hex(16)
    config = uvicorn.Config(
        tiled_app(folder, api_key=api_key), host=host, port=port, log_level="warning"
    )
    with ThreadedServer(config).run_in_thread() as uri:
        yield uri, api_key


def serve(
    folder: str | Path, *, host: str = "127.0.0.1", port: int = 8000, api_key: str | None = None
) -> None:
    """Serve `folder` until interrupted (Ctrl-C)."""
    uvicorn.run(tiled_app(folder, api_key=api_key), host=host, port=port, log_level="info")
