"""Residual chromatic aberration at ColorChecker patch edges (thesis §4.4.3): hand-built
patches with known answers, and simulated charts rendered through lenses of growing
dispersion."""

from __future__ import annotations

import numpy as np
import pytest

from labkit.cfa import channel_index, mosaic
from labkit.errors import DataError
from labkit.io import demosaic_bilinear
from labkit.sim import Lens, SimulatedRig, colorchecker_chart, colorchecker_patch_boxes
from labkit.sim.render import render_irradiance
from reconstruction.evaluate.residual_aberration import patch_regions, residual_aberration

CFA = "GBRG"
#: Big enough for 12-px strips: the chart's 24 patches are 41 px wide (40 whole pixels),
#: leaving 16 × 16 px centres.
SHAPE = (256, 320)
FILL = 0.95
#: Lens reference ≈ the Green channel's centroid under the rig's lamp (535 nm): the patch
#: boxes (scene geometry) are where G's edges are, as the thesis marks contours on G.
REFERENCE_NM = 535.0
AMPLITUDES = (0.0, 1.0, 2.0, 4.0)


@pytest.fixture(scope="module")
def chart(small_sim_rig: SimulatedRig):
    """render(amplitude_px, vignetting) → (rgb peak 1, raw mosaic), cached; and the boxes."""
    scene = colorchecker_chart(SHAPE, fill=FILL)
    cache: dict[tuple[float, float], tuple[np.ndarray, np.ndarray]] = {}

    def render(amplitude: float, vignetting: float = 0.15) -> tuple[np.ndarray, np.ndarray]:
        key = (amplitude, vignetting)
        if key not in cache:
            lens = Lens(
                SHAPE, max_shift_px=amplitude, reference_nm=REFERENCE_NM, vignetting=vignetting
            )
            light = {"u": small_sim_rig.light("unfiltered")}
            rgb = render_irradiance(
                scene, lens, small_sim_rig.response, light, small_sim_rig.wavelengths, workers=2
            )["u"]
            rgb = rgb / rgb.max()
            cache[key] = (rgb, mosaic(rgb, CFA))
        return cache[key]

    return render, colorchecker_patch_boxes(scene)


# -- hand-built patches ------------------------------------------------------------------


def one_patch(shape=(40, 40), box=(10, 30)) -> np.ndarray:
    labels = np.zeros(shape, dtype=np.int32)
    labels[box[0] : box[1], box[0] : box[1]] = 1
    return labels


def test_known_fringe_in_the_outer_ring_gives_the_hand_computed_errors() -> None:
    """A 20 × 20 patch of colour (0.2, 0.5, 0.8), strip 4 px: the strip holds 20² − 12² =
    256 px, the centre 144. An error of +0.1 on R in the outermost ring (76 px) gives
    edge RMSE_R = √(76 · 0.01 / 256) and MRAE_R = 76 · (0.1 / 0.2) / 256."""
    labels = one_patch()
    colour = np.array([0.2, 0.5, 0.8])
    image = np.broadcast_to(colour, (40, 40, 3)).copy()
    image[labels == 0] = 0.05  # background: never evaluated
    raw = mosaic(image, CFA)
    ring = np.zeros((40, 40), bool)
    ring[10:30, 10:30] = True
    ring[11:29, 11:29] = False
    assert ring.sum() == 76
    estimate = image.copy()
    estimate[ring, 0] += 0.1
    result = residual_aberration(estimate, raw, cfa=CFA, labels=labels, strip_px=4)
    assert result.regions.edge.sum() == 256 and result.regions.centre.sum() == 144
    assert result.edge.n_pixels == (256, 256, 256)
    np.testing.assert_allclose(result.edge.rmse, [np.sqrt(76 * 0.01 / 256), 0, 0], atol=1e-12)
    np.testing.assert_allclose(result.edge.mrae, [76 * 0.5 / 256, 0, 0], atol=1e-12)
    np.testing.assert_allclose(result.centre.rmse, 0.0, atol=1e-12)
    np.testing.assert_allclose(result.patch_edge_rmse, [result.edge.rmse], atol=1e-12)
    np.testing.assert_allclose(result.ideal[labels == 1], np.tile(colour, (400, 1)), atol=1e-12)
    assert result.as_dict()["edge"]["rmse"]["R"] == pytest.approx(np.sqrt(76 * 0.01 / 256))

    # the same error in a raw mosaic, evaluated at the CFA sites: only R sites count
    raw_estimate = mosaic(estimate, CFA)
    on_sites = residual_aberration(raw_estimate, raw, cfa=CFA, labels=labels, strip_px=4)
    red_sites = channel_index(CFA, (40, 40)) == 0
    n_red = int((result.regions.edge & red_sites).sum())
    n_fringe = int((ring & red_sites).sum())
    assert on_sites.edge.n_pixels[0] == n_red == 64
    assert on_sites.edge.rmse[0] == pytest.approx(np.sqrt(n_fringe * 0.01 / n_red), rel=1e-12)
    np.testing.assert_allclose(on_sites.edge.rmse[1:], 0.0, atol=1e-12)


