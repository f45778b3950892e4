"""Fiber curves rendered with a standard model fitted to their tables (``usdfiber render --model``).

Aliaga et al. compare their tables with fitted parametric models (Figures 9, 10 and 12); this
renders the same stage with either (:data:`RENDER_MODELS`):

* ``table``: the tabulated BCSDF (:mod:`.fiber_bsdf`), the default;
* ``chiang``: Mitsuba's built-in ``hair`` BSDF (Chiang et al. 2016) with the parameters
  :func:`usdfiber.fit.fit_tables` finds for each fiber slot (cross-section table and colour),
  without lobe tints (``hair`` has none). ``hair`` uses the frame Mitsuba's curves give (local
  y the tangent) and derives the offset h from the hit, so it needs no per-segment data:
  each slot becomes its own curve shape;
* ``khungurn``: Khungurn et al. 2015 (:mod:`.khungurn_bsdf`), one BSDF for all curves with
  per-slot parameters.

Both fitted models are rotation-averaged and opaque: the cross section's rotation ``psi`` and
the pass-through of non-round profiles (``W < D``) are the table's alone. Yarn far fields have
no fitted model (render them with ``--lod-scale 0``, or with the table).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from usdfiber.bake.table import BcsdfTable
from usdfiber.fit import FitResult, FitSettings, fit_tables
from usdfiber.geometry.curves import CurveGeometry

from usdfiber.translators.mitsuba.curves import make_curve_shape
from usdfiber.translators.mitsuba.errors import TranslateError
from usdfiber.translators.mitsuba.fibers import FiberTranslation

__all__ = ["RENDER_MODELS", "check_render_model", "fit_slots", "fitted_fiber_shapes"]

#: The fiber models ``usdfiber render --model`` knows.
RENDER_MODELS = ("table", "chiang", "khungurn")


def check_render_model(model: str) -> str:
    """``model`` if it is one of :data:`RENDER_MODELS`, else ValueError with a one-line message."""
    if model not in RENDER_MODELS:
        raise ValueError(f"unknown fiber model {model!r}; valid: {', '.join(RENDER_MODELS)}")
    return model


def fit_slots(fibers: FiberTranslation, model: str, settings: FitSettings | None = None) -> list[FitResult]:
    """The fit of ``model`` to each slot of ``fibers`` (its table recoloured for the slot's
    colour), cached beside the table like any fit. TranslateError for a yarn far field."""
    st = settings or FitSettings(tints=False)
    out = []
    for k, slot in enumerate(fibers.bank.slots):
        if not isinstance(slot.table, BcsdfTable):
            raise TranslateError(f"--model {model}: slot {k} is a yarn far field, which has no fitted model; "
                                 f"render with --model table, or --lod-scale 0 to draw every fiber")
        try:
            out.append(fit_tables([slot.table], model, sigma_a=list(slot.sigma_a), diameter_scale=1.0,
                                  settings=st))
        except ValueError as exc:
            raise TranslateError(f"--model {model}: cannot fit slot {k}: {exc}") from None
    return out


def _segments(geom: CurveGeometry, keep: np.ndarray) -> CurveGeometry:
    """The segments ``keep`` (mask) of ``geom``, sharing its control points."""
    return CurveGeometry(geom.points, geom.radii, geom.segment_start[keep], geom.segment_curve[keep],
                         geom.curve_count, [])


def fitted_fiber_shapes(mi: Any, fibers: FiberTranslation, model: str,
                        settings: FitSettings | None = None) -> tuple[dict[str, Any], list[FitResult]]:
    """Scene entries (id -> shape) drawing ``fibers`` with the fitted ``model`` (``chiang`` or
    ``khungurn``), and the fits per slot."""
    check_render_model(model)
    if model == "table":
        raise ValueError("the table model is the tabulated BCSDF (fiber_bsdf), not a fit")
    fits = fit_slots(fibers, model, settings)
    geom = fibers.geometry
    if model == "chiang":
        entries = {}
        for k, fit in enumerate(fits):
            keep = fibers.seg_slot == k
            if not keep.any():
                continue
            bsdf = mi.load_dict(fit.params.to_mitsuba())
            entries[f"fibers_{k}"] = make_curve_shape(_segments(geom, keep), bsdf, f"fibers_{k}")
        return entries, fits
    from usdfiber.translators.mitsuba.khungurn_bsdf import khungurn_bsdf

    bsdf = khungurn_bsdf(mi, [f.params for f in fits], fibers.seg_slot)
    return {"fibers": make_curve_shape(geom, bsdf, "fibers")}, fits
