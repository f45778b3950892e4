"""Recolouring a table's p in fused, multi-threaded Dr.Jit (LLVM) kernels.

:meth:`~usdfiber.bake.table.BcsdfTable.recolour` needs, for every bin of every incoming
direction, the bin mass ``F(s)`` interpolated between the two absorption levels around ``s``
(cubic Hermite in ``log F``, :func:`usdfiber.bake.absorption.hermite_log_interp`), then
``p = F / sum(F) / domega``. On a 2 degree table that is 10^8 bins per channel. In numpy
(float64, one core, a temporary array per operation) it takes about 18 s per channel; here
it takes one kernel on all cores and two short passes, in float32, reading the float16 levels
straight from the table's own arrays (Dr.Jit maps them without a copy):

1. one kernel over the bins: a lane takes G = 4 consecutive bins of a direction (2 or 1 where
   a direction's bins do not divide by 4) and reads each level its channels need once, as one
   short vector (a packet gather: x86 has no gather instruction for 16-bit values, and
   reading them one by one cost more than all the arithmetic); the levels' offsets and the
   Hermite weights are kernel parameters, so a new colour reuses the kernel. It computes every
   channel with one ``log`` and one ``exp`` per bin and writes the masses channel-major into
   the result's memory (C x n_dir x B x n_po, each element once);
2. the row sums of that memory (one block reduction), totalled per (channel, direction) in
   numpy (small);
3. the scaling by 1 / total per (channel, direction), in place (numpy, one multiplication per
   value).

The result's memory comes from Dr.Jit's allocator, which keeps freed memory for reuse: the
next recolouring of a table of that size writes into pages already mapped (a first write to
fresh pages costs about as much as the whole computation on a VM). The result is that memory
viewed as ``(..., B, n_po, C)`` without a copy (:class:`~usdfiber.bake.table.Recoloured`). A
compressed table (:func:`recolour_basis`) takes the same passes 2 and 3 after one kernel over
its bins that reads each bin's basis values once (and each direction's coefficients as
packets of 8) and writes every channel's ``max(0, sum_j c_j b_j)``.

Computing the masses twice (once for the sums, once scaled, so that the result is written
once) costs more: the kernel is bound by its arithmetic and reads, not by the memory it writes.

The arithmetic is that of :func:`~usdfiber.bake.absorption.hermite_log_interp` in float32
(checked against it in ``tests/bake/test_recolour.py``); the float64 numpy path stays as the
reference and the fallback where Dr.Jit has no LLVM backend.
"""
from __future__ import annotations

import functools
from typing import Any, Sequence

import numpy as np

from usdfiber.bake.absorption import level_bracket

__all__ = ["available", "recolour_basis", "recolour_p"]

