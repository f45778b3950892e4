"""The ``fiberSchema`` check: how FiberAPI, FiberYarnAPI and FiberProfileAPI are used.

Ranges, units and allowed tokens are those documented in ``schema/schema.usda``; types,
allowed tokens and fallbacks are read from USD's definition of the applied API schemas so
that they cannot drift from the schema. Every value is checked at its default and at every
authored time sample (or at the times the validation asks for, see
:func:`usdfiber.validation.times_for`). Curve geometry and user cross-section polygons are
checked elsewhere (``topology``, ``assets``).

Only authored attributes are read: fallbacks come from the schema and are valid. The
verdict on a set of values that has no time samples depends on the values alone, so it is
computed once per distinct set and shared by every prim authoring it (see ``_CACHE``).

Codes (severity):

- ``NotBasisCurves`` (error): FiberAPI or FiberYarnAPI on a prim that is not BasisCurves.
- ``YarnWithoutFiberAPI`` (warning): FiberYarnAPI without FiberAPI; the fibers get the
  FiberAPI fallbacks.
- ``APINotApplied`` (warning): usdFiber attributes authored on a BasisCurves prim (or on
  a prim with another usdFiber API) without their API; renderers ignore them.
- ``UnknownAttribute`` (warning): an attribute in a usdFiber namespace the schema does not
  define (usually a misspelling; the closest name is suggested).
- ``WrongValueType`` (error): authored with another type than the schema's (read from the
  strongest spec: USD reports the schema's type for builtin attributes).
- ``NonFiniteValue`` (error): NaN or infinity.
- ``ValueOutOfRange`` (error): outside the documented valid range, including the
  cross-attribute ranges (cuticle height <= diameter / 4, a positive molar mass when the
  extinction is molar, beta = arctan(Ra / l) within beta's range).
- ``BeyondIndustryRange`` (warning): depth of shade above 4 % (valid up to 10 %).
- ``UnknownToken`` (error): a token outside allowedTokens (the message lists them).
- ``InvertedRange`` (error): yarn:fiber:migration with rho_min > rho_max.
- ``IgnoredValue`` (warning): depth of shade on an undyed fiber (dye class "none").
- ``ExtinctionOutsideDyeRange`` (warning): the dye's peak extinction per gram (from
  whichever source is selected) outside its class's range: reactive 0.005-0.0158,
  disperse 0.045-0.246 L mg^-1 cm^-1.
- ``SpectrumLengthMismatch``, ``SpectrumNotIncreasing``, ``SpectrumIncomplete`` (errors):
  a spectral extinction that cannot be used (counts differ, wavelengths not strictly
  increasing, 400-700 nm not covered).
- ``ProfileRequired`` (error): fiber:kind "custom" with fiber:profile "auto".
- ``MissingProfileSources``, ``ProfileSourceMissing``, ``ProfileSourceNotProfile``
  (errors): a "user" cross section without usable FiberProfileAPI targets.
"""
from __future__ import annotations

import difflib
import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Iterable

import numpy as np
from pxr import Gf, Sdf, Tf, Usd, Vt

from usdfiber.spec.attributes import (Fiber, Interval, Profile, Yarn, attributes,
                                      industry_extinction_ranges, spectrum_coverage)
from usdfiber.validation import current_times, times_for
from usdfiber.validation.problems import Problem, Severity, prim_check

FIBER, YARN, PROFILE = Fiber.API, Yarn.API, Profile.API
_NAMESPACES = {"fiber": FIBER, "yarn": YARN, "fiberProfile": PROFILE}
_ON_CURVES_ONLY = (FIBER, YARN)
_APIS = frozenset((FIBER, YARN, PROFILE))

E, W = Severity.ERROR, Severity.WARNING



# --- schema facts -------------------------------------------------------------------------

@dataclass(frozen=True)
class AttrDef:
    """What the schema says about one attribute."""

    api: str
    name: str
    type_name: Sdf.ValueTypeName
    allowed: tuple[str, ...] | None
    fallback: Any
    is_relationship: bool = False


@lru_cache(maxsize=None)
def schema_defs() -> dict[str, AttrDef]:
    """Every property of the three usdFiber APIs, by name (from USD's schema registry)."""
    reg = Usd.SchemaRegistry()
    out: dict[str, AttrDef] = {}
    for api in (FIBER, YARN, PROFILE):
        prim_def = reg.FindAppliedAPIPrimDefinition(api)
        if prim_def is None:  # the schema plugin is not registered: nothing to check against
            continue
        for name in prim_def.GetPropertyNames():
            attr = prim_def.GetAttributeDefinition(name)
            if not attr:
                out[name] = AttrDef(api, name, Sdf.ValueTypeName(), None, None, True)
                continue
            allowed = attr.GetMetadata("allowedTokens")
            out[name] = AttrDef(api, name, attr.GetTypeName(),
                                tuple(str(t) for t in allowed) if allowed else None,
                                attr.GetFallbackValue())
    return out


# --- ranges (schema.usda's customData, through usdfiber.spec.attributes) ----------------------

