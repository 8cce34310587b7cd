"""``labkit serve FOLDER``: a folder of labkit files served by Tiled."""

from __future__ import annotations

import argparse
from pathlib import Path

from labkit.cli._commands import Commands
from labkit.errors import ConfigError


def register(commands: Commands) -> None:
    """Add ``labkit serve``."""
    parser = commands.add_parser(
        "serve",
        description="Serve FOLDER's labkit files with Tiled, for the Tiled Python client, "
        "a browser or any HTTP client: capture sessions (each frame an array with its "
        "record), HDR raw EXRs and spectral EXRs (xarray datasets; spectral ones with their "
        "wavelengths in nm) and dispersion models (metadata), in FOLDER's layout. Needs "
        "`pip install 'labkit[tiled]'`. Connect with "
        "`tiled.client.from_uri(URL, api_key=KEY)`.",
    )
    parser.add_argument("folder", type=Path, help="the folder to serve")
    parser.add_argument(
        "--host", default="127.0.0.1", help="address to listen on (default: this machine only)"
    )
    parser.add_argument("--port", type=int, default=8000, help="port (default: 8000)")
    parser.add_argument(
        "--api-key",
        default=None,
        help="the key clients must give (default: anyone who reaches the port may read)",
    )
    parser.set_defaults(handler=_serve)


def _serve(args: argparse.Namespace) -> int:
    try:
        from labkit.tiled.server import serve
    except ImportError as error:
        raise ConfigError(
            f"labkit serve needs Tiled ({error}); install it with `pip install 'labkit[tiled]'`"
        ) from None
    if not 0 < args.port < 65536:
        raise ConfigError(f"--port {args.port} is not a port number (1–65535)")
    print(f"serving {args.folder} at http://{args.host}:{args.port} (Ctrl-C stops)")
    serve(args.folder, host=args.host, port=args.port, api_key=args.api_key)
    return 0
