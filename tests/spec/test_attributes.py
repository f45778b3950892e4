"""One source of truth: the schema's names and ranges, and the code that must follow them.

The ranges are read here straight from ``schema/schema.usda`` (not through the generated
module), and every validator, reader and the authoring API is checked against them by
behaviour: a value just outside a valid range is reported, one on its edge is not. A schema
change that the code does not follow fails here.
"""
from __future__ import annotations

import ast
import math
import pickle
import re
from pathlib import Path

import pytest

import usdfiber  # noqa: F401  (registers the schemas)
from pxr import Gf, Sdf, Usd, UsdGeom

from usdfiber import authoring
from usdfiber.errors import PrimError
from usdfiber.geometry.curves import CurveError, curves_from_prim
from usdfiber.spec import generate
from usdfiber.spec.attributes import Fiber, Interval, Profile, Yarn, attribute, attributes, parse_interval
from usdfiber.spec.fiber import FiberParams, FiberParamsError
from usdfiber.spec.schema_data import PROPERTIES
from usdfiber.spec.yarn import YarnError, YarnParams
from usdfiber.validation import values

ROOT = Path(__file__).resolve().parents[2]
SCHEMA = ROOT / "schema" / "schema.usda"


def schema_facts() -> dict[str, dict]:
    """Each property's customData "usdFiber", read from schema.usda with Sdf."""
    layer = Sdf.Layer.OpenAsAnonymous(str(SCHEMA))
    out = {}
    for api in PROPERTIES:
        for prop in layer.GetPrimAtPath(f"/{api}").properties:
            cd = dict(prop.customData)
            out[prop.name] = dict(cd.get("usdFiber", {}))
    return out


FACTS = schema_facts()
RANGED = sorted(n for n, f in FACTS.items() if "validRange" in f)


# --------------------------------------------------------------------------------------
# The generated module and the registry follow schema.usda
# --------------------------------------------------------------------------------------


def test_generated_module_is_current():
    assert generate.main(["--check"]) == 0, "run python -m usdfiber.spec.generate"


def test_stale_generated_module_is_detected(tmp_path):
    text = SCHEMA.read_text()
    assert 'string validRange = "(0, 1000]"' in text
    stale = tmp_path / "schema.usda"
    stale.write_text(text.replace('string validRange = "(0, 1000]"', 'string validRange = "(0, 900]"', 1))
    assert generate.render(stale) != generate.render(SCHEMA)


def test_names_match_the_registry_and_the_schema():
    layer = Sdf.Layer.OpenAsAnonymous(str(SCHEMA))
    reg = Usd.SchemaRegistry()
    for api, cls in ((Fiber.API, Fiber), (Yarn.API, Yarn), (Profile.API, Profile)):
        in_schema = [p.name for p in layer.GetPrimAtPath(f"/{api}").properties]
        registered = set(reg.FindAppliedAPIPrimDefinition(api).GetPropertyNames())
        constants = {v for k, v in vars(cls).items() if k.isupper() and k != "API"}
        assert list(PROPERTIES[api]) == in_schema
        assert constants == set(in_schema) == registered, api


def test_specs_carry_the_schema_facts():
    for name, facts in FACTS.items():
        spec = attribute(name)
        assert spec.valid == (parse_interval(facts["validRange"]) if "validRange" in facts else None)
        assert spec.industry == (parse_interval(facts["industryRange"])
                                 if "industryRange" in facts else None)
        assert spec.unit == facts.get("unit", "")
    assert attribute(Fiber.DYE_DEPTH_OF_SHADE).industry == Interval(0, 4)
    assert str(parse_interval("(0, 1000]")) == "(0, 1000]" and str(parse_interval("[0, inf)")) == "[0, inf)"
    with pytest.raises(ValueError):
        parse_interval("0..1000")


# --------------------------------------------------------------------------------------
# The validators and the readers apply the schema's ranges
# --------------------------------------------------------------------------------------


