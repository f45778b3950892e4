"""The usdFiber value checks (validation.values) and the UsdValidation plugin around them.

Stages are built in memory; every check runs through ``check_stage``, i.e. through
``UsdValidation.ValidationContext(keywords=["usdFiber"])`` and the python plugin.
"""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

import usdfiber  # noqa: F401  (registers the schemas before any stage exists)
from pxr import Gf, Sdf, Usd, UsdGeom, UsdValidation, Vt

from usdfiber.validation import KEYWORD, PLUGIN_NAME, TimeSelection, plugin, values
from usdfiber.validation.problems import CHECKS, PrimCheck, Problem, Severity
from usdfiber.validation.runner import check_stage

REPO = Path(__file__).resolve().parents[2]
NAN, INF = float("nan"), float("inf")
T = Sdf.ValueTypeNames
FIBERS = "/World/Fibers"


# --------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------

def new_stage() -> Usd.Stage:
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 1e-3)  # millimetres: a 10 um fiber is 0.01 wide
    UsdGeom.Xform.Define(stage, "/World")
    return stage


def curves(stage: Usd.Stage, path: str = FIBERS, apis=("FiberAPI",), width: float = 0.01
           ) -> Usd.Prim:
    """A valid single-fiber BasisCurves prim with ``apis`` applied."""
    c = UsdGeom.BasisCurves.Define(stage, path)
    c.CreateBasisAttr("bspline")
    c.CreateCurveVertexCountsAttr([4])
    c.CreatePointsAttr([(0, 0, 0), (1, 1, 0), (2, 1, 0), (3, 0, 0)])
    c.CreateWidthsAttr([width])
    c.SetWidthsInterpolation(UsdGeom.Tokens.constant)
    prim = c.GetPrim()
    for api in apis:
        prim.ApplyAPI(api)
    return prim


def author(prim: Usd.Prim, name: str, value, type_name: Sdf.ValueTypeName | None = None):
    """Author ``value``: with the schema's type unless ``type_name`` forces another."""
    attr = prim.GetAttribute(name)
    if type_name is not None or not attr:
        attr = prim.CreateAttribute(name, type_name or T.Float)
    attr.Set(value)
    return attr


def fiber(**values_by_name) -> tuple[Usd.Stage, Usd.Prim]:
    """Stage with one FiberAPI prim authoring ``name=value`` (``__`` stands for ``:``)."""
    stage = new_stage()
    d = values_by_name.get("diameter")
    width = d / 1000 if isinstance(d, float) and 0 < d < 1e4 else 0.01  # um -> mm
    prim = curves(stage, width=width)
    for key, v in values_by_name.items():
        author(prim, "fiber:" + key.replace("__", ":"), v)
    return stage, prim


def codes(report, severity: Severity | None = None) -> set[tuple[str, str, str | None]]:
    return {(p.code, p.prim, p.attribute) for p in report.problems
            if severity is None or p.severity == severity}


def only(report, code: str) -> Problem:
    hits = [p for p in report.problems if p.code == code]
    assert len(hits) == 1, report.to_text()
    return hits[0]


# --------------------------------------------------------------------------------------
# Valid stages
# --------------------------------------------------------------------------------------

def test_valid_fiber_has_no_problems():
    stage, prim = fiber(kind="cotton", diameter=18.0, density=1.52, dye__class="reactive",
                        dye__extinction=Gf.Vec3f(0.001, 0.012, 0.012), dye__depthOfShade=2.0)
    author(prim, "fiber:ior:parallel", 1.578)
    author(prim, "fiber:roughness:ra", 14.0)
    curves(stage, "/World/Yarn", ("FiberAPI", "FiberYarnAPI"), width=0.4)
    report = check_stage(stage)
    assert report.problems == [], report.to_text()
    assert report.ok() and report.ok(warnings_as_errors=True)


def test_fallback_values_are_valid():
    stage = new_stage()
    curves(stage, apis=("FiberAPI",))
    curves(stage, "/World/Yarn", ("FiberAPI", "FiberYarnAPI"), width=0.4)
    assert check_stage(stage).problems == []


