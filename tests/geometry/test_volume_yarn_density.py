"""Yarns voxelized from the yarn model's fiber density (no fiber expansion) agree with the
voxelized expanded yarn: fiber length per voxel, mean direction and spread."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import usdfiber  # noqa: F401  (registers schemas first)
from usdfiber import presets
from usdfiber.geometry.voxelize import FiberPolylines, VoxelizeError, voxelize_fibers
from usdfiber.geometry.yarn import expand_yarn
from usdfiber.geometry.yarn_density import (YarnCurve, node_counts, rest_radius_quantiles, voxelize_yarns,
                                            yarn_pieces)
from usdfiber.geometry.yarn_fibers import density_profile
from usdfiber.spec.yarn import YarnParams

MPU_MM = 0.001
D = 0.0185   # cotton fiber diameter, mm


def yarn(name: str, **over) -> YarnParams:
    p = YarnParams.from_attributes(dict(presets.yarn_preset(name).yarn_attributes()), MPU_MM)
    # Flyaways are not part of the density model (module docstring): compare ply fibers.
    return dataclasses.replace(p, hair_density=0.0, loop_density=0.0, **over)


def curved_centre(n: int = 81) -> np.ndarray:
    """6 mm of yarn on an arc, rising and falling (a knit-like bend in every direction)."""
    t = np.linspace(0.0, 1.0, n)
    return np.stack([3.0 * np.cos(2 * t), 3.0 * np.sin(2 * t), 0.3 * np.sin(9 * t)], axis=1)


def both_grids(p: YarnParams, voxel: float):
    centre = curved_centre()
    ex = expand_yarn(centre, 1.0, p)
    fib = FiberPolylines(ex.curve_points(), ex.counts, np.full(len(ex.counts), D), np.zeros(len(ex.counts), int))
    pad = 1.5 * p.yarn_radius + voxel
    bounds = (centre.min(axis=0) - pad, centre.max(axis=0) + pad)
    ge = voxelize_fibers(fib, voxel, n_slots=1, bounds=bounds)
    ga = voxelize_yarns([YarnCurve(centre)], p, voxel, fiber_diameter=D, slots=[0], n_slots=1, bounds=bounds)
    lo = bounds[0]
    shape = tuple(int(np.ceil((bounds[1] - lo)[k] / voxel)) + 1 for k in (2, 1, 0))

    def full(g, a):
        """The cropped grid's array placed back on the common lattice."""
        out = np.zeros(shape + a.shape[3:])
        o = np.round((g.origin - lo) / voxel).astype(int)
        nz, ny, nx = a.shape[:3]
        out[o[2]:o[2] + nz, o[1]:o[1] + ny, o[0]:o[0] + nx] = a
        return out

    return {k: (full(ge, getattr(ge, k)), full(ga, getattr(ga, k))) for k in ("length", "extinction", "direction",
                                                                           "spread")}


@pytest.mark.parametrize("name,over", [("CNe 50", {}),
                                       ("ORA 120", {}),
                                       ("CNe 50", {"migration": (0.7, 1.2), "migration_period": 2.0})])
def test_density_grid_agrees_with_the_expanded_yarn(name, over):
    """Voxels one yarn diameter wide. Total fiber length within 1 % (the expansion's fibers
    differ from the ensemble only by their random rest radii); per-voxel length within 10 %
    relative L1 (the expanded yarn's 150-210 fibers make each voxel's length a sample: a few
    percent of count noise, measured 5 % for CNe 50); in voxels holding at least a fifth of the
    densest voxel's length, the mean directions within 3 degrees on average (measured 1.2) and
    the spreads within 0.02. The numpy streams are the same on every machine."""
    p = yarn(name, **over)
    g = both_grids(p, 2 * p.yarn_radius)
    le, la = g["length"]
    assert abs(la.sum() / le.sum() - 1.0) < 0.01
    assert np.abs(le - la).sum() / le.sum() < 0.10
    ee, ea = g["extinction"]
    assert np.allclose(ee, le * D, rtol=1e-5) and np.allclose(ea, la * D, rtol=1e-5)
    dense = np.minimum(le, la) > 0.2 * le.max()
    de, da = g["direction"]
    ang = np.degrees(np.arccos(np.clip(np.abs(np.sum(de * da, axis=-1))[dense], 0.0, 1.0)))
    assert ang.mean() < 3.0, ang.mean()
    se, sa = g["spread"]
    assert abs(se[dense].mean() - sa[dense].mean()) < 0.02


