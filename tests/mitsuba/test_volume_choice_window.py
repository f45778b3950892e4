"""``--cloth auto``'s prediction reads the window, not the cloth: the coverage map from run
boxes (:class:`usdfiber.geometry.yarn_density.YarnLines`) is the map over every centre-line
sample (the same window, plane and optical depth), and the samples it reads do not grow with
the cloth's size."""
from __future__ import annotations

import math

import numpy as np
import pytest

import usdfiber  # noqa: F401  (registers schemas first)
from usdfiber.geometry.voxelize import VoxelizeError
from usdfiber.geometry.yarn_density import (COVERAGE_SLAB_RADII, CoverageMap, YarnCurve, YarnLines, coverage_map,
                                            yarn_optical_depth)
from usdfiber.spec.yarn import YarnParams


def whole_cloth_map(curves, params, *, fiber_diameter, window, others=(), max_texels=768, bounds=None):
    """The coverage map by its definition (:func:`coverage_map`'s docstring), over every sample
    of every curve: (tau, texel, centre, normal). ``bounds``: the curves' (lo, hi) (default:
    their points')."""
    from scipy.spatial import cKDTree

    pts = np.concatenate([np.asarray(c.points, np.float64) for c in curves])
    r = params.yarn_radius
    lo, hi = bounds if bounds is not None else (pts.min(axis=0), pts.max(axis=0))
    mid = 0.5 * (lo + hi)
    centre = pts[int(np.argmin(np.linalg.norm(pts - mid, axis=1)))]
    near = pts[np.linalg.norm(pts - centre, axis=1) <= 0.75 * window + r]
    normal = (np.linalg.svd(near - near.mean(axis=0), full_matrices=False)[2][-1] if len(near) >= 3
              else np.array([0.0, 0.0, 1.0]))
    eye = np.eye(3)
    proj = eye - np.outer(eye @ normal, normal)
    order = np.argsort(-np.linalg.norm(proj, axis=1))
    u = proj[order[0]] / np.linalg.norm(proj[order[0]])
    v = proj[order[1]] - (proj[order[1]] @ u) * u
    axes = np.stack([u, v / np.linalg.norm(v)])
    q_all = (pts - centre) @ axes.T
    reach = np.minimum(-q_all.min(axis=0), q_all.max(axis=0)) - r
    window = float(min(window, 2.0 * max(float(reach.min()), r)))
    texel = max(r / 8.0, window / max_texels)
    n = max(1, int(math.ceil(window / texel)))
    grid = (np.arange(n) + 0.5) * texel - 0.5 * n * texel
    half = 0.5 * n * texel
    tau = np.zeros((n, n))
    for group, gp, gdia in [(curves, params, fiber_diameter), *others]:
        rg = gp.yarn_radius
        for c in group:
            p = np.asarray(c.points, np.float64) - centre
            q = p @ axes.T
            inside = np.all(np.abs(q) <= half + rg, axis=1) & (np.abs(p @ normal) <= COVERAGE_SLAB_RADII * rg)
            keep = inside[:-1] | inside[1:]
            if not keep.any():
                continue
            seg = np.diff(q, axis=0)
            k = np.maximum(1, np.ceil(np.linalg.norm(seg, axis=1) / (0.25 * texel)).astype(np.int64))
            a, d, k = q[:-1][keep], seg[keep], k[keep]
            rep = np.repeat(np.arange(len(a)), k)
            dense = a[rep] + d[rep] * ((np.arange(len(rep)) - np.repeat(np.cumsum(k) - k, k)) / k[rep])[:, None]
            lo = np.searchsorted(grid, dense.min(axis=0) - rg)
            hi = np.searchsorted(grid, dense.max(axis=0) + rg)
            if hi[0] <= lo[0] or hi[1] <= lo[1]:
                continue
            gi, gj = np.meshgrid(grid[lo[0]:hi[0]], grid[lo[1]:hi[1]], indexing="ij")
            dist, _ = cKDTree(dense).query(np.stack([gi.ravel(), gj.ravel()], axis=1), distance_upper_bound=rg)
            tau[lo[0]:hi[0], lo[1]:hi[1]] += yarn_optical_depth(
                gp, gdia, np.where(np.isfinite(dist), dist, rg)).reshape(gi.shape)
    return tau, texel, centre, normal


