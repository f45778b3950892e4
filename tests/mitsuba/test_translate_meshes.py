"""UsdGeom.Mesh + UsdPreviewSurface -> Mitsuba meshes (usdfiber.translators.mitsuba.meshes)."""
from __future__ import annotations

import numpy as np
import pytest

import usdfiber  # noqa: F401  (registers plugins before any stage is opened)
from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade

from usdfiber.backend import mitsuba
from usdfiber.translators.mitsuba.meshes import material_bsdf, mesh_shape, mesh_shapes
from usdfiber.translators.mitsuba.errors import TranslationError

mi = mitsuba()
I4 = np.eye(4)


def _stage() -> Usd.Stage:
    return Usd.Stage.CreateInMemory()


def _mesh(stage, path="/m", points=None, counts=None, indices=None, scheme="none", **kw):
    m = UsdGeom.Mesh.Define(stage, path)
    m.CreatePointsAttr(points if points is not None else [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)])
    m.CreateFaceVertexCountsAttr(counts if counts is not None else [4])
    m.CreateFaceVertexIndicesAttr(indices if indices is not None else [0, 1, 2, 3])
    m.CreateSubdivisionSchemeAttr(scheme)
    for k, v in kw.items():
        getattr(m, f"Create{k[0].upper()}{k[1:]}Attr")(v)
    return m


def _arrays(shape):
    p = mi.traverse(shape)
    v = np.array(p["vertex_positions"]).reshape(-1, 3)
    f = np.array(p["faces"]).reshape(-1, 3)
    n = np.array(p["vertex_normals"]).reshape(-1, 3) if shape.has_vertex_normals() else None
    uv = np.array(p["vertex_texcoords"]).reshape(-1, 2) if shape.has_vertex_texcoords() else None
    return v, f, n, uv


def _face_normals(v, f):
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


# ---- topology ---------------------------------------------------------------------------------

def test_fan_triangulation_counts_and_area():
    st = _stage()
    # a quad, a pentagon (regular-ish, convex) and a triangle
    pts = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0),
           (2, 0, 0), (3, 0, 0), (3.5, 0.5, 0), (3, 1, 0), (2, 1, 0),
           (4, 0, 0), (5, 0, 0), (4, 1, 0)]
    _mesh(st, points=pts, counts=[4, 5, 3], indices=list(range(12)))
    shape, warns = mesh_shape(st.GetPrimAtPath("/m"), I4, 0)
    assert shape.face_count() == 2 + 3 + 1
    assert shape.vertex_count() == 12
    area = 1.0 + (1.0 + 0.25) + 0.5
    assert float(np.array(shape.surface_area())[0]) == pytest.approx(area, rel=1e-6)
    assert warns == []


def test_holes_and_degenerate_faces_skipped():
    st = _stage()
    pts = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (2, 0, 0), (2, 1, 0)]
    _mesh(st, points=pts, counts=[4, 4, 2], indices=[0, 1, 2, 3, 1, 4, 5, 2, 0, 1], holeIndices=[1])
    shape, warns = mesh_shape(st.GetPrimAtPath("/m"), I4, 0)
    assert shape.face_count() == 2
    assert shape.vertex_count() == 4  # unused points are dropped
    assert any("faceVertexCounts" in w and "fewer than 3" in w for w in warns)


def test_winding_right_left_handed_and_mirror():
    st = _stage()
    _mesh(st, "/r")
    _mesh(st, "/l", orientation="leftHanded")
    for path, xf, expect_z in (("/r", I4, 1.0), ("/l", I4, -1.0),
                               ("/r", np.diag([1.0, 1.0, -1.0, 1.0]), -1.0),   # mirror flips z too
                               ("/l", np.diag([-1.0, 1.0, 1.0, 1.0]), -1.0)):
        shape, _ = mesh_shape(st.GetPrimAtPath(path), xf, 0)
        v, f, _, _ = _arrays(shape)
        fn = _face_normals(v, f)
        # rightHanded: CCW seen from +z -> +z. leftHanded: the same loop means -z.
        # Mirrored in z (det < 0): the world outward normal is the mirrored one.
        assert np.allclose(fn[:, 2], expect_z), (path, fn)


