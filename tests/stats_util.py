"""Statistical tools of the test suite: thresholds from a false-failure budget, and variance
estimates that carry their degrees of freedom.

Every statistical assertion of the suite may fail on a correct implementation with a
probability of at most ``FALSE_FAILURE`` (1e-4). Its threshold is derived from that budget
and from the distribution of the statistic under the null hypothesis (the implementation is
right), never tuned to the numbers one machine happens to produce: Dr.Jit vectorizes with the
host's SIMD width, so a fixed seed gives different random streams on different machines
(``docs/testing.md``). Variances estimated from the data enter with their degrees of freedom
(Student t, F), so a noise estimate from two seeds cannot pass for a precise one.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy import stats

#: Largest false-failure probability allowed for one assertion.
FALSE_FAILURE = 1e-4


def z_limit(p: float = FALSE_FAILURE) -> float:
    """|z| bound that a standard normal exceeds with probability ``p`` (two-sided)."""
    return float(stats.norm.isf(0.5 * p))


def t_limit(dof: float, p: float = FALSE_FAILURE) -> float:
    """|t| bound that Student's t with ``dof`` degrees of freedom exceeds with probability ``p``."""
    return float(stats.t.isf(0.5 * p, dof))


def chi2_limit(dof: float, p: float = FALSE_FAILURE) -> float:
    """Upper bound that a chi-square with ``dof`` degrees of freedom exceeds with probability ``p``."""
    return float(stats.chi2.isf(p, dof))


def f_limit(dof_num: float, dof_den: float, p: float = FALSE_FAILURE) -> float:
    """Upper bound that F(dof_num, dof_den) exceeds with probability ``p``."""
    return float(stats.f.isf(p, dof_num, dof_den))


def binomial_limit(q: float, n: int, p: float = FALSE_FAILURE) -> float:
    """Bound on |k/n - q| (compare with <=) for k ~ Binomial(n, q), exceeded with probability <= ``p``.

    Exact (from the binomial's quantiles, each tail ``p / 2``), so it holds for small n and
    for q near 0 or 1 where the normal approximation does not.
    """
    lo, hi = stats.binom.ppf(0.5 * p, n, q), stats.binom.isf(0.5 * p, n, q)
    return float(max(q - lo / n, hi / n - q))


def poisson_limit(lam: float, p: float = FALSE_FAILURE) -> tuple[int, int]:
    """Counts (lo, hi) such that a Poisson(lam) count falls outside [lo, hi] with probability <= p."""
    return int(stats.poisson.ppf(0.5 * p, lam)), int(stats.poisson.isf(0.5 * p, lam))


def ks_limit(n: int, p: float = FALSE_FAILURE) -> float:
    """Kolmogorov-Smirnov distance that n samples of the tested distribution exceed with
    probability ``p`` (exact distribution of the one-sample statistic)."""
    return float(stats.kstwo.isf(p, n))


def satterthwaite_dof(variances: np.ndarray, dofs: np.ndarray | float) -> float:
    """Effective degrees of freedom of a sum of independent variance estimates.

    ``sum(v_i)`` with ``v_i`` estimated with ``dofs_i`` degrees of freedom is approximately a
    scaled chi-square with (sum v)^2 / sum(v^2 / dof) degrees of freedom (Welch-Satterthwaite).
    A sum dominated by one term has about that term's degrees of freedom.
    """
    v = np.asarray(variances, np.float64)
    d = np.broadcast_to(np.asarray(dofs, np.float64), v.shape)
    den = float(np.sum(v * v / d))
    return float(np.sum(v)) ** 2 / den if den > 0.0 else math.inf


@dataclass(frozen=True)
class BlockComparison:
    """Two Monte-Carlo estimates of the same image, compared block by block.

    ``ratio`` is sum_b d_b^2 / sum_b v_b over image blocks (d_b: difference of the two means of
    block b, v_b: its variance estimated from the spread between seeds): about F(dof_blocks,
    dof_variance) when both estimate the same image, larger when they differ anywhere. ``z``
    is the difference of the image means over its standard deviation estimated from the same
    pooled per-block variances: about Student t with ``dof_variance`` degrees of freedom.
    Each limit is exceeded with probability ``p / 2`` under agreement, so ``agrees`` fails a
    correct pair with probability at most ``p``.
    """

    ratio: float
    ratio_limit: float
    z: float
    z_limit: float
    dof_blocks: float
    dof_variance: float

    def agrees(self) -> bool:
        return self.ratio < self.ratio_limit and abs(self.z) < self.z_limit


def compare_blocks(a: Sequence[np.ndarray], b: Sequence[np.ndarray], block: int = 4,
                   p: float = FALSE_FAILURE) -> BlockComparison:
    """Compare two sets of independent renders (one image per seed, H x W x C) block by block.

    Each block's value is the sum over its pixels and channels (channels of one pixel share
    their paths, so they are not independent). The variance of each set's mean is estimated
    per block from its seeds (K - 1 degrees of freedom each) and pooled over the blocks with
    Welch-Satterthwaite degrees of freedom; with a few seeds and many blocks that is hundreds
    of degrees of freedom, where the spread of whole-image means over two seeds had one.
    The sets must use disjoint seeds.
    """
    def blocks(imgs: Sequence[np.ndarray]) -> np.ndarray:
        x = np.asarray(imgs, np.float64)
        k, h, w, c = x.shape
        if h % block or w % block:
            raise ValueError(f"image {h}x{w} is not a multiple of the block size {block}")
        return x.reshape(k, h // block, block, w // block, block, c).sum(axis=(2, 4, 5)).reshape(k, -1)

    xa, xb = blocks(a), blocks(b)
    ka, kb = len(xa), len(xb)
    if ka < 2 or kb < 2:
        raise ValueError("each set needs at least two seeds to estimate its variance")
    d = xa.mean(axis=0) - xb.mean(axis=0)
    va, vb = xa.var(axis=0, ddof=1) / ka, xb.var(axis=0, ddof=1) / kb
    v = va + vb
    if not np.all(np.isfinite(d)) or v.sum() <= 0.0:
        raise ValueError("renders are not finite or have no variance")
    # Per block: v_b has Satterthwaite dof from its two parts; the sum over blocks pools them.
    dof_b = np.where(v > 0.0, v * v / np.maximum(va * va / (ka - 1) + vb * vb / (kb - 1), 1e-300), 1.0)
    dof_variance = satterthwaite_dof(v, dof_b)
    # The numerator sum d_b^2 with Var(d_b) = v_b is a weighted chi-square: its effective dof
    # has the same form with one dof per block (weights estimated by v_b).
    dof_blocks = satterthwaite_dof(v, 1.0)
    ratio = float((d * d).sum() / v.sum())
    z = float(d.sum() / math.sqrt(v.sum()))
    return BlockComparison(ratio=ratio, ratio_limit=f_limit(dof_blocks, dof_variance, 0.5 * p),
                           z=z, z_limit=t_limit(dof_variance, 0.5 * p),
                           dof_blocks=dof_blocks, dof_variance=dof_variance)
