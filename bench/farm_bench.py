"""Farm bakes: overhead per task, 1 -> 2 local Dask workers, and a model of a 100-worker farm.

    python bench/farm_bench.py [--reps 3] [--out bench/results/farm.json]

Measured here (each figure with the machine's load average next to it):

1. Dask's own cost per task: independent no-op tasks through a ``local:1`` cluster.
2. usdfiber's fixed cost per trace task: :func:`run_trace_task` on a task whose chunks all
   exist (probe, bake context, verifying each chunk), per task.
3. The trace rate of one worker at the modelled settings (the paper's 2 degrees with 1M
   photons per direction; the renderer's 6 degrees with 100k): three slices of directions
   traced in this process, their spread as the error.
4. 1 vs 2 local workers: the same coarse bake on ``local:1`` and ``local:2``, alternated
   ``--reps`` times in one run (a ratio measured side by side, so shared-machine load hits
   both), with the spread of the ratios.
5. The assembly: seconds per direction and per bin of the coarse table.
6. One frame of a small animated stage (time to first image once tables exist).

Modelled from those (nothing at full size is run): a 100-worker farm baking the paper's
2 degree silk table (1M photons per direction) and a 5-variant garment (five such tables),
and the time to the first image of a 100-frame sequence. A worker in the model is one
worker of this machine (its cores); a farm node with more cores scales the trace terms.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "bench"))

from bench_common import json_default, machine, md_table  # noqa: E402

COARSE = dict(resolution_deg=15.0, photons=8_000, batches=4)


def load() -> float:
    return round(os.getloadavg()[0], 2)


def mean_err(xs: list[float]) -> tuple[float, float]:
    """Mean and its standard error (0 with one sample)."""
    m = statistics.fmean(xs)
    return m, (statistics.stdev(xs) / math.sqrt(len(xs)) if len(xs) > 1 else 0.0)


def make_stage(path: Path, frames: int = 0) -> Path:
    """One silk fiber curve (one table); with ``frames``, moving and with an animated depth of shade."""
    import usdfiber  # noqa: F401
    from pxr import Usd, UsdGeom

    from usdfiber import authoring

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    c = UsdGeom.BasisCurves.Define(stage, "/World/Silk")
    c.CreateCurveVertexCountsAttr([4, 4])
    c.CreateWidthsAttr([0.02])
    c.SetWidthsInterpolation(UsdGeom.Tokens.constant)
    pts = c.CreatePointsAttr()
    for t in range(1, max(1, frames) + 1):
        dx = 0.1 * t
        pts.Set([(dx, 0, 0), (dx + 1, 0.2, 0), (dx + 2, 0, 0), (dx + 3, 0.2, 0),
                 (dx, 0.5, 0), (dx + 1, 0.7, 0), (dx + 2, 0.5, 0), (dx + 3, 0.7, 0)], t)
    authoring.apply_fiber(c.GetPrim(), "silk", variant_count=1, dye="disperseRed", depth_of_shade=1.0)
    stage.GetRootLayer().Save()
    return path


def noop(i: int) -> int:
    return i


def dask_overhead(n: int = 300) -> dict:
    """Seconds per no-op task through a local:1 cluster (submit to result, all at once)."""
    from usdfiber.farm.cluster import LocalFarm

    with LocalFarm("local:1") as farm:
        farm.client.gather(farm.client.map(noop, range(10), pure=False))   # warm up
        out = []
        for _ in range(3):
            la = load()
            t0 = time.perf_counter()
            farm.client.gather(farm.client.map(noop, range(n), pure=False))
            out.append(((time.perf_counter() - t0) / n, la))
    m, e = mean_err([x for x, _ in out])
    return {"seconds_per_task": m, "error": e, "tasks": n, "repeats": len(out), "load": [la for _, la in out]}


def trace_and_overheads(req, tmp: Path, task_photons: int) -> dict:
    """Trace tasks in this process (rate), then the same tasks again (fixed cost), then the assembly."""
    from usdfiber.bake.cache import TableCache
    from usdfiber.bake.settings import BakeSettings
    from usdfiber.farm.tasks import assemble_table, plan_tasks, run_trace_task, table_jobs

    st = BakeSettings(**COARSE)
    cache = TableCache(tmp / "inproc")
    job = table_jobs([req], st, cache)[0]
    tasks = plan_tasks([job], task_photons)
    rates, la0 = [], load()
    for t in tasks:
        r = run_trace_task(job, t, str(cache.root))
        rates.append(r["photons"] / r["seconds"])
    fixed = []
    for t in tasks:
        t0 = time.perf_counter()
        run_trace_task(job, t, str(cache.root))       # every chunk exists: the fixed cost only
        fixed.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    res = assemble_table(job, str(cache.root))
    asm = time.perf_counter() - t0
    from usdfiber.bake.table import BcsdfTable

    tab = BcsdfTable.load(res["path"])
    n_dirs = int(tab.arrays["photons"].size)
    g = tab.header["resolution"]
    bins = int(g["theta_o"] * g["phi_o"])
    rate, rate_e = mean_err(rates)
    fx, fx_e = mean_err(fixed)
    return {"tasks": len(tasks), "directions": n_dirs, "photons_per_direction": st.photons,
            "rate_photons_per_s": rate, "rate_error": rate_e, "task_fixed_s": fx, "task_fixed_error": fx_e,
            "assembly_s": asm, "assembly_s_per_direction_bin": asm / (n_dirs * bins), "bins": bins,
            "load_start": la0, "load_end": load()}


def rate_at(req, tmp: Path, st, n_dirs: int, name: str) -> dict:
    """Photons/s of one worker tracing ``st``'s photons per direction: three slices of
    ``n_dirs`` directions (low, middle and grazing theta_i) of the table, each one task."""
    from usdfiber.bake.cache import TableCache
    from usdfiber.farm.tasks import TraceTask, plan_tasks, run_trace_task, table_jobs

    cache = TableCache(tmp / f"rate-{name}")
    job = table_jobs([req], st, cache)[0]
    dirs = [d for t in plan_tasks([job]) for d in t.directions]
    rates, loads = [], []
    for start in (0, len(dirs) // 2, len(dirs) - n_dirs):
        t = TraceTask(job.key, 0, 1, tuple(dirs[start:start + n_dirs]))
        loads.append(load())
        r = run_trace_task(job, t, str(cache.root))
        rates.append(r["photons"] / r["seconds"])
    m, e = mean_err(rates)
    return {"photons_per_direction": st.photons, "resolution_deg": st.resolution_deg, "directions": n_dirs,
            "rate_photons_per_s": m, "rate_error": e, "load": loads}


def scaling(reqs, tmp: Path, task_photons: int, reps: int) -> dict:
    """The coarse bake on local:1 and local:2, alternated; wall times and their ratios."""
    from usdfiber.bake.cache import TableCache
    from usdfiber.bake.settings import BakeSettings
    from usdfiber.farm.cluster import LocalFarm
    from usdfiber.farm.dask_bake import bake_on_dask

    st = BakeSettings(**COARSE)
    walls: dict[int, list[tuple[float, float]]] = {1: [], 2: []}
    with LocalFarm("local:1") as f1, LocalFarm("local:2") as f2:
        for rep in range(reps):
            for n, farm in ((1, f1), (2, f2)) if rep % 2 == 0 else ((2, f2), (1, f1)):
                cache = TableCache(tmp / f"scale-{n}-{rep}")
                la = load()
                t0 = time.perf_counter()
                s = bake_on_dask(farm.client, reqs, st, cache, task_photons=task_photons, show_progress=False)
                assert s.ok, s.to_json()
                walls[n].append((time.perf_counter() - t0, la))
    ratios = [a[0] / b[0] for a, b in zip(walls[1], walls[2])]
    r, r_e = mean_err(ratios)
    return {"wall_s": {str(n): [w for w, _ in v] for n, v in walls.items()},
            "load": {str(n): [la for _, la in v] for n, v in walls.items()},
            "speedup_1_to_2": r, "speedup_error": r_e, "reps": reps}


def first_frame(tmp: Path) -> dict:
    """Seconds to render one frame of a small animated stage whose tables are cached."""
    from usdfiber.translators.mitsuba.render import RenderJob
    from usdfiber.translators.mitsuba.sequence import render_frame

    stage = make_stage(tmp / "anim.usda", frames=4)
    job = RenderJob(stage=str(stage), output=tmp / "f.0001.exr", frame=1.0, resolution=(320, 180), spp=16,
                    bake_resolution_deg=COARSE["resolution_deg"], bake_photons=COARSE["photons"], progress=False)
    render_frame(job)                                   # bakes its table, compiles the kernels
    out = []
    for f in (2, 3):
        la = load()
        r = render_frame(RenderJob(**{**job.__dict__, "frame": float(f), "output": tmp / f"f.{f:04d}.exr"}))
        out.append((r["seconds"], la))
    m, e = mean_err([x for x, _ in out])
    return {"seconds": m, "error": e, "resolution": [320, 180], "spp": 16, "load": [la for _, la in out]}


def farm_model(m: dict, workers: int = 100) -> dict:
    """A ``workers``-worker farm from the measured rate and overheads (see the module docstring)."""
    from usdfiber.bake.baker import table_directions
    from usdfiber.bake.settings import RENDER_BAKE_SETTINGS, BakeSettings
    from usdfiber.farm.tasks import TASK_PHOTONS, directions_per_task

    req, tr, dk = m["request"], m["trace"], m["dask"]

    def bake(st: BakeSettings, tables: int, rate: dict) -> dict:
        dirs = len(table_directions(req, st))
        per = directions_per_task(st, TASK_PHOTONS)
        tasks = tables * math.ceil(dirs / per)
        task_s = per * st.photons / rate["rate_photons_per_s"] + tr["task_fixed_s"]
        rel = rate["rate_error"] / rate["rate_photons_per_s"]
        waves = math.ceil(tasks / workers)
        bins = (180 / st.resolution_deg) * (360 / st.resolution_deg)   # theta_o x phi_o bins
        asm = dirs * bins * tr["assembly_s_per_direction_bin"]
        # Tables assemble in parallel (one task each); the scheduler hands out tasks serially.
        total = waves * task_s + tasks * dk["seconds_per_task"] + math.ceil(tables / workers) * asm
        one = tables * (dirs * st.photons / rate["rate_photons_per_s"]) + tables * asm
        return {"tables": tables, "directions_per_table": dirs, "tasks": tasks, "task_s": task_s,
                "waves": waves, "assembly_s": asm, "farm_s": total, "farm_error_s": total * rel,
                "one_worker_s": one, "speedup": one / total, "busy_fraction": tasks / (waves * workers)}

    paper = BakeSettings()
    silk = bake(paper, 1, m["rate_paper"])
    garment = bake(paper, 5, m["rate_paper"])
    render_tables = bake(RENDER_BAKE_SETTINGS, 1, m["rate_render"])
    first = dk["connect_s"] + render_tables["farm_s"] + m["frame"]["seconds"]
    return {"workers": workers, "silk_2deg": silk, "garment_5_variants": garment,
            "render_quality_table": render_tables,
            "first_image_of_100_frames_s": first,
            "first_image_error_s": math.hypot(render_tables["farm_error_s"], m["frame"]["error"]),
            "all_100_frames_s": dk["connect_s"] + render_tables["farm_s"]
            + math.ceil(100 / workers) * m["frame"]["seconds"] + 100 * dk["seconds_per_task"]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "farm.json")
    args = ap.parse_args()
    from usdfiber.bake.requests import tables_for_stage
    from usdfiber.stage_io import open_stage

    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="farm-bench-") as d:
        tmp = Path(d)
        os.environ["USDFIBER_CACHE_DIR"] = str(tmp / "render-cache")
        stage = make_stage(tmp / "silk.usda")
        reqs = tables_for_stage(open_stage(str(stage)))
        m: dict = {"machine": machine(), "settings": COARSE}
        t0 = time.perf_counter()
        from usdfiber.farm.cluster import LocalFarm

        with LocalFarm("local:1"):
            pass
        connect_s = time.perf_counter() - t0
        m["dask"] = dask_overhead()
        m["dask"]["connect_s"] = connect_s
        print(f"dask: {m['dask']['seconds_per_task'] * 1e3:.2f} +- {m['dask']['error'] * 1e3:.2f} ms per task, "
              f"start of local:1 {connect_s:.1f} s (load {m['dask']['load']})", flush=True)
        task_photons = 8 * COARSE["photons"]
        m["trace"] = trace_and_overheads(reqs[0], tmp, task_photons)
        tr = m["trace"]
        print(f"trace: {tr['rate_photons_per_s'] / 1e6:.3f} +- {tr['rate_error'] / 1e6:.3f} M photons/s over "
              f"{tr['tasks']} tasks; fixed cost {tr['task_fixed_s']:.3f} +- {tr['task_fixed_error']:.3f} s per task; "
              f"assembly {tr['assembly_s']:.2f} s for {tr['directions']} directions "
              f"(load {tr['load_start']} -> {tr['load_end']})", flush=True)
        from usdfiber.bake.settings import RENDER_BAKE_SETTINGS, BakeSettings

        for name, st, n in (("paper", BakeSettings(), 1), ("render", RENDER_BAKE_SETTINGS, 8)):
            m[f"rate_{name}"] = r = rate_at(reqs[0], tmp, st, n, name)
            print(f"trace at {st.resolution_deg:g} deg, {st.photons} photons/direction: "
                  f"{r['rate_photons_per_s'] / 1e6:.2f} +- {r['rate_error'] / 1e6:.2f} M photons/s "
                  f"(load {r['load']})", flush=True)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(m, indent=2, default=json_default))   # kept if a later part is cut short
        m["scaling"] = scaling(reqs, tmp, task_photons, args.reps)
        sc = m["scaling"]
        print(f"scaling: local:1 {sc['wall_s']['1']} s, local:2 {sc['wall_s']['2']} s; speedup "
              f"{sc['speedup_1_to_2']:.2f} +- {sc['speedup_error']:.2f} (load {sc['load']})", flush=True)
        m["frame"] = first_frame(tmp)
        print(f"frame: {m['frame']['seconds']:.2f} +- {m['frame']['error']:.2f} s at 320x180, 16 spp "
              f"(load {m['frame']['load']})", flush=True)
        m["request"] = reqs[0]
        model = farm_model(m)
        del m["request"]
        m["model"] = model
    rows = []
    for name in ("silk_2deg", "garment_5_variants", "render_quality_table"):
        x = model[name]
        rows.append([name, x["tables"], x["tasks"], f"{x['task_s']:.0f}", x["waves"], f"{x['assembly_s']:.0f}",
                     f"{x['farm_s']:.0f} +- {x['farm_error_s']:.0f}", f"{x['one_worker_s'] / 3600:.1f} h",
                     f"{x['speedup']:.0f}x"])
    print(md_table(["bake", "tables", "tasks", "s/task", "waves", "assembly s", "100 workers s",
                    "1 worker", "speedup"], rows))
    print(f"first image of a 100-frame sequence on 100 workers: {model['first_image_of_100_frames_s']:.0f} +- "
          f"{model['first_image_error_s']:.0f} s; all 100 frames {model['all_100_frames_s']:.0f} s")
    m["wall_s"] = time.perf_counter() - t_start
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(m, indent=2, default=json_default))
    print(f"wrote {args.out} ({m['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
