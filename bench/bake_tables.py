"""Benchmark: bake time and size per fiber, extrapolated to 2 deg tables.

    python bench/bake_tables.py [--resolution 15] [--probe-photons 18,21] [--quick]

Writes ``bench/results/tables.json`` (``--out`` names another file); what it records and
the error metrics: :mod:`bake_common`.
"""
from __future__ import annotations

import argparse
import math
import shutil
import sys
import tempfile
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from bench_common import Timer, md_table
from bake_common import (
    DEG, MAX_BOUNCES, Record, bench_parser, bytes_per_direction, fiber_case, fmt_pct, fmt_time,
    model_nbytes, parse_counts, results_path, table_facts)


PAPER_PHOTONS = 16_000_000                  # "sixteen million photons" per light direction
# Aliaga et al. 2017, Table 2: average cost, incoming x outgoing resolution, BCSDF storage.
PAPER_TABLE2 = {
    "polyester": {"minutes": 7, "incoming": [45, 1], "storage_MB": 2.7},
    "silk": {"minutes": 360, "incoming": [45, 180], "storage_MB": 500.5},
    "cotton": {"minutes": 420, "incoming": [45, 180], "storage_MB": 500.5},
    "wool": {"minutes": 900, "incoming": [90, 180], "storage_MB": 1001.0},
}
TARGETS = {
    "bake_minutes_per_fiber_at_16M_error": 30.0,
    "storage_MB_per_fiber_at_1pct": 50.0,
    "recolour_seconds": 1.0,
    "rel_l2": 0.01,
}


def probe(fs, case: dict[str, Any], grid, theta: float, phi: float, n: int, batches: int,
          levels_um: np.ndarray, warm: set[int]) -> dict[str, Any]:
    """One incoming direction traced and binned the way the baker does it (batches with the
    baker's seeds, K absorption levels with path-length moments, batch-variance error)."""
    from usdfiber.bake import tracer
    from usdfiber.bake.assembly import band_rows

    n_r, n_c = grid.n_theta_o, grid.n_phi_o
    nb = n_r * n_c
    K = len(levels_um)
    n_b = int(math.ceil(n / batches))
    for b in range(batches):                     # kernel compilation per seed: not timed
        if b not in warm:
            tracer.trace(fs, theta, phi, 1024, eta=case["eta"], beta_deg=case["beta_deg"],
                         max_bounces=MAX_BOUNCES, seed=b, cuticle=case["cuticle"])
            warm.add(b)
    H = np.zeros((K, nb))
    hists, norms = [], []
    with Timer() as t:
        for b in range(batches):
            r = tracer.trace(fs, theta, phi, n_b, eta=case["eta"], beta_deg=case["beta_deg"],
                             max_bounces=MAX_BOUNCES, seed=b, cuticle=case["cuticle"])
            idx = grid.bin_index(r.directions)
            L = r.path_length.astype(np.float64)
            alive = ~np.asarray(r.cut, dtype=bool)
            h = np.zeros((K, nb))
            gl = np.zeros((K, nb))
            for k, s in enumerate(levels_um):
                w = np.exp(-s * L) if s > 0 else np.ones_like(L)
                w = np.where(alive, w, 0.0)
                h[k] = np.bincount(idx, weights=w, minlength=nb)
                gl[k] = np.bincount(idx, weights=w * L, minlength=nb)
            H += h
            hists.append(h[0])
            norms.append(float(r.n_hit))
        dom = np.repeat(grid.solid_angles(), n_c)
        ps = np.stack([h / nn for h, nn in zip(hists, norms)]) / dom
        if grid.phi_invariant:
            idx_m = (-np.arange(n_c)) % n_c
            ps3 = ps.reshape(len(ps), n_r, n_c)
            ps = (0.5 * (ps3 + ps3[..., idx_m])).reshape(len(ps), nb)
        w = np.asarray(norms) / sum(norms)
        mean = w @ ps
        var = (w @ (ps - mean) ** 2) * len(ps) / (len(ps) - 1) * float((w ** 2).sum())
        err = math.sqrt(float((dom * var).sum()) / float((dom * mean ** 2).sum()))
    mass = np.zeros(n_r)
    Hr = H.reshape(K, n_r, n_c).sum(axis=-1)
    for k in range(K):
        tot = Hr[k].sum()
        if tot > 0:
            mass = np.maximum(mass, Hr[k] / tot)
    lo, hi = band_rows(mass, 1e-5)
    return {"theta_i_deg": math.degrees(theta), "phi_i_deg": math.degrees(phi), "photons": n_b * batches,
            "seconds": t.wall, "cores_used": t.cores, "rel_l2": err, "c": err * math.sqrt(n_b * batches),
            "band_rows": hi - lo}


