"""Yarn far fields only where they contribute, traced once per yarn structure: the Figure 11
close-up before and after, side by side (bench/REPORT.md, "Far fields only where they contribute").

The close-up: ``examples/fig11_threads.usda`` through a camera framing the CNe 50 and S 303
threads (the right half), so that the six Skala 360 and ORA 120 yarns are outside the view.
Every yarn in view is expanded into fibers; far fields are traced only for the yarns outside.

``--code DIR``: run the render with the usdfiber sources in DIR instead of the installed
ones (a ``git archive`` of an earlier commit with ``usdfiber/translators`` and
``usdfiber/resources`` linked in), for the before/after pair. Each run renders into its own
yarn cache (the fiber tables are shared, baked first with the examples' settings), times the
translation (far-field tracing included) and writes the image as .npy.

    python bench/far_field_bench.py render --cache DIR --out after.npy [--seed S] [--margin M]
    python bench/far_field_bench.py render --code /tmp/before --cache DIR --out before.npy
    python bench/far_field_bench.py compare A.npy B.npy [--noise C.npy]
    python bench/far_field_bench.py colours --cache DIR   # far-field cost per extra colour
"""
from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import time
from pathlib import Path

from bench_common import use_source_tree

REPO = Path(__file__).resolve().parents[1]
STAGE = REPO / "examples" / "fig11_threads.usda"
RES = (320, 180)
SPP = 32
TABLES = dict(resolution_deg=10.0, photons=20000, batches=4)   # the examples' tables


def _use_code(code: str | None) -> None:
    """Import usdfiber from ``code`` (a source tree) instead of the installed package."""
    if code:
        use_source_tree(code)


def _close_up(stage):
    """A camera over the right half of the card: the six left yarns are outside its view."""
    from pxr import Gf, UsdGeom

    cam = UsdGeom.Camera.Define(stage, "/Bench/CloseUp")
    cam.CreateFocalLengthAttr(50.0)
    cam.CreateHorizontalApertureAttr(36.0)
    cam.CreateVerticalApertureAttr(36.0 * RES[1] / RES[0])
    width = 4.6
    d = width / (36.0 / 50.0)
    elev = math.radians(55.0)
    eye = Gf.Vec3d(2.2, d * math.sin(elev), d * math.cos(elev))
    target = Gf.Vec3d(2.2, 0.1, 0.15)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.05 * d, 20.0 * d))
    view = Gf.Matrix4d().SetLookAt(eye, target, Gf.Vec3d(0.0, 1.0, 0.0))
    cam.AddTransformOp().Set(view.GetInverse())
    return "/Bench/CloseUp"


def render(args: argparse.Namespace) -> int:
    _use_code(args.code)
    import numpy as np

    import usdfiber  # noqa: F401
    from pxr import Usd

    from usdfiber.backend import mitsuba
    from usdfiber.bake.cache import TableCache
    from usdfiber.bake.settings import BakeSettings
    from usdfiber.translators.mitsuba.scene import SceneOptions, translate_stage

    mi = mitsuba()
    import drjit as dr

    root = Path(args.cache)
    if args.fresh_yarns and (root / "yarns").exists():
        shutil.rmtree(root / "yarns")
    stage = Usd.Stage.Open(str(STAGE))
    stage.SetEditTarget(stage.GetSessionLayer())
    cam = _close_up(stage)
    kw = {}
    if args.margin is not None:
        from usdfiber.translators.mitsuba.lod import LodPolicy

        kw["lod"] = LodPolicy(proxy_margin_diameters=args.margin)
    opts = SceneOptions(resolution=RES, spp=SPP, camera=cam, bake=BakeSettings(**TABLES),
                        cache=TableCache(root), **kw)
    t0 = time.perf_counter()
    tr = translate_stage(stage, opts)
    t_translate = time.perf_counter() - t0
    t1 = time.perf_counter()
    img = np.array(mi.render(tr.scene, spp=args.spp, seed=args.seed), np.float64)[..., :3]
    dr.sync_thread()
    t_render = time.perf_counter() - t1
    np.save(args.out, img)
    out = {"code": args.code or str(REPO), "translate_s": t_translate, "render_s": t_render,
           "tables_s": tr.times.get("tables", 0.0), "counts": tr.counts, "spp": args.spp, "seed": args.seed,
           "far_fields": getattr(tr.fibers, "far_fields", None), "load": os.getloadavg()}
    print(json.dumps(out, default=float))
    return 0


