"""A direction's error estimate from the spread between its batches
(:class:`usdfiber.bake.statistics.DirectionStatistics`): the running weighted moments equal the
module docstring's two-pass formula over every batch, and the state does not grow with the
number of batches (a direction may run to thousands in target-error mode)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from usdfiber.bake.baker import bake_context
from usdfiber.bake.requests import requests_from_preset
from usdfiber.bake.settings import BakeSettings
from usdfiber.bake.statistics import DirectionStatistics, mirror_phi


def _context(preset: str):
    req = requests_from_preset(preset)[0]
    return bake_context(req.profile(), req.eta, req.beta_deg, req.cuticle_scales,
                        BakeSettings(resolution_deg=10, photons=4000, batches=4))


def _two_pass(grid, hists: list[np.ndarray], norms: list[float], weights: list[float]) -> float:
    """sqrt(sum_b dOmega Var[p]) / sqrt(sum_b dOmega p^2), Var the variance of the weighted
    mean of the batches' p, from every batch kept."""
    dom = np.repeat(grid.solid_angles(), grid.n_phi_o)
    ps = np.stack([h / max(n, 1e-300) for h, n in zip(hists, norms)]) / dom
    if grid.phi_invariant:
        ps = mirror_phi(ps.reshape(len(ps), grid.n_theta_o, grid.n_phi_o)).reshape(len(ps), -1)
    w = np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    mean = w @ ps
    nB = len(ps)
    var = (w @ (ps - mean) ** 2) * nB / (nB - 1) * float((w ** 2).sum())
    return math.sqrt(float((dom * var).sum()) / float((dom * mean ** 2).sum()))


@pytest.mark.parametrize("preset", ["silk", "polyester"])    # a grid over phi_o, and one mirrored
def test_running_moments_equal_the_two_pass_error(preset):
    ctx = _context(preset)
    a = DirectionStatistics(ctx, 2, 0)
    assert a.error() == math.inf                     # no batches: no estimate
    rng = np.random.default_rng(3)
    hists, norms, weights = [], [], []
    for b in range(40):
        # Batches that differ in size and weight (box bins weigh batches by their beam's power),
        # one with no light at all; counts near a large mean, where a one-pass sum of squares
        # would lose digits and West's update must not.
        h = rng.poisson(1e4, a.nb).astype(np.float64) * (rng.random(a.nb) < 0.3)
        n = float(rng.integers(5_000, 20_000)) if b != 7 else 0.0
        h = h if n > 0 else 0.0 * h                  # no photon met: nothing binned
        w = float(rng.uniform(0.5, 2.0)) * n
        a._add_moments(h / max(n, 1e-300), w)
        hists.append(h), norms.append(n), weights.append(w)
        if b >= 1:
            assert a.error() == pytest.approx(_two_pass(ctx.grid, hists, norms, weights), rel=1e-9)
    assert a.weight_sum == pytest.approx(sum(weights), rel=1e-15)


def test_state_does_not_grow_with_batches():
    ctx = _context("silk")
    a = DirectionStatistics(ctx, 2, 0)

    def held() -> int:
        return sum(v.nbytes for v in vars(a).values() if isinstance(v, np.ndarray)) + sum(
            len(v) for v in vars(a).values() if isinstance(v, list))

    h = np.ones(a.nb)
    a._add_moments(h, 1.0)
    before = held()
    for _ in range(500):
        a._add_moments(h, 1.0)
    assert held() == before


def test_target_error_mode_stops_where_no_light_left():
    """A direction whose batches carried no light has an infinite error estimate; in
    target-error mode it is not given more batches (none could lower it), and nothing raises."""
    req = requests_from_preset("silk")[0]
    ctx = bake_context(req.profile(), req.eta, req.beta_deg, req.cuticle_scales,
                       BakeSettings(resolution_deg=10, photons=4000, batches=4, target_error=0.01))
    a = DirectionStatistics(ctx, 2, 0)
    a.queue = []
    for _ in range(4):
        a._add_moments(np.zeros(a.nb), 0.0)
    a.plan_more(1000)
    assert a.err == math.inf and a.queue == []
