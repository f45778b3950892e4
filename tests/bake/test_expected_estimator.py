"""The expected-value estimator at the outer boundary (``estimator="expected"``): at every
microfacet event on an outer face, the expected exit of the branch that ends outside and leaves
the fiber for good (always on an edge of the outline's convex hull; elsewhere where an escape
ray per normal meets the fiber no more) is histogrammed over K visible normals and the walk
goes on (the real exit it covers is not recorded). It must estimate what the
plain estimator estimates bin by bin (with absorption), match the exact smooth circle, keep
the furnace and lower the variance.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from usdfiber.bake import profiles, tracer
from usdfiber.bake.baker import bake_table
from usdfiber.bake.binning import bin_direct
from usdfiber.bake.exact import azimuthal_distribution
from usdfiber.bake.fiber_mesh import build_fiber_mesh, hull_edges
from usdfiber.bake.grid import Grid
from usdfiber.bake.settings import BakeError, BakeSettings
from usdfiber.bake.tracer import ExitHistogram, trace, trace_many

from estimator_scenes import scene as shared_scene
from estimator_scenes import star_profile
from stats_util import FALSE_FAILURE, compare_blocks

ETA = 1.55
#: The kernels' histograms are float32 sums: the same deposits added in another order agree to a
#: few ulps (a deposit more or less in a bin changes it by 1e-4 and more).
F32_SUMS = 1e-5
SIGMA = 0.05           # 1/um: absorption across the 10 um fibers below, about 0.4 optical depths
GRID = Grid(6.0)
HIST = ExitHistogram.for_grid(GRID, [SIGMA])

def scene(name: str):
    """Built-in profiles at 10 um, the circle's diameter (estimator_scenes)."""
    return shared_scene(name, None if name in ("circle", "star") else 10.0)


def _densities(fs, theta, phi, beta, n, seeds, K, sigma=SIGMA):
    """One (n_theta_o, n_phi_o, 1) density per seed (independent batches), rows and histogram."""
    res = trace_many(fs, [(theta, phi)] * len(seeds), n, eta=ETA, beta_deg=beta, seed=list(seeds),
                     expected=K, histogram=HIST if K else None)
    return [bin_direct(r, sigma, GRID)[..., None] for r in res]


# ---- the hull marks ---------------------------------------------------------------------------------

def test_hull_edges_of_convex_and_concave_loops():
    square = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    assert hull_edges(square).all()
    # An arrow-head: the two edges into the notch at (0.5, 0.3) are not on the hull.
    notch = np.array([[0, 0], [0.5, 0.3], [1, 0], [0.5, 1]], float)
    assert hull_edges(notch).tolist() == [False, False, True, True]
    m = build_fiber_mesh(star_profile())
    star_hull = hull_edges(star_profile().loops[0])
    assert 0.2 < star_hull.mean() < 0.9
    # Per edge two triangles, both marked; only outer faces; every face of a circle.
    assert m.outer_hull.sum() == 2 * star_hull.sum() and not np.any(m.outer_hull & ~m.outer_faces)
    assert build_fiber_mesh(profiles.circle(64)).outer_hull.all()
    cotton = build_fiber_mesh(profiles.builtin_profiles_um("cotton", 1)[0])
    assert not np.any(cotton.outer_hull & ~cotton.outer_faces) and 0.5 < cotton.outer_hull[cotton.outer_faces].mean() < 1


# ---- unbiased against the plain estimator ------------------------------------------------------------

# Rough convex, rough three-lobed silk (concave sides: an escape ray per normal), rough
# cotton (kidney with a lumen, walls crossed inside), smooth three-lobed (deep lobes: hull
# faces only), smooth circle, rough deep three-lobed (much of its light leaves through the
# concave sides and some of it meets a lobe again).
CASES = [("circle", 1.2, 0.0, 8.0), ("silk", 0.5, 0.9, 6.5), ("cotton", 0.8, 0.7, 14.0),
         ("star", 0.3, 2.0, 0.0), ("circle", 0.5, 0.3, 0.0), ("star", 0.6, 1.1, 8.0)]