def compare(args: argparse.Namespace) -> int:
    """Mean and 4 x 4 block difference of two images, next to the same of two seeds."""
    import numpy as np

    def stats(a, b):
        h, w = a.shape[0] // 4 * 4, a.shape[1] // 4 * 4
        ba = a[:h, :w].reshape(h // 4, 4, w // 4, 4, 3).mean(axis=(1, 3))
        bb = b[:h, :w].reshape(h // 4, 4, w // 4, 4, 3).mean(axis=(1, 3))
        return {"mean_rel": float(a.mean() / b.mean() - 1.0),
                "block_rel_rmse": float(np.sqrt(np.mean((ba - bb) ** 2) / np.mean(bb ** 2)))}

    a, b = np.load(args.a), np.load(args.b)
    out = {"a_vs_b": stats(a, b)}
    if args.noise:
        out["b_vs_noise"] = stats(np.load(args.noise), b)
    print(json.dumps(out))
    return 0


def colours(args: argparse.Namespace) -> int:
    """Far-field cost per extra colour: ORA 120 traced in one colour (the former way, every
    colour a trace) against recolouring the far field traced at the absorption levels."""
    import numpy as np

    import usdfiber  # noqa: F401
    from pxr import Usd

    from usdfiber.bake.cache import TableCache
    from usdfiber.bake.settings import BakeSettings
    from usdfiber.spec.fiber import FiberParams
    from usdfiber.spec.yarn import YarnParams
    from usdfiber.translators.mitsuba.fiber_bank import FiberBank, FiberSlot
    from usdfiber.translators.mitsuba.fiber_bsdf import fiber_bsdf
    from usdfiber.translators.mitsuba.curves import reference_normals
    from usdfiber.translators.mitsuba.yarn_far_field import (YarnBakeSettings, bake_yarn_far_field,
                                                             trace_far_field, yarn_piece)
    from usdfiber.backend import mitsuba
    from usdfiber.bake.requests import requests_for_prim
    from dataclasses import replace

    mi = mitsuba()
    stage = Usd.Stage.Open(str(STAGE))
    cache = TableCache(args.cache)
    st = BakeSettings(**TABLES)
    prims = [stage.GetPrimAtPath(f"/Fig11/ORA120/{n}") for n in ("DoS0p5", "DoS1", "DoS2")]
    yarn = YarnParams.from_prim(prims[0])
    um = 1e-3   # mm per um
    tables = [cache.get_or_bake(r, st).table for r in requests_for_prim(prims[0])]
    ys = YarnBakeSettings()
    fd = FiberParams.from_prim(prims[0]).diameter * um
    sig = [tuple(float(x) for x in tables[0].sigma_for(FiberParams.from_prim(p).mu_a,
                                                       FiberParams.from_prim(p).diameter)) for p in prims]
    piece = yarn_piece(replace(yarn, seed=ys.seed), fd, ys)
    geom = piece.geometry
    rng = np.random.default_rng([ys.seed, 0x7A22])
    variant = rng.integers(0, len(tables), geom.curve_count)
    psi = rng.uniform(0.0, 2 * math.pi, geom.curve_count)
    ys = replace(ys, photons=args.photons)
    out = {"one_colour_s": [], "levels_s": None, "recolour_s": [], "photons": ys.photons, "load": os.getloadavg()}
    for s in sig:
        bsdf = fiber_bsdf(mi, FiberBank.build([FiberSlot(t, s) for t in tables]), variant[geom.segment_curve],
                          psi[geom.segment_curve], reference_normals(geom))
        t0 = time.perf_counter()
        trace_far_field(piece, bsdf, ys)
        out["one_colour_s"].append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    ff = bake_yarn_far_field(yarn, fd, [FiberSlot(t, sig[0]) for t in tables], ys)
    out["levels_s"] = time.perf_counter() - t0
    for s in sig:
        t0 = time.perf_counter()
        ff.recolour(list(s))
        out["recolour_s"].append(time.perf_counter() - t0)
    out["error_estimate"] = ff.header["error_estimate"]
    print(json.dumps(out, default=float))
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("render")
    r.add_argument("--code")
    r.add_argument("--cache", required=True)
    r.add_argument("--out", required=True)
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--spp", type=int, default=SPP)
    r.add_argument("--margin", type=float)
    r.add_argument("--fresh-yarns", action="store_true", help="empty the cache's yarn far fields first")
    r.set_defaults(func=render)
    c = sub.add_parser("compare")
    c.add_argument("a")
    c.add_argument("b")
    c.add_argument("--noise")
    c.set_defaults(func=compare)
    k = sub.add_parser("colours")
    k.add_argument("--cache", required=True)
    k.add_argument("--photons", type=int, default=40_000, help="per direction (default: the render's 40000)")
    k.set_defaults(func=colours)
    args = ap.parse_args()
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
