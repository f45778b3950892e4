"""The far field of a whole yarn: traced through its fibers with their own BCSDFs."""
from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

import usdfiber  # noqa: F401  (registers schemas first)
from usdfiber import presets
from usdfiber.backend import mitsuba
from usdfiber.bake import profiles
from usdfiber.bake.baker import bake_table
from usdfiber.bake.settings import BakeSettings
from usdfiber.bake.cache import TableCache, TableCacheWarning

from usdfiber.translators.mitsuba.curves import CurveGeometry
from usdfiber.translators.mitsuba.fiber_bank import FiberBank, FiberSlot
from usdfiber.translators.mitsuba.fiber_bsdf import fiber_bsdf
from usdfiber.translators.mitsuba.yarn_far_field import (YarnBakeSettings, YarnFarField, YarnFarFieldCache, YarnPiece,
                                                 bake_yarn_far_field, trace_far_field)
from usdfiber.spec.yarn import YarnParams

mi = mitsuba()
import drjit as dr  # noqa: E402  (after the variant is set)

from stats_util import FALSE_FAILURE, binomial_limit, chi2_limit, z_limit  # noqa: E402


@pytest.fixture(scope="module")
def silk():
    prof = profiles.builtin_profiles("silk", 1)[0]
    return bake_table(prof, 1.55, 8.0, None, BakeSettings(resolution_deg=15, photons=2000, batches=2))


def _small_yarn(**kw) -> YarnParams:
    """A 2-ply yarn of 2 x 24 fibers (ORA 120's twist and ply radius), quick to trace."""
    attrs = presets.yarn_preset("ORA 120").yarn_attributes()
    attrs.update({"yarn:fibersPerPly": 24, "yarn:ply:radius": 0.06, "yarn:fiber:stapleLength": 0.0})
    attrs.update(kw)
    return YarnParams.from_attributes(attrs, 0.01)


FIBER_D = 12e-4    # 12 um in cm


def _single_fiber(table, radius: float):
    """One straight fiber on the axis of a piece of bounding radius 1 (a "yarn" of one fiber)."""
    lz = 4.0
    z = np.linspace(-1.0, lz + 1.0, 8)
    pts = np.stack([0 * z, 0 * z, z], 1)
    geom = CurveGeometry(pts, np.full(len(pts), radius), np.arange(len(pts) - 3),
                         np.zeros(len(pts) - 3, np.int64), 1)
    bank = FiberBank.build([FiberSlot(table, (0.0, 0.0, 0.0))])
    n = geom.segment_count
    bsdf = fiber_bsdf(mi, bank, np.zeros(n, np.int64), np.zeros(n), np.tile([1.0, 0.0, 0.0], (n, 1)))
    return YarnPiece(geom, lz, 1.0, 1), bsdf


def _bin_masses(bsdf, grid, theta_i: float, m: int = 6) -> np.ndarray:
    """Each (theta_o, phi_o - phi_i) bin's probability under the BSDF's own sampling density."""
    n_to, n_po = grid.n_theta_o, grid.n_phi_o
    e = grid.theta_o_edges()
    sub = (np.arange(m) + 0.5) / m
    s = np.sin(e[:-1])[:, None] + (np.sin(e[1:]) - np.sin(e[:-1]))[:, None] * sub   # uniform in solid angle
    th = np.broadcast_to(np.arcsin(s)[:, None, :, None], (n_to, n_po, m, m)).ravel()
    ph = np.broadcast_to(((np.arange(n_po)[:, None] + sub) * grid.step - 0.5 * grid.step)[None, :, None, :],
                         (n_to, n_po, m, m)).ravel()
    n = len(th)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
    t, x = np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.0])   # tangent +y, reference +x
    y = np.cross(t, x)
    wv = math.cos(theta_i) * x + math.sin(theta_i) * t
    si.wi = mi.Vector3f(*[float(v) for v in wv])
    si.prim_index = 0
    wl = (np.cos(th)[:, None] * (np.cos(ph)[:, None] * x + np.sin(ph)[:, None] * y) + np.sin(th)[:, None] * t)
    ctx = mi.BSDFContext()
    ctx.type_mask = int(mi.BSDFFlags.Glossy)
    _, pdf = bsdf.eval_pdf(ctx, si, mi.Vector3f(*(mi.Float(wl[:, k].astype(np.float32)) for k in range(3))))
    dom = np.repeat(grid.solid_angles(), n_po).reshape(n_to, n_po)
    mass = np.array(pdf).reshape(n_to, n_po, m * m).mean(-1) * dom
    return mass / mass.sum()


