"""Speed against error of `usdfiber render --model table|chiang|khungurn` on the paper's scenes.

    python bench/model_bench.py [--stages fig1_satin_garter fig11_threads] [--resolution 320x180]
        [--spp 4 16] [--cache-dir /tmp/usdfiber-model-bench] [--out bench/results/models.json]
        [--png-dir docs/renders] [--bake-resolution 15] [--bake-photons 10000]

For each stage (``examples/<stage>.usda``) the three models are rendered side by side in one
run, each at the two sample counts of ``--spp`` (the first run of a model also bakes its
tables or fits its parameters, outside the render time). Reported per model:

* time per spp: the slope of the render time (``render --json``'s ``times_s.render``,
  Mitsuba's passes only) between the two sample counts, which removes the kernel compile
  and other fixed costs; and the fixed cost (the intercept);
* the image error against the table render at the larger count, over pixels whose alpha is
  above 0.5: the relative difference of the mean radiance, and the relative L2 difference
  of 4 x 4 pixel block means (``sqrt(sum (B_model - B_table)^2 / sum B_table^2)``) which
  keeps where light goes, not only how much;
* the noise floor of both: the same metrics between two table renders with different seeds.

A side-by-side picture per stage (table | chiang | khungurn, each titled with its error) is
written to ``--png-dir/models_<stage>.png``. Tables: ``--bake-resolution`` (15 degrees) and
``--bake-photons`` (10000; ``examples/README.md`` renders with 10 degrees and 20000) in
``--cache-dir``; fits are cached beside them.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402

from bench_common import machine, write_results  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
MODELS = ("table", "chiang", "khungurn")
BLOCK = 4


def render(stage: Path, out: Path, model: str, spp: int, resolution: str, cache: Path, bake: list[str],
           seed: int = 0) -> dict:
    """One `usdfiber render --json` in its own process: its summary, plus the EXR's pixels."""
    env = dict(os.environ, USDFIBER_CACHE_DIR=str(cache))
    cmd = [sys.executable, "-m", "usdfiber", "render", str(stage), "-o", str(out), "--resolution", resolution,
           "--spp", str(spp), "--model", model, "--seed", str(seed), "--float", "--no-progress", "--json", *bake]
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=REPO)
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{r.stderr}")
    summary = json.loads(r.stdout)
    summary["wall_s"] = wall
    return summary


def pixels(path: Path) -> tuple[np.ndarray, np.ndarray]:
    from usdfiber.image_output import read_exr_channels

    ch = read_exr_channels(path)
    return np.stack([ch["R"], ch["G"], ch["B"]], -1).astype(np.float64), ch["A"].astype(np.float64)


