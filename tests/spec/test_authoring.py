"""The authoring API and FiberParams resolution on composed stages."""
from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import pytest

import usdfiber  # noqa: F401  (registers the schema before any stage is made)
from pxr import Sdf, Usd, UsdGeom

from usdfiber import authoring as A
from usdfiber.colour import spectrum_to_rec709
from usdfiber.spec.fiber import FiberParams, FiberParamsError

REPO = Path(__file__).resolve().parents[2]
SCHEMA = REPO / "schema" / "schema.usda"
API_SCHEMAS = {"FiberAPI": "fiber:", "FiberYarnAPI": "yarn:", "FiberProfileAPI": "fiberProfile:"}


@pytest.fixture
def stage() -> Usd.Stage:
    return Usd.Stage.CreateInMemory()


def curves(stage: Usd.Stage, path: str = "/c") -> Usd.Prim:
    return UsdGeom.BasisCurves.Define(stage, path).GetPrim()


# ------------------------------------------------------------------ schema registration
def test_schemas_registered_with_fallbacks_of_schema_usda():
    layer = Sdf.Layer.OpenAsAnonymous(str(SCHEMA))
    reg = Usd.SchemaRegistry()
    for api, prefix in API_SCHEMAS.items():
        definition = reg.FindAppliedAPIPrimDefinition(api)
        assert definition is not None, api
        spec = layer.GetPrimAtPath(f"/{api}")
        names = {p.name for p in spec.properties}
        assert names == set(definition.GetPropertyNames())
        assert all(n.startswith(prefix) for n in names)
        for prop in spec.properties:
            if isinstance(prop, Sdf.AttributeSpec):
                a = definition.GetAttributeDefinition(prop.name)
                assert str(a.GetTypeName()) == str(prop.typeName), prop.name
                assert a.GetVariability() == prop.variability, prop.name
                assert a.GetFallbackValue() == prop.default, prop.name


def test_applied_prim_reads_schema_fallbacks(stage):
    prim = curves(stage)
    prim.ApplyAPI("FiberAPI")
    layer = Sdf.Layer.OpenAsAnonymous(str(SCHEMA))
    for prop in layer.GetPrimAtPath("/FiberAPI").properties:
        if isinstance(prop, Sdf.AttributeSpec) and prop.default is not None:
            assert prim.GetAttribute(prop.name).Get() == prop.default, prop.name
    fp = FiberParams.from_prim(prim)  # the fallbacks resolve
    assert fp.kind == "polyester" and fp.profile_family == "round" and fp.variant_count == 1
    assert fp.beta == pytest.approx(math.degrees(math.atan(3.5 / 30)), rel=1e-6)
    assert fp.mu_a == (0.0, 0.0, 0.0)


# ------------------------------------------------------------------ apply / override
def test_apply_fiber_preset_and_overrides(stage):
    prim = A.apply_fiber(curves(stage), "cotton", diameter=18, depth_of_shade=1.5, dye="reactiveRed")
    assert prim.HasAPI("FiberAPI")
    fp = FiberParams.from_prim(prim)
    assert fp.kind == "cotton" and fp.profile_family == "kidney"
    assert fp.diameter == 18 and fp.depth_of_shade == 1.5
    assert fp.density == pytest.approx(1.52)
    assert fp.eta == pytest.approx((1.578 + 1.532) / 2, rel=1e-6)
    assert fp.roughness_source == "beta" and fp.beta == pytest.approx(15.5)
    assert fp.dye_class == "reactive"
    r, g, b = fp.extinction
    assert g > r and b > r
    # mu_a = rho * zeta/100 * eps, in 1/um
    assert fp.mu_a[1] == pytest.approx(1.52e3 * 0.015 * g * 1e3 * 1e-4, rel=1e-6)


def test_override_conveniences(stage):
    p = A.apply_fiber(curves(stage), "silk", ra=10, profile_length=40)
    fp = FiberParams.from_prim(p)
    assert fp.roughness_source == "ra" and fp.beta == pytest.approx(math.degrees(math.atan(10 / 40)), rel=1e-6)
    p = A.apply_fiber(curves(stage, "/d"), "silk", ior=1.6, ior_effective="parallel", beta=9)
    fp = FiberParams.from_prim(p)
    assert fp.eta == pytest.approx(1.6) and fp.beta == pytest.approx(9)
    p = A.apply_fiber(curves(stage, "/e"), "wool", molar_extinction=(20000, 30000, 40000),
                      molar_mass=500, depth_of_shade=2)
    fp = FiberParams.from_prim(p)
    assert fp.dye_class == "custom" and fp.extinction_source == "molar"
    # 20000 L/(mol cm) / 500 g/mol = 40 L/(g cm) = 0.04 L/(mg cm)
    assert fp.extinction == pytest.approx((0.04, 0.06, 0.08), rel=1e-6)
    assert fp.has_cuticle and fp.cuticle_tilt == 3 and fp.cuticle_height == pytest.approx(0.7)


