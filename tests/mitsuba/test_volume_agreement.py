"""A patch of parallel fibers rendered as curves and as a volume (``--cloth volume``) agrees in the
mean; the render mode's choice per prim is reported."""
from __future__ import annotations

import numpy as np
import pytest

import usdfiber  # noqa: F401  (registers schemas first)
from usdfiber.backend import mitsuba
from usdfiber.bake.cache import TableCache
from usdfiber.bake.settings import BakeSettings
from stage_util import add_lit_card

mi = mitsuba()

RES = 32
D = 0.005         # fiber diameter, mm: a voxel holds many fibers
SIZE = 1.0        # patch side, mm
THICK = 0.1       # patch thickness, mm


def fiber_patch(tau: float, seed: int = 3):
    """Straight polyester fibers along x at uniformly random (y, z) in a SIZE x THICK cross
    section: optical thickness ``tau`` across the patch (n D THICK, n fibers per mm^2), over a
    grey card, under a dome and a key light, seen from above."""
    from pxr import Gf, Usd, UsdGeom

    from usdfiber import authoring as A

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    c = UsdGeom.BasisCurves.Define(stage, "/Cloth/Patch")
    A.apply_fiber(c.GetPrim(), "polyester", diameter=D * 1000.0, dye="disperseBlue", depth_of_shade=0.5)
    n = int(round(tau / (D * THICK) * SIZE * THICK))
    rng = np.random.default_rng(seed)
    y = rng.uniform(-SIZE / 2, SIZE / 2, n)
    z = rng.uniform(-THICK / 2, THICK / 2, n)
    L = 1.6 * SIZE
    pts = []
    for yy, zz in zip(y, z):
        pts += [Gf.Vec3f(-L / 2, yy, zz), Gf.Vec3f(L / 2, yy, zz)]
    c.CreateTypeAttr("linear")
    c.CreatePointsAttr(pts)
    c.CreateCurveVertexCountsAttr([2] * n)
    c.CreateWidthsAttr([D])
    c.SetWidthsInterpolation("constant")
    # The patch's central 0.8 mm fill the view.
    add_lit_card(stage, half_width=2 * SIZE, card_z=-3 * THICK, camera_z=0.8 * SIZE * 50.0 / 36.0)
    return stage


def render(stage, cache_dir, cloth: str, spp: int, seed: int, voxels_per_pixel: float = 1.0,
           voxel_size: float | None = None):
    from usdfiber.translators.mitsuba.scene import SceneOptions, translate_stage

    bake = BakeSettings(resolution_deg=15, photons=3000, batches=2)
    tr = translate_stage(stage, SceneOptions(resolution=(RES, RES), spp=1, bake=bake, cache=TableCache(cache_dir),
                                             cloth=cloth, voxels_per_pixel=voxels_per_pixel, voxel_size=voxel_size))
    img = np.array(mi.render(tr.scene, spp=spp, seed=seed), np.float64)[..., :3]
    return img, tr


def test_volume_mode_reports_and_builds_one_grid(tmp_path):
    stage = fiber_patch(1.0)
    img, tr = render(stage, tmp_path, "volume", spp=4, seed=1)
    assert any(w.startswith("cloth: /Cloth/Patch: volume") for w in tr.warnings), tr.warnings
    assert tr.counts["volumes"] == 1 and tr.counts["voxels_occupied"] > 0
    assert np.all(np.isfinite(img)) and img.mean() > 0
    _, tr2 = render(stage, tmp_path, "auto", spp=1, seed=1)
    assert any(w.startswith("cloth: /Cloth/Patch: curves") for w in tr2.warnings), tr2.warnings


def test_near_plane_inside_the_volume_is_reported():
    """The camera's near plane (USD's default, 1 mm, here 1.11 mm above the patch) cutting a
    volume's box is reported with the prim; a box below it is not."""
    from pxr import Usd

    from usdfiber.translators.mitsuba.lod import camera_view
    from usdfiber.translators.mitsuba.volume.scene import near_plane_warning

    stage = fiber_patch(0.5)
    view = camera_view(stage.GetPrimAtPath("/Cam"), Usd.TimeCode.Default(), RES, RES)
    lo = np.array([-0.8, -0.5, -0.05])
    assert near_plane_warning(view, "/Cloth/Patch", lo, np.array([0.8, 0.5, 0.05])) is None
    msg = near_plane_warning(view, "/Cloth/Patch", lo, np.array([0.8, 0.5, 0.2]))
    assert msg is not None and msg.startswith("/Cloth/Patch: the camera's near clipping plane (1 units)")
    assert "\n" not in msg


@pytest.mark.slow
@pytest.mark.parametrize("tau", [0.5, 2.0])
def test_volume_agrees_with_explicit_fibers_in_the_mean(tmp_path, tau):
    """Image means of curves and volume agree within 4 % for voxels of 2.5 to 20 fiber
    diameters (the patch's whole thickness), and for voxels of two pixel footprints (which
    once made a padded box reach past the camera's near plane: +47 %).

    Measured (2-core Intel Xeon 2.8 GHz, load average ~10 from other work, 128 spp, this test, volume over curves): tau 0.5: +2.3, +2.1,
    +1.3, +2.1 % for w / D = 2.5, 5, 10, 20, +1.3 % at two footprints; tau 2: +2.6, +0.4, +0.2,
    +2.2 %, +0.04 %. The difference does not shrink
    with finer voxels: its voxel-size dependence has two parts of opposite trend, the count
    noise (:func:`usdfiber.geometry.voxelize.count_noise_deficit`: the optical depth short by
    ~D / 2w, 18 % at w = 2.5 D, 2.5 % at 20 D, tested exactly in test_volume_voxelize) that
    grows as voxels approach the fiber, and the blur of the cloth's boundary that grows with
    the voxel; in the image they partly cancel (a thinner cloth shows more of the card and
    reflects less). Denser cloth (tau 2) is not worse than sparse. Noise: two seeds of the
    explicit render differ by < 0.1 % at this spp, far below the bound."""
    stage = fiber_patch(tau)
    ref, _ = render(stage, tmp_path, "fibers", spp=128, seed=2)
    means = {}
    for k in (2.5, 5.0, 10.0, 20.0):
        img, _ = render(stage, tmp_path, "volume", spp=128, seed=3, voxel_size=k * D)
        means[f"w={k}D"] = img.mean() / ref.mean() - 1.0
    img, _ = render(stage, tmp_path, "volume", spp=128, seed=3, voxels_per_pixel=0.5)
    means["2 footprints"] = img.mean() / ref.mean() - 1.0
    print(f"tau {tau}: relative mean difference {means}")
    assert all(abs(v) < 0.04 for v in means.values()), means