def test_transform_applied_to_positions_and_normals():
    st = _stage()
    m = _mesh(st, normals=[(0, 0, 1)] * 4)
    m.SetNormalsInterpolation("vertex")
    # row-vector transform: scale x by 2, rotate 90 deg about x (y -> z), translate
    rot = np.array(Gf.Matrix4d().SetRotate(Gf.Rotation(Gf.Vec3d(1, 0, 0), 90)))
    xf = np.diag([2.0, 1.0, 1.0, 1.0]) @ rot
    xf[3, :3] = (10, 20, 30)
    shape, _ = mesh_shape(st.GetPrimAtPath("/m"), xf, 0)
    v, f, n, _ = _arrays(shape)
    expect = np.array([(0, 0, 0), (2, 0, 0), (2, 0, 1), (0, 0, 1)], float) + (10, 20, 30)
    assert sorted(map(tuple, np.round(v, 5))) == sorted(map(tuple, expect))
    assert np.allclose(n, [0, -1, 0], atol=1e-6)            # +z rotated 90 deg about x
    assert np.allclose(_face_normals(v, f), [0, -1, 0], atol=1e-6)


def test_facevarying_normals_split_vertices():
    st = _stage()
    # two quads sharing an edge, with a hard edge (faceVarying normals differ per face)
    pts = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (2, 0, 0), (2, 1, 0)]
    nrm = [(0, 0, 1)] * 4 + [(1, 0, 0)] * 4
    m = _mesh(st, points=pts, counts=[4, 4], indices=[0, 1, 2, 3, 1, 4, 5, 2], normals=nrm)
    m.SetNormalsInterpolation("faceVarying")
    shape, warns = mesh_shape(st.GetPrimAtPath("/m"), I4, 0)
    assert shape.vertex_count() == 8 and shape.face_count() == 4
    v, f, n, _ = _arrays(shape)
    assert np.allclose(n[f[:2]].reshape(-1, 3), [0, 0, 1])
    assert np.allclose(n[f[2:]].reshape(-1, 3), [1, 0, 0])
    # vertex interpolation keeps the 6 shared points
    m.SetNormalsInterpolation("vertex")
    m.GetNormalsAttr().Set([(0, 0, 1)] * 6)
    shape, _ = mesh_shape(st.GetPrimAtPath("/m"), I4, 0)
    assert shape.vertex_count() == 6


def test_primvars_normals_indexed_override_normals():
    st = _stage()
    m = _mesh(st, normals=[(1, 0, 0)] * 4)
    pv = UsdGeom.PrimvarsAPI(m).CreatePrimvar("normals", Sdf.ValueTypeNames.Normal3fArray,
                                              UsdGeom.Tokens.faceVarying)
    pv.Set([(0, 0, 1), (0, 0, -1)])
    pv.SetIndices([0, 0, 1, 1])
    shape, _ = mesh_shape(st.GetPrimAtPath("/m"), I4, 0)
    v, f, n, _ = _arrays(shape)
    assert shape.vertex_count() == 4
    assert sorted(np.round(n[:, 2]).tolist()) == [-1, -1, 1, 1]


def test_subdivision_warns_and_gets_smooth_normals():
    st = _stage()
    # a tent: two quads meeting at a ridge along y at x=1
    pts = [(0, 0, 0), (1, 0, 1), (1, 1, 1), (0, 1, 0), (2, 0, 0), (2, 1, 0)]
    _mesh(st, points=pts, counts=[4, 4], indices=[0, 1, 2, 3, 1, 4, 5, 2], scheme="catmullClark")
    shape, warns = mesh_shape(st.GetPrimAtPath("/m"), I4, 0)
    assert any("subdivisionScheme" in w and "/m" in w for w in warns)
    v, f, n, _ = _arrays(shape)
    ridge = np.isclose(v[:, 0], 1.0)
    assert np.allclose(n[ridge], [0, 0, 1], atol=1e-6)     # averaged across the ridge
    # polygonal mesh without normals: flat
    st2 = _stage()
    _mesh(st2, points=pts, counts=[4, 4], indices=[0, 1, 2, 3, 1, 4, 5, 2])
    shape2, warns2 = mesh_shape(st2.GetPrimAtPath("/m"), I4, 0)
    assert not shape2.has_vertex_normals() and warns2 == []


@pytest.mark.parametrize("attr,counts,indices,match", [
    ("faceVertexIndices", [4], [0, 1, 2, 7], r"/m\.faceVertexIndices: .*out of range"),
    ("faceVertexIndices", [4], [0, 1, -1, 2], r"/m\.faceVertexIndices"),
    ("faceVertexCounts", [4, 3], [0, 1, 2, 3], r"/m\.faceVertexCounts: sum 7"),
])
def test_bad_topology_raises_naming_prim_and_attribute(attr, counts, indices, match):
    st = _stage()
    _mesh(st, counts=counts, indices=indices)
    with pytest.raises(TranslationError, match=match) as info:
        mesh_shape(st.GetPrimAtPath("/m"), I4, 0)
    assert info.value.attribute == attr


