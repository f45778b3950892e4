"""Dyes matched to a colour: the extinction per gram that gives a fiber a target colour.

The colour of a fiber
---------------------
Under a uniform white light of radiance 1 (a white dome) a fiber seen from omega_o has, by
reciprocity, the radiance of its albedo (:mod:`usdfiber.bcsdf`: the integral over omega_i of
``sigma(omega_i, omega_o) / (W(phi_o) cos theta_o)`` is ``Lambda(omega_o)``). The colour this
module matches is that radiance averaged where the fiber is seen: over the rotations psi
(uniform, as the renderer draws them) and the cross-section variants, weighted by the
width each presents, from a view at ``theta_o`` (default 0: perpendicular to the fiber),

    C_c = sum_v int W_v(phi) Lambda_v,c(theta_o, phi) dphi / sum_v int W_v(phi) dphi

per linear Rec.709 channel c, times the light's colour for a light that is not white
(:func:`light_rgb`). ``theta_deg=None`` averages over all views instead, uniform on the
sphere and weighted by the area the fiber shows (``W(phi) cos theta``) at the tables'
incoming nodes: the mean colour that ``primvars:displayColor`` carries. Light scattered between fibers (a yarn's, a cloth's) is not part of it:
for a yarn this is the colour of its fibers, and the yarn looks deeper (measured on the
Table 3 threads, ``bench/yarn_colour_bench.py``: the yarn's albedo is 0.25-0.58 of its
fibers' per channel).

Solving
-------
The dye enters through the absorption of each channel alone,
``mu_a,c = rho * zeta * epsilon_c`` (:func:`usdfiber.spec.fiber.mu_a_per_um`), scaled by the
diameter (:meth:`usdfiber.bake.table.BcsdfTable.sigma_for`), and ``Lambda`` at any absorption
is the table's recolouring (the albedo's absorption levels, interpolated as
:meth:`~usdfiber.bake.table.BcsdfTable.recolour` does; nothing is traced). C_c is a
decreasing function of epsilon_c only, so each channel is one root find within the dye
class's industry range (paper Section 3.1; :func:`usdfiber.spec.attributes.industry_extinction_ranges`;
the class ``custom`` allows the schema's valid range). The colours reachable form a box in
linear RGB: a target outside it gets :class:`ColourOutOfReach` with the nearest reachable
colour (each channel clamped to its end of the box, the nearest point in linear RGB).

A spectral dye (:func:`spectral_extinction`) is a smooth, non-negative extinction curve
whose reduction to Rec.709 channels (:func:`usdfiber.colour.spectrum_to_rec709`, what the
renderer reads) is the matched extinction.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from usdfiber.bake.absorption import log_interpolate
from usdfiber.bake.lookup import eval_incoming
from usdfiber.colour import CIE_1931, CIE_START_NM, CIE_STEP_NM, blackbody_rgb, spectrum_to_rec709
from usdfiber.spec.attributes import Fiber, Interval, attribute, industry_extinction_ranges
from usdfiber.spec.fiber import mu_a_per_um

__all__ = [
    "ColourOutOfReach", "DyeMatch", "DyeMatchError", "FiberColour", "author_dye", "default_dye_class",
    "extinction_range", "LIGHT_RANGE", "light_rgb", "linear_to_srgb", "match_dye", "parse_colour",
    "spectral_extinction", "srgb_hex", "srgb_to_linear",
]

#: Azimuths of the average over rotations (the tables' finest grid is 2 degrees).
PHI_SAMPLES = 720

#: Relative accuracy of a matched channel's colour (the root find's tolerance).
MATCH_RTOL = 1e-6


class DyeMatchError(ValueError):
    """A colour, light or dye request that cannot be used (one line saying why)."""


# ---------------------------------------------------------------------------------- colours
def srgb_to_linear(v: Sequence[float]) -> np.ndarray:
    """sRGB-encoded values in [0, 1] to linear Rec.709 (IEC 61966-2-1 transfer function)."""
    x = np.asarray(v, dtype=np.float64)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(v: Sequence[float]) -> np.ndarray:
    """Linear Rec.709 to sRGB-encoded values (clipped to [0, 1])."""
    x = np.clip(np.asarray(v, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1.0 / 2.4) - 0.055)


def srgb_hex(rgb_linear: Sequence[float]) -> str:
    """``#rrggbb`` of a linear Rec.709 colour (clipped to [0, 1])."""
    return "#" + "".join(f"{int(round(float(c) * 255)):02x}" for c in linear_to_srgb(rgb_linear))


