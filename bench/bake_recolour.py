"""Benchmark: BcsdfTable.recolour time and error against direct traces.

    python bench/bake_recolour.py [--full-size] [--quick]

Writes ``bench/results/recolour.json`` (``--out`` names another file); what it records and
the error metrics: :mod:`bake_common`.
"""
from __future__ import annotations

import argparse
import math
import sys
from typing import Any

import numpy as np

from bench_common import Timer, md_table, meminfo_gib
from bake_common import (
    Record, bench_parser, fiber_case, fmt_pct, model_nbytes, rel_l2, results_path, synthetic_table, table_facts)


def time_recolour(table, rgb_sets: list[tuple[float, float, float]]) -> dict[str, Any]:
    """Cold (fresh table object: includes the solid-angle cache) and warm (new absorption) times."""
    from usdfiber.bake.table import BcsdfTable

    cold, warm, mono = [], [], []
    for i, rgb in enumerate(rgb_sets):
        t = BcsdfTable(header=table.header, arrays=table.arrays)
        with Timer() as tc:
            t.recolour(rgb)
        cold.append(tc.wall)
        with Timer() as tw:
            t.recolour(tuple(x * 1.37 for x in rgb))
        warm.append(tw.wall)
        with Timer() as tm:
            t.recolour(rgb[1] * 0.71)
        mono.append(tm.wall)
        del t
    return {"rgb_cold_s": float(np.median(cold)), "rgb_warm_s": float(np.median(warm)),
            "mono_warm_s": float(np.median(mono)), "repeats": len(rgb_sets),
            "all_rgb_cold_s": cold, "all_rgb_warm_s": warm}


def recolour_error(table, case: dict[str, Any], settings, sigmas, nodes, independent_photons: int) -> list[dict]:
    """As tests/bake/test_table.py: the recoloured table against the bake's own photons weighted by
    exp(-sigma_a L) (same photons: interpolation + float16 only), and against an independent
    trace with that absorption (noise of both)."""
    from usdfiber.bake import binning, tracer
    from usdfiber.bake.baker import batch_seed

    g = table.grid
    xg = g                                   # the outgoing bins of the table's grid
    w = xg.bin_solid_angles()
    fs = tracer.prepare(case["profile"])
    n_b = int(math.ceil(settings.photons / settings.batches))
    out = []
    for (ti, pi) in nodes:
        th, ph = float(g.theta_i_nodes()[ti]), float(g.phi_i_nodes()[pi])
        same = [tracer.trace(fs, th, ph, n_b, eta=case["eta"], beta_deg=case["beta_deg"],
                             max_bounces=settings.max_bounces, seed=batch_seed(settings.seed, b))
                for b in range(settings.batches)]
        indep = [tracer.trace(fs, th, ph, independent_photons // 4, eta=case["eta"], beta_deg=case["beta_deg"],
                              max_bounces=settings.max_bounces, seed=7000 + b) for b in range(4)]
        for sig, dscale in sigmas:
            rec = table.recolour(sig, diameter_scale=dscale)
            s_eff = sig * dscale

            def direct(runs):
                dens = sum(binning.bin_direct(r, s_eff, xg) * r.n_hit for r in runs) / sum(r.n_hit for r in runs)
                lam = float((dens * w).sum())
                return dens / lam, lam

            p_same, lam_same = direct(same)
            # the table's own noise at this absorption: spread between the bake's batches
            pb = []
            for r in same:
                d = binning.bin_direct(r, s_eff, xg)
                pb.append(d / (d * w).sum())
            pb = np.stack(pb)
            e_tab = math.sqrt((w * pb.var(axis=0, ddof=1) / len(pb)).sum() / (w * pb.mean(axis=0) ** 2).sum())
            ps = []
            for r in indep:
                d = binning.bin_direct(r, s_eff, xg)
                ps.append(d / (d * w).sum())
            ps = np.stack(ps)
            p_ind = ps.mean(axis=0)
            e_ind = math.sqrt((w * ps.var(axis=0, ddof=1) / len(ps)).sum() / (w * p_ind ** 2).sum())
            p_tab = np.zeros_like(p_same)
            b0 = int(table.band_start[ti, pi])
            p_tab[b0:b0 + table.n_band] = rec.p[ti, pi, :, :, 0]
            out.append({
                "theta_i_deg": math.degrees(th), "phi_i_deg": math.degrees(ph), "sigma_a": sig,
                "diameter_scale": dscale, "optical_depth": s_eff,
                "l2_vs_same_photons": rel_l2(p_tab, p_same, w),
                "table_noise_estimate_sigma0": float(table.rel_error[ti, pi]),
                "albedo_rel_diff_same_photons": float(rec.albedo[ti, pi, 0] / lam_same - 1.0),
                "l2_vs_independent": rel_l2(p_tab, p_ind, w),
                "independent_noise": e_ind,
                "table_noise_at_sigma": e_tab,
                "difference_expected_from_noise": math.sqrt(e_tab ** 2 + e_ind ** 2),
            })
    return out


