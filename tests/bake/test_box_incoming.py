"""Box-filtered incoming bins: every photon draws its own light direction in the bin.

A box bin's entry is (1/|I|) integral over I of W(phi) cos(theta) p(o | i) di (what makes
the table reciprocal bin for bin). The tracer draws each photon's direction with density
cos^2(theta) (solid angle times the cos of the power; W through the fixed launch width), so
every photon that meets the fiber carries the same power and a batch weighs the bin's power
:func:`~usdfiber.bake.sampling.box_power`. Checked: the inversion of the latitude's CDF
(deterministic), the power (against a brute-force integral) and the histograms against an
independent estimator of the same average: light directions at random points of the bin,
each weighted by W cos there (statistical; false failure 1e-4).
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from usdfiber.bake import profiles, tracer
from usdfiber.bake.grid import Grid
from usdfiber.bake.sampling import box_power, cos2_latitude
from usdfiber.bake.statistics import level_histograms

from stats_util import compare_blocks

ETA = 1.55
BINS = [(0.0, 2.0), (88.0, 90.0), (-1.0, 1.0), (50.0, 70.0), (-90.0, -85.0)]


def _g(t):
    return t + np.sin(t) * np.cos(t)


@pytest.mark.parametrize("lo_deg,hi_deg", BINS)
def test_cos2_latitude_inverts_its_cdf(lo_deg, hi_deg):
    a, b = math.radians(lo_deg), math.radians(hi_deg)
    u = np.concatenate([np.linspace(0.0, 1.0, 4097)[:-1], [0.5, 1.0 - 2.0 ** -53]])
    t = cos2_latitude(a, b, u)
    assert np.all((t >= a) & (t <= b))
    target = _g(a) * (1.0 - u) + _g(b) * u
    assert np.abs(_g(t) - target).max() <= 1e-9 * (_g(b) - _g(a))
    assert np.all(np.diff(t[:4096]) >= 0.0)     # monotone in u: an inverse CDF


def test_cos2_latitude_in_the_kernel_matches_numpy():
    from usdfiber.backend import mitsuba

    mi = mitsuba()
    u = np.random.default_rng(3).random(1000)
    for lo, hi in BINS:
        a, b = math.radians(lo), math.radians(hi)
        ours = np.asarray(cos2_latitude(mi.Float64(a), mi.Float64(b), mi.Float64(u)))
        np.testing.assert_allclose(ours, cos2_latitude(a, b, u), rtol=0.0, atol=1e-12)


def test_box_power_is_the_bin_integral():
    prof = profiles.ellipse(0.5, 0.3).centered().scaled_to_diameter(1.0)
    t0, t1, p0, p1 = math.radians(50), math.radians(70), math.radians(20), math.radians(40)
    widths = prof.projected_width(np.linspace(p0, p1, 33))
    ours = box_power(t0, t1, widths)
    # Brute force: midpoint rule in (theta, phi), solid angle cos(theta) dtheta dphi.
    th = t0 + (np.arange(2000) + 0.5) * (t1 - t0) / 2000
    ph = p0 + (np.arange(400) + 0.5) * (p1 - p0) / 400
    w = prof.projected_width(ph)
    num = (w[None, :] * (np.cos(th) ** 2)[:, None]).sum()
    den = (np.cos(th)[:, None] * np.ones_like(w)[None, :]).sum()
    assert ours == pytest.approx(num / den, rel=1e-5)
    # One azimuth: W there times the mean of cos over the latitudes in solid angle.
    one = box_power(t0, t1, np.array([widths[0]]))
    assert one == pytest.approx(widths[0] * (np.cos(th) ** 2).sum() / np.cos(th).sum(), rel=1e-6)


def test_photons_spread_over_the_bin_estimate_its_average():
    """Bin by bin (6 deg bins) on a rough ellipse, a 20 x 20 deg incoming bin: 6 batches of
    2^16 photons drawing their own directions against 6 batches of 64 jittered points of the
    bin x 1024 photons each, weighted by W cos there. ``compare_blocks``: false failure 1e-4.
    Directions drawn uniformly in solid angle instead of cos^2 (the power left out) fail it
    (block variance ratio 1.95 against its limit of 1.37, checked by hand)."""
    prof = profiles.ellipse(0.5, 0.3).centered().scaled_to_diameter(1.0)
    fs = tracer.prepare(prof)
    grid, beta = Grid(6.0), 10.0
    t0, t1, p0, p1 = math.radians(50), math.radians(70), math.radians(20), math.radians(40)
    widths = prof.projected_width(np.linspace(p0, p1, 33))
    power = box_power(t0, t1, widths)
    levels = np.array([0.0, 0.5])

    def hist(r, weight):
        h, _ = level_histograms(r, grid, levels)
        return (h.reshape(len(levels), grid.n_theta_o, grid.n_phi_o) * weight / r.n_hit).transpose(1, 2, 0)

    node = (0.5 * (t0 + t1), 0.5 * (p0 + p1))
    spread = [hist(r, power) for r in tracer.trace_many(
        fs, [node] * 6, 1 << 16, eta=ETA, beta_deg=beta, seed=list(range(100, 106)),
        spread=[(t0, t1, p0, p1)] * 6)]
    rng = np.random.default_rng(5)
    points = []
    for k in range(6):
        # Jittered 8 x 8 strata, uniform in solid angle: unbiased, and the variation of p
        # over the bin hardly adds to the noise.
        s0, s1 = math.sin(t0), math.sin(t1)
        cell = np.stack(np.meshgrid(np.arange(8), np.arange(8), indexing="ij"), -1).reshape(-1, 2)
        u = (cell + rng.random(cell.shape)) / 8.0
        th = np.arcsin(s0 + u[:, 0] * (s1 - s0))
        ph = p0 + u[:, 1] * (p1 - p0)
        rs = tracer.trace_many(fs, list(zip(th, ph)), 1024, eta=ETA, beta_deg=beta,
                               seed=[1000 * k + j for j in range(64)])
        points.append(np.mean([hist(r, float(prof.projected_width(q)) * math.cos(t))
                               for r, t, q in zip(rs, th, ph)], axis=0))
    c = compare_blocks(spread, points, block=1)
    assert c.agrees(), c


def test_spread_is_checked():
    fs = tracer.prepare(profiles.circle())
    with pytest.raises(ValueError, match="one bin per direction"):
        tracer.trace_many(fs, [(0.1, 0.0)], 16, eta=ETA, beta_deg=5.0, spread=[])
    with pytest.raises(ValueError, match="is not a bin"):
        tracer.trace_many(fs, [(0.1, 0.0)], 16, eta=ETA, beta_deg=5.0, spread=[(0.2, 0.1, 0.0, 0.0)])
    cut = tracer.prepare(profiles.circle(), (3.0, 0.02, 0.5))
    with pytest.raises(ValueError, match="extruded"):
        tracer.trace_many(cut, [(0.1, 0.0)], 16, eta=ETA, beta_deg=5.0, spread=[(0.0, 0.2, 0.0, 0.0)])