def assert_same_map(cov, ref):
    """The window's place is a sample chosen exactly (equal); the raster equal to rounding: the
    3-term products of the projection may be summed in another order by BLAS at another batch
    size (differences of 1e-16 relative; a wrong window, plane or a missed curve differs by
    a texel's depth or more)."""
    tau, texel, centre, normal = ref
    assert cov.texel == texel and cov.tau.shape == tau.shape
    assert np.array_equal(cov.centre, centre)
    np.testing.assert_allclose(cov.normal, normal, rtol=0, atol=1e-12)
    np.testing.assert_allclose(cov.tau, tau, rtol=1e-12, atol=1e-12 * max(1.0, float(tau.max())))
    assert float(tau.max()) > 0


def _stage(kind: str, n: int, tilt: float = 0.0):
    from pxr import Usd, UsdGeom

    from usdfiber import cloth

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    root = (cloth.plain_weave(stage, "/Cloth", warps=n, wefts=n, yarn="Skala 360") if kind == "weave"
            else cloth.stockinette(stage, "/Cloth", rows=n, loops=n))
    if tilt:
        # A tilted cloth: its plane is none of the world's.
        UsdGeom.Xformable(root).AddRotateXOp().Set(tilt)
    return stage


def _skala() -> YarnParams:
    stage = _stage("weave", 2)
    return YarnParams.from_prim(stage.GetPrimAtPath("/Cloth/Warp"))


def _yarns(stage):
    """Per yarn prim: (its samples as polylines, as YarnLines from its B-splines, params, fiber
    diameter, its control points' bounds)."""
    from pxr import Usd, UsdGeom

    from usdfiber.geometry.curves import curves_from_prim
    from usdfiber.spec.fiber import FiberParams
    from usdfiber.translators.mitsuba.fibers import yarn_polylines

    tc = Usd.TimeCode.Default()
    out = {}
    for prim in stage.Traverse():
        if not prim.HasAPI("FiberYarnAPI"):
            continue
        yp = YarnParams.from_prim(prim, tc)
        geom = curves_from_prim(prim, tc, default_width=2 * yp.yarn_radius)
        dia = FiberParams.from_prim(prim, tc).diameter * 1e-6 / UsdGeom.GetStageMetersPerUnit(stage)
        out[str(prim.GetPath())] = ([YarnCurve(p) for p, _ in yarn_polylines(geom, 2)],
                                    YarnLines.from_geometry(geom, 2), yp, dia,
                                    (geom.points.min(axis=0), geom.points.max(axis=0)))
    return out


def test_lines_read_the_samples_of_the_polylines():
    """YarnLines from B-splines evaluates the samples the translator's polylines hold (bitwise:
    the same evaluation), wherever they are read from, and its run boxes hold them."""
    ys = _yarns(_stage("knit", 6, tilt=20.0))
    (curves, lines, _, _, _), = ys.values()
    pts = np.concatenate([c.points for c in curves])
    assert lines.curve_count == len(curves) and lines.sample_count == len(pts)
    rng = np.random.default_rng(3)
    idx = np.sort(rng.choice(len(pts), 500, replace=False))
    assert np.array_equal(lines.points(idx), pts[idx])
    assert np.array_equal(lines.points(np.arange(len(pts))), pts)
    assert len(lines.run_start) > 10
    for r in range(len(lines.run_start)):
        p = pts[lines.run_start[r]:lines.run_stop[r]]
        assert np.all(p >= lines.run_lo[r] - 1e-12) and np.all(p <= lines.run_hi[r] + 1e-12)
        assert lines.run_curve[r] == np.searchsorted(np.cumsum([len(c.points) for c in curves]), lines.run_start[r],
                                                     side="right")


def test_lines_of_control_points_stored_out_of_order():
    """The same curves with each segment's four control points stored apart, in shuffled order
    (a layout whose runs are not spans of the points): the same samples, boxes that hold them."""
    import dataclasses

    from pxr import Usd

    from usdfiber.geometry.curves import curves_from_prim

    stage = _stage("knit", 4, tilt=20.0)
    yp = YarnParams.from_prim(stage.GetPrimAtPath("/Cloth/Rows"))
    geom = curves_from_prim(stage.GetPrimAtPath("/Cloth/Rows"), Usd.TimeCode.Default(),
                            default_width=2 * yp.yarn_radius)
    window = geom.segment_start[:, None] + np.arange(4)
    pos = np.random.default_rng(2).permutation(geom.segment_count)
    points, radii = np.empty((4 * geom.segment_count, 3)), np.empty(4 * geom.segment_count)
    points.reshape(-1, 4, 3)[pos], radii.reshape(-1, 4)[pos] = geom.points[window], geom.radii[window]
    apart = dataclasses.replace(geom, points=points, radii=radii, segment_start=4 * pos)
    lines, shuffled = YarnLines.from_geometry(geom), YarnLines.from_geometry(apart)
    every = np.arange(lines.sample_count)
    pts = lines.points(every)
    assert np.array_equal(shuffled.points(every), pts)
    for r in range(len(shuffled.run_start)):
        p = pts[shuffled.run_start[r]:shuffled.run_stop[r]]
        assert np.all(p >= shuffled.run_lo[r] - 1e-12) and np.all(p <= shuffled.run_hi[r] + 1e-12)