def test_one_fiber_yarn_is_the_fiber(circle_table):
    """A "yarn" of one straight fiber of radius 0.3 in a bounding radius 1: the beam meets it with
    probability 0.3 (its projected width over the bounding width), nothing is absorbed, and the
    exiting directions follow the fiber BSDF's own density (chi-square against its pdf)."""
    piece, bsdf = _single_fiber(circle_table, 0.3)
    st = YarnBakeSettings(resolution_deg=10, photons=24000, batches=4)
    ff = trace_far_field(piece, bsdf, st)
    n = ff.arrays["photons"][:, 0]
    cov = ff.coverage
    # Binomial(n, 0.3) hits per direction: exact limits, false failure 1e-4 over all the
    # directions together (4.5 sd per direction was 7e-6 each, 1.2e-4 over the 18).
    lim = np.array([binomial_limit(0.3, int(k), FALSE_FAILURE / len(n)) for k in n])
    assert np.all(np.abs(cov - 0.3) <= lim), cov
    np.testing.assert_allclose(ff.arrays["albedo"], 1.0, atol=1e-6)
    assert ff.header["lost_energy_max"] == 0.0
    g = ff.grid
    dom = np.repeat(g.solid_angles(), g.n_phi_o).reshape(g.n_theta_o, g.n_phi_o)
    for k in (1, 6, 9, 13):
        expected = _bin_masses(bsdf, g, float(g.theta_i_nodes()[k]))
        n_s = n[k] * cov[k]
        obs = ff.arrays["p"][k, 0, :, :, 0] * dom * n_s
        exp = expected * n_s
        big = exp >= 5
        chi2 = ((obs[big] - exp[big]) ** 2 / exp[big]).sum()
        dof = int(big.sum())
        # Pearson chi-square over the bins expecting >= 5 photons: its quantile at a false
        # failure of 1e-4 over the four directions (the former fixed chi2/dof < 1.45 had no
        # stated level).
        assert chi2 < chi2_limit(dof, FALSE_FAILURE / 4), (k, chi2 / dof, dof)


@pytest.fixture(scope="module")
def undyed_silk_yarn(silk):
    yp = _small_yarn()
    return bake_yarn_far_field(yp, FIBER_D, [FiberSlot(silk, (0.0, 0.0, 0.0))],
                               YarnBakeSettings(resolution_deg=15, photons=2000, batches=4))


def test_white_furnace(undyed_silk_yarn):
    """Undyed fibers absorb nothing: every photon that scatters leaves the yarn (the far field
    recoloured to zero absorption, which is its first traced level)."""
    ff = undyed_silk_yarn
    rec = ff.recolour(0.0)
    np.testing.assert_allclose(rec.albedo, 1.0, atol=1e-3)
    np.testing.assert_array_equal(rec.albedo[..., 0], ff.arrays["albedo"][..., 0])
    assert ff.header["lost_energy_max"] < 1e-3
    for c in range(3):
        masses = rec.p[:, 0, :, :, c] * np.repeat(ff.grid.solid_angles(), ff.grid.n_phi_o).reshape(
            ff.grid.n_theta_o, ff.grid.n_phi_o)
        np.testing.assert_allclose(masses.sum(axis=(1, 2)), 1.0, rtol=1e-5)


