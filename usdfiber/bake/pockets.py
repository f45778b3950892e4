"""Directions that leave a concave pocket of an extruded outline for good, edge by edge.

An edge of the outer loop that is not on the loop's convex hull lies in a *pocket*: the region
between a run of such edges (the chain, from hull vertex ``V_a`` to hull vertex ``V_b``) and the
hull edge ``V_a V_b`` that closes it (the lid). Light leaving the fiber from a point ``P`` of the
chain travels in the pocket until it meets the chain again or crosses the lid; past the lid it
is outside the hull and meets nothing more. Seen from ``P``, the chain behind it (towards
``V_a``) covers the directions from the edge's own line up to an elevation ``Theta_back``, and
the chain ahead (towards ``V_b``) those up to ``Theta_ahead`` measured from the other end of
the line; every direction strictly between the two leaves for good.

For one edge, both elevations are bounded by their values at the corners of the small
rectangle the tracer's exit points lie in (the edge, pushed out by the ray offset): seen from a
point that moves over a convex region that no part of the chain crosses, the direction to a
fixed point turns monotonically, so its extremes are at the region's corners, and a polygon's
chain is covered by its vertices (the direction to the points of a segment is extreme at its
ends). Where the next or previous edge turns back so sharply that a corner of the rectangle lies
behind it (a slot's corner of more than 90 degrees), the edge gets no wedge. The wedge between the bounds,
narrowed by ``margin`` radians on each side, is therefore clear of the fiber for every exit from
that edge (tested against an exact ray-polygon intersection in ``tests/bake/test_pockets.py``).
The tracer skips the ray cast of an exit whose direction is inside its edge's wedge; the cast
would miss, so the estimate is the same.
"""
from __future__ import annotations

import numpy as np

__all__ = ["escape_wedges", "in_wedge"]


def _elevations(chain: np.ndarray, origin: np.ndarray, t: np.ndarray, n: np.ndarray) -> float:
    """Highest elevation, from the direction ``t`` towards ``n``, of the points ``chain`` (in
    order along the outline from the edge outwards) seen from ``origin``, unwrapped along the
    chain so that a chain that curls over the edge counts past pi."""
    rel = chain - origin
    ang = np.arctan2(rel @ n, rel @ t)
    return float(np.max(np.unwrap(ang)))


def _side(a: np.ndarray, b: np.ndarray, p: np.ndarray) -> float:
    """Signed distance of ``p`` from the line of edge a -> b, positive on its outer side (right
    of travel)."""
    e = b - a
    return float((e[1] * (p[0] - a[0]) - e[0] * (p[1] - a[1])) / max(np.hypot(*e), 1e-300))


def escape_wedges(loop: np.ndarray, hull: np.ndarray, offset: tuple[float, float],
                  margin: float = 2e-3) -> np.ndarray:
    """(n, 4) float64: for each edge ``i`` (vertex i to i + 1) of the counter-clockwise outer
    ``loop``, the wedge of exit directions that leave the fiber for good, as two 2D vectors
    ``(Lx, Ly, Hx, Hy)``: a direction ``d`` is inside when ``Lx dy - Ly dx > 0`` and
    ``dx Hy - dy Hx > 0`` (:func:`in_wedge`). All zeros (no direction inside) for edges on the
    hull (their exits always leave) and for pockets whose chain hides every direction.

    ``offset`` = (lo, hi): the exit points lie between ``lo`` and ``hi`` outside the edge's
    line (the tracer's offset along the face normal, with its rounding); ``margin``: radians
    taken off each side of the wedge (the rounding of the directions and points the kernel
    compares, and of the exit points along the edge)."""
    lp = np.asarray(loop, dtype=np.float64)
    m = len(lp)
    hull = np.asarray(hull, dtype=bool)
    out = np.zeros((m, 4))
    if hull.all() or not hull.any():
        return out
    lo, hi = (float(x) for x in offset)
    for i in np.flatnonzero(~hull):
        # The pocket's chain: back to the vertex that starts the run of off-hull edges, ahead to
        # the vertex that ends it (both on the hull).
        a = i
        while not hull[(a - 1) % m]:
            a -= 1
        b = i + 1
        while not hull[b % m]:
            b += 1
        back = lp[np.arange(i, a - 1, -1) % m]         # V_i, V_{i-1}, ..., V_a
        ahead = lp[np.arange(i + 1, b + 1) % m]        # V_{i+1}, ..., V_b
        A, B = lp[i], lp[(i + 1) % m]
        e = B - A
        length = float(np.hypot(*e))
        if length <= 0.0:
            continue
        t = e / length
        n = np.array([t[1], -t[0]])                    # outward: right of travel
        corners = [P + s * n for P in (A, B) for s in (lo, hi)]
        # No edge of the chain may cross the rectangle: the rectangle must lie on the open side
        # of the chain's edges before and after this one (a hull vertex ends the chain).
        prev, nxt = lp[(i - 1) % m], lp[(i + 2) % m]
        if (i != a and min(_side(prev, A, c) for c in corners[:2]) <= 0.0) or (
                (i + 1) % m != b % m and min(_side(B, nxt, c) for c in corners[2:]) <= 0.0):
            continue
        th_back = max(_elevations(back, P, -t, n) for P in corners)
        th_ahead = max(_elevations(ahead, P, t, n) for P in corners)
        a_lo = max(th_back, 0.0) + margin             # from -t towards n
        a_hi = max(th_ahead, 0.0) + margin            # from +t towards n
        if a_lo + a_hi >= np.pi:
            continue
        u_lo = np.cos(a_lo) * -t + np.sin(a_lo) * n
        u_hi = np.cos(a_hi) * t + np.sin(a_hi) * n
        # The sense of the rotation from -t towards n, folded into the vectors so that both
        # tests read "> 0".
        s = np.sign((-t[0]) * n[1] - (-t[1]) * n[0])
        out[i] = np.concatenate([s * u_lo, s * u_hi])
    return out


def in_wedge(wedge: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Whether the 2D directions ``d`` (..., 2) lie inside ``wedge`` (..., 4) (numpy; the
    tracer's kernel computes the same two products)."""
    w = np.asarray(wedge, dtype=np.float64)
    d = np.asarray(d, dtype=np.float64)
    c1 = w[..., 0] * d[..., 1] - w[..., 1] * d[..., 0]
    c2 = d[..., 0] * w[..., 3] - d[..., 1] * w[..., 2]
    return (c1 > 0.0) & (c2 > 0.0)
