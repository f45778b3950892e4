"""Fibers within the plies (Zhao 2016 eqs. 2-4; eqs. Y3-Y6 of :mod:`usdfiber.geometry.yarn`).

Each fiber has a rest radius drawn from the radial density profile p(R) (Zhao's rejection
sampler), an initial angle and a migration phase; along the yarn it turns around its ply
centre with the fiber twist and migrates between rho_min and rho_max of its rest radius.
Staple fibers are cut every staple length from a random offset.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from usdfiber.geometry.yarn_centre import CentreFrames, CentreLine
from usdfiber.geometry.yarn_plies import ply_angle
from usdfiber.geometry.yarn_random import STREAM_FIBERS, random_stream
from usdfiber.spec.yarn import YarnParams

__all__ = ["FiberSet", "density_profile", "fiber_offset", "fiber_set", "migrating", "ply_fibers",
           "sample_rest_radius"]

_TWO_PI = 2.0 * math.pi


def density_profile(R: np.ndarray, eps: float, beta: float) -> np.ndarray:
    """Zhao 2016 eq. 4 (Y3): p(R) = (1 - 2 eps) ((e - exp(R)) / (e - 1))^beta + eps, for R the
    distance from the ply centre as a fraction of R_ply (fibers per unit cross-section area,
    unnormalized; p(0) = 1 - eps, p(1) = eps)."""
    R = np.clip(np.asarray(R, np.float64), 0.0, 1.0)
    base = np.maximum((math.e - np.exp(R)) / (math.e - 1.0), 0.0)
    return (1.0 - 2.0 * eps) * base**beta + eps


def sample_rest_radius(rng: np.random.Generator, n: int, eps: float, beta: float) -> np.ndarray:
    """Zhao 2016 Algorithm 1: points uniform in the unit disk, accepted with probability p(R)."""
    out = np.empty(n)
    filled = 0
    while filled < n:
        m = int(min(max(256, 3 * (n - filled)), 1 << 22))
        r = np.sqrt(rng.random(m))
        acc = r[rng.random(m) < density_profile(r, eps, beta)][: n - filled]
        out[filled:filled + len(acc)] = acc
        filled += len(acc)
    return out


@dataclass
class FiberSet:
    """The random draws of every fiber of a yarn (fiber id = ply * fibersPerPly + j)."""

    ply: np.ndarray        # (F,) int
    rest: np.ndarray       # (F,) R_j as a fraction of R_ply
    theta0: np.ndarray     # (F,)
    theta_mig: np.ndarray  # (F,)
    staple_offset: np.ndarray  # (F,)


def fiber_set(params: YarnParams, seed_offset: int) -> FiberSet:
    """Every fiber's rest radius, angles, staple offset and ply (one stream per yarn)."""
    n = params.fiber_count
    rng = random_stream(params.seed, seed_offset, STREAM_FIBERS)
    eps, beta = params.density_profile
    rest = sample_rest_radius(rng, n, eps, beta)
    theta0 = rng.random(n) * _TWO_PI
    theta_mig = rng.random(n) * _TWO_PI
    staple = rng.random(n) * params.staple_length
    ply = np.repeat(np.arange(params.plies), params.fibers_per_ply)
    return FiberSet(ply, rest, theta0, theta_mig, staple)


def migrating(params: YarnParams) -> bool:
    """Whether fibers migrate (rho_min != rho_max)."""
    return params.migration[0] != params.migration[1]


