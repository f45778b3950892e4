"""Fits of the standard models to tables: recovery, reported errors, cache, bad input.

* Recovery: tables written from the Chiang model's own far field (``fit_synthetic``:
  128 offsets and 8 nodes per bin, against the fit's 32 and 3; absorption levels exact,
  recolouring interpolates between them) give back the parameters: ior within 0.01,
  roughnesses and absorption within 2 %, the cuticle tilt within 0.2 deg (measured:
  1e-5 relative). Same for Khungurn's model (no absorption).
* Real tables (15 degree bakes of a round and a silk fiber): the reported relative L2 error
  equals an independent evaluation of both models, through the table's own
  ``cross_section`` at the bin centres averaged over rotations, and the models' point
  evaluation averaged by midpoints inside each bin, within 10 % of the error (the two
  differ by bin-centre sampling of the table, which the fit's bin masses do not do). The silk
  cases (36 incoming azimuths) are marked slow (measured: within 1 % of the error).
* The fit is deterministic, cached beside the table (a second call returns the stored
  result; a damaged file is reported and refitted) and keyed by colour.
"""
from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

import usdfiber  # noqa: F401
from usdfiber.bake import profiles
from usdfiber.bake.baker import bake_table
from usdfiber.bcsdf import BakeSettings, TableCacheWarning
from usdfiber.fit import ChiangParams, FitCache, FitSettings, KhungurnParams, UnknownModelError, fit_tables

from fit_independent import independent_error
from fit_synthetic import chiang_table, khungurn_table


@pytest.mark.parametrize("alpha", [0.0, 3.0])
def test_chiang_fit_recovers_its_parameters(alpha):
    truth = ChiangParams(ior=1.6, beta_m=0.25, beta_n=0.35, alpha_deg=alpha)
    table = chiang_table(truth)
    res = fit_tables([table], "chiang", sigma_a=(0.5, 1.0, 2.0), cache=False)
    p = res.params
    print(f"\n[fit-recovery] chiang alpha {alpha}: {p}, error {res.error['rel_l2']}")
    assert abs(p.ior - 1.6) < 0.01
    assert p.beta_m == pytest.approx(0.25, rel=0.02) and p.beta_n == pytest.approx(0.35, rel=0.02)
    assert abs(p.alpha_deg - alpha) < 0.2
    # 1/um at the baked diameter of 1 um is half that per unit radius
    assert np.allclose(p.sigma_a, (0.25, 0.5, 1.0), rtol=0.02)
    assert max(res.error["rel_l2"]) < 0.01


def test_khungurn_fit_recovers_its_parameters():
    truth = KhungurnParams((0.1,), (0.7,), 12.0, 20.0, 40.0)
    res = fit_tables([khungurn_table(truth)], "khungurn", cache=False)
    p = res.params
    assert p.c_r[0] == pytest.approx(0.1, rel=0.02) and p.c_tt[0] == pytest.approx(0.7, rel=0.02)
    assert p.beta_r_deg == pytest.approx(12.0, rel=0.02) and p.beta_tt_deg == pytest.approx(20.0, rel=0.02)
    assert p.gamma_tt_deg == pytest.approx(40.0, rel=0.02)


class _Tables(dict):
    """A round fiber (beta 5 deg) and one silk variant, 15 degrees, baked on first use into a
    cache layout (``<root>/tables/<name>.npz``)."""

    def __init__(self, root) -> None:
        super().__init__()
        self.root = root
        (root / "tables").mkdir()

    def __missing__(self, name: str):
        prof = profiles.circle() if name == "round" else profiles.builtin_profiles("silk", 1)[0]
        t = bake_table(prof, 1.55, 5.0, None, BakeSettings(resolution_deg=15.0, photons=10_000, batches=2),
                       header={"eta": 1.55})
        t.save(self.root / "tables" / f"{name}.npz")
        self[name] = t
        return t


@pytest.fixture(scope="module")
def real_tables(tmp_path_factory):
    return _Tables(tmp_path_factory.mktemp("fits"))


@pytest.mark.parametrize("name", ["round", pytest.param("silk", marks=pytest.mark.slow)])
@pytest.mark.parametrize("model", ["chiang", "khungurn"])
def test_reported_error_matches_independent_evaluation(real_tables, name, model):
    table = real_tables[name]
    sig = (0.5, 1.5, 4.0)
    res = fit_tables([table], model, sigma_a=sig, cache=False)
    ind = independent_error(table, model, res.params, sig)
    rep = np.array(res.error["rel_l2"])
    print(f"\n[fit-recovery] {name} {model}: reported {np.round(rep, 4)}, independent {np.round(ind, 4)}, "
          f"albedo table {np.round(res.error['albedo_table'], 3)} model {np.round(res.error['albedo_model'], 3)}")
    assert np.all(np.abs(ind - rep) <= 0.1 * rep + 0.005)
    assert np.all(rep > 0.0)


