"""The tabulated far-field BCSDF of one fiber cross-section variant (:class:`BcsdfTable`).

Far-field convention (see :mod:`usdfiber.bcsdf` for the renderer's side)
--------------------------------------------------------------------------
Fiber frame: t (the fiber axis) is +z, the cross section lies in the xy plane. A direction
is (theta, phi): ``theta`` is the angle from the plane normal to t (sin theta = w . t),
in [-pi/2, pi/2]; ``phi`` the azimuth in that plane from the profile's +x axis towards +y,
in [0, 2 pi). ``omega_i`` points towards the light, ``omega_o`` towards the viewer: both
point away from the fiber. All angles of this module's API are in RADIANS; the header
and the command line use degrees. A fiber rotated by ``psi`` about t sees ``phi - psi``
(every method takes ``psi``).

The table holds, for one cross section:

* ``W(phi)``: the width of the profile's shadow seen from azimuth phi (um at the baked
  size). Per unit length a beam from (theta, phi) meets the area ``W(phi) cos(theta)``.
* ``Lambda(omega_i)``: the albedo, the fraction of the photons meeting that area that
  leave the fiber (1 without absorption, up to photons stopped by ``max_bounces``).
* ``p(omega_o | omega_i)``: where they leave, per steradian; it integrates to 1 over the
  sphere. No cosine is folded into any of them.

The scattering cross section ``sigma(omega_i, omega_o) = W(phi_i) cos(theta_i)
Lambda(omega_i) p(omega_o | omega_i)`` is symmetric (reciprocity).

Grid
----
With a resolution of ``d`` degrees (``d`` divides 90): ``theta_o`` has ``180/d`` bins over
[-90, 90] deg, ``phi_o`` ``360/d`` bins over [0, 360) deg; a bin's value is the average of
``p`` over the bin (photons per bin divided by the bin's solid angle
``d_phi (sin theta_hi - sin theta_lo)``). Incoming directions are sampled at bin centres:

* ``theta_i``: ``90/d`` nodes ``(k + 1/2) d`` over [0, 90] deg for extruded fibers, which obey
  ``p(theta_o, phi_o | -theta_i, phi_i) = p(-theta_o, phi_o | theta_i, phi_i)`` (the mirror
  z -> -z maps the fiber onto itself); ``180/d`` nodes over [-90, 90] deg for fibers with
  cuticle scales, which break that symmetry.
* ``phi_i``: ``360/d`` nodes ``(j + 1/2) d``; or ONE node (``d/2``) for rotationally symmetric
  profiles (round, smooth or rough), where p depends on ``phi_o - phi_i`` only: then
  ``p(theta_o, phi_o | theta_i, phi_i) = p_table(theta_o, phi_o - phi_i + d/2 | theta_i, d/2)``.

The header's ``incoming`` says how a node was traced: ``"centre"`` (the default, as in the
paper): the light comes from the node's direction, so values are point samples in omega_i
and bin averages in omega_o; ``"box"``: the photons of a node come from its whole bin
(weighted by ``W(phi) cos(theta)``), so values are averages over both bins and
``<W cos> Lambda p`` is symmetric bin for bin.

Absorption
----------
Photons are traced once, without absorption; each carries its path length ``L`` inside the
material (um, at the baked size). A dye of absorption coefficient ``sigma_a`` (1/um)
weights a photon by ``exp(-sigma_a L)``. The table keeps, at ``K`` absorption levels
``s_k`` (``levels``, 1/um at the baked size, ``s_0 = 0``), for every bin:

* ``F_k`` = sum over the bin's photons of ``exp(-s_k L)`` / photons meeting the fiber
  (stored as ``p`` at that level times ``Lambda`` at that level times the bin's solid angle),
* ``Lbar_k`` = the mean path length of those photons weighted by ``exp(-s_k L)``, which is
  ``-d log F / ds`` at ``s_k``.

``F(s)`` is the Laplace transform of the bin's path-length distribution: log-convex and
decreasing. Between two levels ``log F`` is interpolated by the cubic Hermite polynomial
that matches the values and the exact slopes ``-Lbar`` at both ends; beyond the last level
it follows the tangent. Lambda is interpolated the same way from per-direction totals.
The relative L2 error of ``p`` from this interpolation, measured against the exact
per-photon weights of traced Table 1 fibers with the default levels (0 and 1/8 ... 64, ratio
2, in optical depth across the diameter), is at most 0.9% for polyester, 0.6% for silk and
wool and 0.3% for cotton (worst over 0 < s <= 60, at s ~ 5 where the reflection and
transmission lobes trade places), independent of the bin size, and 0 at the levels.
:meth:`BcsdfTable.recolour` evaluates this on all cores in float32
(:mod:`usdfiber.bake.recolour`; it agrees with the float64 numpy reference to about 1e-6).

Diameter: the bake traces the profile scaled to a circumscribed diameter of
``baked_diameter_um`` (1 um). All path lengths scale with the diameter, so a fiber of
diameter ``D`` with absorption ``mu_a`` (1/um) is the baked profile with
``sigma_a = mu_a * D / baked_diameter_um``: pass ``sigma_a=mu_a`` and
``diameter_scale=D / baked_diameter_um`` (or use :meth:`BcsdfTable.sigma_for`).

Storage (arrays of the ``.npz`` file written with :mod:`usdfiber.table_format`)
---------------------------------------------------------------------------------
``n_ti, n_pi``: incoming nodes; ``K``: levels; ``n_to, n_po``: outgoing bins; ``B``: the
theta_o band (rows ``band_start .. band_start + B - 1`` of each incoming direction hold all
but ``band_tail`` of its mass at every level; the rest is dropped and ``p`` renormalized).

=================  ==============================  =========  ==================================
name               shape                           dtype      meaning
=================  ==============================  =========  ==================================
``p``              (n_ti, n_pi, K, B, n_po)        f2 or f4   p at level k / ``p_scale``
``p_scale``        (n_ti, n_pi, K)                 f4         per-slice scale of ``p`` (its max)
``lbar``           (n_ti, n_pi, K, B, n_po)        f2 or f4   Lbar_k (um), 0 in empty bins
``band_start``     (n_ti, n_pi)                    i2         first theta_o row of the band
``albedo``         (n_ti, n_pi, K)                 f4         Lambda at each level
``albedo_lbar``    (n_ti, n_pi, K)                 f4         -d log Lambda / ds at each level
``levels``         (K,)                            f8         s_k, 1/um at the baked size
``width``          (n_w,)                          f4         W(phi) at phi = 2 pi j / n_w (um)
``rel_error``      (n_ti, n_pi)                    f4         estimated relative L2 error of p
``photons``        (n_ti, n_pi)                    i8         photons traced per direction
=================  ==============================  =========  ==================================

float16 rounding of ``p`` costs about 2e-4 relative L2 (measured at every bake and recorded
in the header as ``quantization_error``), far below the Monte Carlo noise. The band saves
little for rough fibers at 2 degrees (multiple scattering spreads light over 60-88 of the 90
theta_o rows even when dropping 1e-3 of the mass) and much for smooth round ones.

Sampling needs no stored array: :meth:`Recoloured.cdfs` builds, per incoming node, the
marginal CDF over the band's theta_o rows and the conditional CDFs over phi_o from the
(recoloured) bin masses, and :meth:`Recoloured.sample` draws from them.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from usdfiber import table_format
from usdfiber.bake import recolour as _recolour
from usdfiber.bake.recolour import level_bracket as _level_bracket

__all__ = [
    "BcsdfTable",
    "DEFAULT_LEVELS",
    "Grid",
    "LAYOUT",
    "LAYOUT_VERSION",
    "Recoloured",
    "TableLayoutError",
    "WIDTH_SAMPLES",
    "hermite_log_interp",
]

#: Name and version of the array layout described in the module docstring.
LAYOUT = "usdfiber-bcsdf-levels"
LAYOUT_VERSION = 1
#: Absorption levels (1/um at the baked size of 1 um diameter): 0 and 1/8 ... 64.
DEFAULT_LEVELS: tuple[float, ...] = (0.0,) + tuple(2.0 ** k for k in range(-3, 7))
#: Samples of W(phi) over [0, 2 pi).
WIDTH_SAMPLES = 720

_TWO_PI = 2.0 * math.pi
_HALF_PI = 0.5 * math.pi


class TableLayoutError(ValueError):
    """A table file whose arrays do not follow this layout (the message says why)."""


# ---------------------------------------------------------------------------------------------
# Grid
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Grid:
    """The angular grid of a table (see the module docstring). Angles in radians."""

    resolution_deg: float
    theta_symmetric: bool        # theta_i >= 0 stored, negative theta_i by symmetry
    phi_invariant: bool          # one phi_i node; p depends on phi_o - phi_i

    def __post_init__(self) -> None:
        d = float(self.resolution_deg)
        if not (math.isfinite(d) and d > 0):
            raise ValueError(f"resolution must be a positive number of degrees, got {self.resolution_deg}")
        n = 90.0 / d
        if abs(n - round(n)) > 1e-9 or round(n) < 1:
            raise ValueError(f"resolution {d:g} deg must divide 90 deg (e.g. 1, 2, 3, 5, 10, 15, 30)")

    @property
    def step(self) -> float:
        """Bin size in radians."""
        return math.radians(self.resolution_deg)

    @property
    def n_theta_o(self) -> int:
        return int(round(180.0 / self.resolution_deg))

    @property
    def n_phi_o(self) -> int:
        return int(round(360.0 / self.resolution_deg))

    @property
    def n_theta_i(self) -> int:
        return self.n_theta_o // 2 if self.theta_symmetric else self.n_theta_o

    @property
    def n_phi_i(self) -> int:
        return 1 if self.phi_invariant else self.n_phi_o

    @property
    def theta_i_min(self) -> float:
        return 0.0 if self.theta_symmetric else -_HALF_PI

    def theta_o_edges(self) -> np.ndarray:
        return -_HALF_PI + self.step * np.arange(self.n_theta_o + 1)

    def theta_o_centers(self) -> np.ndarray:
        return -_HALF_PI + self.step * (np.arange(self.n_theta_o) + 0.5)

    def phi_o_centers(self) -> np.ndarray:
        return self.step * (np.arange(self.n_phi_o) + 0.5)

    def theta_i_nodes(self) -> np.ndarray:
        return self.theta_i_min + self.step * (np.arange(self.n_theta_i) + 0.5)

    def phi_i_nodes(self) -> np.ndarray:
        return self.step * (np.arange(self.n_phi_i) + 0.5)

    def solid_angles(self) -> np.ndarray:
        """Solid angle of each theta_o row's bins (n_theta_o,): d_phi (sin hi - sin lo)."""
        e = self.theta_o_edges()
        return self.step * (np.sin(e[1:]) - np.sin(e[:-1]))

    def bin_index(self, directions: np.ndarray) -> np.ndarray:
        """Flat bin index ``row * n_phi_o + col`` of unit directions (M, 3) in the fiber frame."""
        d = np.asarray(directions, dtype=np.float64)
        theta = np.arcsin(np.clip(d[:, 2], -1.0, 1.0))
        phi = np.mod(np.arctan2(d[:, 1], d[:, 0]), _TWO_PI)
        row = np.clip(np.floor((theta + _HALF_PI) / self.step).astype(np.int64), 0, self.n_theta_o - 1)
        col = np.floor(phi / self.step).astype(np.int64) % self.n_phi_o
        return row * self.n_phi_o + col

    def to_header(self) -> dict[str, Any]:
        return {
            "deg": self.resolution_deg,
            "theta_o": self.n_theta_o,
            "phi_o": self.n_phi_o,
            "theta_i": self.n_theta_i,
            "phi_i": self.n_phi_i,
            "theta_o_range_deg": [-90.0, 90.0],
            "phi_o_range_deg": [0.0, 360.0],
            "theta_i_range_deg": [math.degrees(self.theta_i_min), 90.0],
            "theta_i_nodes": "bin centres (k + 1/2) * deg from the range start",
            "phi_i_nodes": "bin centres (j + 1/2) * deg",
            "theta_symmetric": self.theta_symmetric,
            "rotationally_symmetric": self.phi_invariant,
        }

    @classmethod
    def from_header(cls, res: Mapping[str, Any]) -> "Grid":
        return cls(float(res["deg"]), bool(res["theta_symmetric"]), bool(res["rotationally_symmetric"]))


