"""Attributes authored with another type than their schema's.

USD keeps an attribute's authored type, whatever its schema says: ``float widths = 0.01``
(a scalar where BasisCurves has ``float[]``), ``float4 clippingRange`` on a camera,
``int curveVertexCounts = 48``. Readers then see a value of the wrong shape, or, through a
schema's typed getters, silently the fallback, and a render goes wrong far from the cause.

Codes (E = error), on every prim, for every attribute that its prim definition (type and
applied schemas) declares, except the fiber, yarn and profile attributes (whose types and values
:mod:`usdfiber.validation.values` and :mod:`usdfiber.validation.assets` check, ``WrongValueType``):

- ``AttributeTypeMismatch`` (E): the attribute is authored with another value type than the
  schema's (the message names both).
- ``AttributeTokenNotAllowed`` (E): a token attribute's value (default or a time sample) is not
  among its schema's ``allowedTokens`` (``purpose = "bogus"`` hides a prim from every render
  purpose). The fiber and yarn attributes and a curve's ``basis``, ``type`` and ``wrap`` are
  checked, with their own codes, by :mod:`usdfiber.validation.values` and
  :mod:`usdfiber.validation.topology`.
"""
from __future__ import annotations

from typing import Sequence

from pxr import Sdf, Usd

from usdfiber.validation.problems import Problem, Severity, prim_check
from usdfiber.validation.values import strongest_layer


def check_attribute_types(prim: Usd.Prim) -> list[Problem]:
    """``AttributeTypeMismatch`` problems of ``prim`` (see the module docstring)."""
    definition = prim.GetPrimDefinition()
    out: list[Problem] = []
    for attr in prim.GetAuthoredAttributes():
        spec = definition.GetAttributeDefinition(attr.GetName())
        if not spec or attr.GetName().startswith(("fiber:", "yarn:", "fiberProfile:")):  # WrongValueType
            continue
        # The attribute's own GetTypeName() reports the definition's type; the authored one is
        # the strongest spec's.
        stack = attr.GetPropertyStack()
        want, got = spec.GetTypeName(), (stack[0].typeName if stack else spec.GetTypeName())
        if got == want == Sdf.ValueTypeNames.Token and not _checked_elsewhere(attr.GetName()):
            out.extend(_token_problems(prim, attr, spec))
        if got != want:
            out.append(Problem("AttributeTypeMismatch", Severity.ERROR, str(prim.GetPath()), attr.GetName(),
                               f"authored as {got}; expected {want}, the type of {prim.GetTypeName() or 'its'} "
                               f"schema's {attr.GetName()}", layer=strongest_layer(attr)))
    return out


#: Token attributes whose values other checks report (their own codes).
_ELSEWHERE_NAMES = frozenset({"basis", "type", "wrap"})


def _checked_elsewhere(name: str) -> bool:
    return name in _ELSEWHERE_NAMES or name.startswith(("fiber:", "yarn:", "fiberProfile:"))


def _token_problems(prim: Usd.Prim, attr: Usd.Attribute, spec: Sdf.AttributeSpec) -> list[Problem]:
    allowed = spec.GetMetadata("allowedTokens")
    if not allowed:
        return []
    allowed = [str(t) for t in allowed]
    times: list[float | None] = [None] + list(attr.GetTimeSamples()[:100])
    for t in times:
        value = attr.Get() if t is None else attr.Get(t)
        if value is not None and str(value) not in allowed:
            at = "" if t is None else f" at time {t:g}"
            return [Problem("AttributeTokenNotAllowed", Severity.ERROR, str(prim.GetPath()), attr.GetName(),
                            f"is {str(value)!r}{at}; expected one of {', '.join(allowed)}",
                            layer=strongest_layer(attr, t), time=t)]
    return []


@prim_check(
    "attributeTypes",
    "Attributes authored with another value type than their schema declares (a scalar for an "
    "array, float4 for float2): readers would see the wrong shape or the fallback.",
)
def _check_attribute_types(prim: Usd.Prim) -> Sequence[Problem]:
    return check_attribute_types(prim)