def _edges(rng: Interval, integer: bool) -> tuple[list[float], list[float]]:
    """(values just outside, values on or just inside the edges) of ``rng``."""
    out, inside = [], []
    for edge, is_open, sign in ((rng.lo, rng.lo_open, -1), (rng.hi, rng.hi_open, 1)):
        if math.isinf(edge):
            continue
        step = 1 if integer else max(1e-3 * abs(edge), 1e-3)
        out.append(edge if is_open else edge + sign * step)
        inside.append(edge - sign * step if is_open else edge)
    return out, inside


def _value(spec, x: float, component: int | None = None, inner: float | None = None):
    t = spec.type_name
    if t == "int":
        return int(x)
    if t in ("color3f", "float2"):
        n = 3 if t == "color3f" else 2
        comps = [x] * n
        if component is not None:
            comps = [inner] * n
            comps[component] = x
        return Gf.Vec3f(*comps) if n == 3 else Gf.Vec2f(*comps)
    if t.endswith("[]"):
        return [x]
    return float(x)


_STAGES: list = []  # the stages of the prims below stay open for the test run


def _stage_prim():
    stage = Usd.Stage.CreateInMemory()
    _STAGES.append(stage)
    prim = UsdGeom.BasisCurves.Define(stage, "/F").GetPrim()
    prim.ApplyAPI(Fiber.API)
    prim.ApplyAPI(Yarn.API)
    return prim


def _range_problems(name: str, value) -> list:
    prim = _stage_prim()
    spec = attribute(name)
    when = FACTS[name].get("validWhen")
    if when:
        prim.CreateAttribute(when[0], Sdf.ValueTypeNames.Find(attribute(when[0]).type_name)).Set(when[1])
    if name in (Fiber.ROUGHNESS_RA, Fiber.ROUGHNESS_PROFILE_LENGTH):
        # The attribute's own range only: beta = arctan(Ra / l), checked against beta's range
        # while the source is "ra", has its own test (test_check_render_defects).
        prim.CreateAttribute(Fiber.ROUGHNESS_SOURCE, Sdf.ValueTypeNames.Token).Set("beta")
    if name == Fiber.DYE_SPECTRUM_VALUES or name == Fiber.DYE_SPECTRUM_WAVELENGTHS:
        other = Fiber.DYE_SPECTRUM_WAVELENGTHS if name == Fiber.DYE_SPECTRUM_VALUES else Fiber.DYE_SPECTRUM_VALUES
        prim.CreateAttribute(other, Sdf.ValueTypeNames.FloatArray).Set([1.0])
    prim.CreateAttribute(name, Sdf.ValueTypeNames.Find(spec.type_name)).Set(value)
    return [p for p in values.check_fiber_schema(prim)
            if p.attribute == name and p.code in ("ValueOutOfRange", "NonFiniteValue")]


@pytest.mark.parametrize("name", RANGED)
def test_validators_apply_the_schema_range(name):
    spec = attribute(name)
    rng = parse_interval(FACTS[name]["validRange"])
    outside, inside = _edges(rng, spec.type_name == "int")
    for x in outside:
        assert _range_problems(name, _value(spec, x)), f"{name} = {x} outside {rng} not reported"
    for x in inside:
        assert not _range_problems(name, _value(spec, x)), f"{name} = {x} inside {rng} reported"


@pytest.mark.parametrize("name", sorted(n for n, f in FACTS.items() if "componentRanges" in f))
def test_validators_apply_the_schema_component_ranges(name):
    spec = attribute(name)
    ranges = [parse_interval(r) for r in FACTS[name]["componentRanges"]]
    inner = [r.lo if not r.lo_open else r.lo + 1e-3 for r in ranges]
    for i, rng in enumerate(ranges):
        outside, inside = _edges(rng, False)
        ok = inner[1 - i]
        for x in outside:
            assert _range_problems(name, _value(spec, x, i, ok)), (name, i, x)
        for x in inside:
            assert not _range_problems(name, _value(spec, x, i, ok)), (name, i, x)


