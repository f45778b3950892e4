"""`usdfiber check` and the renderer agree on what is not a fiber: render settings, cameras,
lights, meshes, point instancers, attributes authored with the wrong type or token.

A valid base stage (plain curves, a camera, two lights, a mesh with a UsdPreviewSurface, a
point instancer, render settings) is broken one value at a time. For every case, `check`
reports an error naming the prim and attribute, the translation refuses the stage in one line,
and the two agree: the render refuses (its own check, which leaves the renderer's checks to the
translation, or the translation) exactly when `check` reports an error.
"""
from __future__ import annotations

import warnings
from pathlib import Path
from typing import Callable

import pytest

import usdfiber  # noqa: F401  (registers the schemas before any stage exists)
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdRender, UsdShade, Vt

from usdfiber.translators.mitsuba.errors import TranslateError
from usdfiber.translators.mitsuba.scene import SceneOptions, translate_stage
from usdfiber.validation.runner import check_stage

NAN, INF = float("nan"), float("inf")


def _line(stage: Usd.Stage, path: str, y: float, width: float) -> UsdGeom.BasisCurves:
    """One linear curve from x = -1 to 1 at height ``y``, of constant ``width``."""
    c = UsdGeom.BasisCurves.Define(stage, path)
    c.CreateTypeAttr("linear")
    c.CreateCurveVertexCountsAttr(Vt.IntArray([2]))
    c.CreatePointsAttr(Vt.Vec3fArray([Gf.Vec3f(-1, y, 0), Gf.Vec3f(1, y, 0)]))
    c.CreateWidthsAttr(Vt.FloatArray([width]))
    c.SetWidthsInterpolation("constant")
    return c