def test_boundary_values_are_valid():
    stage, prim = fiber(diameter=1000.0, density=5.0, ior__parallel=1.0,
                        ior__perpendicular=3.0, roughness__beta=60.0, cuticle__tilt=30.0,
                        dye__depthOfShade=4.0, profile__variantCount=64)
    author(prim, "fiber:dye:class", "reactive")
    author(prim, "fiber:dye:extinction", Gf.Vec3f(0.0, 0.005, 0.0158))
    prim.GetAttribute("widths").Set([1.0])  # 1000 um in mm
    yarn = curves(stage, "/World/Yarn", ("FiberAPI", "FiberYarnAPI"), width=0.4)
    author(yarn, "yarn:plies", 12)
    author(yarn, "yarn:fiber:migration", Gf.Vec2f(0.0, 2.0))
    author(yarn, "yarn:fiber:densityProfile", Gf.Vec2f(0.0, 0.0))
    errors = [p for p in check_stage(stage).problems if p.code != "WidthMismatch"]
    assert errors == []


def test_example_stages_have_no_errors():
    examples = sorted((REPO / "examples").glob("*.usda"))
    if not examples:
        pytest.skip("no examples/*.usda yet")
    for path in examples:
        report = check_stage(path)
        assert report.errors == [], report.to_text()


def test_authoring_presets_have_no_errors():
    authoring = pytest.importorskip("usdfiber.authoring")
    presets = pytest.importorskip("usdfiber.presets")
    stage = new_stage()
    for i, name in enumerate(sorted(presets.FIBER_PRESETS)):
        prim = curves(stage, f"/World/F{i}", apis=())
        authoring.apply_fiber(prim, name)
    report = check_stage(stage)
    assert [p for p in report.errors if p.code != "WidthMismatch"] == [], report.to_text()


# --------------------------------------------------------------------------------------
# Ranges, non-finite values, tokens, types
# --------------------------------------------------------------------------------------

OUT_OF_RANGE = [
    ("fiber:diameter", -5.0), ("fiber:diameter", 0.0), ("fiber:diameter", 1000.5),
    ("fiber:density", 0.0), ("fiber:density", 5.5),
    ("fiber:ior:parallel", 0.9), ("fiber:ior:parallel", 3.1),
    ("fiber:ior:perpendicular", 0.99),
    ("fiber:roughness:ra", -1.0), ("fiber:roughness:profileLength", 0.0),
    ("fiber:roughness:beta", 61.0), ("fiber:roughness:beta", -0.1),
    ("fiber:cuticle:tilt", 31.0), ("fiber:cuticle:spacing", 0.0),
    ("fiber:dye:depthOfShade", -1.0), ("fiber:dye:depthOfShade", 10.5),
    ("fiber:profile:variantCount", 0), ("fiber:profile:variantCount", 65),
    ("fiber:dye:extinction", Gf.Vec3f(-0.1, 0.01, 0.01)),
    ("fiber:dye:extinction", Gf.Vec3f(0.01, 11.0, 0.01)),
    ("fiber:dye:molarExtinction", Gf.Vec3f(0.0, 2e6, 0.0)),
    ("fiber:dye:molarMass", -1.0),
]


@pytest.mark.parametrize("name,value", OUT_OF_RANGE)
def test_out_of_range_is_an_error(name, value):
    stage = new_stage()
    prim = curves(stage)
    author(prim, name, value)
    p = only(check_stage(stage), "ValueOutOfRange")
    assert (p.severity, p.prim, p.attribute, p.time) == (Severity.ERROR, FIBERS, name, None)
    assert p.message.startswith(f"{name} = ") and "expected" in p.message


YARN_OUT_OF_RANGE = [
    ("yarn:plies", 0), ("yarn:plies", 13), ("yarn:fibersPerPly", 0),
    ("yarn:fibersPerPly", 2001), ("yarn:ply:twist", -1.0), ("yarn:fiber:twist", 101.0),
    ("yarn:ply:radius", 0.0), ("yarn:ply:radius", 11.0),
    ("yarn:ply:compression", Gf.Vec2f(0.0, 1.0)), ("yarn:ply:compression", Gf.Vec2f(1.0, 2.5)),
    ("yarn:fiber:migration", Gf.Vec2f(-0.1, 1.0)), ("yarn:fiber:migrationPeriod", 0.0),
    ("yarn:fiber:densityProfile", Gf.Vec2f(0.5, 2.0)),
    ("yarn:fiber:densityProfile", Gf.Vec2f(-0.1, 2.0)),
    ("yarn:fiber:densityProfile", Gf.Vec2f(0.1, -1.0)),
    ("yarn:flyaway:hairDensity", -1.0), ("yarn:flyaway:loopDensity", 1001.0),
    ("yarn:flyaway:hairLength", Gf.Vec2f(0.5, -0.1)),
    ("yarn:ply:linearDensity", -1.0), ("yarn:fiber:stapleLength", 101.0),
]


