"""Fit time and fit error of the standard models per fiber, and the error against depth of shade.

    python bench/fit_bench.py [--resolution 6] [--photons 20000] [--cache-dir DIR] [--out bench/results/fit.json]

For each fiber (polyester, silk, cotton, wool; one cross-section variant each, the preset's
roughness and index) the table is baked at the render tables' resolution (6 degrees) into
``--cache-dir`` (default: the user's table cache, ``usdfiber.bcsdf.default_cache_dir``), then Chiang (Mitsuba's
parameters, no tints; and with MaterialX's lobe tints) and Khungurn are fitted undyed and
dyed with reactiveRed at depths of shade 0.1, 0.5, 1, 2 and 4 %. Reported per fit: wall time
(fits start from an empty fit cache; a dyed Chiang fit reuses the undyed shape fit, as in
use, so its time is the colour stage only), the relative L2 error of the scattering over the sphere per channel
(:mod:`usdfiber.fit.objective`), and the albedo of table and model. The table's own noise
(its ``rel_error``, relative L2 per direction) is printed with it: a fit error near it is
as good as the table can tell.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402

import usdfiber  # noqa: E402,F401
from bench_common import machine, write_results  # noqa: E402
from pxr import Usd, UsdGeom  # noqa: E402

from usdfiber import authoring  # noqa: E402
from usdfiber.bcsdf import BakeSettings, TableCache, tables_for_prim  # noqa: E402
from usdfiber.fit import FitCache, FitSettings, fit_tables  # noqa: E402
from usdfiber.spec.fiber import FiberParams  # noqa: E402

FIBERS = ("polyester", "silk", "cotton", "wool")
SHADES = (0.1, 0.5, 1.0, 2.0, 4.0)
FITS = (("chiang", FitSettings()), ("chiang+tints", FitSettings(tints=True)), ("khungurn", FitSettings()))


def prim_for(stage: Usd.Stage, fiber: str, dos: float) -> Usd.Prim:
    c = UsdGeom.BasisCurves.Define(stage, f"/{fiber}_{str(dos).replace('.', '_')}")
    c.CreateCurveVertexCountsAttr([4])
    c.CreatePointsAttr([(0, 0, 0), (0, 0, 1), (0, 0, 2), (0, 0, 3)])
    p = c.GetPrim()
    kw = {} if fiber == "polyester" else {"variant_count": 1}
    authoring.apply_fiber(p, fiber, dye="reactiveRed", depth_of_shade=dos, **kw)
    return p


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--resolution", type=float, default=6.0)
    ap.add_argument("--photons", type=int, default=20_000)
    ap.add_argument("--cache-dir", default=None)
    ap.add_argument("--fibers", nargs="*", default=list(FIBERS))
    ap.add_argument("--out", default="bench/results/fit.json")
    args = ap.parse_args()
    cache = TableCache(args.cache_dir)
    settings = BakeSettings(resolution_deg=args.resolution, photons=args.photons, batches=4)
    stage = Usd.Stage.CreateInMemory()
    rows = []
    fits = FitCache(Path(cache.root) / f"fits_bench_{int(time.time())}")
    for fiber in args.fibers:
        t0 = time.perf_counter()
        base = prim_for(stage, fiber, 0.0)
        tables = tables_for_prim(base, settings, cache=cache)
        bake_s = time.perf_counter() - t0
        noise = float(np.sqrt(np.mean(tables[0].rel_error.astype(np.float64) ** 2)))
        print(f"{fiber}: table {tables[0].grid.n_theta_i}x{tables[0].grid.n_phi_i} incoming nodes, "
              f"rms noise {noise:.3f} (relative L2 per direction), ready in {bake_s:.1f} s", flush=True)
        for dos in (0.0,) + SHADES:
            params = FiberParams.from_prim(prim_for(stage, fiber, dos))
            ds = params.diameter / tables[0].baked_diameter_um
            mu = list(params.mu_a) if dos > 0 else [0.0, 0.0, 0.0]
            for name, st in FITS:
                model = name.split("+")[0]
                t1 = time.perf_counter()
                res = fit_tables(tables, model, mu, ds, st, cache=fits)
                wall = time.perf_counter() - t1
                row = {"fiber": fiber, "dos": dos, "fit": name, "seconds": wall, "rel_l2": res.error["rel_l2"],
                       "rms_log": res.error["rms_log"], "albedo_table": res.error["albedo_table"],
                       "albedo_model": res.error["albedo_model"], "table_noise": noise,
                       "params": res.params.to_json()}
                rows.append(row)
                print(f"  dos {dos:4.1f}% {name:13s} {wall:6.1f} s  rel L2 "
                      + " ".join(f"{e:.3f}" for e in res.error["rel_l2"])
                      + "  albedo table " + " ".join(f"{a:.3f}" for a in res.error["albedo_table"])
                      + " model " + " ".join(f"{a:.3f}" for a in res.error["albedo_model"]), flush=True)
    out = {"machine": machine(), "resolution_deg": args.resolution, "photons": args.photons, "rows": rows}
    print(f"wrote {write_results(args.out, out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