@dataclass(frozen=True)
class Rule:
    """Valid range of an attribute, what its value is, and its unit."""

    valid: Interval
    what: str
    unit: str = ""
    components: tuple[str, ...] = ()  # for vectors: one label per component
    industry: Interval | None = None  # beyond it: a warning


# What each ranged value is, for messages ("expected a diameter in (0, 1000] um"); the ranges
# and units themselves are the schema's.
_WHAT: dict[str, str] = {
    Fiber.PROFILE_VARIANT_COUNT: "a variant count",
    Fiber.DIAMETER: "a diameter",
    Fiber.DENSITY: "a density",
    Fiber.IOR_PARALLEL: "a refractive index",
    Fiber.IOR_PERPENDICULAR: "a refractive index",
    Fiber.ROUGHNESS_RA: "a roughness Ra",
    Fiber.ROUGHNESS_PROFILE_LENGTH: "a profile length",
    Fiber.ROUGHNESS_BETA: "a slope angle beta",
    Fiber.CUTICLE_TILT: "a scale tilt",
    Fiber.CUTICLE_HEIGHT: "a scale height",
    Fiber.CUTICLE_SPACING: "a scale spacing",
    Fiber.DYE_EXTINCTION: "an extinction per gram",
    Fiber.DYE_MOLAR_EXTINCTION: "a molar extinction",
    Fiber.DYE_MOLAR_MASS: "a molar mass",
    Fiber.DYE_SPECTRUM_WAVELENGTHS: "a wavelength",
    Fiber.DYE_SPECTRUM_VALUES: "an extinction per gram",
    Fiber.DYE_DEPTH_OF_SHADE: "a depth of shade",
    Fiber.ROTATION: "a rotation",
    Yarn.PLIES: "a ply count",
    Yarn.FIBERS_PER_PLY: "a fiber count per ply",
    Yarn.PLY_LINEAR_DENSITY: "a linear density",
    Yarn.FIBER_STAPLE_LENGTH: "a staple length",
    Yarn.PLY_TWIST: "a twist",
    Yarn.FIBER_TWIST: "a twist",
    Yarn.PLY_RADIUS: "a ply radius",
    Yarn.PLY_COMPRESSION: "a compression",
    Yarn.FIBER_MIGRATION: "a migration factor",
    Yarn.FIBER_MIGRATION_PERIOD: "a migration period",
    Yarn.FLYAWAY_HAIR_DENSITY: "a hair density",
    Yarn.FLYAWAY_HAIR_LENGTH: "a length",
    Yarn.FLYAWAY_LOOP_DENSITY: "a loop density",
    Yarn.FLYAWAY_LOOP_HEIGHT: "a height",
}
# Said after an industry-range warning's limit.
_INDUSTRY_NOTE = {Fiber.DYE_DEPTH_OF_SHADE: " (a deep shade)"}


@lru_cache(maxsize=None)
def rules() -> dict[str, Rule]:
    """The range rule of every attribute with a ``validRange`` in the schema."""
    return {name: Rule(spec.valid, _WHAT.get(name, "a value"), spec.unit, spec.components,
                       spec.industry)
            for name, spec in attributes().items() if spec.valid is not None}


@lru_cache(maxsize=None)
def component_rules() -> dict[str, tuple[tuple[Interval, ...], tuple[str, ...]]]:
    """(ranges, labels) of vectors whose components have different ranges."""
    return {name: (spec.component_valid, spec.components)
            for name, spec in attributes().items() if spec.component_valid is not None}


@lru_cache(maxsize=None)
def _valid_when() -> dict[str, tuple[str, str]]:
    """Attributes whose range holds only while another attribute has a token (``validWhen``)."""
    return {name: tuple(spec.facts["validWhen"]) for name, spec in attributes().items()
            if "validWhen" in spec.facts}


# --- formatting -------------------------------------------------------------------------

def _num(x: float) -> str:
    if isinstance(x, (bool, np.bool_)):
        return "true" if x else "false"
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    x = float(x)
    if math.isnan(x):
        return "nan"
    if math.isinf(x):
        return "inf" if x > 0 else "-inf"
    return f"{x:.6g}"


def fmt_value(v: Any, limit: int = 6) -> str:
    """A short, readable rendering of an attribute value for messages."""
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, (float, int, np.floating, np.integer)):
        return _num(v)
    if isinstance(v, Sdf.AssetPath):
        return f"@{v.path}@"
    try:
        seq = list(v)
    except TypeError:
        return str(v)
    if len(seq) > limit:
        return "[" + ", ".join(fmt_value(x) for x in seq[:limit]) + f", ... ({len(seq)} values)]"
    if isinstance(v, (Gf.Vec2f, Gf.Vec3f, Gf.Vec2d, Gf.Vec3d, Gf.Vec2h, Gf.Vec3h, Gf.Vec2i)):
        return "(" + ", ".join(fmt_value(x) for x in seq) + ")"
    return "[" + ", ".join(fmt_value(x) for x in seq) + "]"