@pytest.mark.parametrize("name,value", YARN_OUT_OF_RANGE)
def test_yarn_out_of_range_is_an_error(name, value):
    stage = new_stage()
    prim = curves(stage, "/World/Yarn", ("FiberAPI", "FiberYarnAPI"), width=0.4)
    author(prim, name, value)
    report = check_stage(stage)
    p = only(report, "ValueOutOfRange")
    assert (p.severity, p.prim, p.attribute) == (Severity.ERROR, "/World/Yarn", name)


def test_message_says_value_and_expectation():
    stage, _ = fiber(diameter=-5.0)
    p = only(check_stage(stage), "ValueOutOfRange")
    assert p.message == "fiber:diameter = -5 um; expected a diameter in (0, 1000] um"


@pytest.mark.parametrize("name,value", [
    ("fiber:diameter", NAN), ("fiber:density", INF), ("fiber:rotation", -INF),
    ("fiber:dye:extinction", Gf.Vec3f(0.01, NAN, 0.01)),
])
def test_non_finite_is_an_error(name, value):
    stage = new_stage()
    author(curves(stage), name, value)
    p = only(check_stage(stage), "NonFiniteValue")
    assert (p.severity, p.attribute) == (Severity.ERROR, name)


def test_non_finite_in_arrays():
    stage, prim = fiber(dye__class="custom", dye__extinctionSource="spectrum")
    author(prim, "fiber:dye:spectrum:wavelengths", Vt.FloatArray([400, 550, 700]))
    author(prim, "fiber:dye:spectrum:values", Vt.FloatArray([0.01, NAN, 0.01]))
    p = only(check_stage(stage), "NonFiniteValue")
    assert p.attribute == "fiber:dye:spectrum:values" and "index 1" in p.message


@pytest.mark.parametrize("name,value", [
    ("fiber:kind", "nylon"), ("fiber:profile", "square"), ("fiber:ior:effective", "max"),
    ("fiber:roughness:source", "rz"), ("fiber:dye:class", "acid"),
    ("fiber:dye:extinctionSource", "perLitre"),
])
def test_unknown_token_lists_allowed_tokens(name, value):
    stage = new_stage()
    author(curves(stage), name, value)
    p = only(check_stage(stage), "UnknownToken")
    assert (p.severity, p.attribute) == (Severity.ERROR, name)
    allowed = values.schema_defs()[name].allowed
    assert p.message == f'{name} = "{value}"; expected one of: {", ".join(allowed)}'


def test_unknown_yarn_token():
    stage = new_stage()
    prim = curves(stage, "/World/Yarn", ("FiberAPI", "FiberYarnAPI"), width=0.4)
    author(prim, "yarn:ply:twistDirection", "X")
    assert only(check_stage(stage), "UnknownToken").message.endswith("expected one of: S, Z")


@pytest.mark.parametrize("name,value,type_name,authored", [
    ("fiber:diameter", "10", T.String, "string"),
    ("fiber:density", 1, T.Int, "int"),
    ("fiber:rotation", 1.0, T.Double, "double"),
    ("fiber:kind", "wool", T.String, "string"),        # a token authored as string
    ("fiber:dye:extinction", Gf.Vec3d(0.01, 0.01, 0.01), T.Double3, "double3"),
    ("fiber:profile:variantCount", 4.0, T.Float, "float"),
])
def test_wrong_value_type(name, value, type_name, authored):
    stage = new_stage()
    curves(stage)
    # The Usd API converts to the schema's type, so author the spec directly as a file would.
    spec = Sdf.AttributeSpec(stage.GetRootLayer().GetPrimAtPath(FIBERS), name, type_name)
    spec.default = value
    report = check_stage(stage)
    hits = [p for p in report.problems if p.code == "WrongValueType"]
    assert [(p.attribute, p.severity) for p in hits] == [(name, Severity.ERROR)]
    expected_type = values.schema_defs()[name].type_name
    assert hits[0].message == f"{name} is authored as {authored}; expected {expected_type}"
    # No range or token verdict on a value of the wrong type.
    assert not [p for p in report.problems
                if p.attribute == name and p.code != "WrongValueType"]


