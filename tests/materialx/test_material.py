"""Fitted materials on the stage: ``usdfiber material`` and ``author_materials``.

Tables are baked small (15 degrees, 4000 photons per direction, a few seconds for round
polyester) into a temporary cache; the checks are structural (the network a Hydra consumer
reads, bindings, colours, reruns, variants, time samples, MaterialX validation), so the
tables' noise does not matter here.
"""
from __future__ import annotations

import os
import stat

import numpy as np
import pytest

import usdfiber  # noqa: F401  (registers the schemas first)
from pxr import Usd, UsdGeom, UsdShade

from usdfiber import authoring
from usdfiber.bcsdf import BakeSettings, TableCache
from usdfiber.cli import UsageError, build_parser
from usdfiber.translators.materialx import LookError, author_materials
from usdfiber.translators.materialx.command import register
from usdfiber.translators.materialx.document import DocumentError, look_document, validate_document

BAKE = BakeSettings(resolution_deg=15.0, photons=4000, batches=2)


def _curves(stage: Usd.Stage, path: str, x: float) -> Usd.Prim:
    c = UsdGeom.BasisCurves.Define(stage, path)
    c.CreateTypeAttr("cubic")
    c.CreateBasisAttr("bspline")
    c.CreateCurveVertexCountsAttr([4])
    c.CreatePointsAttr([(x, 0, 0), (x, 0, 1), (x, 0, 2), (x, 0, 3)])
    c.CreateWidthsAttr([0.02])
    c.SetWidthsInterpolation(UsdGeom.Tokens.constant)
    return c.GetPrim()


def make_stage(path, *, variants: bool = False, animated: bool = False) -> str:
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    root = UsdGeom.Xform.Define(stage, "/Cloth")
    stage.SetDefaultPrim(root.GetPrim())
    authoring.apply_fiber(_curves(stage, "/Cloth/Red", 0.0), "polyester", dye="reactiveRed", depth_of_shade=1.0)
    authoring.apply_fiber(_curves(stage, "/Cloth/RedToo", 1.0), "polyester", dye="reactiveRed", depth_of_shade=1.0)
    authoring.apply_fiber(_curves(stage, "/Cloth/Blue", 2.0), "polyester", dye="disperseBlue", depth_of_shade=1.0)
    if variants:
        p = _curves(stage, "/Cloth/Shades", 3.0)
        authoring.apply_fiber(p, "polyester", dye="reactiveRed")
        authoring.add_depth_of_shade_variants(p, {"pale": 0.1, "deep": 4.0}, default="deep")
    if animated:
        authoring.apply_fiber(_curves(stage, "/Cloth/Fade", 4.0), "polyester", dye="reactiveRed",
                              depth_of_shade={0.0: 0.2, 10.0: 3.0})
    UsdGeom.Xform.Define(stage, "/Cloth/Card")
    stage.Save()
    return str(path)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return TableCache(tmp_path_factory.mktemp("cache"))


def run_cli(argv: list[str]) -> int:
    args = build_parser({"material": register}).parse_args(["material"] + argv)
    return args.func(args)


def network(prim: Usd.Prim):
    """What a Hydra-style consumer reads: the bound material and its mtlx network."""
    mat, _rel = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
    assert mat, f"{prim.GetPath()} has no bound material"
    surf = mat.ComputeSurfaceSource("mtlx")[0]
    assert surf and surf.GetIdAttr().Get() == "ND_surface"
    src = surf.GetInput("bsdf").GetConnectedSource()
    hair = UsdShade.Shader(src[0].GetPrim())
    assert hair.GetIdAttr().Get() == "ND_chiang_hair_bsdf"
    return mat, hair


