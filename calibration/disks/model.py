"""The disk model of :mod:`calibration.disks`: an ellipse with a linear edge, integrated over
each pixel's unit square, under a local illumination gradient; its residuals and Jacobian.
"""

from __future__ import annotations

import numpy as np

#: Parameters of the disk model before the lightnesses (the geometry: centre offset, quadratic
#: form, edge ramp and illumination gradient).
N_GEOMETRY = 8


#: Sign patterns of the 8 corner terms of the CDF of a sum of three uniforms.
_SIGNS = np.array([[e1, e2, e3] for e1 in (1.0, -1.0) for e2 in (1.0, -1.0) for e3 in (1.0, -1.0)])
_PARITY = _SIGNS.prod(axis=1)
#: Σ σ z³ and Σ σ z², Σ σ ε_i z² as matrix products with the (n, 8) corner terms.
_CUBE_WEIGHTS = _PARITY / 6.0
_SQUARE_WEIGHTS = np.column_stack(
    [_PARITY / 2.0, *(_PARITY * _SIGNS[:, i] / 4.0 for i in range(3))]
)
#: Smallest footprint widths (px): keeps the CDF formula well conditioned.
_MIN_FOOTPRINT = 0.02
#: Least width of the model's edge ramp, px: w = √(MIN_EDGE_WIDTH_PX² + max(v, 0)).
MIN_EDGE_WIDTH_PX = 0.02


