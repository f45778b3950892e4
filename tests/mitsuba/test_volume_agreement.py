"""A patch of parallel fibers rendered as curves and as a volume (``--cloth volume``) agrees in the
mean; the render mode's choice per prim is reported."""
from __future__ import annotations

import math

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
#: Volume vs explicit fibers once the count deficit is accounted for (relative image mean), per
#: optical depth: measured residual 0.2 % at tau 0.5, 4.5 % at tau 2 (dense cloth's shadowing).
A_BOUND = {0.5: 0.02, 2.0: 0.06}


def fiber_patch(tau: float, seed: int = 3, card: float = 0.5, keep: float = 1.0):
    """Straight polyester fibers along x at uniformly random (y, z) in a SIZE x THICK cross
    section: optical thickness ``tau`` across the patch (n D THICK, n fibers per mm^2), over a
    card of reflectance ``card``, under a dome and a key light, seen from above. ``keep``: only
    the first fraction of the fibers (the same positions: optical thickness keep * tau)."""
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
    n = int(round(keep * n))
    pts = []
    for yy, zz in zip(y[:n], z[:n]):
        pts += [Gf.Vec3f(-L / 2, yy, zz), Gf.Vec3f(L / 2, yy, zz)]
    c.CreateTypeAttr("linear")
    c.CreatePointsAttr(pts)
    c.CreateCurveVertexCountsAttr([2] * n)
    c.CreateWidthsAttr([D])
    c.SetWidthsInterpolation("constant")
    # The patch's central 0.8 mm fill the view.
    add_lit_card(stage, half_width=2 * SIZE, card_z=-3 * THICK, camera_z=0.8 * SIZE * 50.0 / 36.0)
    UsdGeom.Mesh(stage.GetPrimAtPath("/Card")).CreateDisplayColorAttr([Gf.Vec3f(card, card, card)])
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
def test_volume_agrees_with_explicit_fibers_as_the_count_deficit_predicts(tmp_path, tau):
    """The volume's image mean against the explicit fibers', r(w) = I_vol / I_exp - 1, follows
    the count deficit: voxels of width w spread each fiber over their width, which shortens the
    optical depth tau by tau delta(D / w) (:func:`usdfiber.geometry.voxelize.count_noise_deficit`,
    ~D / 2w), so to first order

        r(w, tau) = -S tau delta(D / w) + e(tau),    |e(tau)| <= A_BOUND[tau],

    with S = d ln I / d tau the image's sensitivity to the optical depth, measured here on the
    explicit fibers themselves (the same patch with its first 80 % of fibers, rendered with the
    same seed: common random numbers). The card is dark (reflectance 0.02), so the image is the
    cloth's reflection and S is large at low density. Asserted at w = 5 and 10 fiber diameters:
    the voxel-size dependence r(5 D) - r(10 D) against the prediction within 1 % (at tau 0.5 the
    test must resolve it: a model without the deficit term fails), and each r within the
    prediction plus A_BOUND[tau].

    Measured (2-core Xeon 2.8 GHz, 64 spp, S from 90 % of the fibers; r, then -S tau delta):
    tau 0.5 (S 1.40): -6.8 / -6.6 % at 5 D, -3.5 / -3.4 % at 10 D; tau 2 (S 0.19): -8.1 / -3.6 %,
    -6.4 / -1.9 %: a residual e = -4.5 % at both sizes, which the deficit does not explain.
    This test (256 spp volumes, S from 80 %): tau 0.5: S 1.39, r(5 D) - r(10 D) -4.1 +- 0.3 %
    against -3.1 %; tau 2: S 0.22, -2.1 +- 0.2 % against -2.0 %, e -4.0 / -3.9 %.
    Outside the asserted range the first order fails: 2.5 D (deficit 18 % of tau) -8.9 / -12.3 %
    (tau 0.5), -12.0 / -6.8 % (tau 2); 20 D (one voxel as thick as the patch, its boundary
    blurred) -4.5 / -1.7 %, -3.9 / -1.0 %.

    Noise: a dark card's image mean is noisy (about 2 % at 64 spp: S read 1.01 with independent
    seeds; r(5 D) - r(10 D) had a standard error of 0.63 % at 64 spp, too much to resolve a
    3.1 % dependence at 4 of them, hence 256 spp for the volumes), so both differences are paired (the volumes share seeds, as do the full and the
    thinned patch: common random numbers), and each render is two halves with their own seeds,
    whose per-pixel differences estimate the noise of every mean and paired difference
    (1,024 pixels, no image structure in them); each bound is widened by 4 of those standard
    errors: false failure below 1e-4 per assertion."""
    from usdfiber.geometry.voxelize import count_noise_deficit

    keep = 0.8
    # The volumes' difference carries the noise that matters: 256 spp resolve it (0.3 %).
    spp = {"fibers": 64, "volume": 256}

    def halves(stage, cloth, seed, **kw):
        a, _ = render(stage, tmp_path, cloth, spp=spp[cloth] // 2, seed=seed, **kw)
        b, _ = render(stage, tmp_path, cloth, spp=spp[cloth] // 2, seed=seed + 1000, **kw)
        return a.mean(axis=2), b.mean(axis=2)

    def mean_se(x, y):
        """(mean, standard error) of the paired difference x - y of two renders' halves."""
        d_a, d_b = x[0] - y[0], x[1] - y[1]
        return 0.5 * float((d_a + d_b).mean()), float((d_a - d_b).std(ddof=1)) / (2 * math.sqrt(d_a.size))

    zero = (np.zeros((RES, RES)), np.zeros((RES, RES)))
    ref = halves(fiber_patch(tau, card=0.02), "fibers", 2)
    thin = halves(fiber_patch(tau, card=0.02, keep=keep), "fibers", 2)
    i_ref, _ = mean_se(ref, zero)
    i_thin, _ = mean_se(thin, zero)
    d, se_d = mean_se(ref, thin)
    sens, se_sens = math.log(i_ref / i_thin) / ((1.0 - keep) * tau), se_d / i_thin / ((1.0 - keep) * tau)
    delta = {k: float(count_noise_deficit(1.0 / k)) for k in (5.0, 10.0)}
    vol = {k: halves(fiber_patch(tau, card=0.02), "volume", 3, voxel_size=k * D) for k in delta}
    pred = {k: -sens * tau * delta[k] for k in delta}
    dv, se_dv = mean_se(vol[5.0], vol[10.0])
    diff, pred_diff = dv / i_ref, pred[5.0] - pred[10.0]
    se_diff = math.hypot(se_dv / i_ref, se_sens * tau * (delta[5.0] - delta[10.0]))
    print(f"tau {tau}: S {sens:.3f} +- {se_sens:.3f}; r(5 D) - r(10 D) {diff:.4f} +- {se_diff:.4f}, "
          f"predicted {pred_diff:.4f}")
    if tau <= 0.5:
        assert 0.01 + 4 * se_diff < abs(pred_diff), (pred_diff, se_diff)     # the test resolves the dependence
    assert abs(diff - pred_diff) <= 0.01 + 4 * se_diff, (diff, pred_diff, se_diff)
    for k in delta:
        dk, se_k = mean_se(vol[k], ref)
        se = math.hypot(se_k / i_ref, se_sens * tau * delta[k])
        print(f"  w = {k:g} D: r {dk / i_ref:.4f} +- {se:.4f}, predicted {pred[k]:.4f}")
        assert abs(dk / i_ref - pred[k]) <= A_BOUND[tau] + 4 * se, (k, dk / i_ref, pred[k], se)


@pytest.mark.slow
def test_volume_agrees_with_explicit_fibers_over_a_grey_card(tmp_path):
    """Over a grey card (0.5) the image is insensitive to the optical depth (the card shows
    where the cloth thins, about as bright as the cloth), and voxels of two pixel footprints
    (which once made a padded box reach past the camera's near plane: +47 %) agree with the
    explicit fibers within A_BOUND. Measured: +1.3 % (tau 0.5)."""
    stage = fiber_patch(0.5)
    ref, _ = render(stage, tmp_path, "fibers", spp=64, seed=2)
    img, _ = render(stage, tmp_path, "volume", spp=64, seed=3, voxels_per_pixel=0.5)
    assert abs(img.mean() / ref.mean() - 1.0) <= A_BOUND[0.5]
