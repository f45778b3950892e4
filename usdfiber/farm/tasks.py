"""The units of a farm bake: tables split into groups of incoming directions.

A table is baked direction by direction (:mod:`usdfiber.bake.baker`): every incoming
direction gets its own photons (its batches use the same random streams whatever else is
traced with it), so a table does not depend on which process traced which direction. A farm
bake therefore splits each missing table into :class:`TraceTask` s, groups of about
:data:`TASK_PHOTONS` photons worth of directions (tens of seconds on one worker), that
trace into the cache's resume chunks (``partial/<key>/``, one verified file per direction,
written by atomic rename), and one assembly per table that reads every chunk back,
verifying its key, direction and checksum, and writes the table.

Plans are deterministic: they depend only on the tables asked for and the settings, never on
what is already done, so every process of a sharded bake (and every client of a Dask bake)
agrees on the tasks and their names. What is done is decided when a task runs: directions
whose chunk already verifies are skipped, and a table already in the cache skips
everything. Running a task twice, concurrently or not, writes the same bytes (each process
renames its own uniquely named temporary file over the chunk), so retries, duplicate shards
and overlapping clients cost time at worst, never correctness. No file locks are used:
they are not reliable on network filesystems.
"""
from __future__ import annotations

import math
import os
import shutil
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Sequence

from usdfiber.bake.baker import assemble_from_chunks, table_directions, trace_to_chunks
from usdfiber.bake.cache import TableCache, TableCacheWarning
from usdfiber.bake.chunks import chunk_name
from usdfiber.bake.requests import TableRequest
from usdfiber.bake.settings import BakeError, BakeSettings
from usdfiber.farm.cluster import Probe, TASK_LOCK, verify_probe

__all__ = ["TASK_PHOTONS", "TableJob", "TraceTask", "assemble_table", "directions_per_task", "plan_tasks",
           "pending_directions", "release_chunks", "run_trace_task", "served_by", "table_done", "table_jobs"]

#: Photons per task (about 2^26): tens of seconds on one worker at the tracer's 2-7 M photons/s.
TASK_PHOTONS = 1 << 26


@dataclass
class TableJob:
    """One table to bake: its cache key, request and settings."""

    key: str
    request: TableRequest
    settings: BakeSettings

    @property
    def label(self) -> str:
        return self.request.label


@dataclass(frozen=True)
class TraceTask:
    """Directions ``directions`` (grid indices ``(ti, pi)``) of the table ``key``: task
    ``index`` of ``count``."""

    key: str
    index: int
    count: int
    directions: tuple[tuple[int, int], ...]

    @property
    def name(self) -> str:
        """The task's name, also its Dask key: equal for equal work in every client."""
        return f"usdfiber-trace-{self.key[:24]}-{self.index + 1:05d}of{self.count:05d}"


def table_jobs(requests: Iterable[TableRequest], settings: BakeSettings, cache: TableCache) -> list[TableJob]:
    """One job per distinct cache key (the prims of duplicates merged), in key order."""
    jobs: dict[str, TableJob] = {}
    for r in requests:
        k = cache.key(r, settings)
        if k in jobs:
            jobs[k].request.prims.extend(p for p in r.prims if p not in jobs[k].request.prims)
        else:
            jobs[k] = TableJob(k, r, settings)
    return [jobs[k] for k in sorted(jobs)]


def directions_per_task(settings: BakeSettings, task_photons: int = TASK_PHOTONS) -> int:
    """Directions in one task: about ``task_photons`` photons (with a target error, the first
    amount per direction is what is known in advance; with a row schedule, its largest row)."""
    per = max([int(settings.photons), *(settings.row_photons or ())])
    return max(1, int(task_photons) // max(1, per))


def plan_tasks(jobs: Sequence[TableJob], task_photons: int = TASK_PHOTONS) -> list[TraceTask]:
    """Every task of every job, table by table (directions in the baker's order)."""
    out: list[TraceTask] = []
    for job in jobs:
        dirs = table_directions(job.request, job.settings)
        per = directions_per_task(job.settings, task_photons)
        n = max(1, math.ceil(len(dirs) / per))
        out.extend(TraceTask(job.key, i, n, tuple(dirs[i * per:(i + 1) * per])) for i in range(n))
    return out


def pending_directions(cache: TableCache, task: TraceTask) -> int:
    """Directions of ``task`` without a chunk file (existence only; running the task verifies)."""
    d = cache.partial_dir(task.key)
    return sum(not (d / chunk_name(ti, pi)).exists() for ti, pi in task.directions)


def _log_start(task_name: str, probe: Probe | None) -> None:
    """Tell the Dask scheduler this task started (counted as a retry when it starts again in
    the same run: the run is named by its probe file, unique per bake)."""
    try:
        from distributed import get_worker

        from usdfiber.farm.progress import EVENT_TOPIC

        get_worker().log_event(EVENT_TOPIC, {"event": "start", "task": task_name, "pid": os.getpid(),
                                           "run": probe.path if probe is not None else None})
    except (ImportError, ValueError):
        pass  # not in a Dask worker (a shard)


def table_done(cache: TableCache, key: str) -> bool:
    """Whether the table of ``key`` is in ``cache`` and verifies (a damaged one is removed)."""
    import warnings

    if not cache.contains(key):
        return False
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TableCacheWarning)
        return cache.load(key) is not None


