"""The stated bound of the middle level-of-detail step (yarns of a few pixels: fewer fibers)."""
from __future__ import annotations

import numpy as np

import usdfiber  # noqa: F401  (registers schemas first)
from usdfiber.backend import mitsuba
from usdfiber.bake.settings import BakeSettings
from usdfiber.bake.cache import TableCache
from usdfiber.translators.mitsuba import lod
from usdfiber.spec.yarn import YarnParams
from stage_util import add_lit_card

mi = mitsuba()

RES = 48                   # pixels across the (square) image
YARN_PX = 5.0              # yarn diameter in pixels at the patch's centre: the middle step at lod_scale 1
SPACING = 1.5              # yarn spacing in yarn diameters


def _yarn_patch():
    """Parallel ORA 120 yarns (2 x 90 fibers, continuous filaments) filling the view of a camera
    above them at which a yarn is YARN_PX pixels wide, over a grey card, under a dome and a key
    light. Every yarn is in view (no far-field proxies)."""
    from pxr import Gf, Usd, UsdGeom

    from usdfiber import authoring as A

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    c = UsdGeom.BasisCurves.Define(stage, "/Patch/Yarns")
    A.apply_yarn(c.GetPrim(), "ORA 120", fiber_preset="polyester", staple_length=0.0, dye="disperseBlue",
                 depth_of_shade=1.0)
    d = 2 * YarnParams.from_prim(c.GetPrim()).yarn_radius
    fov = 36.0 / 50.0                                       # aperture / focal length
    dist = d / (YARN_PX * fov / RES)
    view = fov * dist                                       # the width seen at the patch
    n = int(view / (SPACING * d))                           # yarns whose centres are in view
    length = 1.2 * view
    c.CreateTypeAttr("linear")
    pts = []
    for i in range(n):
        y = (i - (n - 1) / 2) * SPACING * d
        pts += [Gf.Vec3f(-length / 2, y, 0.0), Gf.Vec3f(length / 2, y, 0.0)]
    c.CreatePointsAttr(pts)
    c.CreateCurveVertexCountsAttr([2] * n)
    c.CreateWidthsAttr([d])
    c.SetWidthsInterpolation("constant")
    add_lit_card(stage, half_width=view, card_z=-2.0 * d, camera_z=dist)
    return stage


def render_patch(cache_dir, lod_scale: float, spp: int = 48, seed: int = 5):
    """(image (RES, RES, 3), translation counts) of the patch at ``lod_scale``."""
    from usdfiber.translators.mitsuba.scene import SceneOptions, translate_stage

    bake = BakeSettings(resolution_deg=30, photons=2000, batches=2)     # coarse: the same table for both
    tr = translate_stage(_yarn_patch(), SceneOptions(resolution=(RES, RES), spp=1, bake=bake,
                                                     cache=TableCache(cache_dir), lod_scale=lod_scale))
    return np.array(mi.render(tr.scene, spp=spp, seed=seed), np.float64)[..., :3], tr.counts


def block_rel_rmse(img: np.ndarray, ref: np.ndarray, k: int = 4) -> float:
    b = [x.reshape(RES // k, k, RES // k, k, 3).mean(axis=(1, 3)) for x in (img, ref)]
    return float(np.sqrt(np.mean((b[0] - b[1]) ** 2) / np.mean(b[1] ** 2)))


def test_middle_step_image_matches_full_expansion(tmp_path):
    """The stated bound of the middle level-of-detail step: a patch of 5-pixel ORA 120 yarns at
    lod_scale 1 (half the fibers, lod.MIN_FIBER_FRACTION, widened by 1 / fraction) against every
    fiber, 48 x 48 px over a grey card: the mean within 5 % and 4 x 4 pixel blocks within 10 %
    relative RMSE, noise included. Measured: +0.7 % and 0.042, where two renders of every fiber
    with other seeds differ by -0.1 % and 0.041 (the rest is noise). The former rule (4 fibers
    per pixel, 11 % of them here, widened by 1 / sqrt(fraction)) measures +32 % and 0.31, and
    half the fibers widened by 1 / sqrt(fraction) +5.6 % and 0.066: both fail. On the plain
    weave of bench/cloth_bench.py the step measures a few per cent (bench/REPORT.md, "Yarns,
    cloth and level of detail")."""
    full, cf = render_patch(tmp_path, 0.0)
    lod1, c1 = render_patch(tmp_path, 1.0)
    assert cf["yarn_fibers"] == cf["yarn_fibers_full"] and cf["yarn_far"] == 0 and cf["yarn_culled"] == 0
    assert c1["yarn_far"] == 0 and c1["yarn_culled"] == 0
    kept = c1["yarn_fibers"] / c1["yarn_fibers_full"]
    assert lod.MIN_FIBER_FRACTION - 0.02 <= kept < 1.0            # the middle step, at its floor
    assert np.isfinite(lod1).all() and full.mean() > 0.01
    mean = lod1.mean() / full.mean() - 1.0
    blocks = block_rel_rmse(lod1, full)
    # Bounds on a biased approximation, noise included. Two renders of every fiber with other
    # seeds differ by 0.1 % (mean) and 0.041 (block RMSE, an average over 144 blocks x 3
    # channels whose own relative spread is about 1 / sqrt(2 x 144) = 6 %): 5 % and 0.10 sit
    # tens of standard deviations of the noise away (false failure far below 1e-4).
    assert abs(mean) < 0.05, (mean, blocks)
    assert blocks < 0.10, (mean, blocks)
