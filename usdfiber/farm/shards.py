"""Sharded bakes for farm managers: ``usdfiber bake STAGE --shard I/N``.

Every shard plans the same task list (:func:`usdfiber.farm.tasks.plan_tasks`, over all the
tables the inputs need, whether done or not) and runs its part (:class:`Shard`) in this
process, writing chunks into the shared cache exactly as Dask workers do. Then it assembles
every table whose chunks are all present, whoever traced them: the last shard to finish
assembles what is left, and a shard that runs again, or after the others, finds the tables
done. An interrupted shard keeps its finished directions; rerunning it traces the rest.
"""
from __future__ import annotations

import sys
import time
from typing import Iterable, TextIO

from usdfiber.bake.cache import TableCache
from usdfiber.bake.requests import TableRequest
from usdfiber.bake.settings import BakeError, BakeSettings
from usdfiber.farm.progress import FarmFailure, FarmProgress, FarmSummary
from usdfiber.farm.shard_spec import Shard
from usdfiber.farm.tasks import (TASK_PHOTONS, assemble_table, pending_directions, plan_tasks, run_trace_task,
                                 served_by, table_jobs)

__all__ = ["bake_shard"]


def bake_shard(requests: Iterable[TableRequest], settings: BakeSettings | None, cache: TableCache,
               shard: Shard, *, task_photons: int = TASK_PHOTONS, show_progress: bool = True,
               log: TextIO | None = None) -> FarmSummary:
    """Trace this shard's part of the tables of ``requests`` into ``cache`` and assemble every
    table whose directions are all traced. Returns the run's summary; tables that still wait
    for other shards are listed with status ``"waiting"`` and the directions they lack."""
    st = settings or BakeSettings()
    log = log or sys.stderr
    t0 = time.perf_counter()
    summary = FarmSummary(engine="shard", shard=str(shard))
    root = str(cache.root.absolute())
    cache.root.mkdir(parents=True, exist_ok=True)
    jobs = table_jobs(requests, st, cache)
    tasks = plan_tasks(jobs, task_photons)
    mine = shard.select(tasks)
    summary.tasks["total"] = len(mine)
    by_key = {j.key: j for j in jobs}
    serving = {j.key: served_by(cache, j) for j in jobs}
    todo = [t for t in mine if serving[t.key] is None and pending_directions(cache, t) > 0]
    summary.tasks["skipped"] = len(mine) - len(todo)
    total = sum(len(t.directions) for t in mine)
    pending = {t.name: pending_directions(cache, t) for t in todo}
    summary.times["plan"] = time.perf_counter() - t0
    bar = FarmProgress(total, initial=total - sum(pending.values()), desc=f"shard {shard}", show=show_progress,
                       file=log)
    try:
        for t in todo:
            try:
                run_trace_task(by_key[t.key], t, root)
            except (BakeError, OSError) as exc:
                f = FarmFailure(t.name, _where(), f"{by_key[t.key].label}: {exc}")
                summary.failures.append(f)
                bar.log(f"usdfiber: error: {f.line()}")
                continue
            summary.tasks["run"] += 1
            bar.advance(pending[t.name])
    finally:
        summary.times["trace"] = bar.close()
    t1 = time.perf_counter()
    for job in jobs:
        other = serving[job.key]
        if other is not None and other != job.key:   # another table of the same physics, at least as good
            summary.tables.append({"key": other, "label": job.label, "status": "cached",
                                   "path": str(cache.table_path(other)), "prims": job.request.prims[:16]})
            continue
        remaining = sum(pending_directions(cache, t) for t in tasks if t.key == job.key)
        if cache.contains(job.key) or remaining == 0:
            try:
                summary.tables.append(assemble_table(job, root))
            except (BakeError, OSError) as exc:
                f = FarmFailure(f"usdfiber-assemble-{job.key[:24]}", _where(), f"{job.label}: {exc}")
                summary.failures.append(f)
                print(f"usdfiber: error: {f.line()}", file=log)
        else:
            summary.tables.append({"key": job.key, "label": job.label, "status": "waiting",
                                   "missing_directions": remaining, "path": str(cache.table_path(job.key)),
                                   "prims": job.request.prims[:16]})
    summary.times["assemble"] = time.perf_counter() - t1
    summary.tasks["failed"] = len(summary.failures)
    summary.ok = not summary.failures
    summary.times["total"] = time.perf_counter() - t0
    return summary


def _where() -> str:
    """This machine's name and process (where a shard's failure happened)."""
    import os

    return f"{os.uname().nodename} pid {os.getpid()}"
