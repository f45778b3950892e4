"""The assembly of a table from per-direction histograms: its threads change nothing."""
from __future__ import annotations

import numpy as np
import pytest

from usdfiber.bake.assembly import assemble
from usdfiber.bake.grid import Grid


def _slices(grid: Grid, K: int, seed: int) -> dict[tuple[int, int], dict]:
    """Random histograms with the cases the arithmetic branches on: levels without light,
    a direction without photons, partial theta_o rows."""
    rng = np.random.default_rng(seed)
    out = {}
    for ti in range(grid.n_theta_i):
        for pi in range(grid.n_phi_i):
            r0 = int(rng.integers(0, grid.n_theta_o // 2))
            r1 = int(rng.integers(r0 + 1, grid.n_theta_o + 1))
            H = rng.random((K, r1 - r0, grid.n_phi_o)) ** 8
            H[rng.random(K) < 0.2] = 0.0                    # dark levels
            G = H * rng.random(H.shape) * 3.0
            norm = 0.0 if (ti, pi) == (1, 2) else float(rng.integers(1, 10_000))
            out[(ti, pi)] = {"rows": (r0, r1), "H": H.astype(np.float32), "G": G.astype(np.float32), "norm": norm,
                             "rel_error": float(rng.random()), "photons": int(rng.integers(1, 1 << 20))}
    return out


@pytest.mark.parametrize("threads", [2, 3])
def test_threads_give_the_same_table_bit_for_bit(threads):
    grid = Grid(15.0)
    K = 5
    data = _slices(grid, K, seed=threads)
    calls = []

    def load(ti, pi):
        calls.append((ti, pi))
        return data[(ti, pi)]

    args = (grid, np.linspace(0.0, 2.0, K), (grid.n_theta_i, grid.n_phi_i), load, np.ones(8), {"x": 1})
    one = assemble(*args, band_tail=0.3)
    order_one, calls[:] = list(calls), []
    many = assemble(*args, band_tail=0.3, threads=threads)
    assert calls == order_one       # read in the caller's thread, in the same order
    assert one.header == many.header
    assert set(one.arrays) == set(many.arrays)
    for name, a in one.arrays.items():
        b = many.arrays[name]
        assert a.dtype == b.dtype and a.shape == b.shape
        assert np.array_equal(a.view(np.uint8), b.view(np.uint8)), name
    assert one.header["quantization_error"]["per_level"][0] > 0.0      # the sums were exercised
    assert 0.0 < one.header["band"]["max_dropped_mass"] < 1.0


def test_a_failure_on_a_thread_reaches_the_caller():
    grid = Grid(30.0)
    data = _slices(grid, 2, seed=0)
    data[(2, 3)]["H"] = data[(2, 3)]["H"][:, :, :-1]                     # a broken slice
    with pytest.raises(ValueError):
        assemble(grid, (0.0, 1.0), (grid.n_theta_i, grid.n_phi_i), lambda ti, pi: data[(ti, pi)], np.ones(8), {},
                 threads=2)
