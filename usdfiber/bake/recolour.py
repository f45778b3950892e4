"""Recolouring a table's p in fused, multi-threaded Dr.Jit (LLVM) kernels.

:meth:`~usdfiber.bake.table.BcsdfTable.recolour` needs, for every bin of every incoming
direction, the bin mass ``F(s)`` interpolated between the two absorption levels around ``s``
(cubic Hermite in ``log F``, :func:`usdfiber.bake.absorption.hermite_log_interp`), then
``p = F / sum(F) / domega``. On a 2 degree table that is 10^8 bins per channel. In numpy
(float64, one core, a temporary array per operation) it takes about 18 s per channel; here
it takes three passes on all cores, in float32, reading the float16 levels straight from the
table's own arrays (Dr.Jit maps them without a copy):

1. one kernel over the bins: a lane reads each level its channels need once (the levels'
   offsets and the Hermite weights are kernel parameters, so a new colour reuses the
   kernel), computes every channel with one ``log`` and one ``exp``, and writes the masses
   channel-major into one array of C x n_dir x B x n_po (each element once);
2. the row sums of that array (one block reduction), totalled per (channel, direction) in
   numpy (small);
3. one kernel that reads the masses in order and scales each (channel, direction).

The result is the last kernel's memory, viewed as ``(..., B, n_po, C)`` without a copy
(:class:`~usdfiber.bake.table.Recoloured`). A compressed table (:func:`recolour_basis`)
takes the same passes 2 and 3 after one kernel over its bins that reads each bin's basis
values once and writes every channel's ``max(0, sum_j c_j b_j)``.

The arithmetic is that of :func:`~usdfiber.bake.absorption.hermite_log_interp` in float32
(checked against it in ``tests/bake/test_recolour.py``); the float64 numpy path stays as the
reference and the fallback where Dr.Jit has no LLVM backend.
"""
from __future__ import annotations

import functools
from typing import Sequence

import numpy as np

from usdfiber.bake.absorption import level_bracket

__all__ = ["available", "recolour_basis", "recolour_p"]

#: Elements of the level arrays (or of the output) per launch: indices stay 32-bit.
_MAX_ELEMENTS = 1 << 31


@functools.cache
def available() -> bool:
    """Whether Dr.Jit's LLVM backend can run the kernel here (an LLVM >= 16 was found: older
    ones abort inside the JIT, see :mod:`usdfiber.backend`)."""
    try:
        from usdfiber.backend import configure_llvm, find_llvm

        if find_llvm() is None:
            return False
        configure_llvm()
        import drjit as dr

        return bool(dr.has_backend(dr.JitBackend.LLVM))
    except Exception:   # no drjit, or no usable LLVM: the numpy path is used
        return False


class _Channel:
    """How one channel's absorption ``s`` sits among the levels (plain Python numbers)."""

    def __init__(self, levels: np.ndarray, s: float) -> None:
        s = float(s)
        K = len(levels)
        self.k = level_bracket(levels, s)
        s0 = float(levels[self.k])
        self.ds = s - s0
        if s == s0:
            self.mode = "level"           # exactly at level k: its values
            self.h = (1.0, 0.0, 0.0, 0.0)
        elif self.k == K - 1:
            self.mode = "tangent"         # beyond the last level: the tangent at it
            self.h = (1.0, 0.0, 0.0, 0.0)
        else:
            self.mode = "hermite"         # between levels k and k + 1
            h = float(levels[self.k + 1]) - s0
            t = self.ds / h
            # Cubic Hermite basis, the tangent ones times the interval (slopes are -Lbar).
            self.h = (2 * t ** 3 - 3 * t ** 2 + 1, (t ** 3 - 2 * t ** 2 + t) * h,
                      -2 * t ** 3 + 3 * t ** 2, (t ** 3 - t ** 2) * h)


