"""Render benchmarks: the tabulated fiber BCSDF against Mitsuba's built-in ``hair`` BSDF.

    python bench/render_bench.py          # full run (~14 min on 2 shared cores) -> bench/results/render.json
    python bench/render_bench.py --quick  # smoke test (< 1 min), not a benchmark; JSON in $TMPDIR
    python bench/render_bench.py --parts timing,convergence,scale --ref-spp 1024
    python bench/render_bench.py --parts timing --cases ours_silk,ours_silk_path --out /tmp/t.json

Parts (each prints a markdown table; all numbers go to the JSON with the machine, the load
average before and after, the git HEAD and the SHA-256 of the renderer's sources):

* ``timing``: time per sample per pixel on IDENTICAL curves. The scene is a mat of 10,000
  straight-ish fibers (B-splines, 5 segments each) in one ``bsplinecurve`` shape, a perspective
  camera, a constant dome plus a directional light, max_depth 8, 256 x 256. The integrator is
  the one ``translate_stage`` picks for the BSDF (``scene.fiber_integrator``): ``usdfiber_path``
  (``translators/mitsuba/integrator.py``) when it lets rays pass (a ``Null`` component: non-round
  fibers), else ``path``.
  BSDFs: ``usdfiber_bcsdf`` with a round polyester table and with a non-round silk table,
  ``hair``, and ``diffuse`` as a floor. Silk also with ``volpath`` (the previous choice, the
  reference of its error check) and with ``usdfiber_path`` deciding pass-throughs in the
  BSDF's ``sample`` (``fiber_pass`` false). Profiling variants: silk with ``path`` (opaque
  shadow rays), with pass-through off, and with the table on its coarse native grid;
  polyester and ``hair`` with ``volpath``, ``hair`` with ``usdfiber_path`` (with
  ``null_shadows`` false it draws ``path``'s samples: the Python integrator's own cost; as is,
  hair's ``Null`` component makes its shadow rays walk through the curves).
  ``--cases`` times a subset (``hair``, the reference of every ratio, always). Error at the
  timed spp: each round keeps every case's high-spp image (seeds distinct per case and
  round); the rounds give each case's noise (relative RMS difference between rounds, per
  image) and compare silk under ``usdfiber_path`` with ``volpath`` block by block (the ratio
  R of the squared block differences to their variance estimated from the rounds, about 1
  for equal images). Timing uses ``dr.eval(img); dr.sync_thread()``. A
  warm-up render comes first, and its kernel compile time (Dr.Jit's kernel history) is reported
  separately. The compile is cold: ``HOME`` points to an empty directory, so Dr.Jit's on-disk
  kernel cache starts empty (``--warm-kernel-cache`` keeps it). Time per spp is the slope of
  the time between two spp counts (wall and CPU time; cases run in rounds, see
  ``part_timing``); the intercept is the per-call overhead (tracing the Python BSDF into the
  kernel, launching).
  Also times the BSDF calls alone (``eval_pdf`` and ``sample`` on 2^20 lanes) and counts the
  gather call sites (LLVM masked gathers and Dr.Jit packet gathers) in the IR of the render
  kernel. Only one BSDF is alive at a time: Dr.Jit traces
  a symbolic BSDF call into the kernel for every live BSDF instance.
* ``convergence``: speed against error, same scene at ``--conv-res`` (128 x 128, so that a
  1024 spp reference fits a few minutes on 2 shared cores). A reference is rendered at
  ``--ref-spp`` (passes of 64 spp, distinct seeds) for our BSDF (polyester) and for ``hair``;
  each is measured against its own reference. Then 1, 4, 16 and 64 spp renders with other
  seeds are timed. Error: relative RMSE over all pixels and channels,
  ``sqrt(mean((img - ref)^2) / mean(ref^2))``, corrected for the reference's own noise as
  ``e = d sqrt(M / (M + N))`` (the raw d is in the JSON), and the raw relative MAE.
* ``scale``: translation time and peak memory against the fiber segment count (1e3 ... 1e6),
  each size in a fresh subprocess. The stage is built in memory: one BasisCurves prim with
  polyester FiberAPI, its table pre-baked into a temporary cache. Pieces are timed around
  the functions ``translate_stage`` calls: curve conversion, reference normals, the fiber bank,
  the BSDF, the curve shape, and the Mitsuba scene (with its BVH). The peak RSS comes from
  ``/proc/self/status`` ``VmHWM``, reset through ``/proc/self/clear_refs`` before the
  translation, and an RSS sampler thread (10 ms) backs it up. The largest size is also rendered.
"""
from __future__ import annotations

import argparse
import gc
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import bench_common  # noqa: E402
from bench_common import RssSampler, Timer, json_default as _json_default, md_table as _table, proc_status_mib  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))           # run from a checkout without installing

RESULTS = ROOT / "bench" / "results"
SOURCES = ("translators/mitsuba/fiber_bsdf.py", "translators/mitsuba/fiber_bank.py", "translators/mitsuba/curves.py",
           "translators/mitsuba/fibers.py", "translators/mitsuba/scene.py", "translators/mitsuba/integrator.py", "translators/mitsuba/render.py")
TARGETS = {"time_per_spp_ratio_vs_hair": 1.3, "translate_seconds_1M_segments": 10.0}

# Tables: polyester as `usdfiber render` bakes it on demand (RENDER_BAKE_SETTINGS: 6 deg,
# 100k photons). Silk (4 cross-section variants; variant 0 is used) is baked at 15 deg and laid
# out by the bank on the renderer's 6 deg grid (``FiberBank.build(resolution_deg=...)``
# resamples with the table's own interpolation). That is the memory footprint and the lookups
# of a 6 deg silk table: a real 6 deg bake of silk takes ~5 min here, and the cost of a lookup
# does not depend on how the values were obtained.
SILK_BAKE_RES, SILK_PHOTONS, SILK_BANK_RES = 15.0, 16_384, 6.0


# ---------------------------------------------------------------------------------------------
# Environment record
# ---------------------------------------------------------------------------------------------

def machine() -> dict[str, Any]:
    return bench_common.machine()


def git_state() -> dict[str, Any]:
    return bench_common.git_state(ROOT, SOURCES, ("usdfiber", "translators"))


def _fmt_s(x: float) -> str:
    return f"{x * 1e3:.0f} ms" if x < 1 else f"{x:.2f} s"


