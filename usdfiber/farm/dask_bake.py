"""Bakes on a Dask ``distributed`` cluster: :func:`bake_on_dask`.

The missing tables are split into trace tasks (:mod:`usdfiber.farm.tasks`); each runs on a
worker and writes its directions as chunks into the shared cache, and one assembly task per
table (depending on that table's trace tasks) verifies every chunk and writes the table.

Faults:

- A worker that dies mid-task loses only that task: the scheduler runs it again on another
  worker (``distributed.scheduler.allowed-failures`` times), and the rerun skips the
  directions whose chunks were already written. A task that raises is retried ``retries``
  times. Every start is logged on the scheduler, so the summary counts retries.
- A scheduler that dies loses nothing finished: the chunks are in the cache, and rerunning
  the bake (on any cluster, or locally) traces only what is missing.
- Clients that bake overlapping stages on one scheduler share tasks: task names are the Dask
  keys, and equal work has equal names, so the scheduler runs it once. Across schedulers the
  work is idempotent (see :mod:`usdfiber.farm.tasks`).
- The result is the same table a single-machine bake with the same settings writes.
"""
from __future__ import annotations

import sys
import time
from typing import Any, Iterable, TextIO

from usdfiber.bake.cache import TableCache
from usdfiber.bake.requests import TableRequest
from usdfiber.bake.settings import BakeSettings
from usdfiber.farm.cluster import FarmError, check_workers, write_probe
from usdfiber.farm.progress import EVENT_TOPIC, FarmFailure, FarmProgress, FarmSummary, count_retries
from usdfiber.farm.tasks import (TASK_PHOTONS, assemble_table, pending_directions, plan_tasks, release_chunks,
                                 run_trace_task, served_by, table_jobs)

__all__ = ["bake_on_dask"]


def _error_text(exc: BaseException | None) -> str:
    if exc is None:
        return "unknown error"
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _last_worker(events: list, name: str) -> str:
    for _, msg in reversed(events):
        if isinstance(msg, dict) and msg.get("task") == name:
            return str(msg.get("worker", ""))
    return ""


def bake_on_dask(client: Any, requests: Iterable[TableRequest], settings: BakeSettings | None = None,
                 cache: TableCache | None = None, *, task_photons: int = TASK_PHOTONS, retries: int = 2,
                 show_progress: bool = True, log: TextIO | None = None) -> FarmSummary:
    """Bake the tables of ``requests`` that ``cache`` lacks on the cluster of ``client``.

    ``client``: a connected ``distributed.Client``; its workers must see ``cache``'s
    directory (checked first: FarmError otherwise). ``task_photons``: photons per task.
    Returns the run's :class:`~usdfiber.farm.progress.FarmSummary` (``ok`` is False when a
    task failed for good; ``failures`` names each task, worker and error). Raises FarmError
    when the scheduler is lost (finished chunks are kept: run again to resume).
    """
    from distributed import as_completed

    st = settings or BakeSettings()
    cache = cache or TableCache()
    log = log or sys.stderr
    t0 = time.perf_counter()
    summary = FarmSummary(engine="dask", scheduler=str(client.scheduler.address))
    root = str(cache.root.absolute())
    cache.root.mkdir(parents=True, exist_ok=True)
    probe = write_probe(root)
    workers = check_workers(client, root, probe)
    summary.workers = len(workers)
    jobs = table_jobs(requests, st, cache)
    serving = {j.key: served_by(cache, j) for j in jobs}
    missing = [j for j in jobs if serving[j.key] is None]
    for j in jobs:
        if serving[j.key] is not None:
            release_chunks(cache, j.key)   # chunks of a task that outlived the table's assembly
            summary.tables.append({"key": serving[j.key], "label": j.label, "status": "cached",
                                   "path": str(cache.table_path(serving[j.key])), "prims": j.request.prims[:16]})
    tasks = plan_tasks(missing, task_photons)
    summary.tasks["total"] = len(tasks)
    todo = [t for t in tasks if pending_directions(cache, t) > 0]
    summary.tasks["skipped"] = len(tasks) - len(todo)
    total = sum(len(t.directions) for t in tasks)
    pending = {t.name: pending_directions(cache, t) for t in todo}
    summary.times["plan"] = time.perf_counter() - t0
    bar = FarmProgress(total, initial=total - sum(pending.values()), desc=f"bake {len(missing)} tables",
                       show=show_progress, file=log)
    by_key = {j.key: j for j in jobs}
    trace_futs: dict[str, Any] = {}
    for t in todo:
        trace_futs[t.name] = client.submit(run_trace_task, by_key[t.key], t, root, probe, key=t.name,
                                           retries=retries, pure=False)
    asm_futs = {}
    for j in missing:
        deps = [trace_futs[t.name] for t in todo if t.key == j.key]
        asm_futs[j.key] = client.submit(assemble_table, j, root, probe, *deps,
                                        key=f"usdfiber-assemble-{j.key}", retries=retries, pure=False)
    what = {f.key: (t.key, t.name) for t in todo for f in [trace_futs[t.name]]}
    what.update({f.key: (k, f"usdfiber-assemble-{k[:24]}") for k, f in asm_futs.items()})
    failed_tables: set[str] = set()
    lost = False
    for fut in as_completed(list(trace_futs.values()) + list(asm_futs.values())):
        if fut.status in ("cancelled", "lost") or client.status not in ("running", "connecting"):
            lost = True
            break
        table_key, name = what[fut.key]
        if fut.status == "error":
            if table_key in failed_tables:
                continue  # the assembly of a table whose trace already failed: reported once
            failed_tables.add(table_key)
            f = FarmFailure(name, _last_worker(client.get_events(EVENT_TOPIC), name),
                            f"{by_key[table_key].label}: {_error_text(fut.exception())}")
            summary.failures.append(f)
            bar.log(f"usdfiber: error: {f.line()}")
            continue
        res = fut.result()
        if "traced" in res:
            summary.tasks["run"] += 1
            bar.advance(pending.get(name, 0))
        else:
            summary.tables.append(res)
            bar.advance(0, f"{res['label']}: error {res['error_rms']:.4f} rms")
    summary.times["bake"] = bar.close()
    if lost:
        raise FarmError(f"lost the Dask scheduler {summary.scheduler} mid-bake; finished directions are kept "
                        f"in {cache.root / 'partial'}: run the bake again to resume")
    events = client.get_events(EVENT_TOPIC)
    retried = count_retries(events, list(trace_futs) + [f"usdfiber-assemble-{k[:24]}" for k in asm_futs],
                            run=probe.path)
    summary.tasks["retries"] = sum(retried.values())
    summary.tasks["failed"] = len(summary.failures)
    for name, n in sorted(retried.items()):
        if n:
            print(f"usdfiber: task {name} was retried {n} time{'s' if n > 1 else ''} "
                  f"(its worker died or it failed)", file=log)
    summary.ok = not summary.failures
    summary.times["total"] = time.perf_counter() - t0
    return summary