def _at(t: float | None) -> str:
    return "" if t is None else f" at time {_num(t)}"


def _unit(u: str) -> str:
    return f" {u}" if u else ""


# --- reading a prim ------------------------------------------------------------------------

def strongest_layer(prop: Usd.Property, t: float | None = None) -> str | None:
    """Identifier of the layer holding the strongest value opinion of ``prop`` at ``t``
    (None: its default), else of its strongest spec of any kind."""
    try:
        stack = prop.GetPropertyStack(Usd.TimeCode.Default() if t is None else Usd.TimeCode(t))
    except Exception:  # a relationship: no value opinions
        stack = prop.GetPropertyStack()
    for spec in stack:
        if isinstance(spec, Sdf.AttributeSpec):
            has = (spec.HasDefaultValue() if t is None
                   else spec.layer.GetNumTimeSamplesForPath(spec.path) > 0)
            if has:
                return spec.layer.identifier
    return stack[0].layer.identifier if stack else None


def _strongest_api_layer(prim: Usd.Prim, api: str) -> str | None:
    """Layer of the strongest prim spec that applies ``api`` (else of the strongest spec)."""
    stack = prim.GetPrimStack()
    for spec in stack:
        op = spec.GetInfo("apiSchemas") if spec.HasInfo("apiSchemas") else None
        if op is not None and api in (list(op.explicitItems) + list(op.prependedItems)
                                      + list(op.appendedItems) + list(op.addedItems)):
            return spec.layer.identifier
    return stack[0].layer.identifier if stack else None


_PY_TYPES: dict[str, tuple[type, ...]] = {
    "float": (float,), "double": (float,), "half": (float,), "int": (int,), "bool": (bool,),
    "token": (str,), "string": (str,), "asset": (Sdf.AssetPath,),
    "color3f": (Gf.Vec3f,), "float2": (Gf.Vec2f,), "float3": (Gf.Vec3f,),
    "float[]": (Vt.FloatArray,), "int[]": (Vt.IntArray,), "float2[]": (Vt.Vec2fArray,),
}
_GF_VECTORS = (Gf.Vec2f, Gf.Vec3f, Gf.Vec2d, Gf.Vec3d, Gf.Vec2h, Gf.Vec3h, Gf.Vec2i, Gf.Vec3i)


def _comps(v: Any) -> tuple[float, ...]:
    # Index explicitly: iterating a Gf vector ends with an IndexError thrown from C++,
    # which costs more than reading the components.
    return tuple(float(v[i]) for i in range(len(v)))


@dataclass(frozen=True)
class Finding:
    """A problem before it is placed on a prim: cacheable across prims with equal values.

    The layer is resolved when the finding is placed: ``layer`` when given, else the
    strongest opinion of the first authored attribute of ``layer_from`` (default: the
    attribute itself), else of the API application for prim-level findings.
    """

    code: str
    severity: Severity
    attribute: str | None
    message: str
    time: float | None = None
    layer_from: tuple[str, ...] = ()
    layer: str | None = None


