"""The far field of a whole yarn, for yarns too small on screen to resolve their fibers.

A yarn a pixel or two wide is an aggregate: many fibers, each scattering light as its table
says, light bouncing between them. Seen from afar it is itself a "fiber" with a far-field
scattering function, exactly as a fiber is an aggregate of refractions inside its cross
section (the paper's Section 3; its Figure 8 shows that averaged BCSDFs keep a yarn's look).
This module measures that function by the same brute-force photon tracing as the baker, one
level up: the photons walk through the yarn's expanded fibers (:mod:`usdfiber.geometry.yarn`), and every
interaction with a fiber samples the fiber's own tabulated BCSDF (the renderer's
:mod:`.fiber_bsdf`: its variants, random rotations psi, colour and pass-through). The result,
a :class:`YarnFarField`, has the layout of a rotationally symmetric fiber table, so the
renderer draws a far yarn as ONE curve of the yarn's bounding width with it.

Frame and set-up (yarn frame: t = +z the yarn axis, like a fiber table's fiber frame):

* A straight piece of the yarn of length ``Lz`` (a whole number of ply twists, several yarn
  diameters), scaled so that its bounding radius ``R_b`` (largest distance of a fiber's
  surface from the axis, flyaways included) is 1. The piece is periodic along z: a photon
  crossing an end re-enters at the other. The helical structure makes a straight yarn's far
  field, averaged over its length, depend on ``phi_o - phi_i`` only (a rotation about the
  axis is a shift along it), so the table is rotationally symmetric.
* Several such pieces (``YarnBakeSettings.realizations``, :func:`far_field_pieces`), each its
  own random placement of the fibers, scaled to one ``R_b``, share the photons: the far field
  is the structure's, shared by every yarn of it, and one placement of a few dozen fibers is
  not (its projected width varies by about 5 % from seed to seed).
* A beam from ``omega_i`` = (theta_i, phi_i) over the whole projected bounding width ``2 R_b``
  (phi_i and the axial position uniformly random). A photon that leaves the bounding cylinder
  without having scattered (missed every fiber, or only passed through profiles narrower than
  their curves) is unscattered light: it belongs to the transparency of the yarn, the
  ``coverage(theta_i)`` = fraction of the beam that scatters at least once. The others leave,
  after any number of fiber interactions, into a direction binned as ``omega_o`` in the yarn
  frame, with the throughput (RGB) of their fiber interactions.

Then, as for a fiber table with ``W = 2 R_b coverage(theta)``: ``Lambda(theta_i)`` (RGB) is
the throughput leaving over the photons that scattered, ``p(omega_o | omega_i)`` (RGB, per
steradian) where it leaves. Unlike an extruded fiber's ``W(phi)``, the coverage depends on
theta (grazing rays cross more of the yarn): the renderer's pass-through uses it as the
probability that a ray meeting the yarn's tube interacts.

Colour: traced once, recoloured per dye (as a fiber table is, :mod:`usdfiber.bake.absorption`).
Every fiber of a yarn carries the yarn's dye, so the far field is a function of one optical
depth per colour channel, ``s = sigma_a D`` of its fibers. Fiber scattering is sampled from the
fiber tables' undyed densities whatever the colour (:mod:`.fiber_bank`), so a photon's path does
not depend on ``s``; only its weight does, the product over its fiber interactions of each
table's ``Lambda_s p_s / p_0``. One trace therefore carries the weights at all the absorption
levels ``YarnBakeSettings.levels`` at once (one fiber BSDF per three levels, all drawing the
same direction from the same random numbers), and :meth:`YarnFarField.recolour` interpolates
``log F`` of each bin between the levels (cubic Hermite with slopes from the neighbouring
levels) for any colour: a dye change costs milliseconds, not a trace.

Approximations, on purpose: the yarn is straight and infinitely long at the scale of its
far field (curvature and neighbours are left to the renderer's path tracing between yarn
curves); the periodic wrap joins the two ends of the piece, which need not match exactly.
"""
from __future__ import annotations

import hashlib
import json
import math
import time as _time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from usdfiber import table_format
from usdfiber.bake.absorption import DEFAULT_LEVELS, hermite_log_interp, level_bracket
from usdfiber.bake.cache import load_or_make
from usdfiber.bake.grid import Grid
from usdfiber.bake.table import Recoloured

__all__ = ["YARN_LEVELS", "YarnBakeSettings", "YarnFarField", "YarnFarFieldCache", "bake_yarn_far_field",
           "far_field_entry", "far_field_pieces", "trace_far_field", "yarn_piece"]

FORMAT_KIND = "usdfiber-yarn-far-field"
#: 3: traced through several realizations of the yarn (2: one; 1 held one traced colour).
FORMAT_VERSION = 3
#: Optical depths across a fiber (``sigma_a D``) at which far fields are traced: the fiber
#: tables' levels and one more, twelve, so that four RGB fiber BSDFs carry them.
YARN_LEVELS: tuple[float, ...] = DEFAULT_LEVELS + (128.0,)
_TWO_PI = 2.0 * math.pi
_MAX_WRAPS = 64


