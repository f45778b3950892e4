"""Assembling a table from the baker's per-direction histograms.

For every incoming direction the baker hands over (:mod:`usdfiber.bake.statistics`) the
sums ``H_k`` of ``exp(-s_k L)`` and ``G_k`` of ``L exp(-s_k L)`` over each outgoing bin's
photons at every absorption level, and the photons that met the fiber. :func:`assemble`
turns them into the stored arrays of :mod:`usdfiber.bake.storage`: per direction the albedo
``Lambda_k = sum H_k / norm`` and its slope ``sum G_k / sum H_k``; the theta_o band holding
all but ``band_tail`` of the mass (:func:`band_rows`), one band height for the table; ``p``
per steradian at each level scaled by its maximum and rounded to the storage type (the
rounding error is measured and recorded); ``Lbar_k = G_k / H_k`` per bin.
"""
from __future__ import annotations

from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from usdfiber.bake.grid import Grid
from usdfiber.bake.storage import STORAGE_DTYPES, layout_header
from usdfiber.bake.table import BcsdfTable

__all__ = ["assemble", "band_rows"]


def band_rows(row_mass: np.ndarray, tail: float) -> tuple[int, int]:
    """Smallest [lo, hi) of rows keeping all but ``tail`` of ``row_mass`` (sums to ~1)."""
    n = len(row_mass)
    total = float(row_mass.sum())
    if total <= 0.0:
        return 0, 1
    c = np.cumsum(row_mass) / total
    half = 0.5 * float(tail)
    lo = int(np.searchsorted(c, half, side="right"))
    # rows beyond hi carry at most tail/2
    rc = np.cumsum(row_mass[::-1]) / total
    hi = n - int(np.searchsorted(rc, half, side="right"))
    lo = min(lo, n - 1)
    hi = max(hi, lo + 1)
    return lo, hi


def _each_slice(order: Sequence[tuple[int, int]], load_slice: Callable[[int, int], Mapping[str, Any]],
                work: Callable[[int, int, Mapping[str, Any]], None], threads: int) -> None:
    """``work(ti, pi, load_slice(ti, pi))`` for every direction of ``order``: the slices read
    here in order, the work on ``threads`` threads, at most two slices per thread waiting."""
    if threads <= 1:
        for ti, pi in order:
            work(ti, pi, load_slice(ti, pi))
        return
    with ThreadPoolExecutor(max_workers=threads, thread_name_prefix="usdfiber-assembly") as pool:
        waiting: deque[Future] = deque()
        for ti, pi in order:
            waiting.append(pool.submit(work, ti, pi, load_slice(ti, pi)))
            while len(waiting) > 2 * threads:
                waiting.popleft().result()
        while waiting:
            waiting.popleft().result()