def fiber_offset(params: YarnParams, rest: Any, theta0: Any, theta_mig: Any, s: Any
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Fiber offset from its ply centre in the ply frame (radial, tangential), eqs. Y4-Y6
    before the rotation by phi: (e_N r cos theta, e_T r sin theta)."""
    theta = theta0 + _TWO_PI * params.fiber_twist * s
    rmin, rmax = params.migration
    if migrating(params):
        mig = rmin + (rmax - rmin) * 0.5 * (
            np.cos(_TWO_PI * abs(params.fiber_twist) * s / params.migration_period + theta_mig) + 1.0)
    else:
        mig = rmin
    r = rest * params.ply_radius * mig
    e_n, e_t = params.ply_compression
    return e_n * r * np.cos(theta), e_t * r * np.sin(theta)


def ply_fibers(params: YarnParams, centre: CentreLine, grid: CentreFrames, fs: FiberSet,
                ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Samples of the kept ply fibers on the grid, cut into staples.

    Eqs. Y1-Y6 separate into per-fiber coefficients times per-sample vectors: with
    U = k (cos phi n + sin phi b), V = k (-sin phi n + cos phi b), W = C + d U (the ply centre),
    A = e_N cos(w s) U + e_T sin(w s) V, B = -e_N sin(w s) U + e_T cos(w s) V (w = 2 pi T_fib)
    and the migration factor c0 + c1 cos(nu s + theta_mig),
        P(s) = W + R_j R_ply (c0 + c1 cos(nu s + theta_mig)) (cos theta_j A + sin theta_j B),
    i.e. one (fibers x 6) @ (6 x 3M) matrix product per ply (2 rows without migration).

    Returns (samples (P, 3), counts, fiber id per curve, arclength per point, ply centres
    (plies, M, 3)).
    """
    s = grid.s
    m = len(s)
    k = len(ids)
    pts = np.empty((k, m, 3))
    rmin, rmax = params.migration
    c0, c1 = 0.5 * (rmin + rmax), 0.5 * (rmax - rmin)
    e_n, e_t = params.ply_compression
    om = _TWO_PI * params.fiber_twist * s
    cw, sw = np.cos(om)[:, None], np.sin(om)[:, None]
    sc = grid.scale[:, None]
    nu = _TWO_PI * abs(params.fiber_twist) / params.migration_period * s
    cnu, snu = np.cos(nu)[:, None], np.sin(nu)[:, None]
    varies = migrating(params) and c1 != 0.0
    ply_of = fs.ply[ids]
    centres = np.empty((params.plies, m, 3))
    for i in range(params.plies):
        phi = ply_angle(params, i, s)
        cp, sp = np.cos(phi)[:, None], np.sin(phi)[:, None]
        U = sc * (cp * grid.normal + sp * grid.binormal)
        V = sc * (cp * grid.binormal - sp * grid.normal)
        W = grid.position + params.ply_distance * U
        centres[i] = W
        sel = np.flatnonzero(ply_of == i)
        if len(sel) == 0:
            continue
        A = e_n * cw * U + e_t * sw * V
        B = e_t * cw * V - e_n * sw * U
        f = ids[sel]
        rr = fs.rest[f] * params.ply_radius
        ct, st = rr * np.cos(fs.theta0[f]), rr * np.sin(fs.theta0[f])
        if varies:
            cm, sm = np.cos(fs.theta_mig[f]), np.sin(fs.theta_mig[f])
            coef = np.stack([c0 * ct, c0 * st, c1 * cm * ct, c1 * cm * st,
                             -c1 * sm * ct, -c1 * sm * st], axis=1)
            basis = np.stack([A, B, cnu * A, cnu * B, snu * A, snu * B]).reshape(6, 3 * m)
        else:
            coef = np.stack([rmin * ct, rmin * st], axis=1)
            basis = np.stack([A, B]).reshape(2, 3 * m)
        lo, hi = int(sel[0]), int(sel[-1]) + 1   # ids are sorted, so a ply's fibers are contiguous
        out = pts[lo:hi].reshape(hi - lo, 3 * m)
        np.matmul(coef, basis, out=out)
        out += W.reshape(1, 3 * m)
    pts = pts.reshape(-1, 3)
    arclen = np.tile(s, k)
    if params.staple_length > 0 and k > 0:
        # Cuts at off_j + q l (q = 0, 1, ...): a piece starts at the first sample at or after a cut.
        l = params.staple_length
        nq = int(math.ceil(centre.length / l)) + 1
        cuts = fs.staple_offset[ids, None] + l * np.arange(nq)[None, :]
        bounds = np.concatenate([np.zeros((k, 1), np.int64), np.searchsorted(s, cuts),
                                 np.full((k, 1), m, np.int64)], axis=1)
        counts = np.diff(bounds, axis=1)                      # (k, nq + 1), zeros included
        starts = (bounds[:, :-1] + (np.arange(k) * m)[:, None]).reshape(-1)
        counts = counts.reshape(-1)
        fiber_of_curve = np.repeat(ids, nq + 1)
        nonempty = counts > 0
        starts, counts, fiber_of_curve = starts[nonempty], counts[nonempty], fiber_of_curve[nonempty]
        good = counts >= 2
        if not good.all():
            keep_pt = np.repeat(good, counts)
            pts, arclen = pts[keep_pt], arclen[keep_pt]
            counts, fiber_of_curve = counts[good], fiber_of_curve[good]
    else:
        counts = np.full(k, m, np.int64)
        fiber_of_curve = ids.astype(np.int64)
    return pts, counts.astype(np.int64), fiber_of_curve.astype(np.int64), arclen, centres
