"""Incoming nodes coarser than the outgoing bins: grid, settings, bake, file, lookup, exact answer."""
from __future__ import annotations

import math

import numpy as np
import pytest

from usdfiber.bake import band_limit, exact, profiles
from usdfiber.bake.baker import bake_table, table_directions
from usdfiber.bake.grid import Grid
from usdfiber.bake.lookup import incoming_nodes
from usdfiber.bake.reciprocity import partner_bins
from usdfiber.bake.requests import requests_from_preset
from usdfiber.bake.settings import BakeError, BakeSettings
from usdfiber.bake.storage import TableLayoutError, read_table_file, write_table_file
from usdfiber.bake.table import BcsdfTable

ETA = 1.55


@pytest.fixture(scope="module")
def coarse_silk() -> BcsdfTable:
    """Silk's profile on 15 deg bins with incoming nodes every 30 deg (3 x 12 directions)."""
    prof = profiles.builtin_profiles("silk", 1)[0]
    return bake_table(prof, ETA, 8.0, None, BakeSettings(resolution_deg=15, incoming_deg=30, photons=2000, batches=2))


# ---- grid and settings ---------------------------------------------------------------------------

def test_grid_incoming_nodes_and_header():
    g = Grid(15, True, False, 30)
    assert (g.n_theta_o, g.n_phi_o, g.n_theta_i, g.n_phi_i) == (12, 24, 3, 12)
    np.testing.assert_allclose(np.degrees(g.theta_i_nodes()), [15, 45, 75])
    np.testing.assert_allclose(np.degrees(g.phi_i_nodes()), 15 + 30 * np.arange(12))
    assert Grid.from_header(g.to_header()) == g
    cut = Grid(5, False, False, 10)
    np.testing.assert_allclose(np.degrees(cut.theta_i_nodes()), -85 + 10 * np.arange(18))
    # One node for round profiles, at half an OUTGOING bin (the mirror maps bins onto bins).
    rnd = Grid(2, True, True, 10)
    assert rnd.n_phi_i == 1 and np.degrees(rnd.phi_i_nodes())[0] == pytest.approx(1.0)
    # The paper's grid is unchanged: equal spacing is no spacing, and the header does not name it.
    assert Grid(2, True, False, 2.0) == Grid(2)
    assert "incoming_deg" not in Grid(2).to_header() and "incoming_deg" in g.to_header()
    for bad in (20, 22.5, 7.5, 0, -30, math.nan):   # not a multiple of 15 dividing 90
        with pytest.raises(ValueError, match="incoming node spacing"):
            Grid(15, True, False, bad)


def test_header_counts_must_match_the_grid():
    h = Grid(15, True, False, 30).to_header()
    with pytest.raises(ValueError, match="theta_i = 6"):
        Grid.from_header({**h, "theta_i": 6})
    with pytest.raises(ValueError, match="has 6"):     # a header that lost its incoming_deg
        Grid.from_header({k: v for k, v in h.items() if k != "incoming_deg"})


def test_settings_keep_the_papers_keys_and_refuse_what_cannot_work():
    assert BakeSettings(incoming_deg=2.0) == BakeSettings()
    assert "incoming_deg" not in BakeSettings().result_inputs()
    st = BakeSettings(resolution_deg=3, incoming_deg=6)
    assert st.result_inputs()["incoming_deg"] == 6.0
    with pytest.raises(BakeError, match="multiple"):
        BakeSettings(resolution_deg=3, incoming_deg=4)
    with pytest.raises(BakeError, match="box"):
        BakeSettings(resolution_deg=3, incoming_deg=6, incoming="box")
    for kw in ({"incoming_deg": 6}, {"resolution_deg": 6}):
        with pytest.raises(BakeError, match="auto"):
            BakeSettings(auto_resolution=True, **kw)
    auto = BakeSettings(auto_resolution=True)
    assert auto.result_inputs()["auto_resolution"] is True and "band_limit_rule" in auto.result_inputs()
    assert "auto_resolution" not in BakeSettings().result_inputs()
    # The peak-memory bound counts the coarse grid's directions.
    assert st.table_bytes() < BakeSettings(resolution_deg=3).table_bytes()


def test_reciprocity_refuses_coarse_incoming_nodes():
    with pytest.raises(BakeError, match="incoming nodes at the bin centres"):
        partner_bins(Grid(15, True, False, 30))


def test_baker_traces_the_coarse_nodes():
    req = requests_from_preset("silk")[0]
    assert len(table_directions(req, BakeSettings(resolution_deg=15, incoming_deg=30))) == 3 * 12
    assert len(table_directions(req, BakeSettings(resolution_deg=15))) == 6 * 24


# ---- a baked table ---------------------------------------------------------------------------------

