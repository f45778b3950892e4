"""Frame sequences: ``usdfiber render STAGE --frames 1001-1100 -o shot.####.exr``.

Each frame is one :func:`~usdfiber.translators.mitsuba.render.render_stage` at its time code
(time-sampled transforms, curves, dyes and depths of shade evaluated per frame; tables
recoloured per frame, never re-traced), written to the output pattern with the frame number
(:mod:`usdfiber.farm.frames`). A frame whose EXR already exists and reads back is skipped, so
a rerun renders only what is missing or damaged. Frames run here one after another, on a Dask
cluster (``scheduler``: one task per frame, the tables first baked on the cluster), or as a
shard (``shard``: the frames ``j mod N = I - 1`` of the sequence). A failed frame is reported
with its error and the others go on.
"""
from __future__ import annotations

import os
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable, Sequence, TextIO

from usdfiber.farm.frames import frame_path, has_frame_token
from usdfiber.farm.progress import FarmFailure, FarmProgress, FarmSummary

from usdfiber.translators.mitsuba.errors import RenderRefused
from usdfiber.translators.mitsuba.render import RenderJob, render_stage

__all__ = ["frame_jobs", "render_frame", "render_sequence", "run_sequence_command"]


def frame_jobs(job: RenderJob, frames: Sequence[int]) -> list[RenderJob]:
    """One job per frame: ``job`` at that time code, its output (and PNG) patterns numbered."""
    if len(frames) > 1 and not has_frame_token(job.output):
        raise RenderRefused(f"--output {job.output}: a sequence of {len(frames)} frames needs a frame "
                            f"placeholder in the file name, e.g. shot.####.exr")
    out = []
    for f in frames:
        exr = frame_path(job.output, f) if has_frame_token(job.output) else Path(job.output)
        png = None
        if job.png is not None:
            png = frame_path(job.png, f) if has_frame_token(job.png) else exr.with_suffix(".png")
        out.append(replace(job, frame=float(f), output=exr, png=png, progress=False))
    return out


def _done(path: Path) -> bool:
    """Whether a frame's EXR exists and reads back (a damaged one is rendered again)."""
    from usdfiber import image_output

    if not path.exists():
        return False
    try:
        image_output.read_exr(path)
        return True
    except Exception:  # noqa: BLE001 - unreadable: render it again
        return False


def render_frame(job: RenderJob, summarize: Callable[[str, Any], dict[str, Any]] | None = None) -> dict[str, Any]:
    """Render one frame (on a Dask worker or here); what was written and how long it took.

    ``summarize(stage, result)``: the single-frame summary (``render --json``'s), kept under
    ``"render"``; a module-level function, so that Dask can send it to the workers.
    """
    from usdfiber.farm.cluster import TASK_LOCK

    try:
        from distributed import get_worker

        from usdfiber.farm.progress import EVENT_TOPIC

        get_worker().log_event(EVENT_TOPIC, {"event": "start", "task": f"frame-{job.frame:g}"})
    except (ImportError, ValueError):
        pass
    t0 = time.perf_counter()
    with TASK_LOCK, open(os.devnull, "w") as quiet:
        res = render_stage(job, log=quiet)
    out = {"frame": job.frame, "path": str(job.output), "status": "rendered", "seconds": time.perf_counter() - t0,
           "render_seconds": res.times.get("render", 0.0), "host": os.uname().nodename, "warnings": res.warnings[:8]}
    if summarize is not None:
        out["render"] = summarize(str(job.stage), res)
    return out


def render_sequence(job: RenderJob, frames: Sequence[int], *, scheduler: str | None = None, shard: Any = None,
                    show_progress: bool = True, log: TextIO | None = None,
                    summarize: Callable[[str, Any], dict[str, Any]] | None = None) -> FarmSummary:
    """Render ``frames`` of ``job`` (see the module docstring); the summary lists every frame
    (with ``summarize``'s single-frame summary of each rendered one, see :func:`render_frame`)."""
    log = log or sys.stderr
    t0 = time.perf_counter()
    jobs = frame_jobs(job, frames)
    summary = FarmSummary(engine="dask" if scheduler else ("shard" if shard else "local"),
                          shard=str(shard) if shard else None)
    if shard is not None:
        jobs = shard.select(jobs)
    todo = []
    for j in jobs:
        if _done(Path(j.output)):
            summary.frames.append({"frame": j.frame, "path": str(j.output), "status": "skipped"})
        else:
            todo.append(j)
    summary.tasks.update(total=len(jobs), skipped=len(jobs) - len(todo))
    bar = FarmProgress(len(jobs), initial=len(jobs) - len(todo), unit="frame", desc="frames",
                       show=show_progress, file=log)

    def failed(j: RenderJob, where: str, exc: BaseException) -> None:
        f = FarmFailure(f"frame {j.frame:g}", where, " ".join(str(exc).split())[:500])
        summary.failures.append(f)
        summary.frames.append({"frame": j.frame, "path": str(j.output), "status": "failed", "error": f.error})
        bar.log(f"usdfiber: error: {f.line()}")

    if scheduler and todo:
        _on_dask(scheduler, todo, summary, bar, failed, summarize)
    else:
        for j in todo:
            try:
                summary.frames.append(render_frame(j, summarize))
                summary.tasks["run"] += 1
            except RenderRefused as exc:
                failed(j, os.uname().nodename, exc)
            bar.advance(1)
    summary.times["frames"] = bar.close()
    summary.frames.sort(key=lambda d: d["frame"])
    summary.tasks["failed"] = len(summary.failures)
    summary.ok = not summary.failures
    summary.times["total"] = time.perf_counter() - t0
    return summary