# --------------------------------------------------------------------------------------
# Cross-attribute checks
# --------------------------------------------------------------------------------------

def test_depth_of_shade_beyond_industry_range_is_a_warning():
    stage, _ = fiber(dye__class="reactive", dye__extinction=Gf.Vec3f(0.001, 0.01, 0.01),
                     dye__depthOfShade=6.0)
    report = check_stage(stage)
    p = only(report, "BeyondIndustryRange")
    assert p.severity == Severity.WARNING and report.errors == []
    assert "beyond the industry range" in p.message


def test_depth_of_shade_without_dye_is_ignored_with_a_warning():
    stage, _ = fiber(dye__depthOfShade=2.0)
    p = only(check_stage(stage), "IgnoredValue")
    assert (p.severity, p.attribute) == (Severity.WARNING, "fiber:dye:depthOfShade")


@pytest.mark.parametrize("cls,ext,warn", [
    ("reactive", (0.001, 0.012, 0.012), False), ("reactive", (0.001, 0.02, 0.02), True),
    ("reactive", (0.001, 0.004, 0.004), True), ("disperse", (0.01, 0.2, 0.2), False),
    ("disperse", (0.01, 0.3, 0.3), True), ("disperse", (0.01, 0.04, 0.02), True),
    ("custom", (0.01, 5.0, 5.0), False),
])
def test_extinction_against_dye_class_range(cls, ext, warn):
    stage, _ = fiber(dye__class=cls, dye__extinction=Gf.Vec3f(*ext), dye__depthOfShade=1.0)
    report = check_stage(stage)
    got = [p for p in report.problems if p.code == "ExtinctionOutsideDyeRange"]
    assert bool(got) == warn, report.to_text()
    assert all(p.severity == Severity.WARNING for p in got)


def test_molar_source_needs_a_molar_mass():
    stage, prim = fiber(dye__class="reactive", dye__extinctionSource="molar",
                        dye__molarExtinction=Gf.Vec3f(100, 10000, 10000))
    p = only(check_stage(stage), "ValueOutOfRange")
    assert p.attribute == "fiber:dye:molarMass" and '"molar"' in p.message
    author(prim, "fiber:dye:molarMass", 1000.0)  # 10000 / 1000 / 1000 = 0.01 L/(mg cm)
    assert check_stage(stage).problems == []


@pytest.mark.parametrize("wl,vals,code", [
    ([400, 500, 600, 700], [0.01, 0.02, 0.01], "SpectrumLengthMismatch"),
    ([400, 600, 500, 700], [0.01, 0.02, 0.01, 0.0], "SpectrumNotIncreasing"),
    ([400, 500, 500, 700], [0.01, 0.02, 0.01, 0.0], "SpectrumNotIncreasing"),
    ([420, 500, 700], [0.01, 0.02, 0.01], "SpectrumIncomplete"),
    ([400, 500, 650], [0.01, 0.02, 0.01], "SpectrumIncomplete"),
    ([], [], "SpectrumIncomplete"),
])
def test_spectrum_problems(wl, vals, code):
    stage, prim = fiber(dye__class="custom", dye__extinctionSource="spectrum",
                        dye__depthOfShade=1.0)
    author(prim, "fiber:dye:spectrum:wavelengths", Vt.FloatArray(wl))
    author(prim, "fiber:dye:spectrum:values", Vt.FloatArray(vals))
    p = only(check_stage(stage), code)
    assert p.severity == Severity.ERROR


def test_valid_spectrum_is_checked_against_the_class_range():
    stage, prim = fiber(dye__class="reactive", dye__extinctionSource="spectrum",
                        dye__depthOfShade=1.0)
    author(prim, "fiber:dye:spectrum:wavelengths", Vt.FloatArray([380, 550, 720]))
    author(prim, "fiber:dye:spectrum:values", Vt.FloatArray([0.001, 0.012, 0.002]))
    assert check_stage(stage).problems == []
    author(prim, "fiber:dye:spectrum:values", Vt.FloatArray([0.001, 0.2, 0.002]))
    assert only(check_stage(stage), "ExtinctionOutsideDyeRange").attribute == \
        "fiber:dye:spectrum:values"


