"""Where a volume is biased: the homogenization of a weave's gaps by voxels wider than them
(:class:`usdfiber.geometry.yarn_density.CoverageMap`), ``--cloth auto``'s choice by it and
``--cloth volume``'s warning."""
from __future__ import annotations

import math

import numpy as np
import pytest

import usdfiber  # noqa: F401  (registers schemas first)
from usdfiber.geometry.yarn_density import CoverageMap, YarnCurve, coverage_map, yarn_optical_depth
from usdfiber.spec.yarn import YarnParams


def stripes(period: int, width: int, tau0: float, n: int = 240) -> CoverageMap:
    """Stripes along the raster's second axis: ``width`` of every ``period`` texels at optical
    depth ``tau0``."""
    tau = np.zeros((n, n))
    tau[(np.arange(n) % period) < width, :] = tau0
    return CoverageMap(tau=tau, texel=1.0, centre=np.zeros(3), normal=np.array([0.0, 0.0, 1.0]),
                       axes=np.eye(3)[:2])


@pytest.mark.parametrize("period,width,tau0", [(12, 5, 2.0), (20, 4, 0.5), (8, 7, 6.0)])
def test_voxels_over_whole_periods_lose_the_gaps_exactly(period, width, tau0):
    """Voxels of whole periods hold coverage c = width / period of every stripe at every phase:
    each transmits exp(-c tau0), the yarns 1 - c + c exp(-tau0) (Jensen's gap, exact)."""
    c = width / period
    cov = stripes(period, width, tau0)
    expect = (1.0 - math.exp(-c * tau0)) / (c * (1.0 - math.exp(-tau0))) - 1.0
    for k in (1, 2, 3):
        assert cov.opacity_bias(k * period) == pytest.approx(expect, rel=1e-12)
    assert expect > 0.05


def test_no_excess_without_gaps_or_below_a_texel():
    """A cloth without gaps (uniform depth) or voxels of one texel: no excess; finer voxels
    resolve part of the gaps: less excess than whole periods, more than none."""
    uniform = CoverageMap(tau=np.full((64, 64), 1.3), texel=1.0, centre=np.zeros(3),
                          normal=np.array([0.0, 0.0, 1.0]), axes=np.eye(3)[:2])
    assert abs(uniform.opacity_bias(8.0)) < 1e-12
    cov = stripes(16, 6, 3.0)
    assert cov.opacity_bias(1.0) == 0.0
    assert 0.0 < cov.opacity_bias(4.0) < cov.opacity_bias(16.0)
    assert cov.voxel_for_bias(16.0, 0.02) <= 4.0
    assert math.isnan(cov.opacity_bias(200.0))          # fewer than two voxels across the window


def _yarn() -> YarnParams:
    from pxr import Usd, UsdGeom

    from usdfiber import cloth

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    cloth.plain_weave(stage, "/W", warps=2, wefts=2, yarn="Skala 360")
    return YarnParams.from_prim(stage.GetPrimAtPath("/W/Warp"))


def test_coverage_map_of_parallel_yarns():
    """Straight parallel yarns p apart: they cover d / p of the plane, and the optical depth
    integrates to the fibers' summed width n D per yarn (mean n D / p), to the raster's
    resolution."""
    yarn = _yarn()
    d, D = 2 * yarn.yarn_radius, 0.01
    p = 2.5 * d
    x = np.linspace(-40 * d, 40 * d, 401)              # sampled as densely as a centre line
    curves = [YarnCurve(np.stack([x, np.full_like(x, k * p), np.zeros_like(x)], axis=1)) for k in range(-30, 31)]
    cov = coverage_map(curves, yarn, fiber_diameter=D, window=20 * d)
    assert cov.coverage == pytest.approx(d / p, rel=0.05)
    assert float(cov.tau.mean()) == pytest.approx(yarn.fiber_count * D / p, rel=0.03)
    assert abs(float(cov.normal[2])) == pytest.approx(1.0)
    width = np.trapezoid(yarn_optical_depth(yarn, D, np.linspace(-d, d, 20001)), dx=2 * d / 20000)
    assert width == pytest.approx(yarn.fiber_count * D, rel=1e-4)


# ---------------------------------------------------------------------------------------------
# --cloth auto and --cloth volume on stages
# ---------------------------------------------------------------------------------------------

