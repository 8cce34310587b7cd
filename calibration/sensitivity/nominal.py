"""The channel sensitivities a rig's camera response predicts (thesis Figure 4.12, dotted)."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from calibration.sensitivity.table import ChannelSensitivity, load_response
from labkit.errors import ConfigError
from labkit.spectra import (
    illuminant,
    trapezoid_weights,
    wavelength_grid,
)


def nominal_channel_sensitivity(
    rig, illuminations: Iterable[str] | None = None
) -> ChannelSensitivity:
    """R/G and B/G that a rig's camera response predicts for its filter bands.

    ``ratio_c = ∫ q_c T L dλ / ∫ q_G T L dλ`` over 380–780 nm (trapezoid rule on a
    1 nm grid, or the simulator's grid if finer), with camera response q (zero outside
    its data), filter transmission T and light source L. For a simulated rig this is
    what a spectrally flat (grey) scene gives.

    Parameters
    ----------
    rig : labkit.rig.Rig
        The rig (camera response, slider filters, light source).
    illuminations : iterable of str, optional
        Filtered illuminations to predict (default: every filtered slider position).

    Returns
    -------
    ChannelSensitivity
        ``source = "nominal"``, 0 pairs, unknown residuals; a band where the Green
        integral vanishes is NaN and unreliable.

    Raises
    ------
    ConfigError
        An illumination is unknown or unfiltered.
    """
    names = list(rig.slider.illumination_names() if illuminations is None else illuminations)
    filters = {}
    for name in names:
        filt = rig.filter_for(name)
        if filt is not None:
            filters[name] = filt
        elif illuminations is not None:
            raise ConfigError(
                f"rig {rig.source or rig.name}: illumination {name!r} has no filter, so it "
                "has no channel sensitivity; name a filtered slider position"
            )
    if not filters:
        raise ConfigError(f"rig {rig.source or rig.name} has no filtered slider position")
    step = 1.0 if rig.sim is None else min(1.0, float(rig.sim.spectral_step_nm))
    w = wavelength_grid(380.0, 780.0, step)
    response = load_response(rig.response_source()).select(["R", "G", "B"])
    q = response.resample(w, extrapolate="zero").values
    light = illuminant(rig.light.source, w).values[:, 0] * trapezoid_weights(w)
    order = sorted(filters, key=lambda name: filters[name].centre_nm)
    totals = np.stack([(q * (light * filters[name].transmission(w))[:, None]).sum(0)
                       for name in order])  # fmt: skip
    green = totals[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        r, b = totals[:, 0] / green, totals[:, 2] / green
    ok = green > 0
    reason = tuple("" if good else "green response is zero in this band" for good in ok)
    n = len(order)
    return ChannelSensitivity(
        wavelengths_nm=[filters[name].centre_nm for name in order],
        illuminations=tuple(order),
        r_over_g=np.where(ok, r, np.nan),
        b_over_g=np.where(ok, b, np.nan),
        pairs_r=np.zeros(n),
        pairs_b=np.zeros(n),
        residual_r=np.full(n, np.nan),
        residual_b=np.full(n, np.nan),
        reliable_r=ok,
        reliable_b=ok,
        reason_r=reason,
        reason_b=reason,
        green_level=np.where(ok, green, np.nan),
        source="nominal",
        labkit={
            "method": "∫ q_c T L dλ / ∫ q_G T L dλ, trapezoid rule",
            "rig": rig.source or rig.name,
            "response": rig.camera.response,
            "light": rig.light.source,
            "grid_nm": [float(w[0]), float(w[-1]), step],
        },
    )
