"""The render's bake choice: per fiber by default, ``--bake-resolution``/``--bake-photons``
for every fiber, refused before any table is looked up when no bake accepts them."""
from __future__ import annotations

import pytest

from usdfiber.bake.requests import requests_from_preset
from usdfiber.bake.settings import RENDER_BAKE_SETTINGS, RENDER_EXPECTED_SETTINGS, BakeError, BakeSettings
from usdfiber.bcsdf import render_settings_for
from usdfiber.translators.mitsuba.scene import SceneOptions, bake_settings_for, render_bake


def test_default_is_per_fiber() -> None:
    assert SceneOptions().bake is render_settings_for is render_bake()
    poly, silk = requests_from_preset("polyester")[0], requests_from_preset("silk")[0]
    assert bake_settings_for(render_bake(), poly).resolution_deg == 2.0
    assert bake_settings_for(render_bake(), silk) == RENDER_EXPECTED_SETTINGS
    wool = requests_from_preset("wool")[0]
    assert bake_settings_for(render_bake(), wool) == RENDER_BAKE_SETTINGS


def test_overrides_and_fixed_settings() -> None:
    silk = requests_from_preset("silk")[0]
    st = bake_settings_for(render_bake(15, 4000), silk)
    assert (st.resolution_deg, st.photons) == (15.0, 4000)
    fixed = BakeSettings(resolution_deg=30, photons=200, batches=2)
    assert bake_settings_for(fixed, silk) is fixed


@pytest.mark.parametrize("res,photons", [(7, None), (None, 0)])
def test_bad_overrides_are_refused_up_front(res, photons) -> None:
    with pytest.raises(BakeError):
        render_bake(res, photons)