def test_cached_beside_the_table_deterministic_and_keyed(real_tables, tmp_path):
    table = real_tables["round"]
    res = fit_tables([table], "khungurn", sigma_a=(0.5, 1.0, 2.0))
    store = FitCache.beside(table)
    from pathlib import Path
    assert store.root == Path(table.path).parent.parent / "fits" and store.path(res.key).exists()
    again = fit_tables([table], "khungurn", sigma_a=(0.5, 1.0, 2.0))
    assert again.cached and again.params == res.params and again.error == res.error
    fresh = fit_tables([table], "khungurn", sigma_a=(0.5, 1.0, 2.0), cache=False)
    assert fresh.params == res.params                            # deterministic
    other = fit_tables([table], "khungurn", sigma_a=(0.5, 1.0, 2.1), cache=False)
    assert other.key != res.key
    assert fit_tables([table], "khungurn", sigma_a=(0.5, 1.0, 2.0), settings=FitSettings(floor=0.05),
                      cache=False).key != res.key
    # a damaged file is reported, deleted and fitted again
    path = store.path(res.key)
    doc = json.loads(path.read_text())
    doc["fit"]["params"]["c_r"][0] = 0.5
    path.write_text(json.dumps(doc))
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        redo = fit_tables([table], "khungurn", sigma_a=(0.5, 1.0, 2.0))
    assert any(issubclass(x.category, TableCacheWarning) and "checksum mismatch" in str(x.message) for x in w)
    assert not redo.cached and redo.params == res.params


def test_bad_input(real_tables):
    table = real_tables["round"]
    with pytest.raises(UnknownModelError, match="unknown model 'marschner'; valid: chiang, khungurn"):
        fit_tables([table], "marschner", cache=False)
    with pytest.raises(ValueError, match="sigma_a must be finite and >= 0"):
        fit_tables([table], "chiang", sigma_a=(-1.0, 0.0, 0.0), cache=False)
    with pytest.raises(ValueError, match="no tables"):
        fit_tables([], "chiang", cache=False)
    with pytest.raises(ValueError, match="channels"):
        ChiangParams(sigma_a=(0.1, 0.2), tint_r=(1.0, 1.0, 1.0))


@pytest.mark.parametrize("incoming_bins", [1, 3])
def test_fit_target_of_a_table_with_phi_nodes(incoming_bins):
    """A round model's table written at every phi_i node (nodes every ``incoming_bins`` bins)
    gives the fit the same target as its one-node table: each node's columns are shifted by
    the bin it sits over, not by its index. An even spacing (nodes on bin edges) is refused."""
    from usdfiber.bake.assembly import assemble
    from usdfiber.bake.grid import Grid
    from usdfiber.fit import khungurn
    from usdfiber.fit.objective import FitTarget

    params = KhungurnParams(beta_r_deg=12.0, beta_tt_deg=20.0, gamma_tt_deg=40.0)
    res = 5.0
    one = FitTarget.from_tables([khungurn_table(params, resolution_deg=res)])
    header = {"geometry_key": "synthetic", "inputs": {}, "photons": {}, "error_estimate": {}, "eta": 1.55,
              "baked_diameter_um": 1.0, "variant": 0}

    def table_on(grid):
        stub = FitTarget(np.zeros((grid.n_theta_i, grid.n_theta_o, grid.n_phi_o, 1)), grid.theta_i_nodes(),
                         grid.theta_o_edges(), grid.step, grid.theta_symmetric, np.zeros((grid.n_theta_i, 1)))
        mass = (np.maximum(khungurn.grid_values(params, stub, 8)[..., 0], 0.0)
                * grid.solid_angles()[None, :, None] / np.cos(stub.theta_i)[:, None, None])
        shift = np.rint((grid.phi_i_nodes() - 0.5 * grid.step) / grid.step).astype(int)

        def load_slice(ti: int, pi: int) -> dict:
            H = np.roll(mass[ti], shift[pi], axis=1)[None]
            return {"rows": (0, grid.n_theta_o), "H": H, "G": np.zeros_like(H), "norm": 1.0,
                    "rel_error": 0.0, "photons": 1}
        return assemble(grid, (0.0,), (grid.n_theta_i, grid.n_phi_i), load_slice, np.ones(720), header,
                        band_tail=0.0, storage="float32")

    spacing = None if incoming_bins == 1 else incoming_bins * res
    many = FitTarget.from_tables([table_on(Grid(res, True, False, incoming_deg=spacing))])
    fine = one.values[incoming_bins // 2::incoming_bins]     # the fine theta_i nodes the coarse ones sit on
    np.testing.assert_allclose(many.values, fine, rtol=1e-4, atol=1e-6 * one.values.max())
    with pytest.raises(ValueError, match="bin centres"):
        FitTarget.from_tables([table_on(Grid(res, True, False, incoming_deg=2 * res))])
