"""Wedges of exit directions that leave a concave pocket for good (:mod:`usdfiber.bake.pockets`).

The tracer skips the escape ray of an expected-value exit whose direction lies in its edge's
wedge, so a wedge must never hold a direction whose ray meets the outline: checked against an
exact float64 ray-polygon intersection from points spread over the region the tracer's exit
points lie in, on the presets' outlines and on deep, curled and noisy ones. The expected
value's histograms must then be the same with and without the wedges.
"""
from __future__ import annotations

import numpy as np
import pytest

from usdfiber.bake import profiles, tracer
from usdfiber.bake.fiber_mesh import hull_edges
from usdfiber.bake.grid import Grid
from usdfiber.bake.pockets import escape_wedges, in_wedge
from usdfiber.bake.requests import requests_from_preset
from usdfiber.bake.tracer import ExitHistogram, trace_many

from estimator_scenes import scene, star_profile


def _horseshoe(n: int = 120, opening_deg: float = 80.0) -> np.ndarray:
    """An annular sector open towards +x: its pocket curls around the points of its inner arc."""
    a0 = np.radians(opening_deg / 2)
    t = np.linspace(a0, 2 * np.pi - a0, n)
    outer = np.stack([np.cos(t), np.sin(t)], 1)
    inner = 0.55 * np.stack([np.cos(t[::-1]), np.sin(t[::-1])], 1)
    return np.concatenate([outer, inner])


def _l_slot(per_edge: int = 20) -> np.ndarray:
    """A square with an L-shaped slot cut from its top: the slot's far end sees no way out.
    Returns the outline and the index of the first vertex of the far end's wall."""
    corners = np.array([(0, 0), (3, 0), (3, 3), (1.5, 3), (1.5, 1.5), (2.5, 1.5), (2.5, 1.0), (1.0, 1.0),
                        (1.0, 3), (0, 3)], dtype=np.float64)
    s = np.arange(per_edge)[:, None] / per_edge
    return np.concatenate([a + s * (b - a) for a, b in zip(corners, np.roll(corners, -1, axis=0))])


def _noisy_blob(seed: int, n: int = 400) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts, _ = profiles.fourier_loop(n, cos=rng.normal(0, 0.06, 9), sin=rng.normal(0, 0.06, 9))
    return pts


def _preset_loop(name: str) -> np.ndarray:
    return np.asarray(requests_from_preset(name)[0].profile().loops[0], dtype=np.float64)


LOOPS = {
    "silk": lambda: _preset_loop("silk"),
    "cotton": lambda: _preset_loop("cotton"),
    "star": lambda: np.asarray(star_profile().loops[0], dtype=np.float64),
    "horseshoe": _horseshoe,
    "l_slot": _l_slot,
    "blob": lambda: _noisy_blob(3),
}