def test_cuticle_height_at_most_a_quarter_of_the_diameter():
    stage, prim = fiber(diameter=24.0, cuticle__height=6.0)
    prim.GetAttribute("widths").Set([0.024])
    assert check_stage(stage).problems == []
    author(prim, "fiber:cuticle:height", 6.5)
    p = only(check_stage(stage), "ValueOutOfRange")
    assert p.attribute == "fiber:cuticle:height" and "= [0, 6] um" in p.message


def test_migration_min_above_max():
    stage = new_stage()
    prim = curves(stage, "/World/Yarn", ("FiberAPI", "FiberYarnAPI"), width=0.4)
    author(prim, "yarn:fiber:migration", Gf.Vec2f(1.2, 0.8))
    p = only(check_stage(stage), "InvertedRange")
    assert p.message == "yarn:fiber:migration = (1.2, 0.8); expected rho_min <= rho_max"


def test_custom_kind_needs_a_profile():
    stage, prim = fiber(kind="custom")
    assert only(check_stage(stage), "ProfileRequired").attribute == "fiber:profile"
    author(prim, "fiber:profile", "round")
    assert check_stage(stage).problems == []


def test_user_profile_sources():
    stage, prim = fiber(profile="user")
    assert only(check_stage(stage), "MissingProfileSources").attribute == \
        "fiber:profile:sources"

    rel = prim.GetRelationship("fiber:profile:sources")
    stage.DefinePrim("/World/Plain", "Scope")
    rel.SetTargets([Sdf.Path("/World/Plain"), Sdf.Path("/World/Nowhere")])
    got = codes(check_stage(stage))
    assert got == {("ProfileSourceNotProfile", FIBERS, "fiber:profile:sources"),
                   ("ProfileSourceMissing", FIBERS, "fiber:profile:sources")}

    profile = stage.DefinePrim("/World/Section", "Scope")
    profile.ApplyAPI("FiberProfileAPI")
    profile.GetAttribute("fiberProfile:points").Set(
        Vt.Vec2fArray([(0, 0), (10, 0), (10, 8), (0, 8)]))
    profile.GetAttribute("fiberProfile:loopVertexCounts").Set(Vt.IntArray([4]))
    rel.SetTargets([profile.GetPath()])
    assert check_stage(stage).problems == []


# --------------------------------------------------------------------------------------
# Where the API is, unknown attributes
# --------------------------------------------------------------------------------------

def test_fiber_and_yarn_api_only_on_basis_curves():
    stage = new_stage()
    mesh = stage.DefinePrim("/World/Cloth", "Mesh")
    mesh.ApplyAPI("FiberAPI")
    mesh.ApplyAPI("FiberYarnAPI")
    xf = stage.DefinePrim("/World/Group", "Xform")
    xf.ApplyAPI("FiberProfileAPI")  # a profile can be any prim
    xf.GetAttribute("fiberProfile:points").Set(Vt.Vec2fArray([(0, 0), (1, 0), (0, 1)]))
    xf.GetAttribute("fiberProfile:loopVertexCounts").Set(Vt.IntArray([3]))
    # The renderer's own checks are left out: the empty mesh has no points to render either.
    report = check_stage(stage, bridges=False)
    assert codes(report) == {("NotBasisCurves", "/World/Cloth", None)}
    assert ("MeshInvalid", "/World/Cloth", "points") in codes(check_stage(stage))
    msgs = sorted(p.message for p in report.problems)
    assert msgs[0].startswith('FiberAPI is applied to a "Mesh" prim')
    assert msgs[1].startswith('FiberYarnAPI is applied to a "Mesh" prim')


def test_yarn_without_fiber_api_is_a_warning():
    stage = new_stage()
    curves(stage, "/World/Yarn", ("FiberYarnAPI",), width=0.4)
    p = only(check_stage(stage), "YarnWithoutFiberAPI")
    assert (p.severity, p.attribute) == (Severity.WARNING, None)