def test_coarse_table_round_trips(coarse_silk, tmp_path):
    t = coarse_silk
    assert t.grid == Grid(15, True, False, 30)
    assert t.arrays["p"].shape[:2] == (3, 12) and t.arrays["p"].shape[-1] == 24
    assert t.header["resolution"]["incoming_deg"] == 30
    assert t.header["bake"]["settings"]["incoming_deg"] == 30
    path = tmp_path / "coarse.npz"
    t.save(path)
    back = BcsdfTable.load(path)
    assert back.grid == t.grid
    for name, arr in t.arrays.items():
        np.testing.assert_array_equal(back.arrays[name], arr)
    # A header whose grid does not describe the arrays is refused by the loader, with the file named.
    header, arrays = read_table_file(path)
    for res in ({**header["resolution"], "incoming_deg": 15.0},            # counts disagree
                {k: v for k, v in header["resolution"].items() if k not in ("incoming_deg", "theta_i", "phi_i")}):
        write_table_file(tmp_path / "bad.npz", {**header, "resolution": res}, arrays)
        with pytest.raises(TableLayoutError, match="bad.npz"):
            BcsdfTable.load(tmp_path / "bad.npz")


def test_coarse_table_interpolates_between_its_nodes(coarse_silk):
    t = coarse_silk
    g = t.grid
    th_n, ph_n = g.theta_i_nodes(), g.phi_i_nodes()
    to, po = g.theta_o_centers()[:, None], g.phi_o_centers()[None, :]
    node = lambda i, j: t.eval_p(th_n[i], ph_n[j], to, po, interp_o="nearest")  # noqa: E731
    # At a node: the stored histogram itself.
    p = t.level_p(0)[1, 4].astype(np.float64)
    b0 = int(t.band_start[1, 4])
    # (eval_p goes through the recolouring path, renormalized in float32: agreement to 1e-4, below float16's 5e-4 step)
    np.testing.assert_allclose(node(1, 4)[b0:b0 + t.n_band], p, rtol=1e-4, atol=1e-6 * p.max())
    # Midway between nodes 30 deg apart (not between 15 deg bins): the mean of the two.
    mid = t.eval_p(0.5 * (th_n[1] + th_n[2]), ph_n[4], to, po, interp_o="nearest")
    np.testing.assert_allclose(mid, 0.5 * (node(1, 4) + node(2, 4)), rtol=1e-4, atol=1e-7)
    mid = t.eval_p(th_n[1], 0.5 * (ph_n[4] + ph_n[5]), to, po, interp_o="nearest")
    np.testing.assert_allclose(mid, 0.5 * (node(1, 4) + node(1, 5)), rtol=1e-4, atol=1e-7)
    # Through theta_i = 0: the first node and its mirror (theta_o negated).
    nodes = incoming_nodes(g, np.array([0.0]), np.array([ph_n[4]]), True)
    weight = {}
    for ti, _, fl, w in nodes:
        weight[(int(ti[0]), bool(fl[0]))] = weight.get((int(ti[0]), bool(fl[0])), 0.0) + float(w[0])
    assert weight == pytest.approx({(0, False): 0.5, (0, True): 0.5})
    # Sampling draws from the density evaluation reports, on the coarse grid too.
    rec = t.recolour(0.0)
    u = np.random.default_rng(3).random((64, 5))
    th, ph, pdf = rec.sample(0.4, 1.1, u)
    np.testing.assert_allclose(pdf, rec.eval_p(0.4, 1.1, th, ph, interp_o="nearest")[..., 0], rtol=1e-5)


def test_smooth_circle_exact_at_coarse_nodes():
    """A smooth circle on 2 deg bins with incoming nodes 30 deg apart: every node's light on the
    cone theta_o = -theta_node, and its azimuthal distribution the exact one."""
    n = 1 << 20
    t = bake_table(profiles.circle(), ETA, 0.0, None,
                   BakeSettings(resolution_deg=2, incoming_deg=30, photons=n, batches=4))
    g = t.grid
    assert (g.n_theta_i, g.n_phi_i) == (3, 1)
    dom = t.domega_band()
    for k, theta in enumerate(g.theta_i_nodes()):
        p = t.level_p(0)[k, 0].astype(np.float64)
        mass = p * dom[k, 0][:, None]
        rows = int(t.band_start[k, 0]) + np.arange(t.n_band)
        cone = int(np.floor((math.pi / 2 - theta) / g.step))       # the row holding -theta
        assert mass[rows == cone].sum() > 0.999
        # Column c holds phi_o - phi_i in [2c - 1, 2c + 1) deg (phi_i = 1 deg): two 1 deg exact bins.
        ex = exact.azimuthal_distribution(theta, ETA, n_bins=360, n_h=1 << 19) * (2 * math.pi / 360)
        want = (ex + np.roll(ex, 1))[0::2]
        got = mass.sum(axis=0)
        l1 = float(np.abs(got / got.sum() - want / want.sum()).sum())
        # Noise L1 of 1M mirror-averaged photons over 180 bins is about 0.3 % (the tracer's
        # 0.25 % at 4M unmirrored, test_tracer.py), spread about 10 % of itself: 1.5 % is a bias
        # bound noise does not reach (false failure far below 1e-4); a node traced at the
        # wrong theta (e.g. 2 deg bins' 1, 3, 5 deg) moves the cone and fails the row test.
        assert l1 < 0.015, (math.degrees(theta), l1)