@pytest.mark.parametrize("kind,n,tilt,window_yarns,cut", [("weave", 40, 0.0, 16.0, False),   # the sheer Skala weave
                                                          ("weave", 10, 35.0, 30.0, True),   # tilted, cut by its edge
                                                          ("knit", 24, 0.0, 16.0, False),    # the generator's knit
                                                          ("knit", 8, 50.0, 40.0, True)])    # tilted, cut
def test_map_from_run_boxes_is_the_whole_cloth_map(kind, n, tilt, window_yarns, cut):
    """Weave (warps placing the window, wefts added) and knit, flat and tilted, with windows
    inside the cloth and cut by its edge: the same window, plane and raster as over every
    sample, from the B-splines (centred by their control points' bounds) and from polylines
    (by their points')."""
    ys = _yarns(_stage(kind, n, tilt))
    for path, (curves, lines, yp, dia, ctrl) in ys.items():
        others = [(v[1], v[2], v[3]) for k, v in ys.items() if k != path]
        others_ref = [(v[0], v[2], v[3]) for k, v in ys.items() if k != path]
        window = window_yarns * 2 * yp.yarn_radius
        ref = whole_cloth_map(curves, yp, fiber_diameter=dia, window=window, others=others_ref, bounds=ctrl)
        cov = coverage_map(lines, yp, fiber_diameter=dia, window=window, others=others)
        assert_same_map(cov, ref)
        assert (cov.tau.shape[0] * cov.texel < 0.9 * window) == cut
        ref = whole_cloth_map(curves, yp, fiber_diameter=dia, window=window, others=others_ref)
        assert_same_map(coverage_map(curves, yp, fiber_diameter=dia, window=window, others=others_ref), ref)


def test_parallel_yarns_map_is_the_whole_cloth_map():
    """The straight parallel yarns of test_volume_choice, and a yarn that leaves the window and
    comes back (a run with a gap in the middle): the whole-cloth map."""
    yp = _skala()
    d = 2 * yp.yarn_radius
    x = np.linspace(-40 * d, 40 * d, 401)
    curves = [YarnCurve(np.stack([x, np.full_like(x, k * 2.5 * d), np.zeros_like(x)], axis=1)) for k in range(-30, 31)]
    s = np.linspace(0.0, 1.0, 2001)
    loop = np.stack([30 * d * np.cos(2 * np.pi * s), 12 * d * np.sin(4 * np.pi * s), 0.2 * d * np.sin(40 * s)], axis=1)
    for group in (curves, curves + [YarnCurve(loop)]):
        ref = whole_cloth_map(group, yp, fiber_diameter=0.01, window=20 * d)
        assert_same_map(coverage_map(group, yp, fiber_diameter=0.01, window=20 * d), ref)


def test_nearest_sample_along_a_direction_is_exact():
    """``nearest_along`` finds the least projection over every sample (transformed first when
    asked), the first among equals."""
    rng = np.random.default_rng(5)
    pts = rng.normal(size=(20000, 3)) * [5.0, 2.0, 0.5]
    lines = YarnLines.from_points(pts)
    origin, direction = np.array([1.0, -3.0, 40.0]), np.array([0.3, -0.2, -0.93])
    assert np.array_equal(lines.nearest_along(origin, direction), pts[np.argmin((pts - origin) @ direction)])
    xf = np.eye(4)
    xf[:3, :3] = [[0.0, 2.0, 0.0], [-2.0, 0.0, 0.0], [0.0, 0.0, 2.0]]
    xf[3, :3] = [7.0, -1.0, 3.0]
    world = pts @ xf[:3, :3] + xf[3, :3]
    assert np.array_equal(lines.nearest_along(origin, direction, xf), world[np.argmin((world - origin) @ direction)])
    ties = YarnLines.from_points(np.array([[0.0, 0, 1], [0, 0, 0], [5, 5, 0], [0, 0, 2]]))
    assert np.array_equal(ties.nearest_along(np.zeros(3), np.array([0.0, 0, 1])), [0.0, 0, 0])


