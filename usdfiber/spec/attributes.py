"""The schema's attributes in one place: names, types, fallbacks, units and valid ranges.

Names are constants (:class:`Fiber`, :class:`Yarn`, :class:`Profile`, generated from
``schema/schema.usda`` into :mod:`usdfiber.spec.schema_data`); type, variability, fallback
and allowed tokens come from USD's schema registry; units and ranges from each attribute's
``usdFiber`` customData in ``schema/schema.usda`` (through the generated module, since
usdGenSchema does not carry property customData into the registry). The validators, the
authoring API and the spec readers take their names and ranges from here, so a schema
change they do not follow fails a test (``tests/spec/test_attributes.py``).

Ranges are :class:`Interval` values parsed from the schema's interval notation:
``"(0, 1000]"``, ``"[0, inf)"``, ``"(-inf, inf)"``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any, Mapping

from usdfiber.spec.schema_data import FACTS, PROPERTIES, Fiber, Profile, Yarn

__all__ = [
    "AttributeSpec", "Fiber", "Interval", "Profile", "Yarn", "attribute", "attributes",
    "industry_extinction_ranges", "parse_interval", "spectrum_coverage",
]


def _num(x: float) -> str:
    if math.isinf(x):
        return "inf" if x > 0 else "-inf"
    return f"{x:.6g}"


@dataclass(frozen=True)
class Interval:
    """A closed, open or half-open interval of valid values."""

    lo: float = -math.inf
    hi: float = math.inf
    lo_open: bool = False
    hi_open: bool = False

    def __contains__(self, x: float) -> bool:
        if x < self.lo or (self.lo_open and x == self.lo):
            return False
        return not (x > self.hi or (self.hi_open and x == self.hi))

    def __str__(self) -> str:
        left = "(" if self.lo_open or self.lo == -math.inf else "["
        right = ")" if self.hi_open or self.hi == math.inf else "]"
        return f"{left}{_num(self.lo)}, {_num(self.hi)}{right}"


def parse_interval(text: str) -> Interval:
    """``"(0, 1000]"`` -> Interval(0, 1000, lo_open=True); ValueError for anything else."""
    t = text.strip()
    if len(t) < 5 or t[0] not in "[(" or t[-1] not in "])" or "," not in t:
        raise ValueError(f"not an interval: {text!r} (expected e.g. \"(0, 1000]\")")
    lo_s, hi_s = (s.strip() for s in t[1:-1].split(",", 1))
    lo, hi = float(lo_s), float(hi_s)
    if math.isnan(lo) or math.isnan(hi) or lo > hi:
        raise ValueError(f"not an interval: {text!r}")
    return Interval(lo, hi, t[0] == "(" and lo != -math.inf, t[-1] == ")" and hi != math.inf)


@dataclass(frozen=True)
class AttributeSpec:
    """What the schema says about one property of FiberAPI, FiberYarnAPI or FiberProfileAPI."""

    api: str
    name: str
    type_name: str                       # USD value type ("float", "color3f", ...); "" for relationships
    uniform: bool
    fallback: Any
    allowed_tokens: tuple[str, ...] | None
    is_relationship: bool = False
    unit: str = ""
    valid: Interval | None = None        # each component's range for vectors
    industry: Interval | None = None     # values outside it are warned about
    components: tuple[str, ...] = ()     # labels of a vector's components
    component_valid: tuple[Interval, ...] | None = None  # where components differ
    facts: Mapping[str, Any] = field(default_factory=dict)  # the raw customData "usdFiber"

    def component_ranges(self, n: int) -> tuple[Interval, ...]:
        """The valid range of each of ``n`` components."""
        if self.component_valid is not None:
            return self.component_valid
        return tuple(self.valid or Interval() for _ in range(n))


def _spec(api: str, name: str, prim_def: Any) -> AttributeSpec:
    facts = dict(FACTS.get(name, {}))
    valid = parse_interval(facts["validRange"]) if "validRange" in facts else None
    industry = parse_interval(facts["industryRange"]) if "industryRange" in facts else None
    comp_valid = (tuple(parse_interval(r) for r in facts["componentRanges"])
                  if "componentRanges" in facts else None)
    common = dict(unit=facts.get("unit", ""), valid=valid, industry=industry,
                  components=tuple(facts.get("components", ())), component_valid=comp_valid,
                  facts=facts)
    attr = prim_def.GetAttributeDefinition(name) if prim_def is not None else None
    if not attr:
        return AttributeSpec(api, name, "", True, None, None, True, **common)
    from pxr import Sdf

    allowed = attr.GetMetadata("allowedTokens")
    return AttributeSpec(api, name, str(attr.GetTypeName()),
                         attr.GetVariability() == Sdf.VariabilityUniform, attr.GetFallbackValue(),
                         tuple(str(t) for t in allowed) if allowed else None, False, **common)


@lru_cache(maxsize=None)
def _all() -> dict[str, AttributeSpec]:
    from pxr import Usd

    reg = Usd.SchemaRegistry()
    out: dict[str, AttributeSpec] = {}
    for api, names in PROPERTIES.items():
        prim_def = reg.FindAppliedAPIPrimDefinition(api)
        if prim_def is None:
            raise LookupError(f"{api} is not registered with USD (import usdfiber before opening "
                              "any stage)")
        for name in names:
            out[name] = _spec(api, name, prim_def)
    return out


def attributes(api: str | None = None) -> dict[str, AttributeSpec]:
    """Every property of ``api`` (or of all three APIs), by name, in schema order."""
    specs = _all()
    return {n: s for n, s in specs.items() if api is None or s.api == api}


def attribute(name: str) -> AttributeSpec:
    """The spec of the schema property ``name``; KeyError naming it otherwise."""
    try:
        return _all()[name]
    except KeyError:
        raise KeyError(f"{name} is not a usdFiber schema property") from None


def industry_extinction_ranges() -> dict[str, Interval]:
    """Each dye class's industry range of extinction per gram, L mg^-1 cm^-1 (Section 3.1)."""
    facts = FACTS[Fiber.DYE_CLASS]["industryExtinctionRange"]
    return {cls: parse_interval(r) for cls, r in facts.items()}


def spectrum_coverage() -> Interval:
    """The wavelengths (nm) a spectral extinction must span (``requiredCoverage``)."""
    return parse_interval(FACTS[Fiber.DYE_SPECTRUM_WAVELENGTHS]["requiredCoverage"])
