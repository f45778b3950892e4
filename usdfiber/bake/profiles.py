"""Fiber cross sections (profiles) for the 2.5D scattering bake.

A fiber is modelled, as in Aliaga et al. 2017 (Sec. 3, "Cross section and longitudinal
structure"), as a straight dielectric cylinder extruded from a 2D cross section. The cross
section is a set of closed polygonal loops in the xy plane of the fiber frame (the fiber axis
is +z), in micrometres:

* ``loops[0]`` is the outer boundary, counter-clockwise;
* ``loops[1:]`` are holes (air, e.g. the lumen of cotton), clockwise;

so that the fiber material always lies on the LEFT of the direction of travel. ``normals`` are
unit vectors at the vertices pointing OUT of the material (to the right of travel). For smooth
profiles they come from the underlying smooth curve, not from the polygon facets: faceted
normals bias the caustics of smooth fibers (see the tracer's tests).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
from scipy.interpolate import CubicSpline

__all__ = [
    "Profile",
    "ProfileError",
    "TABLE1_DIAMETER_UM",
    "BUILTIN_KINDS",
    "builtin_profiles",
    "builtin_profiles_um",
    "circle",
    "default_diameter_um",
    "ellipse",
    "fourier_loop",
    "profile_from_polygons",
    "spline_loop",
    "validate_loops",
]

#: Fiber diameters (min, max) in micrometres, Aliaga et al. 2017, Table 1 (after Trotman).
TABLE1_DIAMETER_UM: dict[str, tuple[float, float]] = {
    "polyester": (10, 10),
    "silk": (5, 10),
    "cotton": (17, 20),
    "wool": (24, 40),
}

#: Kinds understood by :func:`builtin_profiles`.
BUILTIN_KINDS: tuple[str, ...] = ("polyester", "silk", "cotton", "mercerizedCotton", "wool")


class ProfileError(ValueError):
    """An invalid cross section (the message names the loop and the defect)."""


# --------------------------------------------------------------------------------------------
# Small geometric functions
# --------------------------------------------------------------------------------------------

def _cross(ax, ay, bx, by):
    return ax * by - ay * bx


def _signed_area(loop: np.ndarray) -> float:
    """Shoelace area, positive for counter-clockwise loops."""
    x, y = loop[:, 0], loop[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _facet_normals(loop: np.ndarray) -> np.ndarray:
    """Unit normals of the edges (i -> i+1), to the right of travel."""
    e = np.roll(loop, -1, axis=0) - loop
    n = np.stack([e[:, 1], -e[:, 0]], axis=1)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.maximum(length, np.finfo(float).tiny)


def _vertex_normals_from_facets(loop: np.ndarray) -> np.ndarray:
    """Average of the two adjacent facet normals at each vertex, renormalized."""
    fn = _facet_normals(loop)
    n = fn + np.roll(fn, 1, axis=0)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    # A vertex where the boundary folds back has no average; keep the incoming facet normal.
    bad = length[:, 0] < 1e-12
    n[bad] = np.roll(fn, 1, axis=0)[bad]
    length[bad] = 1.0
    return n / length


def _point_in_loop(pts: np.ndarray, loop: np.ndarray) -> np.ndarray:
    """Even-odd test of points (M,2) against a closed polygon (N,2)."""
    px = pts[:, 0:1]
    py = pts[:, 1:2]
    ax, ay = loop[None, :, 0], loop[None, :, 1]
    bx, by = np.roll(loop[:, 0], -1)[None, :], np.roll(loop[:, 1], -1)[None, :]
    straddle = (ay > py) != (by > py)
    with np.errstate(divide="ignore", invalid="ignore"):
        xint = ax + (py - ay) * (bx - ax) / (by - ay)
    crossing = straddle & (px < xint)
    return (np.count_nonzero(crossing, axis=1) % 2) == 1


def _min_enclosing_circle(pts: np.ndarray) -> tuple[np.ndarray, float]:
    """Smallest enclosing circle (Welzl's algorithm, iterative form) of 2D points."""
    pts = np.asarray(pts, dtype=np.float64)
    if len(pts) > 3:
        try:
            from scipy.spatial import ConvexHull

            pts = pts[ConvexHull(pts).vertices]
        except Exception:  # degenerate input: fall back to all points
            pass
    # Deterministic shuffle: the expected linear time needs a random order.
    pts = pts[np.random.default_rng(12345).permutation(len(pts))]
    scale = float(np.max(np.abs(pts))) if len(pts) else 1.0
    eps = 1e-12 * max(scale, 1e-300)

    def circle2(a, b):
        c = 0.5 * (a + b)
        return c, float(np.hypot(*(a - c)))

    def circle3(a, b, c):
        d = 2.0 * _cross(b[0] - a[0], b[1] - a[1], c[0] - a[0], c[1] - a[1])
        if abs(d) < 1e-300:
            # Collinear: the circle on the farthest pair.
            best = max((circle2(a, b), circle2(a, c), circle2(b, c)), key=lambda t: t[1])
            return best
        ba, ca = b - a, c - a
        bb, cc = ba @ ba, ca @ ca
        ux = (ca[1] * bb - ba[1] * cc) / d
        uy = (ba[0] * cc - ca[0] * bb) / d
        center = a + np.array([ux, uy])
        return center, float(np.hypot(ux, uy))

    def inside(p, c, r):
        return np.hypot(*(p - c)) <= r + eps

    c, r = pts[0].copy(), 0.0
    for i in range(1, len(pts)):
        if inside(pts[i], c, r):
            continue
        c, r = pts[i].copy(), 0.0
        for j in range(i):
            if inside(pts[j], c, r):
                continue
            c, r = circle2(pts[i], pts[j])
            for k in range(j):
                if not inside(pts[k], c, r):
                    c, r = circle3(pts[i], pts[j], pts[k])
    return c, r


# --------------------------------------------------------------------------------------------
# Profile
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Profile:
    """A fiber cross section made of closed polygonal loops (micrometres).

    ``loops[0]``: outer boundary, counter-clockwise. ``loops[1:]``: holes (air), clockwise.
    The material is on the left of travel along every loop. Each loop is closed implicitly
    (its last vertex differs from its first). ``normals[k][i]`` is the unit normal at vertex
    ``i`` of loop ``k``, pointing out of the material. ``smooth`` says whether the loops sample
    a smooth curve (trace with interpolated normals) or are true polygons (flat facets).
    """

    name: str
    loops: tuple[np.ndarray, ...]
    normals: tuple[np.ndarray, ...]
    smooth: bool = True
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        loops = tuple(np.array(l, dtype=np.float64, copy=True) for l in self.loops)
        normals = tuple(np.array(n, dtype=np.float64, copy=True) for n in self.normals)
        if len(loops) == 0:
            raise ProfileError(f"profile {self.name!r}: no loops")
        if len(normals) != len(loops):
            raise ProfileError(f"profile {self.name!r}: {len(loops)} loops but {len(normals)} normal arrays")
        for k, (l, n) in enumerate(zip(loops, normals)):
            if l.ndim != 2 or l.shape[1] != 2 or l.shape[0] < 3:
                raise ProfileError(f"profile {self.name!r}, loop {k}: expected an (N>=3, 2) array, got {l.shape}")
            if n.shape != l.shape:
                raise ProfileError(f"profile {self.name!r}, loop {k}: normals shape {n.shape} != loop shape {l.shape}")
            if not (np.all(np.isfinite(l)) and np.all(np.isfinite(n))):
                raise ProfileError(f"profile {self.name!r}, loop {k}: non-finite coordinates or normals")
            length = np.linalg.norm(n, axis=1, keepdims=True)
            if np.any(length < 1e-12):
                raise ProfileError(f"profile {self.name!r}, loop {k}: zero-length normal")
            # Renormalize only what is off, so transforms keep unit normals bit for bit.
            off = np.abs(length[:, 0] - 1.0) > 1e-13
            n[off] /= length[off]
            l.setflags(write=False)
            n.setflags(write=False)
        object.__setattr__(self, "loops", loops)
        object.__setattr__(self, "normals", normals)

    # ---- measures ---------------------------------------------------------------------------
    @property
    def area(self) -> float:
        """Material area (outer area minus holes), square micrometres, of the polygon."""
        return float(sum(_signed_area(l) for l in self.loops))

    def _enclosing_circle(self) -> tuple[np.ndarray, float]:
        if "mec" not in self._cache:
            self._cache["mec"] = _min_enclosing_circle(self.loops[0])
        return self._cache["mec"]

    @property
    def circumscribed_diameter(self) -> float:
        """Diameter of the smallest circle enclosing the profile (micrometres)."""
        return 2.0 * self._enclosing_circle()[1]

    @property
    def circumscribed_center(self) -> np.ndarray:
        """Centre of the smallest enclosing circle; the origin after :meth:`centered`."""
        return self._enclosing_circle()[0].copy()

    @property
    def n_edges(self) -> int:
        return int(sum(len(l) for l in self.loops))

    def projected_width(self, phi: float | np.ndarray) -> np.ndarray:
        """Width W(phi) of the profile's shadow for light travelling along 2D azimuth ``phi``.

        The outer loop is projected on (-sin phi, cos phi), the line perpendicular to
        (cos phi, sin phi); W = max - min. Vectorized over ``phi``. Per unit fiber length a
        beam from (theta, phi) sees the area W(phi) cos(theta).
        """
        phi = np.asarray(phi, dtype=np.float64)
        flat = phi.reshape(-1)
        out = np.empty(flat.shape)
        v = self.loops[0]
        step = max(1, (1 << 22) // max(len(v), 1))
        for s in range(0, len(flat), step):
            p = flat[s:s + step, None]
            proj = -np.sin(p) * v[None, :, 0] + np.cos(p) * v[None, :, 1]
            out[s:s + step] = proj.max(axis=1) - proj.min(axis=1)
        return out.reshape(phi.shape)

    # ---- normals ----------------------------------------------------------------------------
    def normal_at(self, loop: int, edge: np.ndarray | int, s: np.ndarray | float) -> np.ndarray:
        """Smooth outward normal on edge ``edge`` (vertex edge -> edge+1) of ``loop`` at ``s`` in [0,1].

        Normalized linear interpolation of the two vertex normals; vectorized over ``edge`` and
        ``s``. Returns (..., 2).
        """
        n = self.normals[loop]
        edge = np.asarray(edge) % len(n)
        s = np.asarray(s, dtype=np.float64)[..., None]
        v = (1.0 - s) * n[edge] + s * n[(edge + 1) % len(n)]
        return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), np.finfo(float).tiny)

    def facet_normals(self, loop: int) -> np.ndarray:
        """Flat outward normals of the edges of ``loop`` (E,2)."""
        return _facet_normals(self.loops[loop])

    # ---- transforms ------------------------------------------------------------------------
    def _transformed(self, points: Callable, normals: Callable, name: str | None = None) -> "Profile":
        return Profile(
            name=self.name if name is None else name,
            loops=tuple(points(l) for l in self.loops),
            normals=tuple(normals(n) for n in self.normals),
            smooth=self.smooth,
        )

    def centered(self) -> "Profile":
        """Translate so that the smallest enclosing circle is centred at the origin."""
        c = self.circumscribed_center
        return self._transformed(lambda l: l - c, lambda n: n)

    def scaled(self, factor: float) -> "Profile":
        """Uniform scale about the origin (normals unchanged)."""
        if not (np.isfinite(factor) and factor > 0):
            raise ProfileError(f"profile {self.name!r}: scale factor must be positive, got {factor}")
        return self._transformed(lambda l: l * factor, lambda n: n)

    def scaled_to_diameter(self, d_um: float) -> "Profile":
        """Uniform scale about the origin so that ``circumscribed_diameter == d_um``."""
        return self.scaled(float(d_um) / self.circumscribed_diameter)

    def rotated(self, psi: float) -> "Profile":
        """Rotate counter-clockwise by ``psi`` radians about the origin (the fiber's twist psi)."""
        c, s = np.cos(psi), np.sin(psi)
        rot = np.array([[c, -s], [s, c]])
        return self._transformed(lambda l: l @ rot.T, lambda n: n @ rot.T)

    def validate(self) -> "Profile":
        """Check orientation, simplicity and containment; raise :class:`ProfileError`."""
        validate_loops(self.loops, name=self.name, oriented=True)
        return self

    # ---- flat edge list for tracers -----------------------------------------------------------
    def edge_arrays(self) -> dict[str, np.ndarray]:
        """All edges of all loops as flat arrays (cached).

        Keys: ``a``, ``b`` (E,2) edge end points; ``na``, ``nb`` (E,2) vertex normals at them;
        ``nf`` (E,2) flat facet normals; ``loop`` (E,) loop index; ``index`` (E,) edge index
        within its loop.
        """
        if "edges" not in self._cache:
            a, b, na, nb, nf, lp, idx = [], [], [], [], [], [], []
            for k, (l, n) in enumerate(zip(self.loops, self.normals)):
                a.append(l)
                b.append(np.roll(l, -1, axis=0))
                na.append(n)
                nb.append(np.roll(n, -1, axis=0))
                nf.append(_facet_normals(l))
                lp.append(np.full(len(l), k, dtype=np.int64))
                idx.append(np.arange(len(l), dtype=np.int64))
            d = {
                "a": np.concatenate(a), "b": np.concatenate(b),
                "na": np.concatenate(na), "nb": np.concatenate(nb),
                "nf": np.concatenate(nf), "loop": np.concatenate(lp),
                "index": np.concatenate(idx),
            }
            for v in d.values():
                v.setflags(write=False)
            self._cache["edges"] = d
        return self._cache["edges"]


