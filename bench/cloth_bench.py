"""Cloth benchmarks: yarn expansion at garment scale, and the image error of level of detail.

    python bench/cloth_bench.py             # full run, writes bench/results/cloth.json (17 min on 2 shared
                                            # cores with the former 3 LOD cameras; there are 4 now)
    python bench/cloth_bench.py --quick     # smoke test (1-2 min): small sizes, not a benchmark
    python bench/cloth_bench.py --parts lod --lod-res 200 --lod-spp 256 --out /tmp/lod.json
    python bench/cloth_bench.py report bench/results/cloth.json    # the markdown tables of a run

Every stage is built in memory with ``usdfiber.cloth`` (yarn centre lines with FiberYarnAPI,
polyester fibers: Table 3's ORA 120 or Skala 360, dyed disperseBlue 1 %), in millimetres, Z up,
over a grey card, with a perspective camera (36 mm aperture, 50 mm lens, 30 degrees from the
fabric normal) and the translator's default lights. Tables: polyester (round, one table),
baked once with coarse settings (``BakeSettings(resolution_deg=10, photons=20000,
batches=4)``) into ``--cache`` (default ``$USDFIBER_CACHE_DIR``, else
/tmp/usdfiber-cache-clothbench); table time is not part of any number below except "tables".

Each measurement runs in a fresh subprocess (``_worker``) so that its peak memory is its own:
``VmHWM`` from ``/proc/self/status`` (also read after building the stage, after translating and
after rendering). While it builds and translates the stage, the worker limits its data segment
(soft ``RLIMIT_DATA``, ``--mem-limit-gib``) so that a stage too big for the machine fails with
MemoryError instead of taking the machine's memory from other work (the limit is lifted for
rendering). The parent kills a worker whose RSS exceeds the limit by 2 GiB, and runs a worker
that dies from a signal once more (recorded under ``crashed_attempts``). The worker logs its
progress (stage, yarns expanded, RSS) to a file, so a failed run says how far it got. The
1-minute load average is recorded before and after every measurement (other work shares the
machine).

Parts:

* ``garment``: stages with thousands of yarn curves, each framed whole by its camera at 640 x 480,
  translated at ``lod_scale`` 1 (and 0 where ``--garment-full`` asks for it), rendered at
  ``--garment-spp`` (after a 1 spp warm-up that compiles the kernels). Reported: yarn curves,
  culled, fiber curves kept and at full detail, segments, peak memory, translate time split into
  tables / centre-line sampling / ``expand_yarn`` / rest of the yarn expansion (LOD, B-spline
  conversion) / USD read / reference normals / BSDF / curve shape / Mitsuba scene + BVH, and
  render time. For stages that cannot be translated, the segment counts are ESTIMATED by
  expanding one yarn of each distinct shape with the translator's own code (``expand_yarn`` at
  the LOD fraction that ``LodPolicy.fiber_fraction`` gives every yarn under the stage's camera).
* ``lod``: a small plain weave seen from 2-4 camera distances at ``--lod-res`` (near: yarns of
  8.4 px, mid: 4.7 px, whole: 2.8 px, far: 0.9 px at 160 px). Reference: ``lod_scale`` 0 (every
  fiber), translated once with the widest camera (nothing culled) and rendered from every
  camera. Then ``lod_scale`` 4, 2, 1, 0.5 with each camera (culling on), and the experiments
  (``--variants``: other values of ``translators.lod``'s constants, set in the worker).
  Every image is two independent halves (different seeds); their difference estimates the
  image's own noise. Error: relative RMSE over the cloth's pixels (all channels)
  ``d = sqrt(mean((img - ref)^2) / mean(ref^2))``, and the part of it that is not noise,
  ``bias = sqrt(max(0, d^2 - n_img^2 - n_ref^2))`` with ``n^2 = mean((half1 - half2)^2) / 4 /
  mean(ref^2)``; the same on 4 x 4 pixel blocks (noise / 4, bias kept); and the relative
  difference of the mean.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path
from typing import Any

import numpy as np
import bench_common  # noqa: E402
from bench_common import Timer, json_default as _json_default, md_table as _table, proc_status_mib  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

RESULTS = ROOT / "bench" / "results"
SOURCES = ("translators/mitsuba/lod.py", "usdfiber/geometry/yarn.py", "usdfiber/geometry/yarn_fibers.py",
           "usdfiber/geometry/yarn_flyaways.py", "usdfiber/spec/yarn.py", "translators/mitsuba/fibers.py",
           "usdfiber/geometry/curves.py", "translators/mitsuba/curves.py",
           "translators/mitsuba/scene.py", "translators/mitsuba/fiber_bsdf.py", "translators/mitsuba/fiber_bank.py", "usdfiber/cloth.py")
BAKE = {"resolution_deg": 10.0, "photons": 20_000, "batches": 4}
DEFAULT_CACHE = "/tmp/usdfiber-cache-clothbench"
DYE, DEPTH_OF_SHADE = "disperseBlue", 1.0
FOCAL_MM, APERTURE_MM, TILT_DEG = 50.0, 36.0, 30.0


# ---------------------------------------------------------------------------------------------
# Environment record
# ---------------------------------------------------------------------------------------------

def _load() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def machine() -> dict[str, Any]:
    return bench_common.machine()


def git_state() -> dict[str, Any]:
    return bench_common.git_state(ROOT, SOURCES, ("usdfiber", "translators"))


def _gib(mib: float | None) -> str:
    return "-" if mib is None else f"{mib / 1024:.2f}"


# ---------------------------------------------------------------------------------------------
# Stages
# ---------------------------------------------------------------------------------------------
# A spec (JSON-able dict) describes a stage:
#   kind: "weave" (one plain weave) or "swatches" (a card of tiles x tiles plain-weave swatches)
#   yarn, warps, wefts, tiles (swatches), gap_mm (between swatches)
#   res: [w, h]; cameras: {name: distance factor} (1 = frames the cloth whole with a 10 % margin)


def build_stage(spec: dict[str, Any]):
    """(stage, info) for ``spec``: the cloth, a grey card under it, and one camera per distance."""
    import usdfiber  # noqa: F401  (registers the schemas before any stage is opened)
    from pxr import Gf, Usd, UsdGeom

    from usdfiber import cloth

    stage = new_stage()
    UsdGeom.Xform.Define(stage, "/Cloth")
    kw = dict(yarn=spec["yarn"], dye=DYE, depth_of_shade=DEPTH_OF_SHADE)
    info: dict[str, Any] = {}
    if spec["kind"] == "weave":
        cloth.plain_weave(stage, "/Cloth/Weave", warps=spec["warps"], wefts=spec["wefts"], **kw)
        info["yarn_curves"] = spec["warps"] + spec["wefts"]
    elif spec["kind"] == "swatches":
        n = spec["tiles"]
        first = cloth.plain_weave(stage, "/Cloth/S_0_0", warps=spec["warps"], wefts=spec["wefts"], **kw)
        r = UsdGeom.BBoxCache(Usd.TimeCode.Default(), ["default", "render"]).ComputeWorldBound(first).ComputeAlignedRange()
        pitch = max(r.GetSize()[0], r.GetSize()[1]) + spec.get("gap_mm", 2.0)
        for i in range(n):
            for j in range(n):
                p = (first if i == j == 0 else
                     cloth.plain_weave(stage, f"/Cloth/S_{i}_{j}", warps=spec["warps"], wefts=spec["wefts"], **kw))
                if i or j:
                    UsdGeom.Xformable(p).AddTranslateOp().Set(Gf.Vec3d(i * pitch, j * pitch, 0.0))
        info["yarn_curves"] = n * n * (spec["warps"] + spec["wefts"])
        info["pitch_mm"] = pitch
    else:
        raise ValueError(spec["kind"])
    root = stage.GetPrimAtPath("/Cloth")
    rng = UsdGeom.BBoxCache(Usd.TimeCode.Default(), ["default", "render"]).ComputeWorldBound(root).ComputeAlignedRange()
    info.update(dress(stage, spec, np.array(rng.GetMin()), np.array(rng.GetMax())))
    return stage, info


def new_stage():
    """An empty in-memory stage in millimetres, Z up (the benchmarks' cloth stages)."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    UsdGeom.SetStageUpAxis(stage, "Z")
    return stage


def dress(stage: Any, spec: dict[str, Any], lo: np.ndarray, hi: np.ndarray) -> dict[str, Any]:
    """A grey card under the cloth box [lo, hi] (diffuse 0.5, 1.6 x the cloth) and the cameras
    of ``spec`` (30 degrees from the normal, looking at the centre; distance factor 1 frames the
    cloth whole with a 10 % margin)."""
    from pxr import Gf, UsdGeom, Vt

    from usdfiber import presets

    centre = 0.5 * (lo + hi)
    size = float(max(hi[0] - lo[0], hi[1] - lo[1]))
    diameter = presets.yarn_preset(spec["yarn"]).yarn_diameter_mm
    info: dict[str, Any] = {"cloth_size_mm": [float(hi[0] - lo[0]), float(hi[1] - lo[1])],
                            "yarn_diameter_mm": diameter, "cloth_lo": lo.tolist(), "cloth_hi": hi.tolist()}
    zc = float(lo[2] - 2.0 * diameter)
    half = 0.8 * size
    card = UsdGeom.Mesh.Define(stage, "/Card")
    card.CreatePointsAttr(Vt.Vec3fArray([Gf.Vec3f(float(centre[0] + sx * half), float(centre[1] + sy * half), zc)
                                         for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))]))
    card.CreateFaceVertexCountsAttr(Vt.IntArray([4]))
    card.CreateFaceVertexIndicesAttr(Vt.IntArray([0, 1, 2, 3]))
    card.CreateDisplayColorAttr(Vt.Vec3fArray([Gf.Vec3f(0.5, 0.5, 0.5)]))

    w, h = spec["res"]
    hfov = 2 * math.atan(APERTURE_MM / 2 / FOCAL_MM)
    vfov = 2 * math.atan(APERTURE_MM * h / w / 2 / FOCAL_MM)
    fit = 1.1 * size / 2 / math.tan(min(hfov, vfov) / 2)
    tilt = math.radians(TILT_DEG)
    view_dir = np.array([0.0, -math.sin(tilt), math.cos(tilt)])
    px_angle = 2 * math.tan(hfov / 2) / w
    info["cameras"] = {}
    for name, factor in spec["cameras"].items():
        dist = fit * float(factor)
        eye = centre + dist * view_dir
        cam = UsdGeom.Camera.Define(stage, f"/Cams/{name}")
        cam.CreateFocalLengthAttr(FOCAL_MM)
        cam.CreateHorizontalApertureAttr(APERTURE_MM)
        cam.CreateVerticalApertureAttr(APERTURE_MM * h / w)
        cam.CreateClippingRangeAttr(Gf.Vec2f(float(max(0.1, dist / 100)), float(dist * 100)))
        m = Gf.Matrix4d().SetLookAt(Gf.Vec3d(*eye), Gf.Vec3d(*centre), Gf.Vec3d(0, 0, 1)).GetInverse()
        UsdGeom.Xformable(cam).AddTransformOp().Set(m)
        info["cameras"][name] = {"distance_mm": dist, "factor": factor,
                                 "yarn_px_at_centre": diameter / (dist * px_angle),
                                 "mm_per_px_at_centre": dist * px_angle}
    return info