def test_no_points_raises():
    st = _stage()
    UsdGeom.Mesh.Define(st, "/m")
    with pytest.raises(TranslationError, match=r"/m\.points"):
        mesh_shape(st.GetPrimAtPath("/m"), I4, 0)


# ---- materials --------------------------------------------------------------------------------

def _preview(stage, path="/Mat", **inputs):
    mat = UsdShade.Material.Define(stage, path)
    sh = UsdShade.Shader.Define(stage, f"{path}/PS")
    sh.CreateIdAttr("UsdPreviewSurface")
    types = {"diffuseColor": Sdf.ValueTypeNames.Color3f, "emissiveColor": Sdf.ValueTypeNames.Color3f,
             "specularColor": Sdf.ValueTypeNames.Color3f, "useSpecularWorkflow": Sdf.ValueTypeNames.Int}
    for k, v in inputs.items():
        sh.CreateInput(k, types.get(k, Sdf.ValueTypeNames.Float)).Set(v)
    mat.CreateSurfaceOutput().ConnectToSource(sh.ConnectableAPI(), "surface")
    return mat, sh


def _bind(prim, mat):
    UsdShade.MaterialBindingAPI.Apply(prim).Bind(mat)


def _bsdf_params(shape):
    return {k: v for k, v in mi.traverse(shape).items() if k.startswith("bsdf.")}


def test_preview_surface_parameters_read_back():
    st = _stage()
    m = _mesh(st)
    mat, _ = _preview(st, diffuseColor=Gf.Vec3f(0.2, 0.4, 0.6), roughness=0.3, metallic=0.7,
                      ior=1.4, clearcoat=0.5, clearcoatRoughness=0.2)
    _bind(m.GetPrim(), mat)
    info = material_bsdf(mat, 0)
    assert info.bsdf["type"] == "principled" and info.warnings == []
    assert info.bsdf["base_color"]["value"] == pytest.approx([0.2, 0.4, 0.6])
    assert info.bsdf["roughness"] == pytest.approx(0.3)
    assert info.bsdf["metallic"] == pytest.approx(0.7)
    assert info.bsdf["eta"] == pytest.approx(1.4)
    assert info.bsdf["clearcoat"] == pytest.approx(0.5)
    assert info.bsdf["clearcoat_gloss"] == pytest.approx(0.8)
    shape, warns = mesh_shape(m.GetPrim(), I4, 0)
    p = _bsdf_params(shape)
    assert np.allclose(np.array(p["bsdf.base_color.value"]).ravel(), [0.2, 0.4, 0.6], atol=1e-6)
    assert float(np.array(p["bsdf.roughness.value"]).ravel()[0]) == pytest.approx(0.3)
    assert float(np.array(p["bsdf.metallic.value"]).ravel()[0]) == pytest.approx(0.7)
    assert float(np.array(p["bsdf.eta"]).ravel()[0]) == pytest.approx(1.4, rel=1e-6)


def test_opacity_emission_double_sided_and_specular_workflow():
    st = _stage()
    mat, _ = _preview(st, opacity=0.25, emissiveColor=Gf.Vec3f(1, 2, 3))
    info = material_bsdf(mat, 0, double_sided=True)
    assert info.bsdf["type"] == "mask" and info.bsdf["opacity"] == pytest.approx(0.25)
    assert info.bsdf["bsdf"]["type"] == "twosided"
    assert info.emitter["radiance"]["value"] == pytest.approx([1, 2, 3])
    # opacityThreshold: cut-out
    mat2, _ = _preview(st, "/Mat2", opacity=0.25, opacityThreshold=0.5)
    assert material_bsdf(mat2, 0).bsdf["type"] == "mask"
    mat3, _ = _preview(st, "/Mat3", opacity=0.75, opacityThreshold=0.5)
    assert material_bsdf(mat3, 0).bsdf["type"] == "principled"
    # specular workflow: approximate, warned
    mat4, _ = _preview(st, "/Mat4", useSpecularWorkflow=1, specularColor=Gf.Vec3f(0.04, 0.04, 0.04))
    info4 = material_bsdf(mat4, 0)
    assert info4.bsdf["specular"] == pytest.approx(0.5, rel=1e-3) and info4.bsdf["metallic"] == 0
    assert "eta" not in info4.bsdf
    assert any("useSpecularWorkflow" in w for w in info4.warnings)