# --------------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------------

#: Cross products whose sine is below this are zero (collinear, touching): relative to the
#: lengths crossed, so that a fine polygon (a 30k-point circle) is judged like a coarse one.
_SINE_TOL = 1e-12
#: Pairs tested at once (memory of the vectorized test).
_PAIR_BLOCK = 1 << 20


def _segment_pairs_intersect(p0, p1, q0, q1, scale: float) -> np.ndarray:
    """Do segments p0-p1 and q0-q1 touch or cross? Broadcasting over leading dims.

    A cross product counts as zero when it is within ``_SINE_TOL`` of the product of the
    lengths crossed, or within the rounding of coordinates of size ``scale``.
    """
    ex, ey = p1[..., 0] - p0[..., 0], p1[..., 1] - p0[..., 1]
    fx, fy = q1[..., 0] - q0[..., 0], q1[..., 1] - q0[..., 1]
    le, lf = np.hypot(ex, ey), np.hypot(fx, fy)
    rounding = 16.0 * np.finfo(np.float64).eps * scale

    def sgn(ax, ay, bx, by, la):
        o = _cross(ax, ay, bx, by)
        lb = np.hypot(bx, by)
        tol = np.maximum(_SINE_TOL * la * lb, rounding * (la + lb))
        return (o > tol).astype(np.int8) - (o < -tol).astype(np.int8)

    s1 = sgn(ex, ey, q0[..., 0] - p0[..., 0], q0[..., 1] - p0[..., 1], le)
    s2 = sgn(ex, ey, q1[..., 0] - p0[..., 0], q1[..., 1] - p0[..., 1], le)
    s3 = sgn(fx, fy, p0[..., 0] - q0[..., 0], p0[..., 1] - q0[..., 1], lf)
    s4 = sgn(fx, fy, p1[..., 0] - q0[..., 0], p1[..., 1] - q0[..., 1], lf)
    hit = (s1 * s2 <= 0) & (s3 * s4 <= 0)
    collinear = (s1 == 0) & (s2 == 0) & (s3 == 0) & (s4 == 0)
    if np.any(collinear & hit):
        # Collinear segments intersect only if their extents overlap along the line.
        lx = np.where(np.abs(ex) >= np.abs(ey), 0, 1)
        pa = np.where(lx == 0, p0[..., 0], p0[..., 1])
        pb = np.where(lx == 0, p1[..., 0], p1[..., 1])
        qa = np.where(lx == 0, q0[..., 0], q0[..., 1])
        qb = np.where(lx == 0, q1[..., 0], q1[..., 1])
        overlap = (np.maximum(np.minimum(pa, pb), np.minimum(qa, qb))
                   <= np.minimum(np.maximum(pa, pb), np.maximum(qa, qb)))
        hit = np.where(collinear, hit & overlap, hit)
    return hit


