"""Hair and loop flyaways (Zhao 2016 Section 4.1; eq. Y7 of :mod:`usdfiber.geometry.yarn`).

Extra curves on top of the ply fibers, Poisson in number (density x yarn length): hairs are
fiber ends leaving the ply and ending outside the yarn; loops are stretches of a migrating
fiber pulled out of its ply and back.
"""
from __future__ import annotations

import math

import numpy as np

from usdfiber.geometry.expanded_fibers import curve_offsets
from usdfiber.geometry.yarn_centre import CentreLine
from usdfiber.geometry.yarn_fibers import FiberSet, fiber_offset, migrating
from usdfiber.geometry.yarn_plies import ply_angle, ply_cross_section
from usdfiber.geometry.yarn_random import STREAM_HAIR, STREAM_LOOP, kept_subset, random_stream, truncated_normal
from usdfiber.spec.yarn import YarnParams

__all__ = ["hairs", "loops"]

_TWO_PI = 2.0 * math.pi


def hairs(params: YarnParams, centre: CentreLine, h: float, fraction: float, seed_offset: int):
    """Hair flyaways: (points, counts, fiber ids (-1), plies, arc lengths), or None."""
    L = centre.length
    rng = random_stream(params.seed, seed_offset, STREAM_HAIR)
    n = int(rng.poisson(params.hair_density * L)) if params.hair_density > 0 else 0
    if n == 0:
        return None
    N = params.plies
    ply = rng.integers(0, N, n)
    s_exit = rng.random(n) * L
    if N > 1:
        theta = (rng.random(n) * 2.0 - 1.0) * (math.pi / 3.0)
    else:
        theta = rng.random(n) * _TWO_PI
    length = truncated_normal(rng, n, *params.hair_length)
    alpha = np.radians(15.0 + 30.0 * rng.random(n))
    sign = np.where(rng.random(n) < 0.5, -1.0, 1.0)
    depth = (0.2 + 0.4 * rng.random(n)) * params.ply_radius
    kept = kept_subset(n, fraction, rng)
    if len(kept) == 0:
        return None
    ply, s_exit, theta, length = ply[kept], s_exit[kept], theta[kept], length[kept]
    alpha, sign, depth = alpha[kept], sign[kept], depth[kept]
    # Exit point on the (compressed) ply boundary, in cross-section coordinates.
    e_n, e_t = params.ply_compression
    phi = ply_angle(params, ply, s_exit)
    ex, ey = ply_cross_section(params, phi, e_n * params.ply_radius * np.cos(theta),
                               e_t * params.ply_radius * np.sin(theta))
    g = np.stack([ex, ey], -1)
    g = g / np.maximum(np.linalg.norm(g, axis=-1, keepdims=True), 1e-300)
    u_in = depth / np.sin(alpha)                    # along-line length inside the ply
    total = u_in + length
    npts = np.maximum(6, np.ceil(total * np.cos(alpha) / h).astype(np.int64) + 1)
    npts = np.minimum(npts, 4096)
    cidx = np.repeat(np.arange(len(kept)), npts)
    t = (np.arange(len(cidx)) - curve_offsets(npts)[cidx]) / (npts[cidx] - 1.0)
    u = -u_in[cidx] + t * total[cidx]               # signed distance from the exit point
    s = s_exit[cidx] + sign[cidx] * u * np.cos(alpha[cidx])
    x = ex[cidx] + u * np.sin(alpha[cidx]) * g[cidx, 0]
    y = ey[cidx] + u * np.sin(alpha[cidx]) * g[cidx, 1]
    pos, nrm, bin_, sc = centre.frames(s)
    pts = pos + (sc * x)[:, None] * nrm + (sc * y)[:, None] * bin_
    return pts, npts, np.full(len(kept), -1, np.int64), ply, s


def loops(params: YarnParams, centre: CentreLine, fs: FiberSet, h: float, fraction: float,
           seed_offset: int):
    """Loop flyaways: (points, counts, parent fiber ids, plies, arc lengths), or None."""
    L = centre.length
    rng = random_stream(params.seed, seed_offset, STREAM_LOOP)
    n = int(rng.poisson(params.loop_density * L)) if params.loop_density > 0 else 0
    if n == 0:
        return None
    N, fpp, R = params.plies, params.fibers_per_ply, params.ply_radius
    parent = rng.integers(0, N, n) * fpp + rng.integers(0, fpp, n)
    s0 = rng.random(n) * L
    height = truncated_normal(rng, n, *params.loop_height)
    theta_out = (rng.random(n) * 2.0 - 1.0) * (math.pi / 4.0)
    kept = kept_subset(n, fraction, rng)
    if len(kept) == 0:
        return None
    parent, s0, height, theta_out = parent[kept], s0[kept], height[kept], theta_out[kept]
    k = len(kept)
    tf = abs(params.fiber_twist)
    lo_span, hi_span = 2.0 * (R + height), 8.0 * (R + height)
    if tf > 0:
        span = np.clip(params.migration_period / (2.0 * tf), lo_span, hi_span)
    else:
        span = 4.0 * (R + height)
    if migrating(params) and tf > 0:
        # Nearest migration maximum of the parent: 2 pi tf s / P + theta_mig = 2 pi m.
        cyc = params.migration_period / tf
        m = np.round((s0 / cyc) + fs.theta_mig[parent] / _TWO_PI)
        s_c = (m - fs.theta_mig[parent] / _TWO_PI) * cyc
        s_c = np.where((s_c < 0) | (s_c > L), s0, s_c)
    else:
        s_c = s0
    span = np.minimum(span, L)
    s_c = np.clip(s_c, 0.5 * span, L - 0.5 * span)
    npts = np.maximum(13, np.ceil(span / h).astype(np.int64) + 1)
    npts = npts + (npts % 2 == 0)                   # odd: a sample at the loop's middle
    npts = np.minimum(npts, 4097)
    cidx = np.repeat(np.arange(k), npts)
    u = (np.arange(len(cidx)) - curve_offsets(npts)[cidx]) / (npts[cidx] - 1.0)
    s = s_c[cidx] + (u - 0.5) * span[cidx]
    p = parent[cidx]
    ply = fs.ply[parent]
    a, b = fiber_offset(params, fs.rest[p], fs.theta0[p], fs.theta_mig[p], s)
    e_n, e_t = params.ply_compression
    if N == 1:
        theta_o = fs.theta0[parent] + _TWO_PI * params.fiber_twist * s_c
    else:
        theta_o = theta_out
    dx, dy = e_n * np.cos(theta_o), e_t * np.sin(theta_o)
    dn = np.hypot(dx, dy)
    peak = R * dn + height                          # D + H (eq. Y7)
    pa, pb = (peak * dx / dn)[cidx], (peak * dy / dn)[cidx]
    w = np.sin(np.pi * u) ** 2
    phi = ply_angle(params, ply[cidx], s)
    x, y = ply_cross_section(params, phi, (1 - w) * a + w * pa, (1 - w) * b + w * pb)
    pos, nrm, bin_, sc = centre.frames(s)
    pts = pos + (sc * x)[:, None] * nrm + (sc * y)[:, None] * bin_
    return pts, npts, parent.astype(np.int64), ply, s