def test_spectrum_extinction(stage):
    assert spectrum_to_rec709([380, 780], [0.02, 0.02]) == pytest.approx((0.02, 0.02, 0.02))
    wl = list(range(400, 701, 10))
    red_dye = [0.001 if w > 600 else 0.02 for w in wl]  # absorbs below 600 nm: looks red
    p = A.apply_fiber(curves(stage), "silk", dye_class="reactive",
                      spectrum_wavelengths=wl, spectrum_values=red_dye, depth_of_shade=1)
    fp = FiberParams.from_prim(p)
    assert fp.extinction_source == "spectrum"
    r, g, b = fp.extinction
    assert r < g and r < b and all(0.001 <= c <= 0.02 for c in fp.extinction)


def test_profile_sources_and_user_profile(stage):
    loops = [[(0, 0), (12, 0), (12, 6), (0, 6), (0, 0)], [(4, 2), (6, 2), (5, 4)]]
    prof = A.define_profile(stage, "/profiles/bean", loops, smooth=True)
    assert prof.HasAPI("FiberProfileAPI")
    assert list(prof.GetAttribute("fiberProfile:loopVertexCounts").Get()) == [4, 3]  # closing point dropped
    p = A.apply_fiber(curves(stage), "cotton")
    A.set_profile_sources(p, ["/profiles/bean"])
    fp = FiberParams.from_prim(p)
    assert fp.profile_family == "user" and fp.variant_count == 1
    assert fp.user_profiles[0].path == "/profiles/bean" and fp.user_profiles[0].smooth
    assert fp.user_profiles[0].loops[1] == ((4.0, 2.0), (6.0, 2.0), (5.0, 4.0))
    assert fp.to_dict()["user_profiles"][0]["loops"][0][1] == [12.0, 0.0]


def test_apply_yarn(stage):
    p = A.apply_yarn(curves(stage), "S 303", dye="reactiveOrange", depth_of_shade=2, hair_density=3)
    assert p.HasAPI("FiberAPI") and p.HasAPI("FiberYarnAPI")
    assert p.GetAttribute("yarn:plies").Get() == 3
    assert p.GetAttribute("yarn:fibersPerPly").Get() == 90
    assert p.GetAttribute("yarn:ply:twist").Get() == pytest.approx(9)
    assert p.GetAttribute("yarn:flyaway:hairDensity").Get() == 3
    assert FiberParams.from_prim(p).kind == "silk"
    r_default = p.GetAttribute("yarn:ply:radius").Get()
    q = A.apply_yarn(curves(stage, "/q"), "S 303", packing_fraction=0.3)
    assert q.GetAttribute("yarn:ply:radius").Get() == pytest.approx(r_default * math.sqrt(2), rel=1e-5)
    w = A.apply_yarn(curves(stage, "/w"), "CNe 50", fiber_preset="mercerizedCotton", seed=7, fiber_seed=3)
    assert w.GetAttribute("yarn:seed").Get() == 7 and w.GetAttribute("fiber:seed").Get() == 3
    assert FiberParams.from_prim(w).profile_family == "swollen"
    assert A.yarn_diameter_mm(w) > 2 * w.GetAttribute("yarn:ply:radius").Get()


# ------------------------------------------------------------------ composition
def test_class_inherited_by_100_curves_and_override_wins(stage):
    cls = A.define_fiber_class(stage, "/_classes/Silk", "silk", dye="reactiveOrange", depth_of_shade=0.5)
    assert cls.IsAbstract()
    prims = []
    for i in range(100):
        prim = curves(stage, f"/fibers/f{i:03d}")
        A.inherit(prim, "/_classes/Silk")
        prims.append(prim)
    A.apply_fiber(prims[42], None, diameter=6.0, depth_of_shade=3.0)
    for i, prim in enumerate(prims):
        assert prim.HasAPI("FiberAPI")
        fp = FiberParams.from_prim(prim)
        assert fp.kind == "silk" and fp.dye_class == "reactive"
        if i == 42:
            assert fp.diameter == 6.0 and fp.depth_of_shade == 3.0
        else:
            assert fp.diameter == 7.5 and fp.depth_of_shade == 0.5
    # The class value changes for all that do not override.
    cls.GetAttribute("fiber:diameter").Set(8.0)
    assert FiberParams.from_prim(prims[0]).diameter == 8.0
    assert FiberParams.from_prim(prims[42]).diameter == 6.0