def test_emissive_mesh_radiance_rendered():
    st = _stage()
    m = _mesh(st, points=[(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)])
    mat, _ = _preview(st, emissiveColor=Gf.Vec3f(0.5, 1.0, 2.0), diffuseColor=Gf.Vec3f(0, 0, 0))
    _bind(m.GetPrim(), mat)
    shape, _ = mesh_shape(m.GetPrim(), I4, 0)
    img = _render_facing(shape)
    assert np.allclose(img[4, 4], [0.5, 1.0, 2.0], rtol=1e-4)


def _render_facing(shape, env=None, res=8, spp=4):
    scene = {"type": "scene", "integrator": {"type": "path", "max_depth": 2}, "shape": shape,
             "sensor": {"type": "perspective", "fov": 20,
                        "to_world": mi.ScalarTransform4f().look_at([0, 0, 5], [0, 0, 0], [0, 1, 0]),
                        "film": {"type": "hdrfilm", "width": res, "height": res,
                                 "rfilter": {"type": "box"}},
                        "sampler": {"type": "independent", "sample_count": spp}}}
    if env is not None:
        scene["env"] = env
    return np.array(mi.render(mi.load_dict(scene)))


def test_non_preview_material_grey_with_warning():
    st = _stage()
    m = _mesh(st)
    mat = UsdShade.Material.Define(st, "/MtlX")
    sh = UsdShade.Shader.Define(st, "/MtlX/S")
    sh.CreateIdAttr("ND_standard_surface_surfaceshader")
    mat.CreateSurfaceOutput("mtlx").ConnectToSource(sh.ConnectableAPI(), "out")
    _bind(m.GetPrim(), mat)
    shape, warns = mesh_shape(m.GetPrim(), I4, 0)
    assert any("/MtlX" in w and "grey" in w for w in warns)
    assert np.allclose(np.array(_bsdf_params(shape)["bsdf.reflectance.value"]).ravel(), 0.18)


def test_display_color_fallbacks():
    st = _stage()
    m = _mesh(st)
    shape, _ = mesh_shape(m.GetPrim(), I4, 0)
    assert np.allclose(np.array(_bsdf_params(shape)["bsdf.reflectance.value"]).ravel(), 0.18)
    m.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set([(0.1, 0.2, 0.3)])
    shape, _ = mesh_shape(m.GetPrim(), I4, 0)
    assert np.allclose(np.array(_bsdf_params(shape)["bsdf.reflectance.value"]).ravel(), [0.1, 0.2, 0.3])
    m.GetDoubleSidedAttr().Set(True)
    shape, _ = mesh_shape(m.GetPrim(), I4, 0)
    assert "twosided" in str(shape.bsdf()).lower()
    # per-vertex display colour -> mesh attribute, rendered under a white furnace
    m.GetDoubleSidedAttr().Set(False)
    m.GetDisplayColorPrimvar().SetInterpolation(UsdGeom.Tokens.vertex)
    m.GetDisplayColorPrimvar().Set([(0.5, 0.25, 1.0)] * 4)
    shape, _ = mesh_shape(m.GetPrim(), I4, 0)
    assert shape.has_attribute("vertex_color")
    m.GetDisplayColorPrimvar().SetInterpolation(UsdGeom.Tokens.uniform)
    m.GetDisplayColorPrimvar().Set([(0.5, 0.25, 1.0)])
    shape, _ = mesh_shape(m.GetPrim(), I4, 0)
    assert shape.has_attribute("face_color")


def _write_png(path, rgb8):
    import OpenImageIO as oiio

    h, w, c = rgb8.shape
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(w, h, c, oiio.UINT8))
    out.write_image(np.ascontiguousarray(rgb8))
    out.close()


def _textured(st, tmp_path, file, **tex_inputs):
    mat, ps = _preview(st)
    tex = UsdShade.Shader.Define(st, "/Mat/Tex")
    tex.CreateIdAttr("UsdUVTexture")
    tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(str(file))
    for k, v in tex_inputs.items():
        tex.CreateInput(k, Sdf.ValueTypeNames.Token).Set(v)
    reader = UsdShade.Shader.Define(st, "/Mat/Reader")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("uvs")
    tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
    ps.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(tex.ConnectableAPI(), "rgb")
    return mat