def assemble(grid: Grid, levels: Sequence[float], n_slices: tuple[int, int],
             load_slice: Callable[[int, int], Mapping[str, Any]], width: np.ndarray,
             header: Mapping[str, Any], *, band_tail: float = 1e-5,
             storage: str = "float16", threads: int = 1) -> BcsdfTable:
    """Build a table from per-direction histograms (the baker's chunks).

    ``load_slice(ti, pi)`` returns a mapping with ``rows`` (r0, r1): the theta_o rows held;
    ``H`` (K, r1 - r0, n_po): sum of exp(-s_k L) over each bin's photons; ``G``: sum of
    L exp(-s_k L); ``norm``: the photons meeting the fiber (divisor); ``rel_error``;
    ``photons``. Two passes: the bands, then the arrays. ``load_slice`` is called in this
    thread, in the directions' order; ``threads`` > 1 does each direction's arithmetic on that
    many threads (numpy releases the GIL), the same arrays bit for bit.
    """
    if storage not in STORAGE_DTYPES:
        raise ValueError("storage must be 'float16' or 'float32'")
    lv = np.asarray(levels, dtype=np.float64)
    K = len(lv)
    n_ti, n_pi = n_slices
    n_r, n_c = grid.n_theta_o, grid.n_phi_o
    dom = grid.solid_angles()

    order = [(ti, pi) for ti in range(n_ti) for pi in range(n_pi)]
    bands = np.zeros((n_ti, n_pi, 2), dtype=np.int64)

    def band_of(ti: int, pi: int, sl: Mapping[str, Any]) -> None:
        r0, r1 = sl["rows"]
        H = np.asarray(sl["H"], dtype=np.float64)
        mass = np.zeros(n_r)
        rm = H.sum(axis=-1)                      # (K, rows): each level's mass by row
        t = rm.sum(axis=-1)
        lit = t > 0
        if lit.any():
            mass[r0:r1] = (rm[lit] / t[lit, None]).max(axis=0)
        bands[ti, pi] = band_rows(mass, band_tail)

    _each_slice(order, load_slice, band_of, threads)
    n_band = int(max(1, (bands[..., 1] - bands[..., 0]).max()))
    start = np.clip(bands[..., 0] - (n_band - (bands[..., 1] - bands[..., 0])) // 2, 0, n_r - n_band)

    dt = STORAGE_DTYPES[storage]
    p_arr = np.zeros((n_ti, n_pi, K, n_band, n_c), dtype=dt)
    l_arr = np.zeros((n_ti, n_pi, K, n_band, n_c), dtype=dt)
    p_scale = np.zeros((n_ti, n_pi, K), dtype=np.float32)
    albedo = np.zeros((n_ti, n_pi, K), dtype=np.float32)
    albedo_l = np.zeros((n_ti, n_pi, K), dtype=np.float32)
    rel_error = np.zeros((n_ti, n_pi), dtype=np.float32)
    photons = np.zeros((n_ti, n_pi), dtype=np.int64)
    # Each direction's share of the quantization sums and of the dropped mass, summed in the
    # directions' order afterwards: the same floats whichever thread assembled it.
    q_parts = np.zeros((n_ti, n_pi, 2, K))
    dropped_parts = np.zeros((n_ti, n_pi))

    def arrays_of(ti: int, pi: int, sl: Mapping[str, Any]) -> None:
        r0, r1 = sl["rows"]
        norm = float(sl["norm"])
        Hf = np.zeros((K, n_r, n_c))
        Gf = np.zeros((K, n_r, n_c))
        Hf[:, r0:r1] = np.asarray(sl["H"], dtype=np.float64)
        Gf[:, r0:r1] = np.asarray(sl["G"], dtype=np.float64)
        b0 = int(start[ti, pi])
        band = slice(b0, b0 + n_band)
        # Every level at once (the same arithmetic level by level: one call for K levels).
        tot_h = Hf.sum(axis=(1, 2))
        albedo[ti, pi] = tot_h / norm if norm > 0 else 0.0
        with np.errstate(invalid="ignore", divide="ignore"):
            albedo_l[ti, pi] = np.where(tot_h > 0, Gf.sum(axis=(1, 2)) / np.where(tot_h > 0, tot_h, 1.0), 0.0)
        fb = Hf[:, band].sum(axis=(1, 2))
        if tot_h[0] > 0:
            dropped_parts[ti, pi] = 1.0 - fb[0] / tot_h[0]
        lit = np.flatnonzero(fb > 0)             # levels with light in the band
        if lit.size:
            Fb = Hf[lit, band]
            w = dom[band, None]
            p = Fb / fb[lit, None, None] / w
            m = p.max(axis=(1, 2))
            p_scale[ti, pi, lit] = m
            q = (p / m[:, None, None]).astype(dt)
            p_arr[ti, pi, lit] = q
            with np.errstate(invalid="ignore", divide="ignore"):
                lb = np.where(Fb > 0, Gf[lit, band] / np.where(Fb > 0, Fb, 1.0), 0.0)
            l_arr[ti, pi, lit] = lb.astype(dt)
            # quantization error of the stored p (relative L2 over the sphere)
            err = q.astype(np.float64) * m[:, None, None] - p
            q_parts[ti, pi, 0, lit] = (w * err ** 2).sum(axis=(1, 2))
            q_parts[ti, pi, 1, lit] = (w * p ** 2).sum(axis=(1, 2))
        rel_error[ti, pi] = float(sl["rel_error"])
        photons[ti, pi] = int(sl["photons"])

    _each_slice(order, load_slice, arrays_of, threads)
    q_num = np.zeros(K)
    q_den = np.zeros(K)
    dropped = 0.0
    for ti, pi in order:
        q_num += q_parts[ti, pi, 0]
        q_den += q_parts[ti, pi, 1]
        dropped = max(dropped, float(dropped_parts[ti, pi]))

    hdr = dict(header)
    hdr["layout"] = layout_header()
    hdr["resolution"] = grid.to_header()
    hdr["levels"] = [float(x) for x in lv]
    hdr["band"] = {"rows": n_band, "tail": float(band_tail), "max_dropped_mass": float(dropped)}
    hdr["storage"] = storage
    with np.errstate(invalid="ignore", divide="ignore"):
        qe = np.sqrt(np.where(q_den > 0, q_num / np.where(q_den > 0, q_den, 1.0), 0.0))
    hdr["quantization_error"] = {"metric": "relative L2 of stored p vs float64, per level",
                                 "per_level": [float(x) for x in qe]}
    arrays = {
        "p": p_arr, "p_scale": p_scale, "lbar": l_arr,
        "band_start": start.astype(np.int16), "albedo": albedo, "albedo_lbar": albedo_l,
        "levels": lv, "width": np.asarray(width, dtype=np.float32), "rel_error": rel_error,
        "photons": photons,
    }
    return BcsdfTable(header=hdr, arrays=arrays)