def served_by(cache: TableCache, job: TableJob) -> str | None:
    """The key of the cached table that serves ``job``: its own, or another of the same physics
    at least as good (:meth:`TableCache.find_serving`); None when the table must be baked."""
    if cache.contains(job.key):
        return job.key
    return cache.find_serving(job.request, job.settings)


def release_chunks(cache: TableCache, key: str) -> bool:
    """Remove the chunks of ``key`` (``partial/<key>/``) once its table exists and verifies.

    Chunks are the only copy of finished work until then, so they are never removed
    before. The folder is first renamed to a unique name, so that no process sees a
    half-removed set of chunks under the table's name; a process still tracing into it
    finds it gone and, seeing the table done, stops (:func:`run_trace_task`). Returns
    whether anything was removed.
    """
    d = cache.partial_dir(key)
    if not d.exists() or not table_done(cache, key):
        return False
    gone = d.with_name(f".{key}.gone-{os.getpid()}-{uuid.uuid4().hex[:8]}")
    try:
        os.rename(d, gone)
    except OSError:
        return False   # removed (or being removed) by another process
    shutil.rmtree(gone, ignore_errors=True)
    return True


def run_trace_task(job: TableJob, task: TraceTask, cache_root: str, probe: Probe | None = None) -> dict[str, Any]:
    """Trace the directions of ``task`` that have no valid chunk yet into the cache.

    Runs on a Dask worker or in a shard process. Returns what it did: ``traced`` and
    ``skipped`` directions, ``photons``, ``seconds``, ``host`` and ``pid``. A task whose
    table is assembled meanwhile (by an overlapping run) stops there and leaves no chunks.
    """
    _log_start(task.name, probe)
    verify_probe(probe, cache_root)
    cache = TableCache(cache_root)
    t0 = time.perf_counter()
    out = {"task": task.name, "key": task.key, "traced": 0, "skipped": len(task.directions), "photons": 0,
           "seconds": 0.0, "host": os.uname().nodename, "pid": os.getpid()}
    if table_done(cache, task.key):
        release_chunks(cache, task.key)   # left by a task that was still tracing when the table was made
        return out
    try:
        with TASK_LOCK:
            stats = trace_to_chunks(job.request, job.settings, task.directions, cache.partial_dir(task.key))
    except (OSError, BakeError):
        # The chunk folder vanished under this task: the table was assembled meanwhile.
        if not table_done(cache, task.key):
            raise
        release_chunks(cache, task.key)
        out["seconds"] = time.perf_counter() - t0
        return out
    # Assembled meanwhile (an overlapping run): what this task wrote is not needed.
    release_chunks(cache, task.key)
    out.update(traced=int(stats["traced"]), skipped=len(task.directions) - int(stats["traced"]),
               photons=int(stats["photons"]), seconds=time.perf_counter() - t0)
    return out


def assemble_table(job: TableJob, cache_root: str, probe: Probe | None = None, *_done: Any) -> dict[str, Any]:
    """Assemble ``job``'s table from its chunks (each verified) and write it to the cache.

    ``_done``: the table's trace results (Dask passes them, so that this runs after them).
    Returns ``status`` ("assembled" or "cached": another process was first), the table's
    ``path``, ``photons``, ``error_rms``/``error_max`` and ``seconds``. Raises BakeError
    naming the chunk when one is missing or does not verify.
    """
    import warnings

    _log_start(f"usdfiber-assemble-{job.key[:24]}", probe)
    verify_probe(probe, cache_root)
    cache = TableCache(cache_root)
    t0 = time.perf_counter()
    path = cache.table_path(job.key)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TableCacheWarning)
        table = cache.load(job.key)
    status = "cached"
    if table is None:
        try:
            with TASK_LOCK:
                table = assemble_from_chunks(job.request, job.settings, cache.partial_dir(job.key))
        except (BakeError, OSError):
            table = cache.load(job.key)   # another process assembled it and removed the chunks
            if table is None:
                raise
        else:
            table.header["cache_key"] = job.key
            path.parent.mkdir(parents=True, exist_ok=True)
            table.save(path)
            status = "assembled"
    release_chunks(cache, job.key)   # only once the table reads back and verifies
    err = table.header.get("error_estimate", {})
    return {"key": job.key, "label": job.label, "status": status, "path": str(path),
            "photons": int(table.arrays["photons"].sum()), "directions": int(table.arrays["photons"].size),
            "error_rms": float(err.get("rms", float("nan"))), "error_max": float(err.get("max", float("nan"))),
            "seconds": time.perf_counter() - t0, "prims": list(job.request.prims[:16])}