def cmd_tables(args: argparse.Namespace) -> int:
    from usdfiber.bake import tracer
    from usdfiber.bake.absorption import DEFAULT_LEVELS
    from usdfiber.bake.baker import bake_table, is_rotationally_symmetric
    from usdfiber.bake.grid import Grid
    from usdfiber.bake.settings import BakeSettings

    rec = Record("tables", args)
    fibers = args.fibers.split(",")
    probe_counts = parse_counts(args.probe_photons)
    res, photons, batches = args.resolution, args.photons, args.batches
    if args.quick:
        probe_counts, res, photons = [1 << 12, 1 << 14], 30.0, 2048
    K = len(DEFAULT_LEVELS)
    results = []
    tmp = Path(tempfile.mkdtemp(prefix="bake-bench-"))
    try:
        for kind in fibers:
            case = fiber_case("wool-cuticle" if kind == "wool" else kind)
            prof, cut = case["profile"], case["cuticle"]
            entry: dict[str, Any] = {"fiber": kind, "eta": case["eta"], "beta_deg": case["beta_deg"], "cuticle": cut}
            # 1. A real bake at a resolution that fits.
            st = BakeSettings(resolution_deg=res, photons=photons, batches=batches)
            print(f"[{kind}] baking at {res:g} deg, {photons} photons per direction ...", flush=True)
            with Timer() as t:
                tab = bake_table(prof, case["eta"], case["beta_deg"], cut, st)
            path = tmp / f"{kind}.npz"
            tab.save(path)
            entry["coarse_bake"] = {"settings": {"resolution_deg": res, "photons": photons, "batches": batches},
                                    "wall_seconds": t.wall, "cores_used": t.cores,
                                    "photons_total": int(tab.arrays["photons"].sum()),
                                    "photons_per_s": int(tab.arrays["photons"].sum()) / t.wall,
                                    **table_facts(tab, path)}
            # 2. Probes at 2 degrees: cost per direction and error per direction vs photons.
            sym = cut is None
            grid2 = Grid(2.0, sym, is_rotationally_symmetric(prof))
            levels_um = np.asarray(DEFAULT_LEVELS) / float(prof.circumscribed_diameter)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)
                with Timer() as tp:
                    fs = tracer.prepare(prof, cut)
            thetas = [5.0, 35.0, 65.0, 85.0] + ([] if sym else [-35.0, -85.0])
            phi = 1.0 if grid2.phi_invariant else 25.0
            warm: set[int] = set()
            probes = []
            for n in probe_counts:
                for td in thetas:
                    pr = probe(fs, case, grid2, td * DEG, phi * DEG, n, args.probe_batches, levels_um, warm)
                    probes.append(pr)
                    print(f"  probe 2 deg theta_i {td:g} phi_i {phi:g}: {pr['photons']} photons "
                          f"{pr['seconds']:.2f} s, rel L2 {100 * pr['rel_l2']:.2f}%, band {pr['band_rows']}", flush=True)
            # Cost per direction: t = a + b N (least squares over the probes).
            A = np.array([[1.0, p["photons"]] for p in probes])
            a, b = np.linalg.lstsq(A, np.array([p["seconds"] for p in probes]), rcond=None)[0]
            a = max(float(a), 0.0)
            big = [p for p in probes if p["photons"] == max(pp["photons"] for pp in probes)]
            small = [p for p in probes if p["photons"] == min(pp["photons"] for pp in probes)]
            c_max = max(p["c"] for p in big)
            c_rms = math.sqrt(float(np.mean([p["c"] ** 2 for p in big])))
            scaling = [pb["rel_l2"] / ps_["rel_l2"] for pb, ps_ in zip(big, small)]
            band = max(p["band_rows"] for p in probes)
            n_dir = grid2.n_theta_i * grid2.n_phi_i
            n1 = (c_max / TARGETS["rel_l2"]) ** 2
            n1_rms = (c_rms / TARGETS["rel_l2"]) ** 2
            t_dir = lambda N: a + b * N  # noqa: E731
            entry["probes_2deg"] = {"prepare_seconds": tp.wall, "batches": args.probe_batches, "probes": probes,
                                    "cost_per_direction": {"a_seconds": a, "b_seconds_per_photon": float(b),
                                                           "photons_per_s": 1.0 / float(b)},
                                    "c_max": c_max, "c_rms": c_rms,
                                    "error_ratio_big_over_small": scaling,
                                    "expected_ratio": math.sqrt(min(probe_counts) / max(probe_counts)),
                                    "band_rows_max": band}
            entry["extrapolation_2deg"] = {
                "formula": "T = n_dir * (a + b * N); N_1% = (c_max / 0.01)^2 with c = rel_L2 * sqrt(N) "
                           "measured at 2 deg; size = n_dir * bytes_per_direction(K, band, 180) + fixed",
                "directions": n_dir, "incoming": [grid2.n_theta_i, grid2.n_phi_i],
                "photons_for_1pct_worst": n1, "photons_for_1pct_rms": n1_rms,
                "minutes_at_1pct_worst": n_dir * t_dir(n1) / 60.0,
                "minutes_at_1pct_rms": n_dir * t_dir(n1_rms) / 60.0,
                "minutes_at_16M": n_dir * t_dir(PAPER_PHOTONS) / 60.0,
                "rel_l2_at_16M_worst": c_max / math.sqrt(PAPER_PHOTONS),
                "rel_l2_at_16M_rms": c_rms / math.sqrt(PAPER_PHOTONS),
                "levels": K, "band_rows": band,
                "bytes_per_direction": bytes_per_direction(K, band, grid2.n_phi_o),
                "bytes": model_nbytes(n_dir, K, band, grid2.n_phi_o),
                "bytes_full_band": model_nbytes(n_dir, K, grid2.n_theta_o, grid2.n_phi_o),
                "bytes_one_level_float32_paper_layout": n_dir * grid2.n_theta_o * grid2.n_phi_o * 4,
                "compression_ratio_measured_coarse": entry["coarse_bake"]["file_bytes"] / entry["coarse_bake"]["nbytes"],
            }
            x = entry["extrapolation_2deg"]
            x["file_bytes_estimate"] = x["bytes"] * x["compression_ratio_measured_coarse"]
            # 3. A real 2 degree table where it fits (round fibers: 45 x 1 directions).
            if grid2.phi_invariant and not args.quick:
                st2 = BakeSettings(resolution_deg=2, photons=args.round_photons, batches=args.probe_batches)
                print(f"[{kind}] real 2 deg bake, {args.round_photons} photons per direction ...", flush=True)
                with Timer() as t2:
                    tab2 = bake_table(prof, case["eta"], case["beta_deg"], cut, st2)
                p2 = tmp / f"{kind}-2deg.npz"
                tab2.save(p2)
                facts = table_facts(tab2, p2)
                entry["real_2deg_bake"] = {"wall_seconds": t2.wall, "cores_used": t2.cores,
                                           "photons_per_direction": args.round_photons, **facts,
                                           "predicted_wall_seconds": n_dir * t_dir(args.round_photons),
                                           "predicted_rel_l2_worst": c_max / math.sqrt(args.round_photons)}
            results.append(entry)
            print_tables_entry(entry)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    rec.doc["results"] = results
    rec.doc["paper_table2"] = PAPER_TABLE2
    rec.doc["targets"] = TARGETS
    print_tables_summary(results)
    rec.finish(results_path(args, "tables"))
    return 0


