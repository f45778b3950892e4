"""Render a USD stage with Mitsuba 3 and the tabulated fiber BCSDF (:func:`render_stage`).

Steps, each timed: validate the stage (the checks of ``usdfiber check``; errors refuse the
render), estimate what the missing fiber tables will cost to bake (a probe of each fiber,
:mod:`usdfiber.bake.cost`; printed before baking starts), resolve the fiber tables (baking
missing ones, with progress), translate
(:mod:`usdfiber.translators.mitsuba.scene`), render in passes (progress and time left), write a
linear EXR with metadata and a display-referred PNG (:mod:`usdfiber.image_output`).

Passes: the samples per pixel are split into passes of at most ``pass_spp`` samples, each
with its own seed; the image is their sample-weighted mean, identical in distribution to
one render with all the samples.
"""
from __future__ import annotations

import os
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, TextIO

import numpy as np

from usdfiber import image_output
from usdfiber.bake.settings import BakeError
from usdfiber.memory_budget import MemoryBudget, MemoryBudgetError
from usdfiber.stage_io import StageOpenError, open_stage
from usdfiber.validation.runner import check_stage, format_problem

from usdfiber.translators.mitsuba.device import select_device
from usdfiber.translators.mitsuba.errors import RenderRefused, TranslateError
from usdfiber.translators.mitsuba.scene import AOVS, SceneOptions, bake_settings_for, render_bake, translate_stage
from usdfiber.translators.mitsuba.table_plan import PlannedTableCache
from usdfiber.translators.mitsuba.yarn_far_field import YarnBakeSettings

__all__ = ["RenderJob", "RenderRefused", "RenderResult", "render_stage"]


@dataclass
class RenderJob:
    """Everything a render needs (see ``usdfiber render --help``)."""

    stage: str
    output: Path
    png: Path | None = None                 # None: no display image
    frame: float | None = None
    resolution: tuple[int, int] | None = None
    spp: int | None = None
    camera: str | None = None
    render_settings: str | None = None
    device: str = "cpu"
    threads: int | None = None
    seed: int = 0
    max_depth: int = 32
    purposes: tuple[str, ...] | None = None
    bake_resolution_deg: float | None = None
    bake_photons: int | None = None
    bake_missing: bool = True
    pass_spp: int = 16
    lod_scale: float = 1.0
    cloth: str = "fibers"                   # fibers | volume | auto (volume/scene.py)
    yarn_resolution_deg: float | None = None
    yarn_photons: int | None = None
    half: bool = True
    view: str | None = None
    display: str | None = None
    ocio_config: str | None = None
    exposure: float = 0.0
    progress: bool = True
    warnings_as_errors: bool = False
    memory_budget: str | None = None        # --memory-budget; None: $USDFIBER_MEMORY_BUDGET or the default
    aovs: tuple[str, ...] = ()              # --aov: layers of scene.AOVS written after R, G, B, A
    model: str = "table"                    # --model: table | chiang | khungurn (fitted_models.py)


@dataclass
class RenderResult:
    """A finished render: the linear image (H, W, 3), the time of each step, the scene's counts,
    the warnings, and what was rendered and written."""

    image: np.ndarray
    times: dict[str, float]
    counts: dict[str, int]
    warnings: list[str]
    camera: str
    spp: int
    resolution: tuple[int, int]
    files: list[Path] = field(default_factory=list)
    alpha: np.ndarray | None = None         # (H, W) coverage, 0 where camera rays met nothing
    aovs: dict[str, np.ndarray] = field(default_factory=dict)  # layer -> (H, W, C), scene.AOVS order
    bakes: list[dict[str, Any]] = field(default_factory=list)  # estimates of the tables baked on demand
    far_fields: list[dict[str, Any]] = field(default_factory=list)  # yarn far fields: traced, cached, skipped, why


