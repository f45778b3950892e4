"""The baker's fast paths give exactly what the plain formulation gives, bit for bit.

* :func:`usdfiber.bake.binning.bin_indices` against :meth:`Grid.bin_index` (edges included);
* :func:`usdfiber.bake.binning.level_sums` (what every batch of a bake is binned with)
  against an independent numpy histogram of the same traced exits, ``np.add.at`` of
  ``w exp(-s L)`` per exit in exit order (the same float64 additions in the same order);
* the tracer's tail phases (long phases, normals seen from below the macro surface drawn in
  the loop) against phases that draw those normals between phases: the same photons.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from usdfiber.bake import tracer
from usdfiber.bake.absorption import DEFAULT_LEVELS
from usdfiber.bake.binning import bin_indices, level_sums
from usdfiber.bake.grid import Grid
from usdfiber.bake.profiles import builtin_profiles_um
from usdfiber.bake.statistics import level_histograms

ETA = 1.55


def _edge_directions(grid: Grid) -> np.ndarray:
    """Unit directions on and next to every theta_o and phi_o bin edge, the poles and phi = +-pi."""
    th_edges = grid.theta_o_edges()
    ph_edges = grid.step * np.arange(grid.n_phi_o + 1)
    th = np.concatenate([th_edges, np.nextafter(th_edges, 10.0), np.nextafter(th_edges, -10.0), [0.0]])
    ph = np.concatenate([ph_edges, ph_edges - math.pi, np.nextafter(ph_edges, 10.0), [math.pi, -math.pi]])
    T, P = np.meshgrid(th, ph, indexing="ij")
    d = np.stack([np.cos(T) * np.cos(P), np.cos(T) * np.sin(P), np.sin(T)], axis=-1).reshape(-1, 3)
    extra = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, -0.0, 0.0], [-1.0, 0.0, 0.0], [-1.0, -0.0, 0.0],
                      [-1.0, -1e-30, 0.0], [0.0, -1.0, 0.0], [1.0, 0.0, 1.0000001]])
    return np.concatenate([d, extra])


@pytest.mark.parametrize("deg", [2.0, 6.0, 10.0])
def test_bin_indices_equal_grid_bin_index(deg):
    grid = Grid(deg)
    rng = np.random.default_rng(7)
    d = rng.normal(size=(200_000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    for dirs in (d, d.astype(np.float32), _edge_directions(grid), _edge_directions(grid).astype(np.float32)):
        np.testing.assert_array_equal(bin_indices(grid, dirs), grid.bin_index(dirs))


def test_bin_indices_reject_non_finite_directions():
    with pytest.raises(ValueError, match="not finite"):
        bin_indices(Grid(2.0), np.array([[np.nan, 0.0, 0.0]]))
    with pytest.raises(ValueError, match="not finite"):
        bin_indices(Grid(2.0), np.array([[1.0, 0.0, np.nan]]))


def _reference_sums(r: tracer.TraceResult, grid: Grid, levels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every exit, one at a time in exit order: ``np.add.at`` of w exp(-s L) and of that x L."""
    nb = grid.n_theta_o * grid.n_phi_o
    w0 = r.exit_weights()
    idx = grid.bin_index(r.directions)
    L = r.path_length.astype(np.float64)
    h = np.zeros((len(levels), nb))
    gl = np.zeros((len(levels), nb))
    for k, s in enumerate(levels):
        w = w0 * np.exp(-s * L) if s > 0 else w0
        np.add.at(h[k], idx, w)
        np.add.at(gl[k], idx, w * L)
    return h, gl


@pytest.fixture(scope="module")
def silk_scene() -> tracer.FiberScene:
    return tracer.prepare(builtin_profiles_um("silk", 1)[0])


@pytest.mark.parametrize("beta, split", [(0.0, 0), (6.5, 0), (6.5, 4)])
def test_level_sums_equal_an_exit_by_exit_histogram(silk_scene, beta, split):
    """Unit weights (plain), fractional weights (splitting), and cut photons, which carry none."""
    grid = Grid(2.0)
    levels = np.asarray(DEFAULT_LEVELS) / 10.0
    r = tracer.trace(silk_scene, 0.6, 0.4, 20_000, eta=ETA, beta_deg=beta, max_bounces=3, seed=2, split=split)
    assert r.n_cut > 0                       # max_bounces = 3 cuts some photons
    assert (r.weight is not None) == bool(split)
    ref = _reference_sums(r, grid, levels)
    got = level_sums(r.directions, r.path_length, r.weight, r.cut, grid, levels)
    for a, b in zip(got, ref):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(level_histograms(r, grid, levels), ref):
        np.testing.assert_array_equal(a, b)