def _first_hits(loop: np.ndarray, p: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Whether each ray p + s d (s > 0) meets a segment of the closed ``loop`` (float64)."""
    q0, q1 = loop, np.roll(loop, -1, axis=0)
    e = q1 - q0                                             # (M, 2)
    rel = q0[None] - p[:, None]                             # (N, M, 2)
    den = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (rel[..., 0] * e[None, :, 1] - rel[..., 1] * e[None, :, 0]) / den
        u = (rel[..., 0] * d[:, None, 1] - rel[..., 1] * d[:, None, 0]) / den
    return np.any((den != 0) & (s > 0) & (u >= 0) & (u <= 1), axis=1)


@pytest.mark.parametrize("name", sorted(LOOPS))
def test_wedge_directions_never_meet_the_outline(name):
    """From points anywhere in each off-hull edge's region of exit points (along the edge,
    between the two offsets; its corners among them), 400 directions over the outward
    half-plane, including directions at the wedge's borders; every one the wedge lets through
    misses the outline."""
    loop = LOOPS[name]()
    hull = hull_edges(loop)
    eps = 2.0**-16
    lo, hi = 0.5 * eps, 2.0 * eps
    w = escape_wedges(loop, hull, offset=(lo, hi))
    rng = np.random.default_rng(7)
    m = len(loop)
    checked = 0
    for i in np.flatnonzero(~hull):
        a, b = loop[i], loop[(i + 1) % m]
        length = float(np.hypot(*(b - a)))
        t = (b - a) / length
        n = np.array([t[1], -t[0]])
        k = 400
        x = rng.uniform(0.0, length, k)
        x[:4] = [0.0, 0.0, length, length]
        y = rng.uniform(lo, hi, k)
        y[:4] = [lo, hi, lo, hi]
        p = a + x[:, None] * t + y[:, None] * n
        ang = rng.uniform(0.0, np.pi, k)
        if np.any(w[i]):
            # Directions just inside the wedge's two borders.
            for j, (vx, vy) in enumerate((w[i, :2], w[i, 2:])):
                border = np.arctan2(np.dot((vx, vy), n), np.dot((vx, vy), -t)) % (2 * np.pi)
                ang[4 + 8 * j:12 + 8 * j] = np.clip(border + (1e-9 if j == 0 else -1e-9), 0, np.pi)
        d = np.cos(ang)[:, None] * -t + np.sin(ang)[:, None] * n
        clear = in_wedge(np.broadcast_to(w[i], (k, 4)), d)
        hits = _first_hits(loop, p[clear], d[clear])
        assert not hits.any(), (name, i, np.flatnonzero(clear)[hits][:5])
        checked += int(clear.sum())
    assert checked > 0 or hull.all()


def test_wedges_cover_most_directions_of_shallow_pockets_and_none_where_the_pocket_closes():
    """Silk's and cotton's pockets are shallow: at least 90 % of the outward directions of every
    off-hull edge skip the ray (the speed the wedges are for). From the far end of an L-shaped
    slot no straight ray gets out: no wedge there; near the slot's mouth, wedges."""
    for name in ("silk", "cotton"):
        loop = LOOPS[name]()
        hull = hull_edges(loop)
        w = escape_wedges(loop, hull, offset=(2.0**-17, 2.0**-15))
        assert not np.any(w[hull])
        ang = np.linspace(0.001, np.pi - 0.001, 2000)
        for i in np.flatnonzero(~hull):
            a, b = loop[i], loop[(i + 1) % len(loop)]
            t = (b - a) / np.hypot(*(b - a))
            n = np.array([t[1], -t[0]])
            d = np.cos(ang)[:, None] * -t + np.sin(ang)[:, None] * n
            assert in_wedge(np.broadcast_to(w[i], (len(ang), 4)), d).mean() > 0.9, (name, i)
    loop = _l_slot()
    hull = hull_edges(loop)
    w = escape_wedges(loop, hull, offset=(2.0**-17, 2.0**-15))
    far_wall = np.arange(5 * 20, 6 * 20)       # (2.5, 1.5) to (2.5, 1.0)
    mouth = np.r_[3 * 20:3 * 20 + 5, 8 * 20 - 5:8 * 20]   # the slot's walls just below its mouth
    assert not hull[far_wall].any() and not np.any(w[far_wall])
    assert np.all(np.any(w[mouth] != 0, axis=1))


@pytest.mark.parametrize("name,theta,phi,beta", [("star", 0.4, 1.1, 8.0), ("silk", 1.2, 0.4, 6.5),
                                                 ("cotton", 0.2, 2.5, 14.0)])
def test_expected_histograms_are_the_same_without_the_wedges(monkeypatch, name, theta, phi, beta):
    """The wedges only skip rays that would miss: the expected value's histograms (weight and
    weight x path length) and every photon's own result are those traced with an escape ray for
    every exit off the hull."""
    fs = scene(name, None if name == "star" else 10.0)
    assert fs.wedge is not None
    hist = ExitHistogram.for_grid(Grid(6.0), [0.0, 0.05])

    def run():
        return trace_many(fs, [(theta, phi)], 1 << 13, eta=1.55, beta_deg=beta, seed=[11], expected=8,
                          histogram=hist)[0]

    with_wedges = run()
    monkeypatch.setattr(tracer, "_POCKET_WEDGES", False)
    without = run()
    assert with_wedges.n_hit == without.n_hit > 0
    assert np.any(with_wedges.histogram > 0)
    for key in ("directions", "path_length", "cut", "bounces", "weight"):
        np.testing.assert_array_equal(getattr(with_wedges, key), getattr(without, key), err_msg=key)
    # float32 sums in another order agree to a few ulps; one deposit more or less in a bin
    # changes it by 1e-4 of the largest bin and more.
    h = without.histogram
    np.testing.assert_allclose(with_wedges.histogram, h, rtol=1e-5, atol=1e-6 * float(np.abs(h).max()))


def test_convex_and_cuticle_fibers_have_no_wedges():
    """A convex outline needs no escape ray at all, and scales are not extruded; a concave
    extruded outline has wedges."""
    assert scene("circle").wedge is None
    assert tracer.prepare(profiles.circle(64)).wedge is None
    assert tracer.prepare(star_profile(), cuticle=(3.0, 0.05, 1.0)).wedge is None
    assert tracer.prepare(star_profile()).wedge is not None