_HEX = re.compile(r"^#?([0-9a-fA-F]{6}|[0-9a-fA-F]{3})$")


def _triple(text: str, what: str) -> np.ndarray:
    parts = [p for p in re.split(r"[,\s]+", text.strip()) if p]
    try:
        vals = np.array([float(p) for p in parts], dtype=np.float64)
    except ValueError:
        vals = np.array([])
    if vals.shape != (3,) or not np.all(np.isfinite(vals)):
        raise DyeMatchError(f"{what} {text!r}: expected an sRGB hex colour (#b0402a) or three linear "
                            f"Rec.709 numbers (0.43,0.05,0.02)")
    return vals


def parse_colour(text: str) -> np.ndarray:
    """A target colour as linear Rec.709: ``#rrggbb`` / ``#rgb`` (sRGB-encoded) or ``r,g,b``
    (linear, each in [0, 1]). DyeMatchError otherwise."""
    t = text.strip()
    m = _HEX.match(t)
    if m:
        h = m.group(1)
        if len(h) == 3:
            h = "".join(c * 2 for c in h)
        return srgb_to_linear([int(h[i:i + 2], 16) / 255.0 for i in (0, 2, 4)])
    rgb = _triple(t, "colour")
    if np.any(rgb < 0) or np.any(rgb > 1):
        raise DyeMatchError(f"colour {text!r}: linear RGB components must be in [0, 1] (a fiber under a "
                            f"white light of radiance 1 reflects at most all of it)")
    return rgb


#: The radiance a light may have per channel, relative to the white light of radiance 1 that
#: target colours are for (beyond it every colour is out of reach, or the sums overflow).
LIGHT_RANGE = (1e-6, 1e6)


def light_rgb(text: str | None) -> np.ndarray:
    """The light's colour (linear Rec.709): ``white`` (1, 1, 1), ``6500K`` (a blackbody of
    luminance 1, :func:`usdfiber.colour.blackbody_rgb`; below about 1950K it has no blue) or
    ``r,g,b``, each channel in :data:`LIGHT_RANGE`."""
    if text is None or text.strip().lower() in ("", "white"):
        return np.ones(3)
    t = text.strip()
    if t[-1] in "kK":
        try:
            kelvin = float(t[:-1])
        except ValueError:
            kelvin = float("nan")
        if not (math.isfinite(kelvin) and 1000.0 <= kelvin <= 40000.0):
            raise DyeMatchError(f"light {text!r}: a colour temperature must be 1000K to 40000K")
        rgb = np.asarray(blackbody_rgb(kelvin), dtype=np.float64)
    else:
        rgb = _triple(t, "light")
    bad = [f"{c} {v:g}" for c, v in zip("RGB", rgb) if not LIGHT_RANGE[0] <= v <= LIGHT_RANGE[1]]
    if bad:
        raise DyeMatchError(f"light {text!r}: every channel must be from {LIGHT_RANGE[0]:g} to {LIGHT_RANGE[1]:g} "
                            f"(got {', '.join(bad)}; a channel without light cannot be matched)")
    return rgb


# --------------------------------------------------------------------------- dye classes
def default_dye_class(kind: str) -> str:
    """The dye class the industry uses for a fiber kind (Section 3.1): disperse dyes for
    polyester, reactive dyes for cotton, silk and wool."""
    return "disperse" if kind == "polyester" else "reactive"