def print_tables_entry(e: dict[str, Any]) -> None:
    cb = e["coarse_bake"]
    pr = e["probes_2deg"]
    print(f"\n### {e['fiber']}: real bake at {cb['resolution_deg']:g} deg: {cb['directions']} directions, "
          f"{cb['photons_per_direction']} photons each, {cb['wall_seconds']:.1f} s wall "
          f"({cb['photons_per_s'] / 1e3:.0f}k photons/s, {cb['cores_used']:.2f} cores), rel L2 rms "
          f"{fmt_pct(cb['rel_error_rms'])} max {fmt_pct(cb['rel_error_max'])}, {cb['nbytes'] / 1e6:.3f} MB in memory "
          f"(layout model {cb['model_nbytes'] / 1e6:.3f} MB), file {cb['file_bytes'] / 1e6:.3f} MB\n")
    rows = [[f"{p['theta_i_deg']:.0f},{p['phi_i_deg']:.0f}", p["photons"], f"{p['seconds']:.2f}",
             f"{p['cores_used']:.2f}", fmt_pct(p["rel_l2"]), f"{p['c']:.0f}", p["band_rows"]] for p in pr["probes"]]
    print(md_table(["dir (deg)", "photons", "s", "cores", "rel L2 (2 deg)", "c = e sqrt(N)", "band rows"], rows))
    cp = pr["cost_per_direction"]
    print(f"\ncost per direction t = {cp['a_seconds']:.3f} s + N / {cp['photons_per_s'] / 1e3:.0f}k; "
          f"error ratio big/small {['%.2f' % s for s in pr['error_ratio_big_over_small']]} "
          f"(1/sqrt scaling: {pr['expected_ratio']:.2f})")
    if "real_2deg_bake" in e:
        r = e["real_2deg_bake"]
        print(f"real 2 deg bake: {r['directions']} directions x {r['photons_per_direction']} photons: "
              f"{r['wall_seconds']:.1f} s (predicted {r['predicted_wall_seconds']:.1f} s), rel L2 rms "
              f"{fmt_pct(r['rel_error_rms'])} max {fmt_pct(r['rel_error_max'])} (predicted worst "
              f"{fmt_pct(r['predicted_rel_l2_worst'])}), {r['nbytes'] / 1e6:.3f} MB (model "
              f"{r['model_nbytes'] / 1e6:.3f}), file {r['file_bytes'] / 1e6:.3f} MB", flush=True)