def cmd_recolour(args: argparse.Namespace) -> int:
    from usdfiber.bake.baker import bake_table
    from usdfiber.bake.settings import BakeSettings

    rec = Record("recolour", args)
    rgb_sets = [(0.3, 1.1, 4.0), (0.05, 0.6, 2.5), (1.5, 3.0, 9.0)]
    out: dict[str, Any] = {"timing": [], "error": []}
    photons = 4096 if args.quick else args.photons
    # 1. Real tables: silk at 30 deg (the tests' recolouring fixture, more photons) and cotton.
    real = {}
    for name in ("silk", "cotton"):
        case = fiber_case(name)
        st = BakeSettings(resolution_deg=30, photons=photons, batches=4)
        with Timer() as t:
            tab = bake_table(case["profile"], case["eta"], case["beta_deg"], None, st)
        real[name] = (tab, case, st)
        print(f"baked {name} at 30 deg ({photons} photons per direction) in {t.wall:.1f} s", flush=True)
        tm = time_recolour(tab, rgb_sets)
        out["timing"].append({"table": f"{name} 30 deg (real)", **table_facts(tab), "bake_seconds": t.wall, **tm})
    # Real 2 degree table of a round fiber (45 x 1 directions, the paper's polyester layout).
    case = fiber_case("polyester")
    st = BakeSettings(resolution_deg=2, photons=4096 if args.quick else args.photons, batches=4)
    with Timer() as t:
        tab = bake_table(case["profile"], case["eta"], case["beta_deg"], None, st)
    print(f"baked polyester at 2 deg in {t.wall:.1f} s", flush=True)
    out["timing"].append({"table": "polyester 2 deg (real)", **table_facts(tab), "bake_seconds": t.wall,
                          **time_recolour(tab, rgb_sets)})
    # 2. Synthetic tables with the real layout at full angular resolution (timing only).
    sizes = [(6.0, True), (3.0, True), (2.5, True), (3.0, False)]
    if args.full_size:
        sizes += [(2.0, True)]
    if args.quick:
        sizes = [(15.0, True)]
    for res, sym in sizes:
        n_to, n_po = int(round(180 / res)), int(round(360 / res))
        est = model_nbytes((n_to // 2 if sym else n_to) * n_po, 11, n_to, n_po)
        avail = (meminfo_gib("MemAvailable") or 0) * 2**30
        if est * 2.5 > avail:
            out["timing"].append({"table": f"synthetic {res:g} deg", "skipped": f"needs ~{2.5 * est / 1e9:.1f} GB, "
                                  f"{avail / 1e9:.1f} GB available"})
            continue
        with Timer() as t:
            syn = synthetic_table(res, sym, None)
        label = f"synthetic {res:g} deg, {'extruded (silk/cotton)' if sym else 'cuticle (wool)'} layout, full band"
        print(f"built {label} ({syn.nbytes() / 1e9:.2f} GB) in {t.wall:.1f} s", flush=True)
        tm = time_recolour(syn, rgb_sets[:2])
        out["timing"].append({"table": label, **{k: v for k, v in table_facts(syn).items()
                                                  if not k.startswith("rel_error") and k != "photons_per_direction"},
                              **tm})
        del syn
    # Linear model of recolour time in the number of stored bins (directions x K x band x phi_o),
    # fitted on the synthetic tables, to put numbers on the full 2 degree layouts.
    pts = [(r["directions"] * r["levels"] * r["band_rows"] * r["outgoing"][1], r["rgb_warm_s"], r["rgb_cold_s"])
           for r in out["timing"] if "rgb_warm_s" in r and r["table"].startswith("synthetic")]
    if len(pts) >= 2:
        x = np.array([p[0] for p in pts], float)
        fw = np.polyfit(x, [p[1] for p in pts], 1)
        fc = np.polyfit(x, [p[2] for p in pts], 1)
        ext = []
        for label, nti, npi in (("silk / cotton 2 deg (45 x 180)", 45, 180), ("wool 2 deg (90 x 180)", 90, 180)):
            for band in (90, 60):
                bins = nti * npi * 11 * band * 180
                ext.append({"table": label, "band_rows": band, "stored_values": bins,
                            "rgb_warm_s": float(np.polyval(fw, bins)), "rgb_cold_s": float(np.polyval(fc, bins))})
        out["extrapolated_full_size"] = {"model": "seconds = a + b * (directions x levels x band x phi_o), "
                                                  "least squares over the synthetic tables",
                                         "warm_ab": fw[::-1].tolist(), "cold_ab": fc[::-1].tolist(), "rows": ext}
    # 3. Error against direct traces (as in tests/bake/test_table.py).
    sigmas = [(0.3, 1.0), (1.5, 2.0), (3.0, 1.0), (5.0, 1.0), (20.0, 1.0), (100.0, 1.0)]
    for name, (tab, case, st) in real.items():
        nodes = [(0, 0), (1, 5), (2, 9)]
        errs = recolour_error(tab, case, st, sigmas, nodes, 4096 if args.quick else 4 * args.photons)
        for e in errs:
            e["table"] = f"{name} 30 deg"
        out["error"] += errs
    rec.doc["results"] = out
    print_recolour(out)
    rec.finish(results_path(args, "recolour"))
    return 0


def print_recolour(out: dict[str, Any]) -> None:
    rows = []
    for r in out["timing"]:
        if "skipped" in r:
            rows.append([r["table"], None, None, None, None, None, r["skipped"]])
            continue
        rows.append([r["table"], f"{r['incoming'][0]}x{r['incoming'][1]}", r["band_rows"],
                     f"{r['nbytes'] / 1e6:.1f}", f"{r['rgb_cold_s']:.3f}", f"{r['rgb_warm_s']:.3f}",
                     f"{r['mono_warm_s']:.3f}"])
    print("\n### recolour time (median; RGB = 3 distinct absorptions)\n")
    print(md_table(["table", "incoming", "band rows", "MB in memory", "RGB cold s", "RGB warm s", "mono warm s"], rows))
    if "extrapolated_full_size" in out:
        x = out["extrapolated_full_size"]
        rows = [[r["table"], r["band_rows"], f"{r['stored_values'] / 1e9:.2f}e9", f"{r['rgb_cold_s']:.1f}",
                 f"{r['rgb_warm_s']:.1f}"] for r in x["rows"]]
        print(f"\nExtrapolated ({x['model']}):\n")
        print(md_table(["table", "band rows", "stored values", "RGB cold s", "RGB warm s"], rows))
    rows = [[r["table"], f"{r['theta_i_deg']:.0f},{r['phi_i_deg']:.0f}",
             f"{r['sigma_a']:g}" + ("" if r["diameter_scale"] == 1.0 else f" x{r['diameter_scale']:g}"),
             fmt_pct(r["l2_vs_same_photons"], 3), f"{100 * r['albedo_rel_diff_same_photons']:+.3f}%",
             fmt_pct(r["table_noise_at_sigma"]), fmt_pct(r["l2_vs_independent"]),
             fmt_pct(r["difference_expected_from_noise"])] for r in out["error"]]
    print("\n### recolour error against direct traces with that absorption (30 deg bins)\n")
    print(md_table(["table", "dir (deg)", "sigma_a (x diameter scale)", "L2 vs same photons",
                    "albedo diff (same photons)", "table noise at sigma", "L2 vs independent trace",
                    "expected from noise"], rows))


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser(__doc__)
    ap.add_argument("--photons", type=int, default=1 << 16, help="photons per direction of the real tables")
    ap.add_argument("--full-size", action="store_true",
                    help="also time a synthetic full 2 deg silk/cotton layout (needs ~15 GB of memory)")
    return cmd_recolour(ap.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