def _validate(stage: Any, path: str, frame: float | None, strict: bool) -> list[str]:
    # The bridge's own refusals come from the translation itself (the same functions).
    report = check_stage(stage, time=frame, bridges=False)
    if report.errors or (strict and report.warnings):
        raise RenderRefused(f"{path}: the stage does not pass `usdfiber check`; not rendering:\n"
                            + report.to_text())
    return [format_problem(p) for p in report.warnings]


def render_stage(job: RenderJob, log: TextIO | None = None,
                 bake_progress: Callable[..., Any] | None = None) -> RenderResult:
    """Run the whole render (see the module docstring); raises RenderRefused with a readable message.
    ``log`` (default: ``sys.stderr`` at the time of the call) gets the bake estimates."""
    log = sys.stderr if log is None else log
    times: dict[str, float] = {}
    t0 = time.perf_counter()
    try:
        budget = MemoryBudget.resolve(job.memory_budget)
        # Before anything long: a render that cannot be written is refused now, not after.
        for target in (job.output, job.png):
            if target is not None:
                image_output.check_writable(target)
    except (image_output.ImageOutputError, MemoryBudgetError) as exc:
        raise RenderRefused(str(exc)) from None
    mi = select_device(job.device, job.threads)
    try:
        stage = open_stage(job.stage)
    except StageOpenError as exc:
        raise RenderRefused(str(exc)) from None
    warnings = _validate(stage, job.stage, job.frame, job.warnings_as_errors)
    times["validate"] = time.perf_counter() - t0

    try:
        bake = render_bake(job.bake_resolution_deg, job.bake_photons)
        yarn_bake = YarnBakeSettings()
        if job.yarn_resolution_deg is not None:
            yarn_bake = replace(yarn_bake, resolution_deg=float(job.yarn_resolution_deg))
        if job.yarn_photons is not None:
            yarn_bake = replace(yarn_bake, photons=int(job.yarn_photons))
    except (BakeError, ValueError) as exc:
        raise RenderRefused(str(exc)) from None
    # The cache lookups made for the estimates serve the translation's (table_plan.py).
    cache = PlannedTableCache()
    bakes = _bake_estimates(stage, job, bake, log, cache) if job.bake_missing else []
    opts = SceneOptions(time=job.frame, resolution=job.resolution, spp=job.spp, camera=job.camera,
                        render_settings=job.render_settings, seed=job.seed, max_depth=job.max_depth,
                        purposes=job.purposes, bake=bake, bake_missing=job.bake_missing, cache=cache,
                        lod_scale=job.lod_scale, yarn_bake=yarn_bake, cloth=job.cloth,
                        memory_budget=budget, alpha=True, aovs=tuple(job.aovs), model=job.model)
    try:
        tr = translate_stage(stage, opts, progress=bake_progress)
    except (TranslateError, ValueError, BakeError) as exc:  # MemoryBudgetError too
        raise RenderRefused(" ".join(str(exc).split()) if "\n" not in str(exc) else str(exc)) from None
    warnings.extend(tr.warnings)
    times["tables"] = tr.times.get("tables", 0.0)
    times["translate"] = tr.times.get("translate", 0.0)

    # ---- render in passes -------------------------------------------------------------------
    import drjit as dr
    from tqdm import tqdm

    t1 = time.perf_counter()
    spp = tr.spp
    passes = [min(job.pass_spp, spp - k) for k in range(0, spp, max(1, job.pass_spp))]
    acc = None
    bar = tqdm(total=spp, unit="spp", desc="render", file=log, disable=not job.progress, dynamic_ncols=True)
    for k, n in enumerate(passes):
        img = mi.render(tr.scene, spp=n, seed=job.seed * 100_003 + k)
        dr.eval(img)
        arr = np.array(img, dtype=np.float64) * n        # R, G, B, A, then the AOVs
        acc = arr if acc is None else acc + arr
        bar.update(n)
    bar.close()
    channels = (acc / spp).astype(np.float32)
    image = np.ascontiguousarray(channels[..., :3])
    alpha = np.ascontiguousarray(channels[..., 3])
    layers: dict[str, np.ndarray] = {}
    c0 = 4
    for name in job.aovs:
        n_ch = len(AOVS[name][1])
        layers[name] = np.ascontiguousarray(channels[..., c0:c0 + n_ch])
        c0 += n_ch
    times["render"] = time.perf_counter() - t1

    # ---- write ------------------------------------------------------------------------------
    t2 = time.perf_counter()
    meta: dict[str, Any] = {
        "stage": os.path.abspath(job.stage), "camera": tr.camera, "spp": int(spp),
        "frame": "default" if tr.time is None else float(tr.time), "device": job.device,
        "variant": mi.variant(), "seed": int(job.seed), "max_depth": int(job.max_depth),
        "fiber_curves": int(tr.counts.get("fiber_curves", 0)),
        "fiber_segments": int(tr.counts.get("fiber_segments", 0)),
        "time_tables_s": float(times["tables"]), "time_translate_s": float(times["translate"]),
        "time_render_s": float(times["render"]),
    }
    nonfinite = ~np.isfinite(image)
    if nonfinite.any():
        raise RenderRefused(f"{job.stage}: the render produced {int(nonfinite.any(axis=-1).sum())} "
                            f"pixels that are NaN or infinite; not writing {job.output}")
    files = []
    try:
        extra = {"A": alpha, **layers}
        names = {"A": ("A",), **{a: AOVS[a][1] for a in layers}}
        image_output.write_exr(job.output, image, meta, half=job.half, extra_channels=extra, channel_names=names)
        files.append(Path(job.output))
        if job.png is not None:
            kw: dict[str, Any] = {"exposure_stops": job.exposure, "config": job.ocio_config}
            if job.view:
                kw["view"] = job.view
            if job.display:
                kw["display"] = job.display
            image_output.write_display_png(job.png, image, metadata={"stage": meta["stage"],
                                                                      "camera": tr.camera}, **kw)
            files.append(Path(job.png))
    except image_output.ImageOutputError as exc:
        raise RenderRefused(str(exc)) from None
    times["write"] = time.perf_counter() - t2
    times["total"] = time.perf_counter() - t0
    return RenderResult(image=image, alpha=alpha, aovs=layers, times=times, counts=tr.counts, warnings=warnings,
                        camera=tr.camera,
                        spp=spp, resolution=tr.resolution, files=files, bakes=bakes,
                        far_fields=list(tr.fibers.far_fields) if tr.fibers is not None else [])


