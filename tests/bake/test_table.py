"""Baked BCSDF tables: normalization, furnace, exact circle, recolouring, reciprocity, symmetry.

Tables are baked small (10-30 degree bins, 10^4-10^5 photons per direction) so the module
runs in about a minute on 2 cores. Every comparison is against noise estimated from the
photons, so a wrong convention (a missing cosine, a wrong width, a wrong path length) fails.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from usdfiber.bake import binning, exact, profiles, tracer
from usdfiber.bake.baker import bake_table, batch_seed, is_rotationally_symmetric
from usdfiber.bake.grid import Grid
from usdfiber.bake import settings as settings_module
from usdfiber.bake.settings import BakeSettings
from usdfiber.bake.table import BcsdfTable

from stats_util import FALSE_FAILURE, chi2_limit, f_limit, z_limit

ETA = 1.55


def unit(profile):
    return profile.centered().scaled_to_diameter(1.0)


@pytest.fixture(scope="module")
def ellipse():
    return unit(profiles.ellipse(0.5, 0.3))


@pytest.fixture(scope="module")
def silk():
    return unit(profiles.builtin_profiles("silk", 1)[0])


@pytest.fixture(scope="module")
def rough_circle_table():
    return bake_table(profiles.circle(), ETA, 12.0, None, BakeSettings(resolution_deg=15, photons=16000, batches=4))


def bin_mass(rec, ti, pi):
    """(n_theta_o, n_phi_o) fraction of the light per bin, from a recoloured table (channel 0)."""
    t = rec.table
    g = t.grid
    out = np.zeros((g.n_theta_o, g.n_phi_o))
    b0 = int(t.band_start[ti, pi])
    out[b0:b0 + t.n_band] = rec.p[ti, pi, :, :, 0] * t.domega_band()[ti, pi][:, None]
    return out


# ---------------------------------------------------------------------------------------------
# Normalization and furnace
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("shape,beta", [("circle", 0.0), ("circle", 12.0), ("ellipse", 0.0), ("ellipse", 12.0)])
def test_normalized_and_white_furnace(shape, beta, ellipse):
    prof = profiles.circle() if shape == "circle" else ellipse
    t = bake_table(prof, ETA, beta, None, BakeSettings(resolution_deg=30, photons=8000, batches=2))
    dom = t.domega_band()
    for sig in (0.0, 0.7, 3.0, 40.0, (0.0, 1.5, 100.0)):
        rec = t.recolour(sig)
        total = (rec.p * dom[..., None, None]).sum(axis=(2, 3))
        np.testing.assert_allclose(total, 1.0, atol=1e-5)
    # White furnace: without absorption every photon that meets the fiber leaves it.
    alb = t.albedo(t.grid.theta_i_nodes()[:, None], t.grid.phi_i_nodes()[None, :], 0.0)
    assert np.all(np.abs(alb - 1.0) <= 1e-3), alb
    # Absorption only removes light, more of it the more there is.
    a1 = t.recolour(1.0).albedo
    a2 = t.recolour(4.0).albedo
    assert np.all(a1 < 1.0) and np.all(a2 < a1)
    assert t.arrays["p"].dtype == np.float16
    assert max(t.header["quantization_error"]["per_level"]) < 1e-3


# ---------------------------------------------------------------------------------------------
# Smooth circle against the exact far field
# ---------------------------------------------------------------------------------------------

def test_smooth_circle_matches_exact():
    """theta_o = -theta_i exactly; the phi_o histogram matches the exact one to noise.

    At 10 degree bins with 3e5 photons per direction, a bin holding a fraction P of the
    light has a multinomial standard deviation sqrt(P (1 - P) / N) ~ 5e-4 for P = 0.1; the
    table mirror-averages the two sides (variance P (1 - 2P) / 2N for a pair). The chi-square
    of the 19 independent bins against that variance must stay below its quantile at a false
    failure of 1e-4 over the nine directions (Bonferroni): a 0.3% bias in a large bin fails.
    """
    t = bake_table(profiles.circle(), ETA, 0.0, None, BakeSettings(resolution_deg=10, photons=200_000, batches=4))
    g = t.grid
    assert g.n_phi_i == 1 and g.n_theta_i == 9
    rec = t.recolour(0.0)
    n = g.n_phi_o
    j = np.arange(n // 2 + 1)
    for ti, th in enumerate(g.theta_i_nodes()):
        m = bin_mass(rec, ti, 0)
        row = int(np.floor((-th + 0.5 * math.pi) / g.step))
        assert m[row].sum() > 1.0 - 1e-6, (math.degrees(th), m.sum(axis=1))
        # exact bins are [k, k+1) * 2pi/n in phi_o - phi_i; the table's are centred on k.
        half = exact.azimuthal_distribution(th, ETA, n_bins=2 * n, n_h=1 << 18) * (math.pi / n)
        E = half[(2 * np.arange(n) - 1) % (2 * n)] + half[2 * np.arange(n)]
        N = int(t.arrays["photons"][ti, 0])
        var = np.where((j == 0) | (j == n // 2), E[j] * (1 - E[j]) / N, E[j] * (1 - 2 * E[j]) / (2 * N))
        c2 = float(((m[row][j] - E[j]) ** 2 / var).sum())
        assert c2 < chi2_limit(len(j), FALSE_FAILURE / g.n_theta_i), (math.degrees(th), c2)


def test_smooth_circle_absorption_matches_exact():
    """Recoloured smooth circle vs the exact attenuation (sigma_a per radius = sigma * D / 2).

    At a level (s = 2) and between levels (s = 3). The variance of a weighted bin is at most
    P / N (weights <= 1), so the chi-square below is conservative; it still fails for a
    path length off by a few percent.
    """
    t = bake_table(profiles.circle(), ETA, 0.0, None, BakeSettings(resolution_deg=15, photons=200_000, batches=4))
    g = t.grid
    n = g.n_phi_o
    j = np.arange(n // 2 + 1)
    for sig in (2.0, 3.0):
        rec = t.recolour(sig)
        for ti in (1, 4):
            th = g.theta_i_nodes()[ti]
            lam_exact = exact.total_energy(th, ETA, sig * 0.5, n_h=1 << 18)
            # Photon weights lie in [0, 1], so the albedo's variance is at most
            # lam (1 - lam) / N: 3e-3 was 2.7-4 standard errors (up to 7e-3 false failure);
            # the bound is now z_limit standard errors for the four checks together.
            N = int(t.arrays["photons"][ti, 0])
            tol = max(3e-3, z_limit(FALSE_FAILURE / 4) * math.sqrt(lam_exact * (1 - lam_exact) / N))
            assert abs(rec.albedo[ti, 0, 0] - lam_exact) < tol, (sig, th, rec.albedo[ti, 0, 0], lam_exact)
            m = bin_mass(rec, ti, 0)
            row = int(np.floor((-th + 0.5 * math.pi) / g.step))
            half = exact.azimuthal_distribution(th, ETA, sigma_a=sig * 0.5, n_bins=2 * n, n_h=1 << 18) * (math.pi / n)
            E = (half[(2 * np.arange(n) - 1) % (2 * n)] + half[2 * np.arange(n)]) / lam_exact
            N = int(t.arrays["photons"][ti, 0]) * lam_exact
            var = np.where((j == 0) | (j == n // 2), E[j] / N, E[j] / (2 * N))
            c2 = float(((m[row][j] - E[j]) ** 2 / var).sum())
            assert c2 < chi2_limit(len(j), FALSE_FAILURE / 4), (sig, math.degrees(th), c2)
            # L1 over the row: a sum of half-normals (mirrored bins count twice) with the same
            # variance bound; its mean plus z_limit sd (four checks). The former fixed 0.02
            # sat 2-3 sd above the noise at s = 3 (measured L1 0.014-0.017 over three seeds).
            mult = np.where((j == 0) | (j == n // 2), 1.0, 2.0)
            sd = mult * np.sqrt(var)
            l1_limit = math.sqrt(2 / math.pi) * sd.sum() + z_limit(FALSE_FAILURE / 4) * math.sqrt(
                (1 - 2 / math.pi) * (sd ** 2).sum())
            assert np.abs(m[row] - E).sum() < l1_limit, (sig, math.degrees(th), l1_limit)


# ---------------------------------------------------------------------------------------------
# Recolouring without re-tracing
# ---------------------------------------------------------------------------------------------

def test_recolour_equals_direct_trace_same_photons(silk, silk_table):
    """The table recoloured at sigma_a equals the bake's own photons weighted by exp(-sigma_a L).

    Same photons, so noise cancels: what remains is the level interpolation and float16
    storage. It must be far below the table's own noise (its error estimate).
    """
    t = silk_table
    st = BakeSettings(resolution_deg=30, photons=12000, batches=4)
    fs = tracer.prepare(silk)
    g = t.grid
    xg = Grid(g.resolution_deg)
    n_b = st.photons // st.batches
    for sig, dscale in ((3.0, 1.0), (1.5, 2.0), (0.3, 1.0), (100.0, 1.0)):
        rec = t.recolour(sig, diameter_scale=dscale)
        s_eff = sig * dscale
        for ti, pi in ((0, 0), (1, 5), (2, 9)):
            th, ph = g.theta_i_nodes()[ti], g.phi_i_nodes()[pi]
            dens = np.zeros((g.n_theta_o, g.n_phi_o))
            hits = 0
            for b in range(st.batches):
                r = tracer.trace(fs, th, ph, n_b, eta=ETA, beta_deg=6.5, max_bounces=st.max_bounces,
                                 seed=batch_seed(st.seed, b))
                dens += binning.bin_direct(r, s_eff, xg) * r.n_hit
                hits += r.n_hit
            dens /= hits
            lam = float((dens * xg.bin_solid_angles()).sum())
            p_direct = dens / lam
            p_table = np.zeros_like(p_direct)
            b0 = int(t.band_start[ti, pi])
            p_table[b0:b0 + t.n_band] = rec.p[ti, pi, :, :, 0]
            w = xg.bin_solid_angles()
            rel = math.sqrt((w * (p_table - p_direct) ** 2).sum() / (w * p_direct ** 2).sum())
            noise = float(t.rel_error[ti, pi])
            # Same photons: no noise in the difference (deterministic up to rounding); the
            # table's noise estimate pools the bins of the direction over 4 batches.
            assert rel < 0.02 and rel < 0.5 * noise, (sig, ti, pi, rel, noise)
            assert abs(rec.albedo[ti, pi, 0] / lam - 1.0) < 5e-3, (sig, rec.albedo[ti, pi, 0], lam)


def test_recolour_equals_independent_trace_within_noise(silk, silk_table):
    """Against an independent trace (other seed): the difference is the two noises only."""
    t = silk_table
    g = t.grid
    xg = Grid(g.resolution_deg)
    fs = tracer.prepare(silk)
    sig = 5.0
    rec = t.recolour(sig)
    w = xg.bin_solid_angles()
    for ti, pi in ((0, 2), (2, 7)):
        th, ph = g.theta_i_nodes()[ti], g.phi_i_nodes()[pi]
        ps = []
        for b in range(4):
            r = tracer.trace(fs, th, ph, 12000, eta=ETA, beta_deg=6.5, seed=1000 + b)
            d = binning.bin_direct(r, sig, xg)
            ps.append(d / (d * w).sum())
        ps = np.stack(ps)
        p_direct = ps.mean(axis=0)
        e_direct2 = (w * ps.var(axis=0, ddof=1) / len(ps)).sum() / (w * p_direct ** 2).sum()
        p_table = np.zeros_like(p_direct)
        b0 = int(t.band_start[ti, pi])
        p_table[b0:b0 + t.n_band] = rec.p[ti, pi, :, :, 0]
        rel = math.sqrt((w * (p_table - p_direct) ** 2).sum() / (w * p_direct ** 2).sum())
        # the table's error estimate is for sigma_a = 0; absorption thins the photons a little
        expected = math.sqrt(2.0 * float(t.rel_error[ti, pi]) ** 2 + e_direct2)
        # (rel / expected)^2 is a ratio of two weighted sums of squares over the direction's
        # bins, each with tens of effective degrees of freedom: about F(>= 20, >= 20), which
        # exceeds 9 (rel > 3 expected) with probability < 1e-5.
        assert rel < 3.0 * expected, (ti, pi, rel, expected)


# ---------------------------------------------------------------------------------------------
# Reciprocity
# ---------------------------------------------------------------------------------------------

def _sigma_matrix(t: BcsdfTable) -> np.ndarray:
    """<W cos> Lambda p between all bin centres, for a box-filtered table."""
    g = t.grid
    th, ph = g.theta_o_centers(), g.phi_o_centers()
    e = g.theta_o_edges()
    cos_avg = (0.5 * np.diff(e) + 0.25 * np.diff(np.sin(2 * e))) / np.diff(np.sin(e))
    fine = (np.arange(3600) + 0.5) * (2 * math.pi / 3600)
    wf = t.width(fine)
    w_avg = np.array([wf[np.abs(((fine - c + math.pi) % (2 * math.pi)) - math.pi) < 0.5 * g.step].mean() for c in ph])
    T, P = (x.ravel() for x in np.meshgrid(th, ph, indexing="ij"))
    C, Wv = (x.ravel() for x in np.meshgrid(cos_avg, w_avg, indexing="ij"))
    p = t.eval_p(T[:, None], P[:, None], T[None, :], P[None, :], interp_i="nearest", interp_o="nearest")
    a = t.albedo(T, P, interp_i="nearest")
    return (Wv * C * a)[:, None] * p


def test_reciprocity_non_circular(ellipse):
    """sigma(omega_i, omega_o) = W cos(theta_i) Lambda p is symmetric, to noise.

    Box-filtered tables (the light of a node spread over its bin) make the discrete table
    symmetric bin for bin. The asymmetry ||S - S^T|| is compared with the difference of two
    independent bakes ||S1 - S2||, which is what noise alone gives (ratio ~1). Dropping the
    cosine or the width makes the ratio 2-4.
    """
    tabs = [bake_table(ellipse, ETA, 15.0, None,
                       BakeSettings(resolution_deg=30, photons=10000, batches=4, seed=s, incoming="box"))
            for s in (0, 1)]
    s1, s2 = (_sigma_matrix(t) for t in tabs)
    noise = np.linalg.norm(s1 - s2)
    for s in (s1, s2):
        ratio = np.linalg.norm(s - s.T) / noise
        # ratio^2 is about F(nu_a, nu_b): each sum of squares has the effective degrees of
        # freedom 3 (sum d^2)^2 / sum d^4 of its entries (Gaussian kurtosis), estimated here
        # from the data; the limit holds both tables together at false failure 1e-4.
        a, d = (s - s.T)[np.triu_indices(len(s), 1)], (s1 - s2).ravel()
        nu_a, nu_b = (3.0 * (x @ x) ** 2 / np.sum(x ** 4) for x in (a, d))
        limit = math.sqrt(f_limit(nu_a, nu_b, FALSE_FAILURE / 2))
        assert ratio < limit, (ratio, limit, nu_a, nu_b)
    # The same statistic flags a table that is not reciprocal (cos(theta_i) left out).
    g = tabs[0].grid
    cos_i = np.cos(np.repeat(g.theta_o_centers(), g.n_phi_o))
    bad = s1 / cos_i[:, None]
    assert np.linalg.norm(bad - bad.T) / noise > 2.0


@pytest.mark.slow
def test_reciprocity_centre_sampled_tables(ellipse):
    """The default tables (light at bin centres) are reciprocal up to discretization.

    Centre samples in omega_i against bin averages in omega_o differ at O(bin^2); at 10
    degrees that is below the noise of 5000 photons per direction (measured ratio ~1.1),
    while leaving out cos(theta_i) gives ~1.4.
    """
    tabs = [bake_table(ellipse, ETA, 15.0, None, BakeSettings(resolution_deg=10, photons=5000, batches=2, seed=s))
            for s in (0, 1)]
    g = tabs[0].grid
    T, P = (x.ravel() for x in np.meshgrid(g.theta_o_centers(), g.phi_o_centers(), indexing="ij"))

    def S(t):
        p = t.eval_p(T[:, None], P[:, None], T[None, :], P[None, :], interp_i="nearest", interp_o="nearest")
        return (t.width(P) * np.cos(T) * t.albedo(T, P, interp_i="nearest"))[:, None] * p

    s1, s2 = S(tabs[0]), S(tabs[1])
    noise = np.linalg.norm(s1 - s2)
    for s in (s1, s2):
        assert np.linalg.norm(s - s.T) / noise < 1.25
    bad = s1 / np.cos(T)[:, None]
    assert np.linalg.norm(bad - bad.T) / noise > 1.3


# ---------------------------------------------------------------------------------------------
# Symmetries and layout
# ---------------------------------------------------------------------------------------------

def test_round_profiles_collapse_to_one_phi_i(ellipse, rough_circle_table):
    assert is_rotationally_symmetric(profiles.circle())
    assert is_rotationally_symmetric(profiles.builtin_profiles("polyester", 1)[0])
    assert not is_rotationally_symmetric(ellipse)
    assert not is_rotationally_symmetric(profiles.profile_from_polygons(
        [np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)]).centered())
    t = rough_circle_table
    assert t.grid.n_phi_i == 1 and t.arrays["p"].shape[1] == 1
    assert t.header["resolution"]["rotationally_symmetric"] is True
    # p depends on phi_o - phi_i only, and W is constant (the diameter).
    rng = np.random.default_rng(1)
    th_i, ph_i = rng.uniform(-1.4, 1.4, 50), rng.uniform(0, 2 * math.pi, 50)
    th_o, ph_o = rng.uniform(-1.4, 1.4, 50), rng.uniform(0, 2 * math.pi, 50)
    d = rng.uniform(0, 2 * math.pi, 50)
    np.testing.assert_allclose(t.eval_p(th_i, ph_i, th_o, ph_o), t.eval_p(th_i, ph_i + d, th_o, ph_o + d),
                               rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(t.width(ph_i), 1.0, atol=2e-4)
    # The mirror phi_o - phi_i -> -(phi_o - phi_i) holds exactly (the bake averages it).
    np.testing.assert_allclose(t.eval_p(th_i, ph_i, th_o, ph_i + d), t.eval_p(th_i, ph_i, th_o, ph_i - d),
                               rtol=1e-4, atol=1e-6)


def test_cuticle_tables_cover_both_theta_hemispheres():
    assert Grid(2.0, theta_symmetric=False, phi_invariant=False).n_theta_i == 90
    assert Grid(2.0, theta_symmetric=True, phi_invariant=False).n_theta_i == 45
    cut = (3.0, 0.7 / 32, 10.0 / 32)  # wool-like scales, relative to a 1 um fiber
    t = bake_table(profiles.circle(), ETA, 5.0, cut, BakeSettings(resolution_deg=30, photons=6000, batches=2))
    g = t.grid
    assert not g.theta_symmetric and g.n_theta_i == 6 and g.n_phi_i == 1
    np.testing.assert_allclose(g.theta_i_nodes(), np.radians([-75, -45, -15, 15, 45, 75]))
    assert t.header["cuticle"]["height_um"] == pytest.approx(cut[1])
    # W is the scales' envelope: the diameter plus two scale heights.
    np.testing.assert_allclose(t.width(np.linspace(0, 6, 7)), 1.0 + 2 * cut[1], rtol=1e-3)
    # Furnace: photons crossing the envelope between scales go straight on; none is lost.
    alb = t.arrays["albedo"][:, :, 0]
    assert np.all(np.abs(alb - 1.0) < 1e-2), alb
    # The scales break the theta symmetry: light from +theta and -theta differs.
    rec = t.recolour(0.0)
    up = bin_mass(rec, 4, 0)[::-1]      # theta_i = +45, theta_o mirrored
    down = bin_mass(rec, 1, 0)          # theta_i = -45
    assert np.abs(up - down).sum() > 0.02


def test_error_estimate_falls_as_inverse_sqrt_photons():
    prof = profiles.circle()
    e = []
    for n in (3000, 48000):
        t = bake_table(prof, ETA, 12.0, None, BakeSettings(resolution_deg=15, photons=n, batches=8))
        e.append(float(np.sqrt(np.mean(t.rel_error.astype(np.float64) ** 2))))
        assert t.header["error_estimate"]["rms"] == pytest.approx(e[-1], rel=1e-6)
    ratio = e[0] / e[1]
    # 16x the photons: 4x less error. Each rms pools the per-bin error estimates of 8 batches
    # over all bins of the table (thousands of dof): its relative spread is a few percent,
    # and 2.8 and 5.6 are -30 % and +40 %, > 8 standard deviations (false failure < 1e-15).
    assert 2.8 < ratio < 5.6, (e, ratio)


def test_target_error_mode_reaches_target():
    st = BakeSettings(resolution_deg=30, photons=8000, batches=2, target_error=0.012, max_photons=400_000)
    t = bake_table(profiles.circle(), ETA, 12.0, None, st)
    assert float(t.rel_error.max()) <= 0.012
    assert int(t.arrays["photons"].min()) > 8000


def test_grouped_directions_bake_the_same_table(monkeypatch):
    """Directions traced together (shared tracer launches) give the table baked one direction
    at a time, value for value: plain, target-error (directions needing different numbers of
    extra batches) and box-sampled bakes, non-round and cuticle fibers."""

    silk = unit(profiles.builtin_profiles("silk", 1)[0])
    cases = [(silk, None, BakeSettings(resolution_deg=30, photons=4000, batches=2)),
             (silk, None, BakeSettings(resolution_deg=30, photons=2000, batches=2, target_error=0.07,
                                       max_photons=12000)),
             (silk, None, BakeSettings(resolution_deg=30, photons=2000, batches=2, incoming="box")),
             (unit(profiles.circle()), (3.0, 0.02, 0.3), BakeSettings(resolution_deg=30, photons=2000, batches=2))]
    for prof, cut, st in cases:
        grouped = bake_table(prof, ETA, 6.5, cut, st)
        monkeypatch.setattr(settings_module, "GROUP_DIRECTIONS", 1)
        alone = bake_table(prof, ETA, 6.5, cut, st)
        monkeypatch.undo()
        assert grouped.arrays.keys() == alone.arrays.keys()
        for k, v in alone.arrays.items():
            np.testing.assert_array_equal(grouped.arrays[k], v, err_msg=k)
        if st.target_error is not None:
            assert len(np.unique(alone.arrays["photons"])) > 1   # the mode was exercised


# ---------------------------------------------------------------------------------------------
# Evaluation at arbitrary directions
# ---------------------------------------------------------------------------------------------

def test_eval_consistent_with_bins(silk_table):
    t = silk_table
    g = t.grid
    rec = t.recolour(0.0)
    # At nodes and bin centres every interpolation returns the stored bin.
    for ti, pi in ((0, 0), (1, 4), (2, 11)):
        th_i, ph_i = g.theta_i_nodes()[ti], g.phi_i_nodes()[pi]
        T, P = np.meshgrid(g.theta_o_centers(), g.phi_o_centers(), indexing="ij")
        want = np.zeros(T.shape)
        b0 = int(t.band_start[ti, pi])
        want[b0:b0 + t.n_band] = rec.p[ti, pi, :, :, 0]
        for ii in ("linear", "nearest"):
            for io in ("bilinear", "nearest"):
                got = t.eval_p(th_i, ph_i, T, P, interp_i=ii, interp_o=io)
                np.testing.assert_allclose(got, want, rtol=2e-6, atol=1e-9)
    # Anywhere in a bin, "nearest" in omega_o returns that bin.
    rng = np.random.default_rng(3)
    th_o = rng.uniform(-math.pi / 2, math.pi / 2, 200)
    ph_o = rng.uniform(0, 2 * math.pi, 200)
    node = t.eval_p(g.theta_i_nodes()[1], g.phi_i_nodes()[3], th_o, ph_o, interp_i="nearest", interp_o="nearest")
    full = np.zeros((g.n_theta_o, g.n_phi_o))
    b0 = int(t.band_start[1, 3])
    full[b0:b0 + t.n_band] = rec.p[1, 3, :, :, 0]
    r = np.clip(np.floor((th_o + math.pi / 2) / g.step).astype(int), 0, g.n_theta_o - 1)
    c = np.floor(ph_o / g.step).astype(int) % g.n_phi_o
    np.testing.assert_allclose(node, full[r, c], rtol=1e-6)
    # Between nodes the distribution stays normalized (a convex mix of normalized slices),
    # and the bilinear form integrates to 1 up to the discretization.
    # Quadrature: 16 x 16 cells per bin, exact cell solid angles.
    e = np.linspace(-math.pi / 2, math.pi / 2, 16 * g.n_theta_o + 1)
    fine_t = 0.5 * (e[1:] + e[:-1])
    fine_p = (np.arange(16 * g.n_phi_o) + 0.5) * (g.step / 16)
    FT, FP = np.meshgrid(fine_t, fine_p, indexing="ij")
    d_omega = (np.sin(e[1:]) - np.sin(e[:-1]))[:, None] * (g.step / 16)
    for th_i, ph_i in ((0.2, 1.0), (-0.9, 4.0), (1.4, 2.5)):
        near = (t.eval_p(th_i, ph_i, FT, FP, interp_o="nearest") * d_omega).sum()
        bil = (t.eval_p(th_i, ph_i, FT, FP, interp_o="bilinear") * d_omega).sum()
        assert abs(near - 1.0) < 1e-5, near
        assert abs(bil - 1.0) < 0.08, bil
    # Theta symmetry of extruded fibers, rotation psi, width W(phi - psi).
    th_i, ph_i = rng.uniform(-1.5, 1.5, 100), rng.uniform(0, 7, 100)
    th_o, ph_o = rng.uniform(-1.5, 1.5, 100), rng.uniform(0, 7, 100)
    np.testing.assert_allclose(t.eval_p(-th_i, ph_i, th_o, ph_o), t.eval_p(th_i, ph_i, -th_o, ph_o), rtol=1e-6)
    psi = 0.77
    np.testing.assert_allclose(t.eval_p(th_i, ph_i + psi, th_o, ph_o + psi, psi=psi),
                               t.eval_p(th_i, ph_i, th_o, ph_o), rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(t.width(ph_i + psi, psi=psi), t.width(ph_i), rtol=1e-6)
    np.testing.assert_allclose(t.albedo(th_i, ph_i + psi, 2.0, psi=psi), t.albedo(th_i, ph_i, 2.0), rtol=1e-6)
    # RGB evaluation is the per-channel scalar evaluation.
    rgb = t.eval_p(th_i, ph_i, th_o, ph_o, (0.0, 2.0, 9.0))
    for c, s in enumerate((0.0, 2.0, 9.0)):
        np.testing.assert_allclose(rgb[..., c], t.eval_p(th_i, ph_i, th_o, ph_o, s), rtol=1e-6)


def test_width_of_ellipse(ellipse):
    t = bake_table(ellipse, ETA, 10.0, None, BakeSettings(resolution_deg=30, photons=2000, batches=2))
    # Semi-axes 0.5 : 0.3 scaled to diameter 1: seen from +x (phi = 0) the shadow spans y.
    np.testing.assert_allclose(t.width([0.0, math.pi / 2, math.pi]), [0.6, 1.0, 0.6], rtol=2e-3)
    np.testing.assert_allclose(t.width(math.pi / 2, psi=math.pi / 2), 0.6, rtol=2e-3)


def test_sampling_follows_p(silk_table):
    t = silk_table
    rec = t.recolour((0.0, 1.0, 3.0))
    rng = np.random.default_rng(5)
    n = 200_000
    th_i, ph_i = 0.6, 2.0
    theta, phi, pdf = rec.sample(th_i, ph_i, rng.random((n, 5)))
    np.testing.assert_allclose(pdf, rec.eval_p(th_i, ph_i, theta, phi, interp_o="nearest").mean(axis=-1), rtol=1e-6)
    g = t.grid
    idx = g.bin_index(np.stack([np.cos(theta) * np.cos(phi), np.cos(theta) * np.sin(phi), np.sin(theta)], -1))
    counts = np.bincount(idx, minlength=g.n_theta_o * g.n_phi_o).reshape(g.n_theta_o, g.n_phi_o)
    T, P = np.meshgrid(g.theta_o_centers(), g.phi_o_centers(), indexing="ij")
    expect = rec.eval_p(th_i, ph_i, T, P, interp_o="nearest").mean(axis=-1) * g.solid_angles()[:, None] * n
    keep = expect > 5
    c2 = float(((counts[keep] - expect[keep]) ** 2 / expect[keep]).sum())
    assert abs(expect.sum() - n) < 1e-3 * n
    # Pearson chi-square over the bins expecting > 5 samples (numpy's seeded stream: the same
    # on every machine): limit at false failure 1e-4 (was 1e-3).
    assert c2 < chi2_limit(int(keep.sum())), c2


def test_save_load_round_trip(tmp_path, silk_table):
    path = tmp_path / "silk.npz"
    silk_table.save(path)
    back = BcsdfTable.load(path)
    for k, v in silk_table.arrays.items():
        assert back.arrays[k].dtype == v.dtype and np.array_equal(back.arrays[k], v)
    a = back.eval_p(0.3, 1.0, -0.3, 2.0, (0.5, 1.0, 2.0))
    b = silk_table.eval_p(0.3, 1.0, -0.3, 2.0, (0.5, 1.0, 2.0))
    np.testing.assert_allclose(a, b)
    assert back.header["error_estimate"]["rms"] > 0
    assert back.header["resolution"]["theta_i"] == 3 and back.header["resolution"]["phi_o"] == 12