# ---------------------------------------------------------------------------------------------
# Absorption-level interpolation
# ---------------------------------------------------------------------------------------------

def hermite_log_interp(levels: np.ndarray, s: float, f0: np.ndarray, l0: np.ndarray,
                       f1: np.ndarray | None, l1: np.ndarray | None, k: int) -> np.ndarray:
    """``F(s)`` from ``F`` and ``Lbar = -d log F / ds`` at levels ``k`` and ``k + 1``.

    Cubic Hermite interpolation of ``log F``; beyond the last level (``f1 is None``) the
    tangent at level ``k``. The result stays between ``F(s_{k+1})`` and ``F(s_k)`` (F is
    decreasing). Bins empty at level ``k + 1`` (underflow) follow the tangent at ``k``.
    """
    s0 = float(levels[k])
    f0 = np.asarray(f0, dtype=np.float64)
    l0 = np.asarray(l0, dtype=np.float64)
    pos0 = f0 > 0.0
    y0 = np.log(np.where(pos0, f0, 1.0))          # only used where pos0
    tangent = y0 - l0 * (s - s0)
    if f1 is None or s == s0:
        if s == s0:
            return f0.copy()
        return np.where(pos0, np.exp(tangent), 0.0)
    s1 = float(levels[k + 1])
    f1 = np.asarray(f1, dtype=np.float64)
    l1 = np.asarray(l1, dtype=np.float64)
    if s >= s1:
        return f1.copy()
    h = s1 - s0
    t = (s - s0) / h
    h00 = 2 * t ** 3 - 3 * t ** 2 + 1
    h10 = t ** 3 - 2 * t ** 2 + t
    h01 = -2 * t ** 3 + 3 * t ** 2
    h11 = t ** 3 - t ** 2
    pos1 = f1 > 0.0
    y1 = np.log(np.where(pos1, f1, 1.0))
    y = h00 * y0 + h10 * h * (-l0) + h01 * y1 + h11 * h * (-l1)
    both = pos0 & pos1
    y = np.where(both, np.clip(y, y1, y0), tangent)
    out = np.where(pos0, np.exp(np.where(pos0, y, 0.0)), 0.0)
    # A bin empty at level k but not at k+1 (rounding of tiny values): keep the k+1 value.
    return np.where(~pos0 & pos1, f1, out)