# ---- the band-limit rule (auto_resolution) -----------------------------------------------------------

def test_every_measured_grid_is_valid_and_the_rule_keeps_its_bound():
    assert band_limit.MEASURED, "the rule has measurements"
    for name, m in band_limit.MEASURED.items():
        for d_o, d_i in m.grids:
            Grid(d_o, not m.cuticle, m.round_profile, d_i)
        for photons in (16_000_000, 1_000_000, 100_000):
            res, inc = band_limit.band_limited_grid(m.beta_deg, m.round_profile, m.cuticle, photons=photons)
            # Presets of one kind and roughness (cotton, mercerized cotton) share the rule's answer.
            peers = [o for o in band_limit.MEASURED.values()
                     if (o.beta_deg, o.round_profile, o.cuticle) == (m.beta_deg, m.round_profile, m.cuticle)]
            allowed = [k for k in m.grids if all(o.bias_ratio(k, photons) <= 0.5 for o in peers)]
            if (res, inc) != (2.0, None):
                key = (int(res), int(inc if inc is not None else res))
                assert key in allowed, (name, photons, key)
            else:
                assert not allowed, (name, photons, allowed)


def test_rule_coarsens_only_with_looser_targets_and_rougher_fibers():
    def directions(g):
        grid = Grid(g[0], True, False, g[1])
        return grid.n_theta_i * grid.n_phi_i

    for m in band_limit.MEASURED.values():
        grids = [band_limit.band_limited_grid(m.beta_deg, m.round_profile, m.cuticle, photons=n)
                 for n in (16_000_000, 1_000_000, 100_000, 1000)]
        counts = [directions(g) for g in grids]
        assert counts == sorted(counts, reverse=True), grids
        # A target error wins over the photons; a smoother fiber than any measured one of its
        # kind gets the paper's grid.
        assert band_limit.band_limited_grid(m.beta_deg, m.round_profile, m.cuticle, photons=1000,
                                            target_error=1e-4) == (2.0, None)
        smallest = min(o.beta_deg for o in band_limit.MEASURED.values()
                       if (o.round_profile, o.cuticle) == (m.round_profile, m.cuticle))
        assert band_limit.band_limited_grid(0.5 * smallest, m.round_profile, m.cuticle, photons=1000) == (2.0, None)


def test_auto_bake_records_its_grid(tmp_path):
    """A round fiber rougher than polyester, at few enough photons for a coarser grid: the
    rule's grid is traced, recorded in the header, and read back."""
    ref = band_limit.MEASURED["polyester"]
    # The most photons at which some grid's bias is at most half the plain table's noise.
    photons = int(0.8 * max((0.5 / kappa) ** 2 for _, kappa, _ in ref.grids.values()))
    st = BakeSettings(auto_resolution=True, photons=max(photons, 64), batches=2)
    want = band_limit.band_limited_grid(15.0, True, False, photons=st.photons)
    assert want != (2.0, None), "a loose target allows a coarser grid"
    t = bake_table(profiles.circle(), ETA, 15.0, None, st)
    assert (t.grid.resolution_deg, t.grid.incoming_deg) == want
    assert t.header["band_limit"]["rule_version"] == band_limit.RULE_VERSION
    assert t.header["bake"]["settings"]["auto_resolution"] is True
    t.save(tmp_path / "auto.npz")
    assert BcsdfTable.load(tmp_path / "auto.npz").grid == t.grid


def test_bake_command_takes_resolution_auto(tmp_path, capsys):
    from usdfiber import cli

    rc = cli.main(["bake", "--preset", "polyester", "--resolution", "auto", "--photons", "1000", "--batches", "2",
                   "--dry-run", "--no-progress", "--cache-dir", str(tmp_path)])
    out = capsys.readouterr().out
    assert rc == 0 and "45 directions" in out        # polyester's measured grid at 1000 photons: 2 deg
    rc = cli.main(["bake", "--preset", "polyester", "--resolution", "auto", "--incoming", "box", "--dry-run",
                   "--cache-dir", str(tmp_path)])
    assert rc == 2 and capsys.readouterr().err.count("\n") == 1
