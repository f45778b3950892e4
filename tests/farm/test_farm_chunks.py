"""Chunks of farm bakes: read once by the assembly, removed only once the table verifies, and no
orphan ``partial/<key>/`` folder from a trace task that outlives its table's assembly."""
from __future__ import annotations

from collections import Counter

import pytest

import usdfiber  # noqa: F401
from farm_util import COARSE_SETTINGS, fiber_stage, same_table
from usdfiber.bake import chunks as chunks_module
from usdfiber.bake import baker
from usdfiber.bake.cache import TableCache
from usdfiber.bake.requests import tables_for_stage
from usdfiber.bake.settings import BakeSettings
from usdfiber.farm import tasks as farm_tasks
from usdfiber.farm.tasks import assemble_table, plan_tasks, release_chunks, run_trace_task, table_jobs
from usdfiber.stage_io import open_stage

ST = BakeSettings(**COARSE_SETTINGS)


@pytest.fixture(scope="module")
def request_(tmp_path_factory):
    stage = fiber_stage(tmp_path_factory.mktemp("stage") / "silk.usda", ("silk",))
    return tables_for_stage(open_stage(str(stage)))[0]


@pytest.fixture(scope="module")
def reference(request_, tmp_path_factory):
    return TableCache(tmp_path_factory.mktemp("ref")).get_or_bake(request_, ST).table


def _assemble_elsewhere(job, cache: TableCache) -> None:
    """What another process's assembly does (this thread holds the task lock: no assemble_table)."""
    table = baker.assemble_from_chunks(job.request, job.settings, cache.partial_dir(job.key))
    table.header["cache_key"] = job.key
    cache.table_path(job.key).parent.mkdir(parents=True, exist_ok=True)
    table.save(cache.table_path(job.key))
    assert release_chunks(cache, job.key)


def _traced(cache: TableCache, request_):
    """The table's job and tasks, every task traced into ``cache`` (not yet assembled)."""
    job = table_jobs([request_], ST, cache)[0]
    tasks = plan_tasks([job], 40 * ST.photons)
    assert len(tasks) >= 2
    for t in tasks:
        run_trace_task(job, t, str(cache.root))
    return job, tasks


def test_assembly_reads_every_chunk_once(request_, reference, tmp_path, monkeypatch):
    cache = TableCache(tmp_path / "cache")
    job, tasks = _traced(cache, request_)
    reads: Counter = Counter()
    real_load = chunks_module.ResumeDirectory.load

    def counting_load(self, ti, pi):
        reads[(ti, pi)] += 1
        return real_load(self, ti, pi)

    monkeypatch.setattr(chunks_module.ResumeDirectory, "load", counting_load)
    res = assemble_table(job, str(cache.root))
    assert res["status"] == "assembled"
    n_dirs = sum(len(t.directions) for t in tasks)
    assert len(reads) == n_dirs and set(reads.values()) == {1}, reads
    assert same_table(cache.load(job.key), reference)
    assert not cache.partial_dir(job.key).exists()


def test_chunks_beyond_the_memory_cap_are_read_again(request_, reference, tmp_path, monkeypatch):
    cache = TableCache(tmp_path / "cache")
    job, _ = _traced(cache, request_)
    monkeypatch.setattr(baker, "KEEP_CHUNK_BYTES", 0)
    reads: Counter = Counter()
    real_load = chunks_module.ResumeDirectory.load
    monkeypatch.setattr(chunks_module.ResumeDirectory, "load",
                        lambda self, ti, pi: (reads.update([(ti, pi)]), real_load(self, ti, pi))[1])
    assemble_table(job, str(cache.root))
    assert set(reads.values()) == {2}
    assert same_table(cache.load(job.key), reference)


def test_chunks_are_kept_until_the_table_verifies(request_, tmp_path):
    cache = TableCache(tmp_path / "cache")
    job, tasks = _traced(cache, request_)
    partial = cache.partial_dir(job.key)
    n_chunks = len(list(partial.glob("d*_*.npz")))
    assert not release_chunks(cache, job.key)                 # no table yet
    cache.table_path(job.key).parent.mkdir(parents=True, exist_ok=True)
    cache.table_path(job.key).write_bytes(b"not a table")   # a damaged table serves nothing
    assert not release_chunks(cache, job.key)
    assert len(list(partial.glob("d*_*.npz"))) == n_chunks
    assert assemble_table(job, str(cache.root))["status"] == "assembled"
    assert not partial.exists()


def test_a_trace_task_finishing_after_the_assembly_leaves_no_orphan(request_, reference, tmp_path, monkeypatch):
    cache = TableCache(tmp_path / "cache")
    job = table_jobs([request_], ST, cache)[0]
    tasks = plan_tasks([job], 40 * ST.photons)
    all_dirs = [d for t in tasks for d in t.directions]
    real_trace = farm_tasks.trace_to_chunks

    def trace_while_another_run_assembles(request, settings, directions, chunk_dir):
        real_trace(request, settings, all_dirs, chunk_dir)      # the other run traces everything ...
        _assemble_elsewhere(job, cache)                         # ... and assembles the table
        return real_trace(request, settings, directions, chunk_dir)   # this task then writes its chunks

    monkeypatch.setattr(farm_tasks, "trace_to_chunks", trace_while_another_run_assembles)
    out = run_trace_task(job, tasks[0], str(cache.root))
    assert out["traced"] == len(tasks[0].directions)
    assert not cache.partial_dir(job.key).exists()
    assert not [p for p in (cache.root / "partial").iterdir()]   # no renamed leftovers either
    assert same_table(cache.load(job.key), reference)



def test_a_trace_task_whose_folder_vanishes_is_done_only_if_the_table_is(request_, tmp_path, monkeypatch):
    cache = TableCache(tmp_path / "cache")
    job = table_jobs([request_], ST, cache)[0]
    tasks = plan_tasks([job], 40 * ST.photons)
    all_dirs = [d for t in tasks for d in t.directions]
    real_trace = farm_tasks.trace_to_chunks
    assemble_meanwhile = {"on": False}

    def folder_removed_under_it(request, settings, directions, chunk_dir):
        if assemble_meanwhile["on"]:     # another run assembles the table and removes the chunks
            real_trace(request, settings, all_dirs, chunk_dir)
            _assemble_elsewhere(job, cache)
        raise FileNotFoundError(2, "No such file or directory", str(chunk_dir))

    monkeypatch.setattr(farm_tasks, "trace_to_chunks", folder_removed_under_it)
    with pytest.raises(FileNotFoundError):          # no table: the error is real
        run_trace_task(job, tasks[1], str(cache.root))
    assemble_meanwhile["on"] = True
    out = run_trace_task(job, tasks[1], str(cache.root))   # the table is there: done, not failed
    assert out["traced"] == 0 and cache.load(job.key) is not None
    assert not cache.partial_dir(job.key).exists()