# ---------------------------------------------------------------------------------------------
# Lookups shared by the table and its recoloured versions
# ---------------------------------------------------------------------------------------------

def _incoming_nodes(grid: Grid, theta_i: np.ndarray, phi_i: np.ndarray,
                    linear: bool) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Interpolation nodes of incoming directions: [(ti, pi, flip, weight), ...].

    ``flip`` says the node is used through the theta symmetry (theta_o must be negated).
    Linear: tent weights between the two nearest theta_i nodes (extruded tables mirror the
    first node below theta_i = 0) and the two nearest phi_i nodes (periodic); beyond the
    outermost theta_i node, the outermost node. Nearest: the node of the bin.
    """
    th = np.asarray(theta_i, dtype=np.float64)
    ph = np.asarray(phi_i, dtype=np.float64)
    n_t = grid.n_theta_i
    if grid.theta_symmetric:
        flip_base = th < 0.0
        a = np.abs(th)
    else:
        flip_base = np.zeros(th.shape, dtype=bool)
        a = th
    u = (a - grid.theta_i_min) / grid.step - 0.5
    if linear:
        k0 = np.floor(u)
        t = u - k0
        k0 = k0.astype(np.int64)
        k1 = k0 + 1
        th_nodes = []
        for k, w in ((k0, 1.0 - t), (k1, t)):
            flip = flip_base.copy()
            if grid.theta_symmetric:
                mirror = k < 0
                flip = flip ^ mirror
                k = np.where(mirror, -k - 1, k)
            th_nodes.append((np.clip(k, 0, n_t - 1), flip, w))
    else:
        k = np.clip(np.floor(u + 0.5).astype(np.int64), 0, n_t - 1)
        th_nodes = [(k, flip_base, np.ones(th.shape))]

    if grid.phi_invariant:
        ph_nodes = [(np.zeros(ph.shape, dtype=np.int64), np.ones(ph.shape))]
    else:
        n_p = grid.n_phi_i
        v = np.mod(ph, _TWO_PI) / grid.step - 0.5
        if linear:
            j0 = np.floor(v)
            t = v - j0
            j0 = j0.astype(np.int64)
            ph_nodes = [(np.mod(j0, n_p), 1.0 - t), (np.mod(j0 + 1, n_p), t)]
        else:
            ph_nodes = [(np.mod(np.floor(v + 0.5).astype(np.int64), n_p), np.ones(ph.shape))]

    out = []
    for ti, flip, wt in th_nodes:
        for pi, wp in ph_nodes:
            out.append((ti, pi, flip, wt * wp))
    return out


def _lookup_out(grid: Grid, band_start: np.ndarray, values: np.ndarray, ti: np.ndarray,
                pi: np.ndarray, theta_o: np.ndarray, phi_o: np.ndarray, bilinear: bool) -> np.ndarray:
    """Values (..., C) of ``values[ti, pi, band_row, col, C]`` at outgoing directions.

    Bilinear between bin centres in (theta_o, phi_o) (periodic in phi, constant beyond the
    outermost theta_o centres), or the bin's value. Rows outside the band are 0.
    """
    n_band = values.shape[2]
    n_r, n_c = grid.n_theta_o, grid.n_phi_o
    start = band_start[ti, pi].astype(np.int64)

    def gather(r, c):
        rr = r - start
        ok = (rr >= 0) & (rr < n_band)
        v = values[ti, pi, np.clip(rr, 0, n_band - 1), c]
        return np.where(ok[..., None], v, 0.0)

    a = (theta_o + _HALF_PI) / grid.step
    b = np.mod(phi_o, _TWO_PI) / grid.step
    if not bilinear:
        r = np.clip(np.floor(a).astype(np.int64), 0, n_r - 1)
        c = np.floor(b).astype(np.int64) % n_c
        return gather(r, c).astype(np.float64)
    a = np.clip(a - 0.5, 0.0, n_r - 1.0)
    r0 = np.minimum(np.floor(a).astype(np.int64), n_r - 1)
    tr = (a - r0)[..., None]
    r1 = np.minimum(r0 + 1, n_r - 1)
    b = b - 0.5
    c0f = np.floor(b)
    tc = (b - c0f)[..., None]
    c0 = c0f.astype(np.int64) % n_c
    c1 = (c0 + 1) % n_c
    return ((1 - tr) * (1 - tc) * gather(r0, c0) + (1 - tr) * tc * gather(r0, c1)
            + tr * (1 - tc) * gather(r1, c0) + tr * tc * gather(r1, c1))


def _eval_directional(grid: Grid, band_start: np.ndarray, values: np.ndarray, theta_i, phi_i,
                      theta_o, phi_o, psi, interp_i: str, interp_o: str) -> np.ndarray:
    if interp_i not in ("linear", "nearest"):
        raise ValueError("interp_i must be 'linear' or 'nearest'")
    if interp_o not in ("bilinear", "nearest"):
        raise ValueError("interp_o must be 'bilinear' or 'nearest'")
    th_i, ph_i, th_o, ph_o = np.broadcast_arrays(*(np.asarray(x, dtype=np.float64)
                                                   for x in (theta_i, phi_i, theta_o, phi_o)))
    ph_i = ph_i - psi
    ph_o = ph_o - psi
    if grid.phi_invariant:
        ph_o = ph_o - ph_i + 0.5 * grid.step
    out = np.zeros(th_i.shape + (values.shape[-1],))
    for ti, pi, flip, w in _incoming_nodes(grid, th_i, ph_i, interp_i == "linear"):
        th = np.where(flip, -th_o, th_o)
        out += w[..., None] * _lookup_out(grid, band_start, values, ti, pi, th, ph_o,
                                          interp_o == "bilinear")
    return out


def _eval_incoming(grid: Grid, values: np.ndarray, theta_i, phi_i, psi, interp_i: str) -> np.ndarray:
    th_i, ph_i = np.broadcast_arrays(np.asarray(theta_i, dtype=np.float64),
                                     np.asarray(phi_i, dtype=np.float64))
    out = np.zeros(th_i.shape + (values.shape[-1],))
    for ti, pi, _flip, w in _incoming_nodes(grid, th_i, ph_i - psi, interp_i == "linear"):
        out += w[..., None] * values[ti, pi]
    return out


def _channels(x: np.ndarray, scalar: bool) -> np.ndarray:
    return x[..., 0] if scalar else x


# ---------------------------------------------------------------------------------------------
# Recoloured table
# ---------------------------------------------------------------------------------------------

@dataclass
class Recoloured:
    """A table recoloured for one absorption: p and Lambda per colour channel (float32).

    ``p``: (n_ti, n_pi, B, n_po, C) per steradian, each slice integrating to 1 over the band;
    ``albedo``: (n_ti, n_pi, C); ``sigma_a``: the effective absorption per channel (1/um at
    the baked size) they were computed for.
    """

    table: "BcsdfTable"
    sigma_a: np.ndarray
    p: np.ndarray
    albedo: np.ndarray
    _cdfs: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)

    @property
    def grid(self) -> Grid:
        return self.table.grid

    def eval_p(self, theta_i, phi_i, theta_o, phi_o, *, psi: float = 0.0, interp_i: str = "linear",
               interp_o: str = "bilinear") -> np.ndarray:
        """p(omega_o | omega_i) per steradian, shape (..., C). Radians; see BcsdfTable.eval_p."""
        return _eval_directional(self.grid, self.table.band_start, self.p, theta_i, phi_i,
                                 theta_o, phi_o, psi, interp_i, interp_o)

    def albedo_at(self, theta_i, phi_i, *, psi: float = 0.0, interp_i: str = "linear") -> np.ndarray:
        """Lambda(omega_i), shape (..., C)."""
        return _eval_incoming(self.grid, self.albedo, theta_i, phi_i, psi, interp_i)

    # ---- sampling ------------------------------------------------------------------------
    def cdfs(self) -> tuple[np.ndarray, np.ndarray]:
        """(marginal, conditional) CDFs for sampling omega_o, from the channel-mean bin masses.

        ``marginal``: (n_ti, n_pi, B + 1) over the band's theta_o rows, from 0 to 1;
        ``conditional``: (n_ti, n_pi, B, n_po + 1) over phi_o within each row (a row
        without mass gets a uniform CDF). float64.
        """
        if self._cdfs is None:
            mass = self.p.astype(np.float64).mean(axis=-1) * self.table.domega_band()[..., None]
            row = mass.sum(axis=-1)
            tot = row.sum(axis=-1, keepdims=True)
            marg = np.concatenate([np.zeros(row.shape[:-1] + (1,)), np.cumsum(row, axis=-1)], axis=-1)
            marg /= np.where(tot > 0, tot, 1.0)
            marg[..., -1] = 1.0
            cond = np.concatenate([np.zeros(mass.shape[:-1] + (1,)), np.cumsum(mass, axis=-1)], axis=-1)
            rs = cond[..., -1:]
            uniform = np.linspace(0.0, 1.0, mass.shape[-1] + 1)
            cond = np.where(rs > 0, cond / np.where(rs > 0, rs, 1.0), uniform)
            cond[..., -1] = 1.0
            self._cdfs = (marg, cond)
        return self._cdfs

    def sample(self, theta_i, phi_i, u: np.ndarray, *, psi: float = 0.0,
               interp_i: str = "linear") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Draw omega_o from the channel-mean p(. | omega_i); ``u`` (..., 5) uniform numbers.

        u[0] picks an incoming node with its interpolation weight, u[1] the theta_o row,
        u[2] the phi_o bin, u[3] and u[4] the point in the bin (uniform in solid angle).
        Returns (theta_o, phi_o, pdf) with the pdf per steradian of the whole mixture, which
        equals the channel mean of ``eval_p(..., interp_o="nearest")``.
        """
        g = self.grid
        marg, cond = self.cdfs()
        u = np.asarray(u, dtype=np.float64)
        th_i, ph_i = np.broadcast_arrays(np.asarray(theta_i, dtype=np.float64),
                                         np.asarray(phi_i, dtype=np.float64))
        shape = np.broadcast_shapes(th_i.shape, u.shape[:-1])
        th_i, ph_i = np.broadcast_to(th_i, shape), np.broadcast_to(ph_i, shape) - psi
        u = np.broadcast_to(u, shape + (5,))
        nodes = _incoming_nodes(g, th_i, ph_i, interp_i == "linear")
        cw = np.cumsum(np.stack([w for *_, w in nodes]), axis=0)
        pick = np.sum(u[..., 0][None] >= cw[:-1] / cw[-1:], axis=0) if len(nodes) > 1 else np.zeros(shape, int)
        ti = np.choose(pick, [n[0] for n in nodes])
        pi = np.choose(pick, [n[1] for n in nodes])
        flip = np.choose(pick, [n[2] for n in nodes])
        m = marg[ti, pi]
        r = np.clip(np.sum(u[..., 1:2] >= m[..., 1:], axis=-1), 0, m.shape[-1] - 2)
        c_cdf = cond[ti, pi, r]
        c = np.clip(np.sum(u[..., 2:3] >= c_cdf[..., 1:], axis=-1), 0, g.n_phi_o - 1)
        row = r + self.table.band_start[ti, pi]
        e = g.theta_o_edges()
        s_lo, s_hi = np.sin(e[row]), np.sin(e[row + 1])
        theta = np.arcsin(np.clip(s_lo + u[..., 3] * (s_hi - s_lo), -1.0, 1.0))
        theta = np.where(flip, -theta, theta)
        phi = (c + u[..., 4]) * g.step
        if g.phi_invariant:
            phi = phi + ph_i - 0.5 * g.step
        phi = np.mod(phi + psi, _TWO_PI)
        pdf = self.eval_p(th_i, ph_i + psi, theta, phi, psi=psi, interp_i=interp_i,
                          interp_o="nearest").mean(axis=-1)
        return theta, phi, pdf


