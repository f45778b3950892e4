"""Reciprocity averaging: each entry of a box-filtered table estimated from both of its halves.

The scattering cross-section sigma(i, o) = W(phi_i) cos(theta_i) Lambda(i) p(o | i) is
symmetric (Helmholtz reciprocity; the convention: :mod:`usdfiber.bcsdf`). A box-filtered bake
(``BakeSettings(incoming="box")``) spreads each incoming node's light uniformly in solid
angle over its bin, so the histogram sum ``H[I, O]`` of node ``I`` and outgoing bin ``O``
(:mod:`usdfiber.bake.statistics`, with ``B_I`` batches) is an unbiased estimate of

    S(I, O) / |I|,   S(I, O) = integral over I and O of sigma(i, o) di do,

and S(I, O) = S(O, I) exactly: the grid's nodes are its bin centres, so the partner (O as the
incoming bin, I as the outgoing one) is another entry of the same table. Where theta_i >= 0
only is stored (extruded fibers), the partner of a bin with theta_o < 0 is found through the
z-mirror; for rotationally symmetric tables (one phi_i node) through the rotation.

The two estimates are independent when every direction has its own random streams
(:func:`usdfiber.bake.sampling.stream_seed`), and a histogram bin's variance is that of a
Poisson count: Var[|I| H / B] = c_I S with c_I = |I| <W cos>_I / N_I (N_I photons that met
the fiber, <W cos>_I the mean batch weight). The weights lambda_I = c_P / (c_I + c_P) come from
the photon counts only, never from the histograms (weights estimated from the same bins
would correlate with them: a bias); the combined estimate has variance c_I c_P / (c_I + c_P)
S, half of either side's when both have the same photons. Absorption keeps the symmetry at
every level, so the ``G`` sums (path-length moments) are combined with the same weights.
Each direction's total per level is then restored to its own estimate: the albedo is the
direction's (1 at zero absorption, the furnace) and the averaging shapes p, which the table
stores normalized per direction anyway (a ratio: its bias is O(1/N), far below the noise).
"""
from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np

from usdfiber.bake.grid import Grid
from usdfiber.bake.settings import BakeError

__all__ = ["MAX_BYTES", "check_grid", "check_memory", "partner_bins", "reciprocal_average"]

#: Largest memory the averaging may take (all directions' H and G in float32, twice).
MAX_BYTES = 4 << 30


def check_grid(grid: Grid) -> None:
    """Raise BakeError when ``grid``'s incoming nodes are not its bin centres: an entry's
    reciprocal partner is then no entry of the table."""
    if grid.incoming_deg is not None:
        raise BakeError(f"reciprocity averaging needs incoming nodes at the bin centres; this grid has "
                        f"{grid.resolution_deg:g} deg bins and {grid.incoming_deg:g} deg incoming nodes: "
                        "bake it without the 'reciprocity' estimator or without incoming_deg")


def check_memory(grid: Grid, n_levels: int) -> None:
    """Raise BakeError (before anything is traced) when averaging a table of ``grid`` with
    ``n_levels`` absorption levels would take more than :data:`MAX_BYTES`, or when the grid
    has no reciprocal partners (:func:`check_grid`)."""
    check_grid(grid)
    need = 4 * grid.n_theta_i * grid.n_phi_i * grid.n_theta_o * grid.n_phi_o * int(n_levels) * 4
    if need > MAX_BYTES:
        raise BakeError(f"reciprocity averaging of a {grid.resolution_deg:g} deg table with "
                        f"{grid.n_theta_i * grid.n_phi_i} directions needs {need / 2 ** 30:.1f} GiB of memory "
                        f"(limit {MAX_BYTES / 2 ** 30:.0f} GiB): bake it without the 'reciprocity' estimator "
                        "or at a coarser resolution")


def partner_bins(grid: Grid) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For every entry (ti, pi, row, col), its reciprocal partner's (ti', pi', row', col').

    Four int64 arrays of shape (n_theta_i, n_phi_i, n_theta_o, n_phi_o). Applying the map
    twice gives the identity. BakeError for a grid with coarser incoming nodes (:func:`check_grid`).
    """
    check_grid(grid)
    n_ti, n_pi, n_r, n_c = grid.n_theta_i, grid.n_phi_i, grid.n_theta_o, grid.n_phi_o
    ti, pi, ro, co = np.meshgrid(np.arange(n_ti), np.arange(n_pi), np.arange(n_r), np.arange(n_c),
                                 indexing="ij")
    if grid.theta_symmetric:
        # Node k is the centre of row n_ti + k; a row below the equator is mirrored (z -> -z).
        upper = ro >= n_ti
        pt = np.where(upper, ro - n_ti, n_ti - 1 - ro)
        pr = np.where(upper, n_ti + ti, n_ti - 1 - ti)
    else:
        pt, pr = ro, ti
    if grid.phi_invariant:
        # Rotate the partner's incoming direction onto the single node: I lands at -col.
        pp, pc = np.zeros_like(co), (-co) % n_c
    else:
        pp, pc = co, pi
    return pt, pp, pr, pc


def _incoming_measure(grid: Grid) -> np.ndarray:
    """|I| of each theta_i node's box (solid angle, the phi width one bin), (n_theta_i,)."""
    th = grid.theta_i_nodes()
    h = 0.5 * grid.step
    return grid.step * (np.sin(np.minimum(th + h, 0.5 * math.pi)) - np.sin(np.maximum(th - h, -0.5 * math.pi)))


