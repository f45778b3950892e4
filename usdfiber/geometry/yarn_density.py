"""Yarns voxelized from the yarn model's fiber density, without expanding their fibers
(:func:`voxelize_yarns`).

A yarn of the procedural model (:mod:`usdfiber.geometry.yarn`, eqs. Y1-Y6) holds, per ply,
``fibersPerPly`` fibers whose rest radii R follow the density profile p(R) per unit area
(Y3), whose initial angles theta_0 and migration phases theta_mig are uniform. At every arc
length s the fibers of a ply are therefore a sample of one distribution over (R, theta_0,
theta_mig); the expected fiber length, extinction and orientation tensor in a voxel are
integrals over it. They are computed here by quadrature: per ply, nodes at the R quantiles
of the pdf R p(R) (stratified midpoints of its inverse CDF), at equally spaced theta_0 and
theta_mig, each standing for ``fibersPerPly / nodes`` fibers. A node follows its fiber's path
(Y4-Y6, :func:`usdfiber.geometry.yarn_fibers.ply_fibers`); at arc lengths a quarter voxel
apart its piece is the path's tangent there, dP/ds (central difference), times the step:
the fiber length per yarn length, helix angles included, however coarse the step is against
the twist. Equally spaced angles integrate the second moments of the fiber directions (the
orientation tensor) exactly from 3 nodes on, so a few nodes serve voxels wider than the yarn;
finer voxels get more (about 4 per voxel width across a ply, :func:`node_counts`).

This is the ensemble mean of the expanded yarn: it has no count noise (the Jensen bias of
:mod:`usdfiber.geometry.voxelize`), and its cost grows with the yarn length over the voxel
size, not with the number of fibers. Not included: flyaways (hairs and loops, a few percent
of a yarn's fiber length at the presets' densities) and staple gaps (the cuts remove no
length); cross sections lie in the plane normal to the centre line, as in the expansion.

Homogenization bias (:func:`coverage_map`). A voxel wider than the gaps between yarns spreads
their optical depth over the gaps: a column of the cloth transmits the mean of exp(-tau) over
its area, the voxel exp(-mean tau), and by Jensen's inequality the voxel is more opaque (it
loses the gaps' transmission). Unlike the count noise of fibers in a voxel
(:func:`usdfiber.geometry.voxelize.count_noise_deficit`) this bias does not vanish for yarns
voxelized from their density: it is the weave's own structure, and on a sheer weave it is the
volume's largest error. :class:`CoverageMap` measures it on a window of the cloth: the yarns'
optical depth along the cloth's normal on a fine raster (each yarn a uniform disc of its
fibers' cross sections, ``tau = (n D / (pi r^2)) 2 sqrt(r^2 - rho^2)`` at distance rho from
its centre line), then the same raster averaged over voxel columns. Its cost follows the
window, not the cloth: the centre lines are :class:`YarnLines`, boxes over runs of their
samples, and only the runs whose boxes reach the window (or may hold its centre) are read.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Callable, Iterable, Sequence

import numpy as np

from usdfiber.geometry.curves import CurveGeometry, evaluate
from usdfiber.geometry.voxelize import (DEFAULT_BUDGET_BYTES, PIECE_FRACTION, FiberPieces, GridAccumulator, VoxelGrid,
                                        VoxelizeError, grid_size)
from usdfiber.geometry.yarn_centre import CentreFrames, CentreLine
from usdfiber.geometry.yarn_fibers import FiberSet, density_profile, migrating, ply_fibers
from usdfiber.spec.yarn import YarnError, YarnParams

__all__ = ["CoverageMap", "RUN_SAMPLES", "YarnCurve", "YarnLines", "coverage_map", "node_counts",
           "rest_radius_quantiles", "voxelize_yarns", "yarn_optical_depth", "yarn_pieces"]

#: :func:`coverage_map` counts yarns within this many yarn radii of the cloth's plane (a knit is
#: about three yarn diameters thick).
COVERAGE_SLAB_RADII = 8.0
#: Pieces deposited per chunk (memory: about 200 bytes each).
CHUNK_PIECES = 1 << 20


@dataclasses.dataclass(frozen=True)
class YarnCurve:
    """One yarn centre line: points (N, 3) and the radius scale per point (or one value)."""

    points: np.ndarray
    radius_scale: np.ndarray | float = 1.0


#: Consecutive samples of one curve under one box of :class:`YarnLines`.
RUN_SAMPLES = 32
#: Runs boxed at once by :meth:`YarnLines.from_geometry` (memory: about 100 bytes per segment).
RUNS_PER_CHUNK = 1 << 15


def _run_starts(first: np.ndarray, count: np.ndarray, size: int) -> np.ndarray:
    """The first index of each run of at most ``size`` of ``count[k]`` items from ``first[k]``."""
    runs = -(-count // size)
    within = np.arange(int(runs.sum())) - np.repeat(np.cumsum(runs) - runs, runs)
    return np.repeat(first, runs) + size * within


def _ranges(start: np.ndarray, stop: np.ndarray) -> np.ndarray:
    """The indices start[k] .. stop[k] - 1 of every k, concatenated."""
    n = stop - start
    return np.repeat(start - np.cumsum(n) + n, n) + np.arange(int(n.sum()))


class YarnLines:
    """Yarn centre lines as samples in one index space (curve k: ``curve_start[k]`` to
    ``curve_start[k + 1]``), in runs of at most :data:`RUN_SAMPLES` consecutive samples of a
    curve, each with a box that holds its samples (``run_lo``, ``run_hi``, (R, 3)). A query
    about a region of the cloth bounds every run by its box, then reads (:meth:`points`) the
    samples of the runs that may reach the region only: its work follows the region, not the
    cloth, beyond one pass over the boxes.

    From polylines (:meth:`from_curves`), or from B-spline curves sampled at ``per_segment``
    parameters per segment and at each curve's end (:meth:`from_geometry`): the samples are
    evaluated when read and the boxes are those of the segments' control points (a point of
    a uniform B-spline segment is a convex combination of its four)."""

    def __init__(self, curve_start: np.ndarray, run_start: np.ndarray, run_lo: np.ndarray, run_hi: np.ndarray,
                 read: Callable[[np.ndarray], np.ndarray]) -> None:
        self.curve_start = np.asarray(curve_start, np.int64)
        self.run_start = np.asarray(run_start, np.int64)
        self.run_stop = np.append(self.run_start[1:], self.curve_start[-1])
        self.run_curve = np.searchsorted(self.curve_start, self.run_start, side="right") - 1
        self.run_lo = run_lo
        self.run_hi = run_hi
        self._read = read
        finite = bool(np.all(np.isfinite(run_lo)) and np.all(np.isfinite(run_hi)))
        size = float(max(np.abs(run_lo).max(), np.abs(run_hi).max())) if len(run_lo) else 0.0
        #: The largest coordinate's magnitude (the scale of rounding); inf where a point is not finite.
        self.extent = size if finite else math.inf

    @property
    def curve_count(self) -> int:
        """Number of curves (of at least two samples)."""
        return len(self.curve_start) - 1

    @property
    def sample_count(self) -> int:
        """Number of samples of all curves."""
        return int(self.curve_start[-1])

    def points(self, index: np.ndarray) -> np.ndarray:
        """The samples at ``index`` (global indices), (M, 3) float64."""
        return self._read(np.asarray(index, np.int64))

    def run_samples(self, runs: np.ndarray) -> np.ndarray:
        """The global indices of the samples of ``runs``, run after run."""
        runs = np.asarray(runs, np.int64)
        return _ranges(self.run_start[runs], self.run_stop[runs])

    def nearest_along(self, origin: np.ndarray, direction: np.ndarray, xform: np.ndarray | None = None) -> np.ndarray:
        """The sample of least ``(p - origin) @ direction`` (the first among equals), (3,):
        exactly the least over every sample, reading those of the runs whose boxes may hold
        it only. ``xform``: a 4x4 row-vector transform applied first (``p @ xform[:3, :3] +
        xform[3, :3]``; the point returned is transformed). ValueError without samples."""
        if self.sample_count == 0:
            raise ValueError("no samples to find the nearest of")
        origin, direction = np.asarray(origin, np.float64), np.asarray(direction, np.float64)
        lo, hi = self.run_lo, self.run_hi
        if xform is not None:
            xf = np.asarray(xform, np.float64)
            mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
            mid = sum(mid[:, j:j + 1] * xf[j, :3] for j in range(3)) + xf[3, :3]
            half = sum(half[:, j:j + 1] * np.abs(xf[j, :3]) for j in range(3))
            lo, hi = mid - half, mid + half
            place = lambda p: p @ xf[:3, :3] + xf[3, :3]  # noqa: E731
        else:
            place = lambda p: p  # noqa: E731
        a, b = (lo - origin) * direction, (hi - origin) * direction
        lower = np.minimum(a, b).sum(axis=1)
        slack = 1e-9 * (float(np.max(np.abs(np.concatenate([lo, hi])))) + float(np.max(np.abs(origin))))
        head = (place(self.points(self.run_samples([int(np.argmin(lower))]))) - origin) @ direction
        pts = place(self.points(self.run_samples(np.flatnonzero(lower <= float(np.min(head)) + slack))))
        return pts[int(np.argmin((pts - origin) @ direction))]

    @classmethod
    def from_points(cls, points: np.ndarray) -> YarnLines:
        """Points (N, 3) as the samples of one curve (the order only places the runs); float32
        points stay so (no float64 copy of them all): their boxes and the points read are
        converted, exactly."""
        pts = np.asarray(points)
        pts = (pts if pts.dtype == np.float32 else pts.astype(np.float64)).reshape(-1, 3)
        return cls._of_polylines(pts, np.array([0, len(pts)], np.int64))

    @classmethod
    def from_curves(cls, curves: Iterable[YarnCurve]) -> YarnLines:
        """Polylines: each curve's points are its samples (curves of fewer than two points are
        left out)."""
        arrays = [p for p in (np.asarray(c.points, np.float64).reshape(-1, 3) for c in curves) if len(p) >= 2]
        pts = np.concatenate(arrays) if arrays else np.zeros((0, 3))
        return cls._of_polylines(pts, np.concatenate([[0], np.cumsum([len(p) for p in arrays], dtype=np.int64)]))

    @classmethod
    def _of_polylines(cls, pts: np.ndarray, curve_start: np.ndarray) -> YarnLines:
        run_start = _run_starts(curve_start[:-1], np.diff(curve_start), RUN_SAMPLES)
        if len(run_start):
            lo = np.minimum.reduceat(pts, run_start, axis=0).astype(np.float64)
            hi = np.maximum.reduceat(pts, run_start, axis=0).astype(np.float64)
        else:
            lo = hi = np.zeros((0, 3))
        return cls(curve_start, run_start, lo, hi, lambda index: pts[index].astype(np.float64))

    @classmethod
    def from_geometry(cls, geom: CurveGeometry, per_segment: int = 2) -> YarnLines:
        """B-spline curves sampled at ``np.linspace(0, 1, per_segment, endpoint=False)`` of each
        segment and at the end of the last, as the renderer bridge samples a yarn centre line
        (curves without segments left out); only the boxes are made here, one pass over the
        control points."""
        seg_n = np.bincount(geom.segment_curve, minlength=geom.curve_count).astype(np.int64)
        first = np.cumsum(seg_n) - seg_n                       # segments are ordered by curve
        first, seg_n = first[seg_n > 0], seg_n[seg_n > 0]
        curve_start = np.concatenate([[0], np.cumsum(per_segment * seg_n + 1)])
        per_run = max(1, RUN_SAMPLES // per_segment)
        run_seg = _run_starts(first, seg_n, per_run)
        run_curve = np.repeat(np.arange(len(first)), -(-seg_n // per_run))
        run_nseg = np.minimum(per_run, first[run_curve] + seg_n[run_curve] - run_seg)
        run_start = curve_start[run_curve] + per_segment * (run_seg - first[run_curve])
        t_of = np.linspace(0.0, 1.0, per_segment, endpoint=False)

        def read(index: np.ndarray) -> np.ndarray:
            c = np.searchsorted(curve_start, index, side="right") - 1
            local = index - curve_start[c]
            end = local == per_segment * seg_n[c]
            seg = first[c] + np.where(end, seg_n[c] - 1, local // per_segment)
            return evaluate(geom, seg, np.where(end, 1.0, t_of[local % per_segment]))[0]

        start = geom.segment_start
        if len(run_seg) and np.all(np.diff(start) > 0):
            # Control points stored in segment order (every layout curves_from_prim makes): a
            # run's lie from its first segment's first on, up to the next run's first, and
            # its last segment's other three.
            cut, last = start[run_seg], start[run_seg + run_nseg - 1]
            lo, hi = np.minimum.reduceat(geom.points, cut, axis=0), np.maximum.reduceat(geom.points, cut, axis=0)
            for j in (1, 2, 3):
                pj = geom.points[last + j]
                np.minimum(lo, pj, out=lo)
                np.maximum(hi, pj, out=hi)
            return cls(curve_start, run_start, lo, hi, read)
        lo, hi = np.empty((len(run_seg), 3)), np.empty((len(run_seg), 3))
        for r0 in range(0, len(run_seg), RUNS_PER_CHUNK):
            r1 = min(len(run_seg), r0 + RUNS_PER_CHUNK)
            s0 = run_seg[r0]
            seg_start = start[s0:run_seg[r1 - 1] + run_nseg[r1 - 1]]
            a = geom.points[seg_start]
            b = a.copy()
            for j in (1, 2, 3):
                pj = geom.points[seg_start + j]
                np.minimum(a, pj, out=a)
                np.maximum(b, pj, out=b)
            lo[r0:r1] = np.minimum.reduceat(a, run_seg[r0:r1] - s0, axis=0)
            hi[r0:r1] = np.maximum.reduceat(b, run_seg[r0:r1] - s0, axis=0)
        return cls(curve_start, run_start, lo, hi, read)


def rest_radius_quantiles(n: int, eps: float, beta: float) -> np.ndarray:
    """``n`` rest radii (fractions of R_ply) at the midpoints of n equal-probability strata of
    the pdf R p(R) on [0, 1] (eq. Y3: p is a density per unit area)."""
    r = np.linspace(0.0, 1.0, 4097)
    pdf = r * density_profile(r, eps, beta)
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (pdf[1:] + pdf[:-1]) * np.diff(r))])
    cdf /= cdf[-1]
    return np.interp((np.arange(n) + 0.5) / n, cdf, r)


def node_counts(params: YarnParams, voxel_size: float) -> tuple[int, int, int]:
    """(radii, angles, migration phases) of the quadrature per ply: about four nodes per voxel
    width across a ply (at least 2 radii and 4 angles, 16 and 64 at most), 3 migration phases
    when fibers migrate."""
    rho = params.ply_radius * max(params.ply_compression) / voxel_size
    n_r = int(min(16, max(2, math.ceil(2.0 * rho))))
    n_t = int(min(64, max(4, math.ceil(8.0 * rho))))
    n_m = 3 if migrating(params) else 1
    return n_r, n_t, n_m


def _nodes(params: YarnParams, counts: tuple[int, int, int]) -> FiberSet:
    n_r, n_t, n_m = counts
    rest = rest_radius_quantiles(n_r, *params.density_profile)
    # Angles staggered between radii so that the nodes do not line up radially.
    R, T, M = np.meshgrid(np.arange(n_r), np.arange(n_t), np.arange(n_m), indexing="ij")
    theta0 = 2.0 * math.pi * (T + (R + 0.5) / n_r) / n_t
    theta_mig = 2.0 * math.pi * (M + 0.5) / n_m
    per_ply = n_r * n_t * n_m
    ply = np.repeat(np.arange(params.plies), per_ply)
    tile = lambda a: np.tile(a.reshape(-1), params.plies)  # noqa: E731
    return FiberSet(ply=ply, rest=tile(rest[R]), theta0=tile(theta0), theta_mig=tile(theta_mig),
                    staple_offset=np.zeros(len(ply)))


def _frames_at(centre: CentreLine, s: np.ndarray) -> CentreFrames:
    """Frames at arbitrary arc lengths, interpolated from the centre line's RMF grid."""
    pos, n, b, scale = centre.frames(s)
    return CentreFrames(s, pos, np.cross(n, b), n, b, scale)


