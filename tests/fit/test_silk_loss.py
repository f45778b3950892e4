"""What a fitted round-fiber model loses on silk (Aliaga et al. Figures 9, 10 and 12).

A Chiang et al. 2016 model (Mitsuba's ``hair``, MaterialX's ``chiang_hair_bsdf``) is fitted
to the table of a round smooth polyester fiber and to the table of silk's rounded-triangle
cross section, and compared with each table over the sphere, independently of the fit
(``fit_independent``: the table through ``cross_section`` at bin centres averaged over
rotations, the model point by point). A rendered image hides the difference (the mean
radiance of a lit silk fiber matches within 0.4 %); the scattering over directions does not.

Noise. Each table is baked twice, with seeds 0 and 1. ``d`` = the relative L2 difference
of the two (the same metric, the second table in place of a model) measures the table's
noise: the fitted model's error against the noiseless table differs from its error against
a baked one by at most ``||A - T|| / ||A||`` (triangle inequality), whose expectation is
``d / sqrt(2)``. Both norms are sums over independently traced incoming directions; taking
only the ``n`` theta_i nodes as their degrees of freedom (the silk tables trace n x 24
directions), ``||A - T||^2 / (||A - B||^2 / 2)`` is at most F(n, n), so ``c d / sqrt(2)``
with ``c^2`` = F(n, n)'s 1e-4 quantile bounds the noise's effect with false-failure
probability 1e-4 per assertion (``stats_util.FALSE_FAILURE``).

Measured (Xeon, AVX-512): polyester 0.096 (d = 0.017), silk 0.571 (d = 0.017); 33-64 s on 2
shared cores at load average 7-11 (four bakes, two fits, the models' point evaluation).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

import usdfiber  # noqa: F401
from usdfiber.bake import profiles
from usdfiber.bake.baker import bake_table
from usdfiber.bcsdf import BakeSettings
from usdfiber.fit import fit_tables

from fit_independent import model_scattering, relative_l2, table_scattering
from stats_util import FALSE_FAILURE

#: The fitted Chiang model of a round smooth fiber is within this relative L2 of its table
#: over the sphere (what is left is the table's own noise and d'Eon's longitudinal lobe shape).
ROUND_BOUND = 0.2
#: Silk's fitted Chiang model is further than this from its table: the round model cannot
#: carry the triangle's azimuthal structure. Above the two seeds' difference (asserted).
SILK_FLOOR = 0.35

#: (profile, eta, beta deg, grid deg, photons): Table 1's polyester and silk, authored values.
FIBERS = {
    "polyester": (profiles.circle, 1.54, 3.1, 15.0, 40_000),
    "silk": (lambda: profiles.builtin_profiles("silk", 1)[0], 1.538, 6.5, 15.0, 10_000),
}


@pytest.fixture(scope="module")
def compared():
    out = {}
    for name, (prof, eta, beta, res, photons) in FIBERS.items():
        a, b = (bake_table(prof(), eta, beta, None,
                           BakeSettings(resolution_deg=res, photons=photons, batches=2, seed=seed),
                           header={"eta": eta})
                for seed in (0, 1))
        fit = fit_tables([a], "chiang", cache=False)
        ref_a, ref_b = table_scattering(a, [0.0]), table_scattering(b, [0.0])
        model = model_scattering(a.grid, "chiang", fit.params, k=6, n_h=48)
        out[name] = {
            "error": float(relative_l2(model, ref_a, a.grid)[0]),
            "reported": float(fit.error["rel_l2"][0]),
            "seeds": float(relative_l2(ref_b, ref_a, a.grid)[0]),
            "dof": a.grid.n_theta_i,
        }
    return out


def _noise(c: dict) -> float:
    """The 1e-4 bound on how far table noise moves the error (module docstring)."""
    k = math.sqrt(float(stats.f.isf(FALSE_FAILURE, c["dof"], c["dof"])))
    return k * c["seeds"] / math.sqrt(2.0)


def test_chiang_matches_round_polyester(compared):
    c = compared["polyester"]
    print(f"\n[silk-loss] polyester: chiang vs table {c['error']:.3f} (fit reports {c['reported']:.3f}), "
          f"seeds differ by {c['seeds']:.3f}, noise bound {_noise(c):.3f}")
    assert c["error"] + _noise(c) <= ROUND_BOUND, c


def test_chiang_misses_silk(compared):
    c, r = compared["silk"], compared["polyester"]
    print(f"\n[silk-loss] silk: chiang vs table {c['error']:.3f} (fit reports {c['reported']:.3f}), "
          f"seeds differ by {c['seeds']:.3f}, noise bound {_noise(c):.3f}")
    # The floor is above what the table itself scores as a model (its other seed): a model as
    # good as the table fails the next assertion.
    assert c["seeds"] + _noise(c) < SILK_FLOOR, c
    assert c["error"] - _noise(c) > SILK_FLOOR, c
    # and the loss is silk's, not the model's: beyond the round fiber's error and both noises
    assert c["error"] - _noise(c) > r["error"] + _noise(r), (c, r)
    # the fit's own report (bin masses) tells the same story as the independent evaluation
    assert np.isclose(c["reported"], c["error"], rtol=0.1) and c["reported"] > SILK_FLOOR
