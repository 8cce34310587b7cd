"""Single images given on the command line: masks and label images (PNG, TIFF, ``.npy``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from labkit.errors import DataError


def read_plane(path: str | Path, *, what: str = "image") -> np.ndarray:
    """The pixel array of a ``.npy``, TIFF or PIL-readable (PNG, …) file, as stored.

    Parameters
    ----------
    path : str or Path
    what : str
        How error messages name the file (e.g. ``"mask"``, ``"--labels"``).

    Raises
    ------
    DataError
        The file does not exist or cannot be read as an image.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{what} {path} does not exist")
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            return np.asarray(np.load(path))
        if suffix in (".tif", ".tiff"):
            import tifffile

            return np.asarray(tifffile.imread(path))
        from PIL import Image

        with Image.open(path) as image:
            return np.asarray(image)
    except Exception as error:
        raise DataError(f"{what} {path}: not a readable image ({error})") from None


def read_labels(path: str | Path, shape: tuple[int, int], *, what: str = "--labels") -> np.ndarray:
    """A patch label image (0 = background, 1, 2, … = patches) on a raw image's grid.

    Parameters
    ----------
    path : str or Path
        ``.npy``, TIFF or PNG (read by :func:`read_plane`).
    shape : (rows, cols)
        The raw image's size, px.
    what : str
        How error messages name the file.

    Returns
    -------
    ndarray (rows, cols) int32

    Raises
    ------
    DataError
        Missing or unreadable file, several channels, or another size.
    """
    labels = read_plane(path, what=what)
    if labels.ndim != 2 or labels.shape != tuple(shape):
        raise DataError(
            f"{what} {path}: expected a single-channel {shape[1]}×{shape[0]} label image, "
            f"got shape {labels.shape}"
        )
    return labels.astype(np.int32)
