"""Colour science: the CIE 1931 observer, Rec.709 primaries, spectra and blackbodies.

* :data:`CIE_1931`: the CIE 1931 2-degree colour matching functions (x_bar, y_bar, z_bar),
  380-780 nm every 10 nm (:data:`CIE_START_NM`, :data:`CIE_STEP_NM`).
* :data:`XYZ_TO_REC709`: CIE XYZ to linear Rec.709 / sRGB primaries, D65 white.
* :func:`spectrum_to_rec709`: a spectral curve (a dye's extinction per gram) reduced to linear
  Rec.709 channels as a weighted average,
  ``eps_c = sum_l eps(l) w_c(l) / sum_l w_c(l)`` with ``w_c = max(0, (M_709 . xyz_bar)(l)_c)``:
  the colour matching functions taken to linear Rec.709 and clipped at zero. A flat spectrum
  gives equal channels. The curve is interpolated linearly and held constant beyond its ends.
* :func:`blackbody_rgb`: the linear Rec.709 colour of a blackbody (UsdLux colour
  temperature).

:func:`spectrum_to_rec709` needs only the standard library; :func:`blackbody_rgb` uses numpy.
"""
from __future__ import annotations

from typing import Any

# CIE 1931 2-degree colour matching functions, 380..780 nm every 10 nm (x_bar, y_bar, z_bar).
CIE_START_NM = 380.0
CIE_STEP_NM = 10.0
CIE_1931 = (
    (0.001368, 0.000039, 0.006450), (0.004243, 0.000120, 0.020050),
    (0.014310, 0.000396, 0.067850), (0.043510, 0.001210, 0.207400),
    (0.134380, 0.004000, 0.645600), (0.283900, 0.011600, 1.385600),
    (0.348280, 0.023000, 1.747060), (0.336200, 0.038000, 1.772110),
    (0.290800, 0.060000, 1.669200), (0.195360, 0.090980, 1.287640),
    (0.095640, 0.139020, 0.812950), (0.032010, 0.208020, 0.465180),
    (0.004900, 0.323000, 0.272000), (0.009300, 0.503000, 0.158200),
    (0.063270, 0.710000, 0.078250), (0.165500, 0.862000, 0.042160),
    (0.290400, 0.954000, 0.020300), (0.433450, 0.994950, 0.008750),
    (0.594500, 0.995000, 0.003900), (0.762100, 0.952000, 0.002100),
    (0.916300, 0.870000, 0.001650), (1.026300, 0.757000, 0.001100),
    (1.062200, 0.631000, 0.000800), (1.002600, 0.503000, 0.000340),
    (0.854450, 0.381000, 0.000190), (0.642400, 0.265000, 0.000050),
    (0.447900, 0.175000, 0.000020), (0.283500, 0.107000, 0.000000),
    (0.164900, 0.061000, 0.000000), (0.087400, 0.032000, 0.000000),
    (0.046770, 0.017000, 0.000000), (0.022700, 0.008210, 0.000000),
    (0.011359, 0.004102, 0.000000), (0.005790, 0.002091, 0.000000),
    (0.002899, 0.001047, 0.000000), (0.001440, 0.000520, 0.000000),
    (0.000690, 0.000249, 0.000000), (0.000332, 0.000120, 0.000000),
    (0.000166, 0.000060, 0.000000), (0.000083, 0.000030, 0.000000),
    (0.000042, 0.000015, 0.000000),
)
# CIE XYZ -> linear Rec.709 / sRGB primaries, D65 white (IEC 61966-2-1).
XYZ_TO_REC709 = (
    (3.2404542, -1.5371385, -0.4985314),
    (-0.9692660, 1.8760108, 0.0415560),
    (0.0556434, -0.2040259, 1.0572252),
)


def _rec709_weights() -> list[tuple[float, float, float]]:
    out = []
    for xyz in CIE_1931:
        out.append(tuple(max(0.0, sum(m * v for m, v in zip(row, xyz))) for row in XYZ_TO_REC709))
    return out  # type: ignore[return-value]


_REC709_WEIGHTS = _rec709_weights()


def _interp(x: float, xs: list[float], ys: list[float]) -> float:
    """Piecewise-linear interpolation, constant beyond the ends (like numpy.interp)."""
    if x <= xs[0]:
        return ys[0]
    if x >= xs[-1]:
        return ys[-1]
    lo, hi = 0, len(xs) - 1
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if xs[mid] <= x:
            lo = mid
        else:
            hi = mid
    t = (x - xs[lo]) / (xs[hi] - xs[lo])
    return ys[lo] + t * (ys[hi] - ys[lo])


def spectrum_to_rec709(wavelengths_nm: list[float], values: list[float]) -> tuple[float, float, float]:
    """Reduce a spectral curve to linear Rec.709 channels (weighted average; module docstring)."""
    sums = [0.0, 0.0, 0.0]
    norms = [0.0, 0.0, 0.0]
    for i, w in enumerate(_REC709_WEIGHTS):
        eps = _interp(CIE_START_NM + i * CIE_STEP_NM, wavelengths_nm, values)
        for c in range(3):
            sums[c] += eps * w[c]
            norms[c] += w[c]
    return (sums[0] / norms[0], sums[1] / norms[1], sums[2] / norms[2])


_C2 = 1.4387769e-2  # second radiation constant h c / k_B, m K


def blackbody_rgb(kelvin: float) -> Any:
    """Linear Rec.709 RGB (a numpy array) of a blackbody at ``kelvin``, normalized to luminance 1.

    Planck's law sampled at the CIE 1931 2-degree colour matching functions (380-780 nm,
    10 nm), XYZ -> linear Rec.709 (D65), negative components clipped to 0, then scaled to
    Y = 0.2126 R + 0.7152 G + 0.0722 B = 1. 6504 K is white within ~2 % (a blackbody is not
    exactly D65); USD's ``UsdLuxBlackbodyTemperatureAsRgb`` (a fitted table) agrees within a
    few percent over 1000-10000 K.
    """
    import numpy as np

    if not kelvin > 0:
        raise ValueError(f"blackbody temperature must be > 0 K, got {kelvin}")
    cmf = np.asarray(CIE_1931, dtype=np.float64)
    lam = (CIE_START_NM + CIE_STEP_NM * np.arange(len(cmf))) * 1e-9
    # Planck up to a constant factor (cancels in the normalization); exp overflow -> 0.
    with np.errstate(over="ignore"):
        spd = lam ** -5 / np.expm1(_C2 / (lam * kelvin))
    xyz = spd @ cmf
    rgb = np.maximum(np.asarray(XYZ_TO_REC709) @ xyz, 0.0)
    lum = float(rgb @ np.array([0.2126, 0.7152, 0.0722]))
    return rgb / lum


__all__ = ["CIE_1931", "CIE_START_NM", "CIE_STEP_NM", "XYZ_TO_REC709", "blackbody_rgb",
           "spectrum_to_rec709"]
