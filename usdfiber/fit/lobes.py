"""Building blocks shared by the fitted fiber models: quadrature nodes and bin averages.

The tables hold bin averages over outgoing directions (``usdfiber.bake.table``), so the
models are compared bin for bin: azimuthal lobes are averaged over each bin of
``Delta phi`` exactly, through the lobe's cumulative distribution (:func:`periodic_bin_mean`),
and longitudinal lobes by Gauss-Legendre nodes inside each theta bin, weighted by
``cos theta`` (the solid angle of a thin ring).
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np

__all__ = ["gauss_legendre", "offset_nodes", "periodic_bin_mean", "periodic_cdf", "theta_bin_nodes", "wrap_pi"]

TWO_PI = 2.0 * math.pi


def gauss_legendre(n: int, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
    """``n`` Gauss-Legendre nodes and weights on [lo, hi]."""
    x, w = np.polynomial.legendre.leggauss(int(n))
    half = 0.5 * (hi - lo)
    return lo + half * (x + 1.0), half * w


def offset_nodes(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Offsets ``h`` across a round fiber and weights for the average ``(1/2) int_{-1}^{1} dh``.

    Gauss-Legendre in ``gamma = asin h`` (the exit azimuths ``Phi(p, h)`` are smooth in
    gamma, not in h near the silhouette): ``h = sin gamma``, weight ``w_gamma cos gamma / 2``.
    """
    g, w = gauss_legendre(n, -0.5 * math.pi, 0.5 * math.pi)
    return np.sin(g), 0.5 * w * np.cos(g)


def theta_bin_nodes(edges: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Nodes (n_bins, n) inside each theta bin and weights that average over the bin's solid
    angle: ``sum_k w_k g(theta_k) ~ int_bin g cos theta d theta / (sin hi - sin lo)``."""
    e = np.asarray(edges, dtype=np.float64)
    x, w = np.polynomial.legendre.leggauss(int(n))
    lo, hi = e[:-1, None], e[1:, None]
    half = 0.5 * (hi - lo)
    th = lo + half * (x[None, :] + 1.0)
    wt = half * w[None, :] * np.cos(th)
    return th, wt / (np.sin(hi) - np.sin(lo))


def wrap_pi(x: np.ndarray) -> np.ndarray:
    """Angles mapped to [-pi, pi)."""
    return np.mod(np.asarray(x, dtype=np.float64) + math.pi, TWO_PI) - math.pi


def periodic_cdf(cdf: Callable[[np.ndarray], np.ndarray], u: np.ndarray) -> np.ndarray:
    """The integral from -pi to ``u`` of a density on the circle, for any real ``u``.

    ``cdf(x)`` is the density's cumulative distribution on [-pi, pi] (0 at -pi, 1 at pi); the
    density repeats with period 2 pi, so the integral is ``k + cdf(x)`` with ``u = x + 2 pi k``.
    """
    u = np.asarray(u, dtype=np.float64)
    k = np.floor((u + math.pi) / TWO_PI)
    return k + cdf(u - TWO_PI * k)


def periodic_bin_mean(cdf: Callable[[np.ndarray], np.ndarray], lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Mean over [lo, hi] (radians, hi - lo <= 2 pi) of a density on the circle, per radian
    (``cdf`` as in :func:`periodic_cdf`)."""
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    return (periodic_cdf(cdf, hi) - periodic_cdf(cdf, lo)) / (hi - lo)
