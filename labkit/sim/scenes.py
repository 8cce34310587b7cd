"""Scenes as spectral reflectance fields with exact pixel-area coverage.

A scene is a set of materials (reflectance spectra) and a geometry that says, for the
unit pixel box centred at any real position (x, y), which materials cover it and with
what area fractions (:meth:`Scene.mixture`). Geometry is analytic, so a box can be
evaluated at any sub-pixel position — the renderer uses this to apply the lens'
dispersion without resampling a raster:

* :class:`CellGrid` — a grid of square cells (side ≥ 1 px), one material each; the box
  overlaps at most 2×2 cells and the overlap areas are exact.
* :class:`DiskGrid` — a regular lattice of disks painted over the grid; the covered area
  is exact along y and integrated by 12-point Gauss–Legendre quadrature along x (i.e.
  better than 12× supersampling), only for boxes that straddle a disk edge.

The thesis' scenes (§4.2): the black-disk calibration pattern, a ColorChecker chart in
its frame, and a textured scene (binary noise, text-like strokes, saturated colours);
and beyond the thesis a natural-like scene (dead leaves of smooth, mostly unsaturated
reflectances) for validation on image statistics closer to the field's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from labkit.errors import ConfigError
from labkit.spectra import COLORCHECKER_PATCHES, Spectra, colorchecker_reflectances, lab_spectra

_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(12)


@dataclass(frozen=True)
class CellGrid:
    """Square cells of side `cell_px` starting at `origin` (x, y); `labels[row, col]`.

    Positions outside the grid show material `outside`.
    """

    labels: np.ndarray
    cell_px: float
    origin: tuple[float, float] = (-0.5, -0.5)
    outside: int = 0

    def __post_init__(self) -> None:
        if self.cell_px < 1.0:
            raise ConfigError(f"cell size must be ≥ 1 px, got {self.cell_px}")
        padded = np.pad(np.asarray(self.labels, dtype=np.int32), 1, constant_values=self.outside)
        object.__setattr__(self, "_padded", padded)

    def mixture(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Labels and area weights (N, 4) of the unit boxes centred at (x, y)."""
        col, wcol = self._axis(x, self.origin[0], self._padded.shape[1])
        row, wrow = self._axis(y, self.origin[1], self._padded.shape[0])
        grid = self._padded
        labels = np.stack(
            [grid[row, col], grid[row, col + 1], grid[row + 1, col], grid[row + 1, col + 1]], axis=1
        )
        weights = np.stack(
            [wrow * wcol, wrow * (1 - wcol), (1 - wrow) * wcol, (1 - wrow) * (1 - wcol)], axis=1
        )
        return labels, weights.astype(np.float32)

    def _axis(
        self, t: np.ndarray, origin: float, padded_size: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """First overlapped (padded) cell index and the box's area fraction inside it."""
        start = (np.asarray(t, dtype=np.float64) - 0.5 - origin) / self.cell_px
        first = np.floor(start)
        # fraction of the unit box before the next cell boundary
        weight = np.minimum((first + 1.0 - start) * self.cell_px, 1.0)
        index = first.astype(np.int64) + 1  # +1: the padding border
        # beyond the grid both overlapped cells are `outside`: put all weight on a border cell
        before, after = index < 0, index > padded_size - 2
        weight[before] = 1.0
        weight[after] = 0.0
        return np.clip(index, 0, padded_size - 2), weight


@dataclass(frozen=True)
class DiskGrid:
    """`count` = (nx, ny) disks of radius `radius_px` on a lattice of pitch `pitch_px`.

    The first disk is centred at `first_centre` (x, y), px.
    """

    radius_px: float
    pitch_px: float
    first_centre: tuple[float, float]
    count: tuple[int, int]
    material: int

    def __post_init__(self) -> None:
        if not 0 < 2 * self.radius_px + 2 < self.pitch_px:
            raise ConfigError(
                f"disk radius {self.radius_px} px does not fit pitch {self.pitch_px} px; "
                "use pitch > 2 × radius + 2"
            )

    def centres(self) -> np.ndarray:
        """All disk centres (n, 2) as (x, y), px."""
        ix, iy = np.meshgrid(np.arange(self.count[0]), np.arange(self.count[1]))
        x = self.first_centre[0] + self.pitch_px * ix.ravel()
        y = self.first_centre[1] + self.pitch_px * iy.ravel()
        return np.column_stack([x, y])

    def coverage(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Area fraction of the unit box centred at (x, y) covered by a disk."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        ix = np.clip(np.rint((x - self.first_centre[0]) / self.pitch_px), 0, self.count[0] - 1)
        iy = np.clip(np.rint((y - self.first_centre[1]) / self.pitch_px), 0, self.count[1] - 1)
        dx = x - (self.first_centre[0] + self.pitch_px * ix)
        dy = y - (self.first_centre[1] + self.pitch_px * iy)
        dist = np.hypot(dx, dy)
        radius = self.radius_px
        cover = (dist <= radius - 0.7072).astype(np.float32)
        edge = np.flatnonzero(np.abs(dist - radius) < 0.7072)
        if edge.size:
            cover[edge] = _disk_box_overlap(dx[edge], dy[edge], radius)
        return cover


def _disk_box_overlap(dx: np.ndarray, dy: np.ndarray, radius: float) -> np.ndarray:
    """Area of a disk (centre 0, `radius`) inside unit boxes centred at (dx, dy)."""
    xs = dx[:, None] + 0.5 * _GL_NODES[None, :]
    half_chord = np.sqrt(np.maximum(radius * radius - xs * xs, 0.0))
    top = np.minimum(half_chord, dy[:, None] + 0.5)
    bottom = np.maximum(-half_chord, dy[:, None] - 0.5)
    inside = np.clip(top - bottom, 0.0, 1.0)
    return (inside @ (0.5 * _GL_WEIGHTS)).astype(np.float32)


@dataclass(frozen=True)
class Scene:
    """Materials (reflectance spectra) and their geometry.

    Attributes
    ----------
    name : str
        Scene name, e.g. ``"disks"``.
    materials : Spectra
        One reflectance spectrum per material (0–1 relative to a white standard).
    grid : CellGrid
        The base layer.
    disks : DiskGrid or None
        Disks painted over the base layer.
    """

    name: str
    materials: Spectra
    grid: CellGrid
    disks: DiskGrid | None = None

    @property
    def n_materials(self) -> int:
        """Number of materials."""
        return len(self.materials.labels)

    def mixture(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Materials and exact area fractions (N, m) of unit pixel boxes centred at (x, y).

        Weights of each row sum to 1 (flat fields render flat).
        """
        labels, weights = self.grid.mixture(x, y)
        if self.disks is None:
            return labels, weights
        cover = self.disks.coverage(x, y)[:, None]
        disk_labels = np.full((labels.shape[0], 1), self.disks.material, dtype=labels.dtype)
        return (
            np.concatenate([labels, disk_labels], axis=1),
            np.concatenate([weights * (1.0 - cover), cover], axis=1),
        )

    def coverage_image(self, shape: tuple[int, int]) -> np.ndarray:
        """Area fraction of every material in every pixel, (rows, cols, n_materials)."""
        rows, cols = shape
        yy, xx = np.mgrid[0:rows, 0:cols]
        labels, weights = self.mixture(xx.ravel().astype(float), yy.ravel().astype(float))
        flat = np.zeros((rows * cols, self.n_materials), dtype=np.float32)
        np.add.at(flat, (np.arange(rows * cols)[:, None], labels), weights)
        return flat.reshape(rows, cols, self.n_materials)


# -- the thesis' scenes -------------------------------------------------------------------


def flat_field(shape: tuple[int, int], *, reflectance: float = 1.0) -> Scene:
    """A uniform grey surface of constant `reflectance` covering the whole view."""
    w = np.array([300.0, 1100.0])
    materials = Spectra(w, np.full((2, 1), reflectance), ("flat",))
    return Scene("flat", materials, CellGrid(np.zeros((1, 1), int), max(shape) + 2.0))


def disk_pattern(
    shape: tuple[int, int],
    *,
    radius_px: float = 14.0,
    pitch_px: float = 64.0,
    margin_px: float | None = None,
    paper: str = "Printer paper (white)",
    ink: str = "Printer paper (toner)",
    offset_px: tuple[float, float] = (0.0, 0.0),
) -> Scene:
    """Black disks on white paper in a square lattice (thesis §3.2.1, §4.2.1).

    Disks fill the view leaving `margin_px` (default half a pitch) at the borders;
    `offset_px` shifts the lattice by a sub-pixel amount so centres need not sit on
    pixel centres.
    """
    rows, cols = shape
    if margin_px is None:
        margin_px = pitch_px / 2
    nx = int((cols - 2 * margin_px - 2 * radius_px) // pitch_px) + 1
    ny = int((rows - 2 * margin_px - 2 * radius_px) // pitch_px) + 1
    if nx < 1 or ny < 1:
        raise ConfigError(
            f"no disk of radius {radius_px} px fits a {cols}×{rows} view with margin "
            f"{margin_px} px; reduce radius_px or margin_px"
        )
    span_x = (nx - 1) * pitch_px
    span_y = (ny - 1) * pitch_px
    first = ((cols - 1 - span_x) / 2 + offset_px[0], (rows - 1 - span_y) / 2 + offset_px[1])
    materials = lab_spectra().select([paper, ink])
    return Scene(
        "disks",
        materials,
        CellGrid(np.zeros((1, 1), int), max(shape) + 2.0),
        DiskGrid(radius_px, pitch_px, first, (nx, ny), material=1),
    )


def colorchecker_chart(
    shape: tuple[int, int],
    *,
    reflectances: str = "measured",
    fill: float = 0.8,
    wall: str = "Large chequerboard (white)",
    frame: str = "Printer paper (toner)",
) -> Scene:
    """A 6×4 ColorChecker in its black frame, filling `fill` of the view's width or height.

    Patches are 5 cells wide with 1-cell gaps of frame, plus a 1-cell frame border: the
    chart is 37 × 25 cells. The chart stands in front of a white wall. Patch geometry is
    available from :func:`colorchecker_patch_boxes` for evaluation.
    """
    rows, cols = shape
    cell = min(fill * cols / 37.0, fill * rows / 25.0)
    if cell < 1.0:
        raise ConfigError(f"a {cols}×{rows} view is too small for a ColorChecker chart")
    chart = colorchecker_reflectances(reflectances)
    wall_frame = (
        lab_spectra().select([wall, frame]).resample(chart.wavelengths, extrapolate="constant")
    )
    materials = Spectra(
        chart.wavelengths,
        np.column_stack([wall_frame.values, chart.values]),
        ("wall", "frame", *COLORCHECKER_PATCHES),
    )
    labels = np.ones((25, 37), dtype=np.int32)  # frame
    for index in range(24):
        r, c = divmod(index, 6)
        labels[1 + 6 * r : 6 + 6 * r, 1 + 6 * c : 6 + 6 * c] = 2 + index
    origin = ((cols - 1) / 2 - 18.5 * cell, (rows - 1) / 2 - 12.5 * cell)
    return Scene("colorchecker", materials, CellGrid(labels, cell, origin, outside=0))


def colorchecker_patch_boxes(scene: Scene) -> np.ndarray:
    """Patch rectangles (24, 4) as (x0, y0, x1, y1) edges, px, in chart order."""
    grid = scene.grid
    ox, oy = grid.origin
    boxes = []
    for index in range(24):
        r, c = divmod(index, 6)
        x0, y0 = ox + (1 + 6 * c) * grid.cell_px, oy + (1 + 6 * r) * grid.cell_px
        boxes.append((x0, y0, x0 + 5 * grid.cell_px, y0 + 5 * grid.cell_px))
    return np.array(boxes)


def textured_scene(
    shape: tuple[int, int],
    *,
    seed: int = 0,
    noise_cell_px: float = 6.0,
    stroke_px: float = 2.0,
) -> Scene:
    """Binary noise, text-like strokes and saturated colour blocks (thesis §4.2.2).

    The view is split into three vertical bands: left, white/black binary noise in
    `noise_cell_px` cells; middle, black text-like glyph strokes `stroke_px` wide on
    white paper; right, blocks of the chart's saturated colours with noise between.
    """
    rng = np.random.default_rng(seed)
    rows, cols = shape
    cell = stroke_px
    grid_rows, grid_cols = int(np.ceil(rows / cell)) + 2, int(np.ceil(cols / cell)) + 2
    labels = np.zeros((grid_rows, grid_cols), dtype=np.int32)  # white paper
    third = grid_cols // 3
    block = max(1, round(noise_cell_px / cell))
    coarse = rng.integers(0, 2, size=(grid_rows // block + 1, grid_cols // block + 1))
    noise = np.kron(coarse, np.ones((block, block), dtype=np.int32))[:grid_rows, :grid_cols]
    labels[:, :third] = noise[:, :third]
    # text-like glyphs: 5×7 stroke patterns on a character grid
    glyph_w, glyph_h = 6, 9
    for top in range(1, grid_rows - glyph_h, glyph_h + 2):
        for left in range(third + 1, 2 * third - glyph_w, glyph_w + 1):
            glyph = rng.random((7, 5)) < 0.45
            glyph[:, rng.integers(0, 5)] = True  # a vertical stem, as in most letters
            labels[top : top + 7, left : left + 5][glyph] = 1
    colours = ("red", "green", "blue", "yellow", "magenta", "cyan", "orange", "purplish blue")
    labels[:, 2 * third :] = noise[:, 2 * third :]
    step = max(grid_rows // 4, 2)
    bw = max((grid_cols - 2 * third) // 3, 2)
    for k, _name in enumerate(colours):
        r0 = (k % 4) * step + step // 6
        c0 = 2 * third + (k // 4) * (bw + bw // 2) + bw // 6
        labels[r0 : r0 + (2 * step) // 3, c0 : c0 + bw] = 2 + k
    paper = lab_spectra().select(["Printer paper (white)", "Printer paper (toner)", *colours])
    materials = Spectra(paper.wavelengths, paper.values, ("paper", "ink", *colours))
    return Scene("texture", materials, CellGrid(labels, cell, origin=(-0.5 - cell, -0.5 - cell)))


DEAD_LEAVES_COVER = 6.0
"""How many times over the dead-leaves scene's disks cover the view on average (the cells
none reaches take their nearest disk's material)."""


def natural_scene(
    shape: tuple[int, int],
    *,
    seed: int = 0,
    smallest_px: float = 1.5,
    materials: int = 24,
) -> Scene:
    """A natural-like scene: dead leaves of natural-like reflectances.

    Occluding disks (each in front of those drawn after it) whose radii follow the
    scale-invariant density r⁻³ between `smallest_px` and a quarter of the view's smaller
    side — the dead-leaves model, whose edges and power spectrum are those of natural
    images. Each disk takes one of `materials` reflectances, each a random convex mixture
    of three ColorChecker patches (Dirichlet weights), so that the spectra are smooth and
    mostly unsaturated, as natural surfaces are. Geometry on a 1 px cell grid.
    """
    rng = np.random.default_rng(seed)
    rows, cols = shape
    largest = max(min(rows, cols) / 4.0, smallest_px)
    grid_rows, grid_cols = rows + 2, cols + 2
    labels = np.full((grid_rows, grid_cols), -1, dtype=np.int32)
    yy, xx = np.arange(grid_rows), np.arange(grid_cols)
    # enough disks to cover the view about DEAD_LEAVES_COVER times over (mean disk area
    # under the r⁻³ density: 2π r_min² ln(r_max / r_min) / (1 − (r_min / r_max)²))
    ratio = smallest_px / largest
    mean_area = 2 * np.pi * smallest_px**2 * np.log(1 / ratio) / max(1 - ratio**2, 1e-12)
    count = int(DEAD_LEAVES_COVER * grid_rows * grid_cols / max(mean_area, 1.0)) + 1
    radii = (smallest_px**-2 - rng.random(count) * (smallest_px**-2 - largest**-2)) ** -0.5
    centres_y = rng.uniform(-radii, grid_rows + radii)
    centres_x = rng.uniform(-radii, grid_cols + radii)
    leaves = rng.integers(materials, size=count)
    for radius, cy, cx, leaf in zip(radii, centres_y, centres_x, leaves, strict=True):
        r0, r1 = max(0, int(cy - radius)), min(grid_rows, int(cy + radius) + 2)
        c0, c1 = max(0, int(cx - radius)), min(grid_cols, int(cx + radius) + 2)
        if r0 >= r1 or c0 >= c1:
            continue
        inside = (yy[r0:r1, None] - cy) ** 2 + (xx[None, c0:c1] - cx) ** 2 <= radius**2
        window = labels[r0:r1, c0:c1]
        window[inside & (window < 0)] = leaf  # earlier disks stay in front
    if (labels < 0).any():  # the few cells no disk reached: their nearest leaf's
        import scipy.ndimage

        nearest = scipy.ndimage.distance_transform_edt(
            labels < 0, return_distances=False, return_indices=True
        )
        labels = labels[tuple(nearest)]
    chart = colorchecker_reflectances("measured")
    picks = np.stack(
        [rng.choice(chart.values.shape[1], 3, replace=False) for _ in range(materials)]
    )
    mixing = rng.dirichlet(np.ones(3), size=materials)
    values = np.einsum("wmk,mk->wm", chart.values[:, picks], mixing)
    spectra = Spectra(chart.wavelengths, values, tuple(f"leaf {k}" for k in range(materials)))
    return Scene("natural", spectra, CellGrid(labels, 1.0, origin=(-1.5, -1.5)))


SCENES = {
    "disks": disk_pattern,
    "colorchecker": colorchecker_chart,
    "texture": textured_scene,
    "natural": natural_scene,
}