@dataclass(frozen=True)
class YarnBakeSettings:
    """How a yarn's far field is traced.

    ``resolution_deg``: bin size (divides 90); ``photons``: photons per theta_i node;
    ``batches``: independent batches for the error estimate; ``max_bounces``: fiber
    interactions after which a photon is dropped (its energy is reported as lost);
    ``length_diameters``: the periodic piece's length in bounding diameters (rounded up to a
    whole number of ply twists); ``samples_per_turn``: of the yarn expansion; ``seed``;
    ``levels``: the fibers' optical depths traced (start at 0, increase, a multiple of three);
    ``realizations``: pieces expanded with seeds ``seed``, ``seed + 1`` ... that share the
    photons (:func:`far_field_pieces`): one random placement of a yarn's fibers is not its
    structure's (the projected width of a 24-fiber Skala 360 piece varies by 5 % from seed to
    seed; one seed was 8.5 % under the mean, and the far field 6 % too light in attenuation and
    reflection against the fibers, bench/REPORT.md, "The far field on a sheer weave").
    """

    resolution_deg: float = 6.0
    photons: int = 40_000
    batches: int = 4
    max_bounces: int = 512
    length_diameters: float = 6.0
    samples_per_turn: int = 12
    seed: int = 1
    levels: tuple[float, ...] = YARN_LEVELS
    realizations: int = 8

    def __post_init__(self) -> None:
        Grid(self.resolution_deg, False, True)
        if self.realizations < 1:
            raise ValueError(f"yarn bake: realizations >= 1, got {self.realizations}")
        if self.photons < self.batches or self.batches < 2:
            raise ValueError("yarn bake needs batches >= 2 and photons >= batches")
        if self.max_bounces < 1 or self.length_diameters <= 0 or self.samples_per_turn < 3:
            raise ValueError("yarn bake: max_bounces >= 1, length_diameters > 0, samples_per_turn >= 3")
        lv = tuple(float(x) for x in self.levels)
        if (not lv or lv[0] != 0.0 or len(lv) % 3 or any(b <= a for a, b in zip(lv, lv[1:]))
                or not all(map(math.isfinite, lv))):
            raise ValueError(f"yarn bake: levels must start at 0, increase and come in threes, got {list(lv)}")
        object.__setattr__(self, "levels", lv)


