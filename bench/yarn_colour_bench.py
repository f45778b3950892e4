"""How much deeper a yarn looks than its fibers: the size of what dye matching and displayColor leave out.

    python bench/yarn_colour_bench.py [--stage examples/threads.usda] [--cache-dir /tmp/usdfiber-yarn-colour]
        [--out bench/results/yarn_colour.json]

``usdfiber dye`` and ``usdfiber material``'s ``primvars:displayColor`` give a yarn the colour
of its fibers (``usdfiber.dye_match``: a fiber's albedo seen perpendicular to it under a white
light of radiance 1, averaged over rotations and variants, width-weighted). Light scattered
between a yarn's fibers is absorbed again on every pass, so the yarn is deeper. For each
yarn prim of the stage (the Table 3 threads, each with its dye) this compares that fiber
colour with the yarn's own far field (the renderer's ``yarn_far_field``: photons traced
through the expanded yarn, every interaction with a fiber sampling the fiber's table):
``Lambda_yarn(theta = 0)``, the yarn's albedo seen perpendicular to it, and its coverage
(the fraction of a beam the yarn intercepts). Tables: 10 degrees, 20000 photons; far fields:
10 degrees, 40000 photons per direction (``YarnBakeSettings``), both in ``--cache-dir``.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402

import usdfiber  # noqa: E402,F401
from bench_common import machine, write_results  # noqa: E402
from pxr import Usd, UsdGeom  # noqa: E402

from usdfiber.bcsdf import BakeSettings, TableCache, tables_for_prim  # noqa: E402
from usdfiber.dye_match import srgb_hex  # noqa: E402
from usdfiber.spec.fiber import FiberParams  # noqa: E402
from usdfiber.spec.yarn import YarnParams  # noqa: E402
from usdfiber.translators.mitsuba.fiber_bank import FiberSlot  # noqa: E402
from usdfiber.translators.mitsuba.yarn_far_field import YarnBakeSettings, YarnFarFieldCache  # noqa: E402

PHI = (np.arange(720) + 0.5) * (2 * math.pi / 720)


def fiber_colour(tables: list, sigma: list[np.ndarray]) -> np.ndarray:
    """The fiber's colour as usdfiber.dye_match defines it (theta = 0), RGB."""
    num, den = np.zeros(3), 0.0
    for t, s in zip(tables, sigma):
        w = t.width(PHI)
        num += (w[:, None] * t.albedo(0.0, PHI, list(s))).sum(axis=0)
        den += float(w.sum())
    return num / den


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--stage", default="examples/threads.usda")
    ap.add_argument("--cache-dir", default="/tmp/usdfiber-yarn-colour")
    ap.add_argument("--out", default="bench/results/yarn_colour.json")
    args = ap.parse_args()
    cache = TableCache(args.cache_dir)
    stage = Usd.Stage.Open(args.stage)
    um = 1e-6 / UsdGeom.GetStageMetersPerUnit(stage)
    bake = BakeSettings(resolution_deg=10.0, photons=20_000, batches=4)
    far = YarnFarFieldCache(cache)
    yarn_settings = YarnBakeSettings(resolution_deg=10.0)
    rows = []
    for prim in stage.Traverse():
        if not prim.HasAPI("FiberYarnAPI"):
            continue
        params = FiberParams.from_prim(prim)
        yarn = YarnParams.from_prim(prim)
        tables = tables_for_prim(prim, bake, cache=cache)
        sigma = [np.asarray(t.sigma_for(params.mu_a, params.diameter), np.float64) for t in tables]
        slots = [FiberSlot(t, tuple(float(x) for x in s)) for t, s in zip(tables, sigma)]
        ff, traced = far.get_or_bake(yarn, params.diameter * um, slots, yarn_settings)
        rec = ff.recolour(sigma[0], 1.0)
        nodes = ff.grid.theta_i_nodes()
        alb = rec.albedo[:, 0, :].astype(np.float64)                       # (n_ti, 3)
        yarn_rgb = np.array([np.interp(0.0, nodes, alb[:, c]) for c in range(3)])
        undyed = ff.recolour(np.zeros(3), 1.0).albedo[:, 0, :].astype(np.float64)
        yarn_white = float(np.interp(0.0, nodes, undyed[:, 1]))
        fib = fiber_colour(tables, sigma)
        cov = float(ff.coverage_at(0.0))
        ratio = yarn_rgb / fib
        row = {"prim": str(prim.GetPath()), "kind": params.kind, "depth_of_shade": params.depth_of_shade,
               "fiber_rgb": fib, "yarn_rgb": yarn_rgb, "ratio": ratio, "fiber_hex": srgb_hex(fib),
               "yarn_hex": srgb_hex(yarn_rgb), "coverage": cov, "undyed_yarn_albedo": yarn_white,
               "far_field_rel_error": float(np.sqrt(np.mean(ff.arrays["rel_error"].astype(np.float64) ** 2))),
               "lost": float(np.max(ff.arrays["lost"])), "traced_now": traced}
        rows.append(row)
        print(f"{row['prim']} ({params.kind}, {params.depth_of_shade:g} %): fiber {fib.round(3)} {row['fiber_hex']}, "
              f"yarn {yarn_rgb.round(3)} {row['yarn_hex']}, yarn/fiber {ratio.round(3)}, coverage {cov:.3f}, "
              f"undyed yarn albedo {yarn_white:.3f}", flush=True)
    out = {"machine": machine(load_average=os.getloadavg()), "rows": rows}
    print(f"wrote {write_results(args.out, out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
