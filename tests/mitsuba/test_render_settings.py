"""UsdRender.Settings reading and stage bounds (usdfiber.translators.mitsuba.render_settings)."""
from __future__ import annotations

import numpy as np
import pytest

import usdfiber  # noqa: F401  (registers plugins before any stage is opened)
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdRender

from usdfiber.translators.mitsuba.errors import TranslationError
from usdfiber.translators.mitsuba.render_settings import (
    SPP_ATTR,
    read_render_settings,
    stage_bbox,
    to_mi_transform,
)


def _settings_stage():
    st = Usd.Stage.CreateInMemory()
    UsdGeom.Camera.Define(st, "/cams/main")
    UsdGeom.Camera.Define(st, "/cams/alt")
    rs = UsdRender.Settings.Define(st, "/Render/Settings")
    rs.CreateResolutionAttr(Gf.Vec2i(320, 240))
    rs.CreateCameraRel().SetTargets(["/cams/main"])
    rs.CreatePixelAspectRatioAttr(1.0)
    rs.CreateAspectRatioConformPolicyAttr("cropAperture")
    rs.GetPrim().CreateAttribute(SPP_ATTR, Sdf.ValueTypeNames.Int).Set(64)
    return st, rs


def test_no_settings_gives_schema_fallbacks():
    st = Usd.Stage.CreateInMemory()
    info = read_render_settings(st)
    assert info.path is None and info.resolution == (2048, 1080) and info.camera is None
    assert info.samples_per_pixel is None and info.aspect_ratio_conform_policy == "expandAperture"


def test_explicit_path_and_stage_metadata():
    st, rs = _settings_stage()
    info = read_render_settings(st, "/Render/Settings")
    assert info.resolution == (320, 240)
    assert info.camera == Sdf.Path("/cams/main")
    assert info.samples_per_pixel == 64
    assert info.aspect_ratio_conform_policy == "cropAperture"
    assert read_render_settings(st).path is None            # no metadata yet
    st.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
    assert read_render_settings(st).resolution == (320, 240)


def test_product_overrides_settings():
    st, rs = _settings_stage()
    prod = UsdRender.Product.Define(st, "/Render/Products/beauty")
    prod.CreateResolutionAttr(Gf.Vec2i(64, 32))
    prod.CreateCameraRel().SetTargets(["/cams/alt"])
    prod.GetPrim().CreateAttribute(SPP_ATTR, Sdf.ValueTypeNames.Int).Set(8)
    rs.CreateProductsRel().SetTargets([prod.GetPath()])
    info = read_render_settings(st, rs.GetPath())
    assert info.product == prod.GetPath()
    assert (info.resolution, info.camera, info.samples_per_pixel) == ((64, 32), Sdf.Path("/cams/alt"), 8)
    assert info.aspect_ratio_conform_policy == "cropAperture"   # not authored on the product


def test_bad_settings_raise_naming_prim_and_attribute():
    st, rs = _settings_stage()
    with pytest.raises(TranslationError, match="/cams/main"):
        read_render_settings(st, "/cams/main")
    rs.GetPrim().GetAttribute(SPP_ATTR).Set(0)
    with pytest.raises(TranslationError, match=rf"/Render/Settings\.{SPP_ATTR}"):
        read_render_settings(st, rs.GetPath())
    rs.GetPrim().GetAttribute(SPP_ATTR).Set(16)
    rs.GetResolutionAttr().Set(Gf.Vec2i(0, 10))
    with pytest.raises(TranslationError, match=r"/Render/Settings\.resolution"):
        read_render_settings(st, rs.GetPath())


def test_stage_bbox_visible_geometry_only():
    st = Usd.Stage.CreateInMemory()
    cube = UsdGeom.Cube.Define(st, "/world/cube")                 # [-1, 1]^3, extent computed
    UsdGeom.Xformable(cube).AddTranslateOp().Set(Gf.Vec3d(10, 0, 0))
    mesh = UsdGeom.Mesh.Define(st, "/world/mesh")                  # no extent authored
    mesh.CreatePointsAttr([(0, 0, 0), (1, 2, 3), (-2, 0, 0)])
    mesh.CreateFaceVertexCountsAttr([3])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2])
    hidden = UsdGeom.Sphere.Define(st, "/world/hidden")
    hidden.CreateRadiusAttr(100.0)
    hidden.CreateVisibilityAttr(UsdGeom.Tokens.invisible)
    guide = UsdGeom.Sphere.Define(st, "/world/guide")
    guide.CreateRadiusAttr(50.0)
    guide.CreatePurposeAttr(UsdGeom.Tokens.guide)
    light = UsdLux.RectLight.Define(st, "/world/light")            # boundable, but not geometry
    light.CreateWidthAttr(500.0)
    lo, hi = stage_bbox(st, Usd.TimeCode.Default(), ("default", "render"))
    assert np.allclose(lo, [-2, -1, -1]) and np.allclose(hi, [11, 2, 3])
    lo, hi = stage_bbox(st, 0, ("default", "render", "guide"))
    assert np.allclose(lo, [-50, -50, -50])
    assert stage_bbox(Usd.Stage.CreateInMemory(), 0) is None


def test_to_mi_transform_transposes():
    m = np.eye(4)
    m[3, :3] = (1, 2, 3)                                             # USD: translation in the last row
    t = to_mi_transform(m)
    from usdfiber.backend import mitsuba

    mi = mitsuba()
    p = np.array(t @ mi.ScalarPoint3f(0, 0, 0))
    assert np.allclose(p, [1, 2, 3])
