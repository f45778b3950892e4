"""Importance sampling of omega_o from a recoloured table (no stored array is needed).

Per incoming node, the channel-mean bin masses of the recoloured ``p`` give a marginal CDF
over the band's theta_o rows and, per row, a conditional CDF over phi_o
(:func:`outgoing_cdfs`). :func:`sample_outgoing` picks an incoming node with its
interpolation weight (:func:`usdfiber.bake.lookup.incoming_nodes`), a row, a bin, then a
point uniform in the bin's solid angle; its pdf is that of the whole mixture, which equals
the channel mean of the table's ``eval_p(..., interp_o="nearest")``.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from usdfiber.bake.lookup import incoming_nodes

__all__ = ["outgoing_cdfs", "sample_outgoing"]

_TWO_PI = 2.0 * math.pi


def outgoing_cdfs(p: np.ndarray, domega_band: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(marginal, conditional) CDFs for sampling omega_o, from the channel-mean bin masses.

    ``p``: (n_ti, n_pi, B, n_po, C) per steradian; ``domega_band``: (n_ti, n_pi, B) solid
    angle of each band row's bins. ``marginal``: (n_ti, n_pi, B + 1) over the band's theta_o
    rows, from 0 to 1; ``conditional``: (n_ti, n_pi, B, n_po + 1) over phi_o within each row
    (a row without mass gets a uniform CDF). float64.
    """
    mass = p.astype(np.float64).mean(axis=-1) * domega_band[..., None]
    row = mass.sum(axis=-1)
    tot = row.sum(axis=-1, keepdims=True)
    marg = np.concatenate([np.zeros(row.shape[:-1] + (1,)), np.cumsum(row, axis=-1)], axis=-1)
    marg /= np.where(tot > 0, tot, 1.0)
    marg[..., -1] = 1.0
    cond = np.concatenate([np.zeros(mass.shape[:-1] + (1,)), np.cumsum(mass, axis=-1)], axis=-1)
    rs = cond[..., -1:]
    uniform = np.linspace(0.0, 1.0, mass.shape[-1] + 1)
    cond = np.where(rs > 0, cond / np.where(rs > 0, rs, 1.0), uniform)
    cond[..., -1] = 1.0
    return marg, cond


def sample_outgoing(rec: Any, theta_i, phi_i, u: np.ndarray, *, psi: float = 0.0,
                    interp_i: str = "linear") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Draw omega_o from the channel-mean p(. | omega_i) of ``rec`` (a
    :class:`~usdfiber.bake.table.Recoloured`); ``u`` (..., 5) uniform numbers.

    u[0] picks an incoming node with its interpolation weight, u[1] the theta_o row,
    u[2] the phi_o bin, u[3] and u[4] the point in the bin (uniform in solid angle).
    Returns (theta_o, phi_o, pdf) with the pdf per steradian of the whole mixture.
    """
    g = rec.grid
    marg, cond = rec.cdfs()
    u = np.asarray(u, dtype=np.float64)
    th_i, ph_i = np.broadcast_arrays(np.asarray(theta_i, dtype=np.float64),
                                     np.asarray(phi_i, dtype=np.float64))
    shape = np.broadcast_shapes(th_i.shape, u.shape[:-1])
    th_i, ph_i = np.broadcast_to(th_i, shape), np.broadcast_to(ph_i, shape) - psi
    u = np.broadcast_to(u, shape + (5,))
    nodes = incoming_nodes(g, th_i, ph_i, interp_i == "linear")
    cw = np.cumsum(np.stack([w for *_, w in nodes]), axis=0)
    pick = np.sum(u[..., 0][None] >= cw[:-1] / cw[-1:], axis=0) if len(nodes) > 1 else np.zeros(shape, int)
    ti = np.choose(pick, [n[0] for n in nodes])
    pi = np.choose(pick, [n[1] for n in nodes])
    flip = np.choose(pick, [n[2] for n in nodes])
    m = marg[ti, pi]
    r = np.clip(np.sum(u[..., 1:2] >= m[..., 1:], axis=-1), 0, m.shape[-1] - 2)
    c_cdf = cond[ti, pi, r]
    c = np.clip(np.sum(u[..., 2:3] >= c_cdf[..., 1:], axis=-1), 0, g.n_phi_o - 1)
    row = r + rec.table.band_start[ti, pi]
    e = g.theta_o_edges()
    s_lo, s_hi = np.sin(e[row]), np.sin(e[row + 1])
    theta = np.arcsin(np.clip(s_lo + u[..., 3] * (s_hi - s_lo), -1.0, 1.0))
    theta = np.where(flip, -theta, theta)
    phi = (c + u[..., 4]) * g.step
    if g.phi_invariant:
        phi = phi + ph_i - g.phi_i_origin
    phi = np.mod(phi + psi, _TWO_PI)
    pdf = rec.eval_p(th_i, ph_i + psi, theta, phi, psi=psi, interp_i=interp_i,
                     interp_o="nearest").mean(axis=-1)
    return theta, phi, pdf
