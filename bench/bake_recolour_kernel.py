"""Benchmark: recolouring in the Dr.Jit kernel against the float64 numpy path, up to full 2 deg tables.

    python bench/bake_recolour_kernel.py [--quick]
    python bench/bake_recolour_kernel.py --versus REV [--res 2] [--paths levels,basis] [--colours 5]
                                         [--codes old,new]

Writes ``bench/results/recolour_kernel.json`` (``--out`` names another file); what it records and
the error metrics: :mod:`bake_common`. ``--versus REV`` times the kernels of
``usdfiber/bake/recolour.py`` at git revision ``REV`` and the working tree's side by side on one
table with the real layout (both paths: the levels and a rank-6 absorption basis), interleaved
(old, new, old, new, ...) so that both see the same load, and records wall and CPU seconds, the
time of every kernel (``dr.kernel_history()``), the page faults of every call, the process's
peak memory after each path and the largest difference between the two
(``recolour_kernel_versus.json``). ``--codes new`` (or ``old``) times one of them alone: its
peak memory without the other's.
"""
from __future__ import annotations

import argparse
import gc
import importlib.util
import resource
import subprocess
import sys
import tempfile
from pathlib import Path
import json
from typing import Any

import numpy as np

from bench_common import Timer, meminfo_gib
from bake_common import Record, bench_parser, model_nbytes, results_path, synthetic_table, table_facts


