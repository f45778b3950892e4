"""Standard fiber models fitted to baked tables (Aliaga et al. 2017, Figures 9, 10 and 12).

* :mod:`usdfiber.fit.chiang`: Chiang et al. 2016 / d'Eon et al. 2011, the model of Mitsuba's
  ``hair`` BSDF and MaterialX's ``chiang_hair_bsdf`` (:class:`ChiangParams` converts to both);
* :mod:`usdfiber.fit.khungurn`: Khungurn et al. 2015's fabric fiber model;
* :mod:`usdfiber.fit.objective`: what is compared (the rotation-averaged scattering over the
  sphere on the table's grid) and the errors reported;
* :mod:`usdfiber.fit.cache`: fits cached beside their tables.

Typical use::

    from usdfiber.bcsdf import tables_for_prim
    from usdfiber.fit import FitSettings, fit_tables

    tables = tables_for_prim(prim)
    res = fit_tables(tables, "chiang", sigma_a=params.mu_a, diameter_scale=params.diameter)
    res.params.to_mitsuba(), res.error["rel_l2"]
"""
from __future__ import annotations

from usdfiber.fit.cache import FitCache, fit_key, table_identity
from usdfiber.fit.chiang import ChiangParams
from usdfiber.fit.fitting import MODELS, UnknownModelError, check_model, fit_tables, fit_target, model_values
from usdfiber.fit.khungurn import KhungurnParams
from usdfiber.fit.objective import FitTarget
from usdfiber.fit.result import FitResult, FitSettings

__all__ = [
    "ChiangParams", "FitCache", "FitResult", "FitSettings", "FitTarget", "KhungurnParams", "MODELS",
    "UnknownModelError", "check_model", "fit_key", "fit_tables", "fit_target", "model_values", "table_identity",
]