# ---------------------------------------------------------------------------------------------
# Scene: a mat of straight-ish fibers
# ---------------------------------------------------------------------------------------------

def fiber_mat(n_fibers: int, n_cp: int = 8, radius: float = 0.01, seed: int = 1):
    """``n_fibers`` wavy fibers along x in a rectangular (y, z) lattice, B-spline controls."""
    from usdfiber.translators.mitsuba.curves import CurveGeometry

    rng = np.random.default_rng(seed)
    ny = max(1, int(round(math.sqrt(4.0 * n_fibers))))
    sp = 2.5 * radius
    length = ny * sp
    k = np.arange(n_fibers)
    iy, iz = k % ny, k // ny
    y0 = (iy - 0.5 * (ny - 1)) * sp + rng.uniform(-0.2, 0.2, n_fibers) * radius
    z0 = -iz * sp + rng.uniform(-0.2, 0.2, n_fibers) * radius
    ph = rng.uniform(0.0, 2 * math.pi, (2, n_fibers))
    x = np.linspace(-0.5 * length, 0.5 * length, n_cp)
    wl = length / 2.0
    pts = np.empty((n_fibers, n_cp, 3))
    pts[:, :, 0] = x[None, :]
    pts[:, :, 1] = y0[:, None] + 0.3 * radius * np.sin(2 * math.pi * x[None, :] / wl + ph[0][:, None])
    pts[:, :, 2] = z0[:, None] + 0.3 * radius * np.sin(2 * math.pi * x[None, :] / wl + ph[1][:, None])
    n_seg = n_cp - 3
    starts = (k[:, None] * n_cp + np.arange(n_seg)[None, :]).reshape(-1)
    geom = CurveGeometry(points=pts.reshape(-1, 3), radii=np.full(n_fibers * n_cp, radius),
                         segment_start=starts.astype(np.int64),
                         segment_curve=np.repeat(k, n_seg).astype(np.int64), curve_count=n_fibers)
    return geom, length


def matched_hair(mi: Any, eta: float, beta_deg: float) -> Any:
    """``hair`` with no pigment, scale_tilt 0, and roughness matched to a Beckmann beta
    (R lobe std sqrt(2) tan beta, as in tests/mitsuba/test_hair_comparison.py)."""
    from scipy.optimize import brentq

    std = math.sqrt(2.0) * math.tan(math.radians(beta_deg))
    b_m = brentq(lambda b: 0.726 * b + 0.812 * b * b + 3.7 * b ** 20 - std, 0.0, 1.0)
    s = std * math.sqrt(3.0) / math.pi
    b_n = brentq(lambda b: math.sqrt(math.pi / 8) * (0.265 * b + 1.194 * b * b + 5.372 * b ** 22) - s, 0.0, 1.0)
    return mi.load_dict({"type": "hair", "eumelanin": 0.0, "pheomelanin": 0.0, "longitudinal_roughness": b_m,
                         "azimuthal_roughness": b_n, "scale_tilt": 0.0, "int_ior": eta})


def mat_scene(mi: Any, geom: Any, length: float, bsdf: Any, res: int, max_depth: int = 8,
              integrator: str | dict = "path") -> Any:
    from usdfiber.translators.mitsuba.curves import make_curve_shape

    d = mat_scene_dict(mi, length, res, max_depth, integrator)
    d["fibers"] = make_curve_shape(geom, bsdf, "fibers")
    return mi.load_dict(d)


def mat_scene_dict(mi: Any, length: float, res: int, max_depth: int = 8,
                   integrator: str | dict = "path") -> dict[str, Any]:
    """The mat's scene without the fibers; ``integrator``: a type, or a dict of properties."""
    origin = [0.0, -0.6 * length, 1.1 * length]
    integ = dict(integrator) if isinstance(integrator, dict) else {"type": integrator}
    return {
        "type": "scene",
        "integrator": {"max_depth": max_depth, **integ},
        "sensor": {"type": "perspective", "fov": 45.0,
                   "to_world": mi.ScalarTransform4f().look_at(origin=origin, target=[0.0, 0.0, -0.04 * length],
                                                               up=[0.0, 0.0, 1.0]),
                   "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": 1}},
        "dome": {"type": "constant", "radiance": {"type": "rgb", "value": 0.5}},
        "sun": {"type": "directional", "direction": [-0.3, 0.5, -1.0], "irradiance": {"type": "rgb", "value": 3.0}},
    }


def render_timed(mi: Any, scene: Any, spp: int, seed: int) -> tuple[float, float, np.ndarray]:
    """(wall s, cores, image) of one render, synchronized."""
    import drjit as dr

    with Timer() as t:
        img = mi.render(scene, spp=spp, seed=seed)
        dr.eval(img)
        dr.sync_thread()
    return t.wall, t.cores, np.array(img)


def _kernel_stats(history: list[dict]) -> dict[str, Any]:
    """Compile time (codegen + LLVM backend, s), cache hits and gathers in the IR of the launches."""
    comp = sum(h.get("codegen_time", 0.0) + h.get("backend_time", 0.0) for h in history) / 1e3
    big = max(history, key=lambda h: h.get("operation_count", 0)) if history else {}
    ir = big["ir"].getvalue() if big and big.get("ir") is not None else ""
    return {
        "kernels": len(history),
        "compile_seconds": comp,
        "cache_hits": sum(int(h.get("cache_hit", 0)) for h in history),
        "disk_cache_hits": sum(int(h.get("cache_disk", 0)) for h in history),
        "largest_kernel_ops": int(big.get("operation_count", 0)) if big else 0,
        # Gather call sites: LLVM's masked gathers and Dr.Jit's packet gathers (one call reads
        # a whole 2/4/8-vector per lane, e.g. @gather_4xf16).
        "largest_kernel_gather_calls": sum(1 for line in ir.splitlines()
                                           if "call" in line and ("llvm.masked.gather" in line or "@gather_" in line)),
    }


TRANSLATOR = "translator"


def translator_integrator(mi: Any, bsdf: Any) -> str:
    """The integrator ``translate_stage`` uses for fibers with ``bsdf``: ``usdfiber_path`` when
    the BSDF has a null (pass-through) component, whose shadow rays it passes; else ``path``."""
    from usdfiber.translators.mitsuba.scene import fiber_integrator

    return fiber_integrator(mi, bsdf)