def cloth_mask(stage: Any, cam_path: str, lo: list[float], hi: list[float], w: int, h: int) -> np.ndarray:
    """(h, w) bool: pixel centres inside the projection of the cloth's rectangle (z = centre)."""
    from pxr import Gf, Usd, UsdGeom

    fr = UsdGeom.Camera(stage.GetPrimAtPath(cam_path)).GetCamera(Usd.TimeCode.Default()).frustum
    vm, pm = fr.ComputeViewMatrix(), fr.ComputeProjectionMatrix()
    z = 0.5 * (lo[2] + hi[2])
    quad = []
    for x, y in ((lo[0], lo[1]), (hi[0], lo[1]), (hi[0], hi[1]), (lo[0], hi[1])):
        ndc = pm.Transform(vm.Transform(Gf.Vec3d(x, y, z)))
        quad.append(((ndc[0] + 1) / 2 * w, (1 - ndc[1]) / 2 * h))
    q = np.array(quad)
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    inside = np.ones((h, w), bool)
    sign = None
    for k in range(4):
        a, b = q[k], q[(k + 1) % 4]
        c = (b[0] - a[0]) * (yy - a[1]) - (b[1] - a[1]) * (xx - a[0])
        s = np.sign(np.sum(c))
        sign = s if sign is None else sign
        inside &= (c * sign) >= 0
    return inside


# ---------------------------------------------------------------------------------------------
# Worker (one fresh process per measurement)
# ---------------------------------------------------------------------------------------------

class Progress:
    """Appends one JSON line per event to a file (survives the process being killed)."""

    def __init__(self, path: str | None) -> None:
        self.path = path
        self.t0 = time.perf_counter()

    def __call__(self, stage: str, **kw: Any) -> None:
        if not self.path:
            return
        rec = {"t": round(time.perf_counter() - self.t0, 2), "stage": stage,
               "rss_mib": proc_status_mib("VmRSS"), "hwm_mib": proc_status_mib("VmHWM"), **kw}
        with open(self.path, "a") as f:
            f.write(json.dumps(rec, default=_json_default) + "\n")


def _render_halves(mi: Any, scene: Any, spp: int, seeds: tuple[int, ...], sensor: Any = None,
                   pass_spp: int = 16) -> tuple[list[np.ndarray], float, float]:
    """One image per seed, each the sample-weighted mean of passes of <= pass_spp samples."""
    import drjit as dr

    imgs = []
    with Timer() as t:
        for s in seeds:
            acc = None
            for k, n in enumerate(min(pass_spp, spp - o) for o in range(0, spp, pass_spp)):
                kw = {"sensor": sensor} if sensor is not None else {}
                img = mi.render(scene, spp=n, seed=s * 1000 + k, **kw)
                dr.eval(img)
                a = np.array(img, dtype=np.float64)[..., :3] * n
                acc = a if acc is None else acc + a
            imgs.append((acc / spp).astype(np.float32))
        dr.sync_thread()
    return imgs, t.wall, t.cores


