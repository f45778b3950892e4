"""The grid a fiber's band limit allows: ``BakeSettings(auto_resolution=True)``,
``usdfiber bake --resolution auto``.

A table needs bins and incoming nodes fine enough for its lobes only. Against the paper's
2 degree table, coarser outgoing bins ``D_o`` (the table read by its own bilinear
interpolation, averaged over each 2 degree bin) and coarser incoming nodes ``D_i`` (read
midway between nodes, the worst place) add an interpolation error, a bias that more photons
do not remove; they save directions (``(2 / D_i)^2`` as many for fibers that are not round)
and photons (a coarse bin collects more of them, so its noise at the 2 degree bins is lower).
The rule allows a grid when its measured bias (estimate plus two standard errors) is at most
HALF the error the bake aims at in every one of six probe directions over theta_i 0-85 deg,
so that noise keeps three quarters of the error budget; among the allowed grids it takes the
cheapest for that error (directions times the photons each needs, ``c_coarse^2 / (target^2
- bias^2)``). The error aimed at: ``BakeSettings.target_error``, else, per direction, that of
the plain 2 degree table at the bake's photons per direction, ``c / sqrt(N)`` with the
direction's own noise constant ``c`` (relative L2 of p, ``bench/REPORT.md`` "Error metrics").

The measurements (:data:`MEASURED`, from ``bench/bake_resolution.py``, ``bench/REPORT.md``
section 8) are of the Table 1 presets, one per kind of cross section: round (polyester),
extruded and not round (silk, cotton, mercerized cotton), with cuticle scales (wool). A
fiber takes the measurement of its kind whose roughness beta is the largest at or below its
own (the worse of two with the same beta, e.g. cotton and mercerized cotton): lobes widen
with beta, so a rougher fiber's interpolation error should be at most the measured one. The
presets bear this out for the quantity the rule compares, the bias over the plain table's
noise constant (silk 3.9e-3 against cotton 1.8e-3 for 3 deg bins and nodes); in absolute
terms cotton's 3 deg bins with 6 deg nodes (26 %) are a little worse than silk's (23 %),
both far beyond any target that grid is allowed at. A fiber smoother than every
measured one of its kind gets the paper's grid.

What the measurements say: at the paper's 16M photons per direction (and at 1M) every coarser
grid is far too coarse for every preset (its bias 5-28 % against targets of 0.3-3 %), so the
rule keeps 2 degrees there; it coarsens only tables of a few thousand to 80k photons per
direction (the renderer's kind), for rough fibers first.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["FINEST_DEG", "MEASURED", "RULE_VERSION", "Measured", "band_limited_grid"]

#: The reference grid and the finest the rule chooses (the paper's).
FINEST_DEG = 2.0
#: Bumped when the rule or its measurements change (part of the cache key of such tables).
RULE_VERSION = 1


@dataclass(frozen=True)
class Measured:
    """One preset's measurement over its probe directions: roughness, kind, the worst plain
    2 degree noise constant ``c`` (rel L2 = c / sqrt(N)), and per grid ``(D_o, D_i)``:
    ``bias`` (bias + 2 standard errors, rel L2 at the 2 degree bins, worst probe), ``kappa``
    (the worst ratio of that bias to the probe's own ``c``: the grid is allowed at N photons
    when ``kappa sqrt(N) <= 1/2``) and ``noise`` (the worst ratio of the coarse table's noise
    constant at the 2 degree bins to the plain one's)."""

    beta_deg: float
    round_profile: bool
    cuticle: bool
    c: float
    grids: dict[tuple[int, int], tuple[float, float, float]]

    def bias_ratio(self, grid: tuple[int, int], photons: int, target_error: float | None = None) -> float:
        """The grid's bias over the error aimed at (the rule allows it up to 1/2)."""
        bias, kappa, _ = self.grids[grid]
        return bias / target_error if target_error is not None else kappa * math.sqrt(max(int(photons), 1))


#: bench/results/bake_resolution.json (bench/REPORT.md section 8): 6 probe directions each,
#: 262,144 photons per direction (round fibers 524,288) in 8 batches.
MEASURED: dict[str, Measured] = {
    "silk": Measured(6.5, False, False, 59.9, {
        (2, 6): (0.2893, 7.801e-03, 1.000), (3, 3): (0.1375, 3.893e-03, 0.423),
        (3, 6): (0.2315, 8.747e-03, 0.423), (6, 6): (0.2907, 1.155e-02, 0.244),
    }),
    "cotton": Measured(15.5, False, False, 75.7, {
        (2, 6): (0.2768, 3.747e-03, 1.000), (3, 3): (0.1298, 1.757e-03, 0.418),
        (3, 6): (0.2584, 3.498e-03, 0.418), (6, 6): (0.2501, 3.386e-03, 0.231),
    }),
    "mercerizedCotton": Measured(15.5, False, False, 78.1, {
        (2, 6): (0.1008, 1.355e-03, 1.000), (3, 3): (0.0580, 9.388e-04, 0.413),
        (3, 6): (0.0974, 1.532e-03, 0.413), (6, 6): (0.1044, 2.260e-03, 0.227),
    }),
    "wool": Measured(5.0, False, True, 64.6, {
        (2, 6): (0.3273, 1.775e-02, 1.000), (3, 3): (0.1630, 8.838e-03, 0.415),
        (3, 6): (0.3472, 1.883e-02, 0.415), (6, 6): (0.4139, 2.245e-02, 0.234),
    }),
    "polyester": Measured(3.1, True, False, 30.9, {
        (2, 6): (0.5889, 4.770e-02, 1.000), (3, 3): (0.2780, 2.251e-02, 0.430),
        (3, 6): (0.5452, 4.416e-02, 0.430), (6, 6): (0.5668, 4.591e-02, 0.261),
    }),
}


def _directions(d_i: float, round_profile: bool) -> float:
    return (90.0 / d_i) * (1.0 if round_profile else 360.0 / d_i)


def _references(beta_deg: float, round_profile: bool, cuticle: bool) -> list[Measured]:
    """The measured presets of the same kind with the largest beta at or below ``beta_deg``
    (several when they share it, as cotton and mercerized cotton do)."""
    same = [m for m in MEASURED.values() if m.round_profile == round_profile and m.cuticle == cuticle
            and m.beta_deg <= beta_deg + 1e-9]
    if not same:
        return []
    top = max(m.beta_deg for m in same)
    return [m for m in same if m.beta_deg == top]


def band_limited_grid(beta_deg: float, round_profile: bool, cuticle: bool, *, photons: int,
                      target_error: float | None = None) -> tuple[float, float | None]:
    """(outgoing bin size, incoming node spacing or None for the bin size), in degrees, for a
    fiber of roughness ``beta_deg`` with a round profile or not and cuticle scales or not,
    baked at ``photons`` per direction or to ``target_error`` (see the module docstring)."""
    refs = _references(float(beta_deg), bool(round_profile), bool(cuticle))
    if not refs:
        return FINEST_DEG, None
    best, best_cost = (FINEST_DEG, FINEST_DEG), _directions(FINEST_DEG, round_profile)
    for key in sorted(set.intersection(*(set(m.grids) for m in refs))):
        # A grid must hold for every reference (the worst of presets of one roughness).
        r = max(m.bias_ratio(key, photons, target_error) for m in refs)
        if r > 0.5:
            continue
        m = max(refs, key=lambda m: m.grids[key][2])
        # Photons per direction for the same total error, relative to the plain table's: the
        # coarse table's noise (its constant squared) gets what the bias leaves.
        d_o, d_i = key
        cost = _directions(d_i, round_profile) * m.grids[key][2] ** 2 / (1.0 - r * r)
        if cost < best_cost:
            best, best_cost = (float(d_o), float(d_i)), cost
    return best[0], (None if best[1] == best[0] else best[1])
