"""Light sources: CIE illuminants and a model of the thesis' DLP projector lamp."""

from __future__ import annotations

import numpy as np

from labkit.errors import DataError
from labkit.spectra.container import Spectra

#: Mercury emission lines of an ultra-high-pressure (UHP) lamp, nm, with relative heights
#: and pressure-broadened widths (FWHM, nm).
_UHP_LINES = ((404.7, 0.55, 12.0), (435.8, 0.85, 12.0), (546.1, 1.0, 14.0), (578.0, 0.95, 16.0))


def uhp_lamp(wavelengths: np.ndarray) -> Spectra:
    """Relative spectral power of a UHP projector lamp, peak-normalised.

    The thesis lit its scenes with a DLP projector (Optoma EP739, colour wheel removed),
    whose light comes from a mercury UHP lamp. The measured lab file holds only the
    filtered light relative to the unfiltered light, not the lamp itself, so the lamp is
    modelled: a smooth high-pressure continuum (a 6500 K Planck curve) plus the broadened
    mercury lines at 405, 436, 546 and 578 nm.

    Parameters
    ----------
    wavelengths : ndarray, shape (n,)
        Sample wavelengths, nm.
    """
    w = np.asarray(wavelengths, dtype=np.float64)
    metres = w * 1e-9
    planck = 1.0 / (metres**5 * np.expm1(1.4388e-2 / (metres * 6500.0)))
    power = 0.45 * planck / planck.max()
    for centre, height, fwhm in _UHP_LINES:
        sigma = fwhm / 2.3548
        power = power + height * np.exp(-0.5 * ((w - centre) / sigma) ** 2)
    return Spectra(w, power / power.max(), ("projector",))


#: Light sources that need no colour-science lookup.
BUILTIN_ILLUMINANTS = ("projector", "E")


def illuminant_names() -> list[str]:
    """Every name :func:`illuminant` accepts: the built-in sources, then colour-science's."""
    import colour

    extra = [name for name in colour.SDS_ILLUMINANTS if name not in BUILTIN_ILLUMINANTS]
    return [*BUILTIN_ILLUMINANTS, *extra]


def illuminant_problem(name: str) -> str:
    """``""`` for a known light source, else what to use instead: a did-you-mean and the
    known names (``"did you mean 'D65'? known: projector, E, A, …"``).

    The built-in names are checked without importing colour-science.
    """
    if name in BUILTIN_ILLUMINANTS:
        return ""
    import difflib

    names = illuminant_names()
    if name in names:
        return ""
    close = difflib.get_close_matches(name, names, n=1)
    if not close:  # case slips: 'd65' for 'D65'
        folded = {n.lower(): n for n in names}
        close = [folded[name.lower()]] if name.lower() in folded else []
    hint = f"did you mean {close[0]!r}? " if close else ""
    common = [n for n in ("A", "D50", "D65", "FL2", "FL11") if n in names]
    shown = ", ".join([*BUILTIN_ILLUMINANTS, *common])
    builtin = " and ".join(BUILTIN_ILLUMINANTS)
    return f"{hint}known: {shown}, … ({builtin} and every name in colour.SDS_ILLUMINANTS)"


def illuminant(name: str, wavelengths: np.ndarray) -> Spectra:
    """A light source's relative spectral power on `wavelengths` (nm), peak-normalised.

    Parameters
    ----------
    name : str
        ``"projector"`` (the UHP lamp model, see :func:`uhp_lamp`), ``"E"`` (equal
        energy), or any colour-science illuminant (``"D65"``, ``"A"``, ``"FL2"``, …).
    wavelengths : ndarray
        Target grid, nm.
    """
    import colour

    w = np.asarray(wavelengths, dtype=np.float64)
    if name == "projector":
        return uhp_lamp(w)
    if name == "E":
        return Spectra(w, np.ones_like(w), ("E",))
    if name not in colour.SDS_ILLUMINANTS:
        raise DataError(f"unknown illuminant {name!r}; {illuminant_problem(name)}")
    sd = colour.SDS_ILLUMINANTS[name].copy()
    data = Spectra(np.array(sd.wavelengths), np.array(sd.values), (name,))
    data = data.resample(w, extrapolate="constant")
    return data.scaled(1.0 / data.values.max())
