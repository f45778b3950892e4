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

Approximations, on purpose: the yarn is straight and infinitely long at the scale of its
far field (curvature and neighbours are left to the renderer's path tracing between yarn
curves); the periodic wrap joins the two ends of the piece, which need not match exactly.
"""
from __future__ import annotations

import hashlib
import json
import math
import time as _time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from usdfiber import table_format
from usdfiber.bake.cache import load_or_make
from usdfiber.bake.grid import Grid
from usdfiber.bake.table import Recoloured

__all__ = ["YarnBakeSettings", "YarnFarField", "YarnFarFieldCache", "bake_yarn_far_field",
           "trace_far_field", "yarn_piece"]

FORMAT_KIND = "usdfiber-yarn-far-field"
FORMAT_VERSION = 1
_TWO_PI = 2.0 * math.pi
_MAX_WRAPS = 64


@dataclass(frozen=True)
class YarnBakeSettings:
    """How a yarn's far field is traced.

    ``resolution_deg``: bin size (divides 90); ``photons``: photons per theta_i node;
    ``batches``: independent batches for the error estimate; ``max_bounces``: fiber
    interactions after which a photon is dropped (its energy is reported as lost);
    ``length_diameters``: the periodic piece's length in bounding diameters (rounded up to a
    whole number of ply twists); ``samples_per_turn``: of the yarn expansion; ``seed``.
    """

    resolution_deg: float = 6.0
    photons: int = 40_000
    batches: int = 4
    max_bounces: int = 512
    length_diameters: float = 6.0
    samples_per_turn: int = 12
    seed: int = 1

    def __post_init__(self) -> None:
        Grid(self.resolution_deg, False, True)
        if self.photons < self.batches or self.batches < 2:
            raise ValueError("yarn bake needs batches >= 2 and photons >= batches")
        if self.max_bounces < 1 or self.length_diameters <= 0 or self.samples_per_turn < 3:
            raise ValueError("yarn bake: max_bounces >= 1, length_diameters > 0, samples_per_turn >= 3")


@dataclass
class YarnFarField:
    """A yarn's tabulated far field: the layout of a rotationally symmetric fiber table.

    Duck-types the parts of :class:`usdfiber.bake.table.BcsdfTable` the renderer's
    :class:`~usdfiber.translators.mitsuba.fiber_bank.FiberBank` reads (``grid``, ``band_start``,
    ``arrays["width"]``, ``baked_diameter_um``, ``recolour``); its colour is traced in, so
    :meth:`recolour` ignores the absorption it is given. Arrays:

    ``p`` (n_ti, 1, n_to, n_po, 3) float32 per steradian, each channel's slice integrating to
    1; ``albedo`` (n_ti, 1, 3); ``coverage`` (n_ti,) at the theta_i nodes; ``width`` (1,) = 1
    (W / D is 1: the transparency is ``coverage``); ``rel_error`` (n_ti, 1) relative L2 error
    of p (channel mean) from independent batches; ``photons`` (n_ti, 1); ``lost`` (n_ti,)
    fraction of the scattered energy dropped at ``max_bounces``.
    """

    header: dict[str, Any]
    arrays: dict[str, np.ndarray]
    path: str | None = None
    _rec: Recoloured | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        self.grid = Grid(float(self.header["resolution"]["deg"]), False, True)
        g = self.grid
        p = self.arrays["p"]
        if p.shape != (g.n_theta_i, 1, g.n_theta_o, g.n_phi_o, 3):
            raise table_format.TableError(self.path or "yarn far field", f"array p has shape {p.shape}")
        for name, shape in (("albedo", (g.n_theta_i, 1, 3)), ("coverage", (g.n_theta_i,))):
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

    def recolour(self, sigma_a_rgb_per_um: Any = 0.0, diameter_scale: float = 1.0) -> Recoloured:
        """The traced colour (the argument is ignored: the fibers' colour is traced in)."""
        if self._rec is None:
            self._rec = Recoloured(self, np.zeros(3), self.arrays["p"].astype(np.float32),  # type: ignore[arg-type]
                                   self.arrays["albedo"].astype(np.float32))
        return self._rec

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


def trace_far_field(piece: YarnPiece, bsdf: Any, settings: YarnBakeSettings,
                    progress: Callable[[int, int], None] | None = None,
                    header: dict[str, Any] | None = None) -> YarnFarField:
    """Trace ``settings.photons`` photons per theta_i node through ``piece`` whose fibers
    scatter with ``bsdf`` (a :func:`~usdfiber.translators.mitsuba.fiber_bsdf.fiber_bsdf` for the
    piece's segments) and tabulate the far field (module docstring)."""
    from usdfiber.backend import mitsuba
    from usdfiber.translators.mitsuba.curves import make_curve_shape

    mi = mitsuba()
    import drjit as dr

    g = Grid(settings.resolution_deg, False, True)
    n_ti, n_to, n_po = g.n_theta_i, g.n_theta_o, g.n_phi_o
    step = g.step
    th_nodes = g.theta_i_nodes()
    shape = make_curve_shape(piece.geometry, bsdf, "yarn_piece")
    scene = mi.load_dict({"type": "scene", "yarn": shape})
    ctx = mi.BSDFContext()
    rng = np.random.default_rng(settings.seed)
    lz = piece.length
    B = settings.batches
    per_batch = -(-settings.photons // B)
    n_bins = n_ti * n_to * n_po
    hist = np.zeros((B, 3, n_bins))
    scattered = np.zeros((B, n_ti))
    lost = np.zeros((B, n_ti, 3))
    launched = np.zeros((B, n_ti))
    lanes = 1 << 18
    total = B * n_ti * per_batch
    done = 0
    for b in range(B):
        ti_all = np.repeat(np.arange(n_ti), per_batch)
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
            thr = np.ones((n, 3))
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
                    for c in range(3):
                        hist[b, c] += np.bincount(flat, weights=thr[rec, c], minlength=n_bins)
                dead = np.zeros(n, bool)
                if np.any(valid):
                    u1 = mi.Float(rng.random(n).astype(np.float32))
                    u2 = mi.Point2f(mi.Float(rng.random(n).astype(np.float32)),
                                    mi.Float(rng.random(n).astype(np.float32)))
                    bs, w = bsdf.sample(ctx, si, u1, u2, mi.Bool(valid))
                    wo = si.to_world(bs.wo)
                    dr.eval(bs, w, wo)   # one kernel, not one per converted component
                    null = np.array(bs.sampled_type, np.uint32) == int(mi.BSDFFlags.Null)
                    ok = valid & (np.array(bs.pdf) > 0)
                    wv = np.stack([np.array(w[k], np.float64) for k in range(3)], axis=1)
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
    return _assemble(g, hist, scattered, launched, lost, settings, header or {})


def _assemble(g: Grid, hist: np.ndarray, scattered: np.ndarray, launched: np.ndarray, lost: np.ndarray,
              settings: YarnBakeSettings, header: dict[str, Any]) -> YarnFarField:
    """The table from per-batch histograms ``hist`` (B, 3, n_ti * n_to * n_po)."""
    n_ti, n_to, n_po = g.n_theta_i, g.n_theta_o, g.n_phi_o
    dom = np.repeat(g.solid_angles(), n_po)                            # per bin of a slice
    B = hist.shape[0]
    Hb = hist.reshape(B, 3, n_ti, n_to * n_po)
    H = Hb.sum(axis=0)                                                 # (3, n_ti, bins)
    S = scattered.sum(axis=0)                                          # photons that scattered
    N = launched.sum(axis=0)
    L = lost.sum(axis=0)                                               # (n_ti, 3)
    tot = H.sum(axis=-1)                                               # (3, n_ti) throughput out

    def ratio(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.where(b > 0, a / np.where(b > 0, b, 1.0), 0.0)

    p = ratio(H, tot[..., None]) / dom                                  # per steradian
    albedo = ratio(tot, S[None, :])                                    # (3, n_ti)
    coverage = ratio(S, N)
    lost_frac = ratio(L.mean(axis=1), tot.mean(axis=0) + L.mean(axis=1))
    # Relative L2 error of p (channel mean) from the spread of the independent batches.
    hm = Hb.mean(axis=1)                                               # (B, n_ti, bins)
    pb = ratio(hm, hm.sum(axis=-1, keepdims=True)) / dom
    pm = pb.mean(axis=0)
    var = ((pb - pm) ** 2).sum(axis=0) / ((B - 1) * B)
    rel = np.sqrt(ratio((dom * var).sum(axis=-1), (dom * pm ** 2).sum(axis=-1)))
    hdr = dict(header)
    hdr.update({
        "kind": FORMAT_KIND, "kind_version": FORMAT_VERSION,
        "resolution": {"deg": g.resolution_deg, "theta_i": n_ti, "theta_o": n_to, "phi_o": n_po,
                       "rotationally_symmetric": True, "theta_symmetric": False},
        "photons": int(N.max()),
        "error_estimate": {"metric": "relative L2 of p per theta_i (channel mean), from independent batches",
                           "max": float(np.max(rel)), "median": float(np.median(rel))},
        "settings": asdict(settings),
        "lost_energy_max": float(np.max(lost_frac)),
    })
    hdr.setdefault("geometry_key", "")
    hdr.setdefault("inputs", {})
    arrays = {
        "p": np.moveaxis(p.reshape(3, n_ti, n_to, n_po), 0, -1)[:, None].astype(np.float32),
        "albedo": albedo.T[:, None].astype(np.float32),
        "coverage": coverage.astype(np.float32),
        "width": np.ones(1, np.float32),
        "rel_error": rel[:, None].astype(np.float32),
        "photons": N[:, None].astype(np.int64),
        "lost": lost_frac.astype(np.float32),
    }
    return YarnFarField(hdr, arrays)


# ---------------------------------------------------------------------------------------------
# A yarn prim's far field, baked on demand and cached
# ---------------------------------------------------------------------------------------------

def far_field_inputs(params: Any, fiber_diameter: float, slots: Sequence[Any],
                     settings: YarnBakeSettings) -> dict[str, Any]:
    """Everything the far field depends on (the cache key's content): the yarn's structure in
    metres, the fiber diameter, each fiber variant's table and effective absorption."""
    mpu = float(params.meters_per_unit)
    skip = {"prim_path", "expand", "linear_density", "fiber_diameter", "meters_per_unit"}
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
                    "photons": int(np.asarray(s.table.arrays["photons"]).sum()),
                    "sigma_a": [round(float(x), 9) for x in s.sigma_a]} for s in slots],
        "settings": asdict(settings),
    }


