"""A fitted model against a table over the sphere, through other code paths than the fit's.

The fit compares bin masses (:class:`usdfiber.fit.objective.FitTarget`, exact logistic CDFs,
Gauss nodes in each bin). Here the table is read back through its own ``cross_section`` at
the bin centres, averaged over one rotation per incoming node, and the models are evaluated
point by point (:func:`usdfiber.fit.chiang.far_field`, :func:`usdfiber.fit.khungurn.far_field`)
and averaged by midpoints inside each bin. Both give ``s = sigma / <W>`` on the table's grid
(n_theta_i, n_theta_o, n_dphi, C), compared by the relative L2 norm with the weights
cos(theta_i) x (solid angle of the theta_o bin).
"""
from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from usdfiber.fit import chiang, khungurn


def table_scattering(table: Any, sigma_a: Sequence[float]) -> np.ndarray:
    """The table's rotation-averaged ``s`` at the bin centres, shape (n_i, n_o, n_dphi, C)."""
    g = table.grid
    dphi = g.step * np.arange(g.n_phi_o)
    psis = -g.step * np.arange(g.n_phi_i)        # a fiber rotated by psi sees the light at phi_i - psi
    phi_i = 0.5 * g.step
    TI, TO, DP = np.meshgrid(g.theta_i_nodes(), g.theta_o_centers(), dphi, indexing="ij")
    wbar = float(np.mean(table.width(np.linspace(0, 2 * math.pi, 720, endpoint=False))))
    tab = np.zeros(TI.shape + (len(sigma_a),))
    for psi in psis:
        tab += table.cross_section(TI, phi_i, TO, phi_i + DP, list(sigma_a), psi=psi,
                                   interp_i="nearest", interp_o="nearest")
    return tab / (len(psis) * wbar)


def model_scattering(grid: Any, model: str, params: Any, k: int = 8, n_h: int = 64) -> np.ndarray:
    """A model's ``s = cos(theta_o) f`` averaged by k x k midpoints in each bin of ``grid``
    (Chiang: over ``n_h`` offsets)."""
    ti = grid.theta_i_nodes()
    to_e = grid.theta_o_edges()
    n_p = grid.n_phi_o
    dphi = grid.step * np.arange(n_p)
    u = (np.arange(k) + 0.5) / k
    out = None
    for o in range(grid.n_theta_o):
        th = to_e[o] + (to_e[o + 1] - to_e[o]) * u
        ph = dphi[:, None] + grid.step * (u[None, :] - 0.5)
        A, B, C = np.meshgrid(ti, th, ph.ravel(), indexing="ij")
        f = chiang.far_field(params, B, A, C, n_h=n_h) if model == "chiang" else khungurn.far_field(params, B, A, C)
        v = (f * (np.cos(B) ** 2)[..., None]).reshape(len(ti), k, n_p, k, -1).sum(axis=(1, 3))
        if out is None:
            out = np.zeros((len(ti), grid.n_theta_o, n_p, v.shape[-1]))
        out[:, o] = v / (np.cos(th).sum() * k)
    return out


def relative_l2(values: np.ndarray, reference: np.ndarray, grid: Any) -> np.ndarray:
    """Per channel ``sqrt(sum w (values - reference)^2 / sum w reference^2)`` (module docstring)."""
    e = np.diff(np.sin(grid.theta_o_edges()))
    w = (np.cos(grid.theta_i_nodes())[:, None] * e[None, :])[..., None, None]
    return np.sqrt((w * (values - reference) ** 2).sum(axis=(0, 1, 2)) / (w * reference ** 2).sum(axis=(0, 1, 2)))


def independent_error(table: Any, model: str, params: Any, sigma_a: Sequence[float]) -> np.ndarray:
    """Relative L2 of the model against the table, per channel (module docstring)."""
    return relative_l2(model_scattering(table.grid, model, params), table_scattering(table, sigma_a), table.grid)