def test_validators_apply_the_schema_industry_and_relative_ranges():
    prim = _stage_prim()
    hi = parse_interval(FACTS[Fiber.DYE_DEPTH_OF_SHADE]["industryRange"]).hi
    prim.CreateAttribute(Fiber.DYE_CLASS, Sdf.ValueTypeNames.Token).Set("reactive")
    dos = prim.CreateAttribute(Fiber.DYE_DEPTH_OF_SHADE, Sdf.ValueTypeNames.Float)
    for x, warned in ((hi, False), (hi + 0.01, True)):
        dos.Set(x)
        codes = {p.code for p in values.check_fiber_schema(prim) if p.attribute == Fiber.DYE_DEPTH_OF_SHADE}
        assert ("BeyondIndustryRange" in codes) == warned, (x, codes)
    facts = FACTS[Fiber.CUTICLE_HEIGHT]
    of, factor = facts["validMaxOf"], float(facts["validMaxFactor"])
    prim.CreateAttribute(of, Sdf.ValueTypeNames.Float).Set(20.0)
    h = prim.CreateAttribute(Fiber.CUTICLE_HEIGHT, Sdf.ValueTypeNames.Float)
    for x, bad in ((20.0 * factor, False), (20.0 * factor + 0.01, True)):
        h.Set(x)
        codes = {p.code for p in values.check_fiber_schema(prim) if p.attribute == Fiber.CUTICLE_HEIGHT}
        assert ("ValueOutOfRange" in codes) == bad, (x, codes)
    for cls, text in FACTS[Fiber.DYE_CLASS]["industryExtinctionRange"].items():
        rng = parse_interval(text)
        prim.GetAttribute(Fiber.DYE_CLASS).Set(cls)
        ext = prim.CreateAttribute(Fiber.DYE_EXTINCTION, Sdf.ValueTypeNames.Color3f)
        for x, warned in ((rng.hi, False), (rng.hi * 1.01, True), (rng.lo * 0.99, True)):
            ext.Set(Gf.Vec3f(x, x, x))
            codes = {p.code for p in values.check_fiber_schema(prim)}
            assert ("ExtinctionOutsideDyeRange" in codes) == warned, (cls, x)


YARN_RANGED = [n for n in RANGED if n.startswith("yarn:")]


@pytest.mark.parametrize("name", YARN_RANGED)
def test_yarn_reader_applies_the_schema_range(name):
    spec = attribute(name)
    rng = parse_interval(FACTS[name]["validRange"])
    outside, inside = _edges(rng, spec.type_name == "int")

    def read(x):
        v = _value(spec, x)
        if name == Yarn.FIBER_MIGRATION:  # rho_min <= rho_max: keep the pair ordered
            v = (x, 2.0) if x < 1 else (1.0, x)
        return YarnParams.from_attributes({name: v}, 0.001)

    for x in outside:
        with pytest.raises(YarnError) as info:
            read(x)
        assert info.value.attribute == name
    for x in inside:
        read(x)


# --------------------------------------------------------------------------------------
# Authoring and the code use the schema's names
# --------------------------------------------------------------------------------------


def test_authoring_names_cover_the_schema():
    fiber = set(authoring.FIBER_NAMES.values()) | {Fiber.PROFILE_SOURCES}  # profile_sources
    assert fiber == set(PROPERTIES[Fiber.API])
    assert set(authoring.YARN_NAMES.values()) == set(PROPERTIES[Yarn.API])
    stage = Usd.Stage.CreateInMemory()
    prof = authoring.define_profile(stage, "/P", [[(0, 0), (1, 0), (0, 1)]])
    assert {a.GetName() for a in prof.GetAuthoredAttributes()} == set(PROPERTIES[Profile.API])


_NAME = re.compile(r"^(fiber|yarn|fiberProfile):[A-Za-z:]+$")