def test_linear_shading_is_extrapolated_from_the_centre_exactly() -> None:
    """Degree-1 shading fitted to the centre samples reproduces a planar shading in the
    strips (to rounding); degree 0 (the centre mean) cannot."""
    labels = one_patch((48, 56), (8, 40))
    yy, xx = np.mgrid[0:48, 0:56].astype(float)
    image = np.dstack([0.3 + 0.004 * xx, 0.6 - 0.003 * yy, 0.5 + 0.002 * (xx + yy)])
    raw = mosaic(image, CFA)
    planar = residual_aberration(image, raw, cfa=CFA, labels=labels, strip_px=6)
    np.testing.assert_allclose(planar.ideal[labels == 1], image[labels == 1], atol=1e-12)
    assert max(planar.edge.rmse) < 1e-12
    flat = residual_aberration(image, raw, cfa=CFA, labels=labels, strip_px=6, shading_degree=0)
    assert min(flat.edge.rmse) > 1e-3


def test_registration_ignores_a_per_channel_gain() -> None:
    labels = one_patch()
    image = np.broadcast_to([0.2, 0.5, 0.8], (40, 40, 3)).copy()
    raw = mosaic(image, CFA)
    estimate = image.copy()
    estimate[labels == 1] += 0.02 * np.sin(np.arange(400))[:, None]
    plain = residual_aberration(estimate, raw, cfa=CFA, labels=labels, strip_px=4)
    gains = np.array([3.0, 0.5, 2.0])
    registered = residual_aberration(
        estimate * gains, raw, cfa=CFA, labels=labels, strip_px=4, register=True
    )
    np.testing.assert_allclose(registered.edge.mrae, plain.edge.mrae, rtol=0.05)
    np.testing.assert_allclose(registered.edge.scale, 1 / gains, rtol=0.01)
    assert plain.edge.scale is None


# -- simulated ColorChecker -------------------------------------------------------------


def test_dispersion_free_render_measures_zero(chart) -> None:
    """The rendered colour image itself, dispersion-free: measured max edge MRAE 1e-8
    without vignetting (float32 rounding); 1.0e-3 with the rig's vignetting (0.15 at the
    corner; a plane per patch misses the cos⁴ curvature), 1.3e-5 with quadratic shading."""
    render, boxes = chart
    rgb, raw = render(0.0, vignetting=0.0)
    result = residual_aberration(rgb, raw, cfa=CFA, boxes=boxes)
    assert result.regions.edge.sum() == 24 * (40 * 40 - 16 * 16)
    assert max(result.edge.mrae) < 1e-6 and max(result.edge.rmse) < 1e-6
    assert max(result.centre.mrae) < 1e-6
    assert result.edge.mrae_excluded == (0, 0, 0)
    # the captured mosaic itself (the thesis' sanity check) is aberration-free too
    assert max(residual_aberration(raw, raw, cfa=CFA, boxes=boxes).edge.mrae) < 1e-6
    # labels marked by hand give the same answer as the boxes
    by_labels = residual_aberration(rgb, raw, cfa=CFA, labels=result.regions.labels)
    np.testing.assert_allclose(by_labels.edge.rmse, result.edge.rmse, atol=1e-15)

    rgb, raw = render(0.0, vignetting=0.15)
    planar = residual_aberration(rgb, raw, cfa=CFA, boxes=boxes)
    assert max(planar.edge.mrae) < 2e-3
    quadratic = residual_aberration(rgb, raw, cfa=CFA, boxes=boxes, shading_degree=2)
    assert max(quadratic.edge.mrae) < 5e-5


