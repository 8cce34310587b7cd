"""Reading the filtered-light images of an HDR folder (the output of ``labkit hdr``).

Layout: ``DIR/<scene>/<illumination>.exr`` (one :class:`~labkit.io.RawImage` each; values
are fractions of saturation at the image's reference exposure). The ``hdr.yaml`` index is
not needed: the images carry their own metadata. A folder that ``labkit hdr`` wrote is
checked against its run manifest first, so a damaged or mixed set is refused.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from labkit.errors import DataError
from labkit.io.exr import RawImage, read_raw_exr
from labkit.io.light import check_light
from labkit.io.output_folder import verify_output_folder
from labkit.session import SESSION_FILE

#: Provenance key under which the loader records the file an image was read from.
SOURCE_KEY = "source_file"


def source_of(image: RawImage) -> str:
    """The file an image was read from (or its illumination name if it was built in memory)."""
    return str(image.labkit.get(SOURCE_KEY, f"<{image.illumination}>"))


def load_filtered_hdr(
    folder: str | Path, *, scenes: Sequence[str] | None = None
) -> dict[str, list[RawImage]]:
    """Filtered-light HDR images of a folder, grouped by scene and sorted by wavelength.

    Parameters
    ----------
    folder : str or Path
        An HDR folder (``DIR/<scene>/<illumination>.exr``).
    scenes : sequence of str, optional
        Only these scenes (default: every scene with filtered images).

    Returns
    -------
    dict of str to list of RawImage
        Scene name → its filtered images (``wavelength_nm`` set); each image's
        provenance records the file it came from under ``"source_file"``. Unfiltered
        images are skipped.

    Raises
    ------
    DataError
        The folder is missing or holds no filtered images, a requested scene is absent,
        or the images of one scene disagree in shape or CFA layout.
    """
    root = _hdr_root(folder)
    grouped: dict[str, list[RawImage]] = {}
    for path in sorted(root.glob("*/*.exr")):
        image = read_raw_exr(path)
        if image.wavelength_nm is None:
            continue
        image.labkit[SOURCE_KEY] = str(path)
        scene = str(image.labkit.get("scene") or path.parent.name)
        grouped.setdefault(scene, []).append(image)
    if not grouped:
        raise DataError(
            f"HDR folder {root} holds no filtered-light images (DIR/<scene>/<illumination>.exr "
            "with a wavelength_nm attribute); merge a session with filtered illuminations "
            f"using `labkit hdr SESSION --out {root}`"
        )
    if scenes:
        missing = [name for name in scenes if name not in grouped]
        if missing:
            raise DataError(
                f"HDR folder {root} has no filtered images of scene(s) {missing}; "
                f"scenes with filtered images: {sorted(grouped)}"
            )
        grouped = {name: grouped[name] for name in scenes}
    for scene, images in grouped.items():
        for image in images:
            _check_light(image)
        check_consistent(images, what=f"scene {scene!r} in {root}")
        images.sort(key=lambda image: float(image.wavelength_nm))
    return grouped


def _check_light(image: RawImage, path: Path | None = None) -> None:
    """Refuse an HDR image that holds no usable light (:func:`labkit.io.light.check_light`)."""
    check_light(
        image.raw,
        name=f"HDR image {path or source_of(image)}",
        fix="merge its session again with `labkit hdr`, or re-take the capture",
    )


def _hdr_root(folder: str | Path) -> Path:
    """The HDR folder as a Path, checked against its run manifest if it has one (a folder
    assembled by hand has none), or a DataError saying how to create it."""
    root = Path(folder)
    if not root.is_dir():
        raise DataError(
            f"HDR folder {root} does not exist; create it with `labkit hdr SESSION --out {root}`"
        )
    if (root / SESSION_FILE).is_file():
        merged = root.parent / f"{root.name or 'session'}-hdr"
        raise DataError(
            f"{root} is a capture session, not an HDR folder; merge it first: "
            f"`labkit hdr {root} --out {merged}`, then give {merged}"
        )
    verify_output_folder(root, what="HDR folder", rerun=f"`labkit hdr SESSION … --out {root}`")
    return root


def check_consistent(images: Sequence[RawImage], *, what: str) -> None:
    """Raise DataError unless all `images` share one mosaic shape and CFA layout."""
    if not images:
        raise DataError(f"{what}: no images")
    first = images[0]
    for image in images[1:]:
        if image.raw.shape != first.raw.shape or image.cfa != first.cfa:
            raise DataError(
                f"{what}: {source_of(image)} is {image.raw.shape[1]}×{image.raw.shape[0]} "
                f"{image.cfa} but {source_of(first)} is "
                f"{first.raw.shape[1]}×{first.raw.shape[0]} {first.cfa}; all images of one "
                "scene must come from the same camera mode (re-run `labkit hdr` on one session)"
            )


def load_scene_hdr(folder: str | Path, scene: str) -> list[RawImage]:
    """Every HDR image (filtered and unfiltered) of one scene, filtered ones by wavelength.

    Raises
    ------
    DataError
        The folder or the scene is missing, or the images disagree in shape or CFA.
    """
    root = _hdr_root(folder)
    paths = sorted((root / scene).glob("*.exr"))
    if not paths:
        present = sorted(p.name for p in root.iterdir() if p.is_dir() and any(p.glob("*.exr")))
        raise DataError(f"HDR folder {root} has no images of scene {scene!r}; scenes: {present}")
    images = []
    for path in paths:
        image = read_raw_exr(path)
        _check_light(image, path)
        image.labkit[SOURCE_KEY] = str(path)
        images.append(image)
    check_consistent(images, what=f"scene {scene!r} in {root}")
    images.sort(key=lambda image: (image.wavelength_nm is not None, image.wavelength_nm or 0.0))
    return images