def test_depth_of_shade_variant_set_switches_zeta(stage):
    cls = A.define_fiber_class(stage, "/_classes/Cotton", "cotton", dye="reactiveRed", depth_of_shade=2.0)
    vset = A.add_depth_of_shade_variants(cls, {"pale": 0.1, "medium": 1.0, "deep": 4.0}, default="medium")
    prim = curves(stage, "/f")
    A.inherit(prim, cls.GetPath())
    assert FiberParams.from_prim(prim).depth_of_shade == pytest.approx(1.0)
    prim.GetVariantSet("depthOfShade").SetVariantSelection("deep")
    deep = FiberParams.from_prim(prim)
    assert deep.depth_of_shade == pytest.approx(4.0)
    vset.SetVariantSelection("pale")  # on the class: the prim's own selection still wins
    assert FiberParams.from_prim(prim).depth_of_shade == pytest.approx(4.0)
    prim.GetVariantSet("depthOfShade").ClearVariantSelection()
    pale = FiberParams.from_prim(prim)
    assert pale.depth_of_shade == pytest.approx(0.1)
    assert deep.mu_a[1] == pytest.approx(40 * pale.mu_a[1], rel=1e-5)
    assert deep.geometry_key() == pale.geometry_key()


def test_time_sampled_depth_of_shade(stage):
    prim = A.apply_fiber(curves(stage), "silk", dye="reactiveRed", depth_of_shade={1: 0.1, 24: 4.0})
    assert FiberParams.from_prim(prim, 1).depth_of_shade == pytest.approx(0.1)
    assert FiberParams.from_prim(prim, Usd.TimeCode(24)).depth_of_shade == pytest.approx(4.0)
    mid = FiberParams.from_prim(prim, 12.5)
    assert mid.depth_of_shade == pytest.approx(0.1 + (4.0 - 0.1) * 11.5 / 23, rel=1e-5)
    assert mid.time == 12.5
    assert FiberParams.from_prim(prim, 1).geometry_key() == FiberParams.from_prim(prim, 24).geometry_key()


# ------------------------------------------------------------------ geometry key
def test_geometry_key_ignores_colour_inputs_and_tracks_geometry(stage):
    base = A.apply_fiber(curves(stage, "/base"), "cotton", dye="reactiveRed", depth_of_shade=1)
    key = FiberParams.from_prim(base).geometry_key()

    def key_of(path, preset="cotton", **ov):
        return FiberParams.from_prim(A.apply_fiber(curves(stage, path), preset, **ov)).geometry_key()

    same = [
        key_of("/s1", dye="reactiveBlue", depth_of_shade=1),
        key_of("/s2", dye="reactiveRed", depth_of_shade=4),
        key_of("/s3", dye="reactiveRed", depth_of_shade=1, diameter=20),
        key_of("/s4", dye="disperseBlack", depth_of_shade=0.1, diameter=17, table="x.npz"),
        key_of("/s5", rotation=30, random_rotation=False),
    ]
    assert all(k == key for k in same)
    # The same physical index given as one explicit value.
    cotton_mean = (1.578 + 1.532) / 2
    a = key_of("/m1", ior_parallel=cotton_mean + 0.1, ior_perpendicular=cotton_mean - 0.1)
    b = key_of("/m2", ior=cotton_mean)
    assert a == b == key

    A.define_profile(stage, "/prof", [[(0, 0), (10, 0), (5, 8)]])
    changed = [
        key_of("/c1", ior_parallel=1.60),
        key_of("/c2", ior_effective="parallel"),
        key_of("/c3", beta=10),
        key_of("/c4", ra=14.15, profile_length=50),  # arctan(Ra/l) = 15.8 deg != 15.5
        key_of("/c5", profile="bean"),
        key_of("/c6", variant_count=8),
        key_of("/c7", seed=5),
        key_of("/c8", profile_sources=["/prof"]),
        key_of("/c9", cuticle_height=0.5, cuticle_tilt=3),
    ]
    assert len({key, *changed}) == len(changed) + 1
    # Round fibers: one exact variant, the seed does not change the trace.
    assert key_of("/r1", "polyester", seed=1) == key_of("/r2", "polyester", seed=2)
    # Wool cuticles are traced relative to the diameter.
    assert key_of("/w1", "wool", diameter=30) != key_of("/w2", "wool", diameter=34)
    assert len(key) == 64 and int(key, 16) >= 0