# ---------------------------------------------------------------------------------------------
# The table
# ---------------------------------------------------------------------------------------------

_ARRAY_NAMES = ("p", "p_scale", "lbar", "band_start", "albedo", "albedo_lbar", "levels", "width",
                "rel_error", "photons")


@dataclass
class BcsdfTable:
    """The tabulated BCSDF of one cross-section variant (layout: module docstring)."""

    header: dict[str, Any]
    arrays: dict[str, np.ndarray]
    path: str | None = None
    _recoloured: dict = field(default_factory=dict, repr=False)
    _domega_band: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        missing = [n for n in _ARRAY_NAMES if n not in self.arrays]
        where = self.path or "table"
        if missing:
            raise TableLayoutError(f"{where}: missing array(s) {', '.join(missing)}")
        lay = self.header.get("layout", {})
        if not isinstance(lay, dict) or lay.get("name") != LAYOUT or lay.get("version") != LAYOUT_VERSION:
            raise TableLayoutError(f"{where}: unsupported array layout {lay!r} "
                                   f"(this usdfiber reads {LAYOUT} version {LAYOUT_VERSION})")
        self.grid = Grid.from_header(self.header["resolution"])
        g = self.grid
        p = self.arrays["p"]
        K = len(self.arrays["levels"])
        expect = (g.n_theta_i, g.n_phi_i, K)
        if p.ndim != 5 or p.shape[:3] != expect or p.shape[4] != g.n_phi_o or p.shape[3] > g.n_theta_o:
            raise TableLayoutError(f"{where}: array p has shape {p.shape}, expected "
                                   f"{expect + ('B', g.n_phi_o)}")
        if self.arrays["lbar"].shape != p.shape:
            raise TableLayoutError(f"{where}: arrays p and lbar differ in shape")
        for name, shape in (("p_scale", expect), ("albedo", expect), ("albedo_lbar", expect),
                            ("band_start", expect[:2]), ("rel_error", expect[:2]), ("photons", expect[:2])):
            if self.arrays[name].shape != shape:
                raise TableLayoutError(f"{where}: array {name} has shape {self.arrays[name].shape}, "
                                       f"expected {shape}")
        lv = self.arrays["levels"]
        if lv[0] != 0.0 or np.any(np.diff(lv) <= 0):
            raise TableLayoutError(f"{where}: levels must start at 0 and increase")
        bs = self.arrays["band_start"]
        if np.any(bs < 0) or np.any(bs + p.shape[3] > g.n_theta_o):
            raise TableLayoutError(f"{where}: band_start out of range")

    # ---- I/O -------------------------------------------------------------------------------
    @classmethod
    def load(cls, path: str | Path) -> "BcsdfTable":
        """Read and verify a table file (TableError for damaged files, TableLayoutError)."""
        header, arrays = table_format.read_table(path)
        return cls(header=header, arrays=arrays, path=str(path))

    def save(self, path: str | Path) -> dict[str, Any]:
        """Write the table atomically (compressed); returns the header written."""
        hdr = {k: v for k, v in self.header.items() if k not in ("arrays", "checksums", "format", "version")}
        written = table_format.write_table(path, hdr, self.arrays)
        self.header = written
        self.path = str(path)
        return written

    # ---- metadata --------------------------------------------------------------------------
    @property
    def levels(self) -> np.ndarray:
        return self.arrays["levels"]

    @property
    def band_start(self) -> np.ndarray:
        return self.arrays["band_start"]

    @property
    def n_band(self) -> int:
        return int(self.arrays["p"].shape[3])

    @property
    def geometry_key(self) -> str:
        return str(self.header.get("geometry_key", ""))

    @property
    def variant(self) -> int:
        return int(self.header.get("variant", 0))

    @property
    def baked_diameter_um(self) -> float:
        return float(self.header.get("baked_diameter_um", 1.0))

    @property
    def rel_error(self) -> np.ndarray:
        """Estimated relative L2 error of p per incoming direction (at sigma_a = 0)."""
        return self.arrays["rel_error"]

    def sigma_for(self, mu_a_per_um: float | Sequence[float], diameter_um: float) -> np.ndarray:
        """Effective absorption of a fiber of ``diameter_um`` with ``mu_a`` (1/um)."""
        return np.asarray(mu_a_per_um, dtype=np.float64) * (float(diameter_um) / self.baked_diameter_um)

    def domega_band(self) -> np.ndarray:
        """Solid angle of each band row's bins, (n_ti, n_pi, B)."""
        if self._domega_band is None:
            dom = self.grid.solid_angles()
            rows = self.band_start[..., None].astype(np.int64) + np.arange(self.n_band)
            self._domega_band = dom[rows]
        return self._domega_band

    def nbytes(self) -> int:
        """Bytes of the arrays in memory (the file is compressed on top)."""
        return int(sum(a.nbytes for a in self.arrays.values()))

    # ---- levels ----------------------------------------------------------------------------
    def level_p(self, k: int) -> np.ndarray:
        """p at level k (n_ti, n_pi, B, n_po), float32, per steradian."""
        return self.arrays["p"][:, :, k].astype(np.float32) * self.arrays["p_scale"][:, :, k, None, None]

    def _level_mass(self, k: int) -> np.ndarray:
        """F_k: fraction of the photons meeting the fiber that leave into each bin, float64."""
        p = self.level_p(k).astype(np.float64)
        return p * self.domega_band()[..., None] * self.arrays["albedo"][:, :, k, None, None]

    def _mass_at(self, s: float) -> np.ndarray:
        """F at absorption ``s``: float64 numpy, the reference for :mod:`~usdfiber.bake.recolour`."""
        lv = self.levels
        k = _level_bracket(lv, s)
        lb = self.arrays["lbar"]
        f0 = self._level_mass(k)
        if s == lv[k]:
            return f0
        l0 = lb[:, :, k].astype(np.float64)
        if k == len(lv) - 1:
            return hermite_log_interp(lv, s, f0, l0, None, None, k)
        return hermite_log_interp(lv, s, f0, l0, self._level_mass(k + 1), lb[:, :, k + 1].astype(np.float64), k)

    def _albedo_at(self, s: float) -> np.ndarray:
        lv = self.levels
        k = _level_bracket(lv, s)
        a = self.arrays["albedo"].astype(np.float64)
        al = self.arrays["albedo_lbar"].astype(np.float64)
        if s == lv[k]:
            return a[:, :, k]
        if k == len(lv) - 1:
            return hermite_log_interp(lv, s, a[:, :, k], al[:, :, k], None, None, k)
        return hermite_log_interp(lv, s, a[:, :, k], al[:, :, k], a[:, :, k + 1], al[:, :, k + 1], k)

    def _p_reference(self, s: float) -> np.ndarray:
        """Recoloured p for one absorption, float64 numpy (one core; slow on large tables)."""
        F = self._mass_at(s)
        tot = F.sum(axis=(-2, -1), keepdims=True)
        return np.where(tot > 0, F / np.where(tot > 0, tot, 1.0), 0.0) / self.domega_band()[..., None]

    def _p_channels(self, sigmas: Sequence[float], kernel: bool) -> np.ndarray:
        """Recoloured p for each absorption, (n_ti, n_pi, B, n_po, C) float32."""
        if kernel:
            p, lb = self.arrays["p"], self.arrays["lbar"]
            n_ti, n_pi, K, B, n_po = p.shape
            n = n_ti * n_pi
            scale = self.arrays["p_scale"].astype(np.float64) * self.arrays["albedo"]
            out = _recolour.recolour_p(p.reshape(n, K, B, n_po), lb.reshape(n, K, B, n_po), scale.reshape(n, K),
                                       self.domega_band().reshape(n, B), self.levels, sigmas)
            return out.reshape(n_ti, n_pi, B, n_po, len(sigmas))
        return np.stack([self._p_reference(s).astype(np.float32) for s in sigmas], axis=-1)

    # ---- recolouring -----------------------------------------------------------------------
    def recolour(self, sigma_a_rgb_per_um: float | Sequence[float] = 0.0,
                 diameter_scale: float = 1.0, *, kernel: bool | None = None) -> Recoloured:
        """p and Lambda for an absorption per channel (1/um), without re-tracing.

        ``sigma_a_rgb_per_um``: a scalar or one value per channel (e.g. linear Rec.709 RGB)
        in 1/um; ``diameter_scale``: the fiber's diameter over ``baked_diameter_um``. The
        effective absorption of the baked profile is their product. Results are cached.
        p is computed by the Dr.Jit kernel of :mod:`usdfiber.bake.recolour` (float32, all
        cores) where Dr.Jit has an LLVM backend, else in float64 numpy; ``kernel`` forces
        one (True / False). A grey absorption is computed once (a read-only view per channel).
        """
        sig = np.atleast_1d(np.asarray(sigma_a_rgb_per_um, dtype=np.float64)).reshape(-1)
        ds = float(diameter_scale)
        if not (math.isfinite(ds) and ds > 0):
            raise ValueError(f"diameter_scale must be > 0, got {diameter_scale}")
        eff = sig * ds
        key = tuple(float(x) for x in eff)
        for s in key:
            _level_bracket(self.levels, s)               # validates s
        use_kernel = _recolour.available() if kernel is None else bool(kernel)
        hit = self._recoloured.get((key, use_kernel))
        if hit is not None:
            return hit
        if len(set(key)) == 1:
            p = self._p_channels(key[:1], use_kernel)
            p = np.broadcast_to(p, p.shape[:-1] + (len(key),)) if len(key) > 1 else p
        else:
            p = self._p_channels(key, use_kernel)
        alb = np.stack([self._albedo_at(s).astype(np.float32) for s in key], axis=-1)
        rec = Recoloured(self, eff, p, alb)
        if len(self._recoloured) >= 8:
            self._recoloured.clear()
        self._recoloured[(key, use_kernel)] = rec
        return rec

    # ---- evaluation --------------------------------------------------------------------------
    def eval_p(self, theta_i, phi_i, theta_o, phi_o, sigma_a: float | Sequence[float] = 0.0, *,
               diameter_scale: float = 1.0, psi: float = 0.0, interp_i: str = "linear",
               interp_o: str = "bilinear") -> np.ndarray:
        """p(omega_o | omega_i) per steradian at arbitrary directions (radians, broadcast).

        ``sigma_a``: scalar (result shape = broadcast shape) or per channel (result (..., C)),
        1/um, times ``diameter_scale``. ``psi``: rotation of the fiber about its axis.
        Interpolation: in omega_i linear between incoming nodes (``interp_i="linear"``;
        extruded tables mirror the first theta_i node through theta_i = 0) or the nearest
        node; in omega_o bilinear between bin centres (``interp_o="bilinear"``) or the bin's
        value (``"nearest"``: exactly the histogram, which integrates to 1).
        """
        scalar = np.ndim(sigma_a) == 0
        rec = self.recolour(sigma_a, diameter_scale)
        return _channels(rec.eval_p(theta_i, phi_i, theta_o, phi_o, psi=psi, interp_i=interp_i,
                                    interp_o=interp_o), scalar)

    def albedo(self, theta_i, phi_i, sigma_a: float | Sequence[float] = 0.0, *,
               diameter_scale: float = 1.0, psi: float = 0.0, interp_i: str = "linear") -> np.ndarray:
        """Lambda(omega_i) (radians, broadcast); channels as in :meth:`eval_p`."""
        scalar = np.ndim(sigma_a) == 0
        rec = self.recolour(sigma_a, diameter_scale)
        return _channels(rec.albedo_at(theta_i, phi_i, psi=psi, interp_i=interp_i), scalar)

    def width(self, phi, *, psi: float = 0.0) -> np.ndarray:
        """W(phi - psi): the projected width (um at the baked size), linear in phi."""
        w = self.arrays["width"].astype(np.float64)
        n = len(w)
        x = np.mod(np.asarray(phi, dtype=np.float64) - psi, _TWO_PI) / _TWO_PI * n
        j0 = np.floor(x).astype(np.int64) % n
        t = x - np.floor(x)
        return (1 - t) * w[j0] + t * w[(j0 + 1) % n]

    def cross_section(self, theta_i, phi_i, theta_o, phi_o, sigma_a: float | Sequence[float] = 0.0,
                      **kw: Any) -> np.ndarray:
        """sigma = W(phi_i) cos(theta_i) Lambda(omega_i) p(omega_o | omega_i) (um per sr).

        Keywords as :meth:`eval_p` (``diameter_scale`` does not rescale W: multiply by the
        diameter scale for a fiber of another size).
        """
        psi = kw.get("psi", 0.0)
        interp_i = kw.get("interp_i", "linear")
        p = self.eval_p(theta_i, phi_i, theta_o, phi_o, sigma_a, **kw)
        a = self.albedo(theta_i, phi_i, sigma_a, diameter_scale=kw.get("diameter_scale", 1.0),
                        psi=psi, interp_i=interp_i)
        wc = self.width(phi_i, psi=psi) * np.cos(np.asarray(theta_i, dtype=np.float64))
        if np.ndim(sigma_a) != 0:
            wc = np.asarray(wc)[..., None]
        return wc * a * p

    # ---- summaries -------------------------------------------------------------------------
    def summary(self) -> dict[str, Any]:
        """Key numbers for reports: resolution, photons, error, albedo range, size."""
        alb0 = self.arrays["albedo"][:, :, 0]
        err = self.rel_error
        return {
            "resolution_deg": self.grid.resolution_deg,
            "shape": {"theta_i": self.grid.n_theta_i, "phi_i": self.grid.n_phi_i,
                      "levels": len(self.levels), "band": self.n_band,
                      "theta_o": self.grid.n_theta_o, "phi_o": self.grid.n_phi_o},
            "photons_total": int(self.arrays["photons"].sum()),
            "photons_per_direction": [int(self.arrays["photons"].min()), int(self.arrays["photons"].max())],
            "rel_error_rms": float(np.sqrt(np.mean(err.astype(np.float64) ** 2))),
            "rel_error_max": float(err.max()),
            "albedo_min": float(alb0.min()),
            "albedo_max": float(alb0.max()),
            "nbytes": self.nbytes(),
        }