def image_error(img: np.ndarray, ref: np.ndarray, alpha: np.ndarray) -> dict:
    """Relative difference of the mean, and relative L2 of 4 x 4 block means (module docstring)."""
    m = alpha > 0.5
    lum = np.array([0.2126, 0.7152, 0.0722])
    a, b = img @ lum, ref @ lum
    mean = float((a[m].mean() - b[m].mean()) / b[m].mean())
    h, w = (a.shape[0] // BLOCK) * BLOCK, (a.shape[1] // BLOCK) * BLOCK

    def blocks(x: np.ndarray) -> np.ndarray:
        return x[:h, :w].reshape(h // BLOCK, BLOCK, w // BLOCK, BLOCK).mean(axis=(1, 3))

    keep = blocks(m.astype(np.float64)) > 0.5
    ba, bb = blocks(a)[keep], blocks(b)[keep]
    return {"mean": mean, "blocks_rel_l2": float(np.sqrt(((ba - bb) ** 2).sum() / (bb ** 2).sum())),
            "pixels": int(m.sum()), "blocks": int(keep.sum())}


def side_by_side(pngs: dict[str, Path], errors: dict[str, dict], noise: dict, out: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt
    import OpenImageIO as oiio

    imgs = {m: np.asarray(oiio.ImageBuf(str(p)).get_pixels(oiio.FLOAT))[..., :3] for m, p in pngs.items()}
    h, w = next(iter(imgs.values())).shape[:2]
    fig, axes = plt.subplots(1, len(imgs), figsize=(3.3 * len(imgs), 3.3 * h / w + 0.6), constrained_layout=True)
    for ax, (m, im) in zip(axes, imgs.items()):
        ax.imshow(np.clip(im, 0, 1), interpolation="nearest")
        ax.set_xticks([])
        ax.set_yticks([])
        if m == "table":
            ax.set_title(f"table (seeds differ: mean {100 * noise['mean']:+.1f} %, "
                         f"blocks {100 * noise['blocks_rel_l2']:.1f} %)", fontsize=7)
        else:
            e = errors[m]
            ax.set_title(f"{m}: mean {100 * e['mean']:+.1f} %, 4x4 blocks {100 * e['blocks_rel_l2']:.1f} %",
                         fontsize=7)
    fig.suptitle(title, fontsize=8)
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--stages", nargs="+", default=["fig11_threads", "fig1_satin_garter"])
    ap.add_argument("--resolution", default="320x180")
    ap.add_argument("--spp", nargs=2, type=int, default=[4, 16])
    ap.add_argument("--cache-dir", type=Path, default=Path("/tmp/usdfiber-model-bench"))
    ap.add_argument("--out", type=Path, default=REPO / "bench/results/models.json")
    ap.add_argument("--png-dir", type=Path, default=REPO / "docs/renders")
    ap.add_argument("--work", type=Path, default=Path("/tmp/usdfiber-model-bench-out"))
    ap.add_argument("--bake-resolution", default="15", help="table grid, degrees (default 15)")
    ap.add_argument("--bake-photons", default="10000", help="photons per direction (default 10000)")
    args = ap.parse_args()
    lo, hi = sorted(args.spp)
    bake = ["--bake-resolution", args.bake_resolution, "--bake-photons", args.bake_photons]
    args.work.mkdir(parents=True, exist_ok=True)
    args.png_dir.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in args.stages:
        stage = REPO / "examples" / f"{name}.usda"
        runs: dict[str, dict] = {}
        for model in MODELS:
            a = render(stage, args.work / f"{name}_{model}_{lo}.exr", model, lo, args.resolution, args.cache_dir, bake)
            b = render(stage, args.work / f"{name}_{model}_{hi}.exr", model, hi, args.resolution, args.cache_dir, bake)
            slope = (b["times_s"]["render"] - a["times_s"]["render"]) / (hi - lo)
            runs[model] = {"first": a, "second": b, "s_per_spp": slope,
                           "fixed_s": a["times_s"]["render"] - slope * lo}
            print(f"{name} {model}: {1000 * slope:.0f} ms/spp (+{runs[model]['fixed_s']:.1f} s fixed), "
                  f"first run: tables {a['times_s'].get('tables', 0):.1f} s, translate "
                  f"{a['times_s'].get('translate', 0):.1f} s", flush=True)
        seed1 = args.work / f"{name}_table_{hi}_seed1.exr"
        render(stage, seed1, "table", hi, args.resolution, args.cache_dir, bake, seed=1)
        ref, alpha = pixels(args.work / f"{name}_table_{hi}.exr")
        noise = image_error(pixels(seed1)[0], ref, alpha)
        errors = {m: image_error(pixels(args.work / f"{name}_{m}_{hi}.exr")[0], ref, alpha) for m in MODELS[1:]}
        print(f"{name}: noise (two table seeds) mean {100 * noise['mean']:+.2f} %, blocks "
              f"{100 * noise['blocks_rel_l2']:.2f} %; "
              + "; ".join(f"{m} mean {100 * e['mean']:+.2f} %, blocks {100 * e['blocks_rel_l2']:.2f} %"
                          for m, e in errors.items()), flush=True)
        pngs = {m: args.work / f"{name}_{m}_{hi}.png" for m in MODELS}
        side_by_side(pngs, errors, noise, args.png_dir / f"models_{name}.png",
                     f"{name}, {args.resolution}, {hi} spp: table | Chiang (Mitsuba hair) | Khungurn 2015; "
                     f"errors against the table render")
        rows.append({"stage": name, "resolution": args.resolution, "spp": [lo, hi], "noise": noise,
                     "errors": errors,
                     "models": {m: {"s_per_spp": r["s_per_spp"], "fixed_s": r["fixed_s"],
                                    "times_first": r["first"]["times_s"], "times_second": r["second"]["times_s"],
                                    "counts": r["second"].get("counts")} for m, r in runs.items()}})
    load = os.getloadavg()
    out = {"machine": machine(load_average=load), "bake": bake, "rows": rows}
    write_results(args.out, out)
    print(f"wrote {args.out}; load average {load[0]:.1f} {load[1]:.1f} {load[2]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