def test_to_dict_is_json(stage):
    import json

    fp = FiberParams.from_prim(A.apply_fiber(curves(stage), "wool", dye="reactiveGreen", depth_of_shade=1))
    d = json.loads(json.dumps(fp.to_dict()))
    assert d["kind"] == "wool" and d["units"]["mu_a"].startswith("1/um") and d["geometry_key"] == fp.geometry_key()
    g = fp.geometry_inputs()
    assert "depth_of_shade" not in g and "diameter" not in g and "extinction" not in g
    assert g["cuticle"]["height_rel"] == pytest.approx(0.7 / 32, abs=1e-6)


# ------------------------------------------------------------------ errors
def test_authoring_errors(stage):
    xf = UsdGeom.Xform.Define(stage, "/xf").GetPrim()
    with pytest.raises(A.AuthoringError, match=r"/xf.*Xform.*BasisCurves"):
        A.apply_fiber(xf, "cotton")
    assert not xf.HasAPI("FiberAPI")
    with pytest.raises(A.AuthoringError, match=r"/xf"):
        A.apply_yarn(xf)
    c = curves(stage)
    with pytest.raises(A.AuthoringError, match=r"unknown parameter\(s\) diamter; valid: .*diameter"):
        A.apply_fiber(c, "cotton", diamter=3)
    with pytest.raises(A.AuthoringError, match="unknown fiber preset 'nylon'.*polyester"):
        A.apply_fiber(c, "nylon")
    with pytest.raises(A.AuthoringError, match="unknown dye 'purple'.*reactiveRed"):
        A.apply_fiber(c, "cotton", dye="purple")
    with pytest.raises(A.AuthoringError, match="fiber:kind.*'linen' is not one of"):
        A.apply_fiber(c, "cotton", kind="linen")
    with pytest.raises(A.AuthoringError, match="fiber:density: is uniform"):
        A.apply_fiber(c, "cotton", density={1: 1.3, 2: 1.5})
    with pytest.raises(A.AuthoringError, match="fiber:diameter: cannot use 'thick'"):
        A.apply_fiber(c, "cotton", diameter="thick")
    with pytest.raises(A.AuthoringError, match="both Ra/l and beta"):
        A.apply_fiber(c, "cotton", ra=3, beta=3)
    assert not c.HasAPI("FiberAPI")  # nothing authored by a failed call
    assert not c.GetAuthoredAttributes()
    with pytest.raises(A.AuthoringError, match="/nowhere is not a prim with FiberProfileAPI"):
        A.apply_fiber(c, "cotton", profile_sources=["/nowhere"])
    with pytest.raises(A.AuthoringError, match="unknown parameter"):
        A.apply_yarn(c, "CNe 50", twist=3)
    with pytest.raises(A.AuthoringError, match="unknown yarn preset"):
        A.apply_yarn(c, "CNe 60")
    with pytest.raises(A.AuthoringError, match="no prim there"):
        A.inherit(c, "/_classes/Missing")
    with pytest.raises(A.AuthoringError, match="loop 0 has 2 points"):
        A.define_profile(stage, "/p", [[(0, 0), (1, 1)]])
    with pytest.raises(A.AuthoringError, match="has no FiberAPI"):
        A.add_depth_of_shade_variants(xf, {"pale": 0.1})
    A.apply_fiber(c, "cotton")
    with pytest.raises(A.AuthoringError, match="default variant 'dark'"):
        A.add_depth_of_shade_variants(c, {"pale": 0.1}, default="dark")