def test_misspelled_attribute_is_a_warning_with_a_suggestion():
    stage, prim = fiber()
    author(prim, "fiber:diamter", 12.0)
    p = only(check_stage(stage), "UnknownAttribute")
    assert p.severity == Severity.WARNING and p.message.endswith("did you mean fiber:diameter?")


def test_fiber_attributes_without_the_api():
    stage = new_stage()
    prim = curves(stage, apis=())
    author(prim, "fiber:diameter", 10.0)
    p = only(check_stage(stage), "APINotApplied")
    assert (p.severity, p.attribute) == (Severity.WARNING, "fiber:diameter")


# --------------------------------------------------------------------------------------
# Time samples
# --------------------------------------------------------------------------------------

def sampled_shade() -> Usd.Stage:
    stage, prim = fiber(dye__class="reactive", dye__extinction=Gf.Vec3f(0.001, 0.01, 0.01))
    attr = prim.GetAttribute("fiber:dye:depthOfShade")
    attr.Set(1.0)                 # default: valid
    attr.Set(2.0, 1.0)
    attr.Set(12.0, 5.0)           # out of range at time 5
    attr.Set(NAN, 7.0)            # non-finite at time 7
    return stage


def test_every_time_sample_is_checked_and_reported_with_its_time():
    report = check_stage(sampled_shade())
    got = sorted((p.code, p.time) for p in report.problems)
    assert got == [("NonFiniteValue", 7.0), ("ValueOutOfRange", 5.0)]
    assert "at time 5" in only(report, "ValueOutOfRange").message


@pytest.mark.parametrize("time,expected", [
    (1.0, []),
    (2.0, [("BeyondIndustryRange", 2.0)]),   # linear interpolation: 4.5 %
    (4.5, [("ValueOutOfRange", 4.5)]),       # 10.75 %
    (5.0, [("ValueOutOfRange", 5.0)]),
    (6.0, [("NonFiniteValue", 6.0)]),        # interpolated towards NaN
    (7.0, [("NonFiniteValue", 7.0)]),
])
def test_time_option_checks_the_value_resolved_at_that_time(time, expected):
    report = check_stage(sampled_shade(), time=time)
    assert sorted((p.code, p.time) for p in report.problems) == expected


def test_bad_default_with_good_samples():
    stage, prim = fiber()
    attr = prim.GetAttribute("fiber:diameter")
    attr.Set(-1.0)
    attr.Set(10.0, 1.0)
    report = check_stage(stage)
    assert [(p.code, p.time) for p in report.problems] == [("ValueOutOfRange", None)]


def test_cross_checks_follow_time_samples():
    stage, prim = fiber(dye__class="none")
    prim.GetAttribute("fiber:dye:depthOfShade").Set(0.0, 1.0)
    prim.GetAttribute("fiber:dye:depthOfShade").Set(3.0, 2.0)
    report = check_stage(stage)
    assert [(p.code, p.time) for p in report.problems] == [("IgnoredValue", 2.0)]


# --------------------------------------------------------------------------------------
# Composition: layers, classes, instances
# --------------------------------------------------------------------------------------

def test_problem_names_the_layer_with_the_strongest_opinion(tmp_path):
    weak = Sdf.Layer.CreateNew(str(tmp_path / "weak.usda"))
    strong = Sdf.Layer.CreateNew(str(tmp_path / "strong.usda"))
    root = Sdf.Layer.CreateNew(str(tmp_path / "root.usda"))
    root.subLayerPaths.append(strong.identifier)
    root.subLayerPaths.append(weak.identifier)
    stage = Usd.Stage.Open(root)
    stage.SetEditTarget(Usd.EditTarget(weak))
    UsdGeom.Xform.Define(stage, "/World")
    prim = curves(stage)
    author(prim, "fiber:diameter", -5.0)
    author(prim, "fiber:density", -1.0)
    stage.SetEditTarget(Usd.EditTarget(strong))
    author(prim, "fiber:density", -2.0)
    # A stronger opinion without a value does not own the value.
    prim.GetAttribute("fiber:diameter").SetDocumentation("measured by SEM")
    report = check_stage(stage)
    layers = {p.attribute: p.layer for p in report.problems}
    assert layers == {"fiber:diameter": weak.identifier, "fiber:density": strong.identifier}
    assert "-2" in [p for p in report.problems if p.attribute == "fiber:density"][0].message


