"""`usdfiber render` end to end, and the stage translation around the fiber BSDF."""
from __future__ import annotations

import math

import numpy as np
import pytest

import usdfiber  # noqa: F401  (registers schemas first)
from pxr import Gf, Usd, UsdGeom, UsdLux, Vt

from usdfiber import authoring as A
from usdfiber.bake.settings import BakeSettings
from usdfiber.bake.cache import TableCache
from usdfiber.cli import main
from usdfiber.image_output import read_exr
from usdfiber.translators.mitsuba import lod
# Imported while the test session collects (another sys.stderr than any test's): a render's log
# must still reach the sys.stderr of its call.
from usdfiber.translators.mitsuba import render as _render  # noqa: F401
from usdfiber.translators.mitsuba.profile import STEPS, TranslationProfile
from usdfiber.translators.mitsuba.scene import SceneOptions, translate_stage
from usdfiber.translators.mitsuba.yarn_far_field import YarnBakeSettings
from usdfiber.spec.yarn import YarnParams
from stage_util import add_camera

FAST = ["--bake-resolution", "15", "--bake-photons", "4000"]
FAST_SETTINGS = BakeSettings(resolution_deg=15, photons=4000, batches=4)
# One fiber placement per far field: these tests are about the command and the level of detail, not
# the far field's average over placements (tests/mitsuba/test_far_field_realizations.py).
FAST_YARN_SETTINGS = YarnBakeSettings(30, photons=600, realizations=1)


@pytest.fixture(autouse=True)
def _cache(table_cache_dir, monkeypatch):
    # The run's shared cache (conftest.py): each distinct table is baked once.
    monkeypatch.setenv("USDFIBER_CACHE_DIR", str(table_cache_dir))
    return table_cache_dir


def _fibers(stage, path, dye, dos, z0, n=12, length=1.0, kind="polyester"):
    curves = UsdGeom.BasisCurves.Define(stage, path)
    curves.CreateTypeAttr("cubic")
    curves.CreateBasisAttr("bspline")
    pts = []
    for i in range(n):
        for j in range(6):
            x = -0.5 * length + length * j / 5
            pts.append(Gf.Vec3f(x, 0.02 + 0.005 * math.sin(3 * x + i), z0 + 0.025 * i))
    curves.CreatePointsAttr(Vt.Vec3fArray(pts))
    curves.CreateCurveVertexCountsAttr(Vt.IntArray([6] * n))
    curves.CreateWidthsAttr(Vt.FloatArray([0.02]))
    curves.SetWidthsInterpolation("constant")
    A.apply_fiber(curves.GetPrim(), kind, dye=dye, depth_of_shade=dos, diameter=20.0)
    return curves.GetPrim()


def _stage(tmp_path, *, camera=True, lights=True, name="s.usda"):
    stage = Usd.Stage.CreateNew(str(tmp_path / name))
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    UsdGeom.SetStageUpAxis(stage, "Y")
    _fibers(stage, "/W/Red", "disperseRed", 2.0, -0.35)
    _fibers(stage, "/W/Blue", "disperseBlue", 2.0, 0.05)
    if camera:
        cam = UsdGeom.Camera.Define(stage, "/W/Cam")
        cam.CreateFocalLengthAttr(50.0)
        cam.CreateHorizontalApertureAttr(36.0)
        cam.CreateVerticalApertureAttr(36.0)
        view = Gf.Matrix4d().SetLookAt(Gf.Vec3d(0, 1.5, 0.4), Gf.Vec3d(0, 0, 0), Gf.Vec3d(0, 0, -1))
        cam.AddTransformOp().Set(view.GetInverse())
    if lights:
        UsdLux.DomeLight.Define(stage, "/W/Sky").CreateIntensityAttr(1.0)
    stage.GetRootLayer().Save()
    return tmp_path / name


