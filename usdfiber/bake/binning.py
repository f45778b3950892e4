"""Binning photon exits into a table's outgoing bins with exact per-photon weights.

Bins are those of :class:`usdfiber.bake.grid.Grid` (theta_o in [-90, 90] deg, phi_o in
[0, 360) deg, phi from +x towards +y in the fiber frame, sin(theta) = w.z; only its outgoing
half is used). Densities are per steradian and per photon that hit the fiber: a bin's value
is the summed weight of its photons divided by (n_hit x its exact solid angle
(sin th1 - sin th0) dphi), so ``sum(density * solid_angle)`` is the albedo Lambda(omega_i)
and density / albedo is p(omega_o | omega_i).

Each exit is weighted by exp(-sigma_a L) with its own path length L in the material (times its
weight at zero absorption, ``TraceResult.weight``, where an estimator leaves several exits
of fractional weight per photon, and plus the exits the expected-value estimator binned in the
tracer, ``TraceResult.histogram``, at its own absorption levels): this is
the direct answer that the baked tables' recolouring (:mod:`usdfiber.bake.absorption`, which
keeps a few absorption levels per bin and interpolates between them) is checked against.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from usdfiber.bake.grid import Grid

__all__ = ["DEFAULT_GRID", "bin_direct"]

#: 2 degree bins, the paper's resolution: 90 theta_o x 180 phi_o.
DEFAULT_GRID = Grid(2.0)


def _valid(result: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    keep = ~np.asarray(result.cut, dtype=bool)
    w = getattr(result, "weight", None)
    w = np.ones(int(keep.sum())) if w is None else np.asarray(w, dtype=np.float64)[keep]
    return np.asarray(result.directions)[keep], np.asarray(result.path_length, dtype=np.float64)[keep], w


def bin_direct(result: Any, sigma_a: float | np.ndarray = 0.0, grid: Grid | None = None) -> np.ndarray:
    """Densities of a tracer result with the exact per-photon weight exp(-sigma_a L).

    Returns (n_theta_o, n_phi_o) for a scalar ``sigma_a`` or (n_theta_o, n_phi_o, C) for C
    channels.
    """
    grid = grid or DEFAULT_GRID
    dirs, L, w = _valid(result)
    idx = grid.bin_index(dirs) if len(dirs) else np.zeros(0, np.int64)
    nb = grid.n_theta_o * grid.n_phi_o
    norm = 1.0 / (max(int(result.n_hit), 1) * grid.bin_solid_angles().ravel())
    s = np.atleast_1d(np.asarray(sigma_a, dtype=np.float64))
    sums = [np.bincount(idx, weights=w * np.exp(-c * L), minlength=nb) for c in s]
    hist = getattr(result, "histogram", None)
    if hist is not None:
        hb = result.histogram_bins
        if (hb.n_theta, hb.n_phi) != (grid.n_theta_o, grid.n_phi_o):
            raise ValueError(f"the result's expected-value histogram has {hb.n_theta}x{hb.n_phi} bins, "
                             f"the grid {grid.n_theta_o}x{grid.n_phi_o}")
        sums = [x + hist[result.histogram_level(c), 0] for x, c in zip(sums, s)]
    out = np.stack([x * norm for x in sums], axis=-1)
    out = out.reshape(grid.n_theta_o, grid.n_phi_o, len(s))
    return out[..., 0] if np.ndim(sigma_a) == 0 else out
