"""Masks and label images read from PNG, TIFF and .npy (labkit.io.plane)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import tifffile
from PIL import Image

from labkit.cli.calibrate import read_mask
from labkit.errors import DataError
from labkit.io.plane import read_labels, read_plane


def _labels() -> np.ndarray:
    labels = np.zeros((12, 16), np.uint16)
    labels[2:6, 3:9], labels[7:11, 10:15] = 3, 300
    return labels


def test_every_format_gives_back_the_stored_pixels(tmp_path: Path) -> None:
    labels = _labels()
    np.save(tmp_path / "l.npy", labels)
    tifffile.imwrite(tmp_path / "l.tiff", labels)
    Image.fromarray(labels.astype(np.uint8) % 200).save(tmp_path / "l.png")
    np.testing.assert_array_equal(read_plane(tmp_path / "l.npy"), labels)
    np.testing.assert_array_equal(read_plane(tmp_path / "l.tiff"), labels)
    np.testing.assert_array_equal(read_plane(tmp_path / "l.png"), labels.astype(np.uint8) % 200)
    np.testing.assert_array_equal(read_labels(tmp_path / "l.tiff", (12, 16)), labels)


def test_a_colour_mask_counts_any_non_zero_channel(tmp_path: Path) -> None:
    rgb = np.zeros((8, 10, 3), np.uint8)
    rgb[1, 2, 0] = rgb[5, 7, 2] = 255
    Image.fromarray(rgb).save(tmp_path / "m.png")
    mask = read_mask(tmp_path / "m.png")
    assert mask.shape == (8, 10) and mask.sum() == 2 and mask[1, 2] and mask[5, 7]


def test_missing_unreadable_and_misshapen_files_are_named(tmp_path: Path) -> None:
    with pytest.raises(DataError, match=r"mask .*nothing\.png does not exist"):
        read_mask(tmp_path / "nothing.png")
    (tmp_path / "junk.png").write_text("not an image")
    with pytest.raises(DataError, match=r"--labels .*junk\.png: not a readable image"):
        read_labels(tmp_path / "junk.png", (12, 16))
    np.save(tmp_path / "small.npy", np.zeros((4, 4), np.int32))
    with pytest.raises(DataError, match=r"16×12 label image, got shape \(4, 4\)"):
        read_labels(tmp_path / "small.npy", (12, 16))