@pytest.mark.parametrize("case", CASES)
def test_expected_is_unbiased_against_plain(case):
    """Bin by bin at absorption sigma_a = 0.05/um (so that a wrong path length shows):
    ``compare_blocks`` of 8 plain and 8 expected-value batches (the sum of squared differences
    over the variance of the difference, about F with Satterthwaite dofs, and the z of the total
    mass; false failure 1e-4 per case). Catches an exit deposited and also recorded (the real
    walk not ended: every exit lobe counted twice), a dropped escape probability (light that
    stays on the microsurface deposited), deposits through concave faces (light that meets the
    fiber again) and a smooth continuation at the wrong weight."""
    name, theta, phi, beta = case
    fs = scene(name)
    a = _densities(fs, theta, phi, beta, 1 << 13, range(100, 108), 0)
    b = _densities(fs, theta, phi, beta, 1 << 13, range(200, 208), 4)
    c = compare_blocks(a, b, block=1)
    assert c.agrees(), c


# Rough three-lobed silk and rough cotton (the tables the stratified schedules bake), the rough
# circle at grazing incidence.
STRATIFIED_CASES = [("silk", 0.5, 0.9, 6.5), ("cotton", 0.8, 0.7, 14.0), ("circle", 1.45, 0.0, 8.0)]


@pytest.mark.parametrize("case", STRATIFIED_CASES)
def test_expected_with_sobol_photons_is_unbiased_against_plain(case):
    """The expected value with each photon's first numbers from a scrambled Sobol point
    (``sampler="sobol"``, the "stratified" estimator; one scramble per batch) against the plain
    estimator's independent photons, bin by bin at absorption (``compare_blocks`` of 8 batches
    each, false failure 1e-4 per case). Catches a Sobol coordinate reused for two decisions
    (the beam offset and the first event's numbers correlated: silk and cotton fail). Batches
    that share a scramble are ``test_estimators.py``'s ``test_stratified_batches_are_independent``."""
    name, theta, phi, beta = case
    fs = scene(name)
    a = _densities(fs, theta, phi, beta, 1 << 13, range(500, 508), 0)
    res = trace_many(fs, [(theta, phi)] * 8, 1 << 13, eta=ETA, beta_deg=beta, seed=list(range(600, 608)),
                     expected=4, histogram=HIST, sampler="sobol")
    b = [bin_direct(r, SIGMA, GRID)[..., None] for r in res]
    c = compare_blocks(a, b, block=1)
    assert c.agrees(), c


def _two_ways(case, seed0: int, **ways):
    """8 batches of expected values of ``case`` each way (a name: trace keyword arguments) from the
    same seeds, and ``compare_blocks`` of the first way's densities against the second's, bin by
    bin at absorption."""
    name, theta, phi, beta = case
    fs = scene(name)
    res = {k: trace_many(fs, [(theta, phi)] * 8, 1 << 13, eta=ETA, beta_deg=beta, seed=list(range(seed0, seed0 + 8)),
                         expected=8, histogram=HIST, **kw) for k, kw in ways.items()}
    a, b = ([bin_direct(r, SIGMA, GRID)[..., None] for r in v] for v in res.values())
    return res, compare_blocks(a, b, block=1)


# Rough silk and deep three-lobed profiles (concave sides), and the rough circle at grazing
# incidence, where the reflections on the outside carry much of the light.
ALLOCATION_CASES = [("silk", 0.5, 0.9, 6.5), ("star", 0.6, 1.1, 8.0), ("circle", 1.45, 0.0, 8.0)]