def cmd_recolour_kernel(args: argparse.Namespace) -> int:
    """Recolouring in the Dr.Jit kernel against the float64 numpy path, up to full 2 deg tables."""
    from usdfiber.bake.table import BcsdfTable

    rec = Record("recolour_kernel", args)
    rgbs = [(0.3, 1.1, 4.0), (0.41, 1.5, 5.5), (0.05, 0.6, 2.5), (1.5, 3.0, 9.0)]
    mono = 0.78
    sizes = [(15.0, True, None)] if args.quick else [(6.0, True, 83), (3.0, True, 83), (2.0, True, 83), (2.0, True, None),
                                                     (2.0, False, None)]
    out = []
    for res, sym, band in sizes:
        g_to, g_po = int(round(180 / res)), int(round(360 / res))
        B = g_to if band is None else min(band, g_to)
        n_dir = (g_to // 2 if sym else g_to) * g_po
        est = model_nbytes(n_dir, 11, B, g_po) + 3 * n_dir * B * g_po * 4
        avail = (meminfo_gib("MemAvailable") or 0) * 2**30
        label = f"{res:g} deg, {'extruded (silk/cotton)' if sym else 'cuticle (wool)'} layout, band {B}"
        if est * 1.3 > avail:
            out.append({"table": label, "skipped": f"needs ~{1.3 * est / 1e9:.1f} GB, {avail / 1e9:.1f} GB available"})
            continue
        syn = synthetic_table(res, sym, band)
        row: dict[str, Any] = {"table": label, **{k: v for k, v in table_facts(syn).items()
                                                  if not k.startswith("rel_error") and k != "photons_per_direction"}}
        t = BcsdfTable(header=syn.header, arrays=syn.arrays)
        with Timer() as tc:
            t.recolour(rgbs[0], kernel=True)
        row["kernel_rgb_cold_s"] = tc.wall
        warm = []
        for rgb in rgbs[1:]:
            t._recoloured.clear()
            with Timer() as tw:
                t.recolour(rgb, kernel=True)
            warm.append((tw.wall, tw.cores))
        row["kernel_rgb_warm_s"] = float(np.median([w for w, _ in warm]))
        row["kernel_rgb_warm_all"] = warm
        t._recoloured.clear()
        with Timer() as tm:
            k_mono = t.recolour(mono, kernel=True).p
        row["kernel_mono_s"] = tm.wall
        # The numpy reference: RGB where it is quick, else one channel (its time is per
        # channel), none where its float64 temporaries (about 12 arrays of one level) do not fit.
        n_ref = 3 if n_dir * B * g_po * 11 < 2e8 else 1
        avail = (meminfo_gib("MemAvailable") or 0) * 2**30
        if n_dir * B * g_po * 8 * 12 > avail:
            row["numpy_skipped"] = f"float64 reference needs ~{n_dir * B * g_po * 96 / 1e9:.0f} GB"
            out.append(row)
            print(f"{label}: kernel RGB cold {row['kernel_rgb_cold_s']:.2f} s, warm {row['kernel_rgb_warm_s']:.2f} s, "
                  f"mono {row['kernel_mono_s']:.2f} s; numpy skipped", flush=True)
            del k_mono, t, syn
            gc.collect()
            continue
        with Timer() as tr:
            ref = t.recolour(rgbs[1][:n_ref] if n_ref > 1 else mono, kernel=False).p
        row["numpy_s"] = tr.wall
        row["numpy_channels"] = n_ref
        k_ref = t.recolour(rgbs[1], kernel=True).p if n_ref > 1 else k_mono
        d = np.abs(k_ref.astype(np.float64) - ref)
        big = ref > 1e-6 * ref.max()
        row["max_rel_diff_kernel_vs_numpy"] = float((d[big] / ref[big]).max())
        row["rel_l2_kernel_vs_numpy"] = float(np.sqrt((d ** 2).sum() / (ref ** 2).sum()))
        del ref, k_ref, k_mono, t, syn
        gc.collect()                     # the next (larger) table needs this memory back
        out.append(row)
        print(f"{label}: kernel RGB cold {row['kernel_rgb_cold_s']:.2f} s, warm {row['kernel_rgb_warm_s']:.2f} s, "
              f"mono {row['kernel_mono_s']:.2f} s; numpy ({n_ref} channel(s)) {row['numpy_s']:.2f} s; "
              f"max rel diff {row['max_rel_diff_kernel_vs_numpy']:.2e}", flush=True)
    rec.doc["results"] = out
    rec.finish(results_path(args, "recolour_kernel"))
    return 0


def _module_at(rev: str):
    """``usdfiber/bake/recolour.py`` as it was at git revision ``rev``, as a module."""
    root = Path(__file__).resolve().parent.parent
    src = subprocess.run(["git", "show", f"{rev}:usdfiber/bake/recolour.py"], cwd=root, check=True,
                         capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp(prefix="recolour-")) / "recolour_at_rev.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location("recolour_at_rev", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _peak_rss_gib() -> float:
    """The process's peak resident memory so far (GiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def _timed(fn) -> dict[str, Any]:
    """Wall and CPU seconds of ``fn()``, its page faults and the seconds of each kernel it launched."""
    import drjit as dr

    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()                                # clears the history
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    with Timer() as t:
        out = fn()
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults
    kernels = [(round(k["execution_time"] / 1e3, 4), int(k["size"])) for k in dr.kernel_history()
               if k.get("execution_time", 0) > 0.5]
    dr.set_flag(dr.JitFlag.KernelHistory, False)
    return {"wall": t.wall, "cpu": t.cpu, "cores": t.cores, "kernels_s": kernels,
            "kernel_total_s": sum(k for k, _ in kernels), "page_faults": faults}, out


def cmd_versus(args: argparse.Namespace) -> int:
    """The working tree's kernels against those of ``args.versus``, interleaved."""
    import os

    from usdfiber.bake import recolour as new
    from usdfiber.bake.grid import Grid

    old = _module_at(args.versus)
    rec = Record("recolour_kernel_versus", args)
    paths = args.paths.split(",")
    codes = [c for c in ("old", "new") if c in args.codes.split(",")]
    # The levels (5.3 GB at 2 deg) only where that path is timed; the basis path needs the layout.
    syn = synthetic_table(args.res if "levels" in paths else 30.0, True, 83)
    g = Grid(args.res, True, False)
    n, B, n_po, K = g.n_theta_i * g.n_phi_i, min(83, g.n_theta_o), g.n_phi_o, len(syn.levels)
    start = (g.n_theta_o - B) // 2
    dom = np.broadcast_to(g.solid_angles()[start:start + B], (n, B)).copy()
    if "levels" in paths:
        a = syn.arrays
        p, lb = a["p"].reshape(n, K, B, n_po), a["lbar"].reshape(n, K, B, n_po)
        scale = (a["p_scale"].astype(np.float64) * a["albedo"]).reshape(n, K)
    R = 6

    def make_basis() -> np.ndarray:
        rng = np.random.default_rng(1)
        basis = np.empty((n, R, B, n_po), np.float16)
        for d0 in range(0, n, 256):
            basis[d0:d0 + 256] = rng.standard_normal((min(256, n - d0), R, B, n_po), dtype=np.float32)
        basis[:, 0] = np.abs(basis[:, 0]) + 2.0         # a positive leading component
        return basis

    rgbs = [(0.3, 1.1, 4.0), (0.41, 1.5, 5.5), (0.05, 0.6, 2.5), (1.5, 3.0, 9.0), (0.2, 0.9, 3.3)][:args.colours]
    facts = {"table": f"{args.res:g} deg, extruded (silk/cotton) layout, band {B}", "directions": n,
             "bins_per_channel": n * B * n_po, "levels_bytes": 4 * n * K * B * n_po, "basis_rank": R,
             "basis_bytes": 2 * n * R * B * n_po, "codes": codes}
    runs: list[dict[str, Any]] = []
    diffs = {"levels": 0.0, "basis": 0.0}
    peak: dict[str, float] = {"before_paths": _peak_rss_gib()}

    def levels(mod, rgb):
        return mod.recolour_p(p, lb, scale, dom, syn.levels, rgb)

    def basis_path(mod, rgb):
        coef = rng_c.standard_normal((n, 3, R)).astype(np.float32) * 0.1
        coef[:, :, 0] = 1.0 + 0.1 * np.asarray(rgb, np.float32)
        return mod.recolour_basis(basis, coef, dom)

    for path, fn in [(q, f) for q, f in (("levels", levels), ("basis", basis_path)) if q in paths]:
        if path == "basis":
            p = lb = syn = a = None                    # the levels' memory back before the basis's
            gc.collect()
            basis = make_basis()
        for k, rgb in enumerate(rgbs):                 # the first colour warms up (compiles) each
            outs = {}
            order = [(c, {"old": old, "new": new}[c]) for c in codes]
            for name, mod in order if k % 2 == 0 else order[::-1]:
                rng_c = np.random.default_rng(k)
                la = os.getloadavg()[0]
                r, out = _timed(lambda: fn(mod, rgb))
                outs[name] = out[:max(1, n // 8)].copy()     # compared on an eighth: memory
                del out
                runs.append({"path": path, "code": name, "rgb": rgb, "warm": k > 0, "load_1min": la, **r})
                print(f"{path} {name} {rgb}: wall {r['wall']:.3f} s, cpu {r['cpu']:.3f} s, "
                      f"kernels {r['kernel_total_s']:.3f} s {r['kernels_s']}, load {la:.1f}", flush=True)
            if len(outs) == 2:
                ref = outs["old"]
                big = ref > 1e-6 * ref.max()
                diffs[path] = max(diffs[path], float((np.abs(outs["new"] - ref)[big] / ref[big]).max()))
                del ref, big
            del outs
            gc.collect()
        peak[f"after_{path}"] = _peak_rss_gib()
    summary = {}
    for path in paths:
        for name in codes:
            w = [r for r in runs if r["path"] == path and r["code"] == name and r["warm"]]
            summary[f"{path}_{name}"] = {q: float(np.median([r[q] for r in w]))
                                         for q in ("wall", "cpu", "kernel_total_s", "load_1min")}
        if len(codes) == 2:
            o, nw = summary[f"{path}_old"], summary[f"{path}_new"]
            summary[f"{path}_ratio_new_over_old"] = {q: nw[q] / o[q] for q in ("wall", "cpu", "kernel_total_s")}
    rec.doc["results"] = {"facts": facts, "versus": args.versus, "runs": runs, "median_warm": summary,
                          "max_rel_diff_new_vs_old": diffs, "peak_rss_gib": peak}
    print(json.dumps(summary, indent=1), flush=True)
    rec.finish(results_path(args, "recolour_kernel_versus"))
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser(__doc__)
    ap.add_argument("--versus", metavar="REV", help="time against the kernels of this git revision, side by side")
    ap.add_argument("--res", type=float, default=2.0, help="bin size of the --versus table (deg)")
    ap.add_argument("--paths", default="levels,basis", help="the --versus paths timed (levels, basis)")
    ap.add_argument("--colours", type=int, default=5, help="RGB colours per --versus path (the first warms up)")
    ap.add_argument("--codes", default="old,new", help="the --versus codes timed (old, new; one alone: its peak memory)")
    args = ap.parse_args(argv)
    return cmd_versus(args) if args.versus else cmd_recolour_kernel(args)


if __name__ == "__main__":
    sys.exit(main())