def _overlap_pairs(lo_a: np.ndarray, hi_a: np.ndarray, lo_b: np.ndarray, hi_b: np.ndarray):
    """Blocks of index pairs (ia, ib) whose intervals [lo, hi] overlap, each pair once.

    Sort and sweep: two intervals overlap when the start of one lies in the other, so the
    pairs are ``lo_b in [lo_a, hi_a]`` plus ``lo_a in (lo_b, hi_b]``, each a range of a sorted
    array (binary search). O((n + K) log n) for K overlapping pairs; yields blocks of at most
    about ``_PAIR_BLOCK`` pairs.
    """
    for lo_s, hi_s, lo_o, swap in ((lo_a, hi_a, lo_b, False), (lo_b, hi_b, lo_a, True)):
        order = np.argsort(lo_o, kind="stable")
        sorted_lo = lo_o[order]
        first = np.searchsorted(sorted_lo, lo_s, side="right" if swap else "left")
        last = np.searchsorted(sorted_lo, hi_s, side="right")
        counts = np.maximum(last - first, 0)
        ends = np.cumsum(counts)
        i = 0
        while i < len(lo_s):
            j = int(np.searchsorted(ends, (ends[i - 1] if i else 0) + _PAIR_BLOCK, side="right"))
            j = max(j, i + 1)
            c = counts[i:j]
            total = int(c.sum())
            if total:
                own = np.repeat(np.arange(i, j), c)
                offs = np.arange(total) - np.repeat(np.cumsum(c) - c, c)
                other = order[np.repeat(first[i:j], c) + offs]
                yield (other, own) if swap else (own, other)
            i = j