def _on_dask(scheduler: str, todo: list[RenderJob], summary: FarmSummary, bar: FarmProgress, failed: Any,
             summarize: Callable[[str, Any], dict[str, Any]] | None) -> None:
    """Bake the frames' tables on the cluster, then one task per frame."""
    from distributed import as_completed

    from usdfiber.bake.cache import TableCache
    from usdfiber.bake.requests import tables_for_stage
    from usdfiber.farm.cluster import FarmError, LocalFarm
    from usdfiber.farm.dask_bake import bake_on_dask
    from usdfiber.stage_io import open_stage

    from usdfiber.translators.mitsuba.scene import bake_settings_for, render_bake

    choice = render_bake(todo[0].bake_resolution_deg, todo[0].bake_photons)
    stage = open_stage(todo[0].stage)
    # The render's settings are per fiber: one cluster bake per distinct settings.
    by_settings: dict[Any, list[Any]] = {}
    for r in (r for j in todo for r in tables_for_stage(stage, j.frame)):
        by_settings.setdefault(bake_settings_for(choice, r), []).append(r)
    with LocalFarm(scheduler) as farm:
        summary.scheduler = farm.address
        summary.tables = []
        for st, reqs in by_settings.items():
            baked = bake_on_dask(farm.client, reqs, st, TableCache(), show_progress=False)
            summary.tables.extend(baked.tables)
            if not baked.ok:
                raise FarmError(f"the tables could not be baked: {baked.failures[0].line()}")
        futs = {farm.client.submit(render_frame, j, summarize, key=_frame_key(j), retries=1, pure=False): j for j in todo}
        summary.workers = len(farm.client.scheduler_info().get("workers", {}))
        for fut in as_completed(list(futs)):
            j = futs[fut]
            if fut.status == "error":
                failed(j, "a Dask worker", fut.exception())
            elif fut.status != "finished":
                raise FarmError(f"lost the Dask scheduler {summary.scheduler}; rendered frames are kept: run again")
            else:
                summary.frames.append(fut.result())
                summary.tasks["run"] += 1
            bar.advance(1)


def _frame_key(job: RenderJob) -> str:
    """The Dask key of a frame: equal in every client for the same stage, frame and output."""
    import hashlib

    digest = hashlib.sha256(f"{Path(job.stage).absolute()}\0{job.frame!r}\0{Path(job.output).absolute()}"
                            .encode()).hexdigest()[:24]
    return f"usdfiber-frame-{job.frame:g}-{digest}"


def run_sequence_command(args: Any, job: RenderJob,
                         summarize: Callable[[str, Any], dict[str, Any]] | None = None) -> int:
    """``usdfiber render --frames`` (with ``--scheduler``, ``--shard``, ``--json``); the exit status.
    ``summarize``: the single-frame ``--json`` summary, given to each frame's entry."""
    from usdfiber.cli import UsageError
    from usdfiber.farm.cluster import FarmError
    from usdfiber.farm.frames import FrameSpecError, parse_frames
    from usdfiber.farm.shard_spec import ShardSpecError, parse_shard

    if args.frame is not None:
        raise UsageError("--frame and --frames exclude each other")
    if args.scheduler and args.shard:
        raise UsageError("--scheduler and --shard exclude each other: a shard runs in this process")
    try:
        frames = parse_frames(args.frames)
        shard = parse_shard(args.shard) if args.shard else None
        frame_jobs(job, frames)   # checks the output pattern before anything runs
    except (FrameSpecError, ShardSpecError, RenderRefused) as exc:
        raise UsageError(f"{exc}") from None
    try:
        summary = render_sequence(job, frames, scheduler=args.scheduler, shard=shard,
                                  show_progress=not args.no_progress, summarize=summarize)
    except FarmError as exc:
        raise UsageError(str(exc)) from None
    if args.json:
        print(summary.to_json())
    else:
        for f in summary.frames:
            print(f"frame {f['frame']:g}: {f['status']}  {f['path']}")
        tk = summary.tasks
        print(f"frames: {tk['run']} rendered, {tk['skipped']} already there, {tk['failed']} failed; "
              f"{summary.times.get('total', 0.0):.1f} s")
    return 0 if summary.ok else 1