@pytest.mark.parametrize("case", ALLOCATION_CASES)
def test_adaptive_allocation_is_unbiased_against_uniform(case):
    """The adaptive allocation (1 to K normals per event from the event's state) against K
    normals for every event, bin by bin at absorption (``compare_blocks``, false failure 1e-4
    per case); the walks are the same photons, so the events are the same and the adaptive one
    evaluates fewer normals. Catches deposits weighted 1/K instead of 1/(the event's normals)
    (mass short by the normals saved: the furnace tests fail too)."""
    res, c = _two_ways(case, 300, uniform=dict(expected_allocation="uniform"),
                       adaptive=dict(expected_allocation="adaptive"))
    assert c.agrees(), c
    ev = {k: sum(r.extra["expected_events"] for r in v) for k, v in res.items()}
    nn = {k: sum(r.extra["expected_normals"] for r in v) for k, v in res.items()}
    assert ev["uniform"] == ev["adaptive"] > 0 and nn["uniform"] == 8 * ev["uniform"]
    assert ev["adaptive"] <= nn["adaptive"] < nn["uniform"], (ev, nn)


# Rough silk, the rough circle at grazing incidence (weights <wi, m> / cos(theta_i) cos(theta_m)
# far from 1 inside, where the walks meet the surface at grazing angles) and rough cotton.
SAMPLER_CASES = [("silk", 0.5, 0.9, 6.5), ("circle", 1.45, 0.0, 8.0), ("cotton", 0.8, 0.7, 14.0)]


@pytest.mark.parametrize("case", SAMPLER_CASES)
def test_ndf_normals_are_unbiased_against_visible_normals(case):
    """Normals drawn from D(m) cos(theta_m) and weighted by their visibility (the default)
    against normals drawn from the visible normals, bin by bin at absorption
    (``compare_blocks``, false failure 1e-4 per case; the same walks, other normals). Catches
    a weight without G1(wi) (mass too high by 1 + Lambda(wi): fails the grazing circle and
    cotton) or without its 1 / cos(theta_m) (cotton; the furnace tests fail too)."""
    res, c = _two_ways(case, 400, visible=dict(expected_sampler="visible"), ndf=dict(expected_sampler="ndf"))
    assert c.agrees(), c
    assert all(np.array_equal(x.directions, y.directions) for x, y in zip(res["visible"], res["ndf"]))


def test_expected_keeps_the_furnace():
    """At zero absorption every photon leaves: the mean exit weight per photon that hit is 1.
    (The rough deep three-lobed profile catches exits deposited through concave sides without
    their escape test: 1.047 against 1.0 at 8 x 2^13 photons, a t of about 20.)
    The estimator conserves it on average only (the deposit is an expectation, the real walk's
    exit is dropped), so the mean of 8 batches is compared with 1 by Student's t (7 dofs,
    false failure 1e-4 for each fiber)."""
    for name, beta in (("cotton", 14.0), ("star", 0.0), ("star", 8.0)):
        res = trace_many(scene(name), [(0.6, 1.1)] * 8, 1 << 13, eta=ETA, beta_deg=beta, seed=list(range(30, 38)),
                         expected=4, histogram=ExitHistogram.for_grid(GRID, [0.0]))
        alb = np.array([r.albedo(0.0) for r in res])
        t = (alb.mean() - 1.0) / (alb.std(ddof=1) / math.sqrt(len(alb)))
        assert abs(t) < stats.t.isf(FALSE_FAILURE / 2, len(alb) - 1), (name, alb)
        assert np.all(np.abs(alb - 1.0) < 0.05), (name, alb)


