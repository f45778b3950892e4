"""A voxelized cloth as Mitsuba ``heterogeneous`` media, one per occupied brick (:func:`cloth_shapes`).

A medium's density is the grid's extinction across round fibers ``E = sum L D / V``
(:mod:`usdfiber.geometry.voxelize`) in a ``gridvolume`` with nearest-voxel lookup (so that a
voxel's density and its phase function's frame agree), scale 1, albedo 1, and the phase
function :mod:`usdfiber.translators.mitsuba.volume.phase`, whose ``projected_area`` turns
``E`` into Eq. 3's ``E (W(phi') / D) cos(theta')`` and whose value carries the fibers'
albedo ``Lambda(omega_v)``.

Bricks. Mitsuba's ``heterogeneous`` medium samples free flights with one majorant, the
densest voxel of its grid; through a sparse knit most tentative collisions are then null
collisions, each paying a grid lookup and the phase function's projected area. The grid is
therefore cut into bricks of ``brick`` voxels a side (:data:`BRICK_VOXELS`): every brick that
holds fibers is a medium of its own, whose majorant is its own densest voxel, and bricks
without fibers hold no medium at all (rays cross them at the cost of two faces). The bricks'
faces are index-matched ``null`` rectangles, one per face between two cells of the brick
lattice of which at least one is occupied: its normal points along +x, +y or +z, its
``interior`` is the medium of the brick below, its ``exterior`` that of the brick above
(Mitsuba takes ``exterior`` for rays leaving along the normal). A face shared by two
bricks is a single shape, so a ray always passes from one medium straight into the next:
no gap and no overlap between bricks, and every brick's free-flight sampling is delta
tracking with a valid majorant: the result is unbiased as with one medium
(``tests/mitsuba/test_volume_phase.py`` measures transmittance through bricks of different
densities against the exact optical depth). ``brick = 0`` gives one medium in one box (the
whole grid under one majorant).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from usdfiber.geometry.voxelize import VoxelGrid
from usdfiber.translators.mitsuba.fiber_bank import FiberBank
from usdfiber.translators.mitsuba.volume.phase import fiber_phase

__all__ = ["BRICK_VOXELS", "MAX_BRICKS", "brick_majorants", "brick_size", "cloth_medium", "cloth_shapes",
           "collision_ratio", "grid_transform"]

#: Voxels per brick side: between a tight majorant (small bricks; :func:`collision_ratio`) and
#: few faces to cross and media to load (large ones). bench/REPORT.md, "Volumetric cloth",
#: gives the collision ratios of 2 to 16 and the render time of 8 against one medium (the
#: Figure 7 knit at 0.071 mm voxels: 0.92 of the collisions, 1.24x faster; 2-voxel bricks
#: would leave 0.37, at ~3,000 media per swatch).
BRICK_VOXELS = 8
#: At most this many bricks per grid (each is a medium and up to three faces to load): larger
#: grids get bricks of twice, four times ... the size.
MAX_BRICKS = 4096


def brick_size(grid: VoxelGrid, brick: int = BRICK_VOXELS) -> int:
    """The brick side in voxels for ``grid``: ``brick``, doubled until the grid has at most
    :data:`MAX_BRICKS` bricks (0 stays 0: one medium)."""
    if brick <= 0:
        return 0
    b = int(brick)
    while math.prod(math.ceil(n / b) for n in grid.shape) > MAX_BRICKS:
        b *= 2
    return b


def grid_transform(mi: Any, lo: np.ndarray, ext: np.ndarray) -> Any:
    """The ScalarTransform4f that maps the unit cube onto the box ``lo .. lo + ext``."""
    return mi.ScalarTransform4f().translate([float(v) for v in lo]).scale([float(v) for v in ext])


def cloth_medium(mi: Any, grid: VoxelGrid, bank: FiberBank, *, phase: Any = None,
                 index: tuple[int, int, int] = (0, 0, 0), shape: tuple[int, int, int] | None = None) -> Any:
    """The loaded ``heterogeneous`` medium of the voxels ``index .. index + shape`` (i, j, k;
    default: the whole grid) of ``grid``, whose slots index ``bank``; ``phase``: the phase
    function to share (default: a new one for ``grid``)."""
    i0, j0, k0 = (int(v) for v in index)
    nx, ny, nz = shape if shape is not None else grid.shape
    sub = grid.extinction[k0:k0 + nz, j0:j0 + ny, i0:i0 + nx]
    lo = np.asarray(grid.origin, np.float64) + grid.voxel_size * np.array([i0, j0, k0], np.float64)
    ext = grid.voxel_size * np.array([nx, ny, nz], np.float64)
    return mi.load_dict({
        "type": "heterogeneous",
        "sigma_t": {"type": "gridvolume", "grid": mi.VolumeGrid(np.ascontiguousarray(sub[..., None], np.float32)),
                    "filter_type": "nearest", "to_world": grid_transform(mi, lo, ext)},
        "albedo": 1.0,
        "scale": 1.0,
        # Grey extinction: one free-flight distance serves all channels.
        "has_spectral_extinction": False,
        "phase": phase if phase is not None else fiber_phase(mi, bank, grid),
    })


def _brick_edges(n: int, brick: int) -> np.ndarray:
    """Voxel indices where the bricks along an axis of ``n`` voxels start, and ``n``."""
    return np.append(np.arange(0, n, brick), n)


def brick_majorants(grid: VoxelGrid, brick: int = BRICK_VOXELS) -> np.ndarray:
    """Per brick (kz, jy, ix) its densest voxel's extinction, the majorant its medium samples
    free flights with (0: no medium)."""
    nx, ny, nz = grid.shape
    b = int(brick) if brick > 0 else max(nx, ny, nz)
    ex, ey, ez = (_brick_edges(n, b) for n in (nx, ny, nz))
    ext = grid.extinction
    m = np.maximum.reduceat(np.maximum.reduceat(np.maximum.reduceat(ext, ez[:-1], axis=0), ey[:-1], axis=1),
                            ex[:-1], axis=2)
    return m


def _face(mi: Any, axis: int, plane: float, lo: tuple[float, float], hi: tuple[float, float],
          interior: Any, exterior: Any) -> dict[str, Any]:
    """A null rectangle in the plane ``x_axis = plane`` spanning ``lo .. hi`` on the other two
    axes (taken cyclically: x -> (y, z), y -> (z, x), z -> (x, y)), normal along +axis."""
    a, b = (axis + 1) % 3, (axis + 2) % 3
    m = np.zeros((4, 4))
    m[a, 0] = 0.5 * (hi[0] - lo[0])
    m[b, 1] = 0.5 * (hi[1] - lo[1])
    m[axis, 2] = 1.0                       # (a, b, axis) is right-handed: the normal is +axis
    m[a, 3], m[b, 3], m[axis, 3] = 0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), plane
    m[3, 3] = 1.0
    face: dict[str, Any] = {"type": "rectangle", "to_world": mi.ScalarTransform4f(m.tolist()),
                            "bsdf": {"type": "null"}}
    if interior is not None:
        face["interior"] = interior
    if exterior is not None:
        face["exterior"] = exterior
    return face


def cloth_shapes(mi: Any, grid: VoxelGrid, bank: FiberBank, *, brick: int = BRICK_VOXELS,
                 prefix: str = "cloth") -> dict[str, Any]:
    """Scene entries of the cloth in ``grid``: one medium per occupied brick of ``brick``
    voxels a side (:func:`brick_size`) behind null faces (module docstring); ``brick = 0``: one
    medium in one box. Keys start with ``prefix``. A grid without extinction anywhere holds no
    medium and gives no entries (nothing to render; :mod:`usdfiber.geometry.voxelize` refuses
    such grids as empty regions)."""
    if not float(grid.extinction.max(initial=0.0)) > 0:
        return {}
    if brick <= 0:
        lo = np.asarray(grid.origin, np.float64)
        centre, half = 0.5 * (lo + grid.upper), 0.5 * (grid.upper - lo)
        return {prefix: {"type": "cube", "bsdf": {"type": "null"}, "interior": cloth_medium(mi, grid, bank),
                         "to_world": mi.ScalarTransform4f().translate([float(v) for v in centre])
                         .scale([float(v) for v in half])}}
    brick = brick_size(grid, brick)
    phase = fiber_phase(mi, bank, grid)
    nx, ny, nz = grid.shape
    edges = [_brick_edges(n, int(brick)) for n in (nx, ny, nz)]
    maj = brick_majorants(grid, brick)                     # (bz, by, bx)
    nb = (len(edges[0]) - 1, len(edges[1]) - 1, len(edges[2]) - 1)
    media: dict[tuple[int, int, int], Any] = {}
    for bz, by, bx in zip(*np.nonzero(maj > 0)):
        i0, j0, k0 = int(edges[0][bx]), int(edges[1][by]), int(edges[2][bz])
        shape = (int(edges[0][bx + 1]) - i0, int(edges[1][by + 1]) - j0, int(edges[2][bz + 1]) - k0)
        media[(int(bx), int(by), int(bz))] = cloth_medium(mi, grid, bank, phase=phase, index=(i0, j0, k0),
                                                          shape=shape)
    coord = [np.asarray(grid.origin[k], np.float64) + grid.voxel_size * edges[k] for k in range(3)]
    out: dict[str, Any] = {}
    for axis in range(3):
        a, b = (axis + 1) % 3, (axis + 2) % 3
        for cell in np.ndindex(*(nb[k] + (1 if k == axis else 0) for k in range(3))):
            # Face at lattice plane cell[axis] between the brick below (cell[axis] - 1) and above.
            below = list(cell)
            below[axis] -= 1
            lower = media.get(tuple(below)) if below[axis] >= 0 else None
            upper = media.get(tuple(cell)) if cell[axis] < nb[axis] else None
            if lower is None and upper is None:
                continue
            lo2 = (float(coord[a][cell[a]]), float(coord[b][cell[b]]))
            hi2 = (float(coord[a][cell[a] + 1]), float(coord[b][cell[b] + 1]))
            out[f"{prefix}_{axis}_{cell[0]}_{cell[1]}_{cell[2]}"] = _face(
                mi, axis, float(coord[axis][cell[axis]]), lo2, hi2, lower, upper)
    return out


def collision_ratio(grid: VoxelGrid, brick: int = BRICK_VOXELS) -> float:
    """Tentative collisions per unit ray length through the grid's box with bricks of
    ``brick`` voxels (empty bricks: none), relative to one majorant for the whole grid: the
    mean brick majorant over the grid's voxels over the densest voxel."""
    top = float(grid.extinction.max())
    if not top > 0:
        return math.nan
    m = brick_majorants(grid, brick)
    nx, ny, nz = grid.shape
    b = int(brick) if brick > 0 else max(nx, ny, nz)
    kk, jj, ii = np.indices((nz, ny, nx)).reshape(3, -1)
    return float(np.mean(m[kk // b, jj // b, ii // b]) / top)