def integrator_label(integ: str | dict) -> str:
    if isinstance(integ, str):
        return integ
    extra = ", ".join(f"{k} {str(v).lower()}" for k, v in integ.items() if k != "type")
    return f"{integ['type']} ({extra})" if extra else integ["type"]


def compare_images(a: list[np.ndarray], b: list[np.ndarray], block: int = 16) -> dict[str, float]:
    """Two cases' images, one per round (independent seeds): are they the same image?

    Per block of ``block`` x ``block`` pixels and channel, d is the difference of the two
    cases' means over the rounds, and v its variance estimated from each case's spread over
    the rounds (sample variance / rounds, summed). R = sum d^2 / sum v is about 1 when both
    render the same image (2 / sqrt(blocks) is its order of fluctuation); z is the difference
    of the image means in standard deviations estimated the same way.
    """
    def blocks(img: np.ndarray) -> np.ndarray:
        h, w, c = img.shape
        return img[: h - h % block, : w - w % block].reshape(h // block, block, w // block, block, c).mean(axis=(1, 3))

    ba, bb = np.stack([blocks(x) for x in a]), np.stack([blocks(x) for x in b])
    d = ba.mean(axis=0) - bb.mean(axis=0)
    v = ba.var(axis=0, ddof=1) / len(a) + bb.var(axis=0, ddof=1) / len(b)
    ma, mb = np.array([x.mean() for x in a]), np.array([x.mean() for x in b])
    sd = math.sqrt(ma.var(ddof=1) / len(a) + mb.var(ddof=1) / len(b))
    return {"R": float((d ** 2).sum() / v.sum()), "blocks": int(d.size), "mean_a": float(ma.mean()),
            "mean_b": float(mb.mean()), "mean_diff_rel": float((ma.mean() - mb.mean()) / mb.mean()),
            "z": float((ma.mean() - mb.mean()) / sd) if sd > 0 else 0.0}


def image_noise(imgs: list[np.ndarray]) -> float:
    """Relative RMS noise of one image, from independent renders of it:
    sqrt(mean over pixels of the sample variance) / mean pixel."""
    st = np.stack(imgs).astype(np.float64)
    return float(math.sqrt(float(st.var(axis=0, ddof=1).mean())) / float(st.mean()))


# ---------------------------------------------------------------------------------------------
# Tables
# ---------------------------------------------------------------------------------------------

def _fiber_stage(n_segments: int, preset: str = "polyester", seed: int = 3):
    """An in-memory stage with one fiber BasisCurves prim of about ``n_segments`` segments."""
    import usdfiber  # noqa: F401
    from pxr import Usd, UsdGeom, Vt

    from usdfiber import authoring

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    UsdGeom.SetStageUpAxis(stage, "Y")
    per = 10                                         # segments per curve (13 bspline vertices)
    n_curves = max(1, n_segments // per)
    nv = per + 3
    rng = np.random.default_rng(seed)
    side = 2.0 * math.sqrt(n_curves / 1e4)          # mm: about the density of a yarn cross-section
    y0 = rng.uniform(-side / 2, side / 2, n_curves)
    z0 = rng.uniform(-side / 2, side / 2, n_curves)
    x = np.linspace(-2.5, 2.5, nv)
    pts = np.empty((n_curves, nv, 3), np.float32)
    pts[:, :, 0] = x
    pts[:, :, 1] = y0[:, None] + 0.02 * np.sin(x[None, :] * 3.0 + rng.uniform(0, 6.3, n_curves)[:, None])
    pts[:, :, 2] = z0[:, None] + 0.02 * np.cos(x[None, :] * 2.0 + rng.uniform(0, 6.3, n_curves)[:, None])
    curves = UsdGeom.BasisCurves.Define(stage, "/Fibers")
    curves.CreateTypeAttr("cubic")
    curves.CreateBasisAttr("bspline")
    curves.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts.reshape(-1, 3)))
    curves.CreateCurveVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(n_curves, nv, np.int32)))
    curves.CreateWidthsAttr(Vt.FloatArray([0.01]))   # 10 um, polyester's preset diameter
    curves.SetWidthsInterpolation("constant")
    authoring.apply_fiber(curves.GetPrim(), preset)
    return stage, n_curves * per


def prebake(cache_dir: Path, settings: Any) -> dict[str, Any]:
    """Bake polyester's table(s) into ``cache_dir`` through the translator (as a render would)."""
    from usdfiber.bake.cache import TableCache
    from usdfiber.translators.mitsuba.scene import SceneOptions, translate_stage

    stage, _ = _fiber_stage(100)
    with Timer() as t:
        tr = translate_stage(stage, SceneOptions(resolution=(16, 16), spp=1, bake=settings,
                                                 cache=TableCache(cache_dir)))
    return {"seconds": t.wall, "tables": len(tr.fibers.tables), "table_seconds": tr.times["tables"],
            "rel_error_rms": [float(np.sqrt(np.mean(x.rel_error ** 2))) for x in tr.fibers.tables]}


def polyester_tables(cache_dir: Path, settings: Any) -> list[Any]:
    from usdfiber.bake.cache import TableCache
    from usdfiber.bcsdf import tables_for_prim

    stage, _ = _fiber_stage(100)
    return tables_for_prim(stage.GetPrimAtPath("/Fibers"), settings, True, cache=TableCache(cache_dir))


# ---------------------------------------------------------------------------------------------
# Part 1: time per spp
# ---------------------------------------------------------------------------------------------

