"""A voxelized cloth as a Mitsuba ``heterogeneous`` medium in a bounding box (:func:`cloth_volume`).

The medium's density is the grid's extinction across round fibers ``E = sum L D / V``
(:mod:`usdfiber.geometry.voxelize`) in a ``gridvolume`` with nearest-voxel lookup (so that a
voxel's density and its phase function's frame agree), scale 1, albedo 1, and the phase
function :mod:`usdfiber.translators.mitsuba.volume.phase`, whose ``projected_area`` turns
``E`` into Eq. 3's ``E (W(phi') / D) cos(theta')`` and whose value carries the fibers'
albedo ``Lambda(omega_v)``. The medium fills a box with a ``null`` BSDF (index-matched), so
rays and shadow rays enter and leave it without scattering at its faces.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from usdfiber.geometry.voxelize import VoxelGrid
from usdfiber.translators.mitsuba.fiber_bank import FiberBank
from usdfiber.translators.mitsuba.volume.phase import fiber_phase

__all__ = ["cloth_medium", "cloth_volume", "grid_transform"]


def grid_transform(mi: Any, grid: VoxelGrid) -> Any:
    """The ScalarTransform4f that maps the unit cube onto the grid's box."""
    ext = grid.voxel_size * np.array(grid.shape, np.float64)
    return (mi.ScalarTransform4f().translate([float(v) for v in grid.origin])
            .scale([float(v) for v in ext]))


def cloth_medium(mi: Any, grid: VoxelGrid, bank: FiberBank) -> Any:
    """The loaded ``heterogeneous`` medium of ``grid`` (slots index ``bank``)."""
    density = mi.VolumeGrid(np.ascontiguousarray(grid.extinction[..., None], np.float32))
    return mi.load_dict({
        "type": "heterogeneous",
        "sigma_t": {"type": "gridvolume", "grid": density, "filter_type": "nearest",
                    "to_world": grid_transform(mi, grid)},
        "albedo": 1.0,
        "scale": 1.0,
        # Grey extinction: one free-flight distance serves all channels.
        "has_spectral_extinction": False,
        "phase": fiber_phase(mi, bank, grid),
    })


def cloth_volume(mi: Any, grid: VoxelGrid, bank: FiberBank) -> dict[str, Any]:
    """A scene entry: the grid's box with a ``null`` BSDF and the cloth medium inside."""
    lo = np.asarray(grid.origin, np.float64)
    hi = grid.upper
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    return {
        "type": "cube",
        "to_world": mi.ScalarTransform4f().translate([float(v) for v in centre]).scale([float(v) for v in half]),
        "bsdf": {"type": "null"},
        "interior": cloth_medium(mi, grid, bank),
    }
