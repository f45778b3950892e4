"""Voxelization of fiber curves into Eq. 3's grid: density, mean direction, spread, slot mix,
footprint-sized voxels, the memory budget and bad input."""
from __future__ import annotations

import math

import numpy as np
import pytest

from usdfiber.geometry.voxelize import (FiberPolylines, VoxelizeError, grid_bytes, voxel_size_for_footprint,
                                        voxelize_fibers)


def parallel_fibers(n_side=10, spacing=0.1, length=2.0, direction=(1.0, 0.0, 0.0), diameter=0.01,
                    n_slots=1, seed=0, jitter=0.0):
    """n_side^2 straight fibers along ``direction`` on a square lattice across it."""
    t = np.asarray(direction, float)
    t /= np.linalg.norm(t)
    a = np.cross(t, [0.0, 0.0, 1.0]) if abs(t[2]) < 0.9 else np.cross(t, [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(t, a)
    rng = np.random.default_rng(seed)
    i, j = np.meshgrid(np.arange(n_side), np.arange(n_side), indexing="ij")
    base = (i.reshape(-1, 1) + 0.5) * spacing * a + (j.reshape(-1, 1) + 0.5) * spacing * b
    base = base + jitter * rng.normal(size=base.shape)
    pts = np.stack([base, base + length * t], axis=1).reshape(-1, 3)
    n = n_side * n_side
    return FiberPolylines(points=pts, counts=np.full(n, 2), diameter=np.full(n, diameter),
                          slot=rng.integers(0, n_slots, n), source="/Cloth/Patch")


def test_density_of_parallel_fibers_is_areal_count():
    """Fibers along x at spacing s: length per volume 1/s^2 and extinction D/s^2 in every
    voxel fully inside the patch; total length conserved exactly."""
    s, D = 0.1, 0.01
    fib = parallel_fibers(spacing=s, diameter=D)
    grid = voxelize_fibers(fib, 0.25, n_slots=1, bounds=(np.array([0.0, -1.0, -1.0]), np.array([2.0, 0.0, 0.0])))
    L = grid.length
    assert math.isclose(L.sum() * grid.voxel_size**3, 100 * 2.0, rel_tol=1e-5)
    # Voxels whose y and z range lies inside the lattice (0.25 voxels hold 2.5 x 2.5 fibers:
    # inner voxels get 2 or 3 fibers per side; average over a block of 4 x 4 voxels).
    inner = L[-4:, -4:, :].mean()
    assert math.isclose(inner, 1 / s**2, rel_tol=0.05), inner
    assert np.allclose(grid.extinction[L > 0] / L[L > 0], D, rtol=1e-5)
    occ = L > 0
    assert np.allclose(np.abs(grid.direction[occ][:, 0]), 1.0, atol=1e-5)
    assert np.all(grid.spread[occ] < 1e-5)
    # The axis is a unit vector perpendicular to the direction.
    ax = grid.axis[occ]
    assert np.allclose(np.linalg.norm(ax, axis=1), 1.0, atol=1e-5)
    assert np.all(np.abs(np.sum(ax * grid.direction[occ], axis=1)) < 1e-5)


def test_direction_is_an_axis_average():
    """Fibers along +d and -d average to d (not zero); crossed fibers give a spread."""
    d = np.array([0.6, 0.0, 0.8])
    pts = np.array([[0, 0, 0], 0.5 * d, 0.5 * d, [0, 0, 0], [0.05, 0, 0], [0.05, 0, 0] + 0.5 * np.array([0, 1.0, 0])])
    fib = FiberPolylines(points=pts, counts=np.array([2, 2, 2]), diameter=np.full(3, 0.01),
                         slot=np.zeros(3, np.int64))
    grid = voxelize_fibers(fib, 1.0, n_slots=1, bounds=(np.array([-0.5, -0.5, -0.5]), np.array([0.5, 0.5, 0.5])))
    assert grid.shape == (1, 1, 1)
    v = grid.direction[0, 0, 0]
    # Two fibers along d (length 1 total) and one along y (0.5): the principal axis is d.
    assert abs(abs(float(v @ d)) - 1.0) < 1e-5
    # Tensor eigenvalues 1 and 0.5 of trace 1.5: spread 1 - 1/1.5.
    assert math.isclose(float(grid.spread[0, 0, 0]), 1 / 3, rel_tol=1e-4)


def test_slot_mix_is_kept():
    """Per-voxel slot draws follow the slots' length shares (binomial bound: 5 sigma,
    false failure below 1e-6); slot_length holds the exact mix."""
    fib = parallel_fibers(n_side=40, spacing=0.025, n_slots=3, seed=3, jitter=0.003)
    grid = voxelize_fibers(fib, 0.05, n_slots=3, seed=11)
    occ = grid.length > 0
    share = grid.slot_length.reshape(3, -1).sum(axis=1) / grid.length.sum()
    assert np.allclose(grid.slot_length.sum(axis=0), grid.length, rtol=1e-4)
    drawn = np.bincount(grid.slot[occ], minlength=3) / occ.sum()
    n = occ.sum()
    assert np.all(np.abs(drawn - share) < 5 * np.sqrt(share * (1 - share) / n)), (drawn, share)
    assert np.all(grid.slot[~occ] == -1)


def test_footprint_voxel_size():
    assert voxel_size_for_footprint(0.2) == 0.2
    assert voxel_size_for_footprint(0.2, per_pixel=2) == 0.1
    assert voxel_size_for_footprint(0.001, fiber_diameter=0.01) == 0.01
    with pytest.raises(VoxelizeError, match="footprint"):
        voxel_size_for_footprint(float("nan"))


def test_budget_coarsens_with_a_warning_or_refuses():
    fib = parallel_fibers()
    fine = 0.01
    shape = tuple(int(math.ceil(e / fine)) for e in (2.01, 1.01, 1.01))
    budget = grid_bytes(shape, 1) // 20
    grid = voxelize_fibers(fib, fine, n_slots=1, budget_bytes=budget)
    assert grid.voxel_size > fine and grid.nbytes() <= budget
    assert grid.warnings and "over the budget" in grid.warnings[0] and "/Cloth/Patch" in grid.warnings[0]
    assert math.isclose(grid.length.sum() * grid.voxel_size**3, 200.0, rel_tol=1e-5)
    with pytest.raises(VoxelizeError, match="budget") as exc:
        voxelize_fibers(fib, fine, n_slots=1, budget_bytes=budget, coarsen=False)
    assert "/Cloth/Patch" in str(exc.value) and "\n" not in str(exc.value)


@pytest.mark.parametrize("change,match", [
    (dict(points=np.full((4, 3), np.nan)), "not all finite"),
    (dict(counts=np.array([1, 3])), "at least 2"),
    (dict(counts=np.array([2, 3])), "sum to"),
    (dict(diameter=np.array([0.01, 0.0])), "positive"),
    (dict(slot=np.array([0, 5])), "slot index"),
    (dict(diameter=np.array([0.01])), "one per curve"),
])
def test_bad_input_is_one_clear_line(change, match):
    base = dict(points=np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.0]]), counts=np.array([2, 2]),
                diameter=np.array([0.01, 0.01]), slot=np.array([0, 0]), source="/Cloth/Bad")
    base.update(change)
    with pytest.raises(VoxelizeError, match=match) as exc:
        voxelize_fibers(FiberPolylines(**base), 0.1, n_slots=1)
    assert "/Cloth/Bad" in str(exc.value) and "\n" not in str(exc.value)


