"""The public Python API of baked fiber BCSDFs.

Load a table file with :func:`load_table`; find (and bake on demand) the tables of a fiber
prim with :func:`tables_for_prim`. A :class:`~usdfiber.bake.table.BcsdfTable` evaluates
``p``, ``Lambda`` and ``W`` at arbitrary directions and recolours for any dye.

Far-field convention
--------------------
Fiber frame: ``t`` is the fiber tangent (the curve's direction from its first towards its
last point); ``theta`` is the angle of a direction from the plane normal to ``t``
(``sin theta = w . t``), ``phi`` its azimuth in that plane from the cross section's +x axis,
rotated by the fiber's ``psi`` (a fiber rotated by ``psi`` sees ``phi - psi``). Both
``omega_i`` (towards the light) and ``omega_o`` (towards the viewer) point away from the
fiber. Angles are radians in Python, degrees in files' headers and on the command line.

* ``W(phi)``: the width of the cross section's shadow seen from azimuth ``phi``. Per unit
  fiber length a beam from ``(theta, phi)`` meets the area ``W(phi) cos(theta)``.
* ``Lambda(omega_i)``: the albedo, the fraction of the photons meeting that area that leave
  the fiber (1 without absorption).
* ``p(omega_o | omega_i)``: where they leave, per steradian, integrating to 1 over the sphere.

No cosine is folded into any of them. The scattering cross section
``sigma(omega_i, omega_o) = W(phi_i) cos(theta_i) Lambda(omega_i) p(omega_o | omega_i)``
(power into ``omega_o`` per unit irradiance, unit length and steradian) is symmetric in its
two directions (Helmholtz reciprocity). A renderer returns, for a light from ``omega_i`` seen
from ``omega_o``, the radiance factor ``sigma(omega_i, omega_o) / (W(phi_o) cos(theta_o))``
(Mitsuba's cosine-weighted ``eval``: no extra cosine to the tube's normal; Mitsuba's ``wi`` is
our ``omega_o``). Importance sampling draws ``omega_i`` from ``p(. | omega_o)``; by reciprocity
its weight is ``Lambda(omega_o)``. With ``Lambda = 1`` and uniform incident radiance the
outgoing radiance is 1 (white furnace).

Sizes and absorption: tables are baked for a circumscribed diameter of ``baked_diameter_um``
(1 um for fibers of a stage); ``W`` is in um of that size. A fiber of diameter ``D`` um and
absorption ``mu_a`` (1/um, ``FiberParams.mu_a``) is evaluated with ``sigma_a=mu_a`` and
``diameter_scale=D / baked_diameter_um``; its width is ``W * diameter_scale``.
"""
from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Any, Callable

from pxr import Usd

from usdfiber.bake.baker import ProgressFn, is_rotationally_symmetric
from usdfiber.bake.cache import TableCache, TableCacheWarning, default_cache_dir
from usdfiber.bake.requests import requests_for_params, requests_for_prim, resolve_table_asset
from usdfiber.bake.settings import BakeError, BakeSettings, render_bake_settings
from usdfiber.bake.storage import TableLayoutError
from usdfiber.bake.table import BcsdfTable, Recoloured
from usdfiber.spec.fiber import FiberParams, FiberParamsError
from usdfiber.table_format import TableError

__all__ = [
    "BakeError",
    "BakeSettings",
    "BcsdfTable",
    "MissingTableError",
    "Recoloured",
    "TableCache",
    "TableCacheWarning",
    "TableError",
    "TableLayoutError",
    "default_cache_dir",
    "load_table",
    "render_settings_for",
    "requests_for_prim",
    "tables_for_prim",
]


class MissingTableError(LookupError):
    """A table that is neither given nor cached, with baking switched off."""


def load_table(path: str | os.PathLike[str]) -> BcsdfTable:
    """Read a table file, verifying its checksums (TableError / TableLayoutError)."""
    return BcsdfTable.load(Path(path))


def render_settings_for(request: Any, resolution_deg: float | None = None, photons: int | None = None) -> BakeSettings:
    """The settings of the table ``request`` (a :class:`usdfiber.bake.requests.TableRequest`)
    when a renderer or material writer bakes it on demand: per fiber,
    :func:`usdfiber.bake.settings.render_bake_settings` for its cross section (round or not)
    and cuticle scales; ``resolution_deg`` and ``photons``, when given, for every fiber."""
    return render_bake_settings(is_rotationally_symmetric(request.profile()), resolution_deg, photons,
                                cuticle_scales=request.cuticle_scales is not None)


def tables_for_prim(prim: Any, settings: BakeSettings | Callable[[Any], BakeSettings] | None = None,
                    bake_missing: bool = True, *,
                    cache: TableCache | None = None, time: Any = None,
                    progress: ProgressFn | None = None) -> list[BcsdfTable]:
    """The tables of a fiber prim: one per cross-section variant, in variant order.

    A prim whose ``fiber:table`` names a readable table baked for its parameters uses that
    one table for all its fibers. Otherwise the tables come from ``cache`` (default:
    :func:`default_cache_dir`) by key, baked with ``settings`` when missing (or a function of
    the table request giving them, e.g. :func:`render_settings_for`); with
    ``bake_missing=False`` a missing table raises MissingTableError. A damaged, missing or
    stale ``fiber:table`` is warned about and replaced by the cache's tables.
    """
    try:
        params = FiberParams.from_prim(prim, Usd.TimeCode.Default() if time is None else time)
    except FiberParamsError as exc:
        raise BakeError(str(exc)) from None
    if params.table:
        path = resolve_table_asset(prim)
        try:
            table = load_table(path) if path else None
        except (TableError, TableLayoutError) as exc:
            warnings.warn(f"{prim.GetPath()}: fiber:table {exc}; using the cache", RuntimeWarning, stacklevel=2)
            table = None
        if table is not None:
            if table.geometry_key == params.geometry_key():
                return [table]
            warnings.warn(f"{prim.GetPath()}: fiber:table {path} was baked for other parameters; "
                          f"using the cache", RuntimeWarning, stacklevel=2)
    cache = cache or TableCache()
    out = []
    for req in requests_for_params(params, str(prim.GetPath())):
        st = settings(req) if callable(settings) else settings or BakeSettings()
        res = cache.get_or_bake(req, st, progress, bake_missing=bake_missing)
        if res is None:
            raise MissingTableError(
                f"{prim.GetPath()}: no cached table for {req.label} (key {cache.key(req, st)}) "
                f"in {cache.root}; run `usdfiber bake` on the stage")
        out.append(res.table)
    return out
