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
its centre line), then the same raster averaged over voxel columns.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Iterable, Sequence

import numpy as np

from usdfiber.geometry.voxelize import (DEFAULT_BUDGET_BYTES, PIECE_FRACTION, FiberPieces, GridAccumulator, VoxelGrid,
                                        VoxelizeError, grid_size)
from usdfiber.geometry.yarn_centre import CentreFrames, CentreLine
from usdfiber.geometry.yarn_fibers import FiberSet, density_profile, migrating, ply_fibers
from usdfiber.spec.yarn import YarnError, YarnParams

__all__ = ["CoverageMap", "YarnCurve", "coverage_map", "node_counts", "rest_radius_quantiles", "voxelize_yarns",
           "yarn_optical_depth", "yarn_pieces"]

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


def coverage_map(curves: Sequence[YarnCurve], params: YarnParams, *, fiber_diameter: float, window: float,
                 others: Sequence[tuple[Sequence[YarnCurve], YarnParams, float]] = (),
                 max_texels: int = 768, source: str = "yarns") -> CoverageMap:
    """The yarns' optical depth along the cloth's normal (:class:`CoverageMap`) on a square of
    side ``window`` in the cloth's local plane, centred at the yarn point nearest the middle
    of the curves' bounds, and within the cloth (a smaller window where the cloth is
    smaller); texels of a sixteenth of a yarn diameter (coarser when the window would exceed
    ``max_texels`` a side). The plane is the principal plane of the centre-line
    points within the window (a curved garment is flat at that scale). A yarn that crosses
    itself within the window counts once where it does. ``others``: more yarns of the same
    cloth, (curves, params, fiber diameter) per group (a weave's wefts for its warps), whose
    optical depth adds to the map; ``curves`` alone place the window."""
    curves = [c for c in curves if len(np.asarray(c.points)) >= 2]
    if not curves:
        raise VoxelizeError(f"{source}: no yarn curves to measure the coverage of")
    if not (math.isfinite(window) and window > 0):
        raise VoxelizeError(f"{source}: coverage window {window!r}; expected a positive finite length")
    pts = np.concatenate([np.asarray(c.points, np.float64) for c in curves])
    if not np.all(np.isfinite(pts)):
        raise VoxelizeError(f"{source}: yarn points are not all finite (NaN or Inf)")
    r = params.yarn_radius
    mid = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
    centre = pts[int(np.argmin(np.linalg.norm(pts - mid, axis=1)))]
    near = pts[np.linalg.norm(pts - centre, axis=1) <= 0.75 * window + r]
    if len(near) >= 3:
        _, _, vt = np.linalg.svd(near - near.mean(axis=0), full_matrices=False)
        normal = vt[-1]
    else:
        normal = np.array([0.0, 0.0, 1.0])
    axes = _plane_axes(normal)
    # Within the cloth: a window past its edge would count the smear into empty space.
    q_all = (pts - centre) @ axes.T
    reach = np.minimum(-q_all.min(axis=0), q_all.max(axis=0)) - r
    window = float(min(window, 2.0 * max(float(reach.min()), r)))
    texel = max(r / 8.0, window / max_texels)
    n = max(1, int(math.ceil(window / texel)))
    grid = (np.arange(n) + 0.5) * texel - 0.5 * n * texel
    tau = np.zeros((n, n))
    half = 0.5 * n * texel
    for group, gparams, gdia in [(curves, params, fiber_diameter), *others]:
        _deposit_depth(tau, grid, texel, half, group, gparams, float(gdia), centre, axes, normal)
    return CoverageMap(tau=tau, texel=texel, centre=centre, normal=normal, axes=axes)


def _deposit_depth(tau: np.ndarray, grid: np.ndarray, texel: float, half: float, curves: Sequence[YarnCurve],
                   params: YarnParams, fiber_diameter: float, centre: np.ndarray, axes: np.ndarray,
                   normal: np.ndarray) -> None:
    """Adds the optical depth of ``curves`` (yarns of ``params``) to the raster ``tau``: the
    parts within the window and within :data:`COVERAGE_SLAB_RADII` yarn radii of its plane
    (another layer of a garment is not this cloth)."""
    from scipy.spatial import cKDTree

    r = params.yarn_radius
    for c in curves:
        p = np.asarray(c.points, np.float64) - centre
        q = p @ axes.T
        inside = np.all(np.abs(q) <= half + r, axis=1) & (np.abs(p @ normal) <= COVERAGE_SLAB_RADII * r)
        if not inside.any():
            continue
        # Densify to a quarter texel so that the nearest sample is the nearest curve point.
        seg = np.diff(q, axis=0)
        k = np.maximum(1, np.ceil(np.linalg.norm(seg, axis=1) / (0.25 * texel)).astype(np.int64))
        keep = inside[:-1] | inside[1:]
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
