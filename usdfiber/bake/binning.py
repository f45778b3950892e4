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

A bake bins each traced batch at all of its absorption levels with :func:`level_sums` (one
bin index and path length per exit for every level; :func:`bin_indices` is
:meth:`Grid.bin_index` without its float64 remainder), bit for bit the sums that binning each
exit in turn gives.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from usdfiber.bake.grid import Grid

__all__ = ["DEFAULT_GRID", "bin_direct", "bin_indices", "level_sums"]

#: 2 degree bins, the paper's resolution: 90 theta_o x 180 phi_o.
DEFAULT_GRID = Grid(2.0)


def bin_indices(grid: Grid, directions: np.ndarray) -> np.ndarray:
    """:meth:`Grid.bin_index` of unit directions (M, 3), bit for bit, with fewer passes.

    The same float64 arcsin, arctan2 and floors; ``np.mod(phi, 2 pi)`` of an arctan2 in
    [-pi, pi] is ``phi + 2 pi`` where ``phi < 0`` (the same addition numpy's remainder does)
    and the column ``% n_phi`` of a floor in [0, n_phi] is a subtraction at ``n_phi``: the
    float64 remainder was most of the cost (tests/bake/test_fast_paths.py checks the
    equality, edges included).
    """
    d = np.asarray(directions)
    n = len(d)
    step = float(grid.step)
    a = np.empty(n)
    b = np.empty(n)
    np.copyto(a, d[:, 2], casting="same_kind")
    np.clip(a, -1.0, 1.0, out=a)
    np.arcsin(a, out=a)
    a += 0.5 * math.pi
    a /= step
    np.floor(a, out=a)
    with np.errstate(invalid="ignore"):      # NaN: reported below
        row = a.astype(np.int64)
    np.copyto(a, d[:, 1], casting="same_kind")
    np.copyto(b, d[:, 0], casting="same_kind")
    np.arctan2(a, b, out=a)
    np.add(a, 2.0 * math.pi, out=a, where=a < 0.0)
    a /= step
    np.floor(a, out=a)
    with np.errstate(invalid="ignore"):
        col = a.astype(np.int64)
    # Finite directions give row, col >= 0 before the clip (NaN casts to the most negative int).
    if n and min(int(row.min()), int(col.min())) < 0:
        raise ValueError("an exit direction is not finite (NaN): it has no outgoing bin")
    np.clip(row, 0, grid.n_theta_o - 1, out=row)
    n_phi = grid.n_phi_o
    col[col >= n_phi] -= n_phi
    row *= n_phi
    row += col
    return row


def level_sums(directions: np.ndarray, path_length: np.ndarray, weight: np.ndarray | None,
               cut: np.ndarray | None, grid: Grid, levels: Any) -> tuple[np.ndarray, np.ndarray]:
    """Summed ``w exp(-s_k L)`` and ``w exp(-s_k L) L`` per outgoing bin at every level ``s_k``.

    Two (levels, bins) float64 arrays, equal bit for bit to ``np.bincount`` of each level's
    weights over all exits in their order (cut exits carry weight 0 and are skipped: adding
    0 to a non-negative sum changes nothing). ``weight`` None is weight 1 (the plain
    estimator: no product). One bin index and one float64 path length serve every level;
    the per-level arrays reuse two buffers (fresh megabyte temporaries cost more than the
    arithmetic).
    """
    nb = grid.n_theta_o * grid.n_phi_o
    d = np.asarray(directions)
    L32 = np.asarray(path_length)
    w0 = None if weight is None else np.asarray(weight, dtype=np.float64)
    if cut is not None:
        keep = ~np.asarray(cut, dtype=bool)
        if not keep.all():
            d, L32 = d[keep], L32[keep]
            w0 = None if w0 is None else w0[keep]
    lv = np.asarray(levels, dtype=np.float64)
    h = np.zeros((len(lv), nb))
    gl = np.zeros((len(lv), nb))
    if len(d) == 0:
        return h, gl
    idx = bin_indices(grid, d)
    L = L32.astype(np.float64)
    e = np.empty(len(L))
    wl = np.empty(len(L))
    for k, s in enumerate(lv):
        if s > 0:
            np.multiply(L, -s, out=e)            # the bits of -s * L
            np.exp(e, out=e)
            if w0 is not None:
                np.multiply(w0, e, out=e)
            w = e
        else:
            w = w0
        if w is None:
            # Unit weights: the float64 sums of ones are exact counts, and 1 x L is L.
            h[k] = np.bincount(idx, minlength=nb)
            gl[k] = np.bincount(idx, weights=L, minlength=nb)
            continue
        h[k] = np.bincount(idx, weights=w, minlength=nb)
        np.multiply(w, L, out=wl)
        gl[k] = np.bincount(idx, weights=wl, minlength=nb)
    return h, gl


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