class DiskModel:
    """Synthetic disk integrated over pixel areas, with an analytic Jacobian.

    Parameters (vector p): ux, uy (centre offset from the initial centre, px), qa, qb, qc
    (quadratic form of the ellipse times r0², so ≈ 1 for a circle of radius r0), v
    (edge ramp width w = √(0.02² + max(v, 0)), px — parametrised by its square, which
    converges in a few steps where the ramp is sharper than the pixel footprint), gx, gy
    (illumination gradient per r0), then the interior and the exterior lightness of each
    of the `m` lightness groups.

    Across the edge, at signed distance s, the scene falls linearly from exterior to
    interior over the width w (the thesis' linear edge). A pixel integrates the scene
    over its unit square; for a locally straight edge with unit normal (nx, ny) that is
    a convolution with uniform kernels of widths ``|nx|`` and ``|ny|``, so the fraction of
    the pixel inside the disk is 1 − F(s), with F the CDF of the sum of three centred
    uniform variables of widths ``|nx|``, ``|ny|`` and w (a piecewise cubic in s). The
    radial direction stands in for the normal (they agree for circles).

    The pixels are given by their positions `x`, `y` (n,) relative to the initial centre,
    px, and their lightness groups `group` (n,) in 0…m−1; `r0` is the initial mean radius,
    px, and `weight` (n,), if given, multiplies the model (and the Jacobian).
    """

    def __init__(
        self,
        x: np.ndarray,
        y: np.ndarray,
        group: np.ndarray,
        m: int,
        r0: float,
        weight: np.ndarray | None = None,
    ) -> None:
        self.x = x
        self.y = y
        self.group = group
        self.m = m
        self.r0 = r0
        self.inv_r02 = 1.0 / (r0 * r0)
        self.onehot = (group[:, None] == np.arange(m)[None, :]).astype(np.float64)
        self.xr = x / r0
        self.yr = y / r0
        self.weight = weight
        self._p: np.ndarray | None = None

    def _evaluate(self, p: np.ndarray) -> None:
        if self._p is not None and np.array_equal(p, self._p):
            return
        m = self.m
        ux, uy, qa, qb, qc, w2, gx, gy = p[:N_GEOMETRY]
        inner = p[N_GEOMETRY : N_GEOMETRY + m]
        outer = p[N_GEOMETRY + m :]
        dx = self.x - ux
        dy = self.y - uy
        r = np.maximum(np.hypot(dx, dy), 1e-9)
        ex = dx / r
        ey = dy / r
        qx = (qa * ex + qb * ey) * self.inv_r02  # Q ĉ, 1/px²
        qy = (qb * ex + qc * ey) * self.inv_r02
        big_r = 1.0 / np.sqrt(np.maximum(ex * qx + ey * qy, 1e-12))  # radius along ĉ, px
        s = r - big_r
        a1 = np.maximum(np.abs(ex), _MIN_FOOTPRINT)
        a2 = np.maximum(np.abs(ey), _MIN_FOOTPRINT)
        w = float(np.sqrt(MIN_EDGE_WIDTH_PX**2 + max(w2, 0.0)))
        half = 0.5 * (a1 + a2 + w)
        band = np.abs(s) < half
        z = s[:, None] + 0.5 * (a1[:, None] * _SIGNS[:, 0] + a2[:, None] * _SIGNS[:, 1])
        z += 0.5 * w * _SIGNS[:, 2]
        np.maximum(z, 0.0, out=z)
        z2 = z * z
        inv = 1.0 / (a1 * a2 * w)
        cdf = np.where(band, (z2 * z) @ _CUBE_WEIGHTS * inv, (s > 0).astype(np.float64))
        h = 1.0 - np.clip(cdf, 0.0, 1.0)
        if m == 1:
            i_px = np.full(r.size, inner[0])
            e_px = np.full(r.size, outer[0])
        else:
            i_px = inner[self.group]
            e_px = outer[self.group]
        contrast = i_px - e_px
        base = e_px + contrast * h
        gain = 1.0 + gx * self.xr + gy * self.yr
        self._p = p.copy()
        self._cache = (r, ex, ey, qx, qy, big_r, a1, a2, w, band, z2, inv, cdf, h, contrast, base)
        self._gain = gain
        model = gain * base
        self.model = model if self.weight is None else model * self.weight

    def residuals(self, p: np.ndarray, values: np.ndarray) -> np.ndarray:
        """The model at parameters `p` (times the pixel weights, if any) minus `values` (n,)."""
        self._evaluate(p)
        return self.model - values

    def jacobian(self, p: np.ndarray, values: np.ndarray) -> np.ndarray:
        """The Jacobian (n, N_GEOMETRY + 2 m) of :meth:`residuals` at parameters `p`."""
        self._evaluate(p)
        r, ex, ey, qx, qy, big_r, a1, a2, w, band, z2, inv, cdf, h, contrast, base = self._cache
        gain = self._gain
        jac = np.empty((r.size, N_GEOMETRY + 2 * self.m))
        sums = (z2 @ _SQUARE_WEIGHTS) * inv[:, None]  # ∂F/∂s and Σ σ ε_i z² / (4 a1 a2 w)
        # f = gain (e + contrast (1 − F)); dF/d(param) enters with −gain·contrast
        df = np.where(band, -gain * contrast, 0.0)
        df_ds = df * sums[:, 0]
        df_da1 = np.where(np.abs(ex) > _MIN_FOOTPRINT, df * (sums[:, 1] - cdf / a1), 0.0)
        df_da2 = np.where(np.abs(ey) > _MIN_FOOTPRINT, df * (sums[:, 2] - cdf / a2), 0.0)
        df_dw = df * (sums[:, 3] - cdf / w)
        r3 = big_r**3
        # ∇_d s = ĉ − (R ĉ − R³ Q ĉ) / r ; moving the centre by +u moves d by −u
        grad_x = ex - (big_r * ex - r3 * qx) / r
        grad_y = ey - (big_r * ey - r3 * qy) / r
        # footprints |ex|, |ey| of the radial direction ĉ = d / r
        sx = np.sign(ex) * df_da1 / r
        sy = np.sign(ey) * df_da2 / r
        exy = ex * ey
        jac[:, 0] = -df_ds * grad_x - sx * ey * ey + sy * exy
        jac[:, 1] = -df_ds * grad_y + sx * exy - sy * ex * ex
        half = 0.5 * r3 * self.inv_r02 * df_ds
        jac[:, 2] = half * ex * ex
        jac[:, 3] = 2.0 * half * exy
        jac[:, 4] = half * ey * ey
        jac[:, 5] = df_dw * (0.5 / w) if p[5] > 0 else 0.0
        jac[:, 6] = base * self.xr
        jac[:, 7] = base * self.yr
        m = self.m
        jac[:, N_GEOMETRY : N_GEOMETRY + m] = (gain * h)[:, None] * self.onehot
        jac[:, N_GEOMETRY + m :] = (gain * (1.0 - h))[:, None] * self.onehot
        if self.weight is not None:
            jac *= self.weight[:, None]
        return jac
