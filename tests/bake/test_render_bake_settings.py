"""The settings of tables baked on demand for renders and materials: chosen per fiber
(:func:`usdfiber.bake.settings.render_bake_settings`, applied to a table request by
:func:`usdfiber.bcsdf.render_settings_for`), overridable for every fiber, and followed by
``tables_for_prim``."""
from __future__ import annotations

from dataclasses import replace

import pytest
from pxr import Usd, UsdGeom

import usdfiber  # noqa: F401  (registers the schemas)
from usdfiber import authoring
from usdfiber.bake.cache import TableCache
from usdfiber.bake.requests import requests_from_preset
from usdfiber.bake.settings import (RENDER_BAKE_SETTINGS, RENDER_EXPECTED_SETTINGS, ROUND_RENDER_RESOLUTION_DEG,
                                    BakeError, BakeSettings, render_bake_settings)
from usdfiber.bcsdf import render_settings_for, tables_for_prim


def test_round_fibers_get_the_fine_grid_and_others_the_render_settings() -> None:
    assert render_bake_settings(True).resolution_deg == ROUND_RENDER_RESOLUTION_DEG
    assert render_bake_settings(False) == RENDER_EXPECTED_SETTINGS
    assert render_bake_settings(False, cuticle_scales=True) == RENDER_BAKE_SETTINGS
    poly = render_settings_for(requests_from_preset("polyester")[0])
    assert poly.resolution_deg == ROUND_RENDER_RESOLUTION_DEG and poly.incoming_deg is None
    assert poly.photons == RENDER_EXPECTED_SETTINGS.photons and poly.batches == RENDER_BAKE_SETTINGS.batches
    assert poly.estimator == ("expected",)
    for kind in ("silk", "cotton"):
        assert all(render_settings_for(r) == RENDER_EXPECTED_SETTINGS for r in requests_from_preset(kind))
    # The expected value needs fibers without cuticle scales: wool keeps the plain estimator.
    assert all(render_settings_for(r) == RENDER_BAKE_SETTINGS for r in requests_from_preset("wool"))


def test_render_expected_settings_differ_only_in_estimator_and_photons() -> None:
    a, b = RENDER_EXPECTED_SETTINGS, RENDER_BAKE_SETTINGS
    assert (a.resolution_deg, a.batches, a.incoming) == (b.resolution_deg, b.batches, b.incoming)
    assert a.estimator == ("expected",) and b.estimator == () and a.photons < b.photons


def test_overrides_apply_to_every_fiber() -> None:
    for kind in ("polyester", "silk"):
        st = render_settings_for(requests_from_preset(kind)[0], resolution_deg=15, photons=4000)
        assert (st.resolution_deg, st.incoming_deg, st.photons, st.estimator) == (15.0, None, 4000, ())
    # A grid alone keeps the per-fiber estimator and photons; photons given are plain photons.
    assert render_settings_for(requests_from_preset("silk")[0], resolution_deg=10) == replace(
        RENDER_EXPECTED_SETTINGS, resolution_deg=10.0)
    assert render_settings_for(requests_from_preset("silk")[0], photons=20000) == replace(
        RENDER_BAKE_SETTINGS, photons=20000)
    # Photons alone keep the per-fiber grid.
    assert render_settings_for(requests_from_preset("polyester")[0], photons=4000).resolution_deg == 2.0
    with pytest.raises(BakeError):
        render_settings_for(requests_from_preset("silk")[0], resolution_deg=7)


def test_plain_render_settings_keep_their_cache_key(tmp_path) -> None:
    # Tables of fibers with cuticle scales baked before the per-fiber choice stay valid under
    # their own keys.
    cache = TableCache(tmp_path)
    req = requests_from_preset("wool")[0]
    assert cache.key(req, render_settings_for(req)) == cache.key(req, BakeSettings(resolution_deg=6.0, photons=100_000,
                                                                                   batches=4))


def _stage(kind: str) -> Usd.Stage:
    stage = Usd.Stage.CreateInMemory()
    curves = UsdGeom.BasisCurves.Define(stage, "/F")
    curves.CreateTypeAttr("linear")
    curves.CreatePointsAttr([(0, 0, 0), (0, 1, 0)])
    curves.CreateCurveVertexCountsAttr([2])
    curves.CreateWidthsAttr([0.01])
    curves.SetWidthsInterpolation("constant")
    authoring.apply_fiber(curves.GetPrim(), kind)
    curves.GetPrim().GetAttribute("fiber:profile:variantCount").Set(2)
    return stage


def test_tables_for_prim_takes_settings_per_request(tmp_path) -> None:
    seen = []

    def choose(req):
        seen.append(req.variant)
        return BakeSettings(resolution_deg=30 if req.variant == 0 else 45, photons=200, batches=2)

    stage = _stage("silk")
    tables = tables_for_prim(stage.GetPrimAtPath("/F"), choose, cache=TableCache(tmp_path))
    assert seen == [0, 1]
    assert [t.grid.resolution_deg for t in tables] == [30.0, 45.0]
