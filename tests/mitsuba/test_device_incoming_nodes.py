"""The renderer's device lookup of a table whose incoming nodes are coarser than its bins."""
from __future__ import annotations

import math

import numpy as np
import pytest

import usdfiber  # noqa: F401  (registers schemas first)
from usdfiber.backend import mitsuba
from usdfiber.bake import profiles
from usdfiber.bake.baker import bake_table
from usdfiber.bake.lookup import incoming_nodes
from usdfiber.bake.settings import BakeSettings

from usdfiber.translators.mitsuba.fiber_bank import FiberBank, FiberSlot, bilinear_integral
from usdfiber.translators.mitsuba.fiber_bsdf import FamilyDevice

mi = mitsuba()

ETA = 1.55


@pytest.fixture(scope="module")
def coarse_tables():
    """Silk (non-round) and a circle (round), 15 deg bins, incoming nodes 30 deg apart."""
    st = BakeSettings(resolution_deg=15, incoming_deg=30, photons=2000, batches=2)
    silk = bake_table(profiles.builtin_profiles("silk", 1)[0], ETA, 8.0, None, st)
    circle = bake_table(profiles.circle(), ETA, 8.0, None, st)
    return silk, circle


@pytest.mark.parametrize("which", [0, 1])
def test_device_lookup_agrees_with_numpy(coarse_tables, which):
    table = coarse_tables[which]
    g = table.grid
    bank = FiberBank.build([FiberSlot(table, (0.2, 0.5, 1.0))])
    fam = bank.families[g.phi_invariant]
    # The family keeps the table's coarse incoming nodes (mirrored through theta = 0).
    assert fam.incoming_deg == 30.0 and fam.resolution_deg == 15.0
    assert fam.pdf.shape[1:3] == (2 * g.n_theta_i, 1 if g.phi_invariant else g.n_phi_i + 1)
    # Normalized before float16 rounding (2^-11 relative per node): the integrals within 5e-4.
    assert np.allclose(bilinear_integral(fam.pdf.astype(np.float64)), 1.0, atol=5e-4)
    # Only the theta_v >= 0 half is stored; the other half is read as its mirror.
    assert fam.mirrored and fam.nodes[0].shape[0] == g.n_theta_i
    dev = FamilyDevice(fam)
    rng = np.random.default_rng(7)
    n = 2000
    th_v = rng.uniform(-0.5 * math.pi, 0.5 * math.pi, n)
    ph_v = rng.uniform(0.0, 2 * math.pi, n)
    h, w = fam.pdf.shape[-2:]
    i, j = rng.integers(0, w, n), rng.integers(0, h, n)       # slice nodes: no omega_l interpolation
    rgb, p0 = dev.eval_f(mi.UInt32(np.zeros(n, np.uint32)), mi.Float(th_v), mi.Float(ph_v),
                         mi.Float(i / (w - 1)), mi.Float(j / (h - 1)), mi.Bool(np.ones(n, bool)))
    got = np.stack([np.array(rgb.x), np.array(rgb.y), np.array(rgb.z)], axis=-1)
    # numpy: the table's own incoming interpolation (usdfiber.bake.lookup) of the family's nodes.
    want = np.zeros((n, 3))
    want0 = np.zeros(n)
    for ti, pi, flip, wt in incoming_nodes(g, th_v, ph_v, True):
        k = np.where(flip, g.n_theta_i - 1 - ti, g.n_theta_i + ti)   # the family's mirrored theta_v node
        want += wt[:, None] * fam.f[0, k, pi, j, i]
        want0 += wt * fam.pdf[0, k, pi, j, i]
    scale = float(np.abs(fam.f).max())
    # float16 nodes: 2^-11 relative per node, so 1e-3 of the largest value bounds the difference.
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-3 * scale)
    np.testing.assert_allclose(np.array(p0), want0, rtol=0, atol=1e-3 * float(fam.pdf.max()))
    # The comparison sees the incoming interpolation: nodes 15 deg apart would not agree.
    assert np.abs(want[:, 0] - np.roll(want[:, 0], 1)).max() > 0.05 * scale
