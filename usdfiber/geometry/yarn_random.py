"""The yarn generator's random streams: one independent stream per purpose and yarn.

Every draw of :func:`usdfiber.geometry.yarn.expand_yarn` comes from a stream keyed by
(``yarn:seed``, seed offset, purpose), so fibers, their order for level of detail, hairs and
loops do not shift when another of them changes.
"""
from __future__ import annotations

import numpy as np

__all__ = ["STREAM_FIBERS", "STREAM_HAIR", "STREAM_LOOP", "STREAM_ORDER", "kept_subset",
           "random_stream", "truncated_normal"]

STREAM_FIBERS, STREAM_ORDER, STREAM_HAIR, STREAM_LOOP = 1, 2, 3, 4


def random_stream(seed: int, seed_offset: int, stream: int) -> np.random.Generator:
    """The generator of ``stream`` for a yarn ``seed`` and ``seed_offset``."""
    ss = np.random.SeedSequence([int(seed) % 2**64, int(seed_offset) % 2**64, stream, 0x59A2])
    return np.random.Generator(np.random.PCG64(ss))


def truncated_normal(rng: np.random.Generator, n: int, mean: float, std: float) -> np.ndarray:
    """N(mean, std) conditioned on >= 0 (rejection; std == 0 gives the mean)."""
    if std <= 0:
        return np.full(n, max(mean, 0.0))
    out = rng.normal(mean, std, n)
    for _ in range(1000):
        bad = out < 0
        if not bad.any():
            return out
        out[bad] = rng.normal(mean, std, int(bad.sum()))
    return np.maximum(out, 0.0)


def kept_subset(count: int, fraction: float, rng: np.random.Generator, minimum: int = 0) -> np.ndarray:
    """Sorted indices of the first max(minimum, round(fraction * count)) of a random
    permutation of range(count) (so smaller fractions give subsets)."""
    order = rng.permutation(count)
    k = min(count, max(minimum, int(round(fraction * count))))
    return np.sort(order[:k])