def test_empty_region_and_degenerate_curves():
    fib = parallel_fibers()
    with pytest.raises(VoxelizeError, match="empty region"):
        voxelize_fibers(fib, 0.1, n_slots=1, bounds=(np.array([5.0, 5, 5]), np.array([6.0, 6, 6])))
    # Zero-length curves only: no length anywhere (a degenerate direction) -> the same error.
    pts = np.zeros((4, 3))
    dead = FiberPolylines(points=pts, counts=np.array([2, 2]), diameter=np.full(2, 0.01), slot=np.zeros(2, np.int64))
    with pytest.raises(VoxelizeError, match="empty region"):
        voxelize_fibers(dead, 0.1, n_slots=1)
    # A zero-length segment among good ones is skipped (it has no direction and no length).
    pts = np.array([[0, 0, 0], [0, 0, 0], [1, 0, 0.0]])
    grid = voxelize_fibers(FiberPolylines(points=pts, counts=np.array([3]), diameter=np.array([0.01]),
                                          slot=np.array([0])), 0.5, n_slots=1)
    assert math.isclose(grid.length.sum() * grid.voxel_size**3, 1.0, rel_tol=1e-6)
    with pytest.raises(VoxelizeError, match="voxel size"):
        voxelize_fibers(fib, 0.0, n_slots=1)


def test_axis_follows_the_fibers_rotation():
    """Given per-curve cross-section axes, a voxel's axis is its picked fiber's axis."""
    fib = parallel_fibers(n_side=4, spacing=0.1)
    ax = np.tile([0.0, math.cos(0.3), math.sin(0.3)], (16, 1))
    fib = FiberPolylines(points=fib.points, counts=fib.counts, diameter=fib.diameter, slot=fib.slot, axis=ax)
    grid = voxelize_fibers(fib, 0.2, n_slots=1)
    occ = grid.length > 0
    assert np.allclose(np.abs(grid.axis[occ] @ ax[0]), 1.0, atol=1e-5)


def test_grid_is_cropped_to_the_occupied_voxels():
    """Explicit bounds far larger than the fibers: the grid keeps only the occupied voxels
    (empty padding could put a camera's near plane inside the box), and nothing is lost."""
    fib = parallel_fibers(n_side=4, spacing=0.1, length=1.0)
    g = voxelize_fibers(fib, 0.05, n_slots=1, bounds=(np.full(3, -5.0), np.full(3, 5.0)))
    pts = fib.points
    assert np.all(g.origin >= pts.min(axis=0) - 0.05 - 1e-9) and np.all(g.upper <= pts.max(axis=0) + 0.05 + 1e-9)
    for axis in range(3):
        # Every face layer of the cropped grid holds fiber length.
        assert np.take(g.length, 0, axis=2 - axis).sum() > 0 and np.take(g.length, -1, axis=2 - axis).sum() > 0
    assert math.isclose(g.length.sum() * g.voxel_size**3, 16 * 1.0, rel_tol=1e-5)