@dataclass
class YarnFarField:
    """A yarn's tabulated far field: the layout of a rotationally symmetric fiber table.

    Duck-types the parts of :class:`usdfiber.bake.table.BcsdfTable` the renderer's
    :class:`~usdfiber.translators.mitsuba.fiber_bank.FiberBank` reads (``grid``, ``band_start``,
    ``arrays["width"]``, ``baked_diameter_um``, ``recolour``, ``forget_recolourings``). Arrays:

    ``p`` (n_ti, 1, n_to, n_po, C) float32 per steradian, each channel's slice integrating to
    1; ``albedo`` (n_ti, 1, C); ``levels`` (C,), when present: channel k was traced with the
    fibers at optical depth ``levels[k]`` and :meth:`recolour` interpolates between them
    (without it the C = 3 channels are one traced colour, which :meth:`recolour` returns
    whatever it is given); ``coverage`` (n_ti,) at the theta_i nodes; ``width`` (1,) = 1
    (W / D is 1: the transparency is ``coverage``); ``rel_error`` (n_ti, 1) relative L2 error
    of p (of the first level, or the channel mean) from independent batches; ``photons``
    (n_ti, 1); ``lost`` (n_ti,) fraction of the scattered energy dropped at ``max_bounces``.
    """

    header: dict[str, Any]
    arrays: dict[str, np.ndarray]
    path: str | None = None
    _rec: Recoloured | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        res = self.header["resolution"]
        # The incoming (theta_i) nodes may be coarser than the bins (usdfiber.bake.grid).
        self.grid = Grid(float(res["deg"]), False, True, res.get("incoming_deg"))
        g = self.grid
        p = self.arrays["p"]
        C = len(self.arrays["levels"]) if "levels" in self.arrays else 3
        if p.shape != (g.n_theta_i, 1, g.n_theta_o, g.n_phi_o, C):
            raise table_format.TableError(self.path or "yarn far field", f"array p has shape {p.shape}")
        for name, shape in (("albedo", (g.n_theta_i, 1, C)), ("coverage", (g.n_theta_i,))):
            if self.arrays[name].shape != shape:
                raise table_format.TableError(self.path or "yarn far field",
                                              f"array {name} has shape {self.arrays[name].shape}")
        self.band_start = np.zeros((g.n_theta_i, 1), np.int16)

    @property
    def baked_diameter_um(self) -> float:
        return 1.0

    @property
    def coverage(self) -> np.ndarray:
        return self.arrays["coverage"]

    def coverage_at(self, theta: np.ndarray) -> np.ndarray:
        """coverage(theta) (radians), linear between the theta_i nodes, constant beyond."""
        return np.interp(np.asarray(theta, np.float64), self.grid.theta_i_nodes(), self.coverage)

    @property
    def recolourable(self) -> bool:
        """Whether the far field was traced at absorption levels (any colour), or in one colour."""
        return "levels" in self.arrays

    def recolour(self, sigma_a_rgb_per_um: Any = 0.0, diameter_scale: float = 1.0) -> Recoloured:
        """The far field with the yarn's fibers at optical depth ``sigma_a * diameter_scale``
        per channel (a number or RGB; the fiber tables' effective absorption, 1/um at their
        baked size of 1 um): interpolated between the traced levels. A far field traced in one
        colour returns that colour whatever it is given."""
        if not self.recolourable:
            if self._rec is None:
                self._rec = Recoloured(self, np.zeros(3), self.arrays["p"].astype(np.float32),  # type: ignore[arg-type]
                                       self.arrays["albedo"].astype(np.float32))
            return self._rec
        s = np.broadcast_to(np.asarray(sigma_a_rgb_per_um, np.float64) * float(diameter_scale), (3,))
        cache = self.__dict__.setdefault("_colours", {})
        key = tuple(float(x) for x in s)
        if key not in cache:
            p, albedo = zip(*(self._channel(x) for x in key))
            cache[key] = Recoloured(self, np.array(key), np.stack(p, -1).astype(np.float32),  # type: ignore[arg-type]
                                    np.stack(albedo, -1).astype(np.float32))
        return cache[key]

    def forget_recolourings(self) -> None:
        """Drop the colours :meth:`recolour` cached (as
        :meth:`usdfiber.bake.table.BcsdfTable.forget_recolourings`): the renderer's fiber bank
        calls it once it has laid them out."""
        self.__dict__.pop("_colours", None)

    def _channel(self, s: float) -> tuple[np.ndarray, np.ndarray]:
        """(p (n_ti, 1, n_to, n_po), albedo (n_ti, 1)) at optical depth ``s``: each bin's mass
        ``F = albedo p domega`` and the albedo interpolated in ``log`` between the levels
        around ``s`` (:func:`usdfiber.bake.absorption.hermite_log_interp`, the tangent beyond
        the last), with slopes ``d log F / ds`` from the neighbouring levels."""
        lv = np.asarray(self.arrays["levels"], np.float64)
        dom = self.grid.solid_angles()[None, None, :, None]
        albedo = np.moveaxis(self.arrays["albedo"].astype(np.float64), -1, 0)          # (K, n_ti, 1)
        F = np.moveaxis(self.arrays["p"].astype(np.float64), -1, 0) * dom * albedo[..., None, None]
        k = level_bracket(lv, s)
        ks = [k] if k == len(lv) - 1 or s == lv[k] else [k, k + 1]
        f = [hermite_log_interp(lv, s, *_level_pair(lv, a, ks), k) for a in (F, albedo)]
        mass = f[0]
        tot = mass.sum(axis=(-2, -1), keepdims=True)
        p = np.where(tot > 0, mass / np.where(tot > 0, tot, 1.0), 0.0) / dom
        return p, f[1]

    def domega_band(self) -> np.ndarray:
        g = self.grid
        return np.broadcast_to(g.solid_angles(), (g.n_theta_i, 1, g.n_theta_o))

    def save(self, path: str | Path) -> None:
        self.header = table_format.write_table(path, self.header, self.arrays)
        self.path = str(path)

    @classmethod
    def load(cls, path: str | Path) -> "YarnFarField":
        header, arrays = table_format.read_table(path)
        if header.get("kind") != FORMAT_KIND or header.get("kind_version") != FORMAT_VERSION:
            raise table_format.TableError(path, f"not a yarn far field of version {FORMAT_VERSION}")
        return cls(header, arrays, str(path))


