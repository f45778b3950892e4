"""The renderer's node storage: pages below Dr.Jit's 2^32-entry array limit, the host nodes
released as they are copied, and the mirrored half of extruded tables."""
from __future__ import annotations

import math

import numpy as np
import pytest

import usdfiber  # noqa: F401  (registers schemas first)
from usdfiber.backend import mitsuba
from usdfiber.bake import profiles
from usdfiber.bake.baker import bake_table
from usdfiber.bake.settings import BakeSettings

from usdfiber.translators.mitsuba import fiber_bsdf as fb
from usdfiber.translators.mitsuba.fiber_bank import FiberBank, FiberSlot, bilinear_integral

mi = mitsuba()
import drjit as dr  # noqa: E402  (after the variant is set)

COLOURS = [(0.0, 0.0, 0.0), (0.2, 0.5, 1.0), (1.5, 0.1, 0.02)]


@pytest.fixture(scope="module")
def silk():
    st = BakeSettings(resolution_deg=15, incoming_deg=30, photons=2000, batches=2)
    return bake_table(profiles.builtin_profiles("silk", 1)[0], 1.55, 8.0, None, st)


def _lanes(n: int, n_slots: int, seed: int = 3):
    rng = np.random.default_rng(seed)
    return (mi.UInt32(rng.integers(0, n_slots, n).astype(np.uint32)),
            mi.Float(rng.uniform(-0.5 * math.pi, 0.5 * math.pi, n)), mi.Float(rng.uniform(0, 2 * math.pi, n)),
            mi.Float(rng.uniform(0, 1, n)), mi.Float(rng.uniform(0, 1, n)),
            mi.Point2f(rng.uniform(0, 1, n), rng.uniform(0, 1, n)), mi.Bool(np.ones(n, bool)))


def _outputs(dev: fb.FamilyDevice, lanes) -> list[np.ndarray]:
    slot, th, ph, x, y, u2, act = lanes
    rgb, p0 = dev.eval_f(slot, th, ph, x, y, act)
    table = dr.gather(mi.UInt32, dev.slot_table, slot, act)
    xs, ys, srgb, sp = dev.sample_f(slot, table, th, ph, x, u2, act)
    return [np.array(v) for v in (rgb.x, rgb.y, rgb.z, p0, xs, ys, srgb.x, sp)]


def test_pages_and_release_read_the_same_nodes(silk, monkeypatch):
    slots = [FiberSlot(silk, c) for c in COLOURS]
    one = fb.FamilyDevice(FiberBank.build(slots).families[False])
    assert len(one.pages) == 1
    lanes = _lanes(4000, len(slots))
    want = _outputs(one, lanes)
    fam = FiberBank.build(slots).families[False]
    per_slot = int(np.prod(fam.slice_shape)) * 4
    # Pages of at most two slots: three slots make two pages, filled slot by slot in place.
    monkeypatch.setattr(fb, "PAGE_ENTRIES", 2 * per_slot + 1)
    paged = fb.FamilyDevice(fam, release=True)
    assert len(paged.pages) == 2
    assert all(a is None for a in fam.nodes)                 # the host copy is gone
    got = _outputs(paged, lanes)
    for a, b in zip(got, want):
        np.testing.assert_array_equal(a, b)                  # the same nodes, bit for bit
    assert np.all(np.isfinite(want[0])) and want[3].max() > 0
    with pytest.raises(ValueError, match="released"):
        fam.full(3)


def test_one_slot_larger_than_a_page_is_refused(silk, monkeypatch):
    fam = FiberBank.build([FiberSlot(silk, COLOURS[0])]).families[False]
    monkeypatch.setattr(fb, "PAGE_ENTRIES", 1000)
    with pytest.raises(ValueError, match="2\\^32"):
        fb.FamilyDevice(fam)


def test_mirrored_half_is_stored(silk):
    fam = FiberBank.build([FiberSlot(silk, COLOURS[1])]).families[False]
    g = silk.grid
    n_ts, n_pv, h, w = fam.slice_shape
    assert fam.mirrored and n_ts == g.n_theta_i and len(fam.theta_v) == 2 * g.n_theta_i
    assert fam.nodes[0].shape == (n_ts, n_pv, h, w, 4)
    # The stored half is theta_v >= 0; a node below reads its twin with theta_l reversed.
    assert np.all(fam.theta_v[fam.stored_start:] > 0) and np.all(fam.theta_v[:fam.stored_start] < 0)
    ks, flip = fam.stored(np.arange(len(fam.theta_v)))
    assert np.array_equal(ks[flip][::-1], ks[~flip]) and flip.sum() == n_ts
    # The albedo of each stored slice is the integral of its f, within the float16 rounding
    # of the nodes (2^-11 relative each).
    f = fam.nodes[0][..., :3].astype(np.float64) / fam.node_scale
    np.testing.assert_allclose(fam.albedo[0], bilinear_integral(np.moveaxis(f, -1, 2)), rtol=6e-4, atol=1e-7)
    assert fam.albedo[0].max() > 0.1


def test_values_past_float16_rescale_the_family(silk, monkeypatch):
    # A node scale 4x too large (as if f exceeded p0's largest value): the layout rescales by
    # a power of two instead of writing infinities, and stores the same values.
    import usdfiber.translators.mitsuba.fiber_bank as bank_mod
    slots = [FiberSlot(silk, c) for c in COLOURS]
    want = FiberBank.build(slots).families[False]
    real = bank_mod._scale_for
    calls = []

    def too_large(top: float) -> float:
        calls.append(top)
        return 4.0 * real(top) if len(calls) == 1 else real(top)

    monkeypatch.setattr(bank_mod, "_scale_for", too_large)
    got = FiberBank.build(slots).families[False]
    assert len(calls) >= 2                                   # it did rescale
    assert all(np.isfinite(a.astype(np.float32)).all() for a in got.nodes)
    np.testing.assert_allclose(got.full(slice(0, 4)), want.full(slice(0, 4)), rtol=2e-3, atol=1e-6)


def test_sampling_tables_of_several_tables(silk):
    # Two tables in one family: their CDFs are copied table by table into one device array,
    # equal to the host's concatenation.
    st = BakeSettings(resolution_deg=15, incoming_deg=30, photons=2000, batches=2)
    other = bake_table(profiles.builtin_profiles("silk", 2)[1], 1.55, 8.0, None, st)
    fam = FiberBank.build([FiberSlot(silk, COLOURS[0]), FiberSlot(other, COLOURS[1]),
                           FiberSlot(other, COLOURS[2])]).families[False]
    assert fam.n_tables == 2
    marg, cond = fam.sampling_cdfs()
    dev = fb.FamilyDevice(fam)
    np.testing.assert_array_equal(np.array(dev.marg), marg.reshape(-1))
    np.testing.assert_array_equal(np.array(dev.cond), cond.reshape(-1))
    assert not np.array_equal(*np.split(marg, 2))            # two different tables