def _axis_pairs(a0, a1, b0, b1):
    """The overlap blocks along the axis (x or y) whose extents overlap least, then filtered
    to the pairs whose boxes overlap along the other axis too."""
    lo_a, hi_a = np.minimum(a0, a1), np.maximum(a0, a1)
    lo_b, hi_b = np.minimum(b0, b1), np.maximum(b0, b1)

    def crowding(axis: int) -> float:
        # Overlapping pairs grow with the extents' total over the span: sweep the emptier axis.
        span = max(float(np.ptp(np.concatenate([lo_a[:, axis], hi_b[:, axis]]))), 1e-300)
        return float(np.sum(hi_a[:, axis] - lo_a[:, axis]) + np.sum(hi_b[:, axis] - lo_b[:, axis])) / span

    axis = 0 if crowding(0) <= crowding(1) else 1
    other = 1 - axis
    for ia, ib in _overlap_pairs(lo_a[:, axis], hi_a[:, axis], lo_b[:, axis], hi_b[:, axis]):
        keep = (lo_a[ia, other] <= hi_b[ib, other]) & (lo_b[ib, other] <= hi_a[ia, other])
        yield ia[keep], ib[keep]


def _first_pair(pairs) -> tuple[int, int] | None:
    best = None
    for a, b in pairs:
        if len(a):
            k = int(np.lexsort((b, a))[0])
            cand = (int(a[k]), int(b[k]))
            best = cand if best is None or cand < best else best
    return best


def _first_self_intersection(loop: np.ndarray, scale: float) -> tuple[int, int] | None:
    """The first pair of edges (i < j) of a loop that touch or cross, adjacent edges only when
    they fold back on each other; O(n log n) for loops of bounded depth (sort and sweep)."""
    n = len(loop)
    p0, p1 = loop, np.roll(loop, -1, axis=0)
    # Adjacent edges share a vertex; they are invalid only if they fold back on each other.
    e = p1 - p0
    e_next = np.roll(e, -1, axis=0)
    fold = (np.abs(_cross(e[:, 0], e[:, 1], e_next[:, 0], e_next[:, 1]))
            <= _SINE_TOL * np.hypot(e[:, 0], e[:, 1]) * np.hypot(e_next[:, 0], e_next[:, 1])) & (
        np.sum(e * e_next, axis=1) < 0)
    if np.any(fold):
        i = int(np.flatnonzero(fold)[0])
        return i, (i + 1) % n

    def hits():
        for i, j in _axis_pairs(p0, p1, p0, p1):
            # Pairs i < j that are not adjacent (around the closing edge too).
            keep = (j > i + 1) & ~((i == 0) & (j == n - 1))
            i, j = i[keep], j[keep]
            for s in range(0, len(i), _PAIR_BLOCK):
                a, b = i[s:s + _PAIR_BLOCK], j[s:s + _PAIR_BLOCK]
                hit = _segment_pairs_intersect(p0[a], p1[a], p0[b], p1[b], scale)
                yield a[hit], b[hit]

    return _first_pair(hits())


