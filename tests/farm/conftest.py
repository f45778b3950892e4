"""Fixtures shared by the farm tests: one small silk stage and its table baked without a farm."""
from __future__ import annotations

import pytest
from farm_util import COARSE_SETTINGS, fiber_stage

from usdfiber.bake.cache import TableCache
from usdfiber.bake.requests import tables_for_stage
from usdfiber.bake.settings import BakeSettings
from usdfiber.stage_io import open_stage


@pytest.fixture(scope="module")
def stage(tmp_path_factory):
    """A stage with one silk fiber prim (one table at the coarse farm-test settings)."""
    return fiber_stage(tmp_path_factory.mktemp("stage") / "silk.usda", ("silk",))


@pytest.fixture(scope="module")
def reference(stage, tmp_path_factory):
    """The stage's table baked in this process, without a farm: what every farm path must equal."""
    req = tables_for_stage(open_stage(str(stage)))[0]
    return TableCache(tmp_path_factory.mktemp("ref")).get_or_bake(req, BakeSettings(**COARSE_SETTINGS)).table
