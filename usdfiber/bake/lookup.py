"""Looking up a table's values at arbitrary directions (interpolation between nodes and bins).

Incoming directions (nodes ``grid.incoming_step`` apart, :mod:`usdfiber.bake.grid`): linear
between the two nearest theta_i nodes (extruded tables mirror
the first node through theta_i = 0) and the two nearest phi_i nodes (periodic), or the
nearest node. Outgoing directions: bilinear between bin centres (periodic in phi_o, constant
beyond the outermost theta_o centres), or the bin's value, which is exactly the histogram.
Rotationally symmetric tables are read at ``phi_o - phi_i + d/2`` (:mod:`usdfiber.bake.grid`).
A fiber rotated by ``psi`` about its axis sees ``phi - psi``. Angles in radians.
"""
from __future__ import annotations

import math

import numpy as np

from usdfiber.bake.grid import Grid

__all__ = ["eval_directional", "eval_incoming", "incoming_nodes", "lookup_outgoing"]

_TWO_PI = 2.0 * math.pi
_HALF_PI = 0.5 * math.pi


def incoming_nodes(grid: Grid, theta_i: np.ndarray, phi_i: np.ndarray,
                   linear: bool) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Interpolation nodes of incoming directions: [(ti, pi, flip, weight), ...].

    ``flip`` says the node is used through the theta symmetry (theta_o must be negated).
    Linear: tent weights between the two nearest theta_i nodes (extruded tables mirror the
    first node below theta_i = 0) and the two nearest phi_i nodes (periodic); beyond the
    outermost theta_i node, the outermost node. Nearest: the node of the bin.
    """
    th = np.asarray(theta_i, dtype=np.float64)
    ph = np.asarray(phi_i, dtype=np.float64)
    n_t = grid.n_theta_i
    if grid.theta_symmetric:
        flip_base = th < 0.0
        a = np.abs(th)
    else:
        flip_base = np.zeros(th.shape, dtype=bool)
        a = th
    u = (a - grid.theta_i_min) / grid.incoming_step - 0.5
    if linear:
        k0 = np.floor(u)
        t = u - k0
        k0 = k0.astype(np.int64)
        k1 = k0 + 1
        th_nodes = []
        for k, w in ((k0, 1.0 - t), (k1, t)):
            flip = flip_base.copy()
            if grid.theta_symmetric:
                mirror = k < 0
                flip = flip ^ mirror
                k = np.where(mirror, -k - 1, k)
            th_nodes.append((np.clip(k, 0, n_t - 1), flip, w))
    else:
        k = np.clip(np.floor(u + 0.5).astype(np.int64), 0, n_t - 1)
        th_nodes = [(k, flip_base, np.ones(th.shape))]

    if grid.phi_invariant:
        ph_nodes = [(np.zeros(ph.shape, dtype=np.int64), np.ones(ph.shape))]
    else:
        n_p = grid.n_phi_i
        v = np.mod(ph, _TWO_PI) / grid.incoming_step - 0.5
        if linear:
            j0 = np.floor(v)
            t = v - j0
            j0 = j0.astype(np.int64)
            ph_nodes = [(np.mod(j0, n_p), 1.0 - t), (np.mod(j0 + 1, n_p), t)]
        else:
            ph_nodes = [(np.mod(np.floor(v + 0.5).astype(np.int64), n_p), np.ones(ph.shape))]

    out = []
    for ti, flip, wt in th_nodes:
        for pi, wp in ph_nodes:
            out.append((ti, pi, flip, wt * wp))
    return out


def lookup_outgoing(grid: Grid, band_start: np.ndarray, values: np.ndarray, ti: np.ndarray,
                    pi: np.ndarray, theta_o: np.ndarray, phi_o: np.ndarray, bilinear: bool) -> np.ndarray:
    """Values (..., C) of ``values[ti, pi, band_row, col, C]`` at outgoing directions.

    Bilinear between bin centres in (theta_o, phi_o) (periodic in phi, constant beyond the
    outermost theta_o centres), or the bin's value. Rows outside the band are 0.
    """
    n_band = values.shape[2]
    n_r, n_c = grid.n_theta_o, grid.n_phi_o
    start = band_start[ti, pi].astype(np.int64)

    def gather(r, c):
        rr = r - start
        ok = (rr >= 0) & (rr < n_band)
        v = values[ti, pi, np.clip(rr, 0, n_band - 1), c]
        return np.where(ok[..., None], v, 0.0)

    a = (theta_o + _HALF_PI) / grid.step
    b = np.mod(phi_o, _TWO_PI) / grid.step
    if not bilinear:
        r = np.clip(np.floor(a).astype(np.int64), 0, n_r - 1)
        c = np.floor(b).astype(np.int64) % n_c
        return gather(r, c).astype(np.float64)
    a = np.clip(a - 0.5, 0.0, n_r - 1.0)
    r0 = np.minimum(np.floor(a).astype(np.int64), n_r - 1)
    tr = (a - r0)[..., None]
    r1 = np.minimum(r0 + 1, n_r - 1)
    b = b - 0.5
    c0f = np.floor(b)
    tc = (b - c0f)[..., None]
    c0 = c0f.astype(np.int64) % n_c
    c1 = (c0 + 1) % n_c
    return ((1 - tr) * (1 - tc) * gather(r0, c0) + (1 - tr) * tc * gather(r0, c1)
            + tr * (1 - tc) * gather(r1, c0) + tr * tc * gather(r1, c1))


def eval_directional(grid: Grid, band_start: np.ndarray, values: np.ndarray, theta_i, phi_i,
                     theta_o, phi_o, psi, interp_i: str, interp_o: str) -> np.ndarray:
    """Values (..., C) of a per-bin array ``values[ti, pi, band_row, col, C]`` at arbitrary
    directions (radians, broadcast) for a fiber rotated by ``psi``: ``interp_i`` ("linear" or
    "nearest") between incoming nodes, ``interp_o`` ("bilinear" or "nearest") in omega_o."""
    if interp_i not in ("linear", "nearest"):
        raise ValueError("interp_i must be 'linear' or 'nearest'")
    if interp_o not in ("bilinear", "nearest"):
        raise ValueError("interp_o must be 'bilinear' or 'nearest'")
    th_i, ph_i, th_o, ph_o = np.broadcast_arrays(*(np.asarray(x, dtype=np.float64)
                                                   for x in (theta_i, phi_i, theta_o, phi_o)))
    ph_i = ph_i - psi
    ph_o = ph_o - psi
    if grid.phi_invariant:
        ph_o = ph_o - ph_i + grid.phi_i_origin
    out = np.zeros(th_i.shape + (values.shape[-1],))
    for ti, pi, flip, w in incoming_nodes(grid, th_i, ph_i, interp_i == "linear"):
        th = np.where(flip, -th_o, th_o)
        out += w[..., None] * lookup_outgoing(grid, band_start, values, ti, pi, th, ph_o,
                                              interp_o == "bilinear")
    return out


def eval_incoming(grid: Grid, values: np.ndarray, theta_i, phi_i, psi, interp_i: str) -> np.ndarray:
    """Values (..., C) of a per-direction array ``values[ti, pi, C]`` at incoming directions."""
    th_i, ph_i = np.broadcast_arrays(np.asarray(theta_i, dtype=np.float64),
                                     np.asarray(phi_i, dtype=np.float64))
    out = np.zeros(th_i.shape + (values.shape[-1],))
    for ti, pi, _flip, w in incoming_nodes(grid, th_i, ph_i - psi, interp_i == "linear"):
        out += w[..., None] * values[ti, pi]
    return out
