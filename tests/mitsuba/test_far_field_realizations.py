"""A yarn's far field is a statistic of its structure, not of one random placement of its
fibers: traced through several realizations (``YarnBakeSettings.realizations``), its projected
width is the structure's mean."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import usdfiber  # noqa: F401  (registers schemas first)
from usdfiber.backend import mitsuba
from usdfiber.bake.baker import bake_table
from usdfiber.bake import profiles
from usdfiber.bake.settings import BakeSettings

from usdfiber.translators.mitsuba.curves import make_curve_shape
from usdfiber.translators.mitsuba.fiber_bank import FiberSlot
from usdfiber.translators.mitsuba.yarn_far_field import (YarnBakeSettings, bake_yarn_far_field, far_field_pieces,
                                                         yarn_piece)
from usdfiber.spec.yarn import YarnParams

mi = mitsuba()

D = 0.01           # Skala 360's polyester, 10 um in mm


def skala() -> YarnParams:
    from pxr import Usd, UsdGeom

    from usdfiber import cloth

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    cloth.plain_weave(stage, "/W", warps=2, wefts=2, yarn="Skala 360")
    return YarnParams.from_prim(stage.GetPrimAtPath("/W/Warp"))


def projected_width(piece, rng, n: int = 60_000) -> float:
    """The fraction of the piece's bounding width its fibers cover, seen perpendicular to the
    yarn (4 azimuths), times the bounding radius: the yarn's projected width over 2."""
    scene = mi.load_dict({"type": "scene", "f": make_curve_shape(piece.geometry, mi.load_dict({"type": "diffuse"}),
                                                                  "f")})
    hits = []
    for phi in np.linspace(0.0, np.pi, 4, endpoint=False):
        u, z = rng.uniform(-1.0, 1.0, n), rng.uniform(0.0, piece.length, n)
        c, s = np.cos(phi), np.sin(phi)
        o = np.stack([-u * s + 2 * c, u * c + 2 * s, z], axis=1)
        ray = mi.Ray3f(mi.Point3f(*(mi.Float(o[:, k].astype(np.float32)) for k in range(3))),
                       mi.Vector3f(float(-c), float(-s), 0.0))
        hits.append(np.mean(np.array(scene.ray_intersect(ray).is_valid())))
    return float(np.mean(hits)) * piece.bound_radius


def test_pieces_share_one_bounding_radius_and_differ():
    yp = skala()
    st = YarnBakeSettings(resolution_deg=30, photons=400, batches=2, realizations=3)
    pieces = far_field_pieces(yp, D, st)
    assert len(pieces) == 3 and len({pc.bound_radius for pc in pieces}) == 1
    for pc in pieces:                       # every fiber inside the unit cylinder
        g = pc.geometry
        inside = (g.points[:, 2] > 0) & (g.points[:, 2] < pc.length)
        assert np.max(np.hypot(g.points[inside, 0], g.points[inside, 1])) <= 1.0 + 1e-9
    assert not np.allclose(pieces[0].geometry.points[:50], pieces[1].geometry.points[:50])


@pytest.mark.slow
def test_far_field_coverage_is_the_structures_mean():
    """Skala 360 (24 fibers): the projected width of a piece varies by about 5 % from seed to
    seed, and the settings' seed 1 alone is 9 % under the mean of seeds 0-23. The traced
    coverage times the bounding radius, with the default realizations (8), is within 5 % of that
    mean. Deterministic (numpy seeds; Mitsuba only intersects); as a statistic of random
    structures the far field's deviation has a standard deviation of about 1.7 % (5 % over
    sqrt(8), the ensemble's own 1 %, the trace's 0.4 %): 5 % is 3 of them. With one
    realization (before) the test fails (-9 %)."""
    yp = skala()
    rng = np.random.default_rng(5)
    st = YarnBakeSettings(resolution_deg=30, photons=4000, batches=2)
    ensemble = np.array([projected_width(yarn_piece(replace(yp, seed=k), D, st), rng) for k in range(24)])
    mean = float(ensemble.mean())
    assert ensemble.std(ddof=1) / mean > 0.02           # the realizations do differ
    table = bake_table(profiles.builtin_profiles("polyester", 1)[0], 1.635, 3.1, None,
                       BakeSettings(resolution_deg=30, photons=2000, batches=2))
    ff = bake_yarn_far_field(yp, D, [FiberSlot(table, (0.0, 0.0, 0.0))], st)
    width = float(np.mean(ff.coverage)) * ff.header["piece"]["bound_radius"]
    assert ff.header["piece"]["realizations"] == st.realizations
    assert abs(width / mean - 1.0) < 0.05, (width, mean)
