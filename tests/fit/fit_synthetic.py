"""Tables written from a fitted model's own far field, for recovery tests of the fits."""
from __future__ import annotations

import numpy as np

from usdfiber.bake.assembly import assemble
from usdfiber.bake.grid import Grid
from usdfiber.fit import chiang, khungurn
from usdfiber.fit.objective import FitTarget

LEVELS = (0.0, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0)     # 1/um at the baked diameter of 1 um (radius 0.5)
WIDTH_SAMPLES = 720


def _stub(grid: Grid) -> FitTarget:
    n_i, n_o, n_p = grid.n_theta_i, grid.n_theta_o, grid.n_phi_o
    return FitTarget(np.zeros((n_i, n_o, n_p, 1)), grid.theta_i_nodes(), grid.theta_o_edges(), grid.step,
                     grid.theta_symmetric, np.zeros((n_i, 1)))


def model_table(values_at, grid: Grid, levels=LEVELS):
    """A BcsdfTable whose bins hold ``values_at(s)`` (n_i, n_o, n_phi): the model's ``s`` for
    the absorption ``s`` (1/um at the baked size) on the grid's bins; round (W = 1)."""
    stub = _stub(grid)
    cos_i = np.cos(stub.theta_i)[:, None, None]
    dom = grid.solid_angles()[None, :, None]

    def mass(s: float) -> np.ndarray:           # per photon meeting the fiber, per bin
        return np.maximum(values_at(s, stub), 0.0) * dom / cos_i

    H, G = [], []
    for s in levels:
        d = 1e-4
        f0 = mass(s)
        lo = mass(max(s - d, 0.0))
        hi = mass(s + d)
        with np.errstate(divide="ignore", invalid="ignore"):
            lbar = -(np.log(hi) - np.log(lo)) / ((s + d) - max(s - d, 0.0))
        lbar = np.where(np.isfinite(lbar), lbar, 0.0)
        H.append(f0)
        G.append(f0 * lbar)
    H = np.stack(H, axis=1)            # (n_i, K, n_o, n_phi)
    G = np.stack(G, axis=1)

    def load_slice(ti: int, pi: int) -> dict:
        return {"rows": (0, grid.n_theta_o), "H": H[ti], "G": G[ti], "norm": 1.0, "rel_error": 0.0, "photons": 1}

    header = {"geometry_key": "synthetic", "inputs": {}, "photons": {}, "error_estimate": {}, "eta": 1.55,
              "baked_diameter_um": 1.0, "variant": 0}
    return assemble(grid, levels, (grid.n_theta_i, 1), load_slice, np.ones(WIDTH_SAMPLES), header,
                    band_tail=0.0, storage="float32")


def chiang_table(params: chiang.ChiangParams, resolution_deg: float = 10.0, n_h: int = 128, n_sub: int = 8):
    """The Chiang model's table; the absorption s (1/um, radius 0.5 um) is 0.5 s per radius."""
    grid = Grid(resolution_deg, params.alpha_deg == 0.0, True)

    def values_at(s: float, stub: FitTarget) -> np.ndarray:
        g = chiang.make_grid(stub, n_h, n_sub)
        return chiang.grid_values(params.with_channels([0.5 * s]), stub, g)[..., 0]
    return model_table(values_at, grid)


def khungurn_table(params: khungurn.KhungurnParams, resolution_deg: float = 10.0, n_sub: int = 8):
    grid = Grid(resolution_deg, True, True)

    def values_at(s: float, stub: FitTarget) -> np.ndarray:
        return khungurn.grid_values(params, stub, n_sub)[..., 0]
    return model_table(values_at, grid, levels=(0.0,))