def _first_cross_intersection(la: np.ndarray, lb: np.ndarray, scale: float) -> tuple[int, int] | None:
    a0, a1 = la, np.roll(la, -1, axis=0)
    b0, b1 = lb, np.roll(lb, -1, axis=0)

    def hits():
        for i, j in _axis_pairs(a0, a1, b0, b1):
            hit = _segment_pairs_intersect(a0[i], a1[i], b0[j], b1[j], scale)
            yield i[hit], j[hit]

    return _first_pair(hits())


def validate_loops(loops: Sequence[np.ndarray], name: str = "profile", oriented: bool = True,
                   labels: Sequence[int] | None = None) -> None:
    """Raise :class:`ProfileError` unless ``loops`` form a valid cross section.

    Checks every loop for >= 3 vertices, finite coordinates, non-zero area, no
    self-intersection; loops must not intersect each other; loops 1.. must lie inside loop 0
    and not inside each other (no islands). With ``oriented`` it also checks the conventions:
    loop 0 counter-clockwise, holes clockwise. ``labels`` are the loop numbers used in
    messages (the caller's own numbering).
    """
    labels = list(range(len(loops))) if labels is None else list(labels)
    if len(loops) == 0:
        raise ProfileError(f"{name}: no loops given")
    arrs = []
    for k, l in zip(labels, loops):
        l = np.asarray(l, dtype=np.float64)
        if l.ndim != 2 or l.shape[1] != 2:
            raise ProfileError(f"{name}, loop {k}: expected an (N, 2) array of points, got shape {l.shape}")
        if len(l) < 3:
            raise ProfileError(f"{name}, loop {k}: a closed loop needs at least 3 distinct vertices, got {len(l)}")
        if not np.all(np.isfinite(l)):
            bad = int(np.flatnonzero(~np.all(np.isfinite(l), axis=1))[0])
            raise ProfileError(f"{name}, loop {k}: non-finite coordinate (NaN or Inf) at vertex {bad}")
        arrs.append(l)
    allpts = np.concatenate(arrs)
    scale = float(np.max(np.ptp(allpts, axis=0)))
    if not scale > 0:
        raise ProfileError(f"{name}: all vertices coincide (zero-size profile)")
    coord = float(np.max(np.abs(allpts)))  # coordinate size, for rounding
    for k, l in zip(labels, arrs):
        area = _signed_area(l)
        sv = np.linalg.svd(l - l.mean(axis=0), compute_uv=False)
        if sv[-1] <= 1e-9 * sv[0]:
            raise ProfileError(f"{name}, loop {k}: zero or near-zero area ({area:.3g}); vertices are collinear")
        hit = _first_self_intersection(l, coord)
        if hit is not None:
            raise ProfileError(f"{name}, loop {k}: self-intersection between edges {hit[0]} and {hit[1]}")
        if abs(area) <= 1e-9 * scale * scale:
            raise ProfileError(f"{name}, loop {k}: zero or near-zero area ({area:.3g})")
    for ia in range(len(arrs)):
        for ib in range(ia + 1, len(arrs)):
            hit = _first_cross_intersection(arrs[ia], arrs[ib], coord)
            if hit is not None:
                raise ProfileError(
                    f"{name}: loop {labels[ia]} (edge {hit[0]}) intersects loop {labels[ib]} (edge {hit[1]})")
    for k, l in zip(labels[1:], arrs[1:]):
        if not _point_in_loop(l[:1], arrs[0])[0]:
            raise ProfileError(f"{name}, loop {k}: hole is not inside the outer boundary (loop {labels[0]})")
    for ia in range(1, len(arrs)):
        for ib in range(1, len(arrs)):
            if ia != ib and _point_in_loop(arrs[ia][:1], arrs[ib])[0]:
                raise ProfileError(
                    f"{name}, loop {labels[ia]}: lies inside hole loop {labels[ib]} (nested islands are not supported)")
    if oriented:
        if _signed_area(arrs[0]) <= 0:
            raise ProfileError(f"{name}, loop {labels[0]}: outer boundary must be counter-clockwise")
        for k, l in zip(labels[1:], arrs[1:]):
            if _signed_area(l) >= 0:
                raise ProfileError(f"{name}, loop {k}: hole must be clockwise")


# --------------------------------------------------------------------------------------------
# User polygons
# --------------------------------------------------------------------------------------------

def _clean_loop(l: np.ndarray, k: int, name: str) -> np.ndarray:
    l = np.asarray(l, dtype=np.float64)
    if l.ndim != 2 or l.shape[1] != 2:
        raise ProfileError(f"{name}, loop {k}: expected an (N, 2) array of points, got shape {l.shape}")
    if not np.all(np.isfinite(l)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(l), axis=1))[0])
        raise ProfileError(f"{name}, loop {k}: non-finite coordinate (NaN or Inf) at vertex {bad}")
    # Tolerate explicitly closed loops and repeated consecutive vertices: drop the duplicates.
    if len(l) >= 2:
        scale = max(float(np.max(np.ptp(l, axis=0))), 1e-300)
        same_as_next = np.all(np.abs(l - np.roll(l, -1, axis=0)) <= 1e-12 * scale, axis=1)
        l = l[~same_as_next] if not np.all(same_as_next) else l[:1]
    if len(l) < 3:
        raise ProfileError(f"{name}, loop {k}: a closed loop needs at least 3 distinct vertices, got {len(l)}")
    return l