@pytest.mark.parametrize("theta_deg", [0.0, 30.0, 60.0])
def test_expected_matches_exact_circle(theta_deg):
    """The exact smooth circle within the plain test's 1 % L1 bound at a quarter of its photons
    (2^20 against 2^22): every hit of the outer surface deposits its exiting Fresnel branch, so
    only the beam offset and the Russian roulette of weak internal reflections are random.
    Measured L1 at 2^18 over 4 seeds: 0.61-0.78 % (spread between seeds under 0.1 %); it
    falls as N^-1/2 (theta 30 deg: 0.67, 0.35, 0.12 % at 2^18, 2^20, 2^22, plain 1.2, 0.62,
    0.26 %), so about 0.35-0.4 % at 2^20: 1 % is many standard deviations of the L1 away."""
    theta = math.radians(theta_deg)
    hb = ExitHistogram.for_grid(Grid(2.0), [0.0])
    r = trace(scene("circle"), theta, 0.0, 1 << 20, eta=ETA, beta_deg=0.0, seed=int(theta_deg) + 9,
              expected=1, histogram=hb)
    # phi_i = 0: the grid's phi_o columns are the bins of phi_o - phi_i.
    col = r.histogram[0, 0].reshape(90, 180).sum(axis=0)
    d = r.directions.astype(np.float64)
    bw = 2.0 * np.pi / 180
    k = np.minimum((np.mod(np.arctan2(d[:, 1], d[:, 0]), 2.0 * np.pi) / bw).astype(np.int64), 179)
    dens = (col + np.bincount(k, weights=r.exit_weights(), minlength=180)) / r.n_hit / bw
    l1 = float(np.abs(dens - azimuthal_distribution(theta, ETA, n_bins=180, n_h=1 << 20)).sum() * bw)
    assert l1 < 0.01, l1


@pytest.mark.parametrize("theta_deg", [20.0, 60.0])
def test_expected_bins_like_the_plain_estimator_on_bin_edges(theta_deg):
    """A smooth extruded fiber sends all its light to theta_o = -theta_i; on a bin edge of the
    2 degree grid, the kernel's histogram must choose the rows numpy's binning chooses."""
    g = Grid(2.0)
    fs = scene("circle")
    kw = dict(eta=ETA, beta_deg=0.0, seed=4)
    plain = bin_direct(trace(fs, math.radians(theta_deg), 2.0, 4096, **kw), 0.0, g)
    ev = bin_direct(trace(fs, math.radians(theta_deg), 2.0, 4096, expected=1,
                          histogram=ExitHistogram.for_grid(g, [0.0]), **kw), 0.0, g)
    # float32 rounding of the exit directions splits the light between the two rows at the
    # edge; the share of each is a binomial fraction (4096 photons: standard deviation below
    # 0.008, so 0.1 is over 8 of them for both estimates together). A kernel that binned in
    # float32 put all of it in one row.
    fp, fe = (p.sum(axis=1) / p.sum() for p in (plain, ev))
    assert set(np.flatnonzero(fp > 0)) == set(np.flatnonzero(fe > 0)) and np.abs(fp - fe).max() < 0.1, (fp, fe)


def test_expected_lowers_the_variance():
    """Rough convex fiber, equal photons: the spread between batches falls (the exit lobe,
    most of the variance, is integrated over K = 4 lattice normals instead of sampled once).
    Measured ratio of summed batch variances plain / expected: about 5. Each sum has about
    7 x (effective bins) dofs, so F(7, 7) at 1e-4 bounds a correct estimator's ratio from below
    by 5 / 14 = 0.36 at worst; requiring > 2 fails with negligible probability at the measured 5
    (the sums are over dozens of effective bins, far tighter than F(7, 7))."""
    fs = scene("circle")
    a = np.stack(_densities(fs, 0.7, 0.4, 8.0, 1 << 14, range(500, 508), 0))
    b = np.stack(_densities(fs, 0.7, 0.4, 8.0, 1 << 14, range(600, 608), 4))
    ratio = a.var(axis=0, ddof=1).sum() / b.var(axis=0, ddof=1).sum()
    assert ratio > 2.0, ratio


def test_launches_cut_for_bounded_histograms_give_the_same_photons(monkeypatch):
    """The histograms of a launch are bounded (``_HIST_BYTES``): launches then end at direction
    boundaries, and every direction still gets exactly its photons."""
    fs = scene("circle")
    dirs = [(0.3, 0.1), (0.9, 0.2), (0.5, 1.0)]
    whole = trace_many(fs, dirs, 4096, eta=ETA, beta_deg=8.0, seed=[1, 2, 3], expected=4, histogram=HIST)
    monkeypatch.setattr(tracer, "_HIST_BYTES", HIST.bytes_per_direction)
    cut = trace_many(fs, dirs, 4096, eta=ETA, beta_deg=8.0, seed=[1, 2, 3], expected=4, histogram=HIST)
    for x, y in zip(whole, cut):
        assert x.n_hit == y.n_hit and np.array_equal(x.directions, y.directions)
        assert np.allclose(x.histogram, y.histogram, rtol=F32_SUMS, atol=F32_SUMS * x.histogram.max())