def print_tables_summary(results: list[dict[str, Any]]) -> None:
    rows = []
    for e in results:
        x = e["extrapolation_2deg"]
        paper = PAPER_TABLE2.get(e["fiber"], PAPER_TABLE2["cotton"] if e["fiber"] == "mercerizedCotton" else None)
        rows.append([
            e["fiber"], f"{x['incoming'][0]}x{x['incoming'][1]}",
            f"{x['photons_for_1pct_worst'] / 1e6:.1f}M", f"{fmt_time(x['minutes_at_1pct_worst'] * 60)}",
            f"{fmt_time(x['minutes_at_16M'] * 60)}", fmt_pct(x["rel_l2_at_16M_worst"]),
            None if paper is None else f"{paper['minutes']} min",
            x["band_rows"], f"{x['bytes'] / 1e6:.0f}", f"{x['file_bytes_estimate'] / 1e6:.0f}",
            f"{x['bytes_one_level_float32_paper_layout'] / 2**20:.1f}",
            None if paper is None else f"{paper['storage_MB']}",
        ])
    print("\n### EXTRAPOLATED to the paper's full resolution (2 deg), per table (one cross-section variant)\n")
    print(md_table(["fiber", "incoming", "photons/dir for 1% (worst)", "time at 1%", "time at 16M/dir",
                    "rel L2 at 16M (worst)", "paper time", "band rows", "MB (our layout, K=11)",
                    "MB compressed (est.)", "MiB one level f32", "paper MB"], rows))


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser(__doc__)
    ap.add_argument("--fibers", default="polyester,silk,cotton,mercerizedCotton,wool",
                    help="presets (wool with its cuticle scales, as the paper's wool table)")
    ap.add_argument("--resolution", type=float, default=15.0, help="resolution of the real bakes (deg)")
    ap.add_argument("--photons", type=int, default=1 << 16, help="photons per direction of the real bakes")
    ap.add_argument("--batches", type=int, default=4, help="batches per direction of the real bakes")
    ap.add_argument("--probe-photons", default="18,21", help="photons per 2 deg probe direction, powers of 2")
    ap.add_argument("--probe-batches", type=int, default=8, help="batches per probe direction (BakeSettings default)")
    ap.add_argument("--round-photons", type=int, default=1 << 18,
                    help="photons per direction of the real 2 deg bake of round fibers")
    return cmd_tables(ap.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