#: --variants names (the lod module's constants) -> LodPolicy fields.
LOD_FIELDS = {"FAR_YARN_PIXELS": "far_yarn_pixels", "FIBERS_PER_PIXEL": "fibers_per_pixel",
              "MIN_FIBER_FRACTION": "min_fiber_fraction", "WIDEN_EXPONENT": "widen_exponent"}


def lod_policy(overrides: dict[str, float] | None) -> Any:
    """EXPERIMENT (not the shipped values): the default LodPolicy with ``overrides`` (constant
    names of ``translators/mitsuba/lod.py``, e.g. ``{"MIN_FIBER_FRACTION": 0.25, "WIDEN_EXPONENT": 1.0}``).
    WIDEN_EXPONENT 1 keeps the yarn's summed projected fiber width (its coverage when the fibers
    do not overlap); 0.5 keeps the summed cross-section area."""
    from dataclasses import replace

    from usdfiber.translators.mitsuba.lod import LodPolicy

    unknown = sorted(set(overrides or {}) - set(LOD_FIELDS))
    if unknown:
        raise KeyError(f"no level-of-detail constant {', '.join(unknown)} (known: {', '.join(LOD_FIELDS)})")
    return replace(LodPolicy(), **{LOD_FIELDS[k]: float(v) for k, v in (overrides or {}).items()})


def _variant_label(overrides: dict[str, float] | None) -> str:
    if not overrides:
        return ""
    short = {"MIN_FIBER_FRACTION": "min", "WIDEN_EXPONENT": "widen exp", "FAR_YARN_PIXELS": "far px",
             "FIBERS_PER_PIXEL": "fibers/px"}
    return " [" + ", ".join(f"{short.get(k, k)} {v:g}" for k, v in overrides.items()) + "] (experiment)"


def coverage(mi: Any, scene: Any, sensor: Any, mask: np.ndarray, z_min: float, sub: int = 4) -> float:
    """Fraction of primary rays (sub x sub per pixel, stratified) inside ``mask`` whose first hit
    is a fiber (above ``z_min``; the card lies below it): the cloth's optical coverage."""
    h, w = mask.shape
    ys, xs = np.mgrid[0:h * sub, 0:w * sub]
    u = ((xs + 0.5) / (w * sub)).ravel()
    v = ((ys + 0.5) / (h * sub)).ravel()
    ray, _ = sensor.sample_ray(0.0, 0.0, mi.Point2f(u, v), mi.Point2f(0.5, 0.5))
    si = scene.ray_intersect(ray)
    hit = np.array(si.is_valid()) & (np.array(si.p.z) > z_min)
    hit = hit.reshape(h, sub, w, sub).mean(axis=(1, 3))
    return float(hit[mask].mean())


def worker(job: dict[str, Any]) -> dict[str, Any]:
    """Build, translate, render one job; returns the record (also on MemoryError: where)."""
    limit = job.get("mem_limit_gib")
    if limit:
        # Soft limit, for building and translating (the numpy arrays that can outgrow the
        # machine); lifted again before rendering.
        hard = resource.getrlimit(resource.RLIMIT_DATA)[1]
        soft = int(limit * 2**30)
        resource.setrlimit(resource.RLIMIT_DATA, (soft if hard == resource.RLIM_INFINITY else min(soft, hard), hard))
    prog = Progress(job.get("progress"))
    out: dict[str, Any] = {"load_start": _load(), "mem_limit_gib": limit}
    t_all = time.perf_counter()
    try:
        _work(job, out, prog)
    except MemoryError:
        out.update(failed="MemoryError", failed_in=traceback.format_exc(limit=-3).splitlines()[-7:],
                   hwm_mib=proc_status_mib("VmHWM"))
        prog("MemoryError")
    out.update(wall_seconds=time.perf_counter() - t_all, load_end=_load())
    return out


def _work(job: dict[str, Any], out: dict[str, Any], prog: Progress) -> None:
    with Timer() as t:
        import usdfiber  # noqa: F401
        from usdfiber.backend import mitsuba

        mi = mitsuba()
        import drjit as dr  # noqa: F401

        from usdfiber.bake.settings import BakeSettings
        from usdfiber.bake.cache import TableCache
        from usdfiber.translators.mitsuba.profile import TranslationProfile
        from usdfiber.translators.mitsuba.scene import SceneOptions, translate_stage
    out["import_seconds"] = t.wall
    prog("imported")
    with Timer() as t:
        stage, info = build_stage(job["spec"])
    out.update(author_seconds=t.wall, stage=info, hwm_after_stage_mib=proc_status_mib("VmHWM"))
    prog("stage built")

    if job.get("validate"):
        from usdfiber.validation.runner import check_stage

        with Timer() as t:
            rep = check_stage(stage)
        out["validate"] = {"seconds": t.wall, "errors": len(rep.errors), "warnings": len(rep.warnings)}
        prog("validated")

    yarn_progress = {"yarns": 0, "points": 0}

    def listen(step: str, result: Any) -> None:
        if step == "expand_yarn":
            yarn_progress["yarns"] += 1
            yarn_progress["points"] += int(len(result.points))
            if yarn_progress["yarns"] % 250 == 0:
                prog("expanding", **yarn_progress)
        elif step == "curve_shape":
            prog("mitsuba scene")

    profile = TranslationProfile(listener=listen)
    policy = lod_policy(job.get("lod_overrides"))
    out["lod_constants"] = {k: getattr(policy, f) for k, f in LOD_FIELDS.items()}
    spec = job["spec"]
    w, h = spec["res"]
    opts = SceneOptions(resolution=(w, h), spp=1, camera=f"/Cams/{job['camera']}", bake=BakeSettings(**BAKE),
                        bake_missing=True, cache=TableCache(job["cache"]), lod_scale=float(job["lod_scale"]),
                        lod=policy, profile=profile)
    prog("translating")
    out["load_translate_start"] = _load()
    out.update(pieces=profile.seconds, yarn_progress=yarn_progress)   # so far, should it run out of memory
    with Timer() as t:
        tr = translate_stage(stage, opts)
    # The translation's steps under this report's names.
    names = {"curves": "usd_read", "centre_sampling": "centre_sampling", "expand_yarn": "expand_yarn",
             "reference_normals": "reference_normals", "bsdf": "bsdf", "curve_shape": "curve_shape",
             "scene": "scene_bvh"}
    pieces = {names[k]: v for k, v in profile.seconds.items() if k in names}
    # Planning the level of detail and expanding the planned yarns: the yarns' whole cost.
    pieces["yarn_expansion_total"] = profile.seconds.get("yarn_lod", 0.0) + profile.seconds.get("yarn_expansion", 0.0)
    out.update(translate_seconds=t.wall, translate_cores=t.cores, times=tr.times, counts=tr.counts, pieces=pieces,
               hwm_after_translate_mib=proc_status_mib("VmHWM"), rss_after_translate_mib=proc_status_mib("VmRSS"),
               yarn_progress=yarn_progress)
    p = pieces
    p["expand_rest"] = p.get("yarn_expansion_total", 0) - p.get("centre_sampling", 0) - p.get("expand_yarn", 0)
    p["other"] = (t.wall - tr.times.get("tables", 0) - p.get("yarn_expansion_total", 0) - p.get("usd_read", 0)
                  - p.get("reference_normals", 0) - p.get("bsdf", 0) - p.get("curve_shape", 0) - p.get("scene_bvh", 0))
    prog("translated", counts=tr.counts)
    hard = resource.getrlimit(resource.RLIMIT_DATA)[1]
    resource.setrlimit(resource.RLIMIT_DATA, (hard, hard))
    out["load_render_start"] = _load()

    renders = {}
    if job.get("warmup"):
        _, ws, _ = _render_halves(mi, tr.scene, 1, (7,))
        out["warmup_1spp_seconds"] = ws
    imgdir = job.get("image_dir")
    z_card = info["cloth_lo"][2] - info["yarn_diameter_mm"]       # between the cloth and the card
    if job.get("sensors"):          # reference: render this translation from several cameras
        from usdfiber.translators.mitsuba.camera import camera_sensor
        from pxr import Usd, UsdGeom

        for name in job["sensors"]:
            prim = stage.GetPrimAtPath(f"/Cams/{name}")
            xf = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default()), np.float64)
            sensor = mi.load_dict(camera_sensor(prim, xf, Usd.TimeCode.Default(), w, h, spp=1))
            imgs, secs, cores = _render_halves(mi, tr.scene, job["spp"], tuple(job["seeds"]), sensor=sensor)
            mask = cloth_mask(stage, f"/Cams/{name}", info["cloth_lo"], info["cloth_hi"], w, h)
            renders[name] = {"seconds": secs, "cores": cores, "spp_per_half": job["spp"], "halves": len(imgs),
                             "mean": float(np.mean(imgs)),
                             "coverage": coverage(mi, tr.scene, sensor, mask, z_card)}
            if imgdir:
                np.savez(os.path.join(imgdir, f"{job['tag']}_{name}.npz"), *imgs, mask=mask)
            prog(f"rendered {name}")
    elif job.get("spp"):
        imgs, secs, cores = _render_halves(mi, tr.scene, job["spp"], tuple(job["seeds"]))
        renders[job["camera"]] = {"seconds": secs, "cores": cores, "spp_per_half": job["spp"], "halves": len(imgs),
                                  "mean": float(np.mean(imgs)),
                                  "finite": bool(all(np.all(np.isfinite(i)) for i in imgs))}
        if imgdir:
            mask = cloth_mask(stage, f"/Cams/{job['camera']}", info["cloth_lo"], info["cloth_hi"], w, h)
            renders[job["camera"]]["coverage"] = coverage(mi, tr.scene, tr.scene.sensors()[0], mask, z_card)
            np.savez(os.path.join(imgdir, f"{job['tag']}_{job['camera']}.npz"), *imgs, mask=mask)
        prog("rendered")
    out.update(renders=renders, hwm_mib=proc_status_mib("VmHWM"))


