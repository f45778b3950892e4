"""The render's table lookups, made once (translators/mitsuba/table_plan.py): the lookups of
the estimates answer the translation's first lookup of each table; a table found missing is
looked up again before it is baked."""
from __future__ import annotations

import copy

import pytest

import usdfiber  # noqa: F401 - registers the schema
from usdfiber.bake.cache import TableCache
from usdfiber.bake.requests import requests_from_preset
from usdfiber.bake.settings import BakeSettings
from usdfiber.translators.mitsuba.table_plan import PlannedTableCache

SETTINGS = BakeSettings(resolution_deg=30, photons=1000, batches=2)


@pytest.fixture
def counted(monkeypatch):
    """The number of real cache lookups (TableCache.find_serving, which reads the headers)."""
    calls = []
    real = TableCache.find_serving

    def find_serving(self, request, settings):
        calls.append(self.key(request, settings))
        return real(self, request, settings)

    monkeypatch.setattr(TableCache, "find_serving", find_serving)
    return calls


def test_planned_lookups_answer_the_first_lookup_of_each_table(tmp_path, counted):
    reqs = requests_from_preset("silk")
    cache = PlannedTableCache(tmp_path)
    missing = cache.plan(reqs, lambda r: SETTINGS)
    assert missing == reqs                      # an empty cache serves none
    assert len(counted) == len(reqs)
    for r in reqs:                              # the translation's first lookups: no reads
        assert cache.find_serving(r, SETTINGS) is None
    assert len(counted) == len(reqs)
    cache.find_serving(reqs[0], SETTINGS)       # a later one reads the cache again
    assert len(counted) == len(reqs) + 1
    other = BakeSettings(resolution_deg=15, photons=1000, batches=2)
    cache.find_serving(reqs[0], other)          # a table that was not planned: read
    assert len(counted) == len(reqs) + 2


def test_a_table_made_after_the_plan_is_found_not_baked(tmp_path, counted, circle_table):
    """A table stored under its key after the plan (another process baked it) is loaded by
    the translation's lookup; the plan's answer only replaces the search for other tables."""
    req = requests_from_preset("polyester")[0]
    cache = PlannedTableCache(tmp_path)
    assert cache.plan([req], lambda r: SETTINGS) == [req]
    key = cache.key(req, SETTINGS)
    table = copy.deepcopy(circle_table)
    table.header["cache_key"] = key
    cache.table_path(key).parent.mkdir(parents=True)
    table.save(cache.table_path(key))
    res = cache.get_or_bake(req, SETTINGS, bake_missing=False)
    assert res is not None and not res.baked and res.key == key
    assert len(counted) == 1                    # the plan's only


def test_a_missing_table_is_looked_up_again_under_its_lock(tmp_path, counted):
    """Without baking, the translation's lookup of a missing table reads nothing (the plan
    answered); a bake looks again under the key's lock before it traces."""
    req = requests_from_preset("polyester")[0]
    cache = PlannedTableCache(tmp_path)
    cache.plan([req], lambda r: SETTINGS)
    assert cache.get_or_bake(req, SETTINGS, bake_missing=False) is None
    assert len(counted) == 1
    res = cache.get_or_bake(req, SETTINGS)
    assert res.baked and len(counted) == 3      # looked up without, then with the lock