def test_coverage_is_a_function_of_abs_theta(undyed_silk_yarn):
    """The line through the yarn from theta is the line from -theta turned by 180 degrees:
    coverage(theta) = coverage(-theta); and grazing rays cross more of the yarn."""
    ff = undyed_silk_yarn
    cov, n = ff.coverage.astype(float), ff.arrays["photons"][:, 0]
    sig = np.sqrt(cov * (1 - cov) / n + cov[::-1] * (1 - cov[::-1]) / n[::-1])
    # Difference of two independent binomial fractions (normal approximation, n >= 2000 per
    # direction): each mirrored pair is checked twice, so len(cov) / 2 independent checks at
    # z_limit share the 1e-4 (4.5 sd was 7e-6 each).
    assert np.all(np.abs(cov - cov[::-1]) < z_limit(FALSE_FAILURE / max(1, len(cov) // 2)) * sig + 1e-9)
    assert 0.2 < cov[len(cov) // 2] < 1.0
    assert cov[0] > cov[len(cov) // 2]


def test_dye_darkens_the_yarn_more_than_one_fiber(silk):
    """A dyed yarn is darker than one of its fibers (light meets several fibers before it
    leaves), and darker for more dye; red dye keeps red brightest."""
    yp = _small_yarn()
    st = YarnBakeSettings(resolution_deg=15, photons=2000, batches=2, realizations=1)  # one placement: a dye test
    light = (0.02, 0.2, 0.4)
    deep = tuple(4 * s for s in light)
    ff = bake_yarn_far_field(yp, FIBER_D, [FiberSlot(silk, light)], st)   # any colour: recoloured
    a_light = ff.recolour(list(light)).albedo[:, 0]
    a_deep = ff.recolour(list(deep)).albedo[:, 0]
    fiber = silk.recolour(list(light)).albedo.mean(axis=(0, 1))
    assert np.all(a_deep < a_light)
    assert np.all(a_light[:, 0] > a_light[:, 1]) and np.all(a_light[:, 1] > a_light[:, 2])
    mid = len(a_light) // 2
    assert np.all(a_light[mid, 1:] < fiber[1:])


def test_cache_reuses_and_replaces_damaged_files(tmp_path, silk):
    yp = _small_yarn()
    st = YarnBakeSettings(resolution_deg=30, photons=400, batches=2, realizations=1)  # one placement: a cache test
    cache = YarnFarFieldCache(TableCache(tmp_path))
    slots = [FiberSlot(silk, (0.1, 0.1, 0.1))]
    ff, traced = cache.get_or_bake(yp, FIBER_D, slots, st)
    assert traced and ff is not None
    again, traced = cache.get_or_bake(yp, FIBER_D, slots, st)
    assert not traced
    np.testing.assert_array_equal(again.arrays["p"], ff.arrays["p"])
    # another colour is the same far field, recoloured; other absorption levels are another one
    assert cache.get_or_bake(yp, FIBER_D, [FiberSlot(silk, (0.2, 0.1, 0.1))], st, bake_missing=False)[0] is not None
    other = YarnBakeSettings(resolution_deg=30, photons=400, batches=2, levels=(0.0, 1.0, 4.0), realizations=1)
    assert cache.get_or_bake(yp, FIBER_D, slots, other, bake_missing=False)[0] is None
    path = next((tmp_path / "yarns").glob("*.npz"))
    path.write_bytes(path.read_bytes()[:200])
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        ff2, traced = cache.get_or_bake(yp, FIBER_D, slots, st)
    assert traced and any(issubclass(w.category, TableCacheWarning) for w in rec)
    assert YarnFarField.load(path).arrays["p"].shape == ff2.arrays["p"].shape


def _yarn_patch(expand: bool, n: int = 24, spacing: float = 0.3):
    """A patch of n parallel small yarns (mm) under a dome and a key light, seen from above at
    a distance where a yarn is about one pixel wide."""
    from pxr import Gf, Usd, UsdGeom, UsdLux

    from usdfiber import authoring as A

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    length = n * spacing
    c = UsdGeom.BasisCurves.Define(stage, "/Patch/Yarns")
    c.CreateTypeAttr("linear")
    pts = []
    for i in range(n):
        y = (i - (n - 1) / 2) * spacing
        pts += [Gf.Vec3f(-length / 2, y, 0.0), Gf.Vec3f(length / 2, y, 0.0)]
    c.CreatePointsAttr(pts)
    c.CreateCurveVertexCountsAttr([2] * n)
    A.apply_yarn(c.GetPrim(), "ORA 120", fiber_preset="polyester", fibers_per_ply=24, ply_radius=0.06,
                 staple_length=0.0, expand_fibers=expand, dye="disperseBlue", depth_of_shade=1.0)
    c.CreateWidthsAttr([2 * YarnParams.from_prim(c.GetPrim()).yarn_radius])
    c.SetWidthsInterpolation("constant")
    cam = UsdGeom.Camera.Define(stage, "/Cam")
    cam.CreateFocalLengthAttr(50.0)
    cam.CreateHorizontalApertureAttr(36.0)
    cam.CreateVerticalApertureAttr(36.0)
    cam.AddTranslateOp().Set(Gf.Vec3d(0.0, 0.0, 1.25 * length / 0.72))
    UsdLux.DomeLight.Define(stage, "/Sky").CreateIntensityAttr(0.5)
    key = UsdLux.DistantLight.Define(stage, "/Key")
    key.CreateIntensityAttr(2.0)
    key.AddRotateXYZOp().Set(Gf.Vec3f(35.0, 20.0, 0.0))
    return stage


def test_far_field_image_matches_full_expansion(table_cache_dir):
    """The stated bound of the far-yarn level of detail: a patch of one-pixel yarns drawn with
    their far field against every fiber expanded, 32 x 32 px: the mean within 8 % and 4 x 4
    pixel blocks within 15 % relative RMSE (bench/REPORT.md measures 2.8 % and 4 %)."""
    from usdfiber.translators.mitsuba.scene import SceneOptions, translate_stage

    bake = BakeSettings(resolution_deg=15, photons=4000, batches=4)
    yb = YarnBakeSettings(resolution_deg=15, photons=6000, batches=4)
    imgs = []
    for expand in (True, False):
        tr = translate_stage(_yarn_patch(expand), SceneOptions(resolution=(32, 32), spp=1, bake=bake, yarn_bake=yb,
                                                               cache=TableCache(table_cache_dir),
                                                               lod_scale=0.0 if expand else 1.0))
        c = tr.counts
        assert (c["yarn_far"], c["yarn_fibers"] > 0) == ((0, True) if expand else (24, False))
        imgs.append(np.array(mi.render(tr.scene, spp=256, seed=3), np.float64)[..., :3])
    full, far = imgs
    assert np.isfinite(far).all() and full.mean() > 0.01
    # Bounds on an approximation (the far field is a different estimator of the yarn), not on
    # noise: measured 2.8 % and 4 % against 8 % and 15 %. Noise of 32 x 32 px at 256 spp moves
    # the mean by about 0.1 % and the block RMSE (an average over 64 blocks) by a few percent
    # of itself, so noise alone fails neither bound (false failure far below 1e-4).
    assert abs(far.mean() / full.mean() - 1.0) < 0.08
    blocks = [im.reshape(8, 4, 8, 4, 3).mean(axis=(1, 3)) for im in imgs]
    rel = np.sqrt(np.mean((blocks[1] - blocks[0]) ** 2) / np.mean(blocks[0] ** 2))
    assert rel < 0.15, rel