def test_residual_aberration_rises_with_dispersion(chart) -> None:
    """Bilinear demosaics of charts rendered with corner dispersion 0, 1, 2, 4 px. Measured
    edge MRAE (mean of R, G, B): 0.0091, 0.0092, 0.0098, 0.0136; edge RMSE (peak 1):
    0.0121, 0.0126, 0.0134, 0.0168; Blue edge RMSE 0.0141, 0.0157, 0.0177, 0.0252. The
    dispersion-free value is bilinear demosaicing's own error at edges. Centre MRAE stays
    below 1e-4: the centres are fringe-free. (Red alone is not monotonic at small
    amplitudes: a sub-pixel shift can offset bilinear interpolation's edge bias.)"""
    render, boxes = chart
    mrae, rmse, blue = [], [], []
    for amplitude in AMPLITUDES:
        _, raw = render(amplitude)
        result = residual_aberration(demosaic_bilinear(raw, CFA), raw, cfa=CFA, boxes=boxes)
        mrae.append(np.mean(result.edge.mrae))
        rmse.append(np.mean(result.edge.rmse))
        blue.append(result.edge.rmse[2])
        assert max(result.centre.mrae) < 1e-3
        assert min(result.edge.mrae) > 3 * max(result.centre.mrae)
    for series in (mrae, rmse, blue):
        assert np.all(np.diff(series) > 0), series
    assert mrae[-1] > 1.4 * mrae[0]


# -- invalid input ----------------------------------------------------------------------


def test_invalid_geometry_and_inputs_are_refused() -> None:
    labels = one_patch()
    raw = np.ones((40, 40))
    rgb = np.ones((40, 40, 3))
    with pytest.raises(DataError, match="exactly one of boxes"):
        residual_aberration(rgb, raw, cfa=CFA)
    with pytest.raises(DataError, match="exactly one of boxes"):
        residual_aberration(rgb, raw, cfa=CFA, labels=labels, boxes=np.zeros((1, 4)))
    with pytest.raises(DataError, match=r"patch\(es\) \[1\] have no centre"):
        residual_aberration(rgb, raw, cfa=CFA, labels=labels, strip_px=10)
    with pytest.raises(DataError, match="estimate has shape"):
        residual_aberration(np.ones((40, 41, 3)), raw, cfa=CFA, labels=labels, strip_px=4)
    with pytest.raises(DataError, match="integer image of shape"):
        residual_aberration(rgb, raw, cfa=CFA, labels=labels[:-1], strip_px=4)
    bad = rgb.copy()
    bad[3, 3, 1] = np.inf
    with pytest.raises(DataError, match="NaN or Inf"):
        residual_aberration(bad, raw, cfa=CFA, labels=labels, strip_px=4)
    with pytest.raises(DataError, match="shading_degree"):
        residual_aberration(rgb, raw, cfa=CFA, labels=labels, strip_px=4, shading_degree=5)
    with pytest.raises(DataError, match="too few centre samples"):
        residual_aberration(rgb, raw, cfa=CFA, labels=one_patch(box=(10, 19)), strip_px=3,
                            shading_degree=3)  # fmt: skip
    with pytest.raises(DataError, match="unknown CFA layout"):
        residual_aberration(rgb, raw, cfa="RGBG", labels=labels, strip_px=4)
    with pytest.raises(DataError, match="overlaps box 0"):
        patch_regions((40, 40), boxes=[[5, 5, 20, 20], [15, 15, 30, 30]])
    with pytest.raises(DataError, match="no whole pixel"):
        patch_regions((40, 40), boxes=[[5, 5, 5.8, 20]])
    with pytest.raises(DataError, match="no edge"):
        patch_regions((40, 40), labels=np.ones((40, 40), np.int32))


def test_boxes_keep_only_whole_pixels() -> None:
    """Box edges at x = 2.3 … 7.5: pixel 3's box [2.5, 3.5] is the first inside, pixel 7's
    [6.5, 7.5] the last; rows 1.5 … 9.0 keep rows 2 … 8."""
    regions = patch_regions((12, 12), boxes=[[2.3, 1.5, 7.5, 9.0]], strip_px=2)
    rows, cols = np.nonzero(regions.labels)
    assert (cols.min(), cols.max(), rows.min(), rows.max()) == (3, 7, 2, 8)
    assert regions.depth[5, 5] == 3.0 and regions.depth[2, 5] == 1.0