class PrimValues:
    """The authored values of one API on one prim, read once and shared by its checks."""

    def __init__(self, prim: Usd.Prim, api: str) -> None:
        self.prim = prim
        self.api = api
        self.defs = schema_defs()
        self.attrs: dict[str, Usd.Attribute] = {}   # authored and of the schema's type
        self.values: dict[str, list[tuple[float | None, Any]]] = {}
        self.findings: list[Finding] = []
        self.sampled = False  # any authored time sample among the attributes read

    # reading --------------------------------------------------------------------------
    def read(self, names: list[str]) -> None:
        """Read ``names`` (authored attributes of ``api``): types first, then values."""
        names = [n for n in names if not self.defs[n].is_relationship]
        attrs = [self.prim.GetAttribute(n) for n in names]
        # One call for the whole prim; most prims have no samples at all.
        self.sampled = bool(attrs) and bool(Usd.Attribute.GetUnionedTimeSamples(attrs))
        for name, attr in zip(names, attrs):
            adef = self.defs[name]
            if not attr:
                rel = self.prim.GetRelationship(name)
                self.finding("WrongValueType", E, name,
                             f"{name} is authored as a relationship; expected an attribute "
                             f"of type {adef.type_name}",
                             layer=strongest_layer(rel) if rel else None)
                continue
            if not self._type_ok(attr, adef):
                continue
            if not self.sampled:
                v = attr.Get()
                vals = [] if v is None else [(None, v)]  # None: a value block
            else:
                vals = []
                for t in times_for(attr):
                    v = attr.Get() if t is None else attr.Get(t)
                    if v is not None:
                        vals.append((t, v))
            self.attrs[name] = attr
            self.values[name] = vals

    def _type_ok(self, attr: Usd.Attribute, adef: AttrDef) -> bool:
        # GetTypeName() answers from the schema, so the authored type is read from the
        # strongest spec: a reader asking for the schema's type gets nothing from another.
        stack = attr.GetPropertyStack()
        if not stack:
            return True
        spec = stack[0]
        tn = spec.typeName
        if tn != adef.type_name and tn.type != adef.type_name.type:
            self.finding("WrongValueType", E, adef.name,
                         f"{adef.name} is authored as {tn}; expected {adef.type_name}",
                         layer=spec.layer.identifier)
            return False
        return True

    def cache_key(self) -> tuple | None:
        """Key of the values read when they alone decide the findings (else None)."""
        if self.sampled:
            return None
        key = []
        for name, vals in self.values.items():
            if not vals:
                key.append((name, None, None))
                continue
            v = vals[0][1]
            if not isinstance(v, (float, int, str, *_GF_VECTORS)):
                return None  # arrays: not hashable, and rare
            key.append((name, type(v), v))
        return (self.api, tuple(key))

    def get(self, name: str, t: float | None = None) -> Any:
        """The value of ``name`` at ``t`` (None: default), the fallback when unauthored."""
        attr = self.attrs.get(name)
        if attr is None:
            return self.defs[name].fallback
        for tt, v in self.values[name]:
            if tt == t:
                return v
        v = attr.Get() if t is None else attr.Get(t)
        return self.defs[name].fallback if v is None else v

    def times(self, *names: str) -> list[float | None]:
        """Union of the times read for ``names`` (None first).

        When the running validation excludes the default time (``--time T``), a default
        value only stands for the selected times: None is dropped when others exist.
        """
        ts = {t for n in names for t, _ in self.values.get(n, ())}
        if None in ts and len(ts) > 1 and not current_times().include_default:
            ts.discard(None)
        return sorted(ts, key=lambda t: (t is not None, t or 0.0)) or [None]

    def authored(self, name: str) -> bool:
        return name in self.attrs

    # reporting ------------------------------------------------------------------------
    def finding(self, code: str, severity: Severity, attribute: str | None, message: str,
                time: float | None = None, layer_from: tuple[str, ...] = (),
                layer: str | None = None) -> None:
        self.findings.append(Finding(code, severity, attribute, message, time,
                                     layer_from or ((attribute,) if attribute else ()), layer))

    def place(self, findings: Iterable[Finding]) -> list[Problem]:
        """``findings`` as Problems of this prim, with the layer of the strongest opinion."""
        if not findings:
            return []
        path = str(self.prim.GetPath())
        out = []
        for f in findings:
            layer = f.layer
            if layer is None:
                for n in f.layer_from:
                    if n in self.attrs:
                        layer = strongest_layer(self.attrs[n], f.time)
                        break
                else:
                    if f.attribute is None or not f.layer_from:
                        layer = _strongest_api_layer(self.prim, self.api)
            out.append(Problem(f.code, f.severity, path, f.attribute, f.message, layer, f.time))
        return out


# --- value checks ------------------------------------------------------------------------

def _scalar_problem(v: Any, rule: Rule) -> tuple[str, str] | None:
    """(code, message tail) when scalar ``v`` breaks ``rule``."""
    x = float(v)
    if not math.isfinite(x):
        noun = rule.what.split(" ", 1)[-1]
        rng = f" in {rule.valid}{_unit(rule.unit)}" if rule.valid != Interval() else ""
        return "NonFiniteValue", f"expected a finite {noun}{rng}"
    if x not in rule.valid:
        return "ValueOutOfRange", f"expected {rule.what} in {rule.valid}{_unit(rule.unit)}"
    return None


def _vector_problem(name: str, v: Any, rule: Rule | None) -> tuple[str, str] | None:
    comps = _comps(v)
    by_component = component_rules().get(name)
    labels = (by_component[1] if by_component else ()) or (rule.components if rule else ()) or tuple(
        str(i) for i in range(len(comps)))
    ranges = by_component[0] if by_component else tuple(rule.valid for _ in comps)
    if not all(math.isfinite(c) for c in comps):
        return "NonFiniteValue", f"expected finite values for {', '.join(labels)}"
    bad = [(lab, rng) for c, lab, rng in zip(comps, labels, ranges) if c not in rng]
    if not bad:
        return None
    if len(set(ranges)) == 1 and rule is not None:
        return "ValueOutOfRange", (f"expected each of {', '.join(labels)} to be {rule.what} "
                                   f"in {ranges[0]}{_unit(rule.unit)}")
    lab, rng = bad[0]
    return "ValueOutOfRange", f"expected {lab} in {rng}"