def _base(path: Path) -> Usd.Stage:
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, "Y")
    UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(stage.GetPrimAtPath("/World"))
    _line(stage, "/World/Curves", 0.0, 0.05)
    cam = UsdGeom.Camera.Define(stage, "/World/Cam")
    cam.CreateFocalLengthAttr(50.0)
    cam.CreateHorizontalApertureAttr(36.0)
    cam.CreateVerticalApertureAttr(24.0)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.1, 100.0))
    cam.AddTranslateOp().Set(Gf.Vec3d(0, 0, 6))
    key = UsdLux.DistantLight.Define(stage, "/World/Key")
    key.CreateIntensityAttr(2.0)
    UsdLux.RectLight.Define(stage, "/World/Fill").CreateWidthAttr(1.0)
    UsdGeom.Xformable(stage.GetPrimAtPath("/World/Fill")).AddTranslateOp().Set(Gf.Vec3d(0, 3, 0))
    mesh = UsdGeom.Mesh.Define(stage, "/World/Card")
    mesh.CreatePointsAttr(Vt.Vec3fArray([Gf.Vec3f(-2, -1, -1), Gf.Vec3f(2, -1, -1), Gf.Vec3f(2, 1, -1),
                                         Gf.Vec3f(-2, 1, -1)]))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([4]))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray([0, 1, 2, 3]))
    mesh.CreateSubdivisionSchemeAttr("none")
    mat = UsdShade.Material.Define(stage, "/World/Looks/Grey")
    sh = UsdShade.Shader.Define(stage, "/World/Looks/Grey/Surface")
    sh.CreateIdAttr("UsdPreviewSurface")
    sh.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0.5, 0.5, 0.5))
    mat.CreateSurfaceOutput().ConnectToSource(sh.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(mat)
    pi = UsdGeom.PointInstancer.Define(stage, "/World/Scatter")
    proto = UsdGeom.Mesh.Define(stage, "/World/Scatter/Protos/Tri")
    proto.CreatePointsAttr(Vt.Vec3fArray([Gf.Vec3f(0, 0, 0), Gf.Vec3f(0.1, 0, 0), Gf.Vec3f(0, 0.1, 0)]))
    proto.CreateFaceVertexCountsAttr(Vt.IntArray([3]))
    proto.CreateFaceVertexIndicesAttr(Vt.IntArray([0, 1, 2]))
    pi.CreatePrototypesRel().SetTargets([proto.GetPath()])
    pi.CreateProtoIndicesAttr(Vt.IntArray([0, 0]))
    pi.CreatePositionsAttr(Vt.Vec3fArray([Gf.Vec3f(0, 0.5, 0), Gf.Vec3f(0.5, 0.5, 0)]))
    rs = UsdRender.Settings.Define(stage, "/Render/Settings")
    rs.CreateResolutionAttr(Gf.Vec2i(16, 12))
    rs.CreateCameraRel().SetTargets([cam.GetPath()])
    rs.GetPrim().CreateAttribute("usdfiber:samplesPerPixel", Sdf.ValueTypeNames.Int).Set(1)
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
    return stage


def _attr(path: str, name: str, type_name: Sdf.ValueTypeName, value) -> Callable[[Usd.Stage], None]:
    """Author ``name`` on ``path`` as ``type_name`` in the root layer (any type: USD's API would
    refuse a type other than the schema's, a file need not)."""
    def edit(stage: Usd.Stage) -> None:
        prim_spec = stage.GetRootLayer().GetPrimAtPath(path)
        if name in prim_spec.properties:
            prim_spec.RemoveProperty(prim_spec.properties[name])
        spec = Sdf.AttributeSpec(prim_spec, name, type_name)
        spec.default = value
    return edit


def _shader_input(name: str, type_name: Sdf.ValueTypeName, value) -> Callable[[Usd.Stage], None]:
    def edit(stage: Usd.Stage) -> None:
        UsdShade.Shader(stage.GetPrimAtPath("/World/Looks/Grey/Surface")).CreateInput(name, type_name).Set(value)
    return edit


def _nan_translate(path: str) -> Callable[[Usd.Stage], None]:
    def edit(stage: Usd.Stage) -> None:
        UsdGeom.Xformable(stage.GetPrimAtPath(path)).AddTranslateOp(opSuffix="bad").Set(Gf.Vec3d(NAN, 0, 0))
    return edit


def _settings_camera_to_mesh(stage: Usd.Stage) -> None:
    UsdRender.Settings(stage.GetPrimAtPath("/Render/Settings")).GetCameraRel().SetTargets([Sdf.Path("/World/Card")])


def _settings_path_missing(stage: Usd.Stage) -> None:
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Nope")


F, F2, F4, I, I2 = (Sdf.ValueTypeNames.Float, Sdf.ValueTypeNames.Float2, Sdf.ValueTypeNames.Float4,
                    Sdf.ValueTypeNames.Int, Sdf.ValueTypeNames.Int2)
C3, TOK = Sdf.ValueTypeNames.Color3f, Sdf.ValueTypeNames.Token

#: (name, edit, expected code, prim, attribute)
CASES = [
    ("camera-focal-zero", _attr("/World/Cam", "focalLength", F, 0.0), "CameraInvalid", "/World/Cam", "focalLength"),
    ("camera-focal-nan", _attr("/World/Cam", "focalLength", F, NAN), "CameraInvalid", "/World/Cam", "focalLength"),
    ("camera-aperture-180-degrees", _attr("/World/Cam", "horizontalAperture", F, 1e30), "CameraInvalid", "/World/Cam",
     "horizontalAperture"),
    ("camera-vaperture-zero", _attr("/World/Cam", "verticalAperture", F, 0.0), "CameraInvalid", "/World/Cam",
     "verticalAperture"),
    ("camera-clip-reversed", _attr("/World/Cam", "clippingRange", F2, Gf.Vec2f(10, 1)), "CameraInvalid",
     "/World/Cam", "clippingRange"),
    ("camera-clip-infinite", _attr("/World/Cam", "clippingRange", F2, Gf.Vec2f(0.1, INF)), "CameraInvalid",
     "/World/Cam", "clippingRange"),
    ("camera-clip-float4", _attr("/World/Cam", "clippingRange", F4, Gf.Vec4f(0.1, 100, 1, 1)),
     "AttributeTypeMismatch", "/World/Cam", "clippingRange"),
    ("camera-translate-nan", _nan_translate("/World/Cam"), "CameraInvalid", "/World/Cam", "xformOpOrder"),
    ("light-intensity-nan", _attr("/World/Key", "inputs:intensity", F, NAN), "LightInvalid", "/World/Key",
     "inputs:intensity"),
    ("light-intensity-inf", _attr("/World/Key", "inputs:intensity", F, INF), "LightInvalid", "/World/Key",
     "inputs:intensity"),
    ("light-exposure-huge", _attr("/World/Key", "inputs:exposure", F, 1e30), "LightInvalid", "/World/Key",
     "inputs:exposure"),
    ("light-color-nan", _attr("/World/Key", "inputs:color", C3, Gf.Vec3f(NAN, 1, 1)), "LightInvalid",
     "/World/Key", "inputs:color"),
    ("light-rect-huge", _attr("/World/Fill", "inputs:width", F, 1e30), "LightInvalid", "/World/Fill", "inputs:width"),
    ("light-rect-inf", _attr("/World/Fill", "inputs:height", F, INF), "LightInvalid", "/World/Fill", "inputs:height"),
    ("light-rect-zero", _attr("/World/Fill", "inputs:width", F, 0.0), "LightInvalid", "/World/Fill",
     "inputs:width"),
    ("mesh-index-out-of-range", _attr("/World/Card", "faceVertexIndices", Sdf.ValueTypeNames.IntArray,
                                      Vt.IntArray([0, 1, 2, 9])), "MeshInvalid", "/World/Card", "faceVertexIndices"),
    ("mesh-point-huge", _attr("/World/Card", "points", Sdf.ValueTypeNames.Point3fArray,
                              Vt.Vec3fArray([Gf.Vec3f(-2, -1, -1), Gf.Vec3f(2, -1, -1), Gf.Vec3f(2, 1e30, -1),
                                             Gf.Vec3f(-2, 1, -1)])), "MeshInvalid", "/World/Card", "points"),
    ("camera-translate-huge", _attr("/World/Cam", "xformOp:translate", Sdf.ValueTypeNames.Double3,
                                    Gf.Vec3d(0, 0, 1e30)), "CameraInvalid", "/World/Cam", "xformOpOrder"),
    ("mesh-point-nan", _attr("/World/Card", "points", Sdf.ValueTypeNames.Point3fArray,
                             Vt.Vec3fArray([Gf.Vec3f(NAN, 0, 0)] * 4)), "MeshInvalid", "/World/Card", "points"),
    ("material-diffuse-nan", _shader_input("diffuseColor", C3, Gf.Vec3f(NAN, 0.5, 0.5)), "MeshInvalid",
     "/World/Looks/Grey/Surface", "inputs:diffuseColor"),
    ("material-emission-inf", _shader_input("emissiveColor", C3, Gf.Vec3f(INF, 1, 1)), "MeshInvalid",
     "/World/Looks/Grey/Surface", "inputs:emissiveColor"),
    ("settings-resolution-zero", _attr("/Render/Settings", "resolution", I2, Gf.Vec2i(0, 12)),
     "RenderSettingsInvalid", "/Render/Settings", "resolution"),
    ("settings-resolution-huge", _attr("/Render/Settings", "resolution", I2, Gf.Vec2i(2_000_000_000, 2_000_000_000)),
     "RenderSettingsInvalid", "/Render/Settings", "resolution"),
    ("settings-spp-huge", _attr("/Render/Settings", "usdfiber:samplesPerPixel", I, 2_147_483_647),
     "RenderSettingsInvalid", "/Render/Settings", "usdfiber:samplesPerPixel"),
    ("settings-camera-not-a-camera", _settings_camera_to_mesh, "RenderSettingsInvalid", "/Render/Settings",
     "camera"),
    ("settings-path-missing", _settings_path_missing, "RenderSettingsInvalid", "/Render/Nope", None),
    ("instancer-index-out-of-range", _attr("/World/Scatter", "protoIndices", Sdf.ValueTypeNames.IntArray,
                                           Vt.IntArray([0, 3])), "PlacementInvalid", "/World/Scatter", None),
    ("instancer-position-nan", _attr("/World/Scatter", "positions", Sdf.ValueTypeNames.Point3fArray,
                                     Vt.Vec3fArray([Gf.Vec3f(0, 0, 0), Gf.Vec3f(NAN, 0, 0)])),
     "PlacementInvalid", "/World/Scatter", None),
    ("instancer-position-huge", _attr("/World/Scatter", "positions", Sdf.ValueTypeNames.Point3fArray,
                                      Vt.Vec3fArray([Gf.Vec3f(0, 0, 0), Gf.Vec3f(0, -1e30, 0)])),
     "PlacementInvalid", "/World/Scatter", None),
    ("curves-widths-scalar", _attr("/World/Curves", "widths", F, 0.05), "AttributeTypeMismatch", "/World/Curves",
     "widths"),
    ("curves-purpose-bogus", _attr("/World/Curves", "purpose", TOK, "bogus"), "AttributeTokenNotAllowed",
     "/World/Curves", "purpose"),
]


def _options() -> SceneOptions:
    return SceneOptions(resolution=(16, 12), spp=1)


def _render_refuses(stage: Usd.Stage) -> str | None:
    """The render's refusal (one line), or None: its own check, then the translation."""
    report = check_stage(stage, bridges=False)
    if report.errors:
        return report.errors[0].message
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            translate_stage(stage, _options())
    except (TranslateError, ValueError) as exc:
        return str(exc)
    return None


def test_base_stage_passes_check_and_translates(tmp_path):
    stage = _base(tmp_path / "base.usda")
    assert check_stage(stage).errors == []
    assert _render_refuses(stage) is None


@pytest.mark.parametrize("name, edit, code, prim, attribute", CASES, ids=[c[0] for c in CASES])
def test_check_reports_what_render_refuses(tmp_path, name, edit, code, prim, attribute):
    stage = _base(tmp_path / f"{name}.usda")
    edit(stage)
    found = {(p.code, p.prim, p.attribute) for p in check_stage(stage).errors}
    assert (code, prim, attribute) in found, found
    refusal = _render_refuses(stage)
    assert refusal is not None and "\n" not in refusal and "Traceback" not in refusal
    assert prim.split("/")[-1] in refusal or code in ("AttributeTypeMismatch", "AttributeTokenNotAllowed")


@pytest.mark.parametrize("fiber", [True, False], ids=["fiber", "plain"])
def test_curves_an_instancer_scales_beyond_float32(tmp_path, fiber):
    """The curves' own check sees the prototype, not the instance a PointInstancer scales by 1e20:
    check reports what the render does (fiber curves refuse it, plain ones are skipped)."""
    stage = _base(tmp_path / "scaled.usda")
    proto = _line(stage, "/World/Scatter/Protos/Hair", 0.0, 0.01)
    if fiber:
        proto.GetPrim().ApplyAPI("FiberAPI")
        proto.GetWidthsAttr().Set(Vt.FloatArray([0.0]))  # a width of 0 is fine at any scale
    pi = UsdGeom.PointInstancer(stage.GetPrimAtPath("/World/Scatter"))
    pi.GetPrototypesRel().AddTarget(proto.GetPath())
    pi.CreateProtoIndicesAttr(Vt.IntArray([0, 1, 1]))
    pi.CreatePositionsAttr(Vt.Vec3fArray([Gf.Vec3f(0, 0.5, 0), Gf.Vec3f(0, 0.2, 0), Gf.Vec3f(0, 0.3, 0)]))
    pi.CreateScalesAttr(Vt.Vec3fArray([Gf.Vec3f(1, 1, 1), Gf.Vec3f(1, 1, 1), Gf.Vec3f(1e20, 1e20, 1e20)]))
    report = check_stage(stage)
    found = [p for p in report.problems if p.prim == "/World/Scatter"]
    assert [(p.code, p.severity.value) for p in found] == (
        [("PlacementInvalid", "error")] if fiber else [("PlainCurvesSkipped", "warning")]), report.problems
    assert "/World/Scatter[2]/World/Scatter/Protos/Hair: in world space" in found[0].message
    assert "magnitude 1e+18 or more" in found[0].message
    refusal = _render_refuses(stage)
    if fiber:
        assert refusal is not None and "/World/Scatter/Protos/Hair" in refusal and "1e+18" in refusal
    else:
        assert refusal is None
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            tr = translate_stage(stage, _options())
        assert any("Hair" in w and "skipped" in w and "1e+18" in w for w in tr.warnings), tr.warnings


def test_a_light_the_render_leaves_out_is_a_check_warning(tmp_path):
    """A negative intensity, a light type without a Mitsuba emitter: the render skips the light
    with a warning (and may fall back to its default rig); check warns the same."""
    stage = _base(tmp_path / "skipped.usda")
    stage.GetPrimAtPath("/World/Key").GetAttribute("inputs:intensity").Set(-2.0)
    UsdLux.CylinderLight.Define(stage, "/World/Tube")
    found = {(p.code, p.prim, p.attribute, p.severity.value) for p in check_stage(stage).problems}
    assert ("LightSkipped", "/World/Key", "inputs:intensity", "warning") in found, found
    assert ("LightSkipped", "/World/Tube", None, "warning") in found, found
    assert _render_refuses(stage) is None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tr = translate_stage(stage, _options())
    assert any(w.startswith("/World/Key.inputs:intensity: negative intensity") for w in tr.warnings)
    assert any(w.startswith("/World/Tube: ") and "skipped" in w for w in tr.warnings), tr.warnings


def test_a_light_broken_at_one_time_sample(tmp_path):
    """Without --time, check looks at every sample of a light or camera; with one, at that time,
    as a render of that frame does."""
    stage = _base(tmp_path / "timed.usda")
    attr = stage.GetPrimAtPath("/World/Key").GetAttribute("inputs:intensity")
    attr.Set(2.0, 1.0)
    attr.Set(NAN, 2.0)
    errors = check_stage(stage).errors
    assert [(p.code, p.time) for p in errors] == [("LightInvalid", 2.0)]
    assert check_stage(stage, time=1.0).errors == []
    assert check_stage(stage, time=2.0).errors != []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        translate_stage(stage, SceneOptions(resolution=(16, 12), spp=1, time=1.0))
        with pytest.raises(TranslateError, match=r"/World/Key.inputs:intensity: must be finite"):
            translate_stage(stage, SceneOptions(resolution=(16, 12), spp=1, time=2.0))


def test_a_zero_sized_yarn_is_left_out_with_a_warning(tmp_path):
    """A yarn of width 0 (allowed, as a fiber of width 0 is) has no fibers to draw: the render
    leaves it out with a warning (it divided by zero)."""
    from usdfiber import authoring
    from usdfiber.bake.cache import TableCache
    from usdfiber.bake.settings import BakeSettings

    stage = _base(tmp_path / "yarn.usda")
    y = _line(stage, "/World/Yarn", 0.2, 0.0)
    authoring.apply_yarn(y.GetPrim(), fiber_preset="polyester")
    assert check_stage(stage).errors == []
    opts = SceneOptions(resolution=(16, 12), spp=1, cache=TableCache(tmp_path / "tables"),
                        bake=BakeSettings(resolution_deg=30, photons=200, batches=2))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tr = translate_stage(stage, opts)
    assert any("/World/Yarn: 1 yarn curve(s) of zero width or length not drawn" in w for w in tr.warnings), tr.warnings


def test_a_renderer_that_cannot_run_is_a_one_line_warning(tmp_path, monkeypatch):
    """Checking works where the renderer does not (no LLVM for Mitsuba, say): the bridge's
    checks are skipped with a warning that says why, not a traceback."""
    from usdfiber.translators.mitsuba import preflight

    def broken(stage, time=None):
        raise RuntimeError("Mitsuba's LLVM variant needs libLLVM >= 16\nsecond line")

    monkeypatch.setattr(preflight, "stage_problems", broken)
    report = check_stage(_base(tmp_path / "s.usda"))
    assert report.errors == []
    [w] = [p for p in report.warnings if p.code == "RendererCheckSkipped"]
    assert "needs libLLVM" in w.message and "\n" not in w.message


def test_a_scene_mitsuba_refuses_is_a_one_line_refusal(tmp_path, monkeypatch):
    """A value the translation's checks let through and Mitsuba refuses when it builds the scene
    (as a field of view of 180 degrees did) is a one-line refusal, not a traceback."""
    from usdfiber.backend import mitsuba

    mi = mitsuba()
    load = mi.load_dict

    def refuse(entries, *args, **kwargs):
        if "sensor" not in entries:  # shapes and emitters are loaded one by one before the scene
            return load(entries, *args, **kwargs)
        raise RuntimeError('[parser.cpp:1718] At dictionary node "sensor": failed\n  more detail')

    monkeypatch.setattr(mi, "load_dict", refuse)
    with warnings.catch_warnings(), pytest.raises(TranslateError) as e:
        warnings.simplefilter("ignore")
        translate_stage(_base(tmp_path / "s.usda"), _options())
    assert str(e.value).startswith("Mitsuba could not build the scene: [parser.cpp:1718]") and "\n" not in str(e.value)