def yarn_pieces(curve: YarnCurve, params: YarnParams, *, voxel_size: float, fiber_diameter: float,
                slots: Sequence[int], source: str = "yarn") -> FiberPieces:
    """The quadrature pieces of one yarn (module docstring): about a quarter voxel long, each
    standing for ``fibersPerPly / nodes`` fibers of ``fiber_diameter``; node k has slot
    ``slots[k % len(slots)]`` (the prim's cross-section variants in equal shares)."""
    try:
        centre = CentreLine(curve.points, curve.radius_scale)
    except YarnError as exc:
        raise VoxelizeError(f"{source}: {exc}") from None
    h = PIECE_FRACTION * voxel_size
    m = max(1, int(math.ceil(centre.length / h)))
    h = centre.length / m
    s = (np.arange(m) + 0.5) * h
    # The RMF grid the frames are interpolated from, one frame per step: the frame only fixes
    # where the plies start (the fibers' angles are uniform), so it needs no finer grid than
    # the density's, and a garment's centre lines are sampled far finer than its voxels.
    grid_s = np.linspace(0.0, centre.length, m + 1)
    centre.build_grid(grid_s)
    counts = node_counts(params, voxel_size)
    nodes = _nodes(params, counts)
    ids = np.arange(len(nodes.ply))
    filament = dataclasses.replace(params, staple_length=0.0)
    # Central difference for the tangent: a step far below the fastest turn of Y2-Y6.
    fastest = abs(params.ply_twist) + abs(params.fiber_twist) * (1.0 + 1.0 / params.migration_period)
    delta = min(1e-3 * h, 1e-3 / fastest if fastest > 0 else h)
    delta = max(delta, 1e-9 * max(centre.length, 1.0))
    p0, *_ = ply_fibers(filament, centre, _frames_at(centre, s - delta), nodes, ids)
    p1, *_ = ply_fibers(filament, centre, _frames_at(centre, s + delta), nodes, ids)
    mid = 0.5 * (p0 + p1)
    vec = (p1 - p0) * (h / (2.0 * delta))
    n = len(ids)
    per_fiber = params.fibers_per_ply / (n // params.plies)
    slot_arr = np.asarray(slots, np.int64)
    return FiberPieces(mid=mid, vec=vec, count=np.full(n * m, per_fiber),
                       diameter=np.full(n * m, float(fiber_diameter)),
                       slot=np.repeat(slot_arr[np.arange(n) % len(slot_arr)], m), axis=None, source=source)


def voxelize_yarns(curves: Iterable[YarnCurve], params: YarnParams, voxel_size: float, *, fiber_diameter: float,
                   slots: Sequence[int], n_slots: int, bounds: tuple[np.ndarray, np.ndarray] | None = None,
                   budget_bytes: int = DEFAULT_BUDGET_BYTES, coarsen: bool = True, seed: int = 0,
                   source: str = "yarns") -> VoxelGrid:
    """Voxelize yarn centre lines from the yarn model's density (module docstring) into a
    :class:`~usdfiber.geometry.voxelize.VoxelGrid`, chunk by chunk (memory: the grid and
    :data:`CHUNK_PIECES` pieces). ``bounds`` default: the centre lines' bounds widened by the
    largest yarn radius and half a voxel. Budget, coarsening and errors as
    :func:`~usdfiber.geometry.voxelize.voxelize_fibers`."""
    curves = list(curves)
    if not curves:
        raise VoxelizeError(f"{source}: no yarn curves to voxelize")
    if not (math.isfinite(voxel_size) and voxel_size > 0):
        raise VoxelizeError(f"{source}: voxel size {voxel_size!r}; expected a positive finite length")
    if not (math.isfinite(fiber_diameter) and fiber_diameter > 0):
        raise VoxelizeError(f"{source}: fiber diameter {fiber_diameter!r}; expected a positive finite length")
    if len(slots) == 0 or min(slots) < 0 or max(slots) >= n_slots:
        raise VoxelizeError(f"{source}: slots {list(slots)} out of range [0, {n_slots})")
    for c in curves:
        if not np.all(np.isfinite(np.asarray(c.points, np.float64))):
            raise VoxelizeError(f"{source}: yarn points are not all finite (NaN or Inf)")
    if bounds is None:
        reach = params.max_fiber_distance * max(float(np.max(c.radius_scale)) for c in curves) + 0.5 * voxel_size
        lo = np.min([np.asarray(c.points, np.float64).min(axis=0) for c in curves], axis=0) - reach
        hi = np.max([np.asarray(c.points, np.float64).max(axis=0) for c in curves], axis=0) + reach
    else:
        lo, hi = (np.asarray(b, np.float64) for b in bounds)
    size, shape, warnings = grid_size(source, lo, hi, voxel_size, n_slots, budget_bytes, coarsen)
    acc = GridAccumulator(lo, hi, size, shape, n_slots, seed=seed, source=source)
    chunk: list[FiberPieces] = []
    held = 0

    def flush() -> None:
        nonlocal held
        if chunk:
            acc.add(FiberPieces(*(np.concatenate([getattr(p, f) for p in chunk]) for f in
                                  ("mid", "vec", "count", "diameter", "slot")), source=source))
            chunk.clear()
            held = 0

    for c in curves:
        pieces = yarn_pieces(c, params, voxel_size=size, fiber_diameter=fiber_diameter, slots=slots, source=source)
        chunk.append(pieces)
        held += len(pieces.count)
        if held >= CHUNK_PIECES:
            flush()
    flush()
    grid = acc.finish()
    grid.warnings = warnings + grid.warnings
    return grid


def yarn_optical_depth(params: YarnParams, fiber_diameter: float, rho: np.ndarray) -> np.ndarray:
    """Optical depth through a yarn at distance ``rho`` (scene units) from its centre line,
    across it: its ``fiber_count`` fibers of ``fiber_diameter`` spread uniformly over the disc
    of the yarn radius (Eq. 3 for fibers seen side on, W = D), ``(n D / (pi r^2)) 2 sqrt(r^2 -
    rho^2)``; its integral across the yarn is ``n D``, the fibers' summed width."""
    r = params.yarn_radius
    rho = np.asarray(rho, np.float64)
    chord = 2.0 * np.sqrt(np.clip(r * r - rho * rho, 0.0, None))
    return params.fiber_count * fiber_diameter / (math.pi * r * r) * chord


@dataclasses.dataclass(frozen=True)
class CoverageMap:
    """The yarns' optical depth along a cloth's normal on a square window of its local plane
    (module docstring, "Homogenization bias"). ``tau`` (n, n): per texel of ``texel`` scene
    units; ``centre`` and ``normal``: the window's place; ``axes`` (2, 3): its raster axes (the
    world axes nearest the plane, as a voxel grid's are)."""

    tau: np.ndarray
    texel: float
    centre: np.ndarray
    normal: np.ndarray
    axes: np.ndarray
    #: Centre-line samples :func:`coverage_map` read (evaluated or transformed) beyond the run
    #: boxes, and the curves that added optical depth: the map's work, which follows the window.
    points_read: int = 0
    curves_deposited: int = 0

    @property
    def coverage(self) -> float:
        """Fraction of the window the yarns cover (optical depth above 1e-3)."""
        return float(np.mean(self.tau > 1e-3))

    @property
    def transmittance(self) -> float:
        """Mean transmittance of the yarns along the normal over the window."""
        return float(np.mean(np.exp(-self.tau)))

    def _cells(self, voxel: float, phase: tuple[int, int]) -> tuple[np.ndarray, int]:
        m = max(1, int(round(voxel / self.texel)))
        n = self.tau.shape[0]
        i0, j0 = phase
        k0, k1 = (n - i0) // m, (n - j0) // m
        return self.tau[i0:i0 + k0 * m, j0:j0 + k1 * m], m

    def opacity_bias(self, voxel: float, phases: int = 4) -> float:
        """Relative excess opacity of voxel columns ``voxel`` wide over the yarns' own:
        ``(1 - T_voxels) / (1 - T_yarns) - 1`` (>= 0: Jensen), averaged over ``phases`` x
        ``phases`` offsets of the voxel lattice. 0 for voxels no wider than a texel; NaN for a
        window of no yarn or narrower than two voxels."""
        m = max(1, int(round(voxel / self.texel)))
        if m == 1:
            return 0.0
        if self.tau.shape[0] < 2 * m:
            return math.nan
        a_vox = a_yarn = 0.0
        for oi in range(phases):
            for oj in range(phases):
                t, m = self._cells(voxel, ((oi * m) // phases, (oj * m) // phases))
                ki, kj = t.shape[0] // m, t.shape[1] // m
                cell = t.reshape(ki, m, kj, m).mean(axis=(1, 3))
                a_vox += 1.0 - float(np.mean(np.exp(-cell)))
                a_yarn += 1.0 - float(np.mean(np.exp(-t)))
        return a_vox / a_yarn - 1.0 if a_yarn > 0 else math.nan

    def voxel_for_bias(self, voxel: float, bound: float) -> float:
        """The largest of ``voxel``, ``voxel / 2``, ``voxel / 4`` ... whose
        :meth:`opacity_bias` is within ``bound`` (at least a texel)."""
        h = float(voxel)
        while h > self.texel and not (self.opacity_bias(h) <= bound):
            h *= 0.5
        return max(h, self.texel)


def _plane_axes(normal: np.ndarray) -> np.ndarray:
    """Two orthonormal in-plane axes: the world axes that lie most in the plane, made
    orthogonal (a cloth in the xy plane gets x and y, as its voxels have)."""
    eye = np.eye(3)
    proj = eye - np.outer(eye @ normal, normal)
    order = np.argsort(-np.linalg.norm(proj, axis=1))
    u = proj[order[0]] / np.linalg.norm(proj[order[0]])
    v = proj[order[1]] - (proj[order[1]] @ u) * u
    return np.stack([u, v / np.linalg.norm(v)])


class _Reader:
    """Reads samples of :class:`YarnLines` and counts them (:attr:`CoverageMap.points_read`)."""

    def __init__(self) -> None:
        self.count = 0

    def __call__(self, lines: YarnLines, index: np.ndarray) -> np.ndarray:
        self.count += len(index)
        return lines.points(index)


def _slack(lines: YarnLines, origin: np.ndarray) -> float:
    """A margin far above the rounding of a coordinate, a distance or a projection (about
    1e-16 of the coordinates' size) and far below anything a yarn resolves: box bounds are
    widened by it so that no sample a box holds is ever left out."""
    return 1e-9 * (lines.extent + float(np.max(np.abs(origin))))


def _projection_bounds(lines: YarnLines, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per run, (R, k) lower and upper bounds of ``(p - origin) @ dirs.T`` over its box (to
    rounding, which :func:`_slack` covers)."""
    mid, half = 0.5 * (lines.run_lo + lines.run_hi) - origin, 0.5 * (lines.run_hi - lines.run_lo)
    # Column by column, not a matrix product: a (R, 3) x (3, k) product goes to a threaded BLAS,
    # which on a loaded machine spins for many times its work.
    centre = sum(mid[:, j:j + 1] * dirs[:, j] for j in range(3))
    reach = sum(half[:, j:j + 1] * np.abs(dirs[:, j]) for j in range(3))
    return centre - reach, centre + reach


def _box_distance(lines: YarnLines, point: np.ndarray) -> np.ndarray:
    """Per run, the distance from ``point`` to its box (a lower bound of its samples')."""
    gap = np.maximum(np.maximum(lines.run_lo - point, point - lines.run_hi), 0.0)
    return np.sqrt(np.sum(gap * gap, axis=1))


def _least(lines: YarnLines, read: _Reader, lower: np.ndarray, value: Callable[[np.ndarray], np.ndarray],
           slack: float) -> float:
    """The least ``value(samples)`` over every sample, exactly, given ``lower`` (per run, a
    bound of its samples' values): the run of the least bound gives an upper bound; only
    runs whose bound is below it are read."""
    head = value(read(lines, lines.run_samples([int(np.argmin(lower))])))
    runs = np.flatnonzero(lower <= float(np.min(head)) + slack)
    return float(np.min(value(read(lines, lines.run_samples(runs)))))


def coverage_map(curves: Sequence[YarnCurve] | YarnLines, params: YarnParams, *, fiber_diameter: float,
                 window: float, others: Sequence[tuple[Sequence[YarnCurve] | YarnLines, YarnParams, float]] = (),
                 max_texels: int = 768, source: str = "yarns") -> CoverageMap:
    """The yarns' optical depth along the cloth's normal (:class:`CoverageMap`) on a square of
    side ``window`` in the cloth's local plane, centred at the yarn point nearest the middle
    of the curves' bounds (of their points for polylines, of their control points for
    :meth:`YarnLines.from_geometry`), and within the cloth (a smaller window where the cloth is
    smaller); texels of a sixteenth of a yarn diameter (coarser when the window would exceed
    ``max_texels`` a side). The plane is the principal plane of the centre-line
    points within the window (a curved garment is flat at that scale). A yarn that crosses
    itself within the window counts once where it does. ``others``: more yarns of the same
    cloth, (curves, params, fiber diameter) per group (a weave's wefts for its warps), whose
    optical depth adds to the map; ``curves`` alone place the window.

    Curves are polylines (:class:`YarnCurve`) or :class:`YarnLines`. The cost follows the
    window, not the cloth: the nearest point, the points within the window, the cloth's
    extent along the plane (where it may cut the window) and the deposit are each computed
    exactly from the samples of the runs whose boxes may matter, so the map is the one over
    every sample; beyond one pass over the run boxes, the samples read
    (:attr:`CoverageMap.points_read`) follow the window and the yarns that cross it."""
    lines = curves if isinstance(curves, YarnLines) else YarnLines.from_curves(curves)
    if lines.curve_count == 0:
        raise VoxelizeError(f"{source}: no yarn curves to measure the coverage of")
    if not (math.isfinite(window) and window > 0):
        raise VoxelizeError(f"{source}: coverage window {window!r}; expected a positive finite length")
    if not math.isfinite(lines.extent):
        raise VoxelizeError(f"{source}: yarn points are not all finite (NaN or Inf)")
    window = float(window)
    read = _Reader()
    r = params.yarn_radius
    # The middle of the run boxes: of the samples' bounds for polylines, of the control points'
    # for B-splines. (The samples' own bounds across a weave are reached at every crest alike,
    # which no box can tell apart: reading them all is a pass over the whole cloth.)
    mid = 0.5 * (lines.run_lo.min(axis=0) + lines.run_hi.max(axis=0))
    slack = _slack(lines, mid)
    # The sample nearest the middle, the first in curve order among equals.
    dist = _box_distance(lines, mid)
    head = read(lines, lines.run_samples([int(np.argmin(dist))]))
    best = float(np.min(np.linalg.norm(head - mid, axis=1)))
    pts = read(lines, lines.run_samples(np.flatnonzero(dist <= best + slack)))
    centre = pts[int(np.argmin(np.linalg.norm(pts - mid, axis=1)))]
    slack = _slack(lines, centre)
    ball = 0.75 * window + r
    pts = read(lines, lines.run_samples(np.flatnonzero(_box_distance(lines, centre) <= ball + slack)))
    near = pts[np.linalg.norm(pts - centre, axis=1) <= ball]
    if len(near) >= 3:
        _, _, vt = np.linalg.svd(near - near.mean(axis=0), full_matrices=False)
        normal = vt[-1]
    else:
        normal = np.array([0.0, 0.0, 1.0])
    axes = _plane_axes(normal)
    # Within the cloth: a window past its edge would count the smear into empty space. The
    # cloth's extent along the plane is read exactly only where it may cut the window: one
    # run at each extreme bounds it from within (their samples are the cloth's), and the
    # cut is monotone in it.
    q_lo, q_hi = _projection_bounds(lines, centre, axes)
    project = lambda p: (p - centre) @ axes.T  # noqa: E731
    least = [float(np.min(project(read(lines, lines.run_samples([int(np.argmin(q_lo[:, k]))])))[:, k]))
             for k in range(2)]
    most = [float(np.max(project(read(lines, lines.run_samples([int(np.argmax(q_hi[:, k]))])))[:, k]))
            for k in range(2)]
    if 2.0 * max(float((np.minimum(-np.array(least), np.array(most)) - r).min()), r) < window:
        reach = np.array([min(-_least(lines, read, q_lo[:, k], lambda p, k=k: project(p)[:, k], slack),
                              -_least(lines, read, -q_hi[:, k], lambda p, k=k: -project(p)[:, k], slack))
                          for k in range(2)]) - r
        window = float(min(window, 2.0 * max(float(reach.min()), r)))
    texel = max(r / 8.0, window / max_texels)
    n = max(1, int(math.ceil(window / texel)))
    grid = (np.arange(n) + 0.5) * texel - 0.5 * n * texel
    tau = np.zeros((n, n))
    half = 0.5 * n * texel
    deposited = 0
    for group, gparams, gdia in [(lines, params, fiber_diameter), *others]:
        glines = group if isinstance(group, YarnLines) else YarnLines.from_curves(group)
        deposited += _deposit_depth(tau, grid, texel, half, glines, gparams, float(gdia), centre, axes, normal, read)
    return CoverageMap(tau=tau, texel=texel, centre=centre, normal=normal, axes=axes, points_read=read.count,
                       curves_deposited=deposited)


def _deposit_depth(tau: np.ndarray, grid: np.ndarray, texel: float, half: float, lines: YarnLines,
                   params: YarnParams, fiber_diameter: float, centre: np.ndarray, axes: np.ndarray,
                   normal: np.ndarray, read: _Reader) -> int:
    """Adds the optical depth of ``lines`` (yarns of ``params``) to the raster ``tau``: the
    parts within the window and within :data:`COVERAGE_SLAB_RADII` yarn radii of its plane
    (another layer of a garment is not this cloth); returns the number of curves that added.
    Only runs whose boxes reach that slab are read, with one sample more at each end (a
    polyline piece counts when either end is inside)."""
    from scipy.spatial import cKDTree

    r = params.yarn_radius
    slab = COVERAGE_SLAB_RADII * r
    if lines.curve_count == 0 or not math.isfinite(lines.extent):
        return 0
    q_lo, q_hi = _projection_bounds(lines, centre, np.stack([axes[0], axes[1], normal]))
    room = np.array([half + r, half + r, slab]) + _slack(lines, centre)
    runs = np.flatnonzero(np.all((q_lo <= room) & (q_hi >= -room), axis=1))
    if not len(runs):
        return 0
    curve = lines.run_curve[runs]
    start = np.maximum(lines.run_start[runs] - 1, lines.curve_start[curve])
    stop = np.minimum(lines.run_stop[runs] + 1, lines.curve_start[curve + 1])
    # Ranges that overlap or meet within a curve are merged (runs are in sample order).
    new = np.ones(len(runs), bool)
    new[1:] = (start[1:] > stop[:-1]) | (curve[1:] != curve[:-1])
    heads = np.flatnonzero(new)
    start, stop, curve = start[heads], stop[np.append(heads[1:] - 1, len(runs) - 1)], curve[heads]
    cuts = np.flatnonzero(np.diff(curve)) + 1
    deposited = 0
    for s_k, e_k in zip(np.split(start, cuts), np.split(stop, cuts)):
        index = _ranges(s_k, e_k)
        joined = np.diff(index) == 1                  # neighbours on the curve, not across a gap
        p = read(lines, index) - centre
        q = p @ axes.T
        inside = np.all(np.abs(q) <= half + r, axis=1) & (np.abs(p @ normal) <= slab)
        if not inside.any():
            continue
        # Densify to a quarter texel so that the nearest sample is the nearest curve point.
        seg = np.diff(q, axis=0)
        k = np.maximum(1, np.ceil(np.linalg.norm(seg, axis=1) / (0.25 * texel)).astype(np.int64))
        keep = (inside[:-1] | inside[1:]) & joined
        if not keep.any():
            continue
        a, d, k = q[:-1][keep], seg[keep], k[keep]
        rep = np.repeat(np.arange(len(a)), k)
        f = (np.arange(len(rep)) - np.repeat(np.cumsum(k) - k, k)) / k[rep]
        dense = a[rep] + d[rep] * f[:, None]
        lo = np.searchsorted(grid, dense.min(axis=0) - r)
        hi = np.searchsorted(grid, dense.max(axis=0) + r)
        if hi[0] <= lo[0] or hi[1] <= lo[1]:
            continue
        gi, gj = np.meshgrid(grid[lo[0]:hi[0]], grid[lo[1]:hi[1]], indexing="ij")
        dist, _ = cKDTree(dense).query(np.stack([gi.ravel(), gj.ravel()], axis=1), distance_upper_bound=r)
        tau[lo[0]:hi[0], lo[1]:hi[1]] += yarn_optical_depth(
            params, fiber_diameter, np.where(np.isfinite(dist), dist, r)).reshape(gi.shape)
        deposited += 1
    return deposited
