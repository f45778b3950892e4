"""Specs: what a prim's schema values mean, resolved, checked and in the units the physics uses.

* :mod:`usdfiber.spec.attributes`: the schema's attribute names, types, fallbacks, units and
  valid ranges (one source for validators, authoring and readers).
* :mod:`usdfiber.spec.schema_data`: the names and customData facts generated from
  ``schema/schema.usda`` by :mod:`usdfiber.spec.generate`.
* :mod:`usdfiber.spec.fiber`: the fiber spec, :class:`~usdfiber.spec.fiber.FiberParams`.
* :mod:`usdfiber.spec.yarn`: the yarn spec, :class:`~usdfiber.spec.yarn.YarnParams`, and the
  yarn diameter of touching plies.

Readers raise :class:`usdfiber.errors.PrimError` subclasses naming file, prim and attribute.
"""
