"""Render tables against image error: the render's default table settings chosen by what a
close-up shows (issue 14, item 5; bench/REPORT.md, section 10).

    python bench/render_defaults.py --fiber polyester --only 10/10@100k 6/6@100k 3/3@100k 2/2@100k
    python bench/render_defaults.py --fiber silk
    python bench/render_defaults.py --fiber polyester --png-only --png-dir docs/renders \
        --before 6/6@100k --after 2/2@100k           # PNGs from the last run's images
    python bench/render_defaults.py --fiber polyester --quick   # checks the script (coarse, 4 spp)

The close-up: 40 parallel fibers of the preset (undyed: the highlight is uncoloured), side by
side, about 7 px wide across a 320 x 240 image, seen from above through a 50 mm camera, lit by
one distant light 8 deg along the fibers and 30 deg around them, so that the specular cone
(theta_o = -theta_i) crosses the image as a band. Silk is authored with one cross-section
variant (``fiber:profile:variantCount = 1``: one table per setting, so that its fine tables
stay affordable here; the render default bakes four).

Each configuration (:data:`CONFIGS`, named bins/nodes@photons) is estimated by the baker's
cost model (:func:`usdfiber.bake.cost.estimate_request`, an idle-machine figure), baked into
its own cache under ``--cache-dir`` (a cache serves a request with any table at least as
good, which would hide the differences measured; wall and process CPU seconds of the bake,
all threads; a table already in the cache is reused and its time taken from an earlier run's
JSON when there is one), then rendered at ``--spp`` (128) with render seed 0; the first one
also with seed 1 (the two-seed noise of a render). The reference is the mean of the renders
of ``ref-a`` and ``ref-b`` (the finest affordable grid, two bake seeds) at ``--ref-spp``
samples with render seeds 0 and 1 (with ``ref-a`` alone: its two render seeds); its own
noise is half their difference.

Errors against the reference, over pixels whose alpha is above 0.5, on luminance: the
relative L2 of 4 x 4 pixel block means (``bench/model_bench.py``'s metric), the relative
difference of the mean, and the highlight: the image's row profile (mean over the fibers of
each row; the fibers run along the columns) at the reference's brightest row, +-2 rows,
relative to the reference's.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402

from bench_common import Timer, machine, write_results  # noqa: E402
from model_bench import image_error  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
RES = (320, 240)
N_FIBERS = 40
PX_PER_FIBER = 7.0
LIGHT_THETA_DEG = 8.0     # along the fibers: the specular cone crosses the view at theta_o = -8 deg
LIGHT_AROUND_DEG = 30.0   # around the fibers, from the camera's axis
PEAK_ROWS = 2

#: The expected-value estimator as the render baked with it when the silk-2deg set was run (K = 8
#: normals for every event), and with the adaptive allocation of normals that followed.
_EXPECTED: dict[str, Any] = dict(estimator=("expected",), expected_normals=8, expected_allocation="uniform")
_ADAPTIVE: dict[str, Any] = dict(estimator=("expected",), expected_normals=8, expected_allocation="adaptive")
#: name -> BakeSettings keyword arguments, per set; "ref-a"/"ref-b" make the reference. A set
#: is named after its fiber preset, with an optional "-suffix".
CONFIGS: dict[str, dict[str, dict[str, Any]]] = {
    "polyester": {
        "ref-a": dict(resolution_deg=2, photons=400_000, batches=4, seed=0),
        "ref-b": dict(resolution_deg=2, photons=400_000, batches=4, seed=1),
        "10/10@100k": dict(resolution_deg=10, photons=100_000, batches=4),
        "6/6@100k": dict(resolution_deg=6, photons=100_000, batches=4),      # the former default
        "3/3@100k": dict(resolution_deg=3, photons=100_000, batches=4),
        "2/2@100k": dict(resolution_deg=2, photons=100_000, batches=4),
        "2/2@25k": dict(resolution_deg=2, photons=25_000, batches=4),
        "2/2@100k split": dict(resolution_deg=2, photons=100_000, batches=4, estimator=("split",)),
    },
    # Silk traces every azimuth: 900 directions at 6 deg nodes (a full 2 deg table is 1.7 h per
    # variant here), so its grids share 10 deg incoming nodes (324 directions): the outgoing bins
    # compared alone. One reference table (its render seeds give the render noise).
    "silk": {
        "ref-a": dict(resolution_deg=2, incoming_deg=10, photons=25_000, batches=4, seed=0),
        "10/10@25k": dict(resolution_deg=10, photons=25_000, batches=4),
        "5/10@25k": dict(resolution_deg=5, incoming_deg=10, photons=25_000, batches=4),
    },
    # Silk against a full 2 deg table (8,100 directions, the expected value at 25k photons:
    # about 26 min by the cost model): every grid compared with bins and nodes together.
    "silk-2deg": {
        "ref-a": dict(resolution_deg=2, photons=25_000, batches=4, seed=0, **_EXPECTED),
        "10/10@25k": dict(resolution_deg=10, photons=25_000, batches=4),
        "6/6@100k": dict(resolution_deg=6, photons=100_000, batches=4),      # the former default
        "6/6@15k ev": dict(resolution_deg=6, photons=15_000, batches=4, **_EXPECTED),   # the render's
        "3/3@15k ev": dict(resolution_deg=3, photons=15_000, batches=4, **_EXPECTED),
        "3/6@15k ev": dict(resolution_deg=3, incoming_deg=6, photons=15_000, batches=4, **_EXPECTED),
    },
}
FORMER_DEFAULT = "6/6@100k"


def close_up(fiber: str, path: Path) -> Path:
    """The close-up stage (module docstring), in millimetres; returns its path."""
    import usdfiber  # noqa: F401  (registers the schemas)
    from pxr import Gf, Usd, UsdGeom, UsdLux, Vt

    from usdfiber import authoring
    from usdfiber.presets import FIBER_PRESETS

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    stage.SetDefaultPrim(stage.DefinePrim("/CloseUp", "Xform"))
    d = FIBER_PRESETS[fiber].diameter_um * 1e-3
    width = RES[0] / PX_PER_FIBER * d                     # the image's width at the fibers
    length = 2.0 * width
    curves = UsdGeom.BasisCurves.Define(stage, "/CloseUp/Fibers")
    curves.CreateTypeAttr(UsdGeom.Tokens.linear)
    pts = []
    for i in range(N_FIBERS):
        x = (i - (N_FIBERS - 1) / 2) * d
        pts += [Gf.Vec3f(x, -length / 2, 0.0), Gf.Vec3f(x, length / 2, 0.0)]
    curves.CreatePointsAttr(Vt.Vec3fArray(pts))
    curves.CreateCurveVertexCountsAttr(Vt.IntArray([2] * N_FIBERS))
    curves.CreateWidthsAttr(Vt.FloatArray([d]))
    curves.SetWidthsInterpolation(UsdGeom.Tokens.constant)
    curves.CreateExtentAttr(UsdGeom.Curves.ComputeExtent(curves.GetPointsAttr().Get(), curves.GetWidthsAttr().Get()))
    prim = authoring.apply_fiber(curves.GetPrim(), fiber)
    if fiber != "polyester":
        prim.GetAttribute("fiber:profile:variantCount").Set(1)

    cam = UsdGeom.Camera.Define(stage, "/CloseUp/Camera")
    cam.CreateFocalLengthAttr(50.0)
    cam.CreateHorizontalApertureAttr(36.0)
    cam.CreateVerticalApertureAttr(36.0 * RES[1] / RES[0])
    dist = width / (36.0 / 50.0)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.05 * dist, 20.0 * dist))
    cam.AddTranslateOp().Set(Gf.Vec3d(0.0, 0.0, dist))      # looks down -z at the fibers
    light = UsdLux.DistantLight.Define(stage, "/CloseUp/Key")
    light.CreateIntensityAttr(3.0)
    light.CreateAngleAttr(0.0)
    t, a = math.radians(LIGHT_THETA_DEG), math.radians(LIGHT_AROUND_DEG)
    towards = Gf.Vec3d(math.cos(t) * math.sin(a), math.sin(t), math.cos(t) * math.cos(a))   # to the light
    aim = Gf.Matrix4d().SetLookAt(towards, Gf.Vec3d(0.0), Gf.Vec3d(0.0, 1.0, 0.0) if abs(towards[1]) < 0.9
                                  else Gf.Vec3d(1.0, 0.0, 0.0))
    UsdGeom.Xformable(light.GetPrim()).AddTransformOp().Set(aim.GetInverse())
    stage.GetRootLayer().Export(str(path))
    return path


def settings_of(kw: dict[str, Any]):
    from usdfiber.bake.settings import BakeSettings

    return BakeSettings(**kw)


def bake(stage_path: Path, st: Any, cache: Any) -> dict[str, Any]:
    """Estimate, then bake the close-up's tables with ``st`` (cost model first, then timed)."""
    from usdfiber.bake.cost import estimate_request
    from usdfiber.bake.requests import tables_for_stage
    from usdfiber.stage_io import open_stage

    reqs = tables_for_stage(open_stage(stage_path))
    cached = all(cache.find_serving(r, st) is not None for r in reqs)
    est = [estimate_request(r, st, cache) for r in reqs]
    with Timer() as tm:
        tables = [cache.get_or_bake(r, st, None).table for r in reqs]
    rel = [t.summary()["rel_error_rms"] for t in tables]
    return {"estimate_s": sum(e.seconds for e in est), "estimate": [e.describe() for e in est],
            "bake_wall_s": None if cached else tm.wall, "bake_cpu_s": None if cached else tm.cpu,
            "cached": cached, "directions": [e.directions for e in est], "table_rel_error": rel}