def bake_yarn_far_field(params: Any, fiber_diameter: float, slots: Sequence[Any],
                        settings: YarnBakeSettings | None = None,
                        progress: Callable[[int, int], None] | None = None) -> YarnFarField:
    """Trace the far field of the yarn ``params`` whose fibers (``fiber_diameter``, scene units)
    are the cross-section variants ``slots`` (:class:`~.fiber_bank.FiberSlot`: table and
    colour), each fiber with a random variant and rotation psi, as the renderer draws them."""
    from usdfiber.backend import mitsuba
    from usdfiber.translators.mitsuba.curves import reference_normals
    from usdfiber.translators.mitsuba.fiber_bank import FiberBank
    from usdfiber.translators.mitsuba.fiber_bsdf import fiber_bsdf

    mi = mitsuba()
    st = settings or YarnBakeSettings()
    piece = yarn_piece(params, fiber_diameter, st)
    geom = piece.geometry
    rng = np.random.default_rng([st.seed, 0x7A22])
    nc = geom.curve_count
    variant = rng.integers(0, len(slots), nc)
    psi = rng.uniform(0.0, _TWO_PI, nc)
    bank = FiberBank.build(list(slots))
    bsdf = fiber_bsdf(mi, bank, variant[geom.segment_curve], psi[geom.segment_curve], reference_normals(geom))
    t0 = _time.perf_counter()
    inputs = far_field_inputs(params, fiber_diameter, slots, st)
    ff = trace_far_field(piece, bsdf, st, progress,
                         header={"geometry_key": _key(inputs), "inputs": inputs,
                                 "piece": {"fibers": piece.fibers, "segments": geom.segment_count,
                                           "length_over_bound_radius": piece.length,
                                           "bound_radius": piece.bound_radius}})
    ff.header["seconds"] = _time.perf_counter() - t0
    return ff


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