def profile_from_polygons(loops: Sequence[np.ndarray], name: str = "user", smooth: bool = False) -> Profile:
    """Build a :class:`Profile` from user polygons (micrometres), in any orientation and order.

    The loop containing all others becomes the outer boundary (made counter-clockwise), the
    others become holes (made clockwise). A repeated closing vertex is dropped. With
    ``smooth=False`` the polygon is the shape: vertex normals are averaged facet normals and
    tracers use flat facets. With ``smooth=True`` the vertices are taken as samples of a smooth
    curve: normals come from a periodic cubic spline through them (chord-length parameter).
    Raises :class:`ProfileError` naming the offending loop (in the caller's numbering).
    """
    cleaned = [_clean_loop(l, k, name) for k, l in enumerate(loops)]
    if not cleaned:
        raise ProfileError(f"{name}: no loops given")
    # The outer loop is the one of largest area; validate_loops then checks containment.
    areas = [abs(_signed_area(l)) for l in cleaned]
    outer = int(np.argmax(areas))
    order = [outer] + [k for k in range(len(cleaned)) if k != outer]
    ordered = [cleaned[k] for k in order]
    validate_loops(ordered, name=name, oriented=False, labels=order)
    oriented = []
    for j, l in enumerate(ordered):
        ccw = _signed_area(l) > 0
        want_ccw = j == 0
        oriented.append(l if ccw == want_ccw else l[::-1].copy())
    if smooth:
        normals = [_spline_normals(l) for l in oriented]
    else:
        normals = [_vertex_normals_from_facets(l) for l in oriented]
    return Profile(name=name, loops=tuple(oriented), normals=tuple(normals), smooth=smooth)


def _spline_normals(loop: np.ndarray) -> np.ndarray:
    """Normals (right of travel) of the periodic cubic spline through the loop's vertices."""
    closed = np.vstack([loop, loop[:1]])
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    u = np.concatenate([[0.0], np.cumsum(seg)])
    spl = CubicSpline(u, closed, bc_type="periodic")
    t = spl(u[:-1], 1)
    n = np.stack([t[:, 1], -t[:, 0]], axis=1)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


# --------------------------------------------------------------------------------------------
# Smooth analytic loops
# --------------------------------------------------------------------------------------------

def _resample_curve(curve: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
                           n: int) -> tuple[np.ndarray, np.ndarray]:
    """Sample a closed parametric curve t in [0, 2pi) at ``n`` points, evenly in a mixed measure.

    ``curve(t)`` returns (points, tangents). Half of the measure is arc length, half is the
    turning of the tangent, so the vertices are evenly spaced along gently curved parts and
    dense where the curve turns sharply (the tips of a slit lumen): both the chord length and
    the angle between neighbouring normals stay small.
    """
    m = max(64 * n, 4096)
    t = np.linspace(0.0, 2.0 * np.pi, m + 1)
    p, tan = curve(t)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    ang = np.arctan2(tan[:, 1], tan[:, 0])
    turn = np.concatenate([[0.0], np.cumsum(np.abs(np.angle(np.exp(1j * np.diff(ang)))))])
    mu = s / s[-1] + turn / max(turn[-1], 1e-300)
    targets = np.arange(n) * (mu[-1] / n)
    tn = np.interp(targets, mu, t)
    return curve(tn)


def _loop_from_curve(curve, n: int, hole: bool) -> tuple[np.ndarray, np.ndarray]:
    """Points and out-of-material normals of a counter-clockwise curve (reversed for a hole)."""
    p, tan = _resample_curve(curve, n)
    nrm = np.stack([tan[:, 1], -tan[:, 0]], axis=1)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    if _signed_area(p) < 0:  # the curve ran clockwise: flip it to counter-clockwise
        p, nrm = p[::-1].copy(), -nrm[::-1]
    if hole:
        # Air inside, material outside: clockwise, normals pointing into the hole.
        p, nrm = p[::-1].copy(), -nrm[::-1]
    return np.ascontiguousarray(p), np.ascontiguousarray(nrm)