def run_worker(job: dict[str, Any], timeout: float = 3600, retries: int = 1) -> dict[str, Any]:
    """Run ``job`` in a fresh interpreter; returns its record plus wall time, load and progress log.
    A worker killed by a signal (a crash, not a MemoryError) is run again up to ``retries`` times;
    the crashed attempts are kept under ``crashed_attempts``."""
    crashed = []
    for _ in range(retries + 1):
        rec = _run_worker_once(job, timeout)
        if rec["returncode"] >= 0:
            break
        crashed.append({k: rec.get(k) for k in ("failed", "returncode", "stderr_tail", "process_wall_seconds",
                                                  "load_before", "load_after", "progress_log")})
        print(f"    worker crashed ({rec.get('failed')}); last progress "
              f"{(rec.get('progress_log') or [{}])[-1].get('stage')}; running it again", flush=True)
    if crashed:
        rec["crashed_attempts"] = crashed
    return rec


def _run_worker_once(job: dict[str, Any], timeout: float) -> dict[str, Any]:
    fd, jpath = tempfile.mkstemp(prefix="clothbench_job_", suffix=".json")
    os.close(fd)
    ppath = jpath.replace(".json", ".progress")
    rpath = jpath.replace(".json", ".result")
    job = dict(job, progress=ppath)
    Path(jpath).write_text(json.dumps(job, default=_json_default))
    cmd = [sys.executable, str(Path(__file__).resolve()), "_worker", jpath, rpath]
    env = dict(os.environ, USDFIBER_CACHE_DIR=str(job["cache"]))
    load0 = _load()
    t0 = time.perf_counter()
    # Watchdog: the worker's RSS may not exceed its data limit + 2 GiB (renders run without
    # RLIMIT_DATA), nor the time limit.
    watch = (job.get("mem_limit_gib") or 1e9) * 1024 + 2048
    killed = None
    with tempfile.TemporaryFile("w+") as fo, tempfile.TemporaryFile("w+") as fe:
        proc = subprocess.Popen(cmd, stdout=fo, stderr=fe, text=True, env=env)
        while proc.poll() is None:
            rss = proc_status_mib("VmRSS", str(proc.pid)) or 0.0
            if rss > watch or time.perf_counter() - t0 > timeout:
                killed = f"killed by the bench's watchdog (RSS {rss:.0f} MiB, {time.perf_counter() - t0:.0f} s)"
                proc.kill()
                proc.wait()
                break
            time.sleep(0.2)
        fe.seek(0)
        se = fe.read()
    wall = time.perf_counter() - t0
    rec: dict[str, Any]
    try:
        rec = json.loads(Path(rpath).read_text())
    except (OSError, ValueError):
        rec = {"failed": killed or f"worker exited with {proc.returncode}", "stderr_tail": se[-2000:]}
    rec.update(returncode=proc.returncode, process_wall_seconds=wall, load_before=load0, load_after=_load())
    try:
        rec["progress_log"] = [json.loads(l) for l in Path(ppath).read_text().splitlines()]
    except (OSError, ValueError):
        rec["progress_log"] = []
    for p in (jpath, ppath, rpath):
        try:
            os.unlink(p)
        except OSError:
            pass
    if proc.returncode != 0 and "failed" not in rec:
        rec["failed"] = f"worker exited with {proc.returncode}"
        rec["stderr_tail"] = se[-2000:]
    return rec


# ---------------------------------------------------------------------------------------------
# Estimates (stages too big to translate)
# ---------------------------------------------------------------------------------------------

