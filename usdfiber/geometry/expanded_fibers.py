"""The fiber curves of one expanded yarn, as uniform cubic B-spline control points.

The generator's samples X_i are corrected by one step towards interpolation,
P_i = X_i - (X_{i-1} - 2 X_i + X_{i+1}) / 6, with phantom end points by quadratic
extrapolation; the B-spline then follows the samples to O(h^4) (see
:mod:`usdfiber.geometry.yarn`, "Sampling and B-splines").
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from usdfiber.geometry.curves import CurveGeometry
from usdfiber.spec.yarn import YarnError

__all__ = ["ExpandedFibers", "KIND_HAIR", "KIND_LOOP", "KIND_PLY", "curve_offsets",
           "second_difference"]

#: ``ExpandedFibers.kind`` values: a ply fiber, a hair flyaway, a loop flyaway.
KIND_PLY, KIND_HAIR, KIND_LOOP = 0, 1, 2


def curve_offsets(counts: np.ndarray) -> np.ndarray:
    """Index of each curve's first point."""
    return np.cumsum(counts) - counts


def second_difference(x: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """X_{i-1} - 2 X_i + X_{i+1} within each curve. At curve ends the neighbour's value: the
    second difference with the quadratically extrapolated phantom point
    X_{-1} = 3 X_0 - 3 X_1 + X_2 (0 for curves of 2 points, whose phantom is 2 X_0 - X_1)."""
    out = np.empty_like(x)
    if len(x) < 3:
        out[:] = 0.0
        return out
    counts = np.asarray(counts, np.int64)
    d = np.diff(x, axis=0)
    np.subtract(d[1:], d[:-1], out=out[1:-1])
    off = curve_offsets(counts)
    last = off + counts - 1
    three = counts >= 3
    out[off[three]] = out[off[three] + 1]
    out[last[three]] = out[last[three] - 1]
    out[off[~three]] = 0.0
    out[last[~three]] = 0.0
    return out


def _phantoms(p: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Phantom control points before and after each curve: quadratic extrapolation
    3 P_0 - 3 P_1 + P_2 (linear 2 P_0 - P_1 for curves of 2 points)."""
    off = curve_offsets(counts)
    last = off + counts - 1
    before = 2.0 * p[off] - p[off + 1]
    after = 2.0 * p[last] - p[last - 1]
    three = counts >= 3
    o3, l3 = off[three], last[three]
    before[three] = 3.0 * p[o3] - 3.0 * p[o3 + 1] + p[o3 + 2]
    after[three] = 3.0 * p[l3] - 3.0 * p[l3 - 1] + p[l3 - 2]
    return before, after


@dataclass
class ExpandedFibers:
    """Fiber curves of one yarn. Curve f owns ``points[offsets[f] : offsets[f] + counts[f]]``.

    ``points`` are uniform cubic B-spline control points; :meth:`to_curve_geometry` adds the
    phantom end points (quadratic extrapolation), and the spline then follows the model's
    samples to O(h^4) (O(h^3) on end segments; module doc). :meth:`curve_points` gives the
    spline's value at each control point's knot. ``kind``: 0 ply fiber, 1 hair
    flyaway, 2 loop flyaway. ``fiber``: source fiber id (ply * fibersPerPly + j) of ply fibers
    (several curves per fiber with staple fibers) and of a loop's parent; -1 for hairs.
    ``arclength``: the yarn arc length whose cross section each point lies in.
    ``ply_centres`` (plies, M, 3): the ply centre lines on the sampling grid ``grid_s``.
    """

    points: np.ndarray
    counts: np.ndarray
    kind: np.ndarray
    ply: np.ndarray
    fiber: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    arclength: np.ndarray = field(default_factory=lambda: np.zeros(0))
    ply_centres: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 3)))
    grid_s: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def curve_count(self) -> int:
        return int(len(self.counts))

    @property
    def offsets(self) -> np.ndarray:
        return curve_offsets(self.counts)

    def curve(self, f: int) -> np.ndarray:
        """Control points of curve ``f``."""
        o = int(self.offsets[f])
        return self.points[o:o + int(self.counts[f])]

    def curve_points(self) -> np.ndarray:
        """(P, 3) positions of the rendered B-spline curves at their knots (the point of each
        control point on its curve): P_i + (P_{i-1} - 2 P_i + P_{i+1}) / 6 with the phantoms
        of :meth:`to_curve_geometry` at the ends."""
        return self.points + second_difference(self.points, self.counts) / 6.0

    def to_curve_geometry(self, fiber_diameter: float) -> CurveGeometry:
        """Uniform cubic B-spline segments for Mitsuba's ``bsplinecurve``: each curve of n points
        gets phantom end points 3 P_0 - 3 P_1 + P_2 and 3 P_{n-1} - 3 P_{n-2} + P_{n-3}
        (2 P_0 - P_1, 2 P_1 - P_0 for n = 2) and n - 1 segments, whose knots are
        :meth:`curve_points`; radius fiber_diameter / 2 everywhere; ``segment_curve`` is the
        curve index in this object (``counts`` order)."""
        d = float(fiber_diameter)
        if not (math.isfinite(d) and d > 0):
            raise YarnError(None, None, None,
                            f"fiber_diameter must be finite and > 0, got {fiber_diameter!r}")
        counts = np.asarray(self.counts, np.int64)
        nc = len(counts)
        if nc and counts.min() < 2:
            raise YarnError(None, None, None, "every fiber curve needs at least 2 points")
        ext_counts = counts + 2
        ext_off = curve_offsets(ext_counts)
        pts = np.empty((int(ext_counts.sum()), 3))
        curve_of = np.repeat(np.arange(nc), counts)
        pts[np.arange(len(self.points)) + 2 * curve_of + 1] = self.points
        pts[ext_off], pts[ext_off + ext_counts - 1] = _phantoms(self.points, counts)
        nseg = counts - 1
        seg_curve = np.repeat(np.arange(nc, dtype=np.int64), nseg)
        seg_k = np.arange(len(seg_curve), dtype=np.int64) - curve_offsets(nseg)[seg_curve]
        return CurveGeometry(pts, np.full(len(pts), 0.5 * d), ext_off[seg_curve] + seg_k,
                             seg_curve, nc, [])
