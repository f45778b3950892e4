"""Brute-force float64 photon tracer for a straight extruded fiber (the bake's reference).

Setup (Aliaga et al. 2017, Sec. 3.2): a single straight, infinitely long fiber with a given
cross section (:class:`~usdfiber.bake.profiles.Profile`) is lit by a collimated beam exactly as
wide as the profile's shadow; every photon random-walks through the dielectric boundaries until
it leaves, and is collected on a sphere at infinity (far field) as a function of its direction.

Fiber frame: t = fiber axis = +z; the profile lies in the xy plane; phi is measured from +x
towards +y; theta is the angle from the xy plane (sin theta = w.z), so
omega(theta, phi) = (cos theta cos phi, cos theta sin phi, sin theta). omega_i points TOWARDS
the light (photons travel along -omega_i) and the exit direction omega_o points towards the
viewer, so both point away from the fiber (the convention of ``exact``). Lengths are in
micrometres, absorption coefficients in 1/micrometre; absorption is applied afterwards, per
channel, from the path length each photon travelled inside the material (Beer-Lambert).

Boundaries (Sec. 3.1): dielectric of relative index ``eta`` (holes are air), smooth normals
interpolated along the polygon edges, Beckmann microfacet roughness of average slope angle
beta (alpha = tan beta, isotropic). A smooth boundary (beta = 0) reflects or refracts about the
interpolated normal, Fresnel (unpolarized, exact dielectric) choosing stochastically; total
internal reflection always reflects. A rough boundary samples microfacet normals from the
distribution of visible normals, Fresnel choosing again at each microfacet; light that the
microsurface sends back into itself scatters again (Heitz et al. 2016, "Multiple-scattering
microfacet BSDFs with the Smith model"), so energy is conserved exactly and the boundary is
reciprocal. Every ray-edge test is exact float64; a culling tree (and, for the first hits, a
sweep across the beam) only skips edges that cannot be hit (``brute_force=True`` tests them
all, with identical results).
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy.special import erf, erfinv

from .exact import fresnel_dielectric
from .profiles import Profile

__all__ = [
    "TraceResult",
    "albedo",
    "azimuthal_marginal",
    "bin_solid_angles",
    "histogram",
    "beckmann_lambda",
    "sample_beckmann_vndf",
    "trace",
    "direction",
]

_TINY = 1e-300
_SQRT_PI_INV = 1.0 / np.sqrt(np.pi)

# Photon media.
_EXTERIOR, _MATERIAL, _HOLE = 0, 1, 2


def direction(theta: float | np.ndarray, phi: float | np.ndarray) -> np.ndarray:
    """Unit vector omega(theta, phi) = (cos th cos ph, cos th sin ph, sin th) in the fiber frame."""
    theta = np.asarray(theta, dtype=np.float64)
    phi = np.asarray(phi, dtype=np.float64)
    c = np.cos(theta)
    return np.stack([c * np.cos(phi), c * np.sin(phi), np.sin(theta)], axis=-1)


@dataclass
class TraceResult:
    """Per-photon outcome of :func:`trace` (arrays of length N = number of photons launched).

    ``direction``: exit direction omega_o (N,3) in the fiber frame (meaningful where
    ``escaped``). ``path_length``: 3D length travelled inside the material, micrometres (not
    counting holes). ``n_bounces``: boundary hits. ``escaped``: the photon left the fiber;
    the others were cut at ``max_bounces`` (``n_cut``) or lost to a numerical inconsistency
    (``n_lost``, expected 0). ``n_corrected`` counts boundary events whose outgoing side had
    to be reconciled with the polygon facet (see ``_scatter_boundary``; rare, grazing).
    ``beam_width``: W(phi_i), micrometres.
    """

    direction: np.ndarray
    path_length: np.ndarray
    n_bounces: np.ndarray
    escaped: np.ndarray
    beam_width: float
    theta_i: float
    phi_i: float
    eta: float
    beta: float
    n_cut: int
    n_lost: int
    n_corrected: int = 0
    omega_i: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def n_photons(self) -> int:
        return int(len(self.escaped))


# --------------------------------------------------------------------------------------------
# Microfacet sampling
# --------------------------------------------------------------------------------------------

def beckmann_lambda(w: np.ndarray, alpha: float) -> np.ndarray:
    """Smith Lambda(w) of an isotropic Beckmann surface (local frame, z = macro normal).

    Lambda = (erf(a) - 1) / 2 + exp(-a^2) / (2 a sqrt(pi)), a = cot(theta) / alpha. For downward
    directions the same expression gives Lambda(-w) = -1 - Lambda(w). Vertical: 0 (up), -1 (down).
    """
    wz = np.clip(w[:, 2], -1.0, 1.0)
    sin_t = np.sqrt(np.maximum(1.0 - wz * wz, 0.0))
    vertical = sin_t < 1e-12
    a = wz / np.where(vertical, 1.0, sin_t) / alpha
    a = np.where(np.abs(a) < 1e-12, np.copysign(1e-12, wz), a)
    with np.errstate(over="ignore", under="ignore"):
        lam = 0.5 * (erf(a) - 1.0) + 0.5 * _SQRT_PI_INV * np.exp(-a * a) / a
    return np.where(vertical, np.where(wz > 0, 0.0, -1.0), lam)


def sample_beckmann_vndf(wi: np.ndarray, alpha: float, u1: np.ndarray, u2: np.ndarray) -> np.ndarray:
    """Sample Beckmann microfacet normals from the distribution of normals visible from ``wi``.

    ``wi`` (M,3): unit directions towards where the photon comes from, in a local frame whose
    z axis is the macro normal (wi may lie below the horizon inside a microsurface walk).
    Heitz & d'Eon 2014: stretch to alpha = 1, sample the slope x~ from the visible-slope
    density (cot th - x~) exp(-x~^2) / sqrt(pi), x~ < cot th, by safeguarded Newton steps on
    its CDF cot (1 + erf x) / 2 + exp(-x^2) / (2 sqrt(pi)); the slope y~ from exp(-y~^2) / sqrt(pi);
    rotate to wi's azimuth; unstretch. Returns unit normals (M,3) with m . wi >= 0.
    """
    wi = np.asarray(wi, dtype=np.float64)
    ws = np.stack([alpha * wi[:, 0], alpha * wi[:, 1], wi[:, 2]], axis=1)
    ws /= np.maximum(np.linalg.norm(ws, axis=1, keepdims=True), _TINY)
    cos_t = np.clip(ws[:, 2], -1.0, 1.0)
    sin_t = np.sqrt(np.maximum(1.0 - cos_t * cos_t, 0.0))
    has_phi = sin_t > 1e-12
    cos_p = np.where(has_phi, ws[:, 0] / np.where(has_phi, sin_t, 1.0), 1.0)
    sin_p = np.where(has_phi, ws[:, 1] / np.where(has_phi, sin_t, 1.0), 0.0)
    cot = np.clip(cos_t / np.maximum(sin_t, 1e-300), -1e12, 1e12)

    def cdf(x, c):
        return 0.5 * c * (1.0 + erf(x)) + 0.5 * _SQRT_PI_INV * np.exp(-x * x)

    hi = np.minimum(cot, 9.0)
    lo = np.minimum(-9.0, cot - 4.0)
    target = np.clip(np.asarray(u1, dtype=np.float64), 0.0, 1.0) * cdf(hi, cot)
    x = np.clip(erfinv(np.clip(2.0 * np.asarray(u1) - 1.0, -1 + 1e-16, 1 - 1e-16)), lo, hi)
    act = np.arange(len(x))
    for _ in range(100):
        # Newton steps on the CDF, inside a bracket [lo, hi] that keeps the root (the CDF
        # increases on x < cot); bisection where Newton would leave it. Converged lanes drop out.
        xa, c = x[act], cot[act]
        gx = cdf(xa, c) - target[act]
        la = np.where(gx < 0, xa, lo[act])
        ha = np.where(gx > 0, xa, hi[act])
        dg = (c - xa) * np.exp(-xa * xa) * _SQRT_PI_INV
        with np.errstate(divide="ignore", invalid="ignore"):
            xn = xa - gx / dg
        bad = ~np.isfinite(xn) | (xn <= la) | (xn >= ha)
        xn = np.where(bad, 0.5 * (la + ha), xn)
        x[act], lo[act], hi[act] = xn, la, ha
        more = (np.abs(xn - xa) > 1e-13 * (1.0 + np.abs(xn))) & (ha - la > 1e-13 * (1.0 + np.abs(xn)))
        act = act[more]
        if len(act) == 0:
            break
    y = erfinv(np.clip(2.0 * np.asarray(u2, dtype=np.float64) - 1.0, -1 + 1e-16, 1 - 1e-16))
    sx = alpha * (cos_p * x - sin_p * y)
    sy = alpha * (sin_p * x + cos_p * y)
    m = np.stack([-sx, -sy, np.ones_like(sx)], axis=1)
    return m / np.linalg.norm(m, axis=1, keepdims=True)


# --------------------------------------------------------------------------------------------
# Ray-edge queries
# --------------------------------------------------------------------------------------------

class _EdgeBVH:
    """Culling tree over the profile's edges; returns exactly the brute-force first hit.

    Leaves hold ``leaf_size`` consecutive edges of one loop (a short arc), inner nodes the
    boxes of ``branch`` consecutive children. Traversal is breadth-first over (photon, node)
    pairs, which vectorizes in numpy; the edge test at the leaves is the same as in
    :meth:`query_brute_force`. Padding boxes are NaN, which fails every comparison.
    """

    def __init__(self, profile: Profile, leaf_size: int = 8, branch: int = 4):
        e = profile.edge_arrays()
        self.a, self.b = e["a"], e["b"]
        self.leaf_size, self.branch = leaf_size, branch
        leaves = []
        start = 0
        for l in profile.loops:
            for s in range(0, len(l), leaf_size):
                idx = np.arange(start + s, start + min(s + leaf_size, len(l)))
                leaves.append(np.pad(idx, (0, leaf_size - len(idx)), constant_values=-1))
            start += len(l)
        leaf_edges = np.array(leaves, dtype=np.int64)
        scale = float(np.max(np.ptp(np.concatenate(profile.loops), axis=0)))
        pad = 1e-9 * scale

        def leaf_box(ix):
            ix = ix[ix >= 0]
            p = np.concatenate([self.a[ix], self.b[ix]])
            return np.concatenate([p.min(axis=0) - pad, p.max(axis=0) + pad])

        boxes = np.array([leaf_box(ix) for ix in leaf_edges])
        levels = []  # bottom-up; all but the top padded to a multiple of ``branch``
        while len(boxes) > branch:
            n_pad = (-len(boxes)) % branch
            boxes = np.concatenate([boxes, np.full((n_pad, 4), np.nan)])
            if not levels:
                leaf_edges = np.concatenate([leaf_edges, np.full((n_pad, leaf_size), -1)])
            levels.append(boxes)
            g = boxes.reshape(-1, branch, 4)
            boxes = np.concatenate([np.nanmin(g[..., :2], axis=1), np.nanmax(g[..., 2:], axis=1)], axis=1)
        levels.append(boxes)
        # Top first. Rows (x0, y0, x1, y1): one gather fetches a whole box.
        self.levels = [np.ascontiguousarray(bx) for bx in levels[::-1]]
        self.leaf_edges = leaf_edges
        # Edge data laid out per leaf, (n_leaves, leaf_size, 4) = (ax, ay, ex, ey); padding is
        # NaN (never hit).
        ee = np.maximum(leaf_edges, 0)
        nan = (leaf_edges < 0)[..., None]
        data = np.concatenate([self.a[ee], self.b[ee] - self.a[ee]], axis=-1)
        self.leaf_data = np.ascontiguousarray(np.where(nan, np.nan, data))

    @staticmethod
    def _edge_test(ox, oy, dx, dy, tmin, excl, e, ax, ay, ex, ey):
        """Distance t (inf if no hit) and edge parameter u of rays o + t d against edges.

        Solves o + t d = a + u (b - a): t = (w x e) / (d x e), u = (w x d) / (d x e), w = a - o.
        """
        wx, wy = ax - ox, ay - oy
        denom = dx * ey - dy * ex
        ok = (e >= 0) & (e != excl) & (denom != 0.0)
        safe = np.where(ok, denom, 1.0)
        t = (wx * ey - wy * ex) / safe
        u = (wx * dy - wy * dx) / safe
        ok &= (u >= -1e-10) & (u <= 1.0 + 1e-10) & (t > tmin)
        return np.where(ok, t, np.inf), u

    def query_brute_force(self, o, d, tmin, excl, chunk: int = 1 << 21):
        """First hit of every ray against every edge (the O(N E) definition)."""
        m, n_e = len(o), len(self.a)
        t_best = np.full(m, np.inf)
        e_best = np.full(m, -1, dtype=np.int64)
        u_best = np.zeros(m)
        rows = max(1, chunk // max(n_e, 1))
        all_e = np.arange(n_e)[None, :]
        ax, ay = self.a[None, :, 0], self.a[None, :, 1]
        ex, ey = self.b[None, :, 0] - ax, self.b[None, :, 1] - ay
        for s in range(0, m, rows):
            sl = slice(s, s + rows)
            with np.errstate(invalid="ignore"):
                t, u = self._edge_test(o[sl, 0:1], o[sl, 1:2], d[sl, 0:1], d[sl, 1:2], tmin[sl, None],
                                       excl[sl, None], all_e, ax, ay, ex, ey)
            j = np.argmin(t, axis=1)
            r = np.arange(len(j))
            t_best[sl] = t[r, j]
            u_best[sl] = u[r, j]
            e_best[sl] = np.where(np.isfinite(t[r, j]), j, -1)
        return t_best, e_best, np.clip(u_best, 0.0, 1.0)

    def query_beam(self, o, d, tmin, s, perp):
        """First hits of parallel rays (one shared 2D direction ``d``) entering from outside.

        ``s`` is each ray's coordinate along ``perp`` (perpendicular to ``d``). An edge can only
        be hit by the rays whose ``s`` lies within the edge's own projection on ``perp``, so each
        ray is tested against just the few edges above it (the same exact edge test).
        """
        m = len(o)
        t_best = np.full(m, np.inf)
        e_best = np.full(m, -1, dtype=np.int64)
        u_best = np.zeros(m)
        order = np.argsort(s, kind="stable")
        s_sorted = s[order]
        pa = self.a @ perp
        pb = self.b @ perp
        span = float(np.ptp(np.concatenate([pa, pb]))) + 1e-300
        lo = np.minimum(pa, pb) - 1e-9 * span
        hi = np.maximum(pa, pb) + 1e-9 * span
        i0 = np.searchsorted(s_sorted, lo, side="left")
        i1 = np.searchsorted(s_sorted, hi, side="right")
        counts = np.maximum(i1 - i0, 0)
        total = int(counts.sum())
        if total == 0:
            return t_best, e_best, u_best
        edge = np.repeat(np.arange(len(self.a)), counts)
        offs = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
        ray = order[np.repeat(i0, counts) + offs]
        ax, ay = self.a[edge, 0], self.a[edge, 1]
        ex, ey = self.b[edge, 0] - ax, self.b[edge, 1] - ay
        with np.errstate(invalid="ignore"):
            t, u = self._edge_test(o[ray, 0], o[ray, 1], d[0], d[1], tmin[ray], -1, edge, ax, ay, ex, ey)
        np.minimum.at(t_best, ray, t)
        win = np.isfinite(t) & (t == t_best[ray])
        e_best[ray[win]] = edge[win]
        u_best[ray[win]] = u[win]
        return t_best, e_best, np.clip(u_best, 0.0, 1.0)

    def query(self, o, d, tmin, excl, chunk: int = 1 << 13):
        """First hit (t, edge, u) of rays o + t d (2D, t scales with |d|); t = inf, edge = -1 if none."""
        m = len(o)
        t_best = np.full(m, np.inf)
        e_best = np.full(m, -1, dtype=np.int64)
        u_best = np.zeros(m)
        # Per-ray rows (ox, oy, 1/dx, 1/dy): one gather per pair. Zero components become tiny
        # ones, which keeps the slab test finite and conservative.
        with np.errstate(divide="ignore"):
            ray = np.stack([o[:, 0], o[:, 1], 1.0 / np.where(d[:, 0] == 0.0, 1e-300, d[:, 0]),
                            1.0 / np.where(d[:, 1] == 0.0, 1e-300, d[:, 1])], axis=1)
        n_top = len(self.levels[0])
        br = self.branch
        kids = np.arange(br)
        for s in range(0, m, chunk):
            ids = np.arange(s, min(m, s + chunk))
            pp = np.repeat(ids, n_top)
            nd = np.tile(np.arange(n_top), len(ids))
            for lev, boxes in enumerate(self.levels):
                if lev > 0:
                    pp = np.repeat(pp, br)
                    nd = (nd[:, None] * br + kids).ravel()
                rr = ray[pp]
                bx = boxes[nd]
                tx0 = (bx[:, 0] - rr[:, 0]) * rr[:, 2]
                tx1 = (bx[:, 2] - rr[:, 0]) * rr[:, 2]
                ty0 = (bx[:, 1] - rr[:, 1]) * rr[:, 3]
                ty1 = (bx[:, 3] - rr[:, 1]) * rr[:, 3]
                tnear = np.maximum(np.minimum(tx0, tx1), np.minimum(ty0, ty1))
                tfar = np.minimum(np.maximum(tx0, tx1), np.maximum(ty0, ty1))
                keep = np.flatnonzero((tnear <= tfar) & (tfar >= tmin[pp]))
                pp, nd = pp[keep], nd[keep]
            if len(pp) == 0:
                continue
            ld = self.leaf_data[nd]
            with np.errstate(invalid="ignore"):
                t, u = self._edge_test(o[pp, 0:1], o[pp, 1:2], d[pp, 0:1], d[pp, 1:2], tmin[pp, None],
                                       excl[pp, None], self.leaf_edges[nd], ld[..., 0], ld[..., 1],
                                       ld[..., 2], ld[..., 3])
            j = np.argmin(t, axis=1)
            r = np.arange(len(j))
            tp, up, ep = t[r, j], u[r, j], self.leaf_edges[nd, j]
            # Reduce over the pairs of each photon (pp is sorted: pairs were only filtered/repeated).
            starts = np.flatnonzero(np.r_[True, pp[1:] != pp[:-1]])
            tmin_seg = np.minimum.reduceat(tp, starts)
            counts = np.diff(np.r_[starts, len(pp)])
            is_min = tp == np.repeat(tmin_seg, counts)
            first = np.minimum.reduceat(np.where(is_min, np.arange(len(tp)), len(tp)), starts)
            who = pp[starts]
            found = np.isfinite(tmin_seg)
            t_best[who[found]] = tmin_seg[found]
            e_best[who[found]] = ep[first[found]]
            u_best[who[found]] = up[first[found]]
        return t_best, e_best, np.clip(u_best, 0.0, 1.0)


# --------------------------------------------------------------------------------------------
# Boundary interaction
# --------------------------------------------------------------------------------------------

def _dot(a, b):
    return np.einsum("ij,ij->i", a, b)


def _normalize(v):
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), _TINY)


def _refract(wi, m, cos_i, rel):
    """Refraction of wi (pointing away from the surface, wi.m = cos_i > 0) through m.

    ``rel`` = eta_t / eta_i; the result points to the other side. Caller excludes TIR.
    """
    cos_t = np.sqrt(np.maximum(1.0 - (1.0 - cos_i * cos_i) / (rel * rel), 0.0))
    t = m * (cos_i / rel - cos_t)[:, None] - wi / rel[:, None]
    # An index-matched boundary is invisible: the direction goes on unchanged.
    return np.where((rel == 1.0)[:, None], -wi, t)


def _microsurface_walk(w, rel, alpha, rng, max_events: int = 256):
    """Random walk of photons on a rough dielectric microsurface (Heitz et al. 2016).

    Local frame: z = macro normal towards the incident side; ``w`` (M,3) travel directions
    (w.z < 0, arriving from above); ``rel`` = eta below / eta above. Smith model with an
    uncorrelated uniform height distribution (C1(h) = (h + 1) / 2), Beckmann slopes: at each
    event the hit height follows the Smith masking, the microfacet normal the distribution of
    visible normals, and Fresnel chooses reflection or refraction; below the surface the walk
    is the same with the whole configuration point-mirrored. Returns (directions, above:
    whether each photon left on the incident side, number forced out at ``max_events``).
    The walk conserves energy exactly and its BSDF is reciprocal.
    """
    n = len(w)
    w = w.copy()
    h = np.full(n, 1.998)          # start above every microfacet: C1(h) = 1
    above = np.ones(n, dtype=bool)
    live = np.arange(n)
    for _ in range(max_events):
        if len(live) == 0:
            break
        wl, hl, ab = w[live], h[live], above[live]
        # Below the surface, mirror everything so that the walk is always computed from above.
        sgn = np.where(ab, 1.0, -1.0)
        wr = wl * sgn[:, None]
        hr = hl * sgn
        c1 = np.clip(0.5 * (hr + 1.0), 0.0, 1.0)
        u = rng.random(len(live))
        lam = beckmann_lambda(wr, alpha)
        up = wr[:, 2] > 0.0
        # Smith masking along the ray: an upward ray escapes with probability G1 = C1(h)^Lambda;
        # otherwise (and always for a downward ray) the next hit is at the height where
        # C1(h') = C1(h) / (1 - u)^(1 / Lambda).
        with np.errstate(divide="ignore", over="ignore", under="ignore", invalid="ignore"):
            g1 = np.where(up, c1 ** np.where(up, lam, 1.0), 0.0)
            c1_new = c1 / (1.0 - u) ** (1.0 / np.where(lam == 0.0, -1.0, lam))
            c1_new = np.where(wr[:, 2] < -0.9999, u * c1, c1_new)
            h_new = np.clip(2.0 * np.minimum(c1_new, 1.0) - 1.0, -1.0, 1.0)
        leave = (up & (u > 1.0 - g1)) | (wr[:, 2] > 0.9999)
        h_new = np.where(np.abs(wr[:, 2]) < 1e-4, hr, h_new)
        h[live] = h_new * sgn
        stay = ~leave
        live = live[stay]
        if len(live) == 0:
            break
        wr, sgn = wr[stay], sgn[stay]
        # Scatter at the hit: wi = -wr seen from (mirrored) above.
        wi = -wr
        m = sample_beckmann_vndf(wi, alpha, rng.random(len(live)), rng.random(len(live)))
        cos_i = np.clip(_dot(wi, m), 0.0, 1.0)
        ab = above[live]
        rel_here = np.where(ab, rel[live], 1.0 / rel[live])
        f = fresnel_dielectric(cos_i, rel_here)
        reflect = rng.random(len(live)) < f
        w_r = -wi + (2.0 * cos_i)[:, None] * m
        w_t = _refract(wi, m, cos_i, rel_here)
        w_new = _normalize(np.where(reflect[:, None], w_r, w_t))
        w[live] = w_new * sgn[:, None]
        above[live] = np.where(reflect, ab, ~ab)
    n_forced = len(live)
    return w, above, n_forced


def _scatter_boundary(d, g_in, s_in, eta_in, eta_out, alpha, rng):
    """Reflect or refract photons travelling along ``d`` (M,3) at a (rough) dielectric boundary.

    ``g_in`` / ``s_in``: geometric (facet) and smooth shading normals (z = 0) pointing to the
    side the photons come from; ``eta_in`` / ``eta_out``: indices on that side and the other.
    Returns (new directions, crossed: bool, number of corrections). The shading normal is the
    macro normal of the microsurface (or the mirror normal when smooth); the facet normal is
    what the next ray segment sees, so it has the last word on the side: a direction that
    disagrees with it (only possible within the tiny angle between the two normals, or by a
    grazing microsurface exit) is mirrored across the facet plane.
    """
    m_count = len(d)
    wi = -d
    # A shading normal that the photon reaches from behind (grazing, within the facet angle)
    # cannot describe this hit: fall back to the facet normal.
    macro = np.where((_dot(wi, s_in) > 1e-12)[:, None], s_in, g_in)
    rel = eta_out / eta_in
    if alpha > 0.0:
        t1 = np.stack([-macro[:, 1], macro[:, 0], np.zeros(m_count)], axis=1)
        local = np.stack([_dot(d, t1), d[:, 2], _dot(d, macro)], axis=1)
        wl, above, n_forced = _microsurface_walk(local, rel, alpha, rng)
        d_new = _normalize(wl[:, 0:1] * t1 + wl[:, 1:2] * np.array([0.0, 0.0, 1.0]) + wl[:, 2:3] * macro)
        crossed = ~above
    else:
        n_forced = 0
        cos_i = np.clip(_dot(wi, macro), 0.0, 1.0)
        f = fresnel_dielectric(cos_i, rel)
        reflect = rng.random(m_count) < f
        d_r = d + (2.0 * cos_i)[:, None] * macro
        d_t = _refract(wi, macro, cos_i, rel)
        d_new = _normalize(np.where(reflect[:, None], d_r, d_t))
        crossed = ~reflect
    # Reconcile with the facet: reflected light must leave on the incident side, transmitted
    # light on the other.
    side = _dot(d_new, g_in)
    wrong = np.where(crossed, side > 0.0, side < 0.0)
    if np.any(wrong):
        d_new[wrong] -= (2.0 * side[wrong])[:, None] * g_in[wrong]
    return d_new, crossed, int(np.count_nonzero(wrong)) + n_forced


# --------------------------------------------------------------------------------------------
# The tracer
# --------------------------------------------------------------------------------------------

@dataclass
class _Setup:
    """Everything a chunk of photons needs (read-only, shared between worker threads)."""

    edges: dict
    query: object
    beam_query: object
    d0: np.ndarray
    s_min: float
    width: float
    start_along: float
    c_phi: float
    s_phi: float
    eps2d: float
    eta: float
    alpha: float
    smooth: bool
    stratified: bool
    n_total: int
    max_bounces: int
    convex_outer: bool


def _trace_chunk(st: _Setup, c0: int, m: int, rng: np.random.Generator):
    """Random-walk photons c0 .. c0+m-1 to completion; returns their outcomes and counters."""
    edges = st.edges
    k = np.arange(c0, c0 + m, dtype=np.float64)
    jitter = rng.random(m)
    frac = (k + jitter) / st.n_total if st.stratified else jitter
    s = st.s_min + st.width * frac
    # Start on a line outside the profile, perpendicular to the beam.
    pos = np.stack([-s * st.s_phi + st.start_along * st.c_phi, s * st.c_phi + st.start_along * st.s_phi], axis=1)
    d = np.tile(st.d0, (m, 1))
    length = np.zeros(m)
    bounces = np.zeros(m, dtype=np.int64)
    medium = np.full(m, _EXTERIOR, dtype=np.int8)
    last = np.full(m, -1, dtype=np.int64)
    done = np.zeros(m, dtype=bool)
    esc = np.zeros(m, dtype=bool)
    n_cut = n_lost = n_fb = 0
    act = np.arange(m)
    first = True
    while len(act):
        dxy = d[act, :2]
        # t parametrizes the 3D path (|d| = 1), so the 2D epsilon is divided by the 2D speed.
        speed = np.hypot(dxy[:, 0], dxy[:, 1])
        tmin = st.eps2d / np.maximum(speed, _TINY)
        if first and st.beam_query is not None:
            # All photons still share the beam direction: sweep the beam instead.
            t, e, u = st.beam_query(pos, st.d0[:2], tmin, s, np.array([-st.s_phi, st.c_phi]))
        else:
            t, e, u = st.query(pos[act], dxy, tmin, last[act])
        first = False
        miss = e < 0
        if np.any(miss):
            am = act[miss]
            # Leaving to infinity is only possible from the exterior air.
            ok = medium[am] == _EXTERIOR
            esc[am[ok]] = True
            n_lost += int(np.count_nonzero(~ok))
            done[am] = True
        hit = ~miss
        ah, t, e, u = act[hit], t[hit], e[hit], u[hit]
        over = bounces[ah] >= st.max_bounces
        if np.any(over):
            # This would be boundary event max_bounces + 1: stop the photon here.
            n_cut += int(np.count_nonzero(over))
            done[ah[over]] = True
            ah, t, e, u = ah[~over], t[~over], e[~over], u[~over]
        nf = edges["nf"][e]
        dh = d[ah]
        # The facet normal points out of the material: travelling along it means leaving it.
        from_material = (dh[:, 0] * nf[:, 0] + dh[:, 1] * nf[:, 1]) > 0.0
        consistent = from_material == (medium[ah] == _MATERIAL)
        if not np.all(consistent):
            n_lost += int(np.count_nonzero(~consistent))
            done[ah[~consistent]] = True
            ah, t, e, u, nf, dh, from_material = (x[consistent] for x in (ah, t, e, u, nf, dh, from_material))
        length[ah] += np.where(from_material, t, 0.0)
        pos[ah] += t[:, None] * dh[:, :2]
        bounces[ah] += 1
        if st.smooth:
            ns = (1.0 - u)[:, None] * edges["na"][e] + u[:, None] * edges["nb"][e]
            ns /= np.maximum(np.linalg.norm(ns, axis=1, keepdims=True), _TINY)
        else:
            ns = nf
        # Normals facing the side the photon comes from; z = 0 on an extruded boundary.
        sign = np.where(from_material, -1.0, 1.0)[:, None]
        zeros = np.zeros((len(ah), 1))
        g_in = np.hstack([sign * nf, zeros])
        s_in = np.hstack([sign * ns, zeros])
        eta_in = np.where(from_material, st.eta, 1.0)
        eta_out = np.where(from_material, 1.0, st.eta)
        d_new, crossed, fb = _scatter_boundary(dh, g_in, s_in, eta_in, eta_out, st.alpha, rng)
        n_fb += fb
        d[ah] = d_new
        air_side = np.where(edges["loop"][e] == 0, _EXTERIOR, _HOLE).astype(np.int8)
        new_medium = np.where(from_material, air_side, _MATERIAL).astype(np.int8)
        medium[ah] = np.where(crossed, new_medium, medium[ah])
        last[ah] = e
        if st.convex_outer:
            # Outside a convex outline, a photon moving away from it never comes back.
            gone = medium[ah] == _EXTERIOR
            esc[ah[gone]] = True
            done[ah[gone]] = True
        act = act[~done[act]]
    return d, length, bounces, esc, n_cut, n_lost, n_fb


def _is_convex(loop: np.ndarray) -> bool:
    """Is a counter-clockwise loop convex (no right turns)?"""
    e = np.roll(loop, -1, axis=0) - loop
    en = np.roll(e, -1, axis=0)
    return bool(np.all(e[:, 0] * en[:, 1] - e[:, 1] * en[:, 0] >= 0.0))


def trace(profile: Profile, theta_i: float, phi_i: float = 0.0, eta: float = 1.55, beta: float = 0.0,
          n_photons: int = 1 << 20, seed: int = 0, max_bounces: int = 256, stratified: bool = True,
          shading: str = "auto", chunk: int = 1 << 16, workers: int | None = None,
          brute_force: bool = False) -> TraceResult:
    """Trace ``n_photons`` photons from direction omega_i = omega(theta_i, phi_i) through the fiber.

    Photons start outside the profile, uniformly across the beam of width
    W(phi_i) = ``profile.projected_width(phi_i)`` (jittered strata when ``stratified``), and
    travel along -omega_i. ``eta``: relative index of the material (holes are air); ``beta``:
    roughness angle in radians (Beckmann, alpha = tan beta; 0 = smooth). ``shading``: 'smooth'
    interpolates the vertex normals along edges, 'flat' uses facet normals, 'auto' follows
    ``profile.smooth``. Photons are processed in chunks of ``chunk``, each with its own random
    stream derived from (``seed``, chunk index), on ``workers`` threads (default: up to 2):
    results depend on ``seed`` and ``chunk`` only. ``brute_force`` tests every edge for every
    ray instead of culling (same hits, for checking).
    """
    if not (np.isfinite(eta) and eta > 0):
        raise ValueError(f"eta must be positive, got {eta}")
    if not (0.0 <= beta < 0.5 * np.pi):
        raise ValueError(f"beta must be in [0, pi/2), got {beta}")
    if shading not in ("auto", "smooth", "flat"):
        raise ValueError("shading must be 'auto', 'smooth' or 'flat'")
    smooth = profile.smooth if shading == "auto" else shading == "smooth"
    bvh = _EdgeBVH(profile)
    omega_i = direction(theta_i, phi_i)
    c_phi, s_phi = float(np.cos(phi_i)), float(np.sin(phi_i))
    outer = profile.loops[0]
    perp = -s_phi * outer[:, 0] + c_phi * outer[:, 1]
    along = c_phi * outer[:, 0] + s_phi * outer[:, 1]
    scale = float(np.max(np.ptp(np.concatenate(profile.loops), axis=0)))
    n = int(n_photons)
    st = _Setup(
        edges=profile.edge_arrays(), query=bvh.query_brute_force if brute_force else bvh.query,
        beam_query=None if brute_force else bvh.query_beam,
        d0=-omega_i, s_min=float(perp.min()), width=float(perp.max() - perp.min()),
        start_along=float(along.max()) + 0.01 * scale, c_phi=c_phi, s_phi=s_phi,
        eps2d=1e-9 * scale, eta=float(eta), alpha=float(np.tan(beta)), smooth=smooth,
        stratified=stratified, n_total=n, max_bounces=int(max_bounces),
        convex_outer=_is_convex(outer))

    starts = list(range(0, n, int(chunk)))
    jobs = [(c0, min(int(chunk), n - c0), np.random.default_rng([int(seed) & 0xFFFFFFFF, j]))
            for j, c0 in enumerate(starts)]
    n_workers = min(2, os.cpu_count() or 1) if workers is None else max(1, int(workers))
    if n_workers > 1 and len(jobs) > 1:
        # numpy releases the GIL inside its kernels, so threads share the cores.
        with ThreadPoolExecutor(max_workers=n_workers) as pool:
            outs = list(pool.map(lambda j: _trace_chunk(st, *j), jobs))
    else:
        outs = [_trace_chunk(st, *j) for j in jobs]

    def cat(i):
        return np.concatenate([o[i] for o in outs]) if outs else np.zeros(0)

    return TraceResult(
        direction=cat(0).reshape(-1, 3), path_length=cat(1), n_bounces=cat(2).astype(np.int64),
        escaped=cat(3).astype(bool), beam_width=st.width, theta_i=float(theta_i), phi_i=float(phi_i),
        eta=float(eta), beta=float(beta), n_cut=sum(o[4] for o in outs), n_lost=sum(o[5] for o in outs),
        n_corrected=sum(o[6] for o in outs), omega_i=omega_i)


# --------------------------------------------------------------------------------------------
# Estimators
# --------------------------------------------------------------------------------------------

def _weights(result: TraceResult, sigma_a) -> tuple[np.ndarray, bool]:
    """Per-channel photon weights exp(-sigma_a L) (0 for photons that did not escape)."""
    scalar = np.ndim(sigma_a) == 0
    sig = np.atleast_1d(np.asarray(sigma_a, dtype=np.float64))
    if np.any(sig < 0) or np.any(np.isnan(sig)):
        raise ValueError("sigma_a must be >= 0")
    L = result.path_length[None, :]
    with np.errstate(invalid="ignore", over="ignore"):
        # L == 0 (surface reflection) keeps weight 1 even for sigma_a = inf.
        w = np.where(L > 0.0, np.exp(-sig[:, None] * L), 1.0)
    w = np.where(result.escaped[None, :], w, 0.0)
    return w, scalar


def albedo(result: TraceResult, sigma_a: float | Sequence[float] = 0.0) -> np.ndarray | float:
    """Lambda(omega_i): escaped weight / photons launched, per channel (sigma_a in 1/um)."""
    w, scalar = _weights(result, sigma_a)
    a = w.sum(axis=1) / max(result.n_photons, 1)
    return float(a[0]) if scalar else a


def bin_solid_angles(n_theta: int = 90, n_phi: int = 180) -> np.ndarray:
    """Exact solid angle (sin th1 - sin th0) dphi of the (theta, phi) bins, shape (n_theta, n_phi)."""
    th = np.linspace(-0.5 * np.pi, 0.5 * np.pi, n_theta + 1)
    band = np.diff(np.sin(th))
    return np.repeat(band[:, None] * (2.0 * np.pi / n_phi), n_phi, axis=1)


def _bin_indices(dirs: np.ndarray, n_theta: int, n_phi: int) -> tuple[np.ndarray, np.ndarray]:
    th = np.arcsin(np.clip(dirs[:, 2], -1.0, 1.0))
    ph = np.mod(np.arctan2(dirs[:, 1], dirs[:, 0]), 2.0 * np.pi)
    it = np.clip(np.floor((th + 0.5 * np.pi) / np.pi * n_theta).astype(np.int64), 0, n_theta - 1)
    ip = np.clip(np.floor(ph / (2.0 * np.pi) * n_phi).astype(np.int64), 0, n_phi - 1)
    return it, ip


def histogram(result: TraceResult, n_theta: int = 90, n_phi: int = 180,
              sigma_a: float | Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """Scattered distribution per steradian over (theta_o, phi_o) bins of the fiber frame.

    Bins: theta_o uniform over [-pi/2, pi/2] (``n_theta``), phi_o uniform over [0, 2 pi) from +x
    (``n_phi``; absolute, not relative to phi_i). Each escaped photon weighs
    exp(-sigma_a L) / N; a bin's weight is divided by its exact solid angle
    (:func:`bin_solid_angles`). Normalization: sum(p * solid_angle) = albedo(result, sigma_a),
    i.e. p = Lambda(omega_i) p(omega_o | omega_i) and W cos(theta_i) p is the scattering
    cross-section per unit length. Shape (C, n_theta, n_phi) for a sequence of C absorption
    coefficients (1/um), (n_theta, n_phi) for a scalar.
    """
    w, scalar = _weights(result, sigma_a)
    it, ip = _bin_indices(result.direction, n_theta, n_phi)
    flat = it * n_phi + ip
    sa = bin_solid_angles(n_theta, n_phi)
    out = np.stack([np.bincount(flat, weights=wc, minlength=n_theta * n_phi) for wc in w])
    out = out.reshape(-1, n_theta, n_phi) / max(result.n_photons, 1) / sa[None]
    return out[0] if scalar else out


def azimuthal_marginal(result: TraceResult, n_phi: int = 180, sigma_a: float = 0.0,
                       relative: bool = True) -> np.ndarray:
    """Scattered power per radian of phi_o (theta_o integrated), per unit intercepted power.

    With ``relative`` the azimuth is phi_o - phi_i in [0, 2 pi), as in
    :func:`usdfiber.bake.exact.azimuthal_distribution`. Integrates to the albedo.
    """
    w, _ = _weights(result, sigma_a)
    ph = np.arctan2(result.direction[:, 1], result.direction[:, 0])
    if relative:
        ph = ph - result.phi_i
    ph = np.mod(ph, 2.0 * np.pi)
    ip = np.clip(np.floor(ph / (2.0 * np.pi) * n_phi).astype(np.int64), 0, n_phi - 1)
    e = np.bincount(ip, weights=w[0], minlength=n_phi) / max(result.n_photons, 1)
    return e / (2.0 * np.pi / n_phi)