def test_fiber_params_errors(stage):
    p = A.apply_fiber(curves(stage, "/molar"), "cotton", molar_extinction=(1, 2, 3))  # molarMass fallback 0
    with pytest.raises(FiberParamsError, match=r"/molar\.fiber:dye:molarMass.*> 0") as exc:
        FiberParams.from_prim(p)
    assert exc.value.prim == "/molar" and exc.value.attribute == "fiber:dye:molarMass"
    p = A.apply_fiber(curves(stage, "/custom"), "cotton", kind="custom")
    with pytest.raises(FiberParamsError, match=r"/custom\.fiber:profile"):
        FiberParams.from_prim(p)
    p = A.apply_fiber(curves(stage, "/user"), "cotton", profile="user")
    with pytest.raises(FiberParamsError, match=r"/user\.fiber:profile:sources"):
        FiberParams.from_prim(p)
    p = A.apply_fiber(curves(stage, "/spec"), "cotton", dye_class="reactive",
                      spectrum_wavelengths=[450, 600], spectrum_values=[0.01, 0.01])
    with pytest.raises(FiberParamsError, match="400-700"):
        FiberParams.from_prim(p)
    with pytest.raises(FiberParamsError, match="no FiberAPI"):
        FiberParams.from_prim(curves(stage, "/plain"))


# ------------------------------------------------------------------ examples
def _check_curves_topology(prim: Usd.Prim) -> None:
    c = UsdGeom.BasisCurves(prim)
    counts = list(c.GetCurveVertexCountsAttr().Get())
    points = c.GetPointsAttr().Get()
    assert sum(counts) == len(points), prim.GetPath()
    ctype, basis, wrap = c.GetTypeAttr().Get(), c.GetBasisAttr().Get(), c.GetWrapAttr().Get()
    minimum = 2 if ctype == "linear" else 4
    assert all(n >= minimum for n in counts), prim.GetPath()
    if ctype == "cubic" and basis == "bezier" and wrap == "nonperiodic":
        assert all((n - 4) % 3 == 0 for n in counts)
    widths = c.GetWidthsAttr().Get()
    interp = c.GetWidthsInterpolation()
    expected = {"constant": 1, "uniform": c.ComputeUniformDataSize(Usd.TimeCode.Default()),
                "vertex": c.ComputeVertexDataSize(Usd.TimeCode.Default()),
                "varying": c.ComputeVaryingDataSize(Usd.TimeCode.Default())}
    assert len(widths) == expected[interp], (prim.GetPath(), interp)


@pytest.mark.parametrize("name", ["fibers.usda", "threads.usda"])
def test_examples_are_valid(name):
    stage = Usd.Stage.Open(str(REPO / "examples" / name))
    assert UsdGeom.GetStageMetersPerUnit(stage) == pytest.approx(0.001)
    assert stage.GetDefaultPrim()
    mpu_um = UsdGeom.GetStageMetersPerUnit(stage) * 1e6  # micrometres per scene unit
    n = 0
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.BasisCurves):
            continue
        n += 1
        _check_curves_topology(prim)
        fp = FiberParams.from_prim(prim)
        widths = UsdGeom.BasisCurves(prim).GetWidthsAttr().Get()
        if prim.HasAPI("FiberYarnAPI"):
            dia_mm = A.yarn_diameter_mm(prim)
            assert all(w == pytest.approx(dia_mm * 1e-3 / UsdGeom.GetStageMetersPerUnit(stage), rel=1e-5) for w in widths)
        else:
            assert all(w * mpu_um == pytest.approx(fp.diameter, rel=1e-5) for w in widths), prim.GetPath()
    assert n >= (8 if name == "fibers.usda" else 4)
    if name == "fibers.usda":
        kinds = {FiberParams.from_prim(p).kind for p in stage.Traverse() if p.IsA(UsdGeom.BasisCurves)}
        assert kinds == {"polyester", "silk", "cotton", "mercerizedCotton", "wool"}
        user = stage.GetPrimAtPath("/Fibers/CottonUserSection")
        assert FiberParams.from_prim(user).profile_family == "user"
        deep = FiberParams.from_prim(stage.GetPrimAtPath("/Fibers/CottonDeep"))
        assert deep.depth_of_shade == pytest.approx(4.0)
        assert FiberParams.from_prim(stage.GetPrimAtPath("/Fibers/Cotton")).depth_of_shade == pytest.approx(1.0)
    else:
        yarns = {FiberParams.from_prim(p).kind for p in stage.Traverse() if p.HasAPI("FiberYarnAPI")}
        assert yarns == {"polyester", "cotton", "silk"}


def test_examples_are_current(tmp_path):
    # The checked-in .usda files are what make_examples.py writes.
    subprocess.run([sys.executable, str(REPO / "examples" / "make_examples.py"), str(tmp_path)],
                   check=True, cwd=REPO, capture_output=True)
    for name in ("fibers.usda", "threads.usda"):
        assert (tmp_path / name).read_text() == (REPO / "examples" / name).read_text(), name
