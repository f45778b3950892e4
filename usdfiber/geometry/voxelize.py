"""Fiber curves -> a voxel grid of the quantities of the paper's Eq. 3 (:func:`voxelize_fibers`).

The volumetric cloth model of the paper's Section 5 (after Jakob et al. 2010) replaces the
fibers inside a voxel of volume V by an anisotropic medium of extinction

    mu_t(x, omega) = (1/V) sum_i L_i D_i (W_i(phi'_i) / D_i) cos(theta_i)
                  ~= (N/V) A-bar(omega') sin(omega, omega_f-bar)                       (Eq. 3)

where fiber piece i has length L_i inside the voxel, circumscribed diameter D_i and
projected width W_i(phi') seen from azimuth phi' in its own frame, and
``cos(theta_i) = sin(omega, omega_f,i)``. The grid holds, per voxel:

* ``extinction``: ``sum_i L_i D_i / V`` (1 / scene length), the extinction across round
  fibers of the voxel's mean direction; the renderer multiplies it by the slot's
  ``W(phi') / D <= 1`` and by ``sin(omega, omega_f)`` (a factor <= 1, so this is also the
  majorant a free-flight sampler needs);
* ``length``: ``sum_i L_i / V``, the fiber length per volume (the paper's N/V for fibers
  crossing the voxel);
* ``direction``: the mean fiber axis, the principal eigenvector of the orientation tensor
  ``sum_i L_i t_i t_i^T`` (fibers have no sign, so directions are averaged as axes);
  ``spread``: ``1 - lambda_max / trace`` of that tensor (0: all parallel, 2/3: isotropic);
* ``slot`` and ``axis``: one fiber piece of the voxel drawn with probability proportional
  to its length (seeded), whose table-and-colour slot and cross-section axis (the profile's
  x axis, the rotation psi applied) stand for the voxel's; over many voxels the slots and
  rotations keep the fibers' mix, where an average of rotations would not exist;
  ``slot_length``: the length per volume of every slot, the mix itself.

Voxel size from the pixel footprint (:func:`voxel_size_for_footprint`): a voxel smaller
than a pixel's footprint is detail the image cannot show ("model only what a scene needs").
Memory is bounded (:func:`grid_bytes`): a grid past the budget is coarsened (a warning
says by how much) or refused.

Curves come as polylines (the renderer's own sampling of the fiber curves): pieces longer
than a quarter voxel are split, and each piece is deposited in the voxel of its midpoint
(:class:`FiberPieces`, also what :mod:`usdfiber.geometry.yarn_density` makes from a yarn's
density profile without expanding its fibers: a piece there stands for ``count`` fibers).

The grid is cropped to its occupied voxels: a box of empty padding around the cloth changes
nothing in the medium, but a camera whose near clipping plane cuts the box starts its rays
inside the volume, where a renderer that tracks media by boundary crossings no longer sees it
(measured: a patch 1.1 mm under a camera with the USD default near plane of 1 mm rendered
47 % too bright with a padded box, in agreement with its explicit fibers once cropped).

Count noise. Each fiber's cross section is spread over its voxel: one opaque fiber of width D
in a voxel column of width w stops a fraction D / w of the rays crossing it, its voxel
exp(-D / w). Over a cloth of Poisson-placed fibers (n per unit width) the explicit fibers
transmit exp(-n D) and the voxels exp(-n w (1 - exp(-D / w))): the volume's optical depth is
short by ``count_noise_deficit(D / w)`` = 1 - (w / D)(1 - exp(-D / w)) ~ D / (2 w) (9 % for
w = 5 D, 2.5 % for w = 20 D): voxels much wider than a fiber, or the ensemble density
(:mod:`usdfiber.geometry.yarn_density`), remove it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from usdfiber.geometry.curves import CurveGeometry, evaluate

__all__ = ["DEFAULT_BUDGET_BYTES", "FiberPieces", "FiberPolylines", "GridAccumulator", "VoxelGrid", "VoxelizeError",
           "PIECE_FRACTION", "count_noise_deficit", "fiber_pieces", "grid_bytes", "grid_size", "polylines_from_segments",
           "voxel_size_for_footprint", "voxelize_fibers", "voxelize_pieces"]

#: Default memory budget of one grid (all its arrays): 512 MiB.
DEFAULT_BUDGET_BYTES = 512 * 2**20
#: Pieces are split to at most this fraction of a voxel before deposit at their midpoints.
PIECE_FRACTION = 0.25


class VoxelizeError(ValueError):
    """Fibers that cannot be voxelized; the message names the source and what was expected."""


@dataclass(frozen=True)
class FiberPolylines:
    """Fiber centre lines as polylines, in scene units.

    ``points`` (P, 3); ``counts`` (C,) vertices per curve (>= 2 each); ``diameter`` (C,)
    circumscribed diameter per curve (scene units); ``slot`` (C,) table-and-colour slot per
    curve; ``axis`` (C, 3) or None: per curve the cross-section's x axis (its rotation psi
    applied), a vector perpendicular to the curve; None: rotations uniform in [0, 2 pi), the
    paper's default. ``source``: what the curves came from, for messages (a prim path).
    """

    points: np.ndarray
    counts: np.ndarray
    diameter: np.ndarray
    slot: np.ndarray
    axis: np.ndarray | None = None
    source: str = "fibers"


@dataclass(frozen=True)
class FiberPieces:
    """Straight fiber pieces, each deposited whole in the voxel of its midpoint.

    ``mid`` (M, 3) midpoints and ``vec`` (M, 3) end-minus-start vectors (scene units);
    ``count`` (M,) how many fibers a piece stands for (1 for a piece of a real fiber);
    ``diameter`` (M,) circumscribed diameter; ``slot`` (M,) table-and-colour slot; ``axis``
    (M, 3) or None: cross-section x axis (rotation psi applied), None for rotations uniform in
    [0, 2 pi). ``source`` names the origin for messages.
    """

    mid: np.ndarray
    vec: np.ndarray
    count: np.ndarray
    diameter: np.ndarray
    slot: np.ndarray
    axis: np.ndarray | None = None
    source: str = "fibers"

    @property
    def length(self) -> np.ndarray:
        """Each piece's own length (one fiber's)."""
        return np.linalg.norm(self.vec, axis=1)


def count_noise_deficit(d_over_w: float | np.ndarray) -> float | np.ndarray:
    """The relative optical-depth deficit of voxels of width w over Poisson-placed fibers of
    diameter D (module docstring): ``1 - (w / D)(1 - exp(-D / w))``, about D / (2 w)."""
    x = np.asarray(d_over_w, np.float64)
    out = np.where(x > 0, 1.0 - (1.0 - np.exp(-x)) / np.where(x > 0, x, 1.0), 0.0)
    return float(out) if out.ndim == 0 else out


@dataclass
class VoxelGrid:
    """A dense voxel grid of Eq. 3's quantities (see the module docstring).

    Voxel (i, j, k) spans ``origin + voxel_size * ([i, j, k], [i + 1, j + 1, k + 1])``; arrays
    are indexed ``[k, j, i]`` (z, y, x), the layout of Mitsuba's grid volumes.
    """

    origin: np.ndarray                 # (3,) scene units
    voxel_size: float                  # scene units
    extinction: np.ndarray             # (nz, ny, nx) float32, sum L D / V
    length: np.ndarray                 # (nz, ny, nx) float32, sum L / V
    direction: np.ndarray              # (nz, ny, nx, 3) float32, unit mean axis
    spread: np.ndarray                 # (nz, ny, nx) float32
    slot: np.ndarray                   # (nz, ny, nx) int32, -1 where empty
    axis: np.ndarray                   # (nz, ny, nx, 3) float32, unit, perpendicular to direction
    slot_length: np.ndarray            # (n_slots, nz, ny, nx) float32
    warnings: list[str] = field(default_factory=list)

    @property
    def shape(self) -> tuple[int, int, int]:
        """(nx, ny, nz)."""
        nz, ny, nx = self.extinction.shape
        return nx, ny, nz

    @property
    def upper(self) -> np.ndarray:
        return self.origin + self.voxel_size * np.array(self.shape, np.float64)

    @property
    def occupied(self) -> int:
        return int(np.count_nonzero(self.length))

    def nbytes(self) -> int:
        return int(sum(a.nbytes for a in (self.extinction, self.length, self.direction, self.spread,
                                          self.slot, self.axis, self.slot_length)))


def grid_bytes(shape: tuple[int, int, int], n_slots: int) -> int:
    """Bytes of a :class:`VoxelGrid` of ``shape`` (nx, ny, nz) with ``n_slots`` slots."""
    n = int(shape[0]) * int(shape[1]) * int(shape[2])
    # extinction, length, spread, slot: 4 B each; direction and axis: 12 B each; slot_length.
    return n * (4 * 4 + 2 * 12 + 4 * max(int(n_slots), 1))


def voxel_size_for_footprint(footprint: float, *, fiber_diameter: float = 0.0, per_pixel: float = 1.0) -> float:
    """The voxel size for a pixel footprint (scene units at the cloth's distance).

    ``per_pixel`` voxels per pixel footprint (1: one voxel per pixel). Never below the
    fiber diameter: a voxel thinner than a fiber has no statistics of fibers to hold.
    """
    if not (math.isfinite(footprint) and footprint > 0):
        raise VoxelizeError(f"pixel footprint {footprint!r}: expected a positive finite length")
    if not (math.isfinite(per_pixel) and per_pixel > 0):
        raise VoxelizeError(f"voxels per pixel {per_pixel!r}: expected a positive finite number")
    return max(footprint / per_pixel, float(fiber_diameter))


def polylines_from_segments(geom: CurveGeometry, seg_slot: np.ndarray, seg_psi: np.ndarray, seg_ref: np.ndarray,
                            *, samples: int = 4, source: str = "fibers") -> FiberPolylines:
    """Fiber B-spline segments as polylines (one per segment, ``samples`` points each).

    ``seg_slot``, ``seg_psi`` (radians), ``seg_ref`` (S, 3): per segment the slot, the rotation
    and the azimuthal reference the curve BSDF uses; the cross-section axis is the reference
    rotated by psi about the segment's chord. Diameters are twice the mean radius.
    """
    n = geom.segment_count
    if n == 0:
        raise VoxelizeError(f"{source}: no fiber curves to voxelize")
    t = np.linspace(0.0, 1.0, max(int(samples), 2))
    seg = np.repeat(np.arange(n), len(t))
    P, R, _ = evaluate(geom, seg, np.tile(t, n))
    P = P.reshape(n, len(t), 3)
    chord = P[:, -1] - P[:, 0]
    norm = np.linalg.norm(chord, axis=1, keepdims=True)
    tan = chord / np.where(norm > 0, norm, 1.0)
    ref = np.asarray(seg_ref, np.float64)
    ref = ref - np.sum(ref * tan, axis=1, keepdims=True) * tan
    ref /= np.maximum(np.linalg.norm(ref, axis=1, keepdims=True), 1e-30)
    psi = np.asarray(seg_psi, np.float64)[:, None]
    axis = np.cos(psi) * ref + np.sin(psi) * np.cross(tan, ref)
    return FiberPolylines(points=P.reshape(-1, 3), counts=np.full(n, len(t)),
                          # A tapered end may reach radius 0: it holds (almost) no cross section.
                          diameter=np.maximum(2.0 * np.abs(R.reshape(n, len(t))).mean(axis=1), 1e-12),
                          slot=np.asarray(seg_slot, np.int64), axis=axis, source=source)


def fiber_pieces(fib: FiberPolylines, max_len: float) -> FiberPieces:
    """The polylines of ``fib`` as :class:`FiberPieces` no longer than ``max_len`` (validated)."""
    pts = np.asarray(fib.points, np.float64)
    counts = np.asarray(fib.counts, np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    seg_start = np.concatenate([np.arange(s, s + c - 1) for s, c in zip(starts, counts)]) if len(counts) else \
        np.zeros(0, np.int64)
    seg_curve = np.repeat(np.arange(len(counts)), counts - 1)
    a, b = pts[seg_start], pts[seg_start + 1]
    d = b - a
    seg_len = np.linalg.norm(d, axis=1)
    keep = seg_len > 0
    a, d, seg_len, seg_curve = a[keep], d[keep], seg_len[keep], seg_curve[keep]
    n_split = np.maximum(np.ceil(seg_len / max_len).astype(np.int64), 1)
    rep = np.repeat(np.arange(len(a)), n_split)
    k = np.arange(len(rep)) - np.repeat(np.cumsum(n_split) - n_split, n_split)
    frac = (k + 0.5) / n_split[rep]
    curve = seg_curve[rep]
    axis = None if fib.axis is None else np.asarray(fib.axis, np.float64)[curve]
    return FiberPieces(mid=a[rep] + d[rep] * frac[:, None], vec=d[rep] / n_split[rep, None],
                       count=np.ones(len(rep)), diameter=np.asarray(fib.diameter, np.float64)[curve],
                       slot=np.asarray(fib.slot, np.int64)[curve], axis=axis, source=fib.source)


def _check(fib: FiberPolylines, n_slots: int) -> None:
    src = fib.source
    pts = np.asarray(fib.points)
    counts = np.asarray(fib.counts)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise VoxelizeError(f"{src}: points have shape {pts.shape}; expected (P, 3)")
    if counts.ndim != 1 or counts.sum() != len(pts):
        raise VoxelizeError(f"{src}: curve vertex counts sum to {int(counts.sum())} for {len(pts)} points")
    if len(counts) and counts.min() < 2:
        raise VoxelizeError(f"{src}: a curve has {int(counts.min())} vertex; expected at least 2 per curve")
    if not np.all(np.isfinite(pts)):
        raise VoxelizeError(f"{src}: points are not all finite (NaN or Inf)")
    for name in ("diameter", "slot"):
        arr = np.asarray(getattr(fib, name))
        if arr.shape != counts.shape:
            raise VoxelizeError(f"{src}: {name} has {arr.shape} values for {len(counts)} curves; expected one per curve")
    dia = np.asarray(fib.diameter, np.float64)
    if len(dia) and not (np.all(np.isfinite(dia)) and dia.min() > 0):
        raise VoxelizeError(f"{src}: fiber diameters must be positive and finite (min {dia.min()!r})")
    slot = np.asarray(fib.slot)
    if len(slot) and (slot.min() < 0 or slot.max() >= n_slots):
        raise VoxelizeError(f"{src}: slot index out of range [0, {n_slots})")
    if fib.axis is not None and np.asarray(fib.axis).shape != (len(counts), 3):
        raise VoxelizeError(f"{src}: axis has shape {np.asarray(fib.axis).shape}; expected ({len(counts)}, 3)")


def _reference(t: np.ndarray) -> np.ndarray:
    """The paper's reference for psi: world y made perpendicular to the fiber (x when the
    fiber is within ~8 degrees of y, where that projection vanishes)."""
    ey = np.array([0.0, 1.0, 0.0])
    ex = np.array([1.0, 0.0, 0.0])
    ref = np.where((np.abs(t @ ey) > 0.99)[:, None], ex, ey)
    ref = ref - np.sum(ref * t, axis=1, keepdims=True) * t
    return ref / np.linalg.norm(ref, axis=1, keepdims=True)


def grid_size(src: str, lo: np.ndarray, hi: np.ndarray, voxel_size: float, n_slots: int, budget_bytes: int,
               coarsen: bool) -> tuple[float, tuple[int, int, int], list[str]]:
    """(voxel size, shape (nx, ny, nz), warnings) of a grid over [lo, hi] within ``budget_bytes``:
    coarsened by factors of 1.25 with a warning (``coarsen``), else VoxelizeError."""
    ext = hi - lo
    warnings: list[str] = []

    def shape_for(s: float) -> tuple[int, int, int]:
        return tuple(int(max(1, math.ceil(e / s - 1e-9))) for e in ext)  # type: ignore[return-value]

    size = float(voxel_size)
    shape = shape_for(size)
    need = grid_bytes(shape, n_slots)
    if need > budget_bytes:
        if not coarsen:
            raise VoxelizeError(f"{src}: a {shape[0]}x{shape[1]}x{shape[2]} grid of {size:g}-unit voxels needs "
                                f"{need / 2**20:.1f} MiB, over the budget of {budget_bytes / 2**20:.1f} MiB; "
                                f"expected a coarser voxel size or a larger budget")
        if grid_bytes((1, 1, 1), n_slots) > budget_bytes:
            raise VoxelizeError(f"{src}: the budget of {budget_bytes} bytes cannot hold one voxel")
        s2 = size
        while grid_bytes(shape_for(s2), n_slots) > budget_bytes:
            s2 *= 1.25
        warnings.append(f"{src}: a grid of {size:g}-unit voxels ({need / 2**20:.1f} MiB) is over the budget of "
                        f"{budget_bytes / 2**20:.1f} MiB; coarsened to {s2:g}-unit voxels")
        size = s2
        shape = shape_for(size)
    return size, shape, warnings


def _bounds(src: str, bounds: tuple[np.ndarray, np.ndarray] | None, pts: np.ndarray,
            voxel_size: float) -> tuple[np.ndarray, np.ndarray]:
    if bounds is None:
        return pts.min(axis=0) - 0.5 * voxel_size, pts.max(axis=0) + 0.5 * voxel_size
    lo, hi = (np.asarray(b, np.float64) for b in bounds)
    if not (lo.shape == hi.shape == (3,) and np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))
            and np.all(hi > lo)):
        raise VoxelizeError(f"{src}: grid bounds {lo} .. {hi}: expected finite lo < hi on every axis")
    return lo, hi


def voxelize_fibers(fibers: FiberPolylines, voxel_size: float, *, n_slots: int,
                    bounds: tuple[np.ndarray, np.ndarray] | None = None,
                    budget_bytes: int = DEFAULT_BUDGET_BYTES, coarsen: bool = True,
                    seed: int = 0) -> VoxelGrid:
    """Voxelize fiber polylines into a :class:`VoxelGrid` of Eq. 3's quantities.

    ``voxel_size``: edge of a voxel (scene units). ``bounds``: (lo, hi) of the region to
    voxelize; default: the fibers' bounds widened by half a voxel; the grid is then cropped to
    its occupied voxels. ``n_slots``: the number of slots ``fibers.slot`` indexes. Past
    ``budget_bytes`` the voxel size grows until the grid fits, with a warning (``coarsen``), or
    VoxelizeError (not ``coarsen``). Raises VoxelizeError for bad input and for fibers that
    leave no length inside the grid (an empty region).
    """
    src = fibers.source
    if not (math.isfinite(voxel_size) and voxel_size > 0):
        raise VoxelizeError(f"{src}: voxel size {voxel_size!r}; expected a positive finite length")
    if n_slots < 1:
        raise VoxelizeError(f"{src}: no fiber slots; expected at least one table")
    _check(fibers, n_slots)
    if len(fibers.counts) == 0:
        raise VoxelizeError(f"{src}: no fiber curves to voxelize")
    lo, hi = _bounds(src, bounds, np.asarray(fibers.points, np.float64), voxel_size)
    size, shape, warnings = grid_size(src, lo, hi, voxel_size, n_slots, budget_bytes, coarsen)
    return _deposit(fiber_pieces(fibers, PIECE_FRACTION * size), lo, hi, size, shape, n_slots, seed, warnings)


def voxelize_pieces(pieces: FiberPieces, voxel_size: float, *, n_slots: int,
                    bounds: tuple[np.ndarray, np.ndarray] | None = None,
                    budget_bytes: int = DEFAULT_BUDGET_BYTES, coarsen: bool = True,
                    seed: int = 0) -> VoxelGrid:
    """:func:`voxelize_fibers` for ready :class:`FiberPieces` (each ``count`` fibers): the
    pieces should be no longer than a quarter voxel (each lands whole in one voxel)."""
    src = pieces.source
    if not (math.isfinite(voxel_size) and voxel_size > 0):
        raise VoxelizeError(f"{src}: voxel size {voxel_size!r}; expected a positive finite length")
    if n_slots < 1:
        raise VoxelizeError(f"{src}: no fiber slots; expected at least one table")
    mid = np.asarray(pieces.mid, np.float64)
    m = len(mid)
    if m == 0:
        raise VoxelizeError(f"{src}: no fiber pieces to voxelize")
    for name, shape in (("mid", (m, 3)), ("vec", (m, 3)), ("count", (m,)), ("diameter", (m,)), ("slot", (m,))):
        if np.asarray(getattr(pieces, name)).shape != shape:
            raise VoxelizeError(f"{src}: {name} has shape {np.asarray(getattr(pieces, name)).shape}; expected {shape}")
    if not (np.all(np.isfinite(mid)) and np.all(np.isfinite(pieces.vec))):
        raise VoxelizeError(f"{src}: piece positions are not all finite (NaN or Inf)")
    if not (np.all(np.isfinite(pieces.count)) and np.min(pieces.count) >= 0):
        raise VoxelizeError(f"{src}: piece counts must be finite and >= 0")
    if not (np.all(np.isfinite(pieces.diameter)) and np.min(pieces.diameter) > 0):
        raise VoxelizeError(f"{src}: fiber diameters must be positive and finite")
    slot = np.asarray(pieces.slot)
    if slot.min() < 0 or slot.max() >= n_slots:
        raise VoxelizeError(f"{src}: slot index out of range [0, {n_slots})")
    lo, hi = _bounds(src, bounds, mid, voxel_size)
    size, shape, warnings = grid_size(src, lo, hi, voxel_size, n_slots, budget_bytes, coarsen)
    return _deposit(pieces, lo, hi, size, shape, n_slots, seed, warnings)


def _deposit(pieces: FiberPieces, lo: np.ndarray, hi: np.ndarray, size: float, shape: tuple[int, int, int],
             n_slots: int, seed: int, warnings: list[str]) -> VoxelGrid:
    acc = GridAccumulator(lo, hi, size, shape, n_slots, seed=seed, source=pieces.source)
    acc.add(pieces)
    grid = acc.finish()
    grid.warnings = warnings + grid.warnings
    return grid


class GridAccumulator:
    """Deposits :class:`FiberPieces` chunk by chunk into a grid of ``shape`` voxels of ``size``
    at ``lo`` (memory: the grid plus one chunk), then crops it to its occupied voxels
    (:meth:`finish`). Pieces whose midpoints fall outside are dropped."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray, size: float, shape: tuple[int, int, int], n_slots: int, *,
                 seed: int = 0, source: str = "fibers") -> None:
        self.lo, self.hi, self.size = np.asarray(lo, np.float64), np.asarray(hi, np.float64), float(size)
        self.shape = tuple(int(v) for v in shape)
        self.n_slots, self.source = int(n_slots), source
        n = self.shape[0] * self.shape[1] * self.shape[2]
        self._n = n
        self._length = np.zeros(n)
        self._ext = np.zeros(n)
        self._slot_length = np.zeros((self.n_slots, n))
        self._tensor = np.zeros((6, n))
        # Per voxel the piece drawn so far (largest Efraimidis-Spirakis key log(u) / L).
        self._key = np.full(n, -np.inf)
        self._slot = np.full(n, -1, np.int64)
        self._axis = np.full((n, 3), np.nan)
        self._rng = np.random.default_rng(seed)

    _PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))

    def add(self, pieces: FiberPieces) -> None:
        """Deposit one chunk of pieces."""
        nx, ny, _ = self.shape
        mid = np.asarray(pieces.mid, np.float64)
        plen = pieces.length
        wlen = plen * np.asarray(pieces.count, np.float64)      # fiber length the piece stands for
        ijk = np.floor((mid - self.lo) / self.size).astype(np.int64)
        idx = np.flatnonzero(np.all((ijk >= 0) & (ijk < np.array(self.shape)), axis=1) & (wlen > 0))
        if len(idx) == 0:
            return
        ijk, plen, wlen = ijk[idx], plen[idx], wlen[idx]
        flat = (ijk[:, 2] * ny + ijk[:, 1]) * nx + ijk[:, 0]
        n = self._n
        dia = np.asarray(pieces.diameter, np.float64)[idx]
        slot_c = np.asarray(pieces.slot, np.int64)[idx]
        self._length += np.bincount(flat, wlen, n)
        self._ext += np.bincount(flat, wlen * dia, n)
        for s in np.unique(slot_c):
            m = slot_c == s
            self._slot_length[s] += np.bincount(flat[m], wlen[m], n)
        t = np.asarray(pieces.vec, np.float64)[idx] / plen[:, None]
        for c, (a, b) in enumerate(self._PAIRS):
            self._tensor[c] += np.bincount(flat, wlen * t[:, a] * t[:, b], n)
        key = np.log(self._rng.random(len(wlen)).clip(1e-300)) / wlen
        order = np.lexsort((key, flat))
        last = np.ones(len(order), bool)
        last[:-1] = flat[order][1:] != flat[order][:-1]
        pick = order[last]
        v = flat[pick]
        better = key[pick] > self._key[v]
        v, pick = v[better], pick[better]
        self._key[v] = key[pick]
        self._slot[v] = slot_c[pick]
        self._axis[v] = np.nan if pieces.axis is None else np.asarray(pieces.axis, np.float64)[idx[pick]]

    def finish(self) -> VoxelGrid:
        """The grid, cropped to its occupied voxels (VoxelizeError when none is)."""
        nx, ny, nz = self.shape
        occ3 = (self._length > 0).reshape(nz, ny, nx)
        if not occ3.any():
            raise VoxelizeError(f"{self.source}: no fiber length inside the grid {self.lo} .. {self.hi} (an empty "
                                f"region); expected fibers inside the cloth's bounds")
        # Crop to the occupied voxels (module docstring: padding can put the camera inside the box).
        kk, jj, ii = (np.flatnonzero(occ3.any(axis=ax)) for ax in ((1, 2), (0, 2), (0, 1)))
        sl = (slice(kk[0], kk[-1] + 1), slice(jj[0], jj[-1] + 1), slice(ii[0], ii[-1] + 1))
        origin = self.lo + self.size * np.array([ii[0], jj[0], kk[0]], np.float64)

        def crop(a: np.ndarray) -> np.ndarray:
            return a.reshape((nz, ny, nx) + a.shape[1:])[sl].reshape((-1,) + a.shape[1:])

        length, ext, key, slot, axis = (crop(a) for a in (self._length, self._ext, self._key, self._slot,
                                                          self._axis))
        tensor_c = np.stack([crop(c) for c in self._tensor])
        slot_length = np.stack([crop(c) for c in self._slot_length])
        cz, cy, cx = (x.stop - x.start for x in sl)
        n_vox = cx * cy * cz
        vol = self.size ** 3
        occ = np.flatnonzero(length > 0)
        tensor = np.zeros((len(occ), 3, 3))
        for c, (a, b) in enumerate(self._PAIRS):
            tensor[:, a, b] = tensor[:, b, a] = tensor_c[c, occ]
        evals, evecs = np.linalg.eigh(tensor)
        direction = np.zeros((n_vox, 3))
        direction[:, 2] = 1.0                      # empty voxels: +z (never scatter: zero extinction)
        direction[occ] = evecs[:, :, -1]
        spread = np.zeros(n_vox)
        spread[occ] = np.clip(1.0 - evals[:, -1] / evals.sum(axis=1), 0.0, 1.0)
        d_occ = direction[occ]
        ax = axis[occ]
        random = np.isnan(ax[:, 0])
        # Uniform rotations: psi about the paper's reference.
        psi = self._rng.uniform(0.0, 2.0 * math.pi, int(random.sum()))
        ref = _reference(d_occ[random])
        ax[random] = np.cos(psi)[:, None] * ref + np.sin(psi)[:, None] * np.cross(d_occ[random], ref)
        ax = ax - np.sum(ax * d_occ, axis=1, keepdims=True) * d_occ
        bad = np.linalg.norm(ax, axis=1) < 1e-6          # axis along the mean direction
        ax[bad] = _reference(d_occ[bad])
        ax /= np.linalg.norm(ax, axis=1, keepdims=True)
        axis_out = np.zeros((n_vox, 3))
        axis_out[:, 0] = 1.0
        axis_out[occ] = ax
        slot = np.where(length > 0, slot, -1)

        def grid(a: np.ndarray, dtype: type = np.float32) -> np.ndarray:
            return np.ascontiguousarray(a.reshape((cz, cy, cx) + a.shape[1:]).astype(dtype))

        return VoxelGrid(origin=origin, voxel_size=self.size, extinction=grid(ext / vol), length=grid(length / vol),
                         direction=grid(direction), spread=grid(spread), slot=grid(slot, np.int32),
                         axis=grid(axis_out),
                         slot_length=np.ascontiguousarray(
                             (slot_length / vol).reshape(self.n_slots, cz, cy, cx).astype(np.float32)))