def recolour_p(p: np.ndarray, lbar: np.ndarray, level_scale: np.ndarray, domega: np.ndarray,
               levels: np.ndarray, sigmas: Sequence[float]) -> np.ndarray:
    """Normalized p per steradian for each effective absorption in ``sigmas``.

    ``p``, ``lbar``: the table's (n_dir, K, B, n_po) arrays (float16 or float32, C-contiguous);
    ``level_scale``: (n_dir, K), ``p_scale * albedo`` per level (so that ``p * level_scale``
    is the bin mass per steradian; only ratios within a direction matter); ``domega``:
    (n_dir, B) solid angle of each band row; ``levels``: the K absorption levels; ``sigmas``:
    C absorptions in the levels' unit. Returns a (n_dir, B, n_po, C) float32 view of
    channel-major memory; each (direction, channel) integrates to 1 over the band (0 where
    the direction has no light).
    """
    import drjit as dr
    from drjit.llvm import Float, Float16, UInt32

    n_dir, K, B, n_po = p.shape
    lv = np.asarray(levels, dtype=np.float64)
    chans = [_Channel(lv, s) for s in sigmas]
    C = len(chans)
    ftype = Float16 if p.dtype == np.float16 else Float
    scale = np.asarray(level_scale, dtype=np.float64)
    domega = np.asarray(domega, dtype=np.float64)
    per = max(1, _MAX_ELEMENTS // (max(K, C) * B * n_po))
    out = np.empty((C, n_dir, B, n_po), dtype=np.float32) if per < n_dir else None
    for d0 in range(0, n_dir, per):
        d1 = min(n_dir, d0 + per)
        # (The arrays Dr.Jit maps stay referenced here until the results are read back.)
        p_c, l_c = np.ascontiguousarray(p[d0:d1]), np.ascontiguousarray(lbar[d0:d1])
        g = _masses(dr, Float, ftype, UInt32, chans, p_c, l_c, scale[d0:d1], K, B, n_po)
        block = _normalized(dr, Float, UInt32, g, C, domega[d0:d1], B, n_po)
        if per >= n_dir:
            return np.moveaxis(block, 0, -1)     # one launch: the kernel's memory is the result
        out[:, d0:d1] = block
    return np.moveaxis(out, 0, -1)


def _normalized(dr, Float, UInt32, g, C: int, domega: np.ndarray, B: int, n_po: int) -> np.ndarray:
    """(C, n_dir, B, n_po) float32: the channel-major masses per steradian ``g`` (one Dr.Jit
    array of C x n_dir x B x n_po, evaluated) scaled so that every (channel, direction)
    integrates to 1 over the band: row sums on all cores, totals in numpy (small), then one
    kernel that reads ``g`` in order and scales it (a factor per direction and channel)."""
    n = domega.shape[0]
    rows = dr.block_sum(g, n_po).numpy().reshape(C, n, B).astype(np.float64)
    tot = np.einsum("cdb,db->cd", rows, domega)
    inv = np.where(tot > 0.0, 1.0 / np.where(tot > 0.0, tot, 1.0), 0.0).astype(np.float32)
    lane = dr.arange(UInt32, C * n * B * n_po)
    res = g * dr.gather(Float, Float(inv.reshape(-1)), lane // (B * n_po))
    return res.numpy().reshape(C, n, B, n_po)


def recolour_basis(basis: np.ndarray, coef: np.ndarray, domega: np.ndarray) -> np.ndarray:
    """Normalized p per steradian of a compressed table (:mod:`usdfiber.bake.compression`).

    ``basis``: (n_dir, R, B, n_po) float16 or float32; ``coef``: (n_dir, C, R) the basis
    coefficients of each channel's absorption; ``domega``: (n_dir, B). Each bin reads its R
    basis values once for all channels: ``p = max(0, sum_j c_j b_j)``, then each (direction,
    channel) is normalized. Returns a (n_dir, B, n_po, C) float32 view of channel-major memory
    (the arithmetic of :func:`~usdfiber.bake.compression.reconstruct_p`).
    """
    import drjit as dr
    from drjit.llvm import Float, Float16, UInt32

    n_dir, R, B, n_po = basis.shape
    C = coef.shape[1]
    ftype = Float16 if basis.dtype == np.float16 else Float
    domega = np.asarray(domega, dtype=np.float64)
    BP = B * n_po
    per = max(1, _MAX_ELEMENTS // (max(R, C) * BP))
    out = np.empty((C, n_dir, B, n_po), dtype=np.float32) if per < n_dir else None
    for d0 in range(0, n_dir, per):
        d1 = min(n_dir, d0 + per)
        n = d1 - d0
        b_c = np.ascontiguousarray(basis[d0:d1])
        b_d = ftype(b_c.reshape(-1))                 # mapped, not copied
        cf = Float(np.ascontiguousarray(coef[d0:d1], dtype=np.float32).reshape(-1))
        lane = dr.arange(UInt32, n * BP)
        d = lane // BP
        base = lane + d * ((R - 1) * BP)             # component 0 of bin j of direction d
        comps = [Float(dr.gather(ftype, b_d, base + j * BP)) for j in range(R)]
        # Each bin's R basis values are read once; the channels are written channel-major
        # into one array, so that the row sums and the scaling read it in order.
        # (Permute: every element is written once, so the scatters share one kernel.)
        g = dr.empty(Float, C * n * BP)
        for c in range(C):
            m = Float(0.0)
            for j in range(R):
                m = dr.fma(dr.gather(Float, cf, d * (C * R) + (c * R + j)), comps[j], m)
            dr.scatter(g, dr.maximum(m, 0.0), lane + dr.opaque(UInt32, c * n * BP), mode=dr.ReduceMode.Permute)
        dr.eval(g)
        block = _normalized(dr, Float, UInt32, g, C, domega[d0:d1], B, n_po)
        if per >= n_dir:
            return np.moveaxis(block, 0, -1)
        out[:, d0:d1] = block
    return np.moveaxis(out, 0, -1)


def _masses(dr, Float, ftype, UInt32, chans: list[_Channel], p: np.ndarray, lbar: np.ndarray,
            scale: np.ndarray, K: int, B: int, n_po: int):
    """Each bin's mass per steradian, up to a factor per (direction, channel), for every channel:
    one Dr.Jit array of C x n_dir x B x n_po (channel-major), evaluated in one kernel over the
    bins. A lane reads each level it needs once, whichever channels need it, and writes its
    channels to their places (every element once)."""
    n_dir = p.shape[0]
    BP = B * n_po
    N = n_dir * BP
    p_d = ftype(p.reshape(-1))            # mapped, not copied
    l_d = ftype(lbar.reshape(-1))
    lane = dr.arange(UInt32, N)           # lanes (d, j): direction d, bin j of its band
    d = lane // BP                        # a literal divisor compiles to a multiplication
    base = lane + d * ((K - 1) * BP)      # level 0 of bin j of direction d

    loaded: dict[int, tuple] = {}

    def load(k: int) -> tuple:
        # The level's offset is a kernel parameter (opaque): a new colour reuses the kernel.
        if k not in loaded:
            i = base + dr.opaque(UInt32, k * BP)
            loaded[k] = Float(dr.gather(ftype, p_d, i)), Float(dr.gather(ftype, l_d, i))
        return loaded[k]

    def per_direction(x: np.ndarray) -> object:
        return dr.gather(Float, Float(np.ascontiguousarray(x, dtype=np.float32)), d)

    g = dr.empty(Float, len(chans) * N)
    l_min = None
    for c, ch in enumerate(chans):
        s0 = scale[:, ch.k]
        # A factor common to a direction cancels in the normalization, so masses are taken
        # relative to level k's (p itself at level k): they stay near the stored values, also
        # where Lambda is tiny. A direction without light at level k takes level k + 1's.
        p0, l0 = load(ch.k)
        if not np.all(s0 > 0.0):
            p0 = p0 * per_direction(s0 > 0.0)
        if ch.mode == "level":
            m = dr.select(p0 > 0.0, p0, 0.0)
        elif ch.mode == "tangent":
            # The tangent falls as exp(-Lbar ds) without bound: measured from the direction's
            # smallest Lbar (among bins with light), float32 underflows only where a value is
            # negligible next to the direction's largest.
            if l_min is None:            # the same last level for every such channel
                pn = p[:, ch.k].reshape(n_dir, BP)
                ln = np.where(pn > 0, lbar[:, ch.k].reshape(n_dir, BP), np.inf).min(axis=1)
                l_min = per_direction(np.where(np.isfinite(ln), ln, 0.0))
            ds = dr.opaque(Float, ch.ds)
            m = dr.select(p0 > 0.0, p0 * dr.exp(-(l0 - l_min) * ds), 0.0)
        else:
            s1 = scale[:, ch.k + 1]
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = np.where(s0 > 0.0, s1 / np.where(s0 > 0.0, s0, 1.0), (s1 > 0.0) * 1.0)
            p1, l1 = load(ch.k + 1)
            p1 = p1 * per_direction(ratio)
            pos0, pos1 = p0 > 0.0, p1 > 0.0
            h00, h10, h01, h11 = (dr.opaque(Float, x) for x in ch.h)
            # Cubic Hermite in log F, written relative to level k: y - y0 = h01 (y1 - y0)
            # - h10 Lbar0 - h11 Lbar1 (h00 + h01 = 1), clipped to [y1 - y0, 0] as
            # hermite_log_interp clips y to [y1, y0]; one log and one exp per bin.
            r = dr.log(dr.select(pos0 & pos1, p1 / p0, 1.0))
            e = dr.minimum(dr.maximum(h01 * r - h10 * l0 - h11 * l1, r), 0.0)
            e = dr.select(pos1, e, -l0 * dr.opaque(Float, ch.ds))      # empty at k + 1: tangent
            m = dr.select(pos0, p0 * dr.exp(e), dr.select(pos1, p1, 0.0))
        # (Permute: every element is written once, so the channels share one kernel.)
        dr.scatter(g, m, lane + dr.opaque(UInt32, c * N), mode=dr.ReduceMode.Permute)
    dr.eval(g)
    return g