def test_materials_bound_and_readable_by_a_hydra_consumer(tmp_path, cache):
    path = make_stage(tmp_path / "cloth.usda")
    stage = Usd.Stage.Open(path)
    report = author_materials(stage, cache=cache, settings=BAKE)
    stage.Save()
    # reopen from disk: the network round-trips through the file
    stage = Usd.Stage.Open(path)
    mats = {}
    for name in ("Red", "RedToo", "Blue"):
        prim = stage.GetPrimAtPath(f"/Cloth/{name}")
        mat, hair = network(prim)
        mats[name] = mat.GetPath()
        vals = {i.GetBaseName(): i.Get() for i in hair.GetInputs()}
        assert set(vals) >= {"ior", "roughness_R", "roughness_TT", "roughness_TRT", "cuticle_angle",
                             "absorption_coefficient", "tint_R", "tint_TT", "tint_TRT"}
        assert 1.2 <= vals["ior"] <= 2.2
        assert vals["roughness_TT"][0] == pytest.approx(vals["roughness_R"][0] / 4, rel=1e-5)
        # Storm: preview surface and display colour, the same mean colour
        prev = mat.ComputeSurfaceSource()[0]
        assert prev.GetIdAttr().Get() == "UsdPreviewSurface"
        diffuse = np.array(prev.GetInput("diffuseColor").Get())
        dc = np.array(UsdGeom.PrimvarsAPI(prim).GetPrimvar("displayColor").Get()[0])
        assert np.allclose(diffuse, dc) and np.all(dc > 0) and np.all(dc < 1)
    assert mats["Red"] == mats["RedToo"] != mats["Blue"]       # one material per distinct look
    assert len(report.materials) == 2
    red = np.array(UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Cloth/Red")).GetPrimvar("displayColor").Get()[0])
    blue = np.array(UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Cloth/Blue")).GetPrimvar("displayColor").Get()[0])
    assert red[0] > red[2] and blue[2] > blue[0]                # a red dye looks red, a blue one blue
    # a red dye absorbs blue and green more than red
    _, hair = network(stage.GetPrimAtPath("/Cloth/Red"))
    a = hair.GetInput("absorption_coefficient").Get()
    assert a[0] < a[1] and a[0] < a[2]
    assert not UsdShade.MaterialBindingAPI(stage.GetPrimAtPath("/Cloth/Card")).ComputeBoundMaterial()[0]


def test_rerun_updates_without_duplicating(tmp_path, cache):
    path = make_stage(tmp_path / "cloth.usda")
    assert run_cli([path, "--cache-dir", str(cache.root), "--bake-resolution", "15", "--bake-photons", "4000"]) == 0
    stage = Usd.Stage.Open(path)
    first = stage.GetRootLayer().ExportToString()
    assert run_cli([path, "--cache-dir", str(cache.root), "--bake-resolution", "15", "--bake-photons", "4000"]) == 0
    stage.Reload()
    assert stage.GetRootLayer().ExportToString() == first
    looks = stage.GetPrimAtPath("/Cloth/FiberLooks").GetChildren()
    assert len(looks) == 2 and all(p.IsA(UsdShade.Material) for p in looks)
    names = {p.GetName() for p in looks}
    # a changed dye replaces the material it no longer uses
    authoring.apply_fiber(stage.GetPrimAtPath("/Cloth/Blue"), None, depth_of_shade=3.0)
    stage.Save()
    assert run_cli([path, "--cache-dir", str(cache.root), "--bake-resolution", "15", "--bake-photons", "4000"]) == 0
    stage = Usd.Stage.Open(path)
    looks2 = stage.GetPrimAtPath("/Cloth/FiberLooks").GetChildren()
    assert len(looks2) == 2 and {p.GetName() for p in looks2} != names


def test_output_layer_leaves_the_stage_alone(tmp_path, cache):
    path = make_stage(tmp_path / "cloth.usda")
    before = open(path).read()
    out = tmp_path / "looks" / "cloth_looks.usda"
    out.parent.mkdir()
    mtlx = tmp_path / "looks.mtlx"
    assert run_cli([path, "-o", str(out), "--mtlx", str(mtlx), "--cache-dir", str(cache.root),
                    "--bake-resolution", "15", "--bake-photons", "4000"]) == 0
    assert open(path).read() == before
    stage = Usd.Stage.Open(str(out))
    network(stage.GetPrimAtPath("/Cloth/Blue"))
    import MaterialX as mx
    doc = mx.createDocument()
    mx.readFromXmlFile(doc, str(mtlx))
    validate_document(doc)
    mats = doc.getMaterialNodes()
    assert len(mats) == 2 and all(doc.getNode(m.getName() + "_bsdf").getCategory() == "chiang_hair_bsdf"
                                  for m in mats)
    try:
        from pxr import UsdMtlx  # noqa: F401  (usd-core wheels ship without it)
    except ImportError:
        return
    mstage = Usd.Stage.Open(str(mtlx))
    assert any(p.IsA(UsdShade.Material) for p in mstage.Traverse())


def test_variants_and_time_samples_carried_through(tmp_path, cache):
    path = make_stage(tmp_path / "cloth.usda", variants=True, animated=True)
    stage = Usd.Stage.Open(path)
    author_materials(stage, cache=cache, settings=BAKE)
    stage.Save()
    stage = Usd.Stage.Open(path)
    prim = stage.GetPrimAtPath("/Cloth/Shades")
    vset = prim.GetVariantSets().GetVariantSet("depthOfShade") if prim.GetVariantSets().HasVariantSet(
        "depthOfShade") else prim.GetVariantSets().GetVariantSet(prim.GetVariantSets().GetNames()[0])
    assert vset.GetVariantSelection() == "deep"
    deep_mat, _ = network(prim)
    deep = np.array(UsdGeom.PrimvarsAPI(prim).GetPrimvar("displayColor").Get()[0])
    vset.SetVariantSelection("pale")
    pale_mat, _ = network(prim)
    pale = np.array(UsdGeom.PrimvarsAPI(prim).GetPrimvar("displayColor").Get()[0])
    assert pale_mat.GetPath() != deep_mat.GetPath()
    assert pale.sum() > deep.sum()                     # a paler shade is lighter
    fade = stage.GetPrimAtPath("/Cloth/Fade")
    _, hair = network(fade)
    a = hair.GetInput("absorption_coefficient").GetAttr()
    assert a.GetTimeSamples() == [0.0, 10.0]
    assert np.all(np.array(a.Get(10.0)) > np.array(a.Get(0.0)))
    dc = UsdGeom.PrimvarsAPI(fade).GetPrimvar("displayColor").GetAttr()
    assert dc.GetTimeSamples() == [0.0, 10.0]


def test_bad_input_gives_one_line_errors(tmp_path, cache, monkeypatch):
    empty = Usd.Stage.CreateNew(str(tmp_path / "empty.usda"))
    UsdGeom.Xform.Define(empty, "/World")
    empty.Save()
    with pytest.raises(UsageError, match="no fiber or yarn curves") as exc:
        run_cli([str(tmp_path / "empty.usda"), "--cache-dir", str(cache.root)])
    assert "\n" not in str(exc.value) and "empty.usda" in str(exc.value)
    with pytest.raises(LookError, match="no fiber or yarn curves"):
        author_materials(Usd.Stage.Open(str(tmp_path / "empty.usda")), cache=cache, settings=BAKE)
    path = make_stage(tmp_path / "ro.usda")
    os.chmod(path, stat.S_IRUSR | stat.S_IRGRP)
    try:
        if os.access(path, os.W_OK):   # root writes read-only files: deny as a normal user would be
            import usdfiber.translators.materialx.command as command
            real = os.access
            monkeypatch.setattr(command.os, "access",
                                lambda p, mode: False if str(p) == path and mode & os.W_OK else real(p, mode))
        with pytest.raises(UsageError, match="read-only") as exc:
            run_cli([path, "--cache-dir", str(cache.root)])
        assert "\n" not in str(exc.value) and "ro.usda" in str(exc.value)
    finally:
        os.chmod(path, stat.S_IRUSR | stat.S_IWUSR)
    with pytest.raises(UsageError, match="no such file"):
        run_cli([str(tmp_path / "missing.usda")])
    with pytest.raises(UsageError, match="no cached table"):
        run_cli([make_stage(tmp_path / "nobake.usda"), "--no-bake", "--cache-dir", str(tmp_path / "empty_cache")])


@pytest.mark.parametrize("option, name, expect", [
    ("-o", "adir.usda", r"adir.usda: -o: is a directory; expected a .usda or .usdc or .usd file"),
    ("-o", "looks.txt", r"looks.txt: -o: expected a .usda or .usdc or .usd file"),
    ("-o", "missing/looks.usda", r"looks.usda: -o: cannot write: no directory .*missing"),
    ("--mtlx", "adir.usda", r"adir.usda: --mtlx: is a directory; expected a .mtlx file"),
    ("--mtlx", "looks.xml", r"looks.xml: --mtlx: expected a .mtlx file"),
    ("--mtlx", "missing/looks.mtlx", r"--mtlx: cannot write: no directory"),
])
def test_outputs_that_cannot_be_written_are_refused_first(tmp_path, option, name, expect):
    """One line, before any table is looked up (the cache here is empty: a lookup would fail
    with another error), never a USD traceback after the fits."""
    (tmp_path / "adir.usda").mkdir()
    path = make_stage(tmp_path / "cloth.usda")
    argv = [path, option, str(tmp_path / name), "--no-bake", "--cache-dir", str(tmp_path / "empty_cache")]
    with pytest.raises(UsageError, match=expect) as exc:
        run_cli(argv)
    assert "\n" not in str(exc.value)


def test_invalid_document_is_refused(cache):
    import MaterialX as mx
    doc = mx.createDocument()
    node = doc.addNode("chiang_hair_bsdf", "bad", "BSDF")
    node.setInputValue("ior", "not a number", "string")      # wrong type for the input
    with pytest.raises(DocumentError, match="validation failed"):
        validate_document(doc)
    assert look_document([]).getMaterialNodes() == []
