"""The MaterialX / Hydra bridge: fitted fiber looks as USD materials and MaterialX documents.

* :mod:`~usdfiber.translators.materialx.looks`: the look of each fiber and yarn prim (the
  Chiang fit of its tables for its dye, and its mean colour under white light);
* :mod:`~usdfiber.translators.materialx.usd_material`: ``UsdShade.Material`` prims with a
  MaterialX ``chiang_hair_bsdf`` network in the UsdMtlx form, a ``UsdPreviewSurface``
  fallback and ``primvars:displayColor``, bound to the curves (:func:`author_materials`);
* :mod:`~usdfiber.translators.materialx.document`: standalone ``.mtlx`` documents, validated
  with MaterialX's own ``validate()``;
* :mod:`~usdfiber.translators.materialx.command`: ``usdfiber material``.

It depends on the core (``usdfiber``) only.
"""
from __future__ import annotations

from usdfiber.translators.materialx.looks import Look, LookError, MATERIAL_BAKE_SETTINGS, look_of_tables
from usdfiber.translators.materialx.usd_material import MaterialReport, author_materials

__all__ = ["Look", "LookError", "MATERIAL_BAKE_SETTINGS", "MaterialReport", "author_materials", "look_of_tables"]