# ---------------------------------------------------------------------------------------------
# Assembly from per-direction histograms
# ---------------------------------------------------------------------------------------------

def band_rows(row_mass: np.ndarray, tail: float) -> tuple[int, int]:
    """Smallest [lo, hi) of rows keeping all but ``tail`` of ``row_mass`` (sums to ~1)."""
    n = len(row_mass)
    total = float(row_mass.sum())
    if total <= 0.0:
        return 0, 1
    c = np.cumsum(row_mass) / total
    half = 0.5 * float(tail)
    lo = int(np.searchsorted(c, half, side="right"))
    # rows beyond hi carry at most tail/2
    rc = np.cumsum(row_mass[::-1]) / total
    hi = n - int(np.searchsorted(rc, half, side="right"))
    lo = min(lo, n - 1)
    hi = max(hi, lo + 1)
    return lo, hi


def assemble(grid: Grid, levels: Sequence[float], n_slices: tuple[int, int],
             load_slice: Callable[[int, int], Mapping[str, Any]], width: np.ndarray,
             header: Mapping[str, Any], *, band_tail: float = 1e-5,
             storage: str = "float16") -> BcsdfTable:
    """Build a table from per-direction histograms (the baker's chunks).

    ``load_slice(ti, pi)`` returns a mapping with ``rows`` (r0, r1): the theta_o rows held;
    ``H`` (K, r1 - r0, n_po): sum of exp(-s_k L) over each bin's photons; ``G``: sum of
    L exp(-s_k L); ``norm``: the photons meeting the fiber (divisor); ``rel_error``;
    ``photons``. Two passes: the bands, then the arrays.
    """
    if storage not in ("float16", "float32"):
        raise ValueError("storage must be 'float16' or 'float32'")
    lv = np.asarray(levels, dtype=np.float64)
    K = len(lv)
    n_ti, n_pi = n_slices
    n_r, n_c = grid.n_theta_o, grid.n_phi_o
    dom = grid.solid_angles()

    bands = np.zeros((n_ti, n_pi, 2), dtype=np.int64)
    for ti in range(n_ti):
        for pi in range(n_pi):
            sl = load_slice(ti, pi)
            r0, r1 = sl["rows"]
            H = np.asarray(sl["H"], dtype=np.float64)
            mass = np.zeros(n_r)
            for k in range(K):
                rm = H[k].sum(axis=-1)
                t = rm.sum()
                if t > 0:
                    mass[r0:r1] = np.maximum(mass[r0:r1], rm / t)
            lo, hi = band_rows(mass, band_tail)
            bands[ti, pi] = (lo, hi)
    n_band = int(max(1, (bands[..., 1] - bands[..., 0]).max()))
    start = np.clip(bands[..., 0] - (n_band - (bands[..., 1] - bands[..., 0])) // 2, 0, n_r - n_band)

    dt = np.float16 if storage == "float16" else np.float32
    p_arr = np.zeros((n_ti, n_pi, K, n_band, n_c), dtype=dt)
    l_arr = np.zeros((n_ti, n_pi, K, n_band, n_c), dtype=dt)
    p_scale = np.zeros((n_ti, n_pi, K), dtype=np.float32)
    albedo = np.zeros((n_ti, n_pi, K), dtype=np.float32)
    albedo_l = np.zeros((n_ti, n_pi, K), dtype=np.float32)
    rel_error = np.zeros((n_ti, n_pi), dtype=np.float32)
    photons = np.zeros((n_ti, n_pi), dtype=np.int64)
    q_num = np.zeros(K)
    q_den = np.zeros(K)
    dropped = 0.0
    for ti in range(n_ti):
        for pi in range(n_pi):
            sl = load_slice(ti, pi)
            r0, r1 = sl["rows"]
            norm = float(sl["norm"])
            Hf = np.zeros((K, n_r, n_c))
            Gf = np.zeros((K, n_r, n_c))
            Hf[:, r0:r1] = np.asarray(sl["H"], dtype=np.float64)
            Gf[:, r0:r1] = np.asarray(sl["G"], dtype=np.float64)
            b0 = int(start[ti, pi])
            band = slice(b0, b0 + n_band)
            for k in range(K):
                tot_h = Hf[k].sum()
                albedo[ti, pi, k] = tot_h / norm if norm > 0 else 0.0
                albedo_l[ti, pi, k] = Gf[k].sum() / tot_h if tot_h > 0 else 0.0
                Fb = Hf[k, band]
                fb = Fb.sum()
                if k == 0 and tot_h > 0:
                    dropped = max(dropped, 1.0 - fb / tot_h)
                if fb <= 0:
                    continue
                p = Fb / fb / dom[band, None]
                m = p.max()
                p_scale[ti, pi, k] = m
                q = (p / m).astype(dt)
                p_arr[ti, pi, k] = q
                with np.errstate(invalid="ignore", divide="ignore"):
                    lb = np.where(Fb > 0, Gf[k, band] / np.where(Fb > 0, Fb, 1.0), 0.0)
                l_arr[ti, pi, k] = lb.astype(dt)
                # quantization error of the stored p (relative L2 over the sphere)
                err = q.astype(np.float64) * m - p
                w = dom[band, None]
                q_num[k] += float((w * err ** 2).sum())
                q_den[k] += float((w * p ** 2).sum())
            rel_error[ti, pi] = float(sl["rel_error"])
            photons[ti, pi] = int(sl["photons"])

    hdr = dict(header)
    hdr["layout"] = {"name": LAYOUT, "version": LAYOUT_VERSION,
                     "arrays": {
                         "p": "p at level k / p_scale, (theta_i, phi_i, level, band row, phi_o)",
                         "p_scale": "max of p per (theta_i, phi_i, level)",
                         "lbar": "exp(-s_k L)-weighted mean path length per bin, um at the baked size",
                         "band_start": "first theta_o row of the band per (theta_i, phi_i)",
                         "albedo": "Lambda per (theta_i, phi_i, level)",
                         "albedo_lbar": "-d log Lambda / d s per (theta_i, phi_i, level), um",
                         "levels": "absorption levels s_k, 1/um at the baked size",
                         "width": "W(phi) at phi = 360 j / n_w deg, um at the baked size",
                         "rel_error": "relative L2 error of p per incoming direction (sigma_a = 0)",
                         "photons": "photons traced per incoming direction"}}
    hdr["resolution"] = grid.to_header()
    hdr["levels"] = [float(x) for x in lv]
    hdr["band"] = {"rows": n_band, "tail": float(band_tail), "max_dropped_mass": float(dropped)}
    hdr["storage"] = storage
    with np.errstate(invalid="ignore", divide="ignore"):
        qe = np.sqrt(np.where(q_den > 0, q_num / np.where(q_den > 0, q_den, 1.0), 0.0))
    hdr["quantization_error"] = {"metric": "relative L2 of stored p vs float64, per level",
                                 "per_level": [float(x) for x in qe]}
    arrays = {
        "p": p_arr, "p_scale": p_scale, "lbar": l_arr,
        "band_start": start.astype(np.int16), "albedo": albedo, "albedo_lbar": albedo_l,
        "levels": lv, "width": np.asarray(width, dtype=np.float32), "rel_error": rel_error,
        "photons": photons,
    }
    return BcsdfTable(header=hdr, arrays=arrays)


def describe_layout() -> str:
    """The module docstring's storage section (for ``usdfiber table inspect``)."""
    doc = __doc__ or ""
    i = doc.find("Storage (")
    j = doc.find("Sampling needs")
    return doc[i:j].strip() if i >= 0 else ""


def header_json(table: BcsdfTable) -> str:
    return json.dumps(table.header, indent=2, sort_keys=True)