def test_render_writes_exr_and_png_with_metadata(tmp_path, capsys):
    src = _stage(tmp_path)
    out = tmp_path / "out.exr"
    rc = main(["render", str(src), "-o", str(out), "--resolution", "40x40", "--spp", "16",
               "--no-progress", *FAST])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert "time: validate" in cap.out and "render" in cap.out and "tables" in cap.out
    img, meta = read_exr(out)
    assert img.shape == (40, 40, 3) and np.all(np.isfinite(img))
    assert meta["usdfiber:camera"] == "/W/Cam"
    assert meta["usdfiber:spp"] == "16"
    assert meta["usdfiber:stage"].endswith("s.usda")
    assert int(meta["usdfiber:fiber_curves"]) == 24
    assert (tmp_path / "out.png").exists()
    # Camera looks down at the fibers (-z is image up): the red tuft is in the upper half.
    top, bottom = img[:20], img[20:]
    red_top = top[..., 0] - top[..., 2]
    blue_bottom = bottom[..., 2] - bottom[..., 0]
    assert red_top.max() > 0.05 and blue_bottom.max() > 0.05


def test_render_log_is_the_stderr_of_the_call(tmp_path, capsys, monkeypatch):
    """The bake estimates go to sys.stderr as it is at the call, not as it was when the module
    was imported (this file imports it while the session collects): an empty cache, so that
    there is a table to estimate."""
    monkeypatch.setenv("USDFIBER_CACHE_DIR", str(tmp_path / "cache"))
    src = _stage(tmp_path)
    rc = main(["render", str(src), "-o", str(tmp_path / "o.exr"), "--resolution", "8x8", "--spp", "1",
               "--no-progress", *FAST])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert "tables: to bake polyester" in cap.err, cap.err


def test_render_refuses_invalid_stage_with_check_messages(tmp_path, capsys):
    src = _stage(tmp_path)
    stage = Usd.Stage.Open(str(src))
    stage.GetPrimAtPath("/W/Red").GetAttribute("fiber:diameter").Set(-3.0)
    stage.Save()
    rc = main(["check", str(src)])
    check_out = capsys.readouterr().out
    rc = main(["render", str(src), "-o", str(tmp_path / "x.exr"), "--no-progress", *FAST])
    err = capsys.readouterr().err
    assert rc == 1
    assert "does not pass `usdfiber check`" in err
    line = next(l for l in check_out.splitlines() if "fiber:diameter" in l)
    assert line.strip() in err
    assert not (tmp_path / "x.exr").exists()


def test_render_unreadable_stage_is_a_usage_error(tmp_path, capsys):
    rc = main(["render", str(tmp_path / "missing.usda")])
    assert rc == 2
    assert "missing.usda" in capsys.readouterr().err