def fourier_loop(n: int = 512, cos: Sequence[float] = (), sin: Sequence[float] = (),
                 scale: tuple[float, float] = (1.0, 1.0), rotation: float = 0.0,
                 center: tuple[float, float] = (0.0, 0.0), radius: float = 1.0,
                 hole: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """A closed curve r(t) = radius (1 + sum_k cos[k-1] cos(k t) + sin[k-1] sin(k t)), then affine.

    The polar curve is scaled by ``scale`` = (sx, sy), rotated by ``rotation`` and moved to
    ``center``. Normals are analytic: the polar tangent, mapped by the same linear map.
    Returns (points, normals) with ``n`` vertices (spaced evenly in arc length plus turning),
    oriented as an outer boundary, or as a hole when ``hole``.
    """
    a = np.asarray(cos, dtype=np.float64)
    b = np.asarray(sin, dtype=np.float64)
    k_a = np.arange(1, len(a) + 1)
    k_b = np.arange(1, len(b) + 1)
    sx, sy = scale
    c, s = np.cos(rotation), np.sin(rotation)
    lin = np.array([[c, -s], [s, c]]) @ np.diag([sx, sy])

    def curve(t):
        t = np.asarray(t, dtype=np.float64)
        r = 1.0 + np.sum(a[:, None] * np.cos(k_a[:, None] * t), axis=0) + np.sum(
            b[:, None] * np.sin(k_b[:, None] * t), axis=0)
        dr = np.sum(-k_a[:, None] * a[:, None] * np.sin(k_a[:, None] * t), axis=0) + np.sum(
            k_b[:, None] * b[:, None] * np.cos(k_b[:, None] * t), axis=0)
        ct, st = np.cos(t), np.sin(t)
        p = radius * np.stack([r * ct, r * st], axis=1)
        tan = np.stack([dr * ct - r * st, dr * st + r * ct], axis=1)
        return p @ lin.T + np.asarray(center), tan @ lin.T

    return _loop_from_curve(curve, n, hole)


def spline_loop(control_points: np.ndarray, n: int = 512, hole: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """A closed periodic cubic spline through ``control_points`` (M,2), sampled at ``n`` points.

    Normals come from the spline's exact derivative. Returns (points, normals) oriented as an
    outer boundary, or as a hole when ``hole``.
    """
    cp = np.asarray(control_points, dtype=np.float64)
    closed = np.vstack([cp, cp[:1]])
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    u = np.concatenate([[0.0], np.cumsum(seg)])
    u = u * (2.0 * np.pi / u[-1])
    spl = CubicSpline(u, closed, bc_type="periodic")

    def curve(t):
        t = np.mod(t, 2.0 * np.pi)
        return spl(t), spl(t, 1)

    return _loop_from_curve(curve, n, hole)


def circle(n: int = 512, radius: float = 0.5, name: str = "circle") -> Profile:
    """A circle of the given radius (default diameter 1) with exact radial normals."""
    p, nrm = fourier_loop(n, radius=radius)
    return Profile(name=name, loops=(p,), normals=(nrm,), smooth=True)


def ellipse(a: float, b: float, n: int = 512, name: str = "ellipse") -> Profile:
    """An ellipse with semi-axes ``a`` (along x) and ``b`` (along y), analytic normals."""
    p, nrm = fourier_loop(n, scale=(a, b))
    return Profile(name=name, loops=(p,), normals=(nrm,), smooth=True)


# --------------------------------------------------------------------------------------------
# Built-in library (modelled on the SEM cross sections of the paper's Figure 2)
# --------------------------------------------------------------------------------------------

_KIND_ID = {k: i for i, k in enumerate(BUILTIN_KINDS)}


def default_diameter_um(kind: str) -> float:
    """Mid-range Table 1 diameter (micrometres) for a built-in kind."""
    base = "cotton" if kind == "mercerizedCotton" else kind
    if base not in TABLE1_DIAMETER_UM:
        raise ValueError(f"unknown fiber kind {kind!r}; expected one of {BUILTIN_KINDS}")
    lo, hi = TABLE1_DIAMETER_UM[base]
    return 0.5 * (lo + hi)


def _variant_rng(kind: str, seed: int, index: int) -> np.random.Generator:
    # Variant i depends only on (kind, seed, i): asking for more variants keeps the first ones.
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, _KIND_ID[kind], int(index)])


def _make(name: str, outer, holes=()) -> Profile:
    loops = (outer[0],) + tuple(h[0] for h in holes)
    normals = (outer[1],) + tuple(h[1] for h in holes)
    prof = Profile(name=name, loops=loops, normals=normals, smooth=True).centered()
    return prof.scaled_to_diameter(1.0).validate()


def _polyester(i: int, rng: np.random.Generator, n: int) -> Profile:
    # Melt-spun through round spinnerets: a circle. All variants are the same circle.
    return _make(f"polyester-{i}", fourier_loop(n))


def _silk(i: int, rng: np.random.Generator, n: int) -> Profile:
    # Degummed fibroin filaments: flat triangles with rounded corners, aspect 1.3-2.5.
    a3 = rng.uniform(0.07, 0.115)          # triangularity (convex below 1/8)
    a2 = rng.uniform(-0.03, 0.03)
    b2 = rng.uniform(-0.03, 0.03)
    a4 = rng.uniform(-0.012, 0.012)
    aspect = rng.uniform(1.3, 2.5)
    tilt = rng.uniform(-0.25, 0.25)
    outer = fourier_loop(n, cos=(0.0, a2, a3, a4), sin=(0.0, b2), scale=(1.0, 1.0 / aspect),
                         rotation=tilt)
    return _make(f"silk-{i}", outer)