def test_fine_voxels_resolve_the_plies():
    """Voxels a quarter of the yarn radius (a voxel crosses ~4 expanded fibers). Total length
    within 1 %. The per-voxel difference is the expanded yarn's count noise: measured 27 %
    relative L1 per voxel, 12 % on 2^3 blocks, 5 % on 4^3 blocks, falling about as
    1 / sqrt(fibers per block) as noise does; bounds 35 % and 10 % (4^3 blocks)."""
    p = yarn("CNe 50")
    g = both_grids(p, p.yarn_radius / 4)
    le, la = g["length"]
    assert abs(la.sum() / le.sum() - 1.0) < 0.01
    assert np.abs(le - la).sum() / le.sum() < 0.35
    s = tuple(x // 4 * 4 for x in le.shape)

    def blocks(a):
        a = a[:s[0], :s[1], :s[2]]
        return a.reshape(s[0] // 4, 4, s[1] // 4, 4, s[2] // 4, 4).sum(axis=(1, 3, 5))

    assert np.abs(blocks(le) - blocks(la)).sum() / blocks(le).sum() < 0.10


def test_quadrature_radii_follow_the_profile():
    """The rest-radius nodes are the strata midpoints of the pdf R p(R): their mean equals
    the profile's mean radius to the quadrature's order (1e-3 for 64 nodes)."""
    eps, beta = 0.2, 2.0
    r = np.linspace(0.0, 1.0, 20001)
    w = r * density_profile(r, eps, beta)
    mean = np.sum(w * r) / np.sum(w)
    assert abs(rest_radius_quantiles(64, eps, beta).mean() - mean) < 1e-3
    nodes = rest_radius_quantiles(5, eps, beta)
    assert np.all(np.diff(nodes) > 0) and 0 < nodes[0] and nodes[-1] < 1


def test_cost_follows_length_over_voxel_not_fibers():
    """A yarn of 10x more fibers gives the same number of pieces; a voxel twice as large, half
    as many (per ply node counts are floored, so wide voxels use the minimum)."""
    p = yarn("CNe 50")
    c = YarnCurve(curved_centre())
    a = yarn_pieces(c, p, voxel_size=1.0, fiber_diameter=D, slots=[0])
    b = yarn_pieces(c, dataclasses.replace(p, fibers_per_ply=10 * p.fibers_per_ply), voxel_size=1.0,
                    fiber_diameter=D, slots=[0])
    h = yarn_pieces(c, p, voxel_size=2.0, fiber_diameter=D, slots=[0])
    assert len(a.count) == len(b.count) and np.isclose(b.count.sum(), 10 * a.count.sum())
    assert node_counts(p, 1.0) == node_counts(p, 2.0)
    assert abs(len(h.count) / len(a.count) - 0.5) < 0.05


def test_slots_share_the_fibers_equally():
    p = yarn("CNe 50")
    pieces = yarn_pieces(YarnCurve(curved_centre()), p, voxel_size=0.3, fiber_diameter=D, slots=[0, 1, 2])
    share = np.bincount(pieces.slot, pieces.count * pieces.length) / np.sum(pieces.count * pieces.length)
    assert np.allclose(share, 1 / 3, atol=0.02)


def test_bad_input_is_one_clear_line():
    p = yarn("CNe 50")
    c = YarnCurve(curved_centre())
    with pytest.raises(VoxelizeError, match="no yarn curves"):
        voxelize_yarns([], p, 0.1, fiber_diameter=D, slots=[0], n_slots=1)
    with pytest.raises(VoxelizeError, match="voxel size"):
        voxelize_yarns([c], p, 0.0, fiber_diameter=D, slots=[0], n_slots=1)
    with pytest.raises(VoxelizeError, match="slots"):
        voxelize_yarns([c], p, 0.1, fiber_diameter=D, slots=[1], n_slots=1)
    bad = curved_centre()
    bad[3, 1] = np.nan
    with pytest.raises(VoxelizeError, match="not all finite"):
        voxelize_yarns([YarnCurve(bad)], p, 0.1, fiber_diameter=D, slots=[0], n_slots=1)
    with pytest.raises(VoxelizeError, match="zero length"):
        voxelize_yarns([YarnCurve(np.zeros((3, 3)))], p, 0.1, fiber_diameter=D, slots=[0], n_slots=1)
    with pytest.raises(VoxelizeError, match="over the budget"):
        voxelize_yarns([c], p, 0.001, fiber_diameter=D, slots=[0], n_slots=1, coarsen=False, budget_bytes=2**20)