def _log_slope(lv: np.ndarray, v: np.ndarray, k: int) -> np.ndarray:
    """``-d log v / ds`` at level ``k`` (``v``: (K, ...) values at the levels): the three-point
    derivative of ``log v`` on the uneven levels where both neighbours hold light, one-sided at
    the ends or beside an empty level, 0 where level ``k`` is empty; never negative (``log F``
    of a bin decreases with the absorption)."""
    def log(x: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(x > 0, np.log(np.where(x > 0, x, 1.0)), np.nan)

    y = log(v[k])
    lo = (y - log(v[k - 1])) / (lv[k] - lv[k - 1]) if k > 0 else np.full_like(y, np.nan)
    hi = (log(v[k + 1]) - y) / (lv[k + 1] - lv[k]) if k + 1 < len(lv) else np.full_like(y, np.nan)
    if 0 < k < len(lv) - 1:
        hm, hp = lv[k] - lv[k - 1], lv[k + 1] - lv[k]
        both = (hm * hi + hp * lo) / (hm + hp)
    else:
        both = np.full_like(y, np.nan)
    d = np.where(np.isfinite(both), both, np.where(np.isfinite(lo), lo, np.where(np.isfinite(hi), hi, 0.0)))
    return np.maximum(-d, 0.0)


def _level_pair(lv: np.ndarray, v: np.ndarray, ks: list[int]) -> tuple:
    """(value, slope) at level ``ks[0]`` and, with two levels, at ``ks[1]`` (else None, None):
    the arguments :func:`usdfiber.bake.absorption.hermite_log_interp` takes."""
    out: list[Any] = []
    for k in ks:
        out += [v[k], _log_slope(lv, v, k)]
    return tuple(out + [None, None] * (2 - len(ks)))


# ---------------------------------------------------------------------------------------------
# The periodic piece
# ---------------------------------------------------------------------------------------------

@dataclass
class YarnPiece:
    """Fiber curves of a straight yarn piece in the yarn frame, scaled to ``R_b = 1``."""

    geometry: Any             # CurveGeometry
    length: float             # Lz, in units of R_b
    bound_radius: float       # R_b in scene units (the scale divided out)
    fibers: int


def yarn_piece(params: Any, fiber_diameter: float, settings: YarnBakeSettings, seed_offset: int = 0) -> YarnPiece:
    """Expand a straight piece of the yarn ``params`` (scene units) for :func:`trace_far_field`.

    The piece is ``length_diameters`` bounding diameters long, rounded up to whole ply twists
    (whole fiber twists for one ply), and expanded beyond both ends so that the curves' end
    segments lie outside it (the tracer only sees the fibers between the ends; staple fibers
    still end inside, as they do in the yarn).
    """
    from usdfiber.geometry.yarn import expand_yarn

    r_guess = params.max_fiber_distance + 0.5 * fiber_diameter
    lz = settings.length_diameters * 2.0 * r_guess
    twist = abs(params.ply_twist) if params.plies > 1 else abs(params.fiber_twist)
    if twist > 0:
        lz = math.ceil(lz * twist - 1e-9) / twist
    margin = 2.0 * r_guess + 0.1 * lz
    z = np.linspace(-margin, lz + margin, 64)
    centre = np.stack([np.zeros_like(z), np.zeros_like(z), z], axis=1)
    ex = expand_yarn(centre, 1.0, params, samples_per_turn=settings.samples_per_turn, seed_offset=seed_offset)
    geom = ex.to_curve_geometry(fiber_diameter)
    # Bounding radius over the part inside the piece (control points bound the B-spline).
    inside = (geom.points[:, 2] > -r_guess) & (geom.points[:, 2] < lz + r_guess)
    rb = float(np.max(np.hypot(geom.points[inside, 0], geom.points[inside, 1]))) + 0.5 * fiber_diameter
    geom.points = geom.points / rb
    geom.radii = geom.radii / rb
    return YarnPiece(geom, lz / rb, rb, ex.curve_count)


def far_field_pieces(params: Any, fiber_diameter: float, settings: YarnBakeSettings) -> list[YarnPiece]:
    """``settings.realizations`` pieces of the yarn (:func:`yarn_piece`, seeds ``settings.seed``,
    ``settings.seed + 1`` ...), scaled to one bounding radius, the largest of theirs, so that
    one cylinder bounds them all and their coverages are fractions of one width."""
    pieces = [yarn_piece(replace(params, seed=settings.seed + k), fiber_diameter, settings)
              for k in range(settings.realizations)]
    rb = max(pc.bound_radius for pc in pieces)
    out = []
    for pc in pieces:
        f = pc.bound_radius / rb
        geom = pc.geometry
        geom.points = geom.points * f
        geom.radii = geom.radii * f
        out.append(YarnPiece(geom, pc.length * f, rb, pc.fibers))
    return out


# ---------------------------------------------------------------------------------------------
# Photon tracing
# ---------------------------------------------------------------------------------------------

def _cylinder_exit(ox, oy, dx, dy):
    """Distance along (dx, dy) from (ox, oy) inside the unit circle to its boundary."""
    a = dx * dx + dy * dy
    b = ox * dx + oy * dy
    c = ox * ox + oy * oy - 1.0
    disc = np.maximum(b * b - a * c, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(a > 1e-14, (-b + np.sqrt(disc)) / np.where(a > 1e-14, a, 1.0), np.inf)
    return np.maximum(t, 0.0)


def trace_far_field(piece: YarnPiece | Sequence[YarnPiece], bsdf: Any, settings: YarnBakeSettings,
                    progress: Callable[[int, int], None] | None = None,
                    header: dict[str, Any] | None = None,
                    levels: Sequence[float] | None = None) -> YarnFarField:
    """Trace ``settings.photons`` photons per theta_i node through ``piece`` whose fibers
    scatter with ``bsdf`` (a :func:`~usdfiber.translators.mitsuba.fiber_bsdf.fiber_bsdf` for the
    piece's segments) and tabulate the far field (module docstring). ``piece`` may be a list of
    pieces of one bounding radius (:func:`far_field_pieces`), ``bsdf`` then a list of as many
    (one BSDF or list of BSDFs each): batch b traces its photons through pieces b, b + B ...

    ``bsdf`` may be a list of such BSDFs over tables with the same sampling densities (the
    same tables in other colours): the first draws every direction, each gives the weights
    of its three channels for the same random numbers, so the far field has three channels
    per BSDF, one path for all. ``levels`` names the optical depth of each channel (a far
    field :meth:`YarnFarField.recolour` interpolates); without it the channels are one
    colour."""
    from usdfiber.backend import mitsuba
    from usdfiber.translators.mitsuba.curves import make_curve_shape

    mi = mitsuba()
    import drjit as dr

    # One set of BSDFs per piece (realization); each set is one BSDF or a list of them.
    pieces = [piece] if isinstance(piece, YarnPiece) else list(piece)
    sets = [bsdf] if isinstance(piece, YarnPiece) else list(bsdf)
    if len(sets) != len(pieces) or not pieces:
        raise ValueError(f"{len(sets)} BSDF sets for {len(pieces)} yarn pieces")
    sets = [list(s) if isinstance(s, (list, tuple)) else [s] for s in sets]
    bsdfs = sets[0]
    C = 3 * len(bsdfs)
    if levels is not None and len(levels) != C:
        raise ValueError(f"{len(levels)} levels for {C} traced channels")
    g = Grid(settings.resolution_deg, False, True)
    n_ti, n_to, n_po = g.n_theta_i, g.n_theta_o, g.n_phi_o
    step = g.step
    th_nodes = g.theta_i_nodes()
    scenes = [mi.load_dict({"type": "scene", "yarn": make_curve_shape(pc.geometry, s[0], "yarn_piece")})
              for pc, s in zip(pieces, sets)]
    ctx = mi.BSDFContext()
    rng = np.random.default_rng(settings.seed)
    K = len(pieces)
    B = settings.batches
    per_batch = -(-settings.photons // B)
    n_bins = n_ti * n_to * n_po
    hist = np.zeros((B, C, n_bins))
    scattered = np.zeros((B, n_ti))
    lost = np.zeros((B, n_ti, C))
    launched = np.zeros((B, n_ti))
    lanes = 1 << 18
    # Batch b traces its photons through the pieces k = b (mod B), in equal shares (or through
    # piece b mod K when there are fewer pieces than batches).
    shares = [[k for k in range(K) if k % B == b] or [b % K] for b in range(B)]
    per_piece = [-(-per_batch // len(s)) for s in shares]
    total = sum(n_ti * per_piece[b] * len(shares[b]) for b in range(B))
    done = 0
    for b in range(B):
        for k in shares[b]:
            scene, bsdfs, lz = scenes[k], sets[k], pieces[k].length
            ti_all = np.repeat(np.arange(n_ti), per_piece[b])
            for start in range(0, len(ti_all), lanes):
                ti = ti_all[start:start + lanes]
                n = len(ti)
                th = th_nodes[ti]
                ph = rng.uniform(0.0, _TWO_PI, n)
                cp, sp = np.cos(ph), np.sin(ph)
                # The beam covers the projected bounding width and enters at the cylinder.
                u = rng.uniform(-1.0, 1.0, n)
                h = np.sqrt(np.maximum(1.0 - u * u, 0.0))
                o = np.stack([-u * sp + h * cp, u * cp + h * sp, rng.uniform(0.0, lz, n)], axis=1)
                d = -np.stack([np.cos(th) * cp, np.cos(th) * sp, np.sin(th)], axis=1)
                thr = np.ones((n, C))
                hit_once = np.zeros(n, bool)
                bounces = np.zeros(n, np.int64)
                wraps = np.zeros(n, np.int64)
                np.add.at(launched[b], ti, 1.0)
                while n:
                    t_cyl = _cylinder_exit(o[:, 0], o[:, 1], d[:, 0], d[:, 1])
                    dz = d[:, 2]
                    safe = np.where(np.abs(dz) > 1e-12, dz, 1.0)
                    t_z = np.where(dz > 1e-12, (lz - o[:, 2]) / safe, np.where(dz < -1e-12, -o[:, 2] / safe, np.inf))
                    t_z = np.maximum(t_z, 0.0)
                    maxt = np.minimum(np.minimum(t_cyl, t_z), 1e30)
                    ray = mi.Ray3f(mi.Point3f(*(mi.Float(o[:, k].astype(np.float32)) for k in range(3))),
                                   mi.Vector3f(*(mi.Float(d[:, k].astype(np.float32)) for k in range(3))))
                    ray.maxt = mi.Float(maxt.astype(np.float32))
                    si = scene.ray_intersect(ray)
                    dr.eval(si)
                    valid = np.array(si.is_valid(), bool)
                    # A photon leaving the bounding cylinder has left the yarn; one reaching an end
                    # of the piece re-enters at the other (a nearly axial one that keeps wrapping
                    # without meeting a fiber is taken as leaving).
                    miss = ~valid
                    esc = miss & ((t_cyl <= t_z) | (wraps >= _MAX_WRAPS))
                    wrap = miss & ~esc
                    rec = esc & hit_once
                    if np.any(rec):
                        dd = d[rec]
                        tho = np.arcsin(np.clip(dd[:, 2], -1.0, 1.0))
                        dphi = np.mod(np.arctan2(dd[:, 1], dd[:, 0]) - ph[rec] + 0.5 * step, _TWO_PI)
                        row = np.clip(np.floor((tho + 0.5 * math.pi) / step).astype(np.int64), 0, n_to - 1)
                        col = np.floor(dphi / step).astype(np.int64) % n_po
                        flat = ti[rec] * (n_to * n_po) + row * n_po + col
                        for c in range(C):
                            hist[b, c] += np.bincount(flat, weights=thr[rec, c], minlength=n_bins)
                    dead = np.zeros(n, bool)
                    if np.any(valid):
                        u1 = mi.Float(rng.random(n).astype(np.float32))
                        u2 = mi.Point2f(mi.Float(rng.random(n).astype(np.float32)),
                                        mi.Float(rng.random(n).astype(np.float32)))
                        bs, w = bsdfs[0].sample(ctx, si, u1, u2, mi.Bool(valid))
                        # The other colours' weights of the same direction (same numbers, same
                        # sampling density): one path carries every channel.
                        ws = [w] + [other.sample(ctx, si, u1, u2, mi.Bool(valid))[1] for other in bsdfs[1:]]
                        wo = si.to_world(bs.wo)
                        dr.eval(bs, ws, wo)   # one kernel, not one per converted component
                        null = np.array(bs.sampled_type, np.uint32) == int(mi.BSDFFlags.Null)
                        ok = valid & (np.array(bs.pdf) > 0)
                        wv = np.stack([np.array(wk[k], np.float64) for wk in ws for k in range(3)], axis=1)
                        won = np.stack([np.array(wo[k], np.float64) for k in range(3)], axis=1)
                        pn = np.stack([np.array(si.p[k], np.float64) for k in range(3)], axis=1)
                        thr[ok] *= wv[ok]
                        hit_once |= ok & ~null
                        bounces += ok & ~null
                        # A failed sample is an interaction that keeps nothing.
                        dead = valid & ~ok
                        hit_once |= dead
                        newd = np.where(null[:, None], d, won)
                        newd /= np.linalg.norm(newd, axis=1, keepdims=True)
                        # Continue from the hit; Mitsuba's curves are not hit from inside, so a
                        # ray entering a fiber's tube leaves it without meeting it again.
                        o = np.where(ok[:, None], pn + 1e-5 * newd, o)
                        d = np.where(ok[:, None], newd, d)
                    if np.any(wrap):
                        ow = o[wrap] + t_z[wrap, None] * d[wrap]
                        ow[:, 2] = np.where(d[wrap, 2] > 0, 0.0, lz)
                        o[wrap] = ow
                        wraps += wrap
                    over = bounces > settings.max_bounces
                    if np.any(over):
                        np.add.at(lost[b], ti[over], thr[over])
                    black = np.max(thr, axis=1) <= 0
                    gone = esc | dead | over | black
                    np.add.at(scattered[b], ti[gone & hit_once], 1.0)
                    keep = ~gone
                    o, d, thr, hit_once = o[keep], d[keep], thr[keep], hit_once[keep]
                    bounces, wraps, ti, ph = bounces[keep], wraps[keep], ti[keep], ph[keep]
                    n = len(ti)
                done += len(ti_all[start:start + lanes])
                if progress is not None:
                    progress(done, total)
    return _assemble(g, hist, scattered, launched, lost, settings, header or {}, levels)


def _assemble(g: Grid, hist: np.ndarray, scattered: np.ndarray, launched: np.ndarray, lost: np.ndarray,
              settings: YarnBakeSettings, header: dict[str, Any],
              levels: Sequence[float] | None = None) -> YarnFarField:
    """The table from per-batch histograms ``hist`` (B, C, n_ti * n_to * n_po)."""
    n_ti, n_to, n_po = g.n_theta_i, g.n_theta_o, g.n_phi_o
    dom = np.repeat(g.solid_angles(), n_po)                            # per bin of a slice
    B, C = hist.shape[:2]
    Hb = hist.reshape(B, C, n_ti, n_to * n_po)
    H = Hb.sum(axis=0)                                                 # (C, n_ti, bins)
    S = scattered.sum(axis=0)                                          # photons that scattered
    N = launched.sum(axis=0)
    L = lost.sum(axis=0)                                               # (n_ti, 3)
    tot = H.sum(axis=-1)                                               # (C, n_ti) throughput out

    def ratio(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.where(b > 0, a / np.where(b > 0, b, 1.0), 0.0)

    p = ratio(H, tot[..., None]) / dom                                  # per steradian
    albedo = ratio(tot, S[None, :])                                    # (C, n_ti)
    coverage = ratio(S, N)
    lost_frac = ratio(L.mean(axis=1), tot.mean(axis=0) + L.mean(axis=1))
    # Relative L2 error of p (channel mean, or the first level) from the spread of the
    # independent batches.
    hm = Hb.mean(axis=1) if levels is None else Hb[:, 0]               # (B, n_ti, bins)
    pb = ratio(hm, hm.sum(axis=-1, keepdims=True)) / dom
    pm = pb.mean(axis=0)
    var = ((pb - pm) ** 2).sum(axis=0) / ((B - 1) * B)
    rel = np.sqrt(ratio((dom * var).sum(axis=-1), (dom * pm ** 2).sum(axis=-1)))
    hdr = dict(header)
    hdr.update({
        "kind": FORMAT_KIND, "kind_version": FORMAT_VERSION,
        "resolution": {"deg": g.resolution_deg, "theta_i": n_ti, "theta_o": n_to, "phi_o": n_po,
                       "rotationally_symmetric": True, "theta_symmetric": False,
                       **({} if g.incoming_deg is None else {"incoming_deg": g.incoming_deg})},
        "photons": int(N.max()),
        "error_estimate": {"metric": "relative L2 of p per theta_i (channel mean, or the first level), from independent batches",
                           "max": float(np.max(rel)), "median": float(np.median(rel))},
        "settings": asdict(settings),
        "lost_energy_max": float(np.max(lost_frac)),
    })
    hdr.setdefault("geometry_key", "")
    hdr.setdefault("inputs", {})
    arrays = {
        "p": np.moveaxis(p.reshape(C, n_ti, n_to, n_po), 0, -1)[:, None].astype(np.float32),
        "albedo": albedo.T[:, None].astype(np.float32),
        "coverage": coverage.astype(np.float32),
        "width": np.ones(1, np.float32),
        "rel_error": rel[:, None].astype(np.float32),
        "photons": N[:, None].astype(np.int64),
        "lost": lost_frac.astype(np.float32),
    }
    if levels is not None:
        arrays["levels"] = np.asarray(levels, np.float64)
        hdr["recolourable"] = True
    return YarnFarField(hdr, arrays)


# ---------------------------------------------------------------------------------------------
# A yarn prim's far field, baked on demand and cached
# ---------------------------------------------------------------------------------------------

def far_field_inputs(params: Any, fiber_diameter: float, slots: Sequence[Any],
                     settings: YarnBakeSettings) -> dict[str, Any]:
    """Everything the far field depends on (the cache key's content): the yarn's structure in
    metres, the fiber diameter, each fiber variant's table and the settings (with the
    absorption levels). Not the fibers' colour: a far field is recoloured, so every dye and
    depth of shade of one yarn shares it."""
    mpu = float(params.meters_per_unit)
    # Not the yarn's seed either: the far field averages over the fibers' placement, so yarns
    # of one structure share it (the piece is expanded with a seed of its own).
    skip = {"prim_path", "expand", "linear_density", "fiber_diameter", "meters_per_unit", "seed"}
    yarn = {}
    for k, v in asdict(params).items():
        if k in skip:
            continue
        yarn[k] = [float(x) for x in v] if isinstance(v, (tuple, list)) else v
    return {
        "kind": FORMAT_KIND, "kind_version": FORMAT_VERSION,
        "meters_per_unit": mpu,
        "yarn": yarn,
        "fiber_diameter": float(fiber_diameter),
        "fibers": [{"table": str(s.table.header.get("cache_key") or s.table.geometry_key),
                    "variant": int(s.table.variant),
                    "photons": int(np.asarray(s.table.arrays["photons"]).sum())} for s in _tables(slots)],
        "settings": asdict(settings),
    }


def bake_yarn_far_field(params: Any, fiber_diameter: float, slots: Sequence[Any],
                        settings: YarnBakeSettings | None = None,
                        progress: Callable[[int, int], None] | None = None) -> YarnFarField:
    """Trace the far field of the yarn ``params`` whose fibers (``fiber_diameter``, scene units)
    are the cross-section variants ``slots`` (:class:`~.fiber_bank.FiberSlot`: their tables;
    their colour is not used), each fiber with a random variant and rotation psi, as the
    renderer draws them, at every absorption level of ``settings`` (recolourable: module
    docstring)."""
    from usdfiber.backend import mitsuba
    from usdfiber.translators.mitsuba.curves import reference_normals
    from usdfiber.translators.mitsuba.fiber_bank import FiberBank, FiberSlot
    from usdfiber.translators.mitsuba.fiber_bsdf import fiber_bsdf

    mi = mitsuba()
    st = settings or YarnBakeSettings()
    # The pieces' own fibers (the settings' seeds), whatever the yarn's seed: a statistic of
    # the structure, shared by every yarn of it (far_field_inputs).
    pieces = far_field_pieces(params, fiber_diameter, st)
    rng = np.random.default_rng([st.seed, 0x7A22])
    tables = _tables(slots)
    # One slot per (level triple, table); BSDF j uses the slots of triple j.
    lv = st.levels
    triples = [tuple(lv[i:i + 3]) for i in range(0, len(lv), 3)]
    bank = FiberBank.build([FiberSlot(t.table, tr) for tr in triples for t in tables])
    sets = []
    for piece in pieces:
        geom = piece.geometry
        nc = geom.curve_count
        variant = rng.integers(0, len(tables), nc)
        psi = rng.uniform(0.0, _TWO_PI, nc)
        seg_var, seg_psi, ref = variant[geom.segment_curve], psi[geom.segment_curve], reference_normals(geom)
        sets.append([fiber_bsdf(mi, bank, j * len(tables) + seg_var, seg_psi, ref) for j in range(len(triples))])
    t0 = _time.perf_counter()
    inputs = far_field_inputs(params, fiber_diameter, slots, st)
    ff = trace_far_field(pieces, sets, st, progress, levels=lv,
                         header={"geometry_key": _key(inputs), "inputs": inputs,
                                 "piece": {"fibers": pieces[0].fibers,
                                           "segments": sum(pc.geometry.segment_count for pc in pieces),
                                           "length_over_bound_radius": pieces[0].length,
                                           "bound_radius": pieces[0].bound_radius,
                                           "realizations": len(pieces)}})
    ff.header["seconds"] = _time.perf_counter() - t0
    return ff


def _tables(slots: Sequence[Any]) -> list[Any]:
    """The distinct tables of ``slots``, in order (one slot per table; colours dropped)."""
    out: dict[int, Any] = {}
    for s in slots:
        out.setdefault(id(s.table), s)
    return list(out.values())


def _key(inputs: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(inputs, sort_keys=True).encode()).hexdigest()


class YarnFarFieldCache:
    """Yarn far fields under ``<table cache root>/yarns/<key>.npz`` (same guarantees as the
    table cache: a lock per key, atomic writes, checksums; a damaged file is reported,
    deleted and traced again)."""

    def __init__(self, table_cache: Any) -> None:
        self.tables = table_cache

    def path(self, key: str) -> Path:
        return Path(self.tables.root) / "yarns" / f"{key}.npz"

    def load(self, key: str) -> YarnFarField | None:
        """The cached far field of ``key``, verified; None when absent or damaged (reported)."""
        return self.tables.load_verified(self.path(key), YarnFarField.load,
                                         lambda ff: ff.header.get("geometry_key") == key, "tracing it again")

    def get_or_bake(self, params: Any, fiber_diameter: float, slots: Sequence[Any],
                    settings: YarnBakeSettings | None = None, *, bake_missing: bool = True,
                    progress: Callable[[int, int], None] | None = None) -> tuple[YarnFarField | None, bool]:
        """(far field, whether it was traced now); (None, False) if missing and not baking."""
        st = settings or YarnBakeSettings()
        key = _key(far_field_inputs(params, fiber_diameter, slots, st))

        def make() -> YarnFarField:
            ff = bake_yarn_far_field(params, fiber_diameter, slots, st, progress)
            path = self.path(key)
            path.parent.mkdir(parents=True, exist_ok=True)
            ff.save(path)
            return ff

        return load_or_make(lambda: self.load(key), lambda: self.tables.lock("yarn-" + key), make,
                            make_missing=bake_missing)


def far_field_entry(prim: str, stats: dict[str, int], ff: YarnFarField | None, traced: bool,
                    seconds: float) -> dict[str, Any]:
    """A yarn prim's line in a render's far-field report: its far field ``"traced"`` now (with
    the seconds it took), found ``"cached"``, or ``"not needed"``, and why: how many of its
    yarns were drawn with it in view (``stats["far"]``: narrower than the level of detail's
    threshold, or not expanded), kept outside the view as proxies near it (``"culled"``) and
    left out far outside it (``"skipped"``), from the yarn plan's ``stats``."""
    in_view, proxies, skipped = int(stats.get("far", 0)), int(stats.get("culled", 0)), int(stats.get("skipped", 0))
    why = []
    if in_view:
        why.append(f"{in_view} in view, too narrow to show their fibers or not expanded")
    if proxies:
        why.append(f"{proxies} outside the view but near enough to shadow or light it")
    if skipped:
        why.append(f"{skipped} far outside the view, left out")
    return {"prim": prim, "far_field": "not needed" if ff is None else ("traced" if traced else "cached"),
            "key": None if ff is None else ff.header.get("geometry_key"),
            "seconds": float(seconds) if traced else 0.0,
            "in_view": in_view, "proxies": proxies, "skipped": skipped, "reason": "; ".join(why)}