def test_diffuse_texture_orientation_and_colour_space(tmp_path):
    """A 2x2 sRGB texture on a quad with st = xy: USD st (0, 0) is the image's bottom-left.
    Intersect the translated mesh near each corner and evaluate the translated texture there."""
    top_left, top_right, bottom_left, bottom_right = (255, 0, 0), (0, 255, 0), (0, 0, 255), (128, 128, 128)
    png = tmp_path / "tex.png"
    _write_png(png, np.array([[top_left, top_right], [bottom_left, bottom_right]], np.uint8))
    st = _stage()
    m = _mesh(st, points=[(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)])
    UsdGeom.PrimvarsAPI(m).CreatePrimvar("uvs", Sdf.ValueTypeNames.TexCoord2fArray,
                                         UsdGeom.Tokens.vertex).Set([(0, 0), (1, 0), (1, 1), (0, 1)])
    mat = _textured(st, tmp_path, png, wrapS="clamp", wrapT="clamp")
    _bind(m.GetPrim(), mat)
    shape, warns = mesh_shape(m.GetPrim(), I4, 0)
    assert warns == [] and shape.has_vertex_texcoords()
    info = material_bsdf(mat, 0)
    assert info.uv_primvar == "uvs"
    tex = mi.load_dict({**info.bsdf["base_color"], "filter_type": "nearest"})
    scene = mi.load_dict({"type": "scene", "s": shape})
    srgb_128 = ((128 / 255 + 0.055) / 1.055) ** 2.4   # sRGB decoded (auto: 8-bit RGB)
    expect = {(-0.5, 0.5): top_left, (0.5, 0.5): top_right, (-0.5, -0.5): bottom_left,
              (0.5, -0.5): (srgb_128 * 255,) * 3}
    for (x, y), rgb in expect.items():
        si = scene.ray_intersect(mi.Ray3f(mi.Point3f(x, y, 1.0), mi.Vector3f(0, 0, -1)))
        value = np.array(tex.eval(si)).ravel()
        assert np.allclose(value, np.array(rgb) / 255.0, atol=1e-6), ((x, y), value)


def test_missing_texture_warns_and_uses_fallback(tmp_path):
    st = _stage()
    m = _mesh(st)
    UsdGeom.PrimvarsAPI(m).CreatePrimvar("uvs", Sdf.ValueTypeNames.TexCoord2fArray,
                                         UsdGeom.Tokens.vertex).Set([(0, 0), (1, 0), (1, 1), (0, 1)])
    mat = _textured(st, tmp_path, tmp_path / "nope.png")
    UsdShade.Shader(st.GetPrimAtPath("/Mat/Tex")).CreateInput(
        "fallback", Sdf.ValueTypeNames.Float4).Set((0.3, 0.2, 0.1, 1))
    _bind(m.GetPrim(), mat)
    shape, warns = mesh_shape(m.GetPrim(), I4, 0)
    assert any("/Mat/Tex.inputs:file" in w and "nope.png" in w for w in warns)
    assert np.allclose(np.array(_bsdf_params(shape)["bsdf.base_color.value"]).ravel(), [0.3, 0.2, 0.1])


def test_geom_subsets_give_one_mesh_per_material():
    st = _stage()
    pts = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (2, 0, 0), (2, 1, 0)]
    m = _mesh(st, points=pts, counts=[4, 4], indices=[0, 1, 2, 3, 1, 4, 5, 2])
    red, _ = _preview(st, "/Red", diffuseColor=Gf.Vec3f(1, 0, 0))
    blue, _ = _preview(st, "/Blue", diffuseColor=Gf.Vec3f(0, 0, 1))
    _bind(m.GetPrim(), blue)
    binding = UsdShade.MaterialBindingAPI(m.GetPrim())
    sub = binding.CreateMaterialBindSubset("left", [0])
    UsdShade.MaterialBindingAPI.Apply(sub.GetPrim()).Bind(red)
    shapes, warns = mesh_shapes(m.GetPrim(), I4, 0)
    assert len(shapes) == 2 and [s.face_count() for s in shapes] == [2, 2]
    colours = [np.array(_bsdf_params(s)["bsdf.base_color.value"]).ravel().tolist() for s in shapes]
    assert colours == [[1, 0, 0], [0, 0, 1]]
    single, warns1 = mesh_shape(m.GetPrim(), I4, 0)
    assert single.face_count() == 4 and any("GeomSubsets" in w for w in warns1)


def test_material_cache_shares_the_bsdf_and_reports_once():
    st = _stage()
    a, b = _mesh(st, "/a"), _mesh(st, "/b")
    mat, _ = _preview(st, diffuseColor=Gf.Vec3f(0.5, 0.5, 0.5), displacement=0.1)
    _bind(a.GetPrim(), mat)
    _bind(b.GetPrim(), mat)
    cache: dict = {}
    sa, wa = mesh_shape(a.GetPrim(), I4, 0, material_cache=cache)
    sb, wb = mesh_shape(b.GetPrim(), I4, 0, material_cache=cache)
    assert sa.bsdf().ptr == sb.bsdf().ptr
    assert any("/Mat/PS.inputs:displacement" in w for w in wa) and wb == []
