"""The farm options of ``usdfiber bake``: ``--scheduler``, ``--shard``, ``--task-photons``, ``--json``.

``usdfiber.commands.bake`` adds these options (:func:`add_bake_options`) and hands the run
here (:func:`run_bake`) when one of them is given. Exit status: 0 every table done (or, for
a shard, its part done), 1 a task failed (each failure printed with its task, worker and
error), 2 bad input (one line).
"""
from __future__ import annotations

import argparse
from typing import Any

from usdfiber.commands.arg_types import positive_int

__all__ = ["add_bake_options", "check_farm_options", "run_bake", "wants_farm"]


def add_bake_options(p: argparse.ArgumentParser) -> None:
    """The farm options of ``usdfiber bake``."""
    g = p.add_argument_group("farm")
    g.add_argument("--scheduler", metavar="ADDRESS",
                   help="bake on a Dask cluster: a scheduler address (tcp://host:8786) or local:N for N worker "
                        "processes on this machine; the cache must be on a filesystem every worker sees")
    g.add_argument("--shard", metavar="I/N",
                   help="bake only the I-th of N disjoint parts of the work into the cache (for farm managers); "
                        "any shard assembles the tables whose parts are all done")
    g.add_argument("--task-photons", type=positive_int, default=None, metavar="N",
                   help="photons per farm task (default 67108864: tens of seconds per task)")
    g.add_argument("--json", action="store_true",
                   help="print a JSON summary (tables, tasks, retries, failures, times) instead of one line per table")


def wants_farm(args: argparse.Namespace) -> bool:
    """Whether ``run_bake`` handles this command line."""
    return bool(args.scheduler or args.shard or args.json)


def check_farm_options(args: argparse.Namespace) -> None:
    """Refuse, with a one-line UsageError, farm options that cannot work: --scheduler with
    --shard, a malformed --shard or --scheduler (no connection is tried), --plot or --compress
    with the farm. Run before anything else, so that ``--dry-run`` refuses what a bake would."""
    from usdfiber.cli import UsageError
    from usdfiber.farm.cluster import FarmError, parse_scheduler
    from usdfiber.farm.shard_spec import ShardSpecError, parse_shard

    if args.scheduler is not None and args.shard is not None:
        raise UsageError("--scheduler and --shard exclude each other: a shard runs in this process")
    if args.shard is not None:
        try:
            parse_shard(args.shard)
        except ShardSpecError as exc:
            raise UsageError(f"--shard: {exc}") from None
    if args.scheduler is not None:
        try:
            parse_scheduler(args.scheduler)
        except FarmError as exc:
            raise UsageError(str(exc)) from None
    if wants_farm(args):
        # No plots or compression there: tables are baked elsewhere (or in parts).
        if args.plot:
            raise UsageError("--plot writes figures next to tables baked here; not with --scheduler or --shard "
                             "(plot them afterwards with `usdfiber table plot TABLE --figure errors`)")
        if args.compress is not None:
            raise UsageError("--compress compresses tables baked here; not with --scheduler or --shard "
                             "(compress them afterwards with `usdfiber table compress --cache`)")


def _print_summary(summary: Any, as_json: bool) -> None:
    if as_json:
        print(summary.to_json(), flush=True)
        return
    for t in summary.tables:
        if t["status"] == "waiting":
            print(f"{t['key']}  {t['path']}  waiting for other shards ({t['missing_directions']} directions "
                  f"missing)  [{t['label']}]")
        elif "photons" in t:
            print(f"{t['key']}  {t['path']}  photons={t['photons']}  error={t['error_rms']:.4f} rms, "
                  f"{t['error_max']:.4f} max  {t['status']}  [{t['label']}]")
        else:
            print(f"{t['key']}  {t['path']}  {t['status']}  [{t['label']}]")
    tk = summary.tasks
    print(f"tasks: {tk['run']} run, {tk['skipped']} already done, {tk['retries']} retried, {tk['failed']} failed; "
          f"{summary.times.get('total', 0.0):.1f} s", flush=True)


def _run_local(reqs: list, settings: Any, cache: Any, show: bool) -> Any:
    """``--json`` without a farm: the tables one after another in this process."""
    import time

    from usdfiber.farm.progress import FarmProgress, FarmSummary
    from usdfiber.farm.tasks import table_jobs

    t0 = time.perf_counter()
    summary = FarmSummary(engine="local")
    jobs = table_jobs(reqs, settings, cache)
    bar = FarmProgress(len(jobs), unit="table", desc="bake", show=show)
    for job in jobs:
        res = cache.get_or_bake(job.request, settings)
        err = res.table.header.get("error_estimate", {})
        summary.tables.append({"key": job.key, "label": job.label, "path": str(res.path),
                               "status": "cached" if not res.baked else "baked",
                               "resumed_directions": int(res.resumed),
                               "photons": int(res.table.arrays["photons"].sum()),
                               "error_rms": float(err.get("rms", float("nan"))),
                               "error_max": float(err.get("max", float("nan"))), "seconds": res.seconds,
                               "prims": job.request.prims[:16]})
        bar.advance(1)
    summary.times["bake"] = bar.close()
    summary.times["total"] = time.perf_counter() - t0
    return summary


def run_bake(args: argparse.Namespace, reqs: list, settings: Any, cache: Any) -> int:
    """Run ``usdfiber bake`` with farm options (see the module docstring)."""
    from usdfiber.cli import UsageError
    from usdfiber.farm.cluster import FarmError, LocalFarm
    from usdfiber.farm.shard_spec import parse_shard
    from usdfiber.farm.tasks import TASK_PHOTONS

    check_farm_options(args)
    task_photons = args.task_photons or TASK_PHOTONS
    show = not args.no_progress
    try:
        if args.shard:
            from usdfiber.farm.shards import bake_shard

            summary = bake_shard(reqs, settings, cache, parse_shard(args.shard), task_photons=task_photons,
                                 show_progress=show)
        elif args.scheduler:
            from usdfiber.farm.dask_bake import bake_on_dask

            with LocalFarm(args.scheduler) as farm:
                summary = bake_on_dask(farm.client, reqs, settings, cache, task_photons=task_photons,
                                       show_progress=show)
        else:
            summary = _run_local(reqs, settings, cache, show)
    except FarmError as exc:
        raise UsageError(str(exc)) from None
    _print_summary(summary, args.json)   # failures were printed on stderr as they happened
    return 0 if summary.ok else 1