def test_prediction_reads_the_window_not_the_cloth():
    """A weave 16x larger in area (4x longer yarns): the map reads about the same samples and
    deposits the same yarns, a vanishing fraction of the cloth's samples (a pass over the
    whole cloth reads every sample of every prim)."""
    stats = {}
    for n in (60, 240):
        ys = _yarns(_stage("weave", n))
        _, lines, yp, dia, _ = ys["/Cloth/Warp"]
        others = [(v[1], v[2], v[3]) for k, v in ys.items() if k != "/Cloth/Warp"]
        cov = coverage_map(lines, yp, fiber_diameter=dia, window=16 * 2 * yp.yarn_radius, others=others)
        stats[n] = (cov.points_read, cov.curves_deposited, sum(v[1].sample_count for v in ys.values()))
    (read_s, dep_s, total_s), (read_l, dep_l, total_l) = stats[60], stats[240]
    assert total_l > 15 * total_s
    assert dep_l == dep_s and dep_s > 10          # the same yarns cross the window
    assert read_l <= 1.1 * read_s                 # the reads follow the window ...
    assert read_l < 0.01 * total_l                # ... not the cloth


def test_not_finite_or_empty_curves_are_one_clear_line():
    yp = _skala()
    bad = np.zeros((5, 3))
    bad[2, 1] = np.nan
    with pytest.raises(VoxelizeError, match=r"^/W: yarn points are not all finite \(NaN or Inf\)$"):
        coverage_map([YarnCurve(bad)], yp, fiber_diameter=0.01, window=1.0, source="/W")
    with pytest.raises(VoxelizeError, match=r"^/W: no yarn curves to measure the coverage of$"):
        coverage_map([YarnCurve(np.zeros((1, 3)))], yp, fiber_diameter=0.01, window=1.0, source="/W")


@pytest.mark.parametrize("kind,n,distance", [("weave", 40, 300.0), ("knit", 24, 600.0)])
def test_auto_choice_numbers_are_those_over_every_point(kind, n, distance):
    """``split_cloth``'s numbers on a tilted cloth: the yarns' pixels over every control point,
    the voxel from the footprint at the nearest of every sample, the excess of the whole-cloth
    map at that voxel."""
    from pxr import Gf, Usd, UsdGeom

    from usdfiber.geometry.voxelize import voxel_size_for_footprint
    from usdfiber.translators.mitsuba.fibers import fiber_prim
    from usdfiber.translators.mitsuba.lod import camera_view
    from usdfiber.translators.mitsuba.stage_walk import walk
    from usdfiber.translators.mitsuba.volume.scene import COVERAGE_WINDOW_VOXELS, COVERAGE_WINDOW_YARNS, split_cloth

    stage = _stage(kind, n, tilt=30.0)
    cam = UsdGeom.Camera.Define(stage, "/Cam")
    cam.AddTranslateOp().Set(Gf.Vec3d(3.0, 2.0, distance))
    cam.CreateFocalLengthAttr(50.0)
    cam.CreateHorizontalApertureAttr(36.0)
    tc = Usd.TimeCode.Default()
    view = camera_view(stage.GetPrimAtPath("/Cam"), tc, 160, 160)
    pls = [pl for pl in walk(stage, tc, ("default", "render"), (UsdGeom.Gprim,)) if fiber_prim(pl.prim)]
    _, _, notes = split_cloth(pls, "auto", view, tc)
    ys = _yarns(stage)
    for pl, note in zip(pls, notes):
        curves, _, yp, dia, ctrl = ys[pl.path]
        xf = np.asarray(pl.xform, np.float64)
        local = np.asarray(UsdGeom.BasisCurves(pl.prim).GetPointsAttr().Get(tc), np.float64)
        assert note.yarn_pixels == view.pixels(2 * yp.yarn_radius, local @ xf[:3, :3] + xf[3, :3]) < 1.0
        footprint = 1.0 / view.pixels(1.0, np.concatenate([c.points for c in curves]))
        voxel = voxel_size_for_footprint(footprint, fiber_diameter=dia, per_pixel=1.0)
        assert note.voxel_size == voxel
        others = [(v[0], v[2], v[3]) for k, v in ys.items() if k != pl.path]
        window = max(COVERAGE_WINDOW_VOXELS * voxel, COVERAGE_WINDOW_YARNS * 2.0 * yp.yarn_radius)
        tau, texel, centre, normal = whole_cloth_map(curves, yp, fiber_diameter=dia, window=window, others=others,
                                                     bounds=ctrl)
        ref = CoverageMap(tau=tau, texel=texel, centre=centre, normal=normal, axes=np.eye(3)[:2])
        assert note.opacity_excess == pytest.approx(ref.opacity_bias(voxel), rel=1e-9, abs=1e-12)
        assert note.coverage == pytest.approx(ref.coverage, abs=1e-12)