def extinction_range(dye_class: str) -> Interval:
    """The extinction per gram (L mg^-1 cm^-1) a dye class may take: the industry range of
    ``reactive`` and ``disperse``, the schema's valid range for ``custom``."""
    ranges = industry_extinction_ranges()
    if dye_class in ranges:
        return ranges[dye_class]
    if dye_class == "custom":
        valid = attribute(Fiber.DYE_EXTINCTION).valid
        assert valid is not None
        return valid
    raise DyeMatchError(f"dye class {dye_class!r}: expected one of {', '.join(list(ranges) + ['custom'])}")


# ----------------------------------------------------------------------- fiber colour
@dataclass
class FiberColour:
    """The colour of a fiber (module docstring) as a function of its dye's extinction.

    ``tables``: the fiber's tables (one per cross-section variant); ``density`` g/cm^3,
    ``diameter_um``, ``depth_of_shade`` percent; ``theta_deg`` the view's angle to the
    plane normal to the fiber, or None for the average over all views.
    """

    tables: Sequence[Any]
    density: float
    diameter_um: float
    depth_of_shade: float
    theta_deg: float | None = 0.0
    _weights: list[np.ndarray] = field(default_factory=list, repr=False)

    def __post_init__(self) -> None:
        if not self.tables:
            raise DyeMatchError("no tables: a fiber colour needs the fiber's baked tables")
        if self.theta_deg is not None and not (math.isfinite(self.theta_deg) and abs(self.theta_deg) < 90.0):
            raise DyeMatchError(f"view angle {self.theta_deg:g} deg: expected |theta| < 90")
        if self.theta_deg is None:
            # Incoming nodes: area shown W cos(theta), times the node's solid angle (cos theta).
            ws = [t.width(t.grid.phi_i_nodes())[None, :] * (np.cos(t.grid.theta_i_nodes()) ** 2)[:, None]
                  for t in self.tables]
        else:
            self._phi = (np.arange(PHI_SAMPLES) + 0.5) * (2.0 * math.pi / PHI_SAMPLES)
            ws = [t.width(self._phi) for t in self.tables]
        total = sum(float(w.sum()) for w in ws)
        self._weights = [w / total for w in ws]

    def sigma(self, extinction: float) -> list[float]:
        """Each table's effective absorption (1/um at its baked size) for one channel's
        extinction per gram."""
        mu = mu_a_per_um(self.density, self.depth_of_shade, float(extinction))
        return [float(t.sigma_for(mu, self.diameter_um)) for t in self.tables]

    def channel(self, extinction: float) -> float:
        """The colour of one channel under white light 1 for its extinction per gram."""
        out = 0.0
        for t, w, s in zip(self.tables, self._weights, self.sigma(extinction)):
            alb = t.arrays["albedo"].astype(np.float64)
            alb_l = t.arrays["albedo_lbar"].astype(np.float64)
            # Lambda at the incoming nodes for this absorption: the recolouring's albedo.
            nodes = log_interpolate(t.levels, s, lambda k: alb[:, :, k], lambda k: alb_l[:, :, k])
            if self.theta_deg is None:
                out += float((w * nodes).sum())
            else:
                lam = eval_incoming(t.grid, nodes[..., None], math.radians(self.theta_deg), self._phi,
                                    0.0, "linear")[..., 0]
                out += float(np.dot(w, lam))
        return out

    def colour(self, extinction: Sequence[float], light: Sequence[float] = (1.0, 1.0, 1.0)) -> np.ndarray:
        """Linear Rec.709 colour for a per-channel extinction, under ``light``."""
        return np.array([self.channel(e) for e in extinction]) * np.asarray(light, dtype=np.float64)