@pytest.mark.parametrize("copies,packets", [(1, True), (2, True), (1, False)])
def test_deposits_to_copies_per_thread_equal_atomic_adds(monkeypatch, copies, packets):
    """Deposits go as packets to a private copy of the histograms per thread where the copies fit
    (``_hist_copies``), else atomically to one copy, and value by value where packets are not
    used (the GPU): the same sums, in another order (3 levels: 6 values padded to 8 a bin)."""
    fs = scene("silk")
    dirs = [(0.3, 0.1), (0.9, 2.2)]
    hist = ExitHistogram.for_grid(GRID, [0.0, SIGMA, 0.3])
    ref = trace_many(fs, dirs, 4096, eta=ETA, beta_deg=8.0, seed=[1, 2], expected=4, histogram=hist)
    monkeypatch.setattr(tracer, "_hist_copies", lambda histogram: copies)
    monkeypatch.setattr(tracer, "_packet_deposits", lambda: packets)
    got = trace_many(fs, dirs, 4096, eta=ETA, beta_deg=8.0, seed=[1, 2], expected=4, histogram=hist)
    for x, y in zip(ref, got):
        assert x.histogram.sum() > 0.0 and np.array_equal(x.directions, y.directions)
        assert np.allclose(x.histogram, y.histogram, rtol=F32_SUMS, atol=F32_SUMS * x.histogram.max())


@pytest.mark.parametrize("levels", [(0.0,), (0.0, 0.02, 0.3), (0.0, 0.01, 0.05, 0.1, 0.4), tuple(np.linspace(0, 1, 11))])
def test_histogram_levels_in_padded_packets(levels):
    """A bin's 2 x levels values are padded to whole packets of at most 8: each level of a
    several-level histogram equals the one-level histogram of the same photons at its sigma."""
    h = ExitHistogram.for_grid(GRID, levels)
    assert h.packet in (2, 4, 8) and h.stride % h.packet == 0 and 2 * len(levels) <= h.stride < 2 * len(levels) + 8
    fs = scene("silk")
    many = trace(fs, 0.5, 0.7, 4096, eta=ETA, beta_deg=8.0, seed=3, expected=4, histogram=h).histogram
    assert many.shape == (len(levels), 2, GRID.n_theta_o * GRID.n_phi_o)
    for k, sigma in enumerate(levels):
        one = trace(fs, 0.5, 0.7, 4096, eta=ETA, beta_deg=8.0, seed=3, expected=4,
                    histogram=ExitHistogram.for_grid(GRID, [sigma])).histogram
        assert one.sum() > 0.0
        assert np.allclose(many[k], one[0], rtol=F32_SUMS, atol=F32_SUMS * one[0].max())


# ---- settings, bakes and refusals ---------------------------------------------------------------------