def render(stage_path: Path, st: Any, cache: Any, spp: int, seed: int) -> tuple[np.ndarray, np.ndarray, float]:
    """The close-up rendered with tables baked with ``st``: (rgb, alpha, render seconds)."""
    import drjit as dr

    from usdfiber.stage_io import open_stage
    from usdfiber.translators.mitsuba.device import select_device
    from usdfiber.translators.mitsuba.scene import SceneOptions, translate_stage

    mi = select_device("cpu", None)
    tr = translate_stage(open_stage(stage_path), SceneOptions(resolution=RES, spp=spp, seed=seed, bake=st,
                                                              cache=cache, bake_missing=False, alpha=True))
    t0 = time.perf_counter()
    acc = None
    step = 16
    for k in range(0, spp, step):
        n = min(step, spp - k)
        img = mi.render(tr.scene, spp=n, seed=seed * 100_003 + k // step)
        dr.eval(img)
        arr = np.array(img, dtype=np.float64) * n
        acc = arr if acc is None else acc + arr
    out = acc / spp
    return out[..., :3], out[..., 3], time.perf_counter() - t0


def luminance(rgb: np.ndarray) -> np.ndarray:
    return rgb @ np.array([0.2126, 0.7152, 0.0722])


def row_profile(rgb: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Mean luminance of the fiber pixels of each row (the fibers run along the columns)."""
    m = alpha > 0.5
    y = luminance(rgb)
    return (y * m).sum(axis=1) / np.maximum(m.sum(axis=1), 1)


def errors(img: np.ndarray, ref: np.ndarray, alpha: np.ndarray) -> dict[str, float]:
    """Block rel L2, mean and highlight-peak errors of ``img`` against ``ref`` (module docstring)."""
    e = image_error(img, ref, alpha)
    pr, pi = row_profile(ref, alpha), row_profile(img, alpha)
    k = int(np.argmax(pr))
    sl = slice(max(0, k - PEAK_ROWS), k + PEAK_ROWS + 1)
    e["peak"] = float(pi[sl].mean() / pr[sl].mean() - 1.0)
    e["peak_row"] = k
    return e


def save_png(rgb: np.ndarray, path: Path, exposure: float) -> None:
    """A small display PNG (sRGB transfer, no tone map; the same exposure for a pair)."""
    import OpenImageIO as oiio

    x = np.clip(rgb * exposure, 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    path.parent.mkdir(parents=True, exist_ok=True)
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(rgb.shape[1], rgb.shape[0], 3, oiio.UINT8))
    out.write_image((srgb * 255 + 0.5).astype(np.uint8))
    out.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fiber", choices=sorted(CONFIGS), required=True)
    ap.add_argument("--only", nargs="+", help="configurations to run (default: all; ref-a and ref-b always)")
    ap.add_argument("--spp", type=int, default=128)
    ap.add_argument("--ref-spp", type=int, default=256)
    ap.add_argument("--cache-dir", type=Path, default=Path("/tmp/usdfiber-render-defaults"))
    ap.add_argument("--work", type=Path, default=Path("/tmp/usdfiber-render-defaults-out"))
    ap.add_argument("--out", type=Path)
    ap.add_argument("--png-dir", type=Path, help="write render_defaults_<fiber>_<config>.png for --before and --after")
    ap.add_argument("--before", default=FORMER_DEFAULT, help="the configuration shown as 'before'")
    ap.add_argument("--after", help="the configuration shown as 'after'")
    ap.add_argument("--quick", action="store_true", help="coarse, noisy tables and 4 spp (checks the script)")
    ap.add_argument("--png-only", action="store_true",
                    help="only write the --png-dir pair from an earlier run's images in --work")
    args = ap.parse_args()
    if args.png_only:
        if not (args.png_dir and args.after):
            raise SystemExit("--png-only needs --png-dir and --after")
        imgs = {n: np.load(args.work / f"{args.fiber}_{_file_name(n)}.npy") for n in (args.before, args.after)}
        print(*write_pair(np.load(args.work / f"{args.fiber}_reference.npy"), imgs, args.png_dir, args.fiber))
        return 0
    if args.quick:
        for kw in CONFIGS[args.fiber].values():
            kw.update(resolution_deg=30, incoming_deg=None, photons=2000)
        args.spp, args.ref_spp = 4, 4

    from usdfiber.bake.cache import TableCache

    out = args.out or REPO / f"bench/results/render_defaults_{args.fiber}.json"
    previous = json.loads(out.read_text()) if out.exists() else {}
    args.work.mkdir(parents=True, exist_ok=True)
    stage_path = close_up(args.fiber.split("-")[0], args.work / f"{args.fiber}_closeup.usda")
    configs = CONFIGS[args.fiber]
    names = [n for n in ("ref-a", "ref-b") if n in configs] + [
        n for n in configs if not n.startswith("ref-") and (not args.only or n in args.only)]
    names += [n for n in (args.before, args.after) if args.png_dir and n and n not in names]
    res: dict[str, Any] = {"machine": machine(), "fiber": args.fiber, "resolution": RES, "spp": args.spp,
                           "ref_spp": args.ref_spp, "configs": {}, "started": time.strftime("%Y-%m-%d %H:%M:%S")}
    imgs: dict[str, np.ndarray] = {}
    alpha = None
    for name in names:
        kw = configs[name]
        st = settings_of(kw)
        # One cache per configuration: a cache serves a request with any table at least as good
        # (a finer grid, more photons, another seed), which would hide the differences measured.
        cache = TableCache(args.cache_dir / args.fiber / _file_name(name).replace("@", "_"))
        b = bake(stage_path, st, cache)
        old = previous.get("configs", {}).get(name, {}).get("bake", {})
        if b["cached"] and old.get("bake_cpu_s") is not None:
            b.update({k: old[k] for k in ("bake_wall_s", "bake_cpu_s") if k in old}, timed_in="an earlier run")
        entry: dict[str, Any] = {"settings": {k: v for k, v in asdict(st).items() if k != "levels"}, "bake": b}
        print(f"{name}: {b['estimate']} bake {b['bake_wall_s']} s wall, {b['bake_cpu_s']} s CPU", flush=True)
        if name.startswith("ref-"):
            seed = 0 if name == "ref-a" else 1
            rgb, alpha, t = render(stage_path, st, cache, args.ref_spp, seed)
            if "ref-b" not in configs:     # one reference table: its second render seed
                imgs["ref-b"] = render(stage_path, st, cache, args.ref_spp, 1)[0]
        else:
            rgb, alpha, t = render(stage_path, st, cache, args.spp, 0)
            if "seed1" not in imgs:     # the first candidate: the two-seed noise of a render
                rgb1, _, _ = render(stage_path, st, cache, args.spp, 1)
                imgs["seed1"], res["render_noise_of"] = rgb1, name
        entry["render_s"] = t
        imgs[name] = rgb
        np.save(args.work / f"{args.fiber}_{_file_name(name)}.npy", rgb)
        res["configs"][name] = entry
    ref = 0.5 * (imgs["ref-a"] + imgs["ref-b"])
    np.save(args.work / f"{args.fiber}_reference.npy", ref)
    # The reference's own noise: half the difference of its two independent halves.
    half = image_error(imgs["ref-a"], imgs["ref-b"], alpha)
    res["reference_noise"] = {"blocks_rel_l2": 0.5 * half["blocks_rel_l2"], "mean": 0.5 * half["mean"]}
    if "seed1" in imgs:
        res["render_noise"] = image_error(imgs["seed1"], imgs[res["render_noise_of"]], alpha)
    for name, entry in res["configs"].items():
        if not name.startswith("ref-"):
            entry["error"] = errors(imgs[name], ref, alpha)
    res["ref_profile"] = row_profile(ref, alpha)
    write_results(out, res)
    print(json.dumps({n: {"err": e.get("error"), "cpu": e["bake"]["bake_cpu_s"], "est": e["bake"]["estimate_s"]}
                      for n, e in res["configs"].items()}, indent=1))
    print("reference noise", res["reference_noise"], "render noise", res.get("render_noise"))
    if args.png_dir and args.after:
        write_pair(ref, {n: imgs[n] for n in (args.before, args.after)}, args.png_dir, args.fiber)
    return 0


def _file_name(config: str) -> str:
    return config.replace("/", "-").replace(" ", "_")


def write_pair(ref: np.ndarray, images: dict[str, np.ndarray], png_dir: Path, fiber: str) -> list[Path]:
    """``render_defaults_<fiber>_<config>.png`` per image, at one exposure (the reference's 99th
    percentile at 0.8)."""
    exposure = 0.8 / float(np.percentile(luminance(ref), 99))
    out = []
    for name, rgb in images.items():
        out.append(png_dir / f"render_defaults_{fiber}_{_file_name(name).replace('@', '_')}.png")
        save_png(rgb, out[-1], exposure)
    return out


if __name__ == "__main__":
    raise SystemExit(main())