# ------------------------------------------------------------------------- matching
@dataclass(frozen=True)
class DyeMatch:
    """A matched dye: class, extinction per gram per channel, and the colours involved
    (linear Rec.709 under ``light``)."""

    target: tuple[float, float, float]
    light: tuple[float, float, float]
    dye_class: str
    extinction: tuple[float, float, float]
    colour: tuple[float, float, float]          # reached (equals target when reachable)
    reachable: tuple[bool, bool, bool]
    lightest: tuple[float, float, float]        # colour at the range's low end
    darkest: tuple[float, float, float]         # colour at the range's high end
    range: tuple[float, float]
    depth_of_shade: float
    theta_deg: float | None

    @property
    def in_reach(self) -> bool:
        return all(self.reachable)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able values, with units and hex colours."""
        return {
            "dye_class": self.dye_class, "extinction": list(self.extinction),
            "extinction_range": list(self.range), "depth_of_shade": self.depth_of_shade,
            "target": list(self.target), "target_hex": srgb_hex(self.target),
            "colour": list(self.colour), "colour_hex": srgb_hex(self.colour),
            "reachable": all(self.reachable), "reachable_channels": list(self.reachable),
            "lightest": list(self.lightest), "darkest": list(self.darkest),
            "light": list(self.light), "view_theta_deg": self.theta_deg,
            "units": {"extinction": "L mg^-1 cm^-1 (linear Rec.709 R, G, B)", "depth_of_shade": "%",
                      "colours": "linear Rec.709", "view_theta_deg": "deg (null: all views)"},
        }


class ColourOutOfReach(DyeMatchError):
    """A target no extinction within the range reaches; ``match`` holds the nearest."""

    def __init__(self, message: str, match: DyeMatch) -> None:
        super().__init__(message)
        self.match = match


def _solve(f: Any, target: float, lo: float, hi: float) -> float:
    """epsilon in [lo, hi] with f(epsilon) = target, f decreasing, f(lo) >= target >= f(hi)."""
    from scipy.optimize import brentq

    # A coarse scan first: Hermite interpolation between absorption levels is monotone in
    # practice, but the bracket must hold whatever the table.
    xs = np.geomspace(max(lo, 1e-9), hi, 33) if lo > 0 else np.concatenate([[0.0], np.geomspace(hi * 1e-6, hi, 32)])
    xs[0], xs[-1] = lo, hi
    fs = np.array([f(x) for x in xs]) - target
    k = int(np.argmax(fs <= 0))
    if fs[k] == 0 or k == 0:
        return float(xs[k])
    return float(brentq(lambda x: f(x) - target, xs[k - 1], xs[k], xtol=1e-14, rtol=1e-12))


def match_dye(fiber: FiberColour, target: Sequence[float], dye_class: str,
              light: Sequence[float] = (1.0, 1.0, 1.0)) -> DyeMatch:
    """The extinction per gram that gives ``fiber`` the colour ``target`` under ``light``.

    ``target``: linear Rec.709; ``dye_class``: ``reactive``, ``disperse`` (industry ranges)
    or ``custom`` (the schema's valid range). Raises :class:`ColourOutOfReach` (holding the
    nearest reachable match) when a channel cannot be reached within the range, and
    DyeMatchError for a fiber without dye (depth of shade 0).
    """
    tgt = np.asarray(target, dtype=np.float64)
    lit = np.asarray(light, dtype=np.float64)
    if tgt.shape != (3,) or not np.all(np.isfinite(tgt)) or np.any(tgt < 0):
        raise DyeMatchError(f"target colour {list(tgt)}: expected three finite linear RGB values >= 0")
    if fiber.depth_of_shade <= 0:
        raise DyeMatchError("depth of shade 0: an undyed fiber has one colour; give a depth of shade > 0")
    rng = extinction_range(dye_class)
    lo, hi = rng.lo, rng.hi
    ext, got, ok, light_c, dark_c = [], [], [], [], []
    for c in range(3):
        need = tgt[c] / lit[c]
        f_lo, f_hi = fiber.channel(lo), fiber.channel(hi)
        light_c.append(f_lo * lit[c])
        dark_c.append(f_hi * lit[c])
        if need > f_lo:
            e, reach = lo, False
        elif need < f_hi:
            e, reach = hi, False
        else:
            e, reach = _solve(fiber.channel, need, lo, hi), True
        ext.append(e)
        ok.append(reach)
        got.append(fiber.channel(e) * lit[c])
    m = DyeMatch(target=tuple(tgt), light=tuple(lit), dye_class=dye_class, extinction=tuple(ext),  # type: ignore[arg-type]
                 colour=tuple(got), reachable=tuple(ok), lightest=tuple(light_c), darkest=tuple(dark_c),  # type: ignore[arg-type]
                 range=(lo, hi), depth_of_shade=fiber.depth_of_shade, theta_deg=fiber.theta_deg)
    if not m.in_reach:
        names = [n for n, r in zip("RGB", ok) if not r]
        raise ColourOutOfReach(
            f"colour {srgb_hex(tgt)} (linear {_fmt(tgt)}) is out of reach of a {dye_class} dye "
            f"(extinction {lo:g}-{hi:g} L/(mg cm)) at {fiber.depth_of_shade:g} % depth of shade: channel(s) "
            f"{', '.join(names)}; reachable per channel from {_fmt(dark_c)} to {_fmt(light_c)}; nearest "
            f"reachable colour {srgb_hex(got)} (linear {_fmt(got)})", m)
    return m


def _fmt(v: Sequence[float]) -> str:
    return "(" + ", ".join(f"{float(x):.4f}" for x in v) + ")"


# ------------------------------------------------------------------------- spectra
#: Smoothness weight of :func:`spectral_extinction` (second differences per 10 nm).
_SMOOTH = 0.05


def spectral_extinction(extinction: Sequence[float]) -> tuple[list[float], list[float]]:
    """A spectral extinction curve (wavelengths nm, values L mg^-1 cm^-1, 380-780 nm every
    10 nm) whose reduction to Rec.709 (:func:`usdfiber.colour.spectrum_to_rec709`) is
    ``extinction``: the smoothest non-negative curve doing so (non-negative least squares on
    the reduction, weighted far above a second-difference penalty). DyeMatchError when no
    such curve reduces to it within 1e-4 relative (a dye more saturated than the observer's
    overlapping channels allow, e.g. one absorbing blue only).
    """
    eps = np.asarray(extinction, dtype=np.float64)
    if eps.shape != (3,) or not np.all(np.isfinite(eps)) or np.any(eps < 0):
        raise DyeMatchError(f"extinction {list(eps)}: expected three finite values >= 0")
    from scipy.optimize import nnls

    n = len(CIE_1931)
    wl = [CIE_START_NM + i * CIE_STEP_NM for i in range(n)]
    # The reduction is linear in the curve's values at the nodes: build its 3 x n matrix by
    # reducing each unit curve (spectrum_to_rec709 itself, so the two cannot disagree).
    R = np.array([spectrum_to_rec709(wl, list(np.eye(n)[i])) for i in range(n)]).T
    scale = float(eps.max()) or 1.0
    D = np.diff(np.eye(n), 2, axis=0)
    A = np.vstack([R / scale * 1e3, _SMOOTH * D / scale])
    b = np.concatenate([eps / scale * 1e3, np.zeros(n - 2)])
    v, _ = nnls(A, b, maxiter=50 * n)
    got = np.array(spectrum_to_rec709(wl, list(v)))
    if np.any(np.abs(got - eps) > 1e-4 * scale):
        raise DyeMatchError(f"extinction {_fmt(eps)}: no smooth non-negative spectrum reduces to it (nearest "
                            f"{_fmt(got)}); author it per channel instead")
    return wl, [float(x) for x in v]


# ------------------------------------------------------------------------- authoring
def author_dye(prim: Any, match: DyeMatch, *, spectral: bool = False) -> None:
    """Write a matched dye on a fiber or yarn prim (FiberAPI): the dye class, the depth of
    shade and the extinction per gram, per channel (``extinctionSource = "perGram"``) or, with
    ``spectral``, as the curve of :func:`spectral_extinction` (``"spectrum"``). Raises
    :class:`usdfiber.authoring.AuthoringError` for prims that are not curves."""
    from usdfiber import authoring

    values: dict[str, Any] = {"dye_class": match.dye_class, "depth_of_shade": match.depth_of_shade}
    if spectral:
        wl, vals = spectral_extinction(match.extinction)
        values.update(extinction_source="spectrum", spectrum_wavelengths=wl, spectrum_values=vals)
    else:
        values.update(extinction_source="perGram", extinction=match.extinction)
    authoring.apply_fiber(prim, None, **values)