def _cotton(i: int, rng: np.random.Generator, n: int) -> Profile:
    # Collapsed, bent tube: a kidney / bean outline (one long side concave) with a slit-like
    # lumen following the bend. Every third variant has a thin wall (a wide, open lumen).
    thin_wall = i % 3 == 2
    for attempt in range(64):
        half_w = rng.uniform(0.42, 0.58) if not thin_wall else rng.uniform(0.5, 0.62)
        bend = rng.uniform(0.1, 0.25)        # banana bend of the whole section
        dent = rng.uniform(0.05, 0.15)       # extra flattening of the concave side
        skew = rng.uniform(-0.08, 0.08)
        tilt = rng.uniform(-0.3, 0.3)
        t = np.linspace(0.0, 2.0 * np.pi, 12, endpoint=False)
        outer_cp = np.stack([np.cos(t), half_w * np.sin(t)], axis=1)
        top = outer_cp[:, 1] > 0
        outer_cp[top, 1] *= 1.0 - dent * np.cos(0.5 * np.pi * outer_cp[top, 0]) ** 2
        if thin_wall:
            lumen_len, lumen_w = rng.uniform(0.72, 0.82), rng.uniform(0.45, 0.6) * half_w
        else:
            lumen_len, lumen_w = rng.uniform(0.5, 0.75), rng.uniform(0.06, 0.2) * half_w
        lumen_dy = -0.3 * dent * half_w

        def bent(cp):
            cp = cp.copy()
            cp[:, 1] += bend * (cp[:, 0] ** 2 - 1.0) + skew * cp[:, 0] ** 3
            return cp

        c, s = np.cos(tilt), np.sin(tilt)
        rot = np.array([[c, -s], [s, c]])

        def lumen_curve(tt, a=lumen_len, b=lumen_w, bend=bend, skew=skew, rot=rot):
            # An ellipse bent like the outline; analytic tangent through the bending map.
            x, y = a * np.cos(tt), b * np.sin(tt) + lumen_dy
            dx, dy = -a * np.sin(tt), b * np.cos(tt)
            p = np.stack([x, y + bend * (x * x - 1.0) + skew * x ** 3], axis=1)
            tan = np.stack([dx, dy + (2.0 * bend * x + 3.0 * skew * x * x) * dx], axis=1)
            return p @ rot.T, tan @ rot.T

        outer = spline_loop(bent(outer_cp) @ rot.T, n)
        lumen = _loop_from_curve(lumen_curve, max(64, n // 2), hole=True)
        try:
            return _make(f"cotton-{i}", outer, [lumen])
        except ProfileError:
            continue
    raise RuntimeError("could not build a valid cotton variant")  # pragma: no cover


def _mercerized(i: int, rng: np.random.Generator, n: int) -> Profile:
    # Caustic soda swells the fiber: rounder, a small lumen, sometimes closed altogether.
    ecc = rng.uniform(1.05, 1.3)
    a2 = rng.uniform(-0.03, 0.03)
    a3 = rng.uniform(-0.04, 0.04)
    b3 = rng.uniform(-0.03, 0.03)
    a4 = rng.uniform(-0.015, 0.015)
    outer = fourier_loop(n, cos=(0.0, a2, a3, a4), sin=(0.0, 0.0, b3), scale=(1.0, 1.0 / ecc),
                         rotation=rng.uniform(-0.4, 0.4))
    if i % 2 == 1:
        return _make(f"mercerizedCotton-{i}", outer)
    r = rng.uniform(0.06, 0.14)
    lumen = fourier_loop(max(64, n // 4), cos=(0.0, rng.uniform(0.0, 0.1)), radius=r,
                         scale=(1.0, rng.uniform(0.5, 0.9)), rotation=rng.uniform(0, np.pi),
                         center=(rng.uniform(-0.08, 0.08), rng.uniform(-0.05, 0.05)), hole=True)
    return _make(f"mercerizedCotton-{i}", outer, [lumen])


def _wool(i: int, rng: np.random.Generator, n: int) -> Profile:
    # Near-elliptical cortex: major/minor axis ratio 1.1-1.3, slightly irregular.
    ratio = rng.uniform(1.1, 1.3)
    a3 = rng.uniform(-0.015, 0.015)
    b3 = rng.uniform(-0.015, 0.015)
    a4 = rng.uniform(-0.01, 0.01)
    outer = fourier_loop(n, cos=(0.0, 0.0, a3, a4), sin=(0.0, 0.0, b3), scale=(1.0, 1.0 / ratio),
                         rotation=rng.uniform(-0.3, 0.3))
    return _make(f"wool-{i}", outer)


_BUILDERS = {
    "polyester": _polyester,
    "silk": _silk,
    "cotton": _cotton,
    "mercerizedCotton": _mercerized,
    "wool": _wool,
}


def builtin_profiles(kind: str, count: int, seed: int = 0, n: int = 512) -> list[Profile]:
    """``count`` deterministic cross-section variants of a fiber ``kind``, unscaled.

    Kinds: ``polyester`` (circle; all variants identical), ``silk`` (flat rounded triangles of
    varying aspect), ``cotton`` (bean / kidney outlines with a lumen; every third variant has a
    thin wall), ``mercerizedCotton`` (rounder, swollen; small lumen in even variants, closed in
    odd ones), ``wool`` (near-elliptical, axis ratio 1.1-1.3). Every profile is centred on its
    smallest enclosing circle, with circumscribed diameter 1: scale it with
    :meth:`Profile.scaled_to_diameter` (see :func:`builtin_profiles_um`). Variant ``i`` depends
    only on (kind, seed, i). ``n`` is the number of vertices of the outer loop.
    """
    if kind not in _BUILDERS:
        raise ValueError(f"unknown fiber kind {kind!r}; expected one of {BUILTIN_KINDS}")
    if count < 0:
        raise ValueError("count must be >= 0")
    return [_BUILDERS[kind](i, _variant_rng(kind, seed, i), n) for i in range(int(count))]


def builtin_profiles_um(kind: str, count: int, seed: int = 0, diameter_um: float | None = None,
                        n: int = 512) -> list[Profile]:
    """:func:`builtin_profiles` scaled to ``diameter_um`` (default: the Table 1 mid-range)."""
    d = default_diameter_um(kind) if diameter_um is None else float(diameter_um)
    return [p.scaled_to_diameter(d) for p in builtin_profiles(kind, count, seed, n)]