def part_timing(args: argparse.Namespace, ctx: dict[str, Any]) -> dict[str, Any]:
    from usdfiber.backend import mitsuba

    mi = mitsuba()
    import drjit as dr

    from usdfiber.bake.baker import bake_request
    from usdfiber.bake.requests import requests_from_preset
    from usdfiber.bake.settings import BakeSettings
    from usdfiber.translators.mitsuba.curves import make_curve_shape, reference_normals
    from usdfiber.translators.mitsuba.fiber_bank import FiberBank, FiberSlot
    from usdfiber.translators.mitsuba.fiber_bsdf import fiber_bsdf

    out: dict[str, Any] = {}
    geom, length = fiber_mat(args.fibers)
    seg_ref = reference_normals(geom)
    rng = np.random.default_rng(5)
    seg_psi = rng.uniform(0, 2 * math.pi, geom.curve_count)[geom.segment_curve]
    n_seg = geom.segment_count
    cover = mi.load_dict({"type": "scene", "integrator": {"type": "depth"},
                          "sensor": mat_scene_dict(mi, length, args.res)["sensor"],
                          "fibers": make_curve_shape(geom, None, "fibers")})
    coverage = float(np.mean(np.array(mi.render(cover, spp=4))[..., 0] > 0))
    del cover                    # its shape's default BSDF must not stay alive (see below)
    out["scene"] = {"fibers": geom.curve_count, "segments": n_seg, "resolution": args.res, "max_depth": 8,
                    "radius": 0.01, "patch": length, "fiber_pixel_fraction": coverage}
    print(f"scene: {geom.curve_count} fibers, {n_seg} segments, fibers cover {100 * coverage:.0f} % of the pixels")

    poly = ctx["polyester_tables"]
    req = requests_from_preset("silk")[0]
    silk_settings = BakeSettings(resolution_deg=args.silk_res, photons=args.silk_photons, batches=2)
    with Timer() as t:
        silk = bake_request(req, silk_settings)
    out["silk_bake"] = {"seconds": t.wall, "cores": t.cores, "resolution_deg": args.silk_res, "photons": args.silk_photons,
                        "rel_error_rms": float(np.sqrt(np.mean(silk.rel_error ** 2)))}
    print(f"silk table ({args.silk_res:g} deg, {args.silk_photons} photons): baked in {t.wall:.1f} s")
    preq = requests_from_preset("polyester")[0]
    eta_p, beta_p = preq.eta, preq.beta_deg

    def ours(tables, pass_through=True, res=None):
        slots = [FiberSlot(tb, (0.0, 0.0, 0.0)) for tb in tables]
        bank = FiberBank.build(slots, resolution_deg=res)
        seg_slot = (np.arange(geom.curve_count) % len(slots))[geom.segment_curve]
        return fiber_bsdf(mi, bank, seg_slot, seg_psi, seg_ref, pass_through=pass_through), bank

    with Timer() as t:
        bank_silk = FiberBank.build([FiberSlot(silk, (0.0, 0.0, 0.0))], resolution_deg={False: args.silk_bank_res})
    out["silk_bank"] = {"seconds": t.wall, "resolution_deg": args.silk_bank_res, "MB": bank_silk.nbytes() / 1e6}
    bank_poly = FiberBank.build([FiberSlot(poly[0], (0.0, 0.0, 0.0))])
    del bank_silk
    # Each case builds its BSDF when its turn comes and drops it afterwards: Dr.Jit traces a
    # symbolic BSDF call for EVERY live BSDF instance, so live extra BSDFs would enlarge the
    # kernel of every render.
    silk_res = {False: args.silk_bank_res}
    # (name, BSDF factory, description, integrator). TRANSLATOR: the integrator
    # translators/mitsuba/scene.py picks for that BSDF (usdfiber_path when it has a pass-through component).
    from usdfiber.translators.mitsuba.integrator import register as register_integrator

    register_integrator(mi)
    cases: list[tuple[str, Callable[[], Any], str, str | dict]] = [
        ("ours_polyester", lambda: ours(poly[:1])[0],
         f"usdfiber_bcsdf, polyester (round) table, {bank_poly.families[True].resolution_deg:g} deg grid, "
         f"{bank_poly.nbytes() / 1e6:.2f} MB bank", TRANSLATOR),
        ("ours_polyester_volpath", lambda: ours(poly[:1])[0],
         "usdfiber_bcsdf, polyester, volpath (profiling: the cost of volpath itself)", "volpath"),
        ("ours_silk", lambda: ours([silk], res=silk_res)[0],
         f"usdfiber_bcsdf, silk (non-round) table on a {args.silk_bank_res:g} deg grid, "
         f"{out['silk_bank']['MB']:.1f} MB bank, pass-through on", TRANSLATOR),
        ("ours_silk_volpath", lambda: ours([silk], res=silk_res)[0],
         "usdfiber_bcsdf, silk, volpath (the previous choice for pass-through fibers; the reference of "
         "silk's error check)", "volpath"),
        ("ours_silk_generic", lambda: ours([silk], res=silk_res)[0],
         "usdfiber_bcsdf, silk, usdfiber_path deciding pass-throughs in the BSDF's sample, with "
         "next-event estimation at every hit, as volpath", {"type": "usdfiber_path", "fiber_pass": False}),
        ("ours_silk_path", lambda: ours([silk], res=silk_res)[0],
         "usdfiber_bcsdf, silk, path (profiling: shadow rays treat the tubes as opaque, wrong for "
         "non-round fibers)", "path"),
        ("ours_silk_no_pass", lambda: ours([silk], pass_through=False, res=silk_res)[0],
         "usdfiber_bcsdf, silk, pass-through off (profiling only: wrong for non-round fibers)", TRANSLATOR),
        ("ours_silk_coarse", lambda: ours([silk])[0],
         f"usdfiber_bcsdf, the same silk table on its own {args.silk_res:g} deg grid "
         f"(profiling: a bank small enough for the CPU caches)", TRANSLATOR),
        ("hair", lambda: matched_hair(mi, eta_p, beta_p),
         f"hair, no pigment, eta {eta_p}, roughness matched to beta {beta_p} deg", "path"),
        ("hair_volpath", lambda: matched_hair(mi, eta_p, beta_p), "hair, volpath (profiling)", "volpath"),
        ("hair_usdfiber_path", lambda: matched_hair(mi, eta_p, beta_p),
         "hair, usdfiber_path with null_shadows false (profiling: the Python integrator drawing path's "
         "samples)", {"type": "usdfiber_path", "null_shadows": False}),
        ("hair_usdfiber_path_walk", lambda: matched_hair(mi, eta_p, beta_p),
         "hair, usdfiber_path (profiling: hair has a Null component too, so shadow rays walk through "
         "the curves by closest hits instead of one occlusion test)", "usdfiber_path"),
        ("diffuse", lambda: mi.load_dict({"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.8}}),
         "diffuse, reflectance 0.8", "path"),
    ]
    if args.cases:
        unknown = set(args.cases) - {c[0] for c in cases}
        if unknown:
            raise SystemExit(f"--cases: unknown case(s) {sorted(unknown)}")
        # hair is the reference of every ratio: always timed.
        cases = [c for c in cases if c[0] in args.cases or c[0] == "hair"]
    spp_lo, spp_hi = args.spp_pair
    # BSDF calls alone: random lanes, eval_pdf and sample, after a warm-up.
    n = 1 << 20 if not args.quick else 1 << 16
    r2 = np.random.default_rng(9)
    prim_np = r2.integers(0, n_seg, n).astype(np.uint32)

    def unit(v):
        return v / np.linalg.norm(v, axis=0, keepdims=True)

    wi_np = unit(r2.normal(size=(3, n)))
    wi_np[2] = np.abs(wi_np[2])
    wo_np = unit(r2.normal(size=(3, n)))
    u_np = r2.random((3, n)).astype(np.float32)

    calls: dict[str, Any] = {}
    # Rounds: every case once per round (BSDF and scene rebuilt, one BSDF alive at a time), so
    # that all cases see the same mix of machine load; medians over rounds. CPU time (all
    # threads) per spp is reported next to wall time: it is far less sensitive to other
    # processes competing for the 2 cores.
    rec: dict[str, dict[str, Any]] = {name: {"desc": desc, "integrator": integ, "wall": {spp_lo: [], spp_hi: []},
                                            "cpu": {spp_lo: [], spp_hi: []}, "warm_1spp": [],
                                            "eval_pdf": [], "sample": [], "images": []} for name, _, desc, integ in cases}
    ctx_b = mi.BSDFContext()
    for rnd in range(args.repeats):
        for ci, (name, make, desc, integ) in enumerate(cases):
            r = rec[name]
            gc.collect()
            bsdf = make()
            if integ == TRANSLATOR:
                integ = r["integrator"] = translator_integrator(mi, bsdf)
            scene = mat_scene(mi, geom, length, bsdf, args.res, integrator=integ)
            if rnd == 0:
                dr.kernel_history_clear()
                with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
                    w0, _, img = render_timed(mi, scene, 1, seed=0)
                r["kernel"] = _kernel_stats(dr.kernel_history())
                dr.kernel_history_clear()
                r["first_render_1spp_s"] = w0
                r["mean_pixel"] = float(img.mean())
            w1, _, _ = render_timed(mi, scene, 1, seed=1)    # trace + launch (kernel in memory)
            r["warm_1spp"].append(w1)
            for spp in (spp_lo, spp_hi):
                # Seeds distinct per case and round: the high-spp images are independent
                # renders, the error check's samples.
                with Timer() as t:
                    img = mi.render(scene, spp=spp, seed=10 + 2 * rnd + (spp == spp_hi) + 1000 * ci)
                    dr.eval(img)
                    dr.sync_thread()
                r["wall"][spp].append(t.wall)
                r["cpu"][spp].append(t.cpu)
            r["images"].append(np.array(img, dtype=np.float32))
            # The BSDF calls alone, on the same random lanes for every case.
            si = dr.zeros(mi.SurfaceInteraction3f, n)
            si.wi = mi.Vector3f(*[mi.Float(x.astype(np.float32)) for x in wi_np])
            si.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
            si.prim_index = mi.UInt32(prim_np)
            vo = mi.Vector3f(*[mi.Float(x.astype(np.float32)) for x in wo_np])
            u1, u2 = mi.Float(u_np[0]), mi.Vector2f(mi.Float(u_np[1]), mi.Float(u_np[2]))
            for op in ("eval_pdf", "sample"):
                for rep in range(3):
                    with Timer() as t:
                        if op == "eval_pdf":
                            v, p = bsdf.eval_pdf(ctx_b, si, vo)
                            dr.eval(v, p)
                        else:
                            bs, wgt = bsdf.sample(ctx_b, si, u1, u2)
                            dr.eval(bs, wgt)
                        dr.sync_thread()
                    if rnd > 0 or rep > 0:                     # the very first call compiles
                        r[op].append(t.cpu / n * 1e9)
            del scene, bsdf, si, vo, u1, u2
            gc.collect()
            dr.flush_malloc_cache()
            print(f"  round {rnd + 1}/{args.repeats} {name:18s} {spp_hi} spp: {r['wall'][spp_hi][-1]:.2f} s wall, "
                  f"{r['cpu'][spp_hi][-1]:.2f} s CPU ({r['cpu'][spp_hi][-1] / r['wall'][spp_hi][-1]:.2f} cores)")

    res = {}
    for name, r in rec.items():
        r["integrator"] = integrator_label(r["integrator"])
        per = {}
        for kind in ("wall", "cpu"):
            lo, hi = float(np.median(r[kind][spp_lo])), float(np.median(r[kind][spp_hi]))
            per[kind] = ((hi - lo) / (spp_hi - spp_lo), lo - spp_lo * (hi - lo) / (spp_hi - spp_lo))
        cores = [c / w for c, w in zip(r["cpu"][spp_hi], r["wall"][spp_hi])]
        res[name] = {"desc": r["desc"], "integrator": r["integrator"], "first_render_1spp_s": r["first_render_1spp_s"], "kernel": r["kernel"],
                     "warm_render_1spp_s": float(np.median(r["warm_1spp"])),
                     "wall_s": {str(k): v for k, v in r["wall"].items()}, "cpu_s": {str(k): v for k, v in r["cpu"].items()},
                     "time_per_spp_s": per["wall"][0], "per_call_overhead_s": per["wall"][1],
                     "cpu_per_spp_s": per["cpu"][0], "cpu_per_call_overhead_s": per["cpu"][1],
                     "cores_median": float(np.median(cores)), "mean_pixel": r["mean_pixel"],
                     "mean_pixel_hi_spp": float(np.mean([x.mean() for x in r["images"]])),
                     "noise_rel_rms_hi_spp": image_noise(r["images"]) if len(r["images"]) > 1 else None}
        calls[name] = {"eval_pdf": float(np.median(r["eval_pdf"])), "sample": float(np.median(r["sample"]))}
    # Error check: the silk image under each integrator against volpath's, at the timed spp.
    checks = {}
    if args.repeats > 1 and "ours_silk_volpath" in rec:
        # ours_silk_path (opaque shadow rays, pass-throughs counted as bounces) shows what a
        # real difference looks like.
        for name in ("ours_silk", "ours_silk_generic", "ours_silk_path"):
            if name in rec:
                checks[f"{name} vs ours_silk_volpath"] = compare_images(rec[name]["images"],
                                                                        rec["ours_silk_volpath"]["images"])
    for name in ("hair_usdfiber_path", "hair_usdfiber_path_walk"):
        if args.repeats > 1 and name in rec:
            checks[f"{name} vs hair"] = compare_images(rec[name]["images"], rec["hair"]["images"])
    out["error_check"] = {"spp": spp_hi, "images_per_case": args.repeats, "block": 16, "comparisons": checks}
    if checks:
        print(_table(["comparison (images at %d spp, %d rounds)" % (spp_hi, args.repeats), "mean (a)", "mean (b)",
                      "mean diff", "z", "R (blocks)"],
                     [[k, f"{c['mean_a']:.4f}", f"{c['mean_b']:.4f}", f"{100 * c['mean_diff_rel']:+.2f} %", f"{c['z']:+.1f}",
                       f"{c['R']:.2f} ({c['blocks']})"] for k, c in checks.items()]))
    rows = []
    for name, r in res.items():
        r["ratio_vs_hair"] = r["time_per_spp_s"] / res["hair"]["time_per_spp_s"]
        r["cpu_ratio_vs_hair"] = r["cpu_per_spp_s"] / res["hair"]["cpu_per_spp_s"]
        k = r["kernel"]
        comp = "cached" if k["disk_cache_hits"] else f"{k['compile_seconds']:.2f} s"
        rows.append([name, r["desc"], r["integrator"], f"{r['time_per_spp_s'] * 1e3:.0f} ms", f"{r['ratio_vs_hair']:.2f}",
                     f"{r['cpu_per_spp_s'] * 1e3:.0f} ms", f"{r['cpu_ratio_vs_hair']:.2f}",
                     _fmt_s(r["warm_render_1spp_s"]), f"{r['first_render_1spp_s']:.2f} s", comp,
                     k["largest_kernel_gather_calls"], f"{r['cores_median']:.2f}",
                     "-" if r["noise_rel_rms_hi_spp"] is None else f"{100 * r['noise_rel_rms_hi_spp']:.1f} %"])
    print(_table(["case", "BSDF", "integrator", "wall / spp", "x hair", "CPU / spp", "x hair (CPU)", "1-spp render (warm)",
                  "first 1-spp render", "kernel compile", "gathers (IR)", "cores", f"noise at {spp_hi} spp"], rows))
    out["renders"] = res
    out["spp_pair"] = [spp_lo, spp_hi]
    out["bsdf_calls_cpu_ns_per_lane"] = calls
    out["bsdf_calls_lanes"] = n
    print(_table(["case", "eval_pdf CPU ns/lane", "sample CPU ns/lane"],
                 [[k, f"{v['eval_pdf']:.0f}", f"{v['sample']:.0f}"] for k, v in calls.items()]))
    return out


# ---------------------------------------------------------------------------------------------
# Part 2: speed against error
# ---------------------------------------------------------------------------------------------

def part_convergence(args: argparse.Namespace, ctx: dict[str, Any]) -> dict[str, Any]:
    from usdfiber.backend import mitsuba

    mi = mitsuba()
    import drjit as dr

    from usdfiber.bake.requests import requests_from_preset
    from usdfiber.translators.mitsuba.curves import reference_normals
    from usdfiber.translators.mitsuba.fiber_bank import FiberBank, FiberSlot
    from usdfiber.translators.mitsuba.fiber_bsdf import fiber_bsdf

    geom, length = fiber_mat(args.fibers)
    seg_ref = reference_normals(geom)
    seg_psi = np.random.default_rng(5).uniform(0, 2 * math.pi, geom.curve_count)[geom.segment_curve]
    preq = requests_from_preset("polyester")[0]
    bank = FiberBank.build([FiberSlot(ctx["polyester_tables"][0], (0.0, 0.0, 0.0))])
    # One BSDF alive at a time (see part_timing).
    cases = {"ours_polyester": lambda: fiber_bsdf(mi, bank, np.zeros(geom.segment_count, np.int64), seg_psi, seg_ref),
             "hair": lambda: matched_hair(mi, preq.eta, preq.beta_deg)}
    out: dict[str, Any] = {"ref_spp": args.ref_spp, "ref_pass_spp": args.ref_pass, "spps": args.conv_spp,
                           "resolution": args.conv_res,
                           "metric": "sqrt(mean((img-ref)^2)/mean(ref^2)), all pixels and channels; "
                                     "corrected e = d*sqrt(M/(M+N)); rel_mae = mean|img-ref|/mean|ref| (raw)"}
    rows = []
    for name, make in cases.items():
        gc.collect()
        scene = mat_scene(mi, geom, length, make(), args.conv_res)
        render_timed(mi, scene, 1, seed=0)                    # warm-up (compile)
        acc = None
        n_pass = max(1, args.ref_spp // args.ref_pass)
        with Timer() as t_ref:
            for k in range(n_pass):
                _, _, img = render_timed(mi, scene, args.ref_pass, seed=100_000 + k)
                acc = img.astype(np.float64) if acc is None else acc + img
        ref = acc / n_pass
        m = n_pass * args.ref_pass
        denom = float(np.mean(ref ** 2))
        res = {"ref_seconds": t_ref.wall, "ref_cores": t_ref.cores, "ref_mean": float(ref.mean()), "runs": []}
        for spp in args.conv_spp:
            ws, es, maes = [], [], []
            for rep in range(args.conv_repeats):
                w, c, img = render_timed(mi, scene, spp, seed=1000 * spp + rep)
                d = math.sqrt(float(np.mean((img - ref) ** 2)) / denom)
                ws.append(w)
                es.append(d)
                maes.append(float(np.mean(np.abs(img - ref))) / float(np.mean(np.abs(ref))))
            d = float(np.sqrt(np.mean(np.square(es))))
            e = d * math.sqrt(m / (m + spp))
            run = {"spp": spp, "seconds": float(np.median(ws)), "raw_rel_rmse": d, "rel_rmse": e,
                   "raw_rel_mae": float(np.mean(maes)), "all_seconds": ws, "all_raw": es}
            res["runs"].append(run)
            run["cores"] = c
            rows.append([name, spp, f"{run['seconds']:.2f} s", f"{100 * e:.2f} %", f"{100 * d:.2f} %",
                         f"{100 * run['raw_rel_mae']:.2f} %", f"{c:.2f}"])
        # Error constant per spp (e ~ c / sqrt(spp)) from the largest run; time for 1 %.
        big = res["runs"][-1]
        res["c_per_sqrt_spp"] = big["rel_rmse"] * math.sqrt(big["spp"])
        tps = big["seconds"] / big["spp"]            # at this part's resolution
        res["time_per_spp_s"] = tps
        res["spp_for_1pct"] = (res["c_per_sqrt_spp"] / 0.01) ** 2
        res["seconds_for_1pct"] = res["spp_for_1pct"] * tps
        out[name] = res
        print(f"  {name}: reference {m} spp in {t_ref.wall:.0f} s; c = {res['c_per_sqrt_spp']:.3f}; "
              f"1 % rel. RMSE needs {res['spp_for_1pct']:.0f} spp = {res['seconds_for_1pct']:.0f} s")
        del scene
        gc.collect()
        dr.flush_malloc_cache()
    print(_table(["BSDF", "spp", "time", "rel. RMSE (corrected)", "raw", "rel. MAE (raw)", "cores"], rows))
    return out


# ---------------------------------------------------------------------------------------------
# Part 3: translation at scale (one subprocess per size)
# ---------------------------------------------------------------------------------------------

def scale_worker(args: argparse.Namespace) -> None:
    """One size, in this (fresh) process; prints one JSON line."""
    t_import = time.perf_counter()
    import usdfiber  # noqa: F401
    from usdfiber.backend import mitsuba

    mi = mitsuba()
    import drjit as dr

    from usdfiber.bake.settings import BakeSettings
    from usdfiber.bake.cache import TableCache
    from usdfiber.translators.mitsuba.profile import TranslationProfile
    from usdfiber.translators.mitsuba.scene import SceneOptions, translate_stage

    out: dict[str, Any] = {"import_seconds": time.perf_counter() - t_import, "rss_after_import_mib": proc_status_mib("VmRSS")}
    with Timer() as t:
        stage, n_seg = _fiber_stage(args.segments)
    out.update(segments=n_seg, author_seconds=t.wall, rss_after_stage_mib=proc_status_mib("VmRSS"))

    profile = TranslationProfile()
    settings = BakeSettings(**json.loads(args.bake))
    cleared = False
    try:
        with open("/proc/self/clear_refs", "w") as f:      # resets VmHWM to the current RSS
            f.write("5")
        cleared = True
    except OSError:
        pass
    sampler = RssSampler()
    sampler.start()
    with Timer() as t:
        tr = translate_stage(stage, SceneOptions(resolution=(args.res, args.res), spp=args.spp, bake=settings,
                                                 bake_missing=False, cache=TableCache(Path(args.cache)), max_depth=8,
                                                 profile=profile))
    sampler.stop = True
    sampler.join()
    # The translation's steps under this report's names.
    names = {"curves": "curves (USD read + B-spline conversion)", "concatenate": "concatenate",
             "reference_normals": "reference normals", "fiber_bank": "fiber bank", "bsdf": "BSDF (upload)",
             "curve_shape": "curve shape (buffers)", "scene": "Mitsuba scene + BVH"}
    pieces = {names[k]: v for k, v in profile.seconds.items() if k in names}
    out.update(translate_seconds=t.wall, translate_cores=t.cores, pieces=pieces, times=tr.times,
               counts=tr.counts, peak_rss_mib=proc_status_mib("VmHWM") if cleared else None,
               peak_rss_sampled_mib=sampler.peak, hwm_reset=cleared, rss_after_translate_mib=proc_status_mib("VmRSS"))
    out["other_seconds"] = t.wall - sum(pieces.values()) - tr.times.get("tables", 0.0)
    if args.render:
        with Timer() as t:
            img = mi.render(tr.scene, spp=args.spp, seed=0)
            dr.eval(img)
            dr.sync_thread()
        a = np.array(img)
        out["render"] = {"seconds": t.wall, "cores": t.cores, "spp": args.spp, "resolution": args.res,
                         "finite": bool(np.all(np.isfinite(a))), "mean": float(a.mean()),
                         "peak_rss_mib": proc_status_mib("VmHWM")}
    print("RESULT " + json.dumps(out, default=_json_default))


def part_scale(args: argparse.Namespace, ctx: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {"sizes": [], "bake_settings": ctx["bake_settings"]}
    rows = []
    for n in args.sizes:
        cmd = [sys.executable, str(Path(__file__).resolve()), "_scale_worker", "--segments", str(n),
               "--cache", str(ctx["cache_dir"]), "--bake", json.dumps(ctx["bake_settings"]),
               "--res", str(args.scale_res), "--spp", str(args.scale_spp)]
        if n == max(args.sizes):
            cmd.append("--render")
        env = dict(os.environ, USDFIBER_CACHE_DIR=str(ctx["cache_dir"]))
        t0 = time.perf_counter()
        p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=1800)
        wall = time.perf_counter() - t0
        line = next((l for l in p.stdout.splitlines() if l.startswith("RESULT ")), None)
        if p.returncode != 0 or line is None:
            print(p.stdout[-3000:], p.stderr[-3000:], file=sys.stderr)
            raise RuntimeError(f"scale worker for {n} segments failed (exit {p.returncode})")
        r = json.loads(line[len("RESULT "):])
        r["process_wall_seconds"] = wall
        out["sizes"].append(r)
        pc = r["pieces"]
        rows.append([f"{r['segments']:,}", f"{r['translate_seconds']:.2f} s ({r['translate_cores']:.2f})",
                     f"{pc.get('curves (USD read + B-spline conversion)', 0):.2f}",
                     f"{pc.get('reference normals', 0):.2f}", f"{pc.get('fiber bank', 0):.2f}",
                     f"{pc.get('BSDF (upload)', 0) + pc.get('curve shape (buffers)', 0):.2f}",
                     f"{pc.get('Mitsuba scene + BVH', 0):.2f}",
                     f"{r['times'].get('tables', 0):.2f}", f"{r['other_seconds']:.2f}",
                     f"{r['rss_after_import_mib']:.0f} / {r['rss_after_stage_mib']:.0f} / "
                     f"{(r['peak_rss_mib'] or r['peak_rss_sampled_mib']):.0f}",
                     f"{r['author_seconds']:.2f} s"])
        print(f"  {r['segments']:>9,} segments: translate {r['translate_seconds']:.2f} s, peak RSS "
              f"{r['peak_rss_mib']} MiB (sampled {r['peak_rss_sampled_mib']:.0f})"
              + (f"; render {r['render']['spp']} spp at {r['render']['resolution']}^2: {r['render']['seconds']:.2f} s"
                 if "render" in r else ""))
    print(_table(["segments", "translate (cores)", "curves s", "ref. normals s", "bank s", "BSDF + shape s",
                  "scene + BVH s", "tables s", "other s", "RSS MiB: import / +stage / peak", "authoring"], rows))
    return out


# ---------------------------------------------------------------------------------------------
# Main
# ---------------------------------------------------------------------------------------------

def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="small sizes: a smoke test (< 2 min), not a benchmark")
    ap.add_argument("--parts", default="timing,convergence,scale")
    ap.add_argument("--out", type=Path, default=None, help="JSON path (default bench/results/render.json; "
                                                           "--quick: $TMPDIR/render_bench_quick.json)")
    ap.add_argument("--fibers", type=int, default=10_000)
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--spp-pair", type=lambda s: tuple(int(x) for x in s.split(",")), default=(4, 16))
    ap.add_argument("--conv-res", type=int, default=128)
    ap.add_argument("--repeats", type=int, default=3, help="timing rounds")
    ap.add_argument("--cases", type=lambda s: [x.strip() for x in s.split(",") if x.strip()], default=None,
                    help="timing: only these cases (comma-separated names; hair is always timed)")
    ap.add_argument("--silk-res", type=float, default=SILK_BAKE_RES)
    ap.add_argument("--silk-photons", type=int, default=SILK_PHOTONS)
    ap.add_argument("--silk-bank-res", type=float, default=SILK_BANK_RES)
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--ref-pass", type=int, default=64)
    ap.add_argument("--conv-spp", type=lambda s: [int(x) for x in s.split(",")], default=[1, 4, 16, 64])
    ap.add_argument("--conv-repeats", type=int, default=2)
    ap.add_argument("--sizes", type=lambda s: [int(float(x)) for x in s.split(",")],
                    default=[1_000, 10_000, 100_000, 1_000_000])
    ap.add_argument("--scale-res", type=int, default=256)
    ap.add_argument("--scale-spp", type=int, default=4)
    ap.add_argument("--warm-kernel-cache", action="store_true",
                    help="keep Dr.Jit's on-disk kernel cache ($HOME/.drjit); default: an empty one")
    sub = ap.add_subparsers(dest="cmd")
    w = sub.add_parser("_scale_worker")
    w.add_argument("--segments", type=int, required=True)
    w.add_argument("--cache", required=True)
    w.add_argument("--bake", required=True)
    w.add_argument("--res", type=int, default=64)
    w.add_argument("--spp", type=int, default=4)
    w.add_argument("--render", action="store_true")
    args = ap.parse_args(argv)
    if args.cmd == "_scale_worker":
        scale_worker(args)
        return 0

    if args.quick:
        args.fibers, args.res, args.spp_pair, args.repeats, args.conv_res = 1000, 64, (2, 8), 1, 64
        args.silk_res, args.silk_photons, args.silk_bank_res = 15.0, 1024, 15.0
        args.ref_spp, args.ref_pass, args.conv_spp, args.conv_repeats = 64, 32, [1, 4, 16], 1
        args.sizes, args.scale_res = [1_000, 10_000], 64
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    out_path = args.out or (Path(tempfile.gettempdir()) / "render_bench_quick.json" if args.quick
                            else RESULTS / "render.json")
    tmp = tempfile.TemporaryDirectory(prefix="usdfiber-render-bench-")
    if not args.warm_kernel_cache:
        # Dr.Jit keeps compiled kernels in $HOME/.drjit: an empty HOME makes the first render of
        # every case compile its kernel (measured cold), here and in the scale workers.
        home = Path(tmp.name) / "home"
        home.mkdir()
        os.environ["HOME"] = str(home)

    import usdfiber  # noqa: F401
    from usdfiber.bake.settings import BakeSettings
    from usdfiber.translators.mitsuba.scene import RENDER_BAKE_SETTINGS

    t_start = time.perf_counter()
    doc: dict[str, Any] = {
        "command": "render",
        "argv": [Path(sys.executable).name, *sys.argv],
        "started": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "load_average_before": [round(x, 2) for x in os.getloadavg()],
        "machine": machine(),
        "git": git_state(),
        "settings": {k: v for k, v in vars(args).items() if k not in ("out", "cmd")},
        "targets": TARGETS,
    }
    cache_dir = Path(tmp.name) / "cache"
    os.environ["USDFIBER_CACHE_DIR"] = str(cache_dir)
    settings = RENDER_BAKE_SETTINGS if not args.quick else BakeSettings(resolution_deg=15.0, photons=4000, batches=2)
    ctx: dict[str, Any] = {"cache_dir": cache_dir,
                           "bake_settings": {k: getattr(settings, k) for k in settings.__dataclass_fields__}}
    try:
        ctx["bake_settings"]["levels"] = list(ctx["bake_settings"]["levels"])
        print(f"pre-baking polyester ({settings.resolution_deg:g} deg, {settings.photons} photons) into {cache_dir}")
        doc["polyester_bake"] = prebake(cache_dir, settings)
        print(f"  {doc['polyester_bake']['seconds']:.1f} s")
        ctx["polyester_tables"] = polyester_tables(cache_dir, settings)
        if "timing" in parts:
            print("\n## timing")
            ctx["timing"] = doc["timing"] = part_timing(args, ctx)
        if "convergence" in parts:
            print("\n## convergence")
            doc["convergence"] = part_convergence(args, ctx)
        if "scale" in parts:
            print("\n## scale")
            doc["scale"] = part_scale(args, ctx)
    finally:
        tmp.cleanup()
    doc["load_average_after"] = [round(x, 2) for x in os.getloadavg()]
    doc["wall_seconds"] = round(time.perf_counter() - t_start, 1)
    g = git_state()
    doc["sources_changed_during_run"] = [s for s, h in g["sha256_16"].items() if h != doc["git"]["sha256_16"].get(s)]
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps(doc, indent=1, default=_json_default) + "\n")
    print(f"\nwrote {out_path} ({doc['wall_seconds']} s; load average before {doc['load_average_before']}, "
          f"after {doc['load_average_after']})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
