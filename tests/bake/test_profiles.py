"""Fiber cross sections: conventions, measures, the built-in library and user polygons."""
from __future__ import annotations

import numpy as np
import pytest

from usdfiber.bake.profiles import (
    BUILTIN_KINDS,
    TABLE1_DIAMETER_UM,
    Profile,
    ProfileError,
    builtin_profiles,
    builtin_profiles_um,
    circle,
    default_diameter_um,
    ellipse,
    profile_from_polygons,
)


def signed_area(loop: np.ndarray) -> float:
    x, y = loop[:, 0], loop[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def inside(pts: np.ndarray, loop: np.ndarray) -> np.ndarray:
    """Even-odd point-in-polygon, written independently of the module."""
    res = np.zeros(len(pts), dtype=bool)
    x0, y0 = loop[:, 0], loop[:, 1]
    x1, y1 = np.roll(x0, -1), np.roll(y0, -1)
    for (px, py), k in zip(pts, range(len(pts))):
        c = ((y0 > py) != (y1 > py)) & (px < x0 + (py - y0) * (x1 - x0) / np.where(y1 == y0, 1, y1 - y0))
        res[k] = np.count_nonzero(c) % 2 == 1
    return res


def in_material(prof: Profile, pts: np.ndarray) -> np.ndarray:
    m = inside(pts, prof.loops[0])
    for hole in prof.loops[1:]:
        m &= ~inside(pts, hole)
    return m


def check_conventions(prof: Profile) -> None:
    """Outer CCW, holes CW, unit normals pointing out of the material on every loop."""
    assert signed_area(prof.loops[0]) > 0
    for hole in prof.loops[1:]:
        assert signed_area(hole) < 0
    eps = 1e-4 * prof.circumscribed_diameter
    for loop, nrm in zip(prof.loops, prof.normals):
        assert loop.dtype == np.float64 and loop.shape == nrm.shape and loop.shape[1] == 2
        assert not np.allclose(loop[0], loop[-1]), "loops are closed implicitly"
        np.testing.assert_allclose(np.linalg.norm(nrm, axis=1), 1.0, atol=1e-12)
        idx = np.linspace(0, len(loop) - 1, 24).astype(int)
        assert np.all(in_material(prof, loop[idx] - eps * nrm[idx])), "material must be behind the normal"
        assert not np.any(in_material(prof, loop[idx] + eps * nrm[idx])), "normals must point out"
        # Material on the left of travel: the left normal of each edge points into it.
        e = np.roll(loop, -1, axis=0)[idx] - loop[idx]
        left = np.stack([-e[:, 1], e[:, 0]], axis=1)
        mid = 0.5 * (loop[idx] + np.roll(loop, -1, axis=0)[idx])
        left /= np.linalg.norm(left, axis=1, keepdims=True)
        assert np.all(in_material(prof, mid + eps * left))


# ---------------------------------------------------------------------------------------------
# Analytic shapes
# ---------------------------------------------------------------------------------------------

def test_circle_conventions_and_exact_normals():
    c = circle(512, radius=0.5)
    check_conventions(c)
    p, n = c.loops[0], c.normals[0]
    np.testing.assert_allclose(np.linalg.norm(p, axis=1), 0.5, rtol=1e-12)
    np.testing.assert_allclose(n, p / 0.5, atol=1e-12)  # radial, analytic (not facet) normals
    assert c.smooth and len(c.loops) == 1


def test_area_circle_and_ellipse():
    assert circle(512, radius=0.5).area == pytest.approx(np.pi * 0.25, rel=1e-4)
    assert ellipse(2.0, 1.0, 512).area == pytest.approx(2.0 * np.pi, rel=1e-4)
    assert ellipse(3.0, 0.5, 1024).area == pytest.approx(1.5 * np.pi, rel=1e-4)


def test_projected_width_of_ellipse():
    a, b = 2.0, 0.7
    e = ellipse(a, b, 1024)
    phi = np.linspace(0, 2 * np.pi, 97)
    # The shadow of light travelling along (cos phi, sin phi), measured on (-sin phi, cos phi).
    expected = 2.0 * np.sqrt(a * a * np.sin(phi) ** 2 + b * b * np.cos(phi) ** 2)
    np.testing.assert_allclose(e.projected_width(phi), expected, rtol=1e-5)
    assert e.projected_width(0.0) == pytest.approx(2 * b, rel=1e-5)  # light along +x sees the height
    assert np.shape(e.projected_width(np.zeros((3, 4)))) == (3, 4)
    np.testing.assert_allclose(circle(512).projected_width(phi), 1.0, rtol=1e-4)


def test_enclosing_circle_centering_scaling_rotation():
    e = ellipse(2.0, 1.0, 512)
    assert e.circumscribed_diameter == pytest.approx(4.0, rel=1e-9)
    moved = Profile("moved", tuple(l + [3.0, -1.0] for l in e.loops), e.normals)
    np.testing.assert_allclose(moved.circumscribed_center, [3.0, -1.0], atol=1e-9)
    np.testing.assert_allclose(moved.centered().circumscribed_center, [0.0, 0.0], atol=1e-9)
    s = e.scaled_to_diameter(10.0)
    assert s.circumscribed_diameter == pytest.approx(10.0, rel=1e-12)
    assert s.area == pytest.approx(e.area * 6.25, rel=1e-12)
    np.testing.assert_array_equal(s.normals[0], e.normals[0])
    psi = 0.7
    r = e.rotated(psi)
    phi = np.linspace(0, 6, 13)
    np.testing.assert_allclose(r.projected_width(phi + psi), e.projected_width(phi), rtol=1e-12)
    check_conventions(r)


def test_normal_at_interpolates_vertex_normals():
    e = ellipse(2.0, 1.0, 64)
    n = e.normals[0]
    np.testing.assert_allclose(e.normal_at(0, 5, 0.0), n[5], atol=1e-15)
    np.testing.assert_allclose(e.normal_at(0, 5, 1.0), n[6], atol=1e-15)
    np.testing.assert_allclose(e.normal_at(0, 63, 1.0), n[0], atol=1e-15)  # wraps around
    mid = e.normal_at(0, np.arange(64), np.full(64, 0.5))
    np.testing.assert_allclose(np.linalg.norm(mid, axis=1), 1.0, atol=1e-14)
    assert np.all(np.sum(mid * n, axis=1) > 0.9)


# ---------------------------------------------------------------------------------------------
# Built-in library
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("kind", BUILTIN_KINDS)
def test_builtin_variants_valid_deterministic_distinct(kind):
    count = 4
    a = builtin_profiles(kind, count, seed=3)
    b = builtin_profiles(kind, count, seed=3)
    assert len(a) == count
    for p, q in zip(a, b):
        assert p.name == q.name
        for l1, l2 in zip(p.loops, q.loops):
            np.testing.assert_array_equal(l1, l2)
    # The first variants do not depend on how many are asked for.
    for p, q in zip(builtin_profiles(kind, 2, seed=3), a):
        np.testing.assert_array_equal(p.loops[0], q.loops[0])
    # Another seed gives other shapes (polyester is always the same circle).
    other = builtin_profiles(kind, 1, seed=4)[0]
    same_as_other = np.array_equal(other.loops[0], a[0].loops[0])
    assert same_as_other == (kind == "polyester")
    for p in a:
        p.validate()  # simple, non-degenerate, oriented, holes inside
        check_conventions(p)
        assert p.smooth
        assert p.circumscribed_diameter == pytest.approx(1.0, rel=1e-9)
        np.testing.assert_allclose(p.circumscribed_center, 0.0, atol=1e-9)
        assert 0.2 < p.area < np.pi / 4 + 1e-9
        # Smooth normals agree with the polygon they label (no wild analytic normals).
        for loop, nrm in zip(p.loops, p.normals):
            fn = np.roll(loop, -1, axis=0) - loop
            fn = np.stack([fn[:, 1], -fn[:, 0]], axis=1) / np.linalg.norm(fn, axis=1, keepdims=True)
            avg = fn + np.roll(fn, 1, axis=0)
            avg /= np.linalg.norm(avg, axis=1, keepdims=True)
            assert np.degrees(np.arccos(np.clip(np.sum(avg * nrm, axis=1), -1, 1))).max() < 2.0
    if kind != "polyester":
        for i in range(count):
            for j in range(i + 1, count):
                same = len(a[i].loops) == len(a[j].loops) and all(
                    l1.shape == l2.shape and np.allclose(l1, l2, atol=1e-3) for l1, l2 in zip(a[i].loops, a[j].loops))
                assert not same, f"{kind} variants {i} and {j} are identical"
    else:
        for p in a[1:]:
            np.testing.assert_array_equal(p.loops[0], a[0].loops[0])


def test_builtin_shape_features():
    for p in builtin_profiles("cotton", 6):
        assert len(p.loops) == 2, "cotton has a lumen"
        assert -signed_area(p.loops[1]) > 0.01 * signed_area(p.loops[0])
    merc = builtin_profiles("mercerizedCotton", 6)
    assert any(len(p.loops) == 1 for p in merc), "some mercerized lumens are closed"
    for p in merc:
        if len(p.loops) > 1:
            assert -signed_area(p.loops[1]) < 0.1 * signed_area(p.loops[0]), "lumen is small"
    thin = builtin_profiles("cotton", 3)[2]
    assert -signed_area(thin.loops[1]) > 0.25 * signed_area(thin.loops[0]), "thin-walled variant"
    for p in builtin_profiles("wool", 6):
        w = p.projected_width(np.linspace(0, np.pi, 181))
        assert 1.05 < w.max() / w.min() < 1.45, "near-elliptical"
    for p in builtin_profiles("silk", 6):
        w = p.projected_width(np.linspace(0, np.pi, 181))
        assert w.max() / w.min() > 1.25, "flat"
    c = builtin_profiles("polyester", 1)[0]
    w = c.projected_width(np.linspace(0, np.pi, 181))
    np.testing.assert_allclose(w, 1.0, rtol=1e-4)


def test_builtin_scaling_to_table1():
    assert default_diameter_um("cotton") == pytest.approx(18.5)
    assert default_diameter_um("mercerizedCotton") == pytest.approx(18.5)
    assert TABLE1_DIAMETER_UM["wool"] == (24, 40)
    for kind in BUILTIN_KINDS:
        for p in builtin_profiles_um(kind, 2):
            assert p.circumscribed_diameter == pytest.approx(default_diameter_um(kind), rel=1e-9)
    assert builtin_profiles_um("silk", 1, diameter_um=7.0)[0].circumscribed_diameter == pytest.approx(7.0)
    with pytest.raises(ValueError):
        builtin_profiles("nylon", 1)


# ---------------------------------------------------------------------------------------------
# User polygons
# ---------------------------------------------------------------------------------------------

SQUARE = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
HOLE = np.array([[3.0, 3.0], [6.0, 3.0], [6.0, 6.0], [3.0, 6.0]])


def test_user_polygons_are_oriented_and_sorted():
    # Outer given clockwise and after the hole; hole given counter-clockwise; closing vertex repeated.
    cw_outer = np.vstack([SQUARE[::-1], SQUARE[::-1][:1]])
    p = profile_from_polygons([HOLE, cw_outer], name="square")
    assert not p.smooth
    assert len(p.loops) == 2 and len(p.loops[0]) == 4 and len(p.loops[1]) == 4
    assert p.area == pytest.approx(100.0 - 9.0)
    check_conventions(p)
    # Facet normals averaged at the vertices: a corner normal is the diagonal.
    corner = np.argmin(np.linalg.norm(p.loops[0] - [10.0, 10.0], axis=1))
    np.testing.assert_allclose(p.normals[0][corner], [np.sqrt(0.5), np.sqrt(0.5)], atol=1e-12)
    hole_corner = np.argmin(np.linalg.norm(p.loops[1] - [6.0, 6.0], axis=1))
    np.testing.assert_allclose(p.normals[1][hole_corner], [-np.sqrt(0.5), -np.sqrt(0.5)], atol=1e-12)
    np.testing.assert_allclose(p.projected_width([0.0, np.pi / 4]), [10.0, 10.0 * np.sqrt(2)])


def test_user_polygon_smooth_option_uses_spline_normals():
    t = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    pts = np.stack([3.0 * np.cos(t), 3.0 * np.sin(t)], axis=1)[::-1]  # clockwise input
    p = profile_from_polygons([pts], smooth=True)
    assert p.smooth
    radial = p.loops[0] / np.linalg.norm(p.loops[0], axis=1, keepdims=True)
    np.testing.assert_allclose(p.normals[0], radial, atol=1e-5)


@pytest.mark.parametrize(
    "loops, message",
    [
        ([np.array([[0.0, 0.0], [1.0, 0.0]])], r"loop 0: .*at least 3"),
        ([np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 0.0]])], r"loop 0: .*at least 3"),
        ([np.array([[0.0, 0.0], [1.0, 1.0], [1.0, 0.0], [0.0, 1.0]])], r"loop 0: self-intersection"),
        ([np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])], r"loop 0: zero or near-zero area"),
        ([np.array([[0.0, 0.0], [1.0, 0.0], [np.nan, 1.0]])], r"loop 0: non-finite"),
        ([np.array([[0.0, 0.0], [1.0, 0.0], [np.inf, 1.0]])], r"loop 0: non-finite"),
        ([SQUARE, HOLE + 20.0], r"loop 1: hole is not inside the outer boundary \(loop 0\)"),
        ([HOLE + 20.0, SQUARE], r"loop 0: hole is not inside the outer boundary \(loop 1\)"),
        ([SQUARE, HOLE + [5.0, 0.0]], r"loop 0 \(edge \d+\) intersects loop 1"),
        ([SQUARE, HOLE, HOLE * 0.5 + 2.25], r"loop [12]: lies inside hole loop [12]"),
        ([np.array([[0.0, 0.0], [2.0, 0.0], [1.0, 0.0], [1.0, 1.0]])], r"loop 0: self-intersection"),
    ],
)
def test_bad_user_polygons_raise_specific_errors(loops, message):
    with pytest.raises(ProfileError, match=message):
        profile_from_polygons(loops, name="bad")


def test_profile_error_is_value_error():
    assert issubclass(ProfileError, ValueError)


def test_validation_is_fast_enough_for_dense_polygons():
    import time

    t = np.linspace(0, 2 * np.pi, 4096, endpoint=False)
    pts = np.stack([np.cos(t) * (1 + 0.1 * np.cos(5 * t)), np.sin(t) * (1 + 0.1 * np.cos(5 * t))], axis=1)
    start = time.perf_counter()
    p = profile_from_polygons([pts])
    assert time.perf_counter() - start < 20.0
    assert len(p.loops[0]) == 4096
    # A single crossing among 4096 vertices is found.
    bad = pts.copy()
    bad[[1000, 3000]] = bad[[3000, 1000]]
    with pytest.raises(ProfileError, match="self-intersection"):
        profile_from_polygons([bad])