def _bake_estimates(stage: Any, job: RenderJob, bake: Any, log: TextIO,
                    cache: PlannedTableCache) -> list[dict[str, Any]]:
    """The estimated cost of each fiber table the render will bake (none serves it in
    ``cache``, which keeps its lookups for the translation), printed on ``log`` before any
    is baked; [] when the stage's fibers cannot be read (the translation reports why)."""
    from pxr import Usd

    from usdfiber.bake.cost import estimate_request, format_seconds, total
    from usdfiber.bake.requests import tables_for_stage
    from usdfiber.memory_budget import format_bytes

    try:
        reqs = tables_for_stage(stage, Usd.TimeCode(job.frame) if job.frame is not None else None)
        missing = cache.plan(reqs, lambda r: bake_settings_for(bake, r))
        estimates = [estimate_request(r, bake_settings_for(bake, r), cache) for r in missing]
    except (BakeError, ValueError):
        return []
    for e in estimates:
        print(f"tables: to bake {e.label}: {e.describe()}", file=log)
    if len(estimates) > 1:
        t = total(estimates)
        print(f"tables: {t['tables']} to bake, about {format_seconds(t['seconds'])} on this machine, "
              f"{format_bytes(t['disk_bytes'])} on disk", file=log)
    return [e.to_json() for e in estimates]