def test_expected_settings_and_cache_key():
    plain = BakeSettings()
    assert "expected_normals" not in BakeSettings(expected_normals=8).result_inputs()
    assert BakeSettings(expected_normals=8).result_inputs() == plain.result_inputs()
    keys = {str(BakeSettings(estimator="expected", expected_normals=k).result_inputs()) for k in (4, 8)}
    assert len(keys) == 2
    # The allocation: adaptive (the default) in the key; uniform keeps the keys of earlier tables.
    uniform = BakeSettings(estimator="expected", expected_allocation="uniform").result_inputs()
    assert "expected_allocation" not in uniform
    assert BakeSettings(estimator="expected").result_inputs()["expected_allocation"] == "adaptive"
    assert "expected_allocation" not in BakeSettings(expected_allocation="uniform").result_inputs()
    with pytest.raises(BakeError, match="expected_allocation"):
        BakeSettings(estimator="expected", expected_allocation="greedy")
    # The normals: "ndf" (the default) in the key; visible normals keep the keys of earlier tables.
    assert BakeSettings(estimator="expected").result_inputs()["expected_sampler"] == "ndf"
    assert "expected_sampler" not in BakeSettings(estimator="expected", expected_sampler="visible").result_inputs()
    assert "expected_sampler" not in plain.result_inputs()
    with pytest.raises(BakeError, match="expected_sampler"):
        BakeSettings(estimator="expected", expected_sampler="ggx")
    assert BakeSettings(estimator=("expected", "stratified")).estimator == ("expected", "stratified")
    for bad in (0, 65, 2.5, "4", True):
        with pytest.raises(BakeError, match="expected_normals"):
            BakeSettings(estimator="expected", expected_normals=bad)
    with pytest.raises(BakeError, match="cannot be combined"):
        BakeSettings(estimator=("expected", "split"))


def test_expected_refusals():
    fs = scene("circle")
    with pytest.raises(ValueError, match="histogram"):
        trace(fs, 0.3, 0.2, 64, eta=ETA, beta_deg=5.0, expected=4)
    with pytest.raises(ValueError, match="expected must be"):
        trace(fs, 0.3, 0.2, 64, eta=ETA, beta_deg=5.0, expected=65, histogram=HIST)
    with pytest.raises(ValueError, match="cannot be combined"):
        trace(fs, 0.3, 0.2, 64, eta=ETA, beta_deg=5.0, expected=4, split=4, histogram=HIST)
    with pytest.raises(ValueError, match="expected_allocation"):
        trace(fs, 0.3, 0.2, 64, eta=ETA, beta_deg=5.0, expected=4, histogram=HIST, expected_allocation="greedy")
    with pytest.raises(ValueError, match="expected_sampler"):
        trace(fs, 0.3, 0.2, 64, eta=ETA, beta_deg=5.0, expected=4, histogram=HIST, expected_sampler="ggx")
    r = trace(fs, 0.3, 0.2, 256, eta=ETA, beta_deg=5.0, expected=4, histogram=HIST)
    with pytest.raises(ValueError, match="not one of the expected-value histogram's levels"):
        r.albedo(0.3)
    ell = profiles.ellipse(0.5, 0.3).centered().scaled_to_diameter(1.0)
    with pytest.raises(BakeError, match="cuticle"):
        bake_table(ell, ETA, 10.0, (3.0, 0.05, 0.5), BakeSettings(resolution_deg=30, photons=64, estimator="expected"))


def test_expected_bake_keeps_the_furnace():
    ell = profiles.ellipse(0.5, 0.3).centered().scaled_to_diameter(1.0)
    t = bake_table(ell, ETA, 12.0, None, BakeSettings(resolution_deg=45, photons=4000, batches=2,
                                                       estimator="expected", expected_normals=4))
    assert t.header["bake"]["settings"]["estimator"] == ["expected"]
    assert t.header["bake"]["settings"]["expected_normals"] == 4
    alb = t.arrays["albedo"][..., 0].astype(np.float64)
    # Furnace per direction within the noise of 4000 photons (the real exit dropped where its
    # expectation was deposited: measured spread of one direction's albedo well below 0.01).
    assert np.all(np.abs(alb - 1.0) < 0.05), alb
    # With the estimators it combines with: stratified first numbers, reciprocity averaging.
    for est, inc in ((("expected", "stratified"), "centre"), (("expected", "reciprocity"), "box")):
        t = bake_table(ell, ETA, 12.0, None, BakeSettings(resolution_deg=45, photons=4000, batches=2,
                                                           estimator=est, incoming=inc))
        assert t.header["bake"]["settings"]["estimator"] == list(est)
        assert np.all(np.abs(t.arrays["albedo"][..., 0].astype(np.float64) - 1.0) < 0.05), est