def reciprocal_average(grid: Grid, slices: Mapping[tuple[int, int], Mapping[str, Any]],
                       photons_per_batch: int) -> dict[tuple[int, int], dict[str, Any]]:
    """Every direction's histograms averaged with their reciprocal partners.

    ``slices`` maps every incoming node (ti, pi) of ``grid`` to the mapping of
    :meth:`~usdfiber.bake.statistics.DirectionStatistics.result` of a box-filtered bake (with
    ``photons_per_batch`` photons per batch, so that ``photons / photons_per_batch`` is its
    number of batches). Returns new mappings of the same form; ``rel_error`` is scaled by the
    variance ratio the weights give (the Poisson model above, mass-weighted over the bins).
    """
    n_ti, n_pi, n_r, n_c = grid.n_theta_i, grid.n_phi_i, grid.n_theta_o, grid.n_phi_o
    missing = [(ti, pi) for ti in range(n_ti) for pi in range(n_pi) if (ti, pi) not in slices]
    if missing:
        raise BakeError(f"reciprocity averaging needs every direction; {len(missing)} missing "
                        f"(first: theta_i node {missing[0][0]}, phi_i node {missing[0][1]})")
    first = next(iter(slices.values()))
    K = int(np.asarray(first["H"]).shape[0])
    check_memory(grid, K)
    H = np.zeros((n_ti, n_pi, n_r, n_c, K), dtype=np.float32)
    G = np.zeros_like(H)
    B = np.zeros((n_ti, n_pi))
    N = np.zeros((n_ti, n_pi))
    wbar = np.zeros((n_ti, n_pi))
    for (ti, pi), d in slices.items():
        r0, r1 = d["rows"]
        H[ti, pi, r0:r1] = np.moveaxis(np.asarray(d["H"], dtype=np.float32), 0, -1)
        G[ti, pi, r0:r1] = np.moveaxis(np.asarray(d["G"], dtype=np.float32), 0, -1)
        B[ti, pi] = max(1.0, round(float(d["photons"]) / float(photons_per_batch)))
        N[ti, pi] = float(d["n_hit"]) + float(d.get("misses", 0.0))
        wbar[ti, pi] = float(d["norm"]) / B[ti, pi]
    meas = np.broadcast_to(_incoming_measure(grid)[:, None], (n_ti, n_pi))
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.where(N > 0, meas * wbar / N, np.inf)
    pt, pp, pr, pc = partner_bins(grid)
    self_pair = (pt == np.arange(n_ti)[:, None, None, None]) & (pp == np.arange(n_pi)[None, :, None, None]) & (
        pr == np.arange(n_r)[None, None, :, None]) & (pc == np.arange(n_c)[None, None, None, :])
    out: dict[tuple[int, int], dict[str, Any]] = {}
    for ti in range(n_ti):
        tP, pP, rP, cP = pt[ti], pp[ti], pr[ti], pc[ti]           # (n_pi, n_r, n_c)
        cI = c[ti][:, None, None]
        cQ = c[tP, pP]
        lam = np.where(np.isfinite(cQ), cQ / (cI + cQ), 1.0)
        lam = np.where(self_pair[ti], 1.0, lam)
        # The partner's H estimates S / |P| per batch sum: rescale it to this node's |I| / B_I.
        scale = (meas[tP, pP] * B[ti][:, None, None]) / (meas[ti][:, None, None] * B[tP, pP])
        a = lam[..., None].astype(np.float32)
        b = ((1.0 - lam) * scale)[..., None].astype(np.float32)
        Hn = a * H[ti] + b * H[tP, pP, rP, cP]
        Gn = a * G[ti] + b * G[tP, pP, rP, cP]
        # Each direction keeps its own total per level: the albedo stays the direction's own
        # estimate (exactly 1 without absorption: the furnace), reciprocity shapes p.
        tot, tot_n = H[ti].sum(axis=(1, 2), dtype=np.float64), Hn.sum(axis=(1, 2), dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            keep = np.where(tot_n > 0, tot / tot_n, 0.0).astype(np.float32)[:, None, None, :]
        Hn *= keep
        Gn *= keep
        for pi in range(n_pi):
            d = slices[(ti, pi)]
            h0 = H[ti, pi, ..., 0].astype(np.float64)
            mass = h0.sum()
            ratio = float((lam[pi] * h0).sum() / mass) if mass > 0 else 1.0
            nz = np.flatnonzero(Hn[pi, ..., 0].sum(axis=-1) > 0)
            r0, r1 = (int(nz[0]), int(nz[-1]) + 1) if nz.size else (0, 1)
            new = dict(d)
            new["rows"] = (r0, r1)
            new["H"] = np.ascontiguousarray(np.moveaxis(Hn[pi, r0:r1], -1, 0))
            new["G"] = np.ascontiguousarray(np.moveaxis(Gn[pi, r0:r1], -1, 0))
            new["rel_error"] = float(d["rel_error"]) * math.sqrt(ratio)
            out[(ti, pi)] = new
    return out