def test_attribute_names_in_code_exist_in_the_schema():
    known = set(attributes())
    unknown = []
    for path in sorted((ROOT / "usdfiber").rglob("*.py")) + sorted((ROOT / "translators").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and _NAME.match(node.value):
                if node.value not in known:
                    unknown.append(f"{path.relative_to(ROOT)}:{node.lineno}: {node.value}")
    assert not unknown, "names not in schema/schema.usda:\n" + "\n".join(unknown)


# --------------------------------------------------------------------------------------
# One prim-error type
# --------------------------------------------------------------------------------------


def test_prim_errors_name_file_prim_and_attribute(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    stage = Usd.Stage.CreateNew(str(tmp_path / "cloth.usda"))
    prim = UsdGeom.BasisCurves.Define(stage, "/Cloth/Fibers").GetPrim()
    authoring.apply_fiber(prim, "cotton", molar_extinction=(1, 2, 3))  # molar mass fallback 0
    with pytest.raises(FiberParamsError) as info:
        FiberParams.from_prim(prim)
    err = info.value
    assert isinstance(err, PrimError) and isinstance(err, ValueError)
    assert (err.file and Path(err.file).name, err.prim, err.attribute) == (
        "cloth.usda", "/Cloth/Fibers", Fiber.DYE_MOLAR_MASS)
    assert str(err).startswith("cloth.usda: /Cloth/Fibers.fiber:dye:molarMass: must be > 0 g/mol")
    assert "\n" not in str(err)
    again = pickle.loads(pickle.dumps(err))
    assert type(again) is FiberParamsError and str(again) == str(err)
    # The other readers raise the same type, with the same one-line form.
    plain = UsdGeom.BasisCurves.Define(stage, "/Plain").GetPrim()
    for call, cls in ((lambda: YarnParams.from_prim(plain), YarnError),
                      (lambda: curves_from_prim(plain), CurveError),
                      (lambda: authoring.apply_fiber(plain, "cotton", kind="linen"), authoring.AuthoringError)):
        with pytest.raises(cls) as info:
            call()
        assert isinstance(info.value, PrimError) and str(info.value).startswith("cloth.usda: /Plain"), str(info.value)
    # In-memory stages have no file to name.
    memory = Usd.Stage.CreateInMemory()
    mem = UsdGeom.BasisCurves.Define(memory, "/M").GetPrim()
    with pytest.raises(YarnError, match=r"^/M: has no FiberYarnAPI"):
        YarnParams.from_prim(mem)


# --------------------------------------------------------------------------------------
# The diameter may be time-sampled (schema and code agree)
# --------------------------------------------------------------------------------------


def test_diameter_is_time_sampled_and_read_per_frame():
    """Only absorption depends on the diameter (a new value recolours the same table), so the
    schema lets it vary over time; what changes the traced geometry or optics is uniform."""
    varying = {n for n, s in attributes(Fiber.API).items() if not s.uniform}
    assert Fiber.DIAMETER in varying
    traced = {Fiber.KIND, Fiber.PROFILE, Fiber.PROFILE_VARIANT_COUNT, Fiber.IOR_PARALLEL,
              Fiber.IOR_PERPENDICULAR, Fiber.IOR_EFFECTIVE, Fiber.ROUGHNESS_SOURCE, Fiber.ROUGHNESS_RA,
              Fiber.ROUGHNESS_PROFILE_LENGTH, Fiber.ROUGHNESS_BETA, Fiber.CUTICLE_TILT,
              Fiber.CUTICLE_HEIGHT, Fiber.CUTICLE_SPACING}
    assert not varying & traced
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 1e-6)
    curves = UsdGeom.BasisCurves.Define(stage, "/F")
    curves.CreateTypeAttr("linear")
    curves.CreatePointsAttr([(0, 0, 0), (0, 0, 100)])
    curves.CreateCurveVertexCountsAttr([2])
    curves.CreateWidthsAttr([15.0])
    curves.SetWidthsInterpolation(UsdGeom.Tokens.constant)
    prim = authoring.apply_fiber(curves.GetPrim(), "polyester", dye="disperseRed", depth_of_shade=1.0,
                                 diameter={1: 10.0, 2: 20.0})
    a, b = FiberParams.from_prim(prim, 1), FiberParams.from_prim(prim, 2)
    assert (a.diameter, b.diameter) == (10.0, 20.0)
    assert a.geometry_key() == b.geometry_key()  # one table recoloured per frame
    from usdfiber.validation.runner import check_stage

    report = check_stage(stage)
    assert not [p for p in report.problems if p.severity.value == "error"], report.problems
    # With cuticle scales their size relative to the diameter is traced: one table per diameter.
    authoring.apply_fiber(prim, None, cuticle_height=2.0)
    assert FiberParams.from_prim(prim, 1).geometry_key() != FiberParams.from_prim(prim, 2).geometry_key()