#: Elements of the level arrays (or of the output) per launch: indices stay 32-bit.
_MAX_ELEMENTS = 1 << 31
#: Elements of the largest result written as one Dr.Jit array (its length is 32-bit); a larger
#: one is normalized launch by launch and copied into place.
_MAX_OUTPUT = 1 << 32


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

    n_dir, K, B, n_po = p.shape
    lv = np.asarray(levels, dtype=np.float64)
    chans = [_Channel(lv, s) for s in sigmas]
    scale = np.asarray(level_scale, dtype=np.float64)
    out = _Output(dr, len(chans), n_dir, B, n_po, domega)
    # (Four bins per lane run about 7% faster than two on a 2 deg table but take about 0.3 s
    # longer to compile: once per combination of channel kinds, cached on disk by Dr.Jit.)
    # Lbar read where p's packets are read: in the same place of a cache line as p (a copy where
    # not). The kernel's packet reads gave wrong values on an AVX-512 Xeon where p started on a
    # 32-byte boundary and Lbar elsewhere; arrays of the same phase read right wherever they start
    # (tests/bake/test_recolour.py places both at every start). A table's arrays, allocated
    # alike, have the same phase: no copy.
    p = np.ascontiguousarray(p)
    lbar = _same_phase(np.ascontiguousarray(lbar), p)
    G = _packet(B * n_po, p, lbar)
    per = max(1, _MAX_ELEMENTS // (max(K, len(chans)) * B * n_po))
    for d0 in range(0, n_dir, per):
        d1 = min(n_dir, d0 + per)
        # (The arrays Dr.Jit maps stay referenced here until the kernel has run.)
        p_c, l_c = np.ascontiguousarray(p[d0:d1]), np.ascontiguousarray(lbar[d0:d1])
        out.write(_masses(dr, chans, p_c, l_c, scale[d0:d1], K, B * n_po, G), d0, d1, G)
    return out.result()


def recolour_basis(basis: np.ndarray, coef: np.ndarray, domega: np.ndarray) -> np.ndarray:
    """Normalized p per steradian of a compressed table (:mod:`usdfiber.bake.compression`).

    ``basis``: (n_dir, R, B, n_po) float16 or float32; ``coef``: (n_dir, C, R) the basis
    coefficients of each channel's absorption; ``domega``: (n_dir, B). Each bin reads its R
    basis values once for all channels: ``p = max(0, sum_j c_j b_j)``, then each (direction,
    channel) is normalized. Returns a (n_dir, B, n_po, C) float32 view of channel-major memory
    (the arithmetic of :func:`~usdfiber.bake.compression.reconstruct_p`).
    """
    import drjit as dr
    from drjit.llvm import Float, UInt32

    n_dir, R, B, n_po = basis.shape
    C = coef.shape[1]
    BP = B * n_po
    out = _Output(dr, C, n_dir, B, n_po, domega)
    G = _packet(BP, basis)
    per = max(1, _MAX_ELEMENTS // (max(R, C) * BP))
    for d0 in range(0, n_dir, per):
        d1 = min(n_dir, d0 + per)
        b_c = np.ascontiguousarray(basis[d0:d1])
        read = _reader(dr, b_c, G)                   # mapped, not copied
        q = dr.arange(UInt32, (d1 - d0) * BP // G)   # lanes: G consecutive bins each
        d = q // (BP // G)
        base = q + d * ((R - 1) * BP // G)           # component 0 of the lane's bins
        comps = [read(base + j * BP // G) for j in range(R)]
        cf = _per_direction(dr, coef[d0:d1].reshape(d1 - d0, C * R), d)
        # Each bin's R basis values are read once for all channels.
        ms = [[_maximum(dr, _dot(dr, cf[c * R:c * R + R], [comps[j][g] for j in range(R)]), 0.0) for g in range(G)]
              for c in range(C)]
        out.write(ms, d0, d1, G)
    return out.result()


def _dot(dr, a: list, b: list):
    m = a[0] * b[0]
    for x, y in zip(a[1:], b[1:]):
        m = dr.fma(x, y, m)
    return m


def _per_direction(dr, x: np.ndarray, d) -> list:
    """The columns of ``x`` (n_dir, m) at each lane's direction ``d``, as m Float32 arrays.

    A lane reads its direction's row as packets of 8 consecutive values (vector loads and a
    transpose): one gather per value costs about 8 loads on x86, as much as the rest of the
    basis kernel."""
    from drjit.llvm import ArrayXf, Float

    n, m = x.shape
    P = -(-m // 8)                            # packets per row
    rows = _aligned_zeros(n * 8 * P, 32).reshape(n, 8 * P)      # packets on 32-byte boundaries
    rows[:, :m] = x
    src = Float(rows.reshape(-1))
    cols: list = []
    for i in range(P):
        v = dr.gather(ArrayXf, src, d * P + i, shape=(8, dr.width(d)))
        cols += [v[j] for j in range(8)]
    return cols[:m]


def _empty_at(shape: tuple[int, ...], dtype: Any, phase: int, line: int) -> np.ndarray:
    """An uninitialized C-contiguous array whose data starts ``phase`` bytes past a boundary of
    ``line`` bytes."""
    dtype = np.dtype(dtype)
    nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    raw = np.empty(nbytes + line, dtype=np.uint8)
    skip = (phase - raw.ctypes.data) % line
    return raw[skip:skip + nbytes].view(dtype).reshape(shape)


def _same_phase(a: np.ndarray, like: np.ndarray, line: int = 64) -> np.ndarray:
    """``a`` (C-contiguous) itself where its data starts at the same offset within a ``line``
    of bytes as ``like``'s, else a copy that does."""
    want = like.ctypes.data % line
    if a.ctypes.data % line == want:
        return a
    out = _empty_at(a.shape, a.dtype, want, line)
    out[...] = a
    return out


def _aligned_zeros(size: int, align: int) -> np.ndarray:
    """A float32 array of zeros whose data starts on an ``align``-byte boundary."""
    out = _empty_at((size,), np.float32, 0, align)
    out[...] = 0.0
    return out


def _packet(BP: int, *arrays: np.ndarray) -> int:
    """Bins per lane: the largest of 4, 2, 1 that divides a direction's ``BP`` bins (and the
    arrays' alignment), so that a lane reads each level as one short vector."""
    for G in (4, 2):
        if BP % G == 0 and all(a.ctypes.data % (G * a.itemsize) == 0 for a in arrays):
            return G
    return 1


def _reader(dr, a: np.ndarray, G: int):
    """``read(i)``: the G consecutive elements of packet ``i`` (UInt32 lanes) of the contiguous
    float16 or float32 array ``a`` (mapped without a copy), as G Float32 arrays.

    A packet is read as one vector per lane (Dr.Jit's packet gathers): x86 has no gather
    instruction for 16-bit values, and its 32-bit gathers cost about as much as a load per
    element; one short vector load per lane and a transpose cost several times less."""
    import drjit.llvm as m

    half = a.dtype == np.float16
    src = (m.Float16 if half else m.Float)(a.reshape(-1))
    if G == 1:
        return lambda i: [m.Float(dr.gather(type(src), src, i))]
    ptype = getattr(m, f"Array{G}f16" if half else f"Array{G}f")

    def read(i):
        v = dr.gather(ptype, src, i)
        return [m.Float(v[g]) for g in range(G)]
    return read


class _Output:
    """The result's channel-major memory (C x n_dir x B x n_po float32), written by the mass
    kernels, then normalized in place.

    It is one Dr.Jit array: Dr.Jit's allocator keeps freed memory for reuse, so a recolouring
    that follows another of its size writes into pages already mapped (a first write to fresh
    pages costs about as much as the whole computation on a VM), and the mass kernels write it
    in place (no second array of the result's size)."""

    def __init__(self, dr, C: int, n_dir: int, B: int, n_po: int, domega: np.ndarray) -> None:
        from drjit.llvm import Float

        self.dr, self.C, self.n_dir, self.B, self.n_po = dr, C, n_dir, B, n_po
        self.domega = np.asarray(domega, dtype=np.float64)
        self.whole = C * n_dir * B * n_po < _MAX_OUTPUT
        self.buf = dr.empty(Float, C * n_dir * B * n_po) if self.whole else None
        self.parts: list[np.ndarray] = []

    def write(self, ms: list[list], d0: int, d1: int, G: int) -> None:
        """Write the masses of directions ``[d0, d1)``: ``ms[c][g]`` is bin ``g`` of each lane's
        G bins of channel c (unevaluated; one kernel evaluates all, the scatters of every
        channel write each element once, ``ReduceMode.Permute``)."""
        import drjit.llvm as m

        dr, BP = self.dr, self.B * self.n_po
        n = d1 - d0
        # Where the launch's directions start in the array: a launch's own array, normalized on
        # its own, where the result is longer than one array.
        n_arr, at = (self.n_dir, d0) if self.whole else (n, 0)
        if not self.whole:
            self.buf = dr.empty(m.Float, self.C * n * BP)
        q = dr.arange(m.UInt32, n * BP // G)
        ptype = m.Float if G == 1 else getattr(m, f"Array{G}f")
        for c, vals in enumerate(ms):
            # The channel's offset is a kernel parameter (opaque): launches share the kernel.
            i = q + dr.opaque(m.UInt32, (c * n_arr + at) * BP // G)
            dr.scatter(self.buf, vals[0] if G == 1 else ptype(*vals), i, mode=dr.ReduceMode.Permute)
        dr.eval(self.buf)
        if not self.whole:
            self.parts.append(self._normalized(self.buf, self.domega[d0:d1]))
            self.buf = None

    def result(self) -> np.ndarray:
        """(n_dir, B, n_po, C) view of the normalized channel-major memory."""
        if self.whole:
            out = self._normalized(self.buf, self.domega)
            self.buf = None
        else:
            out = np.concatenate(self.parts, axis=1)
        return np.moveaxis(out.reshape(self.C, self.n_dir, self.B, self.n_po), 0, -1)

    def _normalized(self, buf, domega: np.ndarray) -> np.ndarray:
        """``buf`` (C x n x B x n_po masses) scaled in place so that every (channel, direction)
        integrates to 1 over the band: row sums on all cores (one block reduction), totals in
        numpy (small), then one multiplication per value, in place, in numpy."""
        C, n, BP = self.C, domega.shape[0], self.B * self.n_po
        rows = self.dr.block_sum(buf, self.n_po).numpy().reshape(C, n, self.B).astype(np.float64)
        tot = np.einsum("cdb,db->cd", rows, domega)
        inv = np.where(tot > 0.0, 1.0 / np.where(tot > 0.0, tot, 1.0), 0.0).astype(np.float32)
        g = buf.numpy().reshape(C, n, BP)     # Dr.Jit's memory (no copy), kept alive by the view
        np.multiply(g, inv[:, :, None], out=g)
        return g


def _maximum(dr, a, b):
    """max(a, b) as a compare and a blend (``dr.maximum`` also orders signed zeros and NaNs,
    at several instructions more on x86; neither matters here)."""
    return dr.select(a > b, a, b)


def _minimum(dr, a, b):
    """min(a, b) as a compare and a blend (see :func:`_maximum`)."""
    return dr.select(a < b, a, b)


def _masses(dr, chans: list[_Channel], p: np.ndarray, lbar: np.ndarray, scale: np.ndarray,
            K: int, BP: int, G: int) -> list[list]:
    """Each bin's mass per steradian, up to a factor per (direction, channel), for every channel
    (unevaluated): ``[c][g]``, bin g of each lane's G consecutive bins. A lane reads each level
    it needs once (one packet of p and of Lbar), whichever channels need it."""
    from drjit.llvm import Float, UInt32

    n_dir = p.shape[0]
    read_p, read_l = _reader(dr, p, G), _reader(dr, lbar, G)      # mapped, not copied
    q = dr.arange(UInt32, n_dir * BP // G)   # lanes (d, j): direction d, bins G j ... G j + G - 1
    d = q // (BP // G)                       # a literal divisor compiles to a multiplication
    base = q + d * ((K - 1) * BP // G)       # level 0 of the lane's bins (in packets)

    loaded: dict[int, tuple] = {}

    def load(k: int) -> tuple:
        # The level's offset is a kernel parameter (opaque): a new colour reuses the kernel.
        if k not in loaded:
            i = base + dr.opaque(UInt32, k * BP // G)
            loaded[k] = read_p(i), read_l(i)
        return loaded[k]

    cols = _direction_values(chans, p, lbar, scale, BP)
    at = dict(zip(cols, _per_direction(dr, np.stack(list(cols.values()), axis=1), d))) if cols else {}
    ms = []
    for c, ch in enumerate(chans):
        # A factor common to a direction cancels in the normalization, so masses are taken
        # relative to level k's (p itself at level k): they stay near the stored values, also
        # where Lambda is tiny. A direction without light at level k takes level k + 1's.
        p0s, l0s = load(ch.k)
        if ("lit", c) in at:
            p0s = [x * at["lit", c] for x in p0s]
        if ch.mode == "level":
            ms.append([dr.select(p0 > 0.0, p0, 0.0) for p0 in p0s])
        elif ch.mode == "tangent":
            ds = dr.opaque(Float, ch.ds)
            l_min = at["l_min"]
            ms.append([dr.select(p0 > 0.0, p0 * dr.exp(-(l0 - l_min) * ds), 0.0) for p0, l0 in zip(p0s, l0s)])
        else:
            p1s, l1s = load(ch.k + 1)
            rd = at["ratio", c]
            h = [dr.opaque(Float, x) for x in ch.h]
            ds = dr.opaque(Float, ch.ds)
            ms.append([_hermite(dr, p0, l0, p1 * rd, l1, h, ds) for p0, l0, p1, l1 in zip(p0s, l0s, p1s, l1s)])
    return ms


def _direction_values(chans: list[_Channel], p: np.ndarray, lbar: np.ndarray, scale: np.ndarray,
                      BP: int) -> dict:
    """What the mass kernel needs per direction (n_dir float64 each), by name: ``("lit", c)``
    where channel c's level k has directions without light, ``("ratio", c)`` level k + 1's
    scale over level k's for a Hermite channel, ``"l_min"`` for the tangent channels."""
    n_dir = p.shape[0]
    cols: dict = {}
    for c, ch in enumerate(chans):
        s0 = scale[:, ch.k]
        if not np.all(s0 > 0.0):
            cols["lit", c] = (s0 > 0.0) * 1.0
        if ch.mode == "tangent" and "l_min" not in cols:
            # The tangent falls as exp(-Lbar ds) without bound: measured from the direction's
            # smallest Lbar (among bins with light), float32 underflows only where a value is
            # negligible next to the direction's largest (the same last level for all).
            pn = p[:, ch.k].reshape(n_dir, BP)
            ln = np.where(pn > 0, lbar[:, ch.k].reshape(n_dir, BP), np.inf).min(axis=1)
            cols["l_min"] = np.where(np.isfinite(ln), ln, 0.0)
        elif ch.mode == "hermite":
            s1 = scale[:, ch.k + 1]
            with np.errstate(divide="ignore", invalid="ignore"):
                cols["ratio", c] = np.where(s0 > 0.0, s1 / np.where(s0 > 0.0, s0, 1.0), (s1 > 0.0) * 1.0)
    return cols


def _hermite(dr, p0, l0, p1, l1, h: list, ds):
    """Cubic Hermite in log F, written relative to level k: y - y0 = h01 (y1 - y0) - h10 Lbar0
    - h11 Lbar1 (h00 + h01 = 1), clipped to [y1 - y0, 0] as hermite_log_interp clips y to
    [y1, y0]; one log and one exp per bin. ``p1`` is level k + 1's p in level k's scale."""
    _, h10, h01, h11 = h
    pos0, pos1 = p0 > 0.0, p1 > 0.0
    r = dr.log(dr.select(pos0 & pos1, p1 / p0, 1.0))
    e = _minimum(dr, _maximum(dr, h01 * r - h10 * l0 - h11 * l1, r), 0.0)
    e = dr.select(pos1, e, -l0 * ds)                # empty at k + 1: the tangent at k
    return dr.select(pos0, p0 * dr.exp(e), dr.select(pos1, p1, 0.0))