def test_class_prims_are_not_checked_but_what_inherits_them_is():
    stage = new_stage()
    cls = stage.CreateClassPrim("/_Template")
    cls.SetTypeName("BasisCurves")
    cls.ApplyAPI("FiberAPI")
    author(cls, "fiber:density", 0.0)
    report = check_stage(stage)
    assert report.problems == []
    prim = curves(stage, apis=())
    prim.GetInherits().AddInherit("/_Template")
    assert codes(check_stage(stage)) == {("ValueOutOfRange", FIBERS, "fiber:density")}


def test_instance_proxies_are_checked():
    stage = new_stage()
    src = curves(stage, "/Asset/Fibers")
    asset = stage.GetPrimAtPath("/Asset")
    asset.SetSpecifier(Sdf.SpecifierOver)  # only reachable through the instances
    author(src, "fiber:roughness:beta", 70.0)
    for name in ("A", "B"):
        inst = stage.DefinePrim(f"/World/{name}", "Xform")
        inst.GetReferences().AddInternalReference(asset.GetPath())
        inst.SetInstanceable(True)
    report = check_stage(stage)
    assert {p.prim for p in report.problems} == {"/World/A/Fibers", "/World/B/Fibers"}


def test_inactive_prims_are_not_checked():
    stage, prim = fiber(diameter=-1.0)
    prim.SetActive(False)
    assert check_stage(stage).problems == []


def test_equal_value_sets_share_findings_but_not_prims():
    stage = new_stage()
    for i in range(3):
        author(curves(stage, f"/World/F{i}"), "fiber:diameter", -5.0)
    report = check_stage(stage)
    assert sorted(p.prim for p in report.problems) == [f"/World/F{i}" for i in range(3)]
    assert len({p.message for p in report.problems}) == 1


# --------------------------------------------------------------------------------------
# The UsdValidation plugin
# --------------------------------------------------------------------------------------

def test_plugin_info_declares_exactly_the_registered_checks():
    declared = plugin.declared_validators()
    plugin.load_check_modules()
    assert sorted(declared) == sorted(CHECKS), (
        "plugInfo.json is stale: run python -m usdfiber.validation.plugin")
    for name, entry in declared.items():
        assert entry["doc"] == CHECKS[name].doc
        assert entry["keywords"] == list(CHECKS[name].keywords)
        assert entry["isTimeDependent"] is True
    assert json.loads(plugin.PLUGIN_INFO.read_text()) == plugin.plugin_info()


def test_every_check_is_a_usd_validator_with_the_keyword():
    registry = UsdValidation.ValidationRegistry()
    for name in CHECKS:
        meta = registry.GetValidatorMetadata(f"{PLUGIN_NAME}:{name}")
        assert meta is not None, name
        assert KEYWORD in meta.GetKeywords()
        assert registry.HasValidator(f"{PLUGIN_NAME}:{name}")
        assert meta.plugin is not None and meta.plugin.name == PLUGIN_NAME  # from plugInfo
    names = {m.name for m in registry.GetValidatorMetadataForKeyword(KEYWORD)}
    assert names == {f"{PLUGIN_NAME}:{n}" for n in CHECKS}


def test_validation_errors_carry_type_sites_and_code():
    stage, _ = fiber(diameter=-5.0, dye__depthOfShade=2.0)
    ctx = UsdValidation.ValidationContext(keywords=[KEYWORD])
    errors = ctx.Validate(stage)
    by_name = {e.GetName(): e for e in errors}
    err = by_name["ValueOutOfRange"]
    assert err.GetType() == UsdValidation.ValidationErrorType.Error
    assert err.GetIdentifier() == "usdFiber:fiberSchema.ValueOutOfRange"
    assert err.GetMessage().startswith("ValueOutOfRange: fiber:diameter = -5 um")
    (site,) = err.GetSites()
    assert site.IsProperty()
    assert site.GetProperty().GetPath() == Sdf.Path(FIBERS + ".fiber:diameter")
    assert site.GetLayer() == stage.GetRootLayer()
    assert by_name["IgnoredValue"].GetType() == UsdValidation.ValidationErrorType.Warn


