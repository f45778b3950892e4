"""The look of a fiber prim: a Chiang fit of its tables for its dye, and its mean colour.

The fit (:func:`usdfiber.fit.fit_tables`, model ``chiang`` with lobe tints, the inputs of
MaterialX's ``chiang_hair_bsdf``) is of the prim's tables (all cross-section variants,
averaged over rotations) recoloured for the prim's dye and diameter.

Mean colour: under uniform white light of radiance 1 a fiber seen from ``omega`` has
radiance ``Lambda(omega)`` (reciprocity; ``usdfiber.bcsdf``). Averaged over viewing
directions uniform on the sphere, weighted by the area the fiber shows (``W(phi) cos
theta``), over rotations and variants::

    colour = sum Lambda W(phi) cos^2(theta) / sum W(phi) cos^2(theta)

over the tables' incoming nodes (one more ``cos theta`` is the solid angle of a node). It
is linear Rec.709, the scene's rendering space, as ``primvars:displayColor`` is. A yarn
prim gets the colour of its fibers: the light its fibers scatter between each other is not
included (a yarn looks deeper than this: its own albedo is 0.25-0.58 of its fibers' per
channel on the Table 3 threads, ``bench/yarn_colour_bench.py``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from usdfiber.bcsdf import render_settings_for
from usdfiber.fit import ChiangParams, FitCache, FitResult, FitSettings, fit_tables

__all__ = ["Look", "LookError", "MATERIAL_BAKE_SETTINGS", "MATERIAL_FIT_SETTINGS", "look_of_tables", "mean_colour"]

#: Tables baked for materials: the render's, per fiber (a function of the table request,
#: :func:`usdfiber.bcsdf.render_settings_for`), so that both share the cache.
MATERIAL_BAKE_SETTINGS = render_settings_for
#: Fits for materials: Chiang with MaterialX's lobe tints.
MATERIAL_FIT_SETTINGS = FitSettings(tints=True)


class LookError(ValueError):
    """A stage or prim that cannot be given materials (one line: file, prim, what is wrong)."""


@dataclass(frozen=True)
class Look:
    """One fiber look: the fitted model, its error and the mean colour (linear Rec.709)."""

    key: str                      # the fit's cache key
    kind: str                     # fiber kind (for names)
    params: ChiangParams
    colour: tuple[float, float, float]
    rel_l2: tuple[float, ...]     # the fit's error per channel

    @classmethod
    def from_fit(cls, fit: FitResult, kind: str, colour: Sequence[float]) -> "Look":
        return cls(fit.key, kind, fit.params, tuple(float(c) for c in colour), tuple(fit.error["rel_l2"]))


def mean_colour(tables: Sequence[Any], sigma_a: Sequence[float], diameter_scale: float) -> np.ndarray:
    """The mean colour under white light (module docstring), one value per channel."""
    num = 0.0
    den = 0.0
    for t in tables:
        g = t.grid
        rec = t.recolour(list(sigma_a), diameter_scale)
        w = t.width(g.phi_i_nodes())[None, :] * (np.cos(g.theta_i_nodes()) ** 2)[:, None]   # (n_ti, n_pi)
        num = num + (w[..., None] * rec.albedo.astype(np.float64)).sum(axis=(0, 1))
        den = den + float(w.sum())
    return np.asarray(num) / den


def look_of_tables(tables: Sequence[Any], kind: str, mu_a: Sequence[float], diameter_um: float,
                   fit_cache: FitCache | None, settings: FitSettings = MATERIAL_FIT_SETTINGS) -> Look:
    """The look of a fiber of ``diameter_um`` with absorption ``mu_a`` (1/um per channel)."""
    ds = float(diameter_um) / tables[0].baked_diameter_um
    mu = [float(x) for x in mu_a]
    if not all(math.isfinite(x) and x >= 0 for x in mu):
        raise LookError(f"absorption must be finite and >= 0, got {mu}")
    fit = fit_tables(tables, "chiang", mu, ds, settings, cache=fit_cache if fit_cache is not None else False)
    return Look.from_fit(fit, kind, mean_colour(tables, mu, ds))
