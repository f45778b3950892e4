"""Volumetric cloth (``render --cloth volume``): voxelization time, grid memory, render time per
spp and image error against explicit fibers, for the Figure 7 swatch; and the analytic
voxelization of the 5,000-yarn shirt panel (no fiber expansion).

    python bench/volume_bench.py swatch [--res 320x120] [--spp 16]     # three modes, one stage
    python bench/volume_bench.py shirt [--yarns 5000] [--voxel-mm 1.04]

``swatch``: examples/fig7_swatches.usda rendered as explicit fibers (``--lod-scale 0``; the
reference, at ``--ref-spp``), as the yarn far field (``--lod-scale 0.01``: every yarn below the far-field
threshold) and as a volume; per mode the translate time, the voxel grids' bytes, the render
time per spp, the image mean relative to the reference and the RMS error over 4 x 4 pixel
blocks relative to the reference's mean; then an equal-time run (each mode given the
volume's render time) with the same errors. Tables: 15 degrees, 5,000 photons (cached in
``$USDFIBER_CACHE_DIR``).

``shirt``: yarns of bench/cloth_bench.py's shirt panel (2,500 x 2,500 Skala 360, 66.5 cm)
voxelized from the yarn density at the footprint of a 640-pixel view of the whole panel
(1.04 mm): time, pieces, grid bytes. ``--yarns N`` voxelizes N full-length warps and
extrapolates linearly to the panel's 5,000 yarns (the cost is per yarn length).

Prints one JSON object.
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


def part_swatch(args: argparse.Namespace) -> dict[str, Any]:
    import usdfiber  # noqa: F401  (registers the schemas first)
    from pxr import Usd

    from usdfiber.backend import mitsuba
    from usdfiber.bake.cache import TableCache
    from usdfiber.bake.settings import BakeSettings

    mi = mitsuba()
    from usdfiber.translators.mitsuba.scene import SceneOptions, translate_stage

    stage = Usd.Stage.Open(os.path.join(ROOT, "examples", "fig7_swatches.usda"))
    w, h = (int(v) for v in args.res.split("x"))
    bake = BakeSettings(resolution_deg=15, photons=5000, batches=2)
    cache = TableCache(os.environ.get("USDFIBER_CACHE_DIR") or None)
    modes = {"fibers": dict(cloth="fibers", lod_scale=0.0), "far field": dict(cloth="fibers", lod_scale=0.01),
             "volume": dict(cloth="volume", lod_scale=1.0)}

    def render(mode: str, spp: int, seed: int) -> tuple[np.ndarray, dict[str, Any]]:
        t0 = time.perf_counter()
        tr = translate_stage(stage, SceneOptions(resolution=(w, h), spp=1, bake=bake, cache=cache, **modes[mode]))
        t1 = time.perf_counter()
        img = np.array(mi.render(tr.scene, spp=spp, seed=seed), np.float64)[..., :3]
        t2 = time.perf_counter()
        return img, {"translate_s": t1 - t0, "render_s": t2 - t1, "s_per_spp": (t2 - t1) / spp,
                     "voxel_bytes": tr.counts.get("voxel_bytes", 0), "voxels": tr.counts.get("voxels_occupied", 0),
                     "segments": tr.counts.get("fiber_segments", 0)}

    ref, ref_rec = render("fibers", args.ref_spp, 101)
    out: dict[str, Any] = {"stage": "examples/fig7_swatches.usda", "res": [w, h], "reference": ref_rec,
                           "reference_spp": args.ref_spp, "modes": {}}
    for mode in modes:
        img, rec = render(mode, args.spp, 7)
        rec.update(spp=args.spp, mean_rel=float(img.mean() / ref.mean() - 1.0), block_rms=block_rms(img, ref))
        out["modes"][mode] = rec
    budget = out["modes"]["volume"]["render_s"]
    out["equal_time_s"] = budget
    for mode in modes:
        spp = max(1, int(budget / out["modes"][mode]["s_per_spp"]))
        img, rec = render(mode, spp, 11)
        out["modes"][mode]["equal_time"] = {"spp": spp, "render_s": rec["render_s"],
                                            "mean_rel": float(img.mean() / ref.mean() - 1.0),
                                            "block_rms": block_rms(img, ref)}
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
    # The panel's warps at full length (66.5 cm across 2,500 wefts); the whole panel's 50 M
    # control points exceed the generator's memory budget on 24 GiB, and every yarn costs the same.
    cloth.plain_weave(stage, "/Shirt", warps=min(args.yarns, 2500), wefts=2500, yarn="Skala 360",
                      dye="disperseBlue", depth_of_shade=1.0)
    t_stage = time.perf_counter() - t0
    prims = [stage.GetPrimAtPath("/Shirt/Warp")]
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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("part", choices=("swatch", "shirt"))
    ap.add_argument("--res", default="320x120")
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--ref-spp", type=int, default=64)
    ap.add_argument("--yarns", type=int, default=5000)
    ap.add_argument("--voxel-mm", type=float, default=665.0 / 640.0)
    args = ap.parse_args(argv)
    out = {"machine": machine(), "part": args.part}
    out.update(part_swatch(args) if args.part == "swatch" else part_shirt(args))
    out["machine"]["load_average_end"] = os.getloadavg()
    json.dump(out, sys.stdout, indent=1, default=float)
    print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
