"""Procedural expansion of yarn centre lines into fiber curves (pure numpy, vectorized).

The parts, one concept per module: :mod:`~usdfiber.geometry.yarn_centre` (centre line and
frames, Y1), :mod:`~usdfiber.geometry.yarn_plies` (Y2, Y6), :mod:`~usdfiber.geometry.yarn_fibers`
(Y3-Y6, staples), :mod:`~usdfiber.geometry.yarn_flyaways` (hairs, loops, Y7),
:mod:`~usdfiber.geometry.yarn_random` (random streams) and
:mod:`~usdfiber.geometry.expanded_fibers` (the B-spline output); the values come from the
yarn spec, :class:`usdfiber.spec.yarn.YarnParams`.

The model is the procedural yarn of Zhao, Luan and Bala 2016, "Fitting Procedural Yarn Models
for Realistic Cloth Rendering" (SIGGRAPH 2016, Section 4.1; after Schroeder et al. 2015), driven
by the values of FiberYarnAPI (``schema/schema.usda``). Equation numbers below are this module's
own (Zhao 2016's equation numbers are given where they exist: (1)-(4) of its Section 4.1).

Frames. The yarn centre line is a polyline C(s) over its arc length s in [0, L]. The yarn
cross section at s is spanned by a rotation-minimizing frame (n(s), b(s) = t(s) x n(s)),
computed by double reflection (Wang et al. 2008, via ``geometry.curves.reference_normals``) on the
sampling grid, so that (n, b, t) is right-handed and does not flip. A cross-section point
(x, y) lies at::

    P(s) = C(s) + k(s) (x n(s) + y b(s))                                              (Y1)

with k(s) = ``radius_scale`` (the authored curve width relative to the nominal yarn width, for
example). An angle that grows with s from n towards b is a right-handed helix: Z twist (the
schema's convention: S left-handed, Z right-handed); S twist is a negative signed twist.

Plies (Zhao 2016 eq. 1). Ply i of N sits at the angle and distance::

    phi_i(s) = 2 pi i / N + 2 pi T_ply s,    c_i(s) = d (cos phi_i, sin phi_i)        (Y2)

T_ply = signed ply twist in turns per scene unit (1 / alpha_ply). d = R_ply / sin(pi / N) puts
N circular plies of radius R_ply in contact (d = R_ply for 2 plies, 0 for 1): the "touching
plies" rule of :func:`usdfiber.spec.yarn.ply_distance`, whose nominal yarn diameter
2 R_ply (1 + 1 / sin(pi / N)) (:func:`usdfiber.spec.yarn.yarn_diameter`) the presets and the
validators use too, so the nominal yarn radius is d + R_ply.

Fibers in a ply (Zhao 2016 eqs. 2-4). Fiber j has a rest radius R_j (fraction of R_ply) drawn
by Zhao's rejection sampler (his Algorithm 1: a point uniform in the unit disk is accepted with
probability p(R)), so p is a density per unit *area* of the ply cross section and the pdf of
R_j is proportional to R p(R)::

    p(R) = (1 - 2 eps) ((e - exp(R)) / (e - 1))^beta + eps,     R in [0, 1]           (Y3)

an initial angle theta_j (uniform) and a migration phase theta_mig,j (uniform). Along the yarn::

    theta_j(s) = theta_j + 2 pi T_fib s                                               (Y4)
    r_j(s) = R_j R_ply [rho_min + (rho_max - rho_min)
                        (cos(2 pi |T_fib| s / P_mig + theta_mig,j) + 1) / 2]                 (Y5)

(Y5) is Zhao's r(theta) = R_i [rho_min + (rho_max - rho_min)(cos(s theta + theta_i^mig) + 1)/2]
with s = 1 / P_mig (P_mig = yarn:fiber:migrationPeriod, in turns of fiber twist) and the
constant s theta_j absorbed into the random phase. The angle theta is measured in the ply's own
frame (radial = away from the yarn centre, tangential = +90 degrees), which rotates with phi_i;
the ply cross section is compressed to an ellipse there (Zhao 2016's e_N, e_T)::

    (x, y) = c_i + Rot(phi_i) (e_N r_j cos theta_j, e_T r_j sin theta_j)              (Y6)

Staple fibers. With yarn:fiber:stapleLength = l > 0 each fiber path is cut every l of yarn
length, starting at a random offset in [0, l) per fiber (continuous filament when l = 0).

Flyaways (Zhao 2016 Section 4.1, "Flyaway fibers"): extra curves, kind 1 (hair) and kind 2
(loop); their numbers are Poisson with mean density x L, per yarn.

- Hair: a fiber end that leaves the ply and ends free outside the yarn. Zhao's hair has linear
  r, z and theta along it; here theta_span = 0 and the ply twist is frozen at the exit point,
  which makes the hair a straight line in the cross-section frame of its exit point: it starts
  at a depth delta ~ U(0.2, 0.6) R_ply inside the ply, exits through the ply boundary at a
  random angle (on the outer side, |angle| < 60 degrees from the ply's radial direction, when
  N > 1), and extends for the hair length h ~ N(mean, std) (truncated at 0) beyond it, at an
  elevation alpha ~ U(15, 45) degrees from the yarn axis in a random axial direction, away
  from the yarn centre. The schema gives no elevation or depth: those ranges are ours.
- Loop: a stretch of a migrating ply fiber pulled out of the ply (Zhao: loops form where a
  migrating fiber is at its outermost). A random parent fiber of a random ply; the loop is
  centred at the parent's migration maximum nearest to a uniform random position (a uniform
  position when the fiber does not migrate), spans half a migration cycle P_mig / (2 |T_fib|)
  of yarn length, clamped to [2, 8] (R_ply + H), and rises to H ~ N(mean, std) (truncated at
  0) above the ply boundary at its middle::

      o_loop(s) = c_i(s) + (1 - w) o_j(s) + w Rot(phi_i(s)) (D + H) e_hat,  w = sin^2(pi u)   (Y7)

  with o_j the parent's offset from its ply centre (Y6), u in [0, 1] along the loop, e_hat the
  unit direction of (e_N cos theta_o, e_T sin theta_o) and D = R_ply |(e_N cos theta_o, e_T sin
  theta_o)| the ply boundary along it; theta_o is the parent's angle at the loop centre for one
  ply and uniform in +-45 degrees around the outward radial direction for N > 1 (loops stick
  out of the yarn, not into the neighbouring plies). The loop is a separate curve on top of its
  parent (Zhao edits the parent fiber itself): ply fibers are never changed by flyaways.

Sampling and B-splines. All ply fibers of a yarn are sampled on one arc-length grid with
``samples_per_turn`` samples per turn of the fastest component of (Y2)-(Y6),
f = |T_ply| + |T_fib| (+ |T_fib| / P_mig when migrating), and no coarser than the median
centre-line segment (and l / 4 for staple fibers). The control points are the samples X_i
corrected by one step towards interpolation, P_i = X_i - (X_{i-1} - 2 X_i + X_{i+1}) / 6, with
phantom end points by quadratic extrapolation (P_{-1} = 3 P_0 - 3 P_1 + P_2, likewise after the
last point; an end point's second difference is its neighbour's). The uniform cubic B-spline
then lies within O(h^4) of the model inside a curve and O(h^3) on its end segments, where raw
samples as control points give O(h^2) (the spline cuts every bend by |X''| h^2 / 6).
Measured on a 10 mm CNe 50 yarn at 12 samples per turn against a 128-per-turn expansion of the
same fibers: largest deviation 0.08 um (S ply / Z fiber twist) and 0.39 um (Z / Z twist with
migration (0.7, 1.2), the fiber circling its ply fastest), i.e. 1 % and 4 % of the cotton fiber
radius (9.25 um); raw samples as control points: 0.74 um and 2.5 um.
``ExpandedFibers.curve_points`` gives the B-spline at its knots (= the samples to O(h^4)).

Level of detail: ``fiber_fraction`` keeps the first round(fraction x count) fibers of a fixed
random permutation of all plies x fibersPerPly fibers (and likewise of the hairs and of the
loops): fewer fibers are always a subset of more, each with identical geometry.

Simplifications (beyond those above): the ply and fiber cross sections lie in the plane normal
to the yarn centre line (not to the ply's own helical axis; exact in the limit of small helix
angles); the staple length is the same for every fiber; the centre polyline is interpolated
linearly (its tangent, for the frames, is interpolated between vertex tangents); no collision
handling between fibers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from usdfiber.geometry.expanded_fibers import KIND_HAIR, KIND_LOOP, KIND_PLY, ExpandedFibers, second_difference
from usdfiber.geometry.yarn_centre import CentreLine
from usdfiber.geometry.yarn_fibers import fiber_set, migrating, ply_fibers
from usdfiber.geometry.yarn_flyaways import hairs, loops
from usdfiber.geometry.yarn_random import STREAM_ORDER, kept_subset, random_stream
from usdfiber.spec.yarn import YarnError, YarnParams, is_real

__all__ = ["BYTES_PER_POINT", "ExpansionEstimate", "estimate_expansion", "expand_yarn"]

#: Peak bytes per output control point of :func:`expand_yarn` and its B-spline curve geometry
#: (the samples, the interpolation step, per-curve arrays and the curve conversion): measured
#: 104-124 with tracemalloc on ORA 120 and CNe 50 yarns (staple and filament);
#: tests/core/test_memory_budget.py checks that it stays an upper bound.
BYTES_PER_POINT = 200


@dataclass(frozen=True)
class ExpansionEstimate:
    """What :func:`expand_yarn` will make: curves and control points (upper bounds)."""

    curves: int
    points: int

    @property
    def bytes(self) -> int:
        """Peak bytes of the expansion (:data:`BYTES_PER_POINT` per point)."""
        return int(self.points) * BYTES_PER_POINT

    def __add__(self, other: "ExpansionEstimate") -> "ExpansionEstimate":
        return ExpansionEstimate(self.curves + other.curves, self.points + other.points)


def estimate_expansion(params: YarnParams, length: float, median_segment: float, *,
                       fiber_fraction: float = 1.0, samples_per_turn: int = 12) -> ExpansionEstimate:
    """The curves and points :func:`expand_yarn` makes for a centre line of arc ``length``
    whose samples are ``median_segment`` apart, without making them (no allocation).

    Exact for ply fibers of continuous filaments (the same grid as the expansion); staple
    pieces, hairs and loops are bounded from above (Poisson counts by their mean plus six
    standard deviations, lengths by the largest the model draws).
    """
    length = float(length)
    if not (math.isfinite(length) and length > 0):
        return ExpansionEstimate(0, 0)
    median_segment = float(median_segment) if median_segment > 0 else length
    h = _grid_spacing(params, length, median_segment, int(samples_per_turn))
    m = max(2, int(math.ceil(length / h - 1e-9)) + 1)
    fibers = max(1, int(round(float(fiber_fraction) * params.fiber_count)))
    curves, points = fibers, fibers * m
    if params.staple_length > 0:
        pieces = int(math.ceil(length / params.staple_length)) + 1
        curves, points = fibers * pieces, fibers * (m + pieces)

    def poisson_bound(mean: float) -> int:
        return int(math.ceil(mean + 6.0 * math.sqrt(mean))) if mean > 0 else 0

    R = params.ply_radius
    n_hair = poisson_bound(params.hair_density * length * fiber_fraction)
    if n_hair:
        mean, std = params.hair_length
        reach = 0.6 * R / math.sin(math.radians(15.0)) + mean + 6.0 * std
        curves += n_hair
        points += n_hair * min(4096, max(6, int(math.ceil(reach / h)) + 1))
    n_loop = poisson_bound(params.loop_density * length * fiber_fraction)
    if n_loop:
        mean, std = params.loop_height
        span = min(length, 8.0 * (R + mean + 6.0 * std))
        curves += n_loop
        points += n_loop * min(4097, max(13, int(math.ceil(span / h)) + 2))
    return ExpansionEstimate(curves, points + 2 * curves)   # + the B-spline's phantom end points


def _grid_spacing(params: YarnParams, length: float, median_segment: float, samples_per_turn: int) -> float:
    f = abs(params.ply_twist) + abs(params.fiber_twist)
    if migrating(params):
        f += abs(params.fiber_twist) / params.migration_period
    h = min(length, median_segment)
    if f > 0:
        h = min(h, 1.0 / (samples_per_turn * f))
    if params.staple_length > 0:
        h = min(h, params.staple_length / 4.0)
    return h


def expand_yarn(centre: Any, radius_scale: Any = 1.0, params: YarnParams | None = None, *,
                fiber_fraction: float = 1.0, samples_per_turn: int = 12,
                seed_offset: int = 0) -> ExpandedFibers:
    """Expand one yarn centre line into fiber curves (Zhao et al. 2016; module doc, eqs. Y1-Y7).

    ``centre``: (N, 3) polyline of the yarn centre in world space. ``radius_scale``: scale of
    the whole cross section (eq. Y1), a scalar or one value per centre point (for example the
    authored width over ``2 * params.yarn_radius``; flyaway heights and lengths scale with it
    radially, the axial extents of flyaways do not). ``fiber_fraction`` in (0, 1] keeps that
    fraction of the fibers and flyaways, always a subset of larger fractions.
    ``samples_per_turn``: samples per turn of the fastest helix component. The result depends
    only on (params, centre, radius_scale, samples_per_turn, seed, seed_offset) and the
    fraction. ``expand_yarn(centre, params)`` is accepted for radius_scale 1.
    """
    if params is None and isinstance(radius_scale, YarnParams):
        params, radius_scale = radius_scale, 1.0
    if not isinstance(params, YarnParams):
        raise TypeError(f"params must be a YarnParams, got {type(params).__name__}")
    if not (is_real(fiber_fraction) and 0.0 < fiber_fraction <= 1.0):
        raise YarnError(None, params.prim_path or None, None,
                        f"fiber_fraction must be in (0, 1], got {fiber_fraction!r}")
    if int(samples_per_turn) != samples_per_turn or samples_per_turn < 3:
        raise YarnError(None, params.prim_path or None, None,
                        f"samples_per_turn must be an integer >= 3, got {samples_per_turn!r}")
    c = CentreLine(centre, radius_scale)
    h = _grid_spacing(params, c.length, c.median_segment, int(samples_per_turn))
    m = max(2, int(math.ceil(c.length / h - 1e-9)) + 1)
    s = np.linspace(0.0, c.length, m)
    h = c.length / (m - 1)
    grid = c.build_grid(s)

    fs = fiber_set(params, seed_offset)
    ids = kept_subset(params.fiber_count, float(fiber_fraction),
                random_stream(params.seed, seed_offset, STREAM_ORDER), minimum=1)
    parts = []
    pts, counts, fib, arc, ply_centres = ply_fibers(params, c, grid, fs, ids)
    parts.append((pts, counts, np.full(len(counts), KIND_PLY), fs.ply[fib], fib, arc))
    for kind, res in ((KIND_HAIR, hairs(params, c, h, float(fiber_fraction), seed_offset)),
                      (KIND_LOOP, loops(params, c, fs, h, float(fiber_fraction), seed_offset))):
        if res is not None:
            p_, n_, f_, ply_, s_ = res
            parts.append((p_, n_, np.full(len(n_), kind), ply_, f_, s_))

    points = parts[0][0] if len(parts) == 1 else np.concatenate([p[0] for p in parts])
    counts = np.concatenate([p[1] for p in parts]).astype(np.int64)
    # One correction step towards interpolation (module doc): P = X - (second difference) / 6.
    corr = second_difference(points, counts)
    corr *= 1.0 / 6.0
    points -= corr
    del corr

    return ExpandedFibers(
        points=points,
        counts=counts,
        kind=np.concatenate([p[2] for p in parts]).astype(np.int8),
        ply=np.concatenate([p[3] for p in parts]).astype(np.int64),
        fiber=np.concatenate([p[4] for p in parts]).astype(np.int64),
        arclength=np.concatenate([p[5] for p in parts]),
        ply_centres=ply_centres,
        grid_s=s,
    )