def _cloth_stage(kind: str, distance: float):
    """A sheer plain weave of Skala 360 (coverage 0.4 per direction) or a stockinette of the
    default yarn (the generator's densest), seen from ``distance`` mm above by a 160-pixel
    camera (50 mm lens, 36 mm aperture)."""
    from pxr import Gf, Usd, UsdGeom

    from usdfiber import cloth

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    UsdGeom.SetStageUpAxis(stage, "Z")
    if kind == "sheer":
        root = cloth.plain_weave(stage, "/Cloth", warps=40, wefts=40, yarn="Skala 360")
    else:
        root = cloth.stockinette(stage, "/Cloth", rows=24, loops=24)
    box = UsdGeom.BBoxCache(Usd.TimeCode.Default(), ["default"]).ComputeWorldBound(root).ComputeAlignedRange()
    c = 0.5 * (box.GetMin() + box.GetMax())
    cam = UsdGeom.Camera.Define(stage, "/Cam")
    cam.AddTranslateOp().Set(Gf.Vec3d(c[0], c[1], c[2] + distance))
    cam.CreateFocalLengthAttr(50.0)
    cam.CreateHorizontalApertureAttr(36.0)
    cam.CreateVerticalApertureAttr(36.0)
    return stage


def _choices(stage, mode="auto"):
    from pxr import Usd, UsdGeom

    from usdfiber.translators.mitsuba.fibers import fiber_prim
    from usdfiber.translators.mitsuba.lod import camera_view
    from usdfiber.translators.mitsuba.stage_walk import walk
    from usdfiber.translators.mitsuba.volume.scene import split_cloth

    tc = Usd.TimeCode.Default()
    view = camera_view(stage.GetPrimAtPath("/Cam"), tc, 160, 160)
    pls = [pl for pl in walk(stage, tc, ("default", "render"), (UsdGeom.Gprim,)) if fiber_prim(pl.prim)]
    return split_cloth(pls, mode, view, tc)


def test_auto_keeps_a_sheer_weave_of_subpixel_yarns_out_of_the_volume():
    """Yarns a tenth of a pixel wide, 2.5 diameters apart: a footprint voxel holds yarns and gaps
    alike; the volume would be far more opaque than the weave, so auto keeps the far field and
    says why (the predicted excess, the voxel that would resolve the gaps)."""
    from usdfiber.translators.mitsuba.volume.scene import VOLUME_OPACITY_BOUND

    vols, curves, notes = _choices(_cloth_stage("sheer", 300.0))
    assert vols == [] and len(curves) == 2
    for n in notes:
        assert n.mode == "yarn far field" and n.yarn_pixels < 1.0
        assert n.opacity_excess > 2 * VOLUME_OPACITY_BOUND
        line = str(n)
        assert line.startswith(f"{n.path}: yarn far field (") and "over the gaps" in line and "\n" not in line
        assert n.to_json()["mode"] == "yarn far field"


def test_auto_makes_a_dense_knit_at_garment_distance_a_volume():
    """The generator's stockinette (coverage 0.89) at 0.6 m, yarns a tenth of a pixel: its
    voxels lose only the knit's small holes, within the bound: a volume."""
    from usdfiber.translators.mitsuba.volume.scene import VOLUME_OPACITY_BOUND

    vols, curves, notes = _choices(_cloth_stage("knit", 600.0))
    assert len(vols) == 1 and curves == []
    (n,) = notes
    assert n.mode == "volume" and 0.0 < n.opacity_excess <= VOLUME_OPACITY_BOUND
    assert n.coverage > 0.8
    assert str(n).startswith("/Cloth/Rows: volume (yarns ")


def test_volume_mode_warns_where_the_voxels_exceed_the_gaps(tmp_path):
    """``--cloth volume`` on the sheer weave: one line per prim naming it, the expected excess
    and the voxel size that resolves the gaps; on the dense knit none."""
    from pxr import Usd

    from usdfiber.backend import mitsuba
    from usdfiber.bake.cache import TableCache
    from usdfiber.bake.settings import BakeSettings
    from usdfiber.translators.mitsuba.volume.scene import translate_volumes

    mi = mitsuba()
    stage = _cloth_stage("sheer", 300.0)
    vols, _, notes = _choices(stage, "volume")
    assert [n.mode for n in notes] == ["volume", "volume"]
    vt, _ = translate_volumes(mi, vols[:1], stage, Usd.TimeCode.Default(), voxel_size=0.5,
                              settings=BakeSettings(resolution_deg=15, photons=2000, batches=2),
                              cache=TableCache(tmp_path))
    msgs = [w for w in vt.warnings if "over the gaps" in w]
    assert len(msgs) == 1 and msgs[0].startswith("/Cloth/Warp: 0.5-unit voxels spread the yarns")
    assert "more opaque than the cloth" in msgs[0] and "MiB" in msgs[0] and "\n" not in msgs[0]
