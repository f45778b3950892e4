"""Mitsuba plugins written in Python: a class per Mitsuba variant, registered once per variant.

A Python plugin subclasses a variant's ``mi.BSDF`` or ``mi.SamplingIntegrator``, so its class
is defined anew for each variant (by a function of ``mi``) and kept; Mitsuba's plugin registry
is per variant too, so registering is done once per variant. :class:`VariantPlugin` holds both
for one plugin name; :func:`forwarding_bsdf` is the base of the BSDF plugins, which forward
Mitsuba's calls to a Dr.Jit model object.
"""
from __future__ import annotations

from typing import Any, Callable, Literal

__all__ = ["VariantPlugin", "forwarding_bsdf"]

_FORWARDING: dict[str, type] = {}


class VariantPlugin:
    """The Python plugin ``name`` of kind ``kind``: its class for a variant is ``define(mi)``,
    called once per variant."""

    def __init__(self, name: str, kind: Literal["bsdf", "integrator"], define: Callable[[Any], type]) -> None:
        self.name = name
        self.kind = kind
        self._define = define
        self._classes: dict[str, type] = {}
        self._registered: set[str] = set()

    def plugin_class(self, mi: Any) -> type:
        """The class for Mitsuba's active variant (defined on first use)."""
        variant = mi.variant()
        if variant not in self._classes:
            self._classes[variant] = self._define(mi)
        return self._classes[variant]

    def register(self, mi: Any) -> type:
        """Register the plugin with Mitsuba's active variant (once); returns its class."""
        cls = self.plugin_class(mi)
        variant = mi.variant()
        if variant not in self._registered:
            register = mi.register_bsdf if self.kind == "bsdf" else mi.register_integrator
            register(self.name, lambda props: cls(props))
            self._registered.add(variant)
        return cls


def forwarding_bsdf(mi: Any) -> type:
    """An ``mi.BSDF`` of the active variant whose ``eval``, ``pdf``, ``eval_pdf`` and ``sample``
    are those of its attribute ``model`` (a Dr.Jit BSDF model with Mitsuba's signatures)."""
    variant = mi.variant()
    if variant not in _FORWARDING:

        class ForwardingBsdf(mi.BSDF):
            model: Any

            def eval(self, ctx: Any, si: Any, wo: Any, active: Any = True) -> Any:
                return self.model.eval(ctx, si, wo, active)

            def pdf(self, ctx: Any, si: Any, wo: Any, active: Any = True) -> Any:
                return self.model.pdf(ctx, si, wo, active)

            def eval_pdf(self, ctx: Any, si: Any, wo: Any, active: Any = True) -> tuple[Any, Any]:
                return self.model.eval_pdf(ctx, si, wo, active)

            def sample(self, ctx: Any, si: Any, sample1: Any, sample2: Any, active: Any = True) -> tuple[Any, Any]:
                return self.model.sample(ctx, si, sample1, sample2, active)

        _FORWARDING[variant] = ForwardingBsdf
    return _FORWARDING[variant]