def test_tail_phases_trace_the_same_photons(silk_scene, monkeypatch):
    """Drawing normals seen from below in the loop (and phases of _TAIL_STEPS) from the first
    phase on, or never: bit for bit the same exits, at a grazing angle where such normals are
    common (some phases end with lanes waiting for one: checked)."""
    between = []
    vndf = tracer._vndf_below

    def counting(*args, **kw):
        between.append(1)
        return vndf(*args, **kw)

    kw = dict(eta=ETA, beta_deg=15.0, max_bounces=4096, seed=5)
    dirs = [(1.45, 0.3), (1.5, 2.0)]
    monkeypatch.setattr(tracer, "_TAIL_LANES", -1)          # never: drawn between phases only
    monkeypatch.setattr(tracer, "_vndf_below", counting)
    plain = tracer.trace_many(silk_scene, dirs, 6000, **kw)
    assert len(between) > 0
    monkeypatch.setattr(tracer, "_vndf_below", vndf)
    monkeypatch.setattr(tracer, "_TAIL_LANES", 1 << 30)     # always: in the loop
    tail = tracer.trace_many(silk_scene, dirs, 6000, **kw)
    for a, b in zip(plain, tail):
        assert a.n_hit == b.n_hit and a.extra == b.extra
        np.testing.assert_array_equal(a.directions, b.directions)
        np.testing.assert_array_equal(a.path_length, b.path_length)
        np.testing.assert_array_equal(a.cut, b.cut)
        np.testing.assert_array_equal(a.bounces, b.bounces)


def _assert_same_sums(a: np.ndarray, b: np.ndarray) -> None:
    """The in-kernel histograms of the same deposits: float32 sums added in another order agree
    to a few ulps (one photon more or less in a bin would change it by 1e-4 and more)."""
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6 * a.max())


def test_tail_phases_give_the_same_expected_values(silk_scene, monkeypatch):
    """With the expected-value estimator too: the same exits and the same in-kernel histograms
    (up to the order of the kernels' float32 additions) whether the tail phases start at once or never."""
    hb = tracer.ExitHistogram.for_grid(Grid(6.0), [0.0, 0.05])
    kw = dict(eta=ETA, beta_deg=15.0, max_bounces=4096, seed=7, expected=4, histogram=hb)
    dirs = [(1.45, 0.3), (0.6, 2.0)]
    monkeypatch.setattr(tracer, "_TAIL_LANES", -1)
    never = tracer.trace_many(silk_scene, dirs, 4000, **kw)
    monkeypatch.setattr(tracer, "_TAIL_LANES", 1 << 30)
    always = tracer.trace_many(silk_scene, dirs, 4000, **kw)
    for a, b in zip(never, always):
        assert a.n_hit == b.n_hit and a.histogram.sum() > 0
        np.testing.assert_array_equal(a.directions, b.directions)
        np.testing.assert_array_equal(a.exit_weights(), b.exit_weights())
        _assert_same_sums(a.histogram, b.histogram)


def test_expected_values_do_not_depend_on_the_launches(silk_scene):
    """A direction whose photons several launches share (its histograms summed over them) gets
    the exits and in-kernel histograms of one launch (up to the order of the kernels' float32
    additions)."""
    hb = tracer.ExitHistogram.for_grid(Grid(6.0), [0.0, 0.05])
    kw = dict(eta=ETA, beta_deg=15.0, max_bounces=4096, seed=[3, 4, 5], expected=4, histogram=hb)
    dirs = [(1.2, 0.3), (0.6, 2.0), (0.1, 4.0)]
    one = tracer.trace_many(silk_scene, dirs, 4000, batch=1 << 21, **kw)
    split = tracer.trace_many(silk_scene, dirs, 4000, batch=3000, **kw)    # launches cut inside directions
    for a, b in zip(one, split):
        assert a.n_hit == b.n_hit and a.histogram.sum() > 0 and a.histogram.shape == (2, 2, hb.n_bins)
        np.testing.assert_array_equal(a.directions, b.directions)
        _assert_same_sums(a.histogram, b.histogram)