def test_render_no_bake_names_the_missing_table(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("USDFIBER_CACHE_DIR", str(tmp_path / "empty-cache"))
    src = _stage(tmp_path)
    rc = main(["render", str(src), "-o", str(tmp_path / "x.exr"), "--no-bake", "--no-progress", *FAST])
    err = capsys.readouterr().err
    assert rc == 1
    assert "/W/Red" in err and "usdfiber bake" in err


FAST_YARN = ["--yarn-bake-resolution", "30", "--yarn-bake-photons", "600"]


def test_yarn_level_approximation_renders_without_fibers(tmp_path, capsys):
    """yarn:expandFibers = false: each yarn curve is one curve with the yarn's far field."""
    src = _stage(tmp_path)
    stage = Usd.Stage.Open(str(src))
    A.apply_yarn(stage.GetPrimAtPath("/W/Blue"), "Skala 360", expand_fibers=False)
    stage.Save()
    rc = main(["render", str(src), "-o", str(tmp_path / "x.exr"), "--no-progress", "--resolution", "48x32",
               "--spp", "4", *FAST, *FAST_YARN])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "0 fibers expanded of 0 at full detail; with their far field: 12 in view" in out
    assert "far field /W/Blue: traced" in out
    img = read_exr(tmp_path / "x.exr")[0]
    assert np.isfinite(img).all() and img.max() > 0


def test_yarn_level_approximation_needs_baking_or_a_cached_far_field(tmp_path, capsys):
    src = _stage(tmp_path)
    stage = Usd.Stage.Open(str(src))
    A.apply_yarn(stage.GetPrimAtPath("/W/Blue"), "Skala 360", expand_fibers=False)
    stage.Save()
    rc = main(["render", str(src), "-o", str(tmp_path / "x.exr"), "--no-progress", "--no-bake",
               "--resolution", "16x16", "--spp", "1", *FAST, "--yarn-bake-resolution", "30",
               "--yarn-bake-photons", "601"])
    err = capsys.readouterr().err
    assert rc == 1 and "/W/Blue" in err and "far field" in err


def test_gpu_device_without_cuda_is_a_clear_error(tmp_path, capsys):
    pytest.importorskip("mitsuba")
    import drjit as dr

    if dr.has_backend(dr.JitBackend.CUDA):
        pytest.skip("a CUDA device is present")
    src = _stage(tmp_path)
    rc = main(["render", str(src), "-o", str(tmp_path / "x.exr"), "--device", "gpu", "--no-progress", *FAST])
    err = capsys.readouterr().err
    assert rc == 1 and "gpu" in err and "--device cpu" in err
    # The failed switch leaves the CPU variant usable.
    from usdfiber.backend import mitsuba

    assert mitsuba("llvm_ad_rgb").variant() == "llvm_ad_rgb"


def test_list_views(capsys):
    assert main(["render", "--list-views"]) == 0
    out = capsys.readouterr().out
    assert "sRGB - Display" in out and "ACES 2.0 - SDR 100 nits (Rec.709)" in out


def test_stage_without_camera_and_lights_renders_with_defaults(tmp_path, capsys):
    src = _stage(tmp_path, camera=False, lights=False)
    out = tmp_path / "d.exr"
    rc = main(["render", str(src), "-o", str(out), "--resolution", "32x18", "--spp", "4", "--no-png",
               "--no-progress", *FAST])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert "no camera" in cap.err and "no lights" in cap.err
    img, meta = read_exr(out)
    assert meta["usdfiber:camera"] == "default"
    assert img.max() > 0.0 and not (tmp_path / "d.png").exists()


# ---------------------------------------------------------------------------------------------
# Translation
# ---------------------------------------------------------------------------------------------

def test_prims_share_tables_and_colours(tmp_path):
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    _fibers(stage, "/A", "disperseRed", 1.0, 0.0)
    _fibers(stage, "/B", "disperseRed", 1.0, 0.5)     # same fiber, same colour: same slot
    _fibers(stage, "/C", "disperseRed", 3.0, 1.0)     # same fiber, deeper shade: own slot
    cache = TableCache()
    tr = translate_stage(stage, SceneOptions(resolution=(8, 8), spp=1, bake=FAST_SETTINGS, cache=cache))
    f = tr.fibers
    assert tr.counts["fiber_tables"] == 1 and len(f.bank.slots) == 2
    assert tr.counts["fiber_curves"] == 36
    # One shape and one BSDF for all fiber curves.
    assert sum(1 for s in tr.scene.shapes() if s.id() == "fibers") == 1
    seg_prim = f.geometry.segment_part
    slots_a = set(f.seg_slot[seg_prim == 0]); slots_b = set(f.seg_slot[seg_prim == 1]); slots_c = set(f.seg_slot[seg_prim == 2])
    assert slots_a == slots_b and slots_a.isdisjoint(slots_c)
    # The deeper shade absorbs more: a larger effective sigma_a in every channel.
    sa = np.array(f.bank.slots[next(iter(slots_a))].sigma_a)
    sc = np.array(f.bank.slots[next(iter(slots_c))].sigma_a)
    assert np.allclose(sc, 3.0 * sa)


def test_fiber_rotation_is_deterministic_and_per_prim():
    def psi(seed, path="/A", random=True):
        stage = Usd.Stage.CreateInMemory()
        UsdGeom.SetStageMetersPerUnit(stage, 0.001)
        prim = _fibers(stage, path, "disperseRed", 1.0, 0.0)
        A.apply_fiber(prim, None, seed=seed, random_rotation=random, rotation=30.0)
        tr = translate_stage(stage, SceneOptions(resolution=(8, 8), spp=1, bake=FAST_SETTINGS))
        return tr.fibers.seg_psi
    a, b = psi(1), psi(1)
    assert np.array_equal(a, b)
    assert not np.allclose(a, psi(2)) and not np.allclose(a, psi(1, "/Other"))
    fixed = psi(1, random=False)
    assert np.allclose(fixed, math.radians(30.0))
    # Random rotations cover the circle.
    assert np.ptp(a) > 3.0


def test_frame_selects_transforms_and_depth_of_shade_without_rebaking():
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    prim = _fibers(stage, "/A", "disperseRed", 1.0, 0.0)
    op = UsdGeom.Xformable(prim).AddTranslateOp()
    op.Set(Gf.Vec3d(0, 0, 0), 1.0)
    op.Set(Gf.Vec3d(2.0, 0, 0), 2.0)
    dos = prim.GetAttribute("fiber:dye:depthOfShade")
    dos.Set(0.5, 1.0)
    dos.Set(4.0, 2.0)
    cache = TableCache()
    tr1 = translate_stage(stage, SceneOptions(time=1.0, resolution=(8, 8), spp=1, bake=FAST_SETTINGS, cache=cache))
    tr2 = translate_stage(stage, SceneOptions(time=2.0, resolution=(8, 8), spp=1, bake=FAST_SETTINGS, cache=cache))
    g1, g2 = tr1.fibers.geometry, tr2.fibers.geometry
    assert np.allclose(g2.points - g1.points, [2.0, 0.0, 0.0])
    s1 = np.array(tr1.fibers.bank.slots[0].sigma_a)
    s2 = np.array(tr2.fibers.bank.slots[0].sigma_a)
    assert np.allclose(s2, 8.0 * s1)
    # Same geometry: the second frame reuses the baked table (no bake time spent tracing).
    assert tr1.fibers.tables[0].geometry_key == tr2.fibers.tables[0].geometry_key
    assert tr2.times["tables"] < 2.0


def _yarn_stage(cam_z: float):
    """Two CNe 50 yarns, one in front of a camera at distance cam_z, one just beside its view
    (0.6 mm, 2.5 of its diameters, from the frustum: kept as a far-field proxy, within
    lod.PROXY_MARGIN_DIAMETERS)."""
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    # The view is 0.36 cam_z wide each side of the axis at z = 0 (add_camera); the yarn reaches
    # 1 mm and its radius 0.12 mm from x0.
    for name, x0 in (("Seen", 0.0), ("Aside", 0.36 * cam_z + 1.0 + 0.12 + 0.6)):
        c = UsdGeom.BasisCurves.Define(stage, f"/Y/{name}")
        c.CreateTypeAttr("cubic")
        c.CreateBasisAttr("bspline")
        c.CreatePointsAttr([Gf.Vec3f(x0 + x, 0, 0) for x in (-1.0, -0.5, 0.0, 0.5, 1.0)])
        c.CreateCurveVertexCountsAttr([5])
        c.CreateWidthsAttr([0.2415])
        c.SetWidthsInterpolation("constant")
        A.apply_yarn(c.GetPrim(), "CNe 50", fiber_preset="polyester")
    add_camera(stage, cam_z)
    return stage


def test_yarns_expand_with_culling_and_level_of_detail():
    near = translate_stage(_yarn_stage(1.0), SceneOptions(resolution=(256, 256), spp=1, bake=FAST_SETTINGS,
                                                          yarn_bake=FAST_YARN_SETTINGS))
    c = near.counts
    assert c["yarn_yarns"] == 2 and c["yarn_culled"] == 1      # the yarn aside: no fibers,
    assert c["yarn_fibers"] == c["yarn_fibers_full"] >= 3 * 70   # close up: every fiber and flyaway
    assert c["yarn_far"] == 0
    assert near.fibers.curve_count == c["yarn_fibers"] + 1       # but a far-field proxy (shadows)
    # At 5 mm the yarn is 4.3 px wide: the middle step, fewer fibers (4 per pixel would be 17 of
    # 210), never fewer than lod.MIN_FIBER_FRACTION of them.
    mid = translate_stage(_yarn_stage(5.0), SceneOptions(resolution=(64, 64), spp=1, bake=FAST_SETTINGS,
                                                         yarn_bake=FAST_YARN_SETTINGS))
    cm = mid.counts
    assert cm["yarn_culled"] == 1 and cm["yarn_far"] == 0 and cm["yarn_fibers"] < cm["yarn_fibers_full"]
    assert cm["yarn_fibers"] / cm["yarn_fibers_full"] == pytest.approx(lod.MIN_FIBER_FRACTION, abs=0.02)
    # Within its tested bound (tests/mitsuba/test_lod_bound.py) the middle step does not warn.
    assert not any("level of detail" in w for w in mid.warnings + near.warnings)
    # Kept fibers are widened by fraction ** -WIDEN_EXPONENT (1: the yarn keeps its summed fiber width).
    f_near = near.fibers.geometry.radii.mean()
    f_mid = mid.fibers.geometry.radii.mean()
    widen = (cm["yarn_fibers_full"] / cm["yarn_fibers"]) ** lod.WIDEN_EXPONENT
    assert f_mid / f_near == pytest.approx(widen, rel=0.15)
    off = translate_stage(_yarn_stage(5.0), SceneOptions(resolution=(64, 64), spp=1, bake=FAST_SETTINGS,
                                                           yarn_bake=FAST_YARN_SETTINGS, lod_scale=0.0))
    assert off.counts["yarn_fibers"] == c["yarn_fibers"]


def test_level_of_detail_policy_and_profile_come_with_the_scene_options():
    """The options carry the level-of-detail policy (what benchmarks vary instead of the module's
    constants) and the profile that times the translation's steps."""
    prof = TranslationProfile()
    opts = dict(resolution=(64, 64), spp=1, bake=FAST_SETTINGS, yarn_bake=FAST_YARN_SETTINGS)
    mid = translate_stage(_yarn_stage(5.0), SceneOptions(**opts, lod=lod.LodPolicy(min_fiber_fraction=0.8),
                                                         profile=prof))
    cm = mid.counts
    assert cm["yarn_culled"] == 1 and cm["yarn_far"] == 0
    assert cm["yarn_fibers"] / cm["yarn_fibers_full"] == pytest.approx(0.8, abs=0.02)   # default: 0.5
    assert mid.profile is prof
    assert prof.calls["yarn_expansion"] == 2 and prof.calls["expand_yarn"] == 1     # the culled yarn: none
    assert prof.calls["bsdf"] == prof.calls["scene"] == prof.calls["fiber_bank"] == 1
    assert all(prof.seconds[k] >= 0 for k in prof.calls) and set(prof.calls) <= set(STEPS)
    # A policy whose far step reaches this 4.3 px yarn draws it with its far field.
    far = translate_stage(_yarn_stage(5.0), SceneOptions(**opts, lod=lod.LodPolicy(far_yarn_pixels=5.0)))
    assert far.counts["yarn_far"] == 1 and far.counts["yarn_fibers"] == 0
    assert "expand_yarn" not in far.profile.calls
    with pytest.raises(ValueError, match="min_fiber_fraction"):
        lod.LodPolicy(min_fiber_fraction=0.0)


def test_sub_pixel_yarns_use_their_far_field():
    """At 200 mm the yarn is 0.11 px wide: one curve of the far field's bounding width."""
    far = translate_stage(_yarn_stage(200.0), SceneOptions(resolution=(64, 64), spp=1, bake=FAST_SETTINGS,
                                                            yarn_bake=FAST_YARN_SETTINGS))
    c = far.counts
    assert c["yarn_far"] == 1 and c["yarn_fibers"] == 0 and c["yarn_culled"] == 1
    geom = far.fibers.geometry
    # Sub-pixel: the 2 mm yarn (2.25 mm per pixel here) needs no more than its two end points,
    # and so does the out-of-view proxy of the yarn aside.
    assert far.fibers.segment_count == 2
    ff = far.fibers.bank.slots[int(far.fibers.seg_slot[0])].table
    rb = ff.header["piece"]["bound_radius"]
    # The curve is the yarn's centre line widened to the fibers' bounding radius.
    assert geom.radii.max() == pytest.approx(0.2415 / 2 * rb / YarnParams.from_prim(
        _yarn_stage(1.0).GetPrimAtPath("/Y/Seen")).yarn_radius, rel=1e-6)
    assert 0.3 < float(ff.coverage.min()) <= float(ff.coverage.max()) <= 1.0


def test_check_warnings_are_reported_as_check_lines(tmp_path, capsys):
    src = _stage(tmp_path)
    stage = Usd.Stage.Open(str(src))
    stage.GetPrimAtPath("/W/Red").GetAttribute("fiber:dye:depthOfShade").Set(6.0)  # beyond the industry range
    stage.Save()
    rc = main(["render", str(src), "-o", str(tmp_path / "w.exr"), "--resolution", "8x8", "--spp", "1",
               "--no-png", "--no-progress", *FAST])
    err = capsys.readouterr().err
    assert rc == 0
    line = next(l for l in err.splitlines() if "fiber:dye:depthOfShade" in l)
    assert line.startswith("usdfiber: warning: /W/Red.fiber:dye:depthOfShade") and "Problem(" not in line
    rc = main(["render", str(src), "-o", str(tmp_path / "w.exr"), "--warnings-as-errors", "--no-progress", *FAST])
    assert rc == 1