def test_message_round_trip():
    p = Problem("ValueOutOfRange", Severity.ERROR, "/A", "fiber:x", "a: b; c", "l", 2.5)
    stage = Usd.Stage.CreateInMemory()  # /A does not exist: prim and attribute go in the text
    back = plugin.from_validation_error(plugin.to_validation_error(p, stage))
    assert back == Problem("ValueOutOfRange", Severity.ERROR, "/A", "fiber:x", "a: b; c",
                           None, 2.5)


def test_a_failing_check_becomes_a_problem():
    def broken(prim):
        raise RuntimeError("boom")

    task = plugin._make_task(PrimCheck("broken", "doc", broken))
    stage, prim = fiber()
    (err,) = task(prim, UsdValidation.ValidationTimeRange())
    p = plugin.from_validation_error(err)
    assert (p.code, p.severity, p.prim) == ("CheckFailed", Severity.ERROR, FIBERS)
    assert "RuntimeError: boom" in p.message


def test_the_task_skips_class_prims():
    stage = new_stage()
    cls = stage.CreateClassPrim("/_T")
    task = plugin._make_task(PrimCheck("all", "doc", lambda prim: [
        Problem("X", Severity.ERROR, str(prim.GetPath()), None, "x")]))
    assert task(cls, UsdValidation.ValidationTimeRange()) == []


def test_time_selection_from_the_time_range():
    sel = plugin._selection(UsdValidation.ValidationTimeRange(Usd.TimeCode(3)))
    assert sel == TimeSelection(3.0, 3.0, False) and sel.single == 3.0
    assert plugin._selection(UsdValidation.ValidationTimeRange()).everything


PLUGIN_SCRIPT = r"""
import sys
{imports}
from pxr import Usd, UsdGeom, UsdValidation
stage = Usd.Stage.CreateInMemory()
c = UsdGeom.BasisCurves.Define(stage, "/F")
c.GetPrim().ApplyAPI("FiberAPI")
c.GetPrim().GetAttribute("fiber:diameter").Set(-5.0)
assert "usdfiber.validation.plugin" not in sys.modules
errors = UsdValidation.ValidationContext(keywords=["usdFiber"]).Validate(stage)
print(sorted(e.GetIdentifier() for e in errors if "fiberSchema" in e.GetIdentifier()))
print("usdfiber.validation.plugin" in sys.modules)
"""


def _run_plugin_script(imports: str, cwd: Path) -> list[str]:
    code = PLUGIN_SCRIPT.format(imports=imports)
    out = subprocess.run([sys.executable, "-c", code], cwd=cwd, capture_output=True,
                         text=True, env={"PYTHONPATH": str(REPO), "PATH": ""}, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stderr == "", out.stderr
    return out.stdout.splitlines()


def test_usd_loads_the_python_plugin_on_demand(tmp_path):
    # A fresh process that never imports the plugin module: USD's Plug system loads it
    # (``import usdFiber``) when the context asks for the usdFiber validators.
    lines = _run_plugin_script("import usdfiber\nimport usdfiber.validation", tmp_path)
    assert lines == ["['usdFiber:fiberSchema.ValueOutOfRange']", "True"]


def test_import_usdfiber_alone_is_enough(tmp_path):
    probe = subprocess.run(
        [sys.executable, "-c", "import sys, usdfiber; print('usdfiber.validation' in sys.modules)"],
        env={"PYTHONPATH": str(REPO), "PATH": ""}, capture_output=True, text=True, timeout=120)
    if probe.stdout.strip() != "True":
        pytest.skip("usdfiber/__init__.py does not import usdfiber.validation yet, so USD "
                    "cannot resolve `import usdFiber` after `import usdfiber` alone")
    lines = _run_plugin_script("import usdfiber", tmp_path)
    assert lines == ["['usdFiber:fiberSchema.ValueOutOfRange']", "True"]


# --------------------------------------------------------------------------------------
# Formatting helpers
# --------------------------------------------------------------------------------------

def test_interval_text_and_membership():
    iv = values.Interval(0, 1000, lo_open=True)
    assert str(iv) == "(0, 1000]" and 1000 in iv and 0 not in iv and 1e-6 in iv
    assert str(values.Interval(0, math.inf)) == "[0, inf)"