def _array_problem(v: Any, rule: Rule) -> tuple[str, str] | None:
    a = np.asarray(v, dtype=np.float64)
    if a.size == 0:
        return None
    rows = a.reshape(len(a), -1)
    finite = np.isfinite(rows).all(axis=1)
    if not finite.all():
        return "NonFiniteValue", (f"{int((~finite).sum())} non-finite value(s), first at index "
                                  f"{int(np.argmin(finite))}; expected finite values")
    lo_bad = rows <= rule.valid.lo if rule.valid.lo_open else rows < rule.valid.lo
    hi_bad = rows >= rule.valid.hi if rule.valid.hi_open else rows > rule.valid.hi
    bad = (lo_bad | hi_bad).any(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        return "ValueOutOfRange", (f"{int(bad.sum())} value(s) out of range, first "
                                   f"{fmt_value(rows[i] if rows.shape[1] > 1 else rows[i, 0])} "
                                   f"at index {i}; expected {rule.what} in {rule.valid}"
                                   f"{_unit(rule.unit)}")
    return None


def _check_value(pv: PrimValues, name: str, t: float | None, v: Any) -> None:
    adef = pv.defs[name]
    tname = str(adef.type_name)
    ok_types = _PY_TYPES.get(tname)
    if (ok_types and not isinstance(v, ok_types)) or (tname != "bool" and isinstance(v, bool)):
        pv.finding("WrongValueType", E, name,
                   f"{name} holds a {type(v).__name__} value{_at(t)}; expected {tname}", t)
        return
    if adef.allowed:
        if v not in adef.allowed:
            pv.finding("UnknownToken", E, name,
                       f"{name} = {fmt_value(v)}{_at(t)}; expected one of: "
                       f"{', '.join(adef.allowed)}", t)
        return
    rule = rules().get(name)
    if tname in ("float", "double", "half", "int"):
        if rule is None:
            return
        when = _valid_when().get(name)
        if when is not None and pv.get(when[0], t) != when[1]:
            # Unused unless ``when`` holds (the molar mass without a molar extinction source):
            # its fallback (0) lies outside the range, so only impossible values are reported.
            x = float(v)
            if not math.isfinite(x) or x < 0:
                pv.finding("NonFiniteValue" if not math.isfinite(x) else "ValueOutOfRange", E,
                           name, f"{name} = {fmt_value(v)}{_unit(rule.unit)}{_at(t)}; expected "
                           f"{rule.what} in {rule.valid}{_unit(rule.unit)}", t)
            return
        found = _scalar_problem(v, rule)
        if found:
            code, tail = found
            pv.finding(code, E, name,
                       f"{name} = {fmt_value(v)}{_unit(rule.unit)}{_at(t)}; {tail}", t)
        elif rule.industry is not None and float(v) not in rule.industry:
            x, ind = float(v), rule.industry
            limit = f"at most {_num(ind.hi)}" if x > ind.hi else f"at least {_num(ind.lo)}"
            pv.finding("BeyondIndustryRange", W, name,
                       f"{name} = {fmt_value(v)}{_unit(rule.unit)}{_at(t)} is beyond the industry "
                       f"range; expected {limit}{_unit(rule.unit)}{_INDUSTRY_NOTE.get(name, '')}", t)
    elif tname in ("color3f", "float2", "float3"):
        if rule is None and name not in component_rules():
            return
        found = _vector_problem(name, v, rule)
        if found:
            code, tail = found
            unit = _unit(rule.unit) if rule else ""
            pv.finding(code, E, name, f"{name} = {fmt_value(v)}{unit}{_at(t)}; {tail}", t)
        elif name == Yarn.FIBER_MIGRATION and float(v[0]) > float(v[1]):
            pv.finding("InvertedRange", E, name,
                       f"{name} = {fmt_value(v)}{_at(t)}; expected rho_min <= rho_max", t)
    elif tname.endswith("[]") and rule is not None:
        found = _array_problem(v, rule)
        if found:
            code, tail = found
            pv.finding(code, E, name, f"{name}{_at(t)}: {tail}", t)


def _judge(pv: PrimValues) -> None:
    """Every check of the values read (no stage access unless values are time-sampled)."""
    for name, vals in pv.values.items():
        for t, v in vals:
            _check_value(pv, name, t, v)
    if pv.api == FIBER:
        _fiber_cross_checks(pv)


# --- cross-attribute checks ------------------------------------------------------------------

def _finite(*vals: Any) -> bool:
    try:
        return all(math.isfinite(float(v)) for v in vals)
    except (TypeError, ValueError):
        return False


def _fiber_cross_checks(pv: PrimValues) -> None:
    if pv.get(Fiber.KIND) == "custom" and pv.get(Fiber.PROFILE) == "auto":
        pv.finding("ProfileRequired", E, Fiber.PROFILE,
                   'fiber:kind = "custom" with fiber:profile = "auto"; expected fiber:profile '
                   'to name a cross-section family or "user" (a custom fiber has no built-in '
                   'cross section)', layer_from=(Fiber.PROFILE, Fiber.KIND))

    for name, (of, factor) in _relative_maxima().items():
        _relative_maximum_check(pv, name, of, factor)
    _derived_beta_check(pv)
    _dye_checks(pv)


def _derived_beta_check(pv: PrimValues) -> None:
    """beta = arctan(Ra / l) (paper Sec. 3.1), when the roughness comes from Ra and the
    profile length, must lie in beta's own valid range: l = 1e-40 nm makes beta 90 degrees,
    which no table can be baked for."""
    names = (Fiber.ROUGHNESS_SOURCE, Fiber.ROUGHNESS_RA, Fiber.ROUGHNESS_PROFILE_LENGTH)
    if not any(pv.authored(n) for n in names):
        return
    rule = rules()[Fiber.ROUGHNESS_BETA]
    for t in pv.times(*names):
        if pv.get(Fiber.ROUGHNESS_SOURCE, t) != "ra":
            continue
        ra, plen = pv.get(Fiber.ROUGHNESS_RA, t), pv.get(Fiber.ROUGHNESS_PROFILE_LENGTH, t)
        if not (_finite(ra, plen) and float(ra) >= 0 and float(plen) > 0):
            continue  # the value checks report them
        beta = math.degrees(math.atan(float(ra) / float(plen)))
        if beta not in rule.valid:
            pv.finding("ValueOutOfRange", E, Fiber.ROUGHNESS_PROFILE_LENGTH,
                       f"fiber:roughness:ra = {_num(ra)} nm and {Fiber.ROUGHNESS_PROFILE_LENGTH} = "
                       f"{_num(plen)} nm{_at(t)} give beta = arctan(Ra / l) = {_num(beta)} deg; "
                       f"expected {rule.what} in {rule.valid}{_unit(rule.unit)}", t,
                       layer_from=(Fiber.ROUGHNESS_PROFILE_LENGTH, Fiber.ROUGHNESS_RA,
                                   Fiber.ROUGHNESS_SOURCE))


@lru_cache(maxsize=None)
def _relative_maxima() -> dict[str, tuple[str, float]]:
    """Attributes at most a factor of another (``validMaxOf``, ``validMaxFactor``): the cuticle
    scales' height is at most a quarter of the diameter."""
    return {name: (spec.facts["validMaxOf"], float(spec.facts["validMaxFactor"]))
            for name, spec in attributes(FIBER).items() if "validMaxOf" in spec.facts}


def _relative_maximum_check(pv: PrimValues, name: str, of: str, factor: float) -> None:
    if not (pv.authored(name) or pv.authored(of)):
        return
    rule = rules()[name]
    unit = _unit(rule.unit)
    inverse = 1.0 / factor
    bound = f"{of} / {_num(inverse)}" if inverse == round(inverse) else f"{_num(factor)} {of}"
    for t in pv.times(name, of):
        h, d = pv.get(name, t), pv.get(of, t)
        if _finite(h, d) and float(d) > 0 and float(h) > float(d) * factor:
            pv.finding("ValueOutOfRange", E, name,
                       f"{name} = {_num(h)}{unit}{_at(t)}; expected {rule.what} in "
                       f"[0, {bound}] = [0, {_num(float(d) * factor)}]{unit}",
                       t, layer_from=(name, of))


_DYE_NAMES = (Fiber.DYE_CLASS, Fiber.DYE_DEPTH_OF_SHADE, Fiber.DYE_EXTINCTION_SOURCE,
              Fiber.DYE_EXTINCTION, Fiber.DYE_MOLAR_EXTINCTION, Fiber.DYE_MOLAR_MASS,
              Fiber.DYE_SPECTRUM_WAVELENGTHS, Fiber.DYE_SPECTRUM_VALUES)


def _dye_checks(pv: PrimValues) -> None:
    if not any(pv.authored(n) for n in _DYE_NAMES):
        return
    for t in pv.times(*_DYE_NAMES):
        cls = pv.get(Fiber.DYE_CLASS, t)
        dos = pv.get(Fiber.DYE_DEPTH_OF_SHADE, t)
        if cls == "none":
            if _finite(dos) and float(dos) > 0:
                pv.finding("IgnoredValue", W, Fiber.DYE_DEPTH_OF_SHADE,
                           f'fiber:dye:depthOfShade = {_num(dos)} %{_at(t)} but fiber:dye:class '
                           f'= "none": the fiber is undyed and the depth of shade is ignored; '
                           f'expected a dye class (reactive, disperse, custom) or a depth of '
                           f'shade of 0', t,
                           layer_from=(Fiber.DYE_DEPTH_OF_SHADE, Fiber.DYE_CLASS))
            continue
        source = pv.get(Fiber.DYE_EXTINCTION_SOURCE, t)
        peak, attr = None, Fiber.DYE_EXTINCTION
        if source == "perGram":
            ext = pv.get(Fiber.DYE_EXTINCTION, t)
            if ext is not None and _finite(*_comps(ext)):
                peak = max(_comps(ext))
        elif source == "molar":
            attr = Fiber.DYE_MOLAR_EXTINCTION
            mass = pv.get(Fiber.DYE_MOLAR_MASS, t)
            if _finite(mass) and float(mass) <= 0:
                mr = rules()[Fiber.DYE_MOLAR_MASS]
                pv.finding("ValueOutOfRange", E, Fiber.DYE_MOLAR_MASS,
                           f'fiber:dye:molarMass = {_num(mass)}{_unit(mr.unit)}{_at(t)} with '
                           f'fiber:dye:extinctionSource = "molar"; expected {mr.what} in '
                           f'{mr.valid}{_unit(mr.unit)}', t,
                           layer_from=(Fiber.DYE_MOLAR_MASS, Fiber.DYE_EXTINCTION_SOURCE))
            me = pv.get(Fiber.DYE_MOLAR_EXTINCTION, t)
            if _finite(mass) and float(mass) > 0 and me is not None and _finite(*_comps(me)):
                # epsilon = epsilon_m / w_m in L g^-1 cm^-1; / 1000 for L mg^-1 cm^-1.
                peak = max(_comps(me)) / float(mass) / 1000.0
        elif source == "spectrum":
            attr = Fiber.DYE_SPECTRUM_VALUES
            peak = _spectrum_checks(pv, t)
        industry = industry_extinction_ranges().get(cls)
        rng = (industry.lo, industry.hi) if industry else None
        # Relative slack of float32 precision: 0.246 authored reads back as 0.24600000679.
        if rng and peak is not None and not (rng[0] * (1 - 1e-6) <= peak <= rng[1] * (1 + 1e-6)):
            pv.finding("ExtinctionOutsideDyeRange", W, attr,
                       f"peak extinction per gram {_num(peak)} L/(mg cm){_at(t)} from {attr} is "
                       f"outside the {cls} dye range; expected {_num(rng[0])} to {_num(rng[1])} "
                       f"L/(mg cm) (paper Section 3.1) or fiber:dye:class = \"custom\"", t,
                       layer_from=(attr, Fiber.DYE_CLASS))


def _array(v: Any) -> np.ndarray:
    return np.zeros(0) if v is None else np.asarray(v, dtype=np.float64).reshape(-1)


def _spectrum_checks(pv: PrimValues, t: float | None) -> float | None:
    wl_name, val_name = Fiber.DYE_SPECTRUM_WAVELENGTHS, Fiber.DYE_SPECTRUM_VALUES
    wl, vals = _array(pv.get(wl_name, t)), _array(pv.get(val_name, t))
    if len(wl) != len(vals):
        pv.finding("SpectrumLengthMismatch", E, val_name,
                   f"{val_name} has {len(vals)} values and {wl_name} {len(wl)}{_at(t)}; "
                   f"expected one extinction per wavelength", t, layer_from=(val_name, wl_name))
        return None
    if not (np.isfinite(wl).all() and np.isfinite(vals).all()):
        return None  # reported as NonFiniteValue
    steps = np.diff(wl) > 0
    if not steps.all():
        i = int(np.argmin(steps))
        pv.finding("SpectrumNotIncreasing", E, wl_name,
                   f"{wl_name}{_at(t)}: {_num(wl[i + 1])} nm follows {_num(wl[i])} nm at index "
                   f"{i + 1}; expected strictly increasing wavelengths", t)
        return None
    cover = spectrum_coverage()
    lo, hi = cover.lo, cover.hi
    if len(wl) < 2 or wl[0] > lo or wl[-1] < hi:
        have = f"covers [{_num(wl[0])}, {_num(wl[-1])}] nm" if len(wl) else "is empty"
        pv.finding("SpectrumIncomplete", E, wl_name,
                   f'{wl_name} {have}{_at(t)} with fiber:dye:extinctionSource = "spectrum"; '
                   f'expected a spectrum covering {_num(lo)}-{_num(hi)} nm', t,
                   layer_from=(wl_name, Fiber.DYE_EXTINCTION_SOURCE))
        return None
    return float(vals.max()) if len(vals) else None


def _profile_source_findings(pv: PrimValues) -> list[Finding]:
    """A "user" cross section needs FiberProfileAPI targets (reads the stage: not cached)."""
    if pv.get(Fiber.PROFILE) != "user":
        return []
    name = Fiber.PROFILE_SOURCES
    rel = pv.prim.GetRelationship(name)
    layer = strongest_layer(rel) if rel and rel.IsAuthored() else None
    from_ = () if layer else (Fiber.PROFILE,)
    try:
        targets = rel.GetTargets() if rel else []
    except Tf.ErrorException as exc:  # e.g. a target outside a reference's scope (Pcp)
        from usdfiber.validation.plugin import one_line_reason

        return [Finding("ProfileSourceMissing", E, name,
                        f"{name} targets cannot be resolved ({one_line_reason(exc)}); expected "
                        f"prims with FiberProfileAPI on this stage", None, from_, layer)]
    if not targets:
        return [Finding("MissingProfileSources", E, name,
                        f'fiber:profile = "user" but {name} has no targets; expected one or '
                        f'more prims with FiberProfileAPI (one per cross-section variant)',
                        None, from_, layer)]
    out = []
    stage = pv.prim.GetStage()
    for target in targets:
        target_prim = stage.GetPrimAtPath(target.GetPrimPath())
        if not target_prim:
            out.append(Finding("ProfileSourceMissing", E, name,
                               f"{name} targets <{target}>, which does not exist on the stage; "
                               f"expected a prim with FiberProfileAPI", None, from_, layer))
        elif not target_prim.HasAPI(PROFILE):
            out.append(Finding("ProfileSourceNotProfile", E, name,
                               f"{name} targets <{target}>, which has no FiberProfileAPI; "
                               f"expected a prim with FiberProfileAPI", None, from_, layer))
    return out


# --- the registered check ---------------------------------------------------------------------

# Findings by value set: prims authoring the same values share them (100k fibers written by
# one tool usually author a handful of distinct value sets).
_CACHE: dict[tuple, tuple[Finding, ...]] = {}
_CACHE_LIMIT = 4096


def _our_names(names: Iterable[str]) -> dict[str, list[str]]:
    """Authored property names of the usdFiber namespaces, grouped by API."""
    out: dict[str, list[str]] = {}
    for n in names:
        head, sep, _ = n.partition(":")
        if sep:
            api = _NAMESPACES.get(head)
            if api is not None:
                out.setdefault(api, []).append(n)
    return out


def _not_applied(prim: Usd.Prim, by_api: dict[str, list[str]], applied: Iterable[str]
                 ) -> list[Problem]:
    defs = schema_defs()
    out = []
    for api, names in by_api.items():
        if api in applied:
            continue
        known = sorted(n for n in names if n in defs and defs[n].api == api)
        if known:
            out.append(Problem(
                "APINotApplied", W, str(prim.GetPath()), known[0],
                f"{', '.join(known)} authored on a prim without {api}, so renderers ignore "
                f"{'it' if len(known) == 1 else 'them'}; expected {api} in the prim's "
                f"apiSchemas", strongest_layer(prim.GetProperty(known[0]))))
    return out


def _placement(prim: Usd.Prim, apis: list[str]) -> list[Problem]:
    out = []
    on_curves = [a for a in _ON_CURVES_ONLY if a in apis]
    if on_curves:
        type_name = prim.GetTypeName()
        if type_name != "BasisCurves":
            from pxr import UsdGeom

            if not prim.IsA(UsdGeom.BasisCurves):
                shown = f'a "{type_name}"' if type_name else "a typeless"
                for api in on_curves:
                    out.append(Problem(
                        "NotBasisCurves", E, str(prim.GetPath()), None,
                        f"{api} is applied to {shown} prim; expected a BasisCurves prim (its "
                        f"curves are the fibers or yarns)", _strongest_api_layer(prim, api)))
    if YARN in apis and FIBER not in apis:
        out.append(Problem(
            "YarnWithoutFiberAPI", W, str(prim.GetPath()), None,
            "FiberYarnAPI is applied without FiberAPI, so the yarn's fibers take FiberAPI's "
            "fallback values (polyester); expected FiberAPI on the same prim describing the "
            "fiber", _strongest_api_layer(prim, YARN)))
    return out


@prim_check(
    "fiberSchema",
    "FiberAPI, FiberYarnAPI and FiberProfileAPI: applied to the right prims (fibers and "
    "yarns on BasisCurves), attributes known to the schema and authored with its types, "
    "tokens among allowedTokens, values finite and within the documented ranges (also "
    "across attributes: cuticle vs diameter, dye class vs extinction and depth of shade, "
    "spectra, user cross-section targets), at the default and every time sample.",
)
def check_fiber_schema(prim: Usd.Prim) -> list[Problem]:
    """Every usdFiber schema problem of ``prim`` (see the module docs for the codes)."""
    applied = prim.GetAppliedSchemas()
    apis = [a for a in applied if a in _APIS] if applied else []
    if not apis:
        # Fiber attributes on curves that lack the API are a common authoring slip; other
        # prims are not read at all (a stage may hold millions of them).
        if prim.GetTypeName() == "BasisCurves":
            return _not_applied(prim, _our_names(prim.GetAuthoredPropertyNames()), ())
        return []
    problems = _placement(prim, apis)
    by_api = _our_names(prim.GetAuthoredPropertyNames())
    problems += _not_applied(prim, by_api, apis)
    defs = schema_defs()
    for api in apis:
        names = by_api.get(api, [])
        known = [n for n in names if n in defs and defs[n].api == api]
        pv = PrimValues(prim, api)
        for n in names:
            if n not in known:
                close = difflib.get_close_matches(
                    n, [d for d in defs if defs[d].api == api], 1)
                hint = f"; did you mean {close[0]}?" if close else ""
                problems.append(Problem(
                    "UnknownAttribute", W, str(prim.GetPath()), n,
                    f"{n} is not a {api} attribute and is ignored{hint}",
                    strongest_layer(prim.GetProperty(n))))
        pv.read(known)
        key = pv.cache_key()
        cached = _CACHE.get(key) if key is not None else None
        if cached is None:
            _judge(pv)
            cached = tuple(pv.findings)
            pv.findings = []
            if key is not None:
                if len(_CACHE) >= _CACHE_LIMIT:
                    _CACHE.clear()
                _CACHE[key] = tuple(f for f in cached if f.layer is None)
        # Findings with an explicit layer (WrongValueType from the specs) are the prim's own.
        findings = list(pv.findings) + list(cached)
        if api == FIBER:
            findings += _profile_source_findings(pv)
        problems += pv.place(findings)
    return problems