def estimate_weave(spec: dict[str, Any], lod_scales: list[float]) -> dict[str, Any]:
    """Fiber curves and segments of a square N x N plain weave at each lod_scale, ESTIMATED with
    the translator's own code, without building the stage: warp i has the shape of warp (i % 2)
    of a 2 x N weave moved along x, weft j that of warp ((j + 1) % 2) with x and y swapped (the
    weave's symmetry). Each yarn's LOD fraction is LodPolicy.fiber_fraction of its pixel footprint
    under the stage's camera (as _expand_yarns computes it); its counts are those of expand_yarn
    on that shape at that fraction."""
    import usdfiber  # noqa: F401
    from pxr import Usd

    from usdfiber import cloth
    from usdfiber.translators.mitsuba import lod
    from usdfiber.translators.mitsuba.curves import curves_from_prim
    from usdfiber.translators.mitsuba.fibers import pixel_polyline, yarn_polylines
    from usdfiber.geometry.yarn import expand_yarn
    from usdfiber.spec.yarn import YarnParams

    n = spec["warps"]
    assert spec["kind"] == "weave" and spec["wefts"] == n
    s2 = new_stage()
    cloth.plain_weave(s2, "/W", warps=2, wefts=n, yarn=spec["yarn"], dye=DYE, depth_of_shade=DEPTH_OF_SHADE)
    prim = s2.GetPrimAtPath("/W/Warp")
    yp = YarnParams.from_prim(prim)
    geom = curves_from_prim(prim, Usd.TimeCode.Default(), np.eye(4), default_width=2 * yp.yarn_radius)
    polys = list(yarn_polylines(geom))
    spacing = float(polys[1][0][0, 0] - polys[0][0][0, 0])
    # The N x N stage's box, as its authored extents give it (control points +- half width).
    cp = np.array(prim.GetAttribute("points").Get(), np.float64)
    r = 0.5 * float(prim.GetAttribute("widths").Get()[0])
    lo = np.array([cp[:, 1].min() - r, cp[:, 1].min() - r, cp[:, 2].min() - r])
    hi = np.array([cp[:, 1].max() + r, cp[:, 1].max() + r, cp[:, 2].max() + r])
    cam_stage = new_stage()
    info = dress(cam_stage, spec, lo, hi)
    cam = list(spec["cameras"])[0]
    w, h = spec["res"]
    view = lod.camera_view(cam_stage.GetPrimAtPath(f"/Cams/{cam}"), Usd.TimeCode.Default(), w, h)
    policy = lod.LodPolicy()
    shapes = []                                    # (parity, pixels) per yarn
    for i in range(n):
        k = i % 2
        pts, rad = polys[k]
        shapes.append((k, view.pixels(2 * float(rad.max()), pts + [(i - k) * spacing, 0.0, 0.0])))
        k = (i + 1) % 2
        pts, rad = polys[k]
        shapes.append((k, view.pixels(2 * float(rad.max()), pts[:, [1, 0, 2]] + [0.0, (i - k) * spacing, 0.0])))
    px = np.array([x[1] for x in shapes])
    out: dict[str, Any] = {"method": "expand_yarn on each yarn shape at each LOD fraction, summed over the yarns",
                           "yarn_curves": 2 * n, "stage": info, "yarn_px_min_max": [float(px.min()), float(px.max())],
                           "centre_polyline_points_per_yarn": int(len(polys[0][0])),
                           "centre_bspline_segments_per_yarn": int(geom.segment_count // 2), "lod": {}}
    counts: dict[tuple, tuple[int, int]] = {}

    def count(k: int, fr: float) -> tuple[int, int]:
        key = (k, round(fr, 6))
        if key not in counts:
            pts, rad = polys[k]
            ex = expand_yarn(pts, rad / yp.yarn_radius, yp, fiber_fraction=fr, seed_offset=k)
            counts[key] = (ex.curve_count, int(ex.counts.sum() - ex.curve_count))
        return counts[key]

    for scale in lod_scales:
        curves = segs = 0
        fr_all = []
        far = 0
        for k, p in shapes:
            if policy.far_yarn(p, lod_scale=scale):      # one curve with the yarn's far field
                far += 1
                pts, rad = polys[k]
                segs += len(pixel_polyline(pts, 2 * float(rad.max()) / p)) - 1
                continue
            fr = policy.fiber_fraction(p, yp.fiber_count, lod_scale=scale)
            fr_all.append(fr)
            c, s = count(k, fr)
            curves += c
            segs += s
        out["lod"][str(scale)] = {"fiber_curves": curves, "segments": segs, "far_yarns": far,
                                  "fraction_min_max": [float(min(fr_all)), float(max(fr_all))] if fr_all else None}
    c, s = count(0, 1.0)
    out["per_yarn_full"] = {"fiber_curves": c, "segments": s, "fibers": yp.fiber_count,
                            "yarn_length_mm": float(np.linalg.norm(np.diff(polys[0][0], axis=0), axis=1).sum())}
    return out


# ---------------------------------------------------------------------------------------------
# Part: garment scale
# ---------------------------------------------------------------------------------------------

def garment_specs(quick: bool) -> list[dict[str, Any]]:
    if quick:
        return [
            {"name": "swatch card 5x5 of 10x10 ORA 120 (500 yarn curves)", "kind": "swatches", "yarn": "ORA 120",
             "warps": 10, "wefts": 10, "tiles": 5, "gap_mm": 2.0, "res": [320, 240], "cameras": {"whole": 1.0},
             "run": True, "full": False},
            {"name": "shirt panel: Skala 360 plain weave 2500 x 2500", "kind": "weave", "yarn": "Skala 360",
             "warps": 2500, "wefts": 2500, "res": [640, 480], "cameras": {"whole": 1.0},
             "run": False, "estimate": True},
        ]
    return [
        {"name": "shirt panel: Skala 360 plain weave 2500 x 2500", "kind": "weave", "yarn": "Skala 360",
         "warps": 2500, "wefts": 2500, "res": [640, 480], "cameras": {"whole": 1.0},
         "run": True, "estimate": True, "full": False},
        {"name": "swatch card: 21 x 21 swatches of 6 x 6 ORA 120 (5292 yarn curves)", "kind": "swatches",
         "yarn": "ORA 120", "warps": 6, "wefts": 6, "tiles": 21, "gap_mm": 2.0, "res": [640, 480],
         "cameras": {"whole": 1.0}, "run": True, "full": False},
        {"name": "one piece: ORA 120 plain weave 120 x 120", "kind": "weave", "yarn": "ORA 120",
         "warps": 120, "wefts": 120, "res": [640, 480], "cameras": {"whole": 1.0},
         "run": True, "estimate": True, "full": False},
    ]


def part_garment(args: argparse.Namespace, ctx: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {"runs": []}
    for spec in garment_specs(args.quick):
        rec: dict[str, Any] = {"spec": spec}
        if spec.get("estimate"):
            with Timer() as t:
                rec["estimate"] = estimate_weave(spec, [1.0, 0.0])
            rec["estimate"]["seconds"] = t.wall
            e = rec["estimate"]
            print(f"  {spec['name']}: ESTIMATE lod 1: {e['lod']['1.0']['fiber_curves']:,} fiber curves, "
                  f"{e['lod']['1.0']['segments']:,} segments; full: {e['lod']['0.0']['fiber_curves']:,} curves, "
                  f"{e['lod']['0.0']['segments']:,} segments (yarn px {e['yarn_px_min_max']})", flush=True)
        runs = []
        if spec.get("run"):
            scales = [1.0] + ([0.0] if spec.get("full") or args.garment_full else [])
            for scale in scales:
                job = {"spec": spec, "camera": "whole", "lod_scale": scale, "cache": str(ctx["cache_dir"]),
                       "spp": args.garment_spp, "seeds": [1], "warmup": True, "validate": True,
                       "mem_limit_gib": args.mem_limit_gib, "tag": "garment"}
                r = run_worker(job)
                r["lod_scale"] = scale
                runs.append(r)
                if "failed" in r:
                    last = r["progress_log"][-1] if r["progress_log"] else {}
                    print(f"  {spec['name']} lod {scale}: FAILED ({r['failed']}) after "
                          f"{r['process_wall_seconds']:.0f} s; last progress {last}", flush=True)
                else:
                    c = r["counts"]
                    rr = r["renders"]["whole"]
                    if c["yarn_fibers"]:
                        # Full expansion, ESTIMATED: segments per fiber curve x fiber curves at full detail,
                        # memory at this run's peak bytes per segment.
                        seg_full = c["fiber_segments"] * c["yarn_fibers_full"] / c["yarn_fibers"]
                        bps = (r["hwm_mib"] - r["hwm_after_stage_mib"]) * 2**20 / c["fiber_segments"]
                        r["full_estimate"] = {"segments": seg_full, "peak_bytes_per_segment": bps,
                                              "peak_gib": (r["hwm_after_stage_mib"] * 2**20 + bps * seg_full) / 2**30}
                    print(f"  {spec['name']} lod {scale}: {c['yarn_yarns']} yarns, {c['yarn_culled']} culled, "
                          f"{c['yarn_fibers']:,} / {c['yarn_fibers_full']:,} fibers, {c['fiber_segments']:,} segments; "
                          f"translate {r['translate_seconds']:.1f} s, render {rr['seconds']:.1f} s, "
                          f"peak {_gib(r['hwm_mib'])} GiB, load {r['load_before']} -> {r['load_after']}", flush=True)
        rec["runs"] = runs
        out["runs"].append(rec)
    return out


# ---------------------------------------------------------------------------------------------
# Part: LOD error
# ---------------------------------------------------------------------------------------------

def _block(a: np.ndarray, k: int) -> np.ndarray:
    h, w = a.shape[0] // k * k, a.shape[1] // k * k
    a = a[:h, :w]
    return a.reshape(h // k, k, w // k, k, *a.shape[2:]).mean(axis=(1, 3))


def image_error(img: list[np.ndarray], ref: list[np.ndarray], mask: np.ndarray, block: int = 1) -> dict[str, float]:
    """Relative RMSE of mean(img) against mean(ref) over ``mask`` (all channels) with the noise of
    each (from its two halves) and the bias (the part of the error that is not noise)."""
    A, B = (np.asarray(x, np.float64) for x in img)
    R1, R2 = (np.asarray(x, np.float64) for x in ref)
    m = mask
    if block > 1:
        A, B, R1, R2 = (_block(x, block) for x in (A, B, R1, R2))
        m = _block(mask.astype(np.float64), block) >= 1.0
    M, R = 0.5 * (A + B), 0.5 * (R1 + R2)
    sel = m[..., None] & np.ones(M.shape, bool)
    norm = float(np.mean(R[sel] ** 2))
    d2 = float(np.mean((M - R)[sel] ** 2)) / norm
    nm2 = float(np.mean((A - B)[sel] ** 2)) / 4 / norm
    nr2 = float(np.mean((R1 - R2)[sel] ** 2)) / 4 / norm
    return {"rel_rmse": math.sqrt(d2), "noise_img": math.sqrt(nm2), "noise_ref": math.sqrt(nr2),
            "bias": math.sqrt(max(0.0, d2 - nm2 - nr2)), "bias_sq_minus": d2 - nm2 - nr2,
            "rel_mean_diff": float(np.mean(M[sel]) / np.mean(R[sel]) - 1.0), "pixels": int(m.sum())}


def part_lod(args: argparse.Namespace, ctx: dict[str, Any]) -> dict[str, Any]:
    n = args.lod_yarns
    cams = ({"near": 1 / 3, "whole": 1.0} if args.quick else {"near": 1 / 3, "mid": 0.6, "whole": 1.0, "far": 3.0})
    if args.cameras:
        cams = {k: v for k, v in cams.items() if k in args.cameras}
    spec = {"name": f"ORA 120 plain weave {n} x {n}", "kind": "weave", "yarn": "ORA 120", "warps": n, "wefts": n,
            "res": [args.lod_res, args.lod_res], "cameras": cams}
    widest = max(cams, key=lambda k: cams[k])
    imgdir = tempfile.mkdtemp(prefix="clothbench_img_")
    out: dict[str, Any] = {"spec": spec, "spp_per_half": args.lod_spp // 2, "ref_spp_per_half": args.ref_spp // 2,
                           "scales": args.lod_scales, "runs": []}
    try:
        ref_job = {"spec": spec, "camera": widest, "lod_scale": 0.0, "cache": str(ctx["cache_dir"]),
                   "spp": args.ref_spp // 2, "seeds": [101, 102], "sensors": list(cams), "warmup": True,
                   "mem_limit_gib": args.mem_limit_gib, "tag": "ref", "image_dir": imgdir}
        ref = run_worker(ref_job)
        if "failed" in ref:
            raise RuntimeError(f"reference failed: {ref.get('failed')} {ref.get('stderr_tail', '')}")
        out["reference"] = ref
        c = ref["counts"]
        print(f"  reference (lod 0, camera {widest}): {c['yarn_fibers']:,} fibers, {c['fiber_segments']:,} segments, "
              f"{c['yarn_culled']} culled; translate {ref['translate_seconds']:.1f} s, peak {_gib(ref['hwm_mib'])} GiB; "
              + ", ".join(f"{k} {v['seconds']:.1f} s cov {v['coverage']:.3f}" for k, v in ref["renders"].items()),
              flush=True)
        out["cameras"] = ref["stage"]["cameras"]
        for cam in cams:
            rz = np.load(os.path.join(imgdir, f"ref_{cam}.npz"))
            refimgs, mask = [rz["arr_0"], rz["arr_1"]], rz["mask"]
            culled_full = None
            configs = ([(scale, None) for scale in args.lod_scales if scale > 0 or cam in args.full_cameras]
                       + [(scale, {"WIDEN_EXPONENT": 1.0}) for scale in args.widen_experiment]
                       + [(scale, v) for v in args.variants for scale in args.variant_scales])
            for k, (scale, over) in enumerate(configs):
                label = f"{scale:g}" + _variant_label(over)
                job = {"spec": spec, "camera": cam, "lod_scale": scale, "cache": str(ctx["cache_dir"]),
                       "spp": args.lod_spp // 2, "seeds": [200 + 2 * k, 201 + 2 * k], "warmup": True,
                       "mem_limit_gib": args.mem_limit_gib, "tag": f"lod{k}", "image_dir": imgdir,
                       "lod_overrides": over}
                r = run_worker(job)
                r.update(lod_scale=scale, camera=cam, lod_overrides=over, label=label)
                if "failed" not in r:
                    lz = np.load(os.path.join(imgdir, f"lod{k}_{cam}.npz"))
                    imgs = [lz["arr_0"], lz["arr_1"]]
                    r["error"] = image_error(imgs, refimgs, mask)
                    r["error_4x4"] = image_error(imgs, refimgs, mask, block=4)
                    if scale == 0 and over is None:
                        culled_full = imgs          # same camera, every fiber: culling alone
                    elif culled_full is not None:
                        # The fiber reduction alone: against the full expansion with the same culling.
                        r["error_vs_culled_full"] = image_error(imgs, culled_full, mask)
                    e, e4 = r["error"], r["error_4x4"]
                    c = r["counts"]
                    print(f"  {cam:5s} lod {label:>4}: {c['yarn_fibers']:>6,} fibers {c['fiber_segments']:>10,} seg "
                          f"culled {c['yarn_culled']:>3} cov {r['renders'][cam]['coverage']:.3f} (ref "
                          f"{ref['renders'][cam]['coverage']:.3f}); rel RMSE {e['rel_rmse']:.4f} (noise img {e['noise_img']:.4f}, "
                          f"ref {e['noise_ref']:.4f}; bias {e['bias']:.4f}; 4x4 bias {e4['bias']:.4f}; mean "
                          f"{e['rel_mean_diff']:+.4f}); translate {r['translate_seconds']:.1f} s render "
                          f"{r['renders'][cam]['seconds']:.1f} s peak {_gib(r['hwm_mib'])} GiB load "
                          f"{r['load_before'][0]}", flush=True)
                else:
                    print(f"  {cam} lod {scale}: FAILED {r['failed']}", flush=True)
                out["runs"].append(r)
    finally:
        shutil.rmtree(imgdir, ignore_errors=True)
    return out


# ---------------------------------------------------------------------------------------------
# Report: markdown tables from a results JSON
# ---------------------------------------------------------------------------------------------

def report(path: Path) -> str:
    d = json.loads(Path(path).read_text())
    out = [f"{d['argv']}: started {d['started']}, {d['wall_seconds'] / 60:.1f} min, load "
           f"{d['load_average_before']} -> {d['load_average_after']}"]
    g = d.get("garment")
    if g:
        rows, trows = [], []
        for rec in g["runs"]:
            sp = rec["spec"]
            e = rec.get("estimate")
            if e:
                for sc in ("1.0", "0.0"):
                    rows.append([sp["name"], f"{sc[0]} (ESTIMATE)", f"{e['yarn_curves']:,}", "0",
                                 f"{e['lod'][sc]['fiber_curves']:,}", f"{e['lod'][sc]['segments']:,}", "-", "-"])
            for r in rec["runs"]:
                lab = f"{r['lod_scale']:g}"
                if "failed" in r:
                    yp = r.get("yarn_progress") or {}
                    where = (r.get("failed_in") or ["?"])[0].strip()
                    rows.append([sp["name"], lab, f"{sp['warps'] * 2 if sp['kind'] == 'weave' else '-'}", "-",
                                 f"FAILED: {r['failed']} after {r['process_wall_seconds']:.0f} s, "
                                 f"{yp.get('yarns', 0)} yarns expanded ({where})", "-",
                                 f"{_gib(r.get('hwm_mib'))} (limit {r.get('mem_limit_gib')})",
                                 f"{r['load_before'][0]} -> {r['load_after'][0]}"])
                    continue
                c, pc = r["counts"], r["pieces"]
                rows.append([sp["name"], lab, f"{c['yarn_yarns']:,}", str(c["yarn_culled"]),
                             (f"{c['yarn_fibers']:,} of {c['yarn_fibers_full']:,} "
                              f"({c['yarn_fibers'] / c['yarn_fibers_full']:.1%})" if c["yarn_fibers_full"] else
                              f"0 ({c.get('yarn_far', 0):,} yarns as far fields)"),
                             f"{c['fiber_segments']:,}", f"{_gib(r['hwm_mib'])} (stage {_gib(r['hwm_after_stage_mib'])}, "
                             f"translate {_gib(r['hwm_after_translate_mib'])})",
                             f"{r['load_before'][0]} -> {r['load_after'][0]}"])
                rr = list(r["renders"].values())[0]
                trows.append([sp["name"], lab, f"{r['author_seconds']:.1f}", f"{r['validate']['seconds']:.1f}",
                              f"{r['translate_seconds']:.1f} ({r['translate_cores']:.2f})",
                              f"{r['times'].get('tables', 0):.2f}", f"{pc.get('usd_read', 0):.1f}",
                              f"{pc.get('centre_sampling', 0):.1f}", f"{pc.get('expand_yarn', 0):.1f}",
                              f"{pc.get('expand_rest', 0):.1f}", f"{pc.get('reference_normals', 0):.1f}",
                              f"{pc.get('bsdf', 0) + pc.get('curve_shape', 0):.1f}", f"{pc.get('scene_bvh', 0):.1f}",
                              f"{pc.get('other', 0):.1f}", f"{r.get('warmup_1spp_seconds', 0):.1f}",
                              f"{rr['seconds']:.1f} ({rr['cores']:.2f})"])
                fe = r.get("full_estimate")
                if fe:
                    rows.append([sp["name"], "0 (ESTIMATE from this run)", "", "", f"{c['yarn_fibers_full']:,}",
                                 f"{fe['segments']:,.0f}", f"{fe['peak_gib']:.0f} (at {fe['peak_bytes_per_segment']:.0f} B/segment)", ""])
        out.append(_table(["stage", "lod_scale", "yarn curves", "culled", "fiber curves kept of full", "segments",
                           "peak GiB", "load 1 min"], rows))
        out.append(_table(["stage", "lod_scale", "author s", "validate s", "translate s (cores)", "tables",
                           "USD read", "centre sampling", "expand_yarn", "rest of expansion", "ref. normals",
                           "BSDF + shape", "scene + BVH", "other", "warm-up 1 spp s", "render s (cores)"], trows))
    lo = d.get("lod")
    if lo:
        ref = lo["reference"]
        c = ref["counts"]
        out.append(f"reference: lod 0, {c['yarn_fibers']:,} fibers, {c['fiber_segments']:,} segments, culled "
                   f"{c['yarn_culled']}, translate {ref['translate_seconds']:.1f} s ({ref['translate_cores']:.2f} cores), "
                   f"peak {_gib(ref['hwm_mib'])} GiB; renders " + ", ".join(
                       f"{k}: {v['seconds']:.0f} s ({v['cores']:.2f} cores), coverage {v['coverage']:.3f}"
                       for k, v in ref["renders"].items()))
        cams = lo["cameras"]
        for cam, ci in cams.items():
            rows = []
            for r in lo["runs"]:
                if r["camera"] != cam or "failed" in r:
                    continue
                c, e, e4 = r["counts"], r["error"], r["error_4x4"]
                rr = r["renders"][cam]
                ec = r.get("error_vs_culled_full")
                rows.append([r["label"], f"{c['yarn_fibers']:,} ({c['yarn_fibers'] / max(1, ref['counts']['yarn_fibers']):.1%})",
                             f"{c['fiber_segments']:,}", str(c["yarn_culled"]),
                             f"{rr['coverage']:.3f}", f"{e['rel_rmse']:.3f}", f"{e['noise_img']:.3f} / {e['noise_ref']:.3f}",
                             f"**{e['bias']:.3f}**", f"{e4['bias']:.3f}", f"{e['rel_mean_diff']:+.1%}",
                             f"{ec['bias']:.3f} ({ec['rel_mean_diff']:+.1%})" if ec else "-",
                             f"{r['translate_seconds']:.1f}", f"{rr['seconds']:.0f} ({rr['cores']:.2f})",
                             f"{_gib(r['hwm_mib'])}", f"{r['load_before'][0]}"])
            out.append(f"camera {cam}: distance {ci['distance_mm']:.1f} mm, yarn {ci['yarn_px_at_centre']:.1f} px at the "
                       f"centre, reference coverage {ref['renders'][cam]['coverage']:.3f}")
            out.append(_table(["lod_scale", "fibers kept (of full)", "segments", "culled", "coverage", "rel RMSE",
                               "noise img / ref", "bias", "bias 4x4 px", "mean", "bias (mean) vs lod 0 same culling",
                               "translate s", "render s (cores)",
                               "peak GiB", "load"], rows))
    return "\n\n".join(out)


# ---------------------------------------------------------------------------------------------
# Main
# ---------------------------------------------------------------------------------------------

def prebake(cache_dir: Path) -> dict[str, Any]:
    """Bake the polyester table (what every stage here needs) once, as a render would."""
    import usdfiber  # noqa: F401
    from pxr import Usd, UsdGeom

    from usdfiber import authoring
    from usdfiber.bake.settings import BakeSettings
    from usdfiber.bake.cache import TableCache
    from usdfiber.bcsdf import tables_for_prim

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    prim = UsdGeom.BasisCurves.Define(stage, "/Y").GetPrim()
    authoring.apply_yarn(prim, "ORA 120", dye=DYE, depth_of_shade=DEPTH_OF_SHADE)
    with Timer() as t:
        tables = tables_for_prim(prim, BakeSettings(**BAKE), True, cache=TableCache(cache_dir))
    return {"seconds": t.wall, "tables": len(tables), "settings": BAKE}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "report":
        print(report(Path(argv[1]) if len(argv) > 1 else RESULTS / "cloth.json"))
        return 0
    if argv and argv[0] == "_worker":
        job = json.loads(Path(argv[1]).read_text())
        rec = worker(job)
        Path(argv[2]).write_text(json.dumps(rec, default=_json_default))
        return 0
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="small sizes: a smoke test (< 3 min), not a benchmark")
    ap.add_argument("--parts", default="garment,lod")
    ap.add_argument("--out", type=Path, default=None,
                    help="JSON path (default bench/results/cloth.json; --quick: cloth_quick.json)")
    ap.add_argument("--cache", type=Path, default=Path(os.environ.get("USDFIBER_CACHE_DIR", DEFAULT_CACHE)))
    ap.add_argument("--mem-limit-gib", type=float, default=16.0,
                    help="RLIMIT_DATA of each worker (the machine is shared: leave room for other work)")
    ap.add_argument("--garment-spp", type=int, default=16)
    ap.add_argument("--garment-full", action="store_true", help="also try lod_scale 0 on the garment stages")
    ap.add_argument("--lod-yarns", type=int, default=None, help="warps = wefts of the LOD cloth (default 20; quick 8)")
    ap.add_argument("--lod-res", type=int, default=None, help="LOD image size (default 160; quick 96)")
    ap.add_argument("--lod-spp", type=int, default=None, help="spp of each LOD image (two halves; default 256; quick 32)")
    ap.add_argument("--ref-spp", type=int, default=None, help="spp of the reference (two halves; default 512; quick 64)")
    floats = lambda s: [float(x) for x in s.split(",") if x.strip()]  # noqa: E731
    ap.add_argument("--lod-scales", type=floats, default=None,
                    help="lod_scale values against the reference (0: full expansion with the camera's own culling); "
                         "default 0,4,2,1,0.5; quick 0,1")
    ap.add_argument("--full-cameras", type=lambda s: [x for x in s.split(",") if x], default=["near", "mid", "whole"],
                    help="cameras that also render lod_scale 0 translated with their own camera (culling only; "
                         "without culling it is the reference again: a check of the error estimate)")
    ap.add_argument("--cameras", type=lambda s: [x for x in s.split(",") if x], default=None,
                    help="LOD cameras to run (of near, mid, whole, far; default all)")
    ap.add_argument("--widen-experiment", type=floats, default=None,
                    help="lod_scale values also run with the experimental 1/fraction widening (default none)")

    def variants(s: str) -> list[dict[str, float]]:
        out = []
        for v in s.split(";"):
            if v.strip():
                out.append({k.strip(): float(x) for k, x in (kv.split("=") for kv in v.split(","))})
        return out

    ap.add_argument("--variants", type=variants, default=[],
                    help="EXPERIMENTS: translators.lod constants to override, e.g. "
                         "'MIN_FIBER_FRACTION=0.25,WIDEN_EXPONENT=0.75;MIN_FIBER_FRACTION=0.5'; each is run at every "
                         "--variant-scales value")
    ap.add_argument("--variant-scales", type=floats, default=[1.0], help="lod_scale values of --variants (default 1)")
    args = ap.parse_args(argv)
    q = args.quick
    args.lod_yarns = args.lod_yarns or (8 if q else 20)
    args.lod_res = args.lod_res or (96 if q else 160)
    args.lod_spp = args.lod_spp or (32 if q else 256)
    args.ref_spp = args.ref_spp or (64 if q else 512)
    args.lod_scales = args.lod_scales if args.lod_scales is not None else ([0.0, 1.0] if q else [0.0, 4.0, 2.0, 1.0, 0.5])
    args.widen_experiment = args.widen_experiment if args.widen_experiment is not None else []
    out_path = args.out or RESULTS / ("cloth_quick.json" if q else "cloth.json")
    args.cache.mkdir(parents=True, exist_ok=True)
    os.environ["USDFIBER_CACHE_DIR"] = str(args.cache)

    t0 = time.perf_counter()
    res: dict[str, Any] = {"command": "cloth", "argv": ["python", "bench/cloth_bench.py", *argv],
                           "started": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
                           "load_average_before": _load(), "machine": machine(), "git": git_state(),
                           "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
                           "bake_settings": BAKE}
    ctx = {"cache_dir": args.cache}
    print(f"machine: {res['machine']['cpu_model']}, {res['machine']['cores']} cores; load {res['load_average_before']}",
          flush=True)
    res["prebake"] = prebake(args.cache)
    print(f"tables: {res['prebake']['seconds']:.1f} s", flush=True)
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    for part in parts:
        print(f"== {part}", flush=True)
        res[part] = {"garment": part_garment, "lod": part_lod}[part](args, ctx)
        res.setdefault("part_load_after", {})[part] = _load()
    res["load_average_after"] = _load()
    res["wall_seconds"] = round(time.perf_counter() - t0, 1)
    after = git_state()["sha256_16"]
    res["sources_changed_during_run"] = [s for s in SOURCES if after.get(s) != res["git"]["sha256_16"].get(s)]
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps(res, indent=1, default=_json_default))
    print(f"wrote {out_path} ({res['wall_seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
