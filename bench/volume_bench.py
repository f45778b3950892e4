"""Volumetric cloth (``render --cloth volume``): voxelization time, grid memory, render time per
spp and image error against explicit fibers (Figure 7 swatch) or the far field (a piece of the
5,000-yarn shirt panel), next to the explicit and far-field modes; equal-time errors.

    python bench/volume_bench.py swatch [--modes 'fibers;far field;volume;volume, 2 voxels/px']
                                        [--res 160x60] [--spp 2] [--passes 4] [--ref-passes 24]
                                        [--bricks 0,4,16] [--fine 2] --save IMAGES.npz > RUN.json
    python bench/volume_bench.py swatch-errors --inputs RUN.json,IMAGES.npz,... [--budgets 10,30,100]
    python bench/volume_bench.py shirt-render [--yarns 500|2500] [--res 160x120] [--spp 2] [--passes 4] [--ref-passes 16]
                                              [--explicit] [--voxels 0.13,0.065] [--auto] [--explicit-estimate]
                                              [--budgets 3,10,30,100] [--save IMAGES.npz]
    python bench/volume_bench.py auto [--yarns 2500] [--res 160x120] [--rounds 1]
    python bench/volume_bench.py bricks [--res 80x30] [--spp 4] [--rounds 2] [--bricks 8,0]
    python bench/volume_bench.py shirt [--yarns 5000] [--voxel-mm 1.04]
    python bench/volume_bench.py far-field-cause [--yarns 60] [--variants sheer,sparse,warps,single]
                                                 [--dye disperseBlue|none] [--card 0.5]
                                                 [--res 160x120] [--spp 2] [--passes 4] [--ref-passes 8]

Timing: CPU seconds of the rendering process (``time.process_time``: all its threads), which a
shared machine's load changes far less than wall time; wall times are recorded next to them.
Every render after the first of a mode reuses its compiled kernels: the seed is an opaque
Dr.Jit value and every pass has the same spp.

``swatch``: examples/fig7_swatches.usda rendered as explicit fibers (``--lod-scale 0``), as the
yarn far field (``--lod-scale 0.01``: every yarn below the far-field threshold), as a volume in
bricks of the default size (:data:`usdfiber.translators.mitsuba.volume.medium.BRICK_VOXELS`),
in bricks of ``--bricks`` voxels (0: one medium) and with ``--fine`` voxels per pixel footprint
(the voxel-size dependence of the error). Per mode: translate time (CPU and wall), voxelization
time, the voxel grids' bytes, a compiling pass (not timed), then ``--passes`` timed passes of
``--spp`` samples; explicit fibers also render ``--ref-passes`` passes, the reference. Modes
can run in separate processes (``--modes``, ';'-separated; their CPU times stay their own).
Tables: 15 degrees, 5,000 photons (cached in ``$USDFIBER_CACHE_DIR``).

``swatch-errors``: the runs' errors against the reference, on 4 x 4 pixel blocks relative to
the reference's mean (:func:`mode_errors`): the error of n spp is modelled as
err(n)^2 = bias^2 + noise1^2 / n, noise1 from the spread of the passes, the bias from the
error of all passes less the noise of both; the equal-time error at a CPU budget T is
err(T / (CPU s per spp)) (:func:`equal_time`). Also the image mean and the mean per swatch.

``shirt-render``: a piece of bench/cloth_bench.py's shirt panel (Skala 360 plain weave, the
panel's yarn and spacing; ``--yarns`` warps and as many wefts; 2500: the whole panel, one
stage) at ``--res`` as the yarn far field (the reference, at ``--ref-passes``) and as a volume
(voxels of ``--voxel-mm``, default the pixel footprint; ``--voxels`` a list of them). Explicit
fibers do not fit the machine at the scale of the panel (bench/REPORT.md, "Garment scale";
``--explicit-estimate`` counts their segments without translating); ``--explicit`` adds them
for small pieces, and then they are the reference. Also the generation's time and peak memory,
per mode the peak memory, the mean over the cloth only (``--cloth-box``, and the cloth's
projected rectangle), the volume's homogenization warnings (the predicted excess opacity), the
equal-time errors (``--budgets``) and, with ``--auto``, what ``--cloth auto`` chooses.

``auto``: what ``--cloth auto`` makes of the shirt-render stage (``--yarns`` warps and as many
wefts; 2500: the whole panel) at ``--res``, and the cost of deciding it (:func:`auto_choice`:
CPU seconds of the choice alone, no translation), ``--rounds`` times in one process; also the
stage's generation time and the process's peak memory over its memory before the choice.

``bricks``: the speed of bricks: the Figure 7 volume (the 320 x 120 view's 0.0713 mm voxels)
in bricks of ``--bricks`` voxels and as one medium (0), rendered alternately at a low
resolution: CPU seconds per spp, the image means against one medium, and the tentative
collisions per ray length (:func:`usdfiber.translators.mitsuba.volume.medium.collision_ratio`).

``shirt``: yarns of bench/cloth_bench.py's shirt panel (2,500 x 2,500 Skala 360, 66.5 cm)
voxelized from the yarn density at the footprint of a 640-pixel view of the whole panel
(1.04 mm): time, pieces, grid bytes. ``--yarns N`` voxelizes N full-length warps (above
2,500: the whole panel, warps then wefts) and extrapolates linearly to the panel's 5,000
yarns (the cost is per yarn length).

``far-field-cause``: the yarn far field against explicit fibers on the sheer weave and on
variants without neighbours or crossings (:func:`part_far_field_cause`).

Prints one JSON object (progress per mode on stderr).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from typing import Any

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def machine() -> dict[str, Any]:
    cpu = platform.processor()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "load_average": os.getloadavg()}


def block_rms(img: np.ndarray, ref: np.ndarray, b: int = 4) -> float:
    """RMS over b x b pixel blocks of (img - ref), relative to the reference's mean."""
    h, w = (img.shape[0] // b) * b, (img.shape[1] // b) * b

    def blocks(a: np.ndarray) -> np.ndarray:
        return a[:h, :w].mean(axis=2).reshape(h // b, b, w // b, b).mean(axis=(1, 3))

    return float(np.sqrt(np.mean((blocks(img) - blocks(ref)) ** 2)) / ref.mean())


def quarter_means(img: np.ndarray, ref: np.ndarray) -> list[float]:
    """Image mean relative to the reference per quarter of the width (one swatch each)."""
    q = img.shape[1] // 4
    return [float(img[:, k * q:(k + 1) * q].mean() / ref[:, k * q:(k + 1) * q].mean() - 1.0) for k in range(4)]


SWATCH_MODES: dict[str, dict[str, Any]] = {
    "fibers": dict(cloth="fibers", lod_scale=0.0),
    "far field": dict(cloth="fibers", lod_scale=0.01),
    "volume": dict(cloth="volume", lod_scale=1.0),
}


def swatch_modes(bricks: list[int], fine: list[float]) -> dict[str, dict[str, Any]]:
    """The modes of ``swatch``: explicit fibers, far field, the volume (default bricks), the
    volume at other brick sizes (0: one majorant) and at other voxels per pixel footprint."""
    modes = dict(SWATCH_MODES)
    for b in bricks:
        modes[f"volume, bricks {b}"] = dict(cloth="volume", lod_scale=1.0, volume_brick=b)
    for v in fine:
        modes[f"volume, {v:g} voxels/px"] = dict(cloth="volume", lod_scale=1.0, voxels_per_pixel=v)
    return modes


def _opaque_seed(mi: Any, seed: int) -> Any:
    """The seed as an opaque Dr.Jit value: passes with other seeds reuse the compiled kernel."""
    import drjit as dr

    return dr.opaque(mi.UInt32, seed)


def render_passes(mi: Any, scene: Any, spp: int, passes: int, seed0: int) -> tuple[np.ndarray, list[float], list[float]]:
    """``passes`` independent renders of ``spp`` samples (seeds seed0, seed0 + 1, ...): the images
    (passes, h, w, 3) and each pass's CPU seconds (all threads of this process) and wall seconds."""
    imgs, cpu, wall = [], [], []
    for k in range(passes):
        c0, t0 = time.process_time(), time.perf_counter()
        imgs.append(np.array(mi.render(scene, spp=spp, seed=_opaque_seed(mi, seed0 + k)), np.float64)[..., :3])
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - t0)
    return np.stack(imgs), cpu, wall


def time_mode(mi: Any, stage: Any, options: Any, spp: int, passes: int) -> tuple[Any, np.ndarray, dict[str, Any]]:
    """Translate ``stage`` with ``options``, render one compiling pass (not timed), then
    ``passes`` timed passes: (translation, images, record of CPU and wall times)."""
    from usdfiber.translators.mitsuba.scene import translate_stage

    c0, t0 = time.process_time(), time.perf_counter()
    tr = translate_stage(stage, options)
    c1, t1 = time.process_time(), time.perf_counter()
    mi.render(tr.scene, spp=spp, seed=_opaque_seed(mi, 0))   # kernel compilation, not timed
    c2, t2 = time.process_time(), time.perf_counter()
    imgs, cpu, wall = render_passes(mi, tr.scene, spp, passes, 1)
    rec = {"translate_s": t1 - t0, "translate_cpu_s": c1 - c0, "compile_pass_s": t2 - t1,
           "compile_pass_cpu_s": c2 - c1, "pass_cpu_s": cpu, "pass_wall_s": wall,
           "cpu_s_per_spp": float(np.median(cpu)) / spp, "wall_s_per_spp": float(np.median(wall)) / spp,
           "load": os.getloadavg()[0]}
    return tr, imgs, rec


def part_swatch(args: argparse.Namespace) -> dict[str, Any]:
    """One or more modes of the Figure 7 swatch (``--modes``), each: translate, a compiling pass,
    then ``--passes`` timed passes of ``--spp`` samples; ``fibers`` also renders ``--ref-passes``
    reference passes. Images go to ``--save`` (.npz) for ``swatch-errors``."""
    import usdfiber  # noqa: F401  (registers the schemas first)
    from pxr import Usd

    from usdfiber.backend import mitsuba
    from usdfiber.bake.cache import TableCache
    from usdfiber.bake.settings import BakeSettings

    mi = mitsuba()
    from usdfiber.translators.mitsuba.scene import SceneOptions
    from usdfiber.translators.mitsuba.volume.medium import BRICK_VOXELS

    stage = Usd.Stage.Open(os.path.join(ROOT, "examples", "fig7_swatches.usda"))
    w, h = (int(v) for v in args.res.split("x"))
    bake = BakeSettings(resolution_deg=15, photons=5000, batches=2)
    cache = TableCache(os.environ.get("USDFIBER_CACHE_DIR") or None)
    modes = swatch_modes([int(b) for b in args.bricks.split(",") if b], [float(v) for v in args.fine.split(",") if v])
    chosen = [m.strip() for m in args.modes.split(";")] if args.modes else list(modes)
    images: dict[str, np.ndarray] = {}
    out: dict[str, Any] = {"stage": "examples/fig7_swatches.usda", "res": [w, h], "spp_per_pass": args.spp,
                           "passes": args.passes, "reference_passes": args.ref_passes,
                           "default_brick": BRICK_VOXELS, "modes": {}}
    for mode in chosen:
        tr, imgs, rec = time_mode(mi, stage, SceneOptions(resolution=(w, h), spp=args.spp, bake=bake, cache=cache,
                                                          **modes[mode]), args.spp, args.passes)
        images[mode] = imgs
        rec["counts"] = {k: v for k, v in tr.counts.items() if k in ("voxel_bytes", "voxels_occupied", "volume_faces",
                                                                     "voxelize_ms", "fiber_segments", "volumes",
                                                                     "fiber_curves", "yarn_far_fields")}
        if mode == "fibers" and args.ref_passes:
            ref, rcpu, _ = render_passes(mi, tr.scene, args.spp, args.ref_passes, 1000)
            images["reference"] = ref
            out["reference_cpu_s"] = float(np.sum(rcpu))
        out["modes"][mode] = rec
        print(mode, json.dumps(rec, default=float), file=sys.stderr, flush=True)
        del tr
    if args.save:
        np.savez_compressed(args.save, **images)
    return out


def block_means(img: np.ndarray, b: int = 4) -> np.ndarray:
    """Means over b x b pixel blocks and the colour channels (the last two axes are h, w, 3)."""
    h, w = (img.shape[-3] // b) * b, (img.shape[-2] // b) * b
    a = img[..., :h, :w, :].mean(axis=-1)
    return a.reshape(a.shape[:-2] + (h // b, b, w // b, b)).mean(axis=(-3, -1))


def mode_errors(passes: np.ndarray, ref_passes: np.ndarray, spp: int, cpu_s_per_spp: float) -> dict[str, Any]:
    """Error of a mode's passes against the reference's, on 4 x 4 pixel blocks relative to the
    reference's mean: err(n spp)^2 = bias^2 + noise1^2 / n, with noise1 (the error of one spp)
    from the spread of the passes (passes - 1 degrees of freedom per block, pooled over every
    block) and bias^2 the rest of the measured error of all passes, less the reference's own
    noise (from the spread of its passes)."""
    ref = ref_passes.mean(axis=0)
    m = ref.mean()
    bp, br = block_means(passes), block_means(ref_passes)
    p, r = len(bp), len(br)
    noise1_sq = float(np.mean(bp.var(axis=0, ddof=1))) * spp / m**2          # one spp
    ref_noise_sq = float(np.mean(br.var(axis=0, ddof=1))) / r / m**2        # the reference mean's
    err_all_sq = float(np.mean((bp.mean(axis=0) - br.mean(axis=0)) ** 2)) / m**2
    err_one_sq = float(np.mean((bp[0] - br.mean(axis=0)) ** 2)) / m**2
    bias_sq = err_all_sq - noise1_sq / (p * spp) - ref_noise_sq
    # err_all_sq averages (Gaussian) squared block errors: its standard error is about
    # err_all_sq * sqrt(2 / blocks); the noise terms' (from pooled variances) is smaller.
    bias_sq_se = err_all_sq * float(np.sqrt(2.0 / bp[0].size))
    img = passes.mean(axis=0)
    return {"mean_rel": float(img.mean() / m - 1.0),
            "mean_rel_se": float(np.sqrt(np.var(passes.mean(axis=(1, 2, 3)), ddof=1) / p) / m),
            "quarter_mean_rel": quarter_means(img, ref),
            "block_rms_one_pass": float(np.sqrt(err_one_sq)), "block_rms_all_passes": float(np.sqrt(err_all_sq)),
            "noise_1spp": float(np.sqrt(noise1_sq)), "reference_noise": float(np.sqrt(ref_noise_sq)),
            "bias": float(np.sqrt(max(bias_sq, 0.0))), "bias_sq": bias_sq, "bias_sq_se": bias_sq_se,
            "bias_resolved": bool(bias_sq > 2.0 * bias_sq_se),
            "predicted_one_pass": float(np.sqrt(max(bias_sq, 0.0) + noise1_sq / spp + ref_noise_sq)),
            "cpu_s_per_spp": cpu_s_per_spp}


def equal_time(errors: dict[str, dict[str, Any]], budgets: list[float]) -> dict[str, dict[str, float]]:
    """err(T) = sqrt(bias^2 + noise1^2 / spp(T)), spp(T) = T / (CPU s per spp), per mode and budget;
    a bias within two standard errors of 0 counts as 0 (not resolved by the run)."""
    def bias_sq(e: dict[str, Any]) -> float:
        return e["bias_sq"] if e["bias_resolved"] else 0.0

    return {f"{t:g}": {mode: float(np.sqrt(bias_sq(e) + e["noise_1spp"] ** 2 * e["cpu_s_per_spp"] / t))
                       for mode, e in errors.items()} for t in budgets}


def part_swatch_errors(args: argparse.Namespace) -> dict[str, Any]:
    """Combines ``swatch`` runs (``--inputs``: pairs of JSON result and .npz images, comma
    separated) into the errors against the explicit-fiber reference and the equal-time errors."""
    files = [f for f in args.inputs.split(",") if f]
    runs = [(json.load(open(files[i])), np.load(files[i + 1])) for i in range(0, len(files), 2)]
    ref = next(z["reference"] for _, z in runs if "reference" in z.files)
    out: dict[str, Any] = {"runs": [f for f in files[::2]], "modes": {}}
    for res, z in runs:
        for mode, rec in res["modes"].items():
            out["modes"][mode] = mode_errors(z[mode], ref, res["spp_per_pass"], rec["cpu_s_per_spp"])
            out["modes"][mode].update(spp=res["spp_per_pass"] * res["passes"], res=res["res"], run=rec,
                                      machine=res["machine"], argv=res.get("argv"))
    out["equal_time_cpu_s"] = equal_time(out["modes"], [float(t) for t in args.budgets.split(",")])
    return out


def part_bricks(args: argparse.Namespace) -> dict[str, Any]:
    """The Figure 7 volume in bricks of ``--bricks`` voxels against one medium (brick 0), the same
    grids (``--voxel-mm``, the 320 x 120 view's footprint), rendered alternately at ``--res``:
    CPU and wall seconds per spp, the image means (against brick 0, with their standard errors)
    and, per brick size, the tentative collisions per ray length relative to one majorant."""
    import usdfiber  # noqa: F401  (registers the schemas first)
    from pxr import Usd

    from usdfiber.backend import mitsuba
    from usdfiber.bake.cache import TableCache
    from usdfiber.bake.settings import BakeSettings

    mi = mitsuba()
    from usdfiber.translators.mitsuba.scene import SceneOptions, translate_stage
    from usdfiber.translators.mitsuba.stage_walk import walk
    from usdfiber.translators.mitsuba.fibers import fiber_prim
    from usdfiber.translators.mitsuba.volume.medium import brick_size, collision_ratio
    from usdfiber.translators.mitsuba.volume.scene import translate_volumes
    from pxr import UsdGeom

    stage = Usd.Stage.Open(os.path.join(ROOT, "examples", "fig7_swatches.usda"))
    w, h = (int(v) for v in args.res.split("x"))
    bake = BakeSettings(resolution_deg=15, photons=5000, batches=2)
    cache = TableCache(os.environ.get("USDFIBER_CACHE_DIR") or None)
    sizes = [int(b) for b in args.bricks.split(",")]
    tc = Usd.TimeCode.Default()
    pls = [pl for pl in walk(stage, tc, ("default", "render"), (UsdGeom.Gprim,)) if fiber_prim(pl.prim)]
    vt, _ = translate_volumes(mi, pls, stage, tc, settings=bake, cache=cache, voxel_size=args.voxel_mm, brick_voxels=0)
    out: dict[str, Any] = {"stage": "examples/fig7_swatches.usda", "res": [w, h], "spp": args.spp,
                           "voxel_mm": args.voxel_mm, "rounds": args.rounds,
                           "grids": {p: list(g.shape) for p, g in vt.grids.items()}, "bricks": {}}
    for b in sizes + [4, 16]:
        out["bricks"].setdefault(str(b), {})["collision_ratio"] = [
            collision_ratio(g, brick_size(g, b)) for g in vt.grids.values()]
    scenes = {}
    for b in sizes:
        tr = translate_stage(stage, SceneOptions(resolution=(w, h), spp=1, bake=bake, cache=cache, cloth="volume",
                                                 voxel_size=args.voxel_mm, volume_brick=b))
        t0 = time.perf_counter()
        mi.render(tr.scene, spp=1, seed=1)           # kernel compilation, not timed
        scenes[b] = tr.scene
        out["bricks"][str(b)].update(faces=tr.counts["volume_faces"], compile_s=time.perf_counter() - t0)
    imgs: dict[int, list[np.ndarray]] = {b: [] for b in sizes}
    for r in range(args.rounds):
        for b in sizes:                              # alternated: the machine's load hits both alike
            c0, t0 = time.process_time(), time.perf_counter()
            imgs[b].append(np.array(mi.render(scenes[b], spp=args.spp, seed=100 + r), np.float64)[..., :3])
            rec = out["bricks"][str(b)]
            rec.setdefault("cpu_s", []).append(time.process_time() - c0)
            rec.setdefault("wall_s", []).append(time.perf_counter() - t0)
            rec.setdefault("load", []).append(os.getloadavg()[0])
    base = np.mean(imgs[sizes[-1]], axis=0) if 0 not in sizes else np.mean(imgs[0], axis=0)
    for b in sizes:
        img = np.mean(imgs[b], axis=0)
        px = img.mean(axis=2).reshape(-1)
        rec = out["bricks"][str(b)]
        rec.update(cpu_s_per_spp=float(np.sum(rec["cpu_s"]) / (args.spp * args.rounds)),
                   wall_s_per_spp=float(np.sum(rec["wall_s"]) / (args.spp * args.rounds)),
                   mean=float(px.mean()), mean_se=float(px.std(ddof=1) / np.sqrt(len(px))),
                   mean_rel_to_one_majorant=float(img.mean() / base.mean() - 1.0),
                   block_rms_to_one_majorant=block_rms(img, base))
    return out


def part_shirt(args: argparse.Namespace) -> dict[str, Any]:
    import usdfiber  # noqa: F401
    from pxr import Usd, UsdGeom

    from usdfiber import cloth
    from usdfiber.geometry.curves import curves_from_prim
    from usdfiber.geometry.voxelize import GridAccumulator, grid_size
    from usdfiber.geometry.yarn_density import YarnCurve, yarn_pieces
    from usdfiber.spec.fiber import FiberParams
    from usdfiber.spec.yarn import YarnParams
    from usdfiber.translators.mitsuba.fibers import yarn_polylines

    t0 = time.perf_counter()
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    # Up to 2,500 yarns: the panel's warps at full length (66.5 cm across 2,500 wefts); more:
    # the whole panel (50 M control points, 0.84 GiB), its wefts after its warps.
    cloth.plain_weave(stage, "/Shirt", warps=min(args.yarns, 2500), wefts=2500, yarn="Skala 360",
                      dye="disperseBlue", depth_of_shade=1.0)
    t_stage = time.perf_counter() - t0
    prims = [stage.GetPrimAtPath("/Shirt/Warp")] + ([stage.GetPrimAtPath("/Shirt/Weft")] if args.yarns > 2500 else [])
    params = YarnParams.from_prim(prims[0])
    fiber = FiberParams.from_prim(prims[0], Usd.TimeCode.Default())
    dia = fiber.diameter * 1e-3                      # um -> mm
    voxel = args.voxel_mm
    curves: list[YarnCurve] = []
    for prim in prims:
        geom = curves_from_prim(prim, Usd.TimeCode.Default(), np.eye(4), default_width=2 * params.yarn_radius)
        for pts, rad in yarn_polylines(geom, 2):
            curves.append(YarnCurve(pts, rad / params.yarn_radius))
            if len(curves) >= args.yarns:
                break
        if len(curves) >= args.yarns:
            break
    pts = np.concatenate([c.points for c in curves])
    lo, hi = pts.min(axis=0) - voxel, pts.max(axis=0) + voxel
    size, shape, _ = grid_size("/Shirt", lo, hi, voxel, 1, 512 * 2**20, True)
    t_centre = time.perf_counter() - t0 - t_stage
    t1 = time.perf_counter()
    acc = GridAccumulator(lo, hi, size, shape, 1, source="/Shirt")
    n_pieces = 0
    length = 0.0
    for c in curves:
        p = yarn_pieces(c, params, voxel_size=size, fiber_diameter=dia, slots=[0], source="/Shirt")
        acc.add(p)
        n_pieces += len(p.count)
        length += float(np.sum(np.linalg.norm(np.diff(c.points, axis=0), axis=1)))
    grid = acc.finish()
    t_vox = time.perf_counter() - t1
    scale = 5000 / len(curves)
    return {"yarns": len(curves), "yarn_length_mm": length, "voxel_mm": size, "grid_shape": list(grid.shape),
            "grid_bytes": grid.nbytes(), "accumulator_grid_shape": list(shape), "pieces": n_pieces,
            "stage_s": t_stage, "centre_lines_s": t_centre, "voxelize_s": t_vox,
            "cpu_s": time.process_time(),
            "estimate_5000_yarns": {"voxelize_s": t_vox * scale, "centre_lines_s": t_centre * scale,
                                    "pieces": int(n_pieces * scale)},
            "fiber_count_per_yarn": params.fiber_count}


def _reset_peak_memory() -> bool:
    """Start a new peak of this process's resident memory (``VmHWM``; Linux: /proc/self/clear_refs)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _memory_mib() -> dict[str, float | None]:
    from bench_common import proc_status_mib

    return {"rss_mib": proc_status_mib("VmRSS"), "peak_mib": proc_status_mib("VmHWM")}


def auto_choice(stage: Any, camera: str, w: int, h: int) -> dict[str, Any]:
    """What ``--cloth auto`` makes of every yarn prim under ``camera`` at w x h, and why (the
    lines of ``ClothChoice``), without translating: the choice alone, with its CPU seconds."""
    from pxr import Usd, UsdGeom

    from usdfiber.translators.mitsuba.fibers import fiber_prim
    from usdfiber.translators.mitsuba.lod import camera_view
    from usdfiber.translators.mitsuba.stage_walk import walk
    from usdfiber.translators.mitsuba.volume.scene import split_cloth

    tc = Usd.TimeCode.Default()
    c0 = time.process_time()
    pls = [pl for pl in walk(stage, tc, ("default", "render"), (UsdGeom.Gprim,)) if fiber_prim(pl.prim)]
    vols, curves, choices = split_cloth(pls, "auto", camera_view(stage.GetPrimAtPath(camera), tc, w, h), tc)
    return {"volume_prims": len(vols), "curve_prims": len(curves), "choices": [str(c) for c in choices],
            "cpu_s": time.process_time() - c0}


def part_auto(args: argparse.Namespace) -> dict[str, Any]:
    """``--cloth auto``'s choice on the shirt-render stage, timed (module docstring)."""
    import usdfiber  # noqa: F401  (registers the schemas first)

    from cloth_bench import build_stage

    w, h = (int(v) for v in args.res.split("x"))
    spec = {"kind": "weave", "yarn": "Skala 360", "warps": args.yarns, "wefts": args.yarns, "res": [w, h],
            "cameras": {"whole": 1.0}}
    c0 = time.process_time()
    stage, info = build_stage(spec)
    out: dict[str, Any] = {"spec": spec, "cloth_size_mm": info["cloth_size_mm"],
                           "stage_cpu_s": time.process_time() - c0, "rounds": []}
    for _ in range(args.rounds):
        mem0 = _memory_mib()
        peak_reset = _reset_peak_memory()
        t0 = time.perf_counter()
        rec = auto_choice(stage, "/Cams/whole", w, h)
        rec.update(wall_s=time.perf_counter() - t0, load_average=os.getloadavg(),
                   peak_over_before_mib=(_memory_mib()["peak_mib"] - mem0["rss_mib"]) if peak_reset else None)
        out["rounds"].append(rec)
        print("auto", json.dumps(rec, default=float), file=sys.stderr, flush=True)
    return out


#: Peak bytes per fiber segment of an explicit-fiber translation (bench/REPORT.md, "Garment
#: scale": 0.86-0.89 KB measured on stages that translated).
EXPLICIT_BYTES_PER_SEGMENT = 870.0


def part_shirt_render(args: argparse.Namespace) -> dict[str, Any]:
    """A square piece of the shirt panel, or the whole panel (``--yarns 2500``: 2,500 warps and
    2,500 wefts of Skala 360, the panel's yarn and density; bench/cloth_bench.py's stage: grey
    card, camera 30 degrees from the normal framing it whole) at ``--res``: the yarn far field
    (``--cloth fibers``, every yarn below a pixel) with ``--ref-passes`` more passes as the
    reference, and the volume from the yarn density. Generation: CPU and wall seconds, the
    process's peak memory over its memory before, against ``cloth.memory_estimate``. Per mode:
    translate and voxelization time, grid bytes, peak memory, CPU seconds per spp, the errors
    of :func:`mode_errors` against the reference (the whole image, ``--cloth-box`` and the
    cloth's projected rectangle) and the equal-time errors at ``--budgets`` CPU seconds.
    ``--auto``: what ``--cloth auto`` chooses and why; ``--explicit-estimate``: the explicit
    fibers' segments at lod_scale 0 and 1 (bench/cloth_bench.py's ``estimate_weave``) and their
    memory at :data:`EXPLICIT_BYTES_PER_SEGMENT`."""
    import usdfiber  # noqa: F401  (registers the schemas first)

    from cloth_bench import build_stage, cloth_mask, estimate_weave
    from usdfiber import cloth
    from usdfiber.backend import mitsuba
    from usdfiber.bake.cache import TableCache
    from usdfiber.bake.settings import BakeSettings

    mi = mitsuba()
    from usdfiber.translators.mitsuba.scene import SceneOptions

    w, h = (int(v) for v in args.res.split("x"))
    spec = {"kind": "weave", "yarn": "Skala 360", "warps": args.yarns, "wefts": args.yarns, "res": [w, h],
            "cameras": {"whole": 1.0}}
    n = args.yarns
    prim_points = [n * (4 * n + 3), n * (4 * n + 3)]
    before = _memory_mib()
    peak_reset = _reset_peak_memory()
    c0, t0 = time.process_time(), time.perf_counter()
    stage, info = build_stage(spec)
    after = _memory_mib()
    out: dict[str, Any] = {"spec": spec, "cloth_size_mm": info["cloth_size_mm"], "stage_s": time.perf_counter() - t0,
                           "stage_cpu_s": time.process_time() - c0, "spp_per_pass": args.spp, "passes": args.passes,
                           "reference_passes": args.ref_passes, "modes": {},
                           "generation": {"control_points": sum(prim_points),
                                          "memory_estimate_mib": cloth.memory_estimate(prim_points) / 2**20,
                                          "rss_before_mib": before["rss_mib"], "rss_after_mib": after["rss_mib"],
                                          "peak_over_before_mib": (after["peak_mib"] - before["rss_mib"])
                                          if peak_reset else None},
                           "yarn_px_at_centre": info["cameras"]["whole"]["yarn_px_at_centre"],
                           "mm_per_px_at_centre": info["cameras"]["whole"]["mm_per_px_at_centre"]}
    print("generation", json.dumps(out["generation"], default=float), out["stage_s"], file=sys.stderr, flush=True)
    if args.auto:
        out["auto"] = auto_choice(stage, "/Cams/whole", w, h)
        print("auto", json.dumps(out["auto"], default=float), file=sys.stderr, flush=True)
    if args.explicit_estimate:
        c1 = time.process_time()
        est = estimate_weave(spec, [0.0, 1.0])
        out["explicit_estimate"] = {
            "lod": est["lod"], "per_yarn_full": est["per_yarn_full"], "cpu_s": time.process_time() - c1,
            "bytes_per_segment": EXPLICIT_BYTES_PER_SEGMENT,
            "gib": {k: v["segments"] * EXPLICIT_BYTES_PER_SEGMENT / 2**30 for k, v in est["lod"].items()}}
        print("explicit estimate", json.dumps(out["explicit_estimate"], default=float), file=sys.stderr, flush=True)
    bake = BakeSettings(resolution_deg=15, photons=5000, batches=2)
    cache = TableCache(os.environ.get("USDFIBER_CACHE_DIR") or None)
    images: dict[str, np.ndarray] = {}
    modes: list[tuple[str, dict[str, Any]]] = [("far field", dict(cloth="fibers", lod_scale=1.0))]
    if args.explicit:
        modes.append(("fibers", dict(cloth="fibers", lod_scale=0.0)))
    voxels = [float(v) for v in args.voxels.split(",") if v] if args.voxels else [args.voxel_mm]
    for v in voxels:
        modes.append(("volume" if v is None else f"volume, {v:g} mm", dict(cloth="volume", voxel_size=v)))
    reference = "fibers" if args.explicit else "far field"
    for mode, kw in modes:
        mem0 = _memory_mib()
        _reset_peak_memory()
        tr, imgs, rec = time_mode(mi, stage, SceneOptions(resolution=(w, h), spp=args.spp, bake=bake, cache=cache,
                                                          camera="/Cams/whole", **kw), args.spp, args.passes)
        images[mode] = imgs
        rec.update(counts=dict(tr.counts), warnings=list(tr.warnings)[:8],
                   homogenization=[w for w in tr.warnings if "over the gaps" in w],
                   rss_before_mib=mem0["rss_mib"], peak_mib=_memory_mib()["peak_mib"])
        if mode == reference:
            images["reference"], rcpu, _ = render_passes(mi, tr.scene, args.spp, args.ref_passes, 1000)
            out["reference_cpu_s"] = float(np.sum(rcpu))
        out["modes"][mode] = rec
        print(mode, json.dumps(rec, default=float), file=sys.stderr, flush=True)
        del tr
    r0, r1, c0_, c1_ = (int(v) for v in args.cloth_box.split(","))
    mask = cloth_mask(stage, "/Cams/whole", info["cloth_lo"], info["cloth_hi"], w, h)
    ref = images["reference"].mean(axis=0)
    ref_cloth = ref[r0:r1, c0_:c1_]
    for mode, rec in out["modes"].items():
        rec["errors"] = mode_errors(images[mode], images["reference"], args.spp, rec["cpu_s_per_spp"])
        # The cloth only (--cloth-box rows, columns): the mean and per channel against the reference's.
        cl = images[mode].mean(axis=0)[r0:r1, c0_:c1_]
        per_pass = images[mode][:, r0:r1, c0_:c1_].mean(axis=(1, 2, 3))
        rec["cloth_mean_rel"] = float(cl.mean() / ref_cloth.mean() - 1.0)
        rec["cloth_mean_rel_se"] = float(np.std(per_pass, ddof=1) / np.sqrt(len(per_pass)) / ref_cloth.mean())
        rec["cloth_rgb_rel"] = [float(cl[..., k].mean() / ref_cloth[..., k].mean() - 1.0) for k in range(3)]
        # The cloth's projected rectangle (every pixel of it).
        img = images[mode].mean(axis=0)
        per_pass = np.array([p[mask].mean() for p in images[mode]])
        rec["cloth_rect_mean_rel"] = float(img[mask].mean() / ref[mask].mean() - 1.0)
        rec["cloth_rect_mean_rel_se"] = float(np.std(per_pass, ddof=1) / np.sqrt(len(per_pass)) / ref[mask].mean())
    out["equal_time_cpu_s"] = equal_time({m: r["errors"] for m, r in out["modes"].items()},
                                         [float(t) for t in args.budgets.split(",")])
    out["reference"] = reference
    out["cloth_box_rows_cols"] = [r0, r1, c0_, c1_]
    out["cloth_rect_pixels"] = int(mask.sum())
    if args.save:
        np.savez_compressed(args.save, **images)
    return out


def part_far_field_cause(args: argparse.Namespace) -> dict[str, Any]:
    """The far field's excess on a sheer weave, isolated: the same Skala 360 yarns and framing
    (bench/cloth_bench.py's card and camera, yarns about ``--res``'s 0.9 px), as explicit fibers
    (the reference) and as the yarn far field, in variants that keep or remove what lies
    between the yarns: ``sheer`` (``--yarns`` warps and wefts 2.5 diameters apart, the shirt
    panel's weave), ``sparse`` (a quarter of them, 10 diameters apart: no neighbour within
    reach, crossings 4x rarer), ``warps`` (the sheer weave's warps alone: no crossings) and
    ``single`` (one warp). Per variant: the mean over the cloth's pixels (the projected
    rectangle, bench/cloth_bench.py's ``cloth_mask``) relative to the explicit fibers', per
    channel, and relative to what the yarns add over the bare card (``(far - explicit) /
    (explicit - card)``: the far field's error in the yarns' own light)."""
    import usdfiber  # noqa: F401  (registers the schemas first)
    from pxr import Gf, UsdGeom

    from cloth_bench import new_stage, cloth_mask, dress
    from usdfiber import cloth, presets
    from usdfiber.backend import mitsuba
    from usdfiber.bake.cache import TableCache
    from usdfiber.bake.settings import BakeSettings

    mi = mitsuba()
    from usdfiber.translators.mitsuba.scene import SceneOptions, translate_stage

    w, h = (int(v) for v in args.res.split("x"))
    bake = BakeSettings(resolution_deg=15, photons=5000, batches=2)
    cache = TableCache(os.environ.get("USDFIBER_CACHE_DIR") or None)
    d = presets.yarn_preset("Skala 360").yarn_diameter_mm
    n = args.yarns
    span = (n - 1) * 2.5 * d                        # every variant spans the sheer weave's size
    k = max(2, n // 4)
    # (warps, wefts, spacing mm, prim hidden)
    variants = {"sheer": (n, n, 2.5 * d, None), "sparse": (k, k, span / (k - 1), None),
                "warps": (n, n, 2.5 * d, "Weft"), "single": (1, n, 2.5 * d, "Weft")}
    chosen = [v for v in args.variants.split(",") if v] or list(variants)
    out: dict[str, Any] = {"res": [w, h], "spp_per_pass": args.spp, "passes": args.passes,
                           "reference_passes": args.ref_passes, "yarn_diameter_mm": d, "dye": args.dye,
                           "card": args.card, "variants": {}}
    for name in chosen:
        warps, wefts, spacing, hide = variants[name]
        stage = new_stage()
        UsdGeom.Xform.Define(stage, "/Cloth")
        dyed = dict(dye="disperseBlue", depth_of_shade=1.0) if args.dye == "disperseBlue" else {}
        cloth.plain_weave(stage, "/Cloth/Weave", warps=warps, wefts=wefts, yarn="Skala 360", spacing=spacing, **dyed)
        if hide:
            UsdGeom.Imageable(stage.GetPrimAtPath(f"/Cloth/Weave/{hide}")).MakeInvisible()
        lo = np.array([-d, -d, -d])
        hi = np.array([span + d, span + d, d])     # the sheer weave's box: the same framing for all
        spec = {"yarn": "Skala 360", "res": [w, h], "cameras": {"whole": 1.0}}
        info = dress(stage, spec, lo, hi)
        UsdGeom.Mesh(stage.GetPrimAtPath("/Card")).CreateDisplayColorAttr([Gf.Vec3f(args.card, args.card, args.card)])
        mask = cloth_mask(stage, "/Cams/whole", lo.tolist(), hi.tolist(), w, h)
        rec: dict[str, Any] = {"warps": warps, "wefts": wefts, "spacing_mm": spacing, "hidden": hide,
                               "yarn_px_at_centre": info["cameras"]["whole"]["yarn_px_at_centre"], "modes": {}}
        imgs: dict[str, np.ndarray] = {}
        for mode, kw, passes in (("explicit", dict(lod_scale=0.0), args.ref_passes),
                                 ("far field", dict(lod_scale=1.0), args.passes)):
            c0 = time.process_time()
            tr = translate_stage(stage, SceneOptions(resolution=(w, h), spp=args.spp, bake=bake, cache=cache,
                                                     camera="/Cams/whole", **kw))
            imgs[mode], cpu, _ = render_passes(mi, tr.scene, args.spp, passes, 1 if mode == "explicit" else 500)
            rec["modes"][mode] = {"translate_cpu_s": time.process_time() - c0 - float(np.sum(cpu)),
                                  "cpu_s_per_spp": float(np.median(cpu)) / args.spp,
                                  "counts": {k: v for k, v in tr.counts.items()
                                             if k in ("fiber_curves", "fiber_segments", "yarn_far_fields")}}
            del tr
        for p in ("/Cloth/Weave/Warp", "/Cloth/Weave/Weft"):
            UsdGeom.Imageable(stage.GetPrimAtPath(p)).MakeInvisible()
        tr = translate_stage(stage, SceneOptions(resolution=(w, h), spp=args.spp, bake=bake, cache=cache,
                                                 camera="/Cams/whole"))
        card, _, _ = render_passes(mi, tr.scene, args.spp, 2, 900)
        ex, ff, cd = (imgs["explicit"].mean(axis=0), imgs["far field"].mean(axis=0), card.mean(axis=0))
        m3 = mask[..., None]

        def cloth_mean(a: np.ndarray, k: int | None = None) -> float:
            a = a if k is None else a[..., k:k + 1]
            return float((a * m3).sum() / (m3.sum() * a.shape[-1]))

        def se(passes_: np.ndarray) -> float:
            per = np.array([cloth_mean(p_) for p_ in passes_])
            return float(per.std(ddof=1) / np.sqrt(len(per)))

        rec["cloth_pixels"] = int(mask.sum())
        rec["cloth_mean"] = {"explicit": cloth_mean(ex), "far field": cloth_mean(ff), "card": cloth_mean(cd),
                             "explicit_se": se(imgs["explicit"]), "far_field_se": se(imgs["far field"])}
        rec["far_vs_explicit"] = cloth_mean(ff) / cloth_mean(ex) - 1.0
        rec["far_vs_explicit_rgb"] = [cloth_mean(ff, k) / cloth_mean(ex, k) - 1.0 for k in range(3)]
        rec["far_error_in_yarn_light"] = (cloth_mean(ff) - cloth_mean(ex)) / (cloth_mean(ex) - cloth_mean(cd))
        out["variants"][name] = rec
        print(name, json.dumps(rec, default=float), file=sys.stderr, flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("part", choices=("swatch", "swatch-errors", "bricks", "shirt", "shirt-render", "auto",
                                     "far-field-cause"))
    ap.add_argument("--res", default=None, help="swatch: 160x60; shirt-render: 160x120; bricks: 80x30")
    ap.add_argument("--spp", type=int, default=None,
                    help="swatch, shirt-render: samples per pass (2); bricks: per render (4)")
    ap.add_argument("--passes", type=int, default=4, help="swatch, shirt-render: timed passes per mode")
    ap.add_argument("--ref-passes", type=int, default=24, help="swatch: reference passes (explicit fibers)")
    ap.add_argument("--modes", default="", help="swatch: modes separated by ';' (default: all of them)")
    ap.add_argument("--bricks", default=None, help="swatch: other brick sizes (default none; 0: one majorant); "
                                                  "bricks: the sizes to time (default 8,0)")
    ap.add_argument("--fine", default="2", help="swatch: other voxels per pixel footprint")
    ap.add_argument("--save", default="", help="swatch, shirt-render: save the images (.npz)")
    ap.add_argument("--inputs", default="", help="swatch-errors: result.json,images.npz,... of swatch runs")
    ap.add_argument("--budgets", default="10,30,100",
                    help="swatch-errors, shirt-render: CPU seconds for the equal-time errors")
    ap.add_argument("--auto", action="store_true", help="shirt-render: also what --cloth auto chooses, and why")
    ap.add_argument("--explicit-estimate", action="store_true",
                    help="shirt-render: the explicit fibers' segments and memory, estimated without translating")
    ap.add_argument("--yarns", type=int, default=5000, help="shirt: yarns; shirt-render: warps = wefts of the piece")
    ap.add_argument("--voxel-mm", type=float, default=None,
                    help="voxel edge, mm (shirt: 1.04, the 640-pixel view's footprint; "
                         "bricks: 0.0713, the 320 x 120 one's)")
    ap.add_argument("--explicit", action="store_true",
                    help="shirt-render: also explicit fibers, then the reference (small pieces only)")
    ap.add_argument("--voxels", default="", help="shirt-render: volume voxel edges in mm, comma separated "
                                                 "(default: --voxel-mm, else the pixel footprint)")
    ap.add_argument("--cloth-box", default="30,110,30,130",
                    help="shirt-render: rows r0,r1 and columns c0,c1 of the cloth-only region")
    ap.add_argument("--dye", default="disperseBlue", choices=("disperseBlue", "none"),
                    help="far-field-cause: the yarns' dye (1 %% disperseBlue, the shirt panel's) or none")
    ap.add_argument("--card", type=float, default=0.5, help="far-field-cause: the card's reflectance")
    ap.add_argument("--variants", default="", help="far-field-cause: sheer,sparse,warps,single (default all)")
    ap.add_argument("--rounds", type=int, default=2,
                    help="bricks: alternated timed renders per brick size; auto: timed choices")
    args = ap.parse_args(argv)
    if args.bricks is None:
        args.bricks = "8,0" if args.part == "bricks" else ""
    if args.spp is None:
        args.spp = 4 if args.part == "bricks" else 2
    if args.res is None:
        args.res = {"bricks": "80x30", "shirt-render": "160x120", "auto": "160x120",
                    "far-field-cause": "160x120"}.get(args.part, "160x60")
    if args.voxel_mm is None and args.part != "shirt-render":     # shirt-render: the pixel footprint
        args.voxel_mm = 0.0713 if args.part == "bricks" else 665.0 / 640.0
    out = {"machine": machine(), "part": args.part, "argv": sys.argv[1:] if argv is None else argv}
    out.update({"swatch": part_swatch, "swatch-errors": part_swatch_errors, "bricks": part_bricks,
                "shirt": part_shirt, "shirt-render": part_shirt_render, "auto": part_auto,
                "far-field-cause": part_far_field_cause}[args.part](args))
    out["machine"]["load_average_end"] = os.getloadavg()
    json.dump(out, sys.stdout, indent=1, default=float)
    print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
