"""Bakes on a real Dask LocalCluster of 2 worker processes (usdfiber.farm.dask_bake)."""
from __future__ import annotations

import threading

import pytest

import usdfiber  # noqa: F401
from farm_util import COARSE_SETTINGS, fiber_stage, same_table
from usdfiber.bake.cache import TableCache
from usdfiber.bake.requests import tables_for_stage
from usdfiber.bake.settings import BakeSettings
from usdfiber.bake.table import BcsdfTable
from usdfiber.stage_io import open_stage

ST = BakeSettings(**COARSE_SETTINGS)
TASK_PHOTONS = 64_000        # 32 directions per task: 5 tasks for a 144-direction table


@pytest.fixture(scope="module")
def farm():
    from usdfiber.farm.cluster import LocalFarm

    with LocalFarm("local:2") as f:
        yield f


def _requests(path):
    return tables_for_stage(open_stage(str(path)))


def test_local_cluster_bake_equals_the_local_bake_bit_for_bit(farm, tmp_path):
    from usdfiber.farm.dask_bake import bake_on_dask

    stage = fiber_stage(tmp_path / "silk.usda", ("silk",))
    reqs = _requests(stage)
    cache = TableCache(tmp_path / "farm")
    s = bake_on_dask(farm.client, reqs, ST, cache, task_photons=TASK_PHOTONS, show_progress=False)
    assert s.ok and s.workers == 2 and s.tasks["total"] == 5 and s.tasks["run"] == 5, s.to_json()
    assert [t["status"] for t in s.tables] == ["assembled"]
    farm_table = BcsdfTable.load(s.tables[0]["path"])
    assert not (cache.partial_dir(s.tables[0]["key"])).exists()      # chunks removed once assembled
    local = TableCache(tmp_path / "local").get_or_bake(reqs[0], ST)
    assert local.key == s.tables[0]["key"]
    assert same_table(farm_table, local.table)
    # Again: nothing to do.
    again = bake_on_dask(farm.client, reqs, ST, cache, task_photons=TASK_PHOTONS, show_progress=False)
    assert again.ok and again.tasks["total"] == 0 and [t["status"] for t in again.tables] == ["cached"]


@pytest.mark.slow   # about a minute on 2 busy cores
def test_overlapping_clients_bake_each_task_once(farm, tmp_path):
    """Two clients on one scheduler, baking stages that share a table at the same time."""
    from distributed import Client, get_task_stream

    from usdfiber.farm.dask_bake import bake_on_dask

    a = fiber_stage(tmp_path / "a.usda", ("silk",))
    b = fiber_stage(tmp_path / "b.usda", ("silk", "polyester"))
    cache = TableCache(tmp_path / "cache")
    out: dict[str, object] = {}

    def run(name, stage):
        with Client(farm.address) as c:
            out[name] = bake_on_dask(c, _requests(stage), ST, cache, task_photons=TASK_PHOTONS, show_progress=False)

    with get_task_stream(client=farm.client) as ts:
        threads = [threading.Thread(target=run, args=(n, p)) for n, p in (("a", a), ("b", b))]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=600)
    assert set(out) == {"a", "b"} and out["a"].ok and out["b"].ok
    ran = [d["key"] for d in ts.data if str(d["key"]).startswith("usdfiber-trace-")]
    assert ran and len(ran) == len(set(ran)), sorted(ran)            # no trace task ran twice
    silk_key = out["a"].tables[0]["key"]
    silk_tasks = {k for k in ran if k.startswith(f"usdfiber-trace-{silk_key[:24]}")}
    assert len(silk_tasks) == 5
    assert {t["key"] for t in out["b"].tables} >= {silk_key}
    assert cache.load(silk_key) is not None


def test_a_second_bake_of_the_same_tables_on_one_scheduler_counts_no_retries(farm, tmp_path):
    from usdfiber.farm.dask_bake import bake_on_dask

    reqs = _requests(fiber_stage(tmp_path / "silk.usda", ("silk",)))
    runs = [bake_on_dask(farm.client, reqs, ST, TableCache(tmp_path / name), task_photons=TASK_PHOTONS,
                         show_progress=False) for name in ("first", "second")]
    # The scheduler keeps the first run's start events under the same task names.
    assert all(s.ok and s.tasks["run"] == 5 and s.tasks["retries"] == 0 for s in runs), [s.tasks for s in runs]