@pytest.mark.parametrize("w_over_d", [2.5, 5.0, 20.0])
def test_count_noise_shortens_the_optical_depth_as_predicted(w_over_d):
    """Fibers along x at Poisson positions across y (a 1-voxel-thick layer): the explicit fibers
    leave a fraction exp(-n D) of a normal ray's positions uncovered, the voxel columns
    transmit mean_j exp(-k_j D / w) whose expectation is exp(-n w (1 - exp(-D / w))): the
    volume's optical depth is short by count_noise_deficit(D / w) (~D / 2w), which shrinks as
    voxels grow. Checked on the grid's own columns against the expectation within 5 standard
    errors of the column mean (false failure < 6e-7 per assertion; 8,000 columns)."""
    from usdfiber.geometry.voxelize import count_noise_deficit

    D, tau = 0.01, 1.0
    w = w_over_d * D
    cols = 8000
    Y = cols * w
    rng = np.random.default_rng(11)
    n = rng.poisson(tau / D * Y)
    y = rng.uniform(0.0, Y, n)
    z = np.full(n, 0.5 * w)
    pts = np.stack([np.stack([np.zeros(n), y, z], 1), np.stack([np.full(n, w), y, z], 1)], 1).reshape(-1, 3)
    fib = FiberPolylines(pts, np.full(n, 2), np.full(n, D), np.zeros(n, int))
    g = voxelize_fibers(fib, w, n_slots=1, bounds=(np.array([0.0, 0.0, 0.0]), np.array([w, Y, w])))
    od = g.extinction.sum(axis=0)[:, 0] * w                 # per y column, normal incidence
    t_vox = np.exp(-od)
    m = n / cols                                            # fibers per column
    a = D / w
    expect = math.exp(-m * (1.0 - math.exp(-a)))
    var = math.exp(-m * (1.0 - math.exp(-2 * a))) - expect**2   # Poisson k: E[e^{-2ak}] - E[e^{-ak}]^2
    assert abs(t_vox.mean() - expect) < 5.0 * math.sqrt(var / g.shape[1])
    # The same as an optical depth deficit against the explicit fibers' exp(-n D).
    deficit = 1.0 + math.log(expect) / (m * a)
    assert math.isclose(deficit, count_noise_deficit(a), rel_tol=1e-9)
    assert 0.4 * a < deficit < 0.5 * a


def test_zero_density_is_an_empty_region():
    """Pieces that stand for no fibers (count 0: a yarn of zero fibers per ply) leave no length:
    the same one-line error as an empty region, naming the source."""
    from usdfiber.geometry.voxelize import FiberPieces, voxelize_pieces

    m = 50
    rng = np.random.default_rng(2)
    pieces = FiberPieces(mid=rng.uniform(0, 1, (m, 3)), vec=np.tile([0.01, 0.0, 0.0], (m, 1)), count=np.zeros(m),
                         diameter=np.full(m, 0.01), slot=np.zeros(m, np.int64), source="/Cloth/Thin")
    with pytest.raises(VoxelizeError, match="empty region") as exc:
        voxelize_pieces(pieces, 0.1, n_slots=1)
    assert "/Cloth/Thin" in str(exc.value) and "\n" not in str(exc.value)
    with pytest.raises(VoxelizeError, match="counts must be finite and >= 0"):
        voxelize_pieces(FiberPieces(mid=pieces.mid, vec=pieces.vec, count=np.full(m, -1.0), diameter=pieces.diameter,
                                    slot=pieces.slot, source="/Cloth/Thin"), 0.1, n_slots=1)


@pytest.mark.parametrize("direction", [(0.0, 1.0, 0.0), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0)])
def test_degenerate_axes_fall_back_to_the_reference(direction):
    """A cross-section axis given along the fiber itself (no rotation can be read from it), and
    fibers along world y (where the paper's reference, y made perpendicular, vanishes): every
    occupied voxel still gets a unit axis perpendicular to its direction (the documented
    fallback: the reference, x for fibers along y)."""
    fib = parallel_fibers(n_side=4, spacing=0.1, direction=direction)
    t = np.asarray(direction, float)
    fib = FiberPolylines(points=fib.points, counts=fib.counts, diameter=fib.diameter, slot=fib.slot,
                         axis=np.tile(t, (len(fib.counts), 1)), source=fib.source)
    grid = voxelize_fibers(fib, 0.2, n_slots=1)
    occ = grid.length > 0
    ax, d = grid.axis[occ].astype(float), grid.direction[occ].astype(float)
    assert np.allclose(np.linalg.norm(ax, axis=1), 1.0, atol=1e-5)
    assert np.allclose(np.abs(d @ t), 1.0, atol=1e-5)
    assert np.all(np.abs(np.sum(ax * d, axis=1)) < 1e-5)
    assert np.all(np.isfinite(grid.extinction)) and np.all(np.isfinite(grid.direction))
