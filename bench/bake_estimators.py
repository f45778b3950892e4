"""Variance-reduction estimators of the baker: gain at equal error, side by side in one run.

Part ``direction`` (the stratified estimator, per incoming direction): for each fiber and
probe direction, a plain reference of ``16 x N`` photons (``--ref-factor``) in 4 independent
batches (their spread gives the reference's own noise), then ``--repeats`` interleaved pairs
of calls of N photons: plain (independent PCG32 numbers) and stratified (scrambled Sobol beam
offset and first event). Error: relative L2 of p on the paper's 2 degree bins against the
reference, with the reference's noise subtracted in quadrature (``e^2 = d^2 - e_ref^2``; the
raw d is in the JSON). Gain = (t_plain e_plain^2) / (t_new e_new^2): the ratio of the times to
reach the same error if the error falls as N^-1/2 (true for plain; the stratified error falls
at least as fast, so the gain at more photons is at least this). The worst direction of a
fiber sets its figure.

Part ``split`` (splitting at the outer surface, ``--splits`` walks per hit): as ``direction``,
with plain and split calls interleaved; both wall and CPU time (``time.process_time``: all
threads of this process) are recorded, and the gain is computed from the CPU time, which a
machine shared with other work distorts less than the wall time.

Part ``expected`` (the expected-value estimator at the outer boundary, ``--expected`` normals
per event): as ``split``, with plain and expected-value calls interleaved; each call is timed
with what a bake does with its exits, the histograms at the baker's 11 absorption levels
(plain: numpy binning of every exit, as ``DirectionStatistics.add``; expected: the same for the
exits it does not deposit, plus its in-kernel histograms): CPU seconds of the trace and of the
binning are recorded apart, and the gain uses their sum. ``ev_fraction`` is the share of the
exit weight deposited as expectations (the rest left where leaving is not known to be for good).

Part ``table`` (reciprocity, which needs whole tables): box-filtered bakes of a table, plain
and with reciprocity averaging, ``--table-photons`` per direction, against a plain box bake
with 16x the photons; error per direction as above (the table's own bins, p at zero
absorption), time = the whole bake (tracing and assembly).

    python bench/bake_estimators.py                      # about 15 min on 2 idle cores
    python bench/bake_estimators.py --quick              # smoke test
"""
from __future__ import annotations

import argparse
import math
import time

import numpy as np

from bake_common import RESULTS, Record, fiber_case, fmt_pct, rel_l2, solid_angles
from bench_common import md_table

DEFAULT_DIRECTIONS = "0,25;20,115;40,25;60,205;75,65;85,155"
TABLE_CASES = {"polyester": 2.0, "silk": 30.0, "cotton": 30.0}


def _p2(r) -> np.ndarray:
    """p per steradian on the 2 degree bins (90 x 180), per photon that hit."""
    from usdfiber.bake.binning import bin_direct

    return bin_direct(r)


def direction_part(args, rec) -> list[dict]:
    from usdfiber.bake import tracer

    dirs = [tuple(float(x) for x in d.split(",")) for d in args.directions.split(";") if d]
    w = solid_angles()
    N, M = 1 << args.photons_log2, (1 << args.photons_log2) * args.ref_factor
    out = []
    for name in args.fibers.split(","):
        case = fiber_case(name)
        fs = tracer.prepare(case["profile"], case["cuticle"])
        kw = dict(eta=case["eta"], beta_deg=case["beta_deg"], cuticle=case["cuticle"], max_bounces=4096)
        for smp in ("independent", "sobol"):        # compile both kernels before timing
            tracer.trace(fs, 0.3, 0.2, 4096, seed=1, sampler=smp, **kw)
        for j, (th, ph) in enumerate(dirs):
            t_i, p_i = math.radians(th), math.radians(ph)
            refs = [_p2(tracer.trace(fs, t_i, p_i, M // 4, seed=10_000 + 10 * j + b, **kw)) for b in range(4)]
            ref = np.mean(refs, axis=0)
            e_ref2 = float(np.sum(w * np.var(refs, axis=0, ddof=1) / 4) / np.sum(w * ref ** 2))
            runs: dict[str, list] = {"independent": [], "sobol": []}
            for k in range(args.repeats):
                for smp in ("independent", "sobol"):
                    t0 = time.perf_counter()
                    r = tracer.trace(fs, t_i, p_i, N, seed=20_000 + 100 * j + 2 * k + (smp == "sobol"), sampler=smp, **kw)
                    dt = time.perf_counter() - t0
                    d = rel_l2(_p2(r), ref, w)
                    runs[smp].append({"seconds": dt, "d": d, "e": math.sqrt(max(d * d - e_ref2, 0.0))})
            row = {"fiber": name, "theta_i": th, "phi_i": ph, "photons": N, "ref_photons": M,
                   "e_ref": math.sqrt(e_ref2), "load": list(np.round(np.array(__import__("os").getloadavg()), 2))}
            for smp, rs in runs.items():
                row[smp] = {"seconds": float(np.median([x["seconds"] for x in rs])),
                            "e": float(np.sqrt(np.mean([x["e"] ** 2 for x in rs]))),
                            "d": [x["d"] for x in rs], "runs": rs}
            a, b = row["independent"], row["sobol"]
            row["gain"] = (a["seconds"] * a["e"] ** 2) / (b["seconds"] * b["e"] ** 2) if b["e"] > 0 else math.inf
            # Raw distances include the reference's noise on both sides: closer to 1 than the truth.
            d2a, d2b = np.mean(np.square(a["d"])), np.mean(np.square(b["d"]))
            row["gain_raw"] = float((a["seconds"] * d2a) / (b["seconds"] * d2b))
            print(f"{name:10s} theta {th:4.0f} phi {ph:4.0f}: plain {fmt_pct(a['e'])} {a['seconds']:.2f} s, "
                  f"stratified {fmt_pct(b['e'])} {b['seconds']:.2f} s, gain {row['gain']:.2f}", flush=True)
            out.append(row)
    return out


def _plain_reference(trace_plain, seed0: int, M: int, w: np.ndarray) -> tuple[np.ndarray, float]:
    """The plain reference of ``M`` photons in 4 independent batches and its own squared error
    (from their spread): ``trace_plain(n, seed)`` traces one batch."""
    refs = [_p2(trace_plain(M // 4, seed0 + b)) for b in range(4)]
    ref = np.mean(refs, axis=0)
    return ref, float(np.sum(w * np.var(refs, axis=0, ddof=1) / 4) / np.sum(w * ref ** 2))


def _row(name: str, th: float, ph: float, N: int, M: int, e_ref2: float) -> dict:
    return {"fiber": name, "theta_i": th, "phi_i": ph, "photons": N, "ref_photons": M,
            "e_ref": math.sqrt(e_ref2), "load": list(np.round(np.array(__import__("os").getloadavg()), 2))}


def _ratios_to_plain(row: dict, ks: list[int]) -> None:
    """Variance, CPU and wall ratios of each K against plain (K0), and the gain at equal error."""
    a = row["K0"]
    for k in ks:
        b = row[f"K{k}"]
        row[f"var_ratio_K{k}"] = a["e"] ** 2 / b["e"] ** 2 if b["e"] > 0 else math.inf
        row[f"cpu_ratio_K{k}"] = b["cpu"] / a["cpu"]
        row[f"wall_ratio_K{k}"] = b["seconds"] / a["seconds"]
        row[f"gain_K{k}"] = row[f"var_ratio_K{k}"] / row[f"cpu_ratio_K{k}"]


def split_part(args, rec) -> list[dict]:
    from usdfiber.bake import tracer

    dirs = [tuple(float(x) for x in d.split(",")) for d in args.directions.split(";") if d]
    ks = [int(k) for k in args.splits.split(",")]
    w = solid_angles()
    N, M = 1 << args.split_photons_log2, (1 << args.split_photons_log2) * args.ref_factor
    out = []
    for name in args.split_fibers.split(","):
        case = fiber_case(name)
        fs = tracer.prepare(case["profile"], case["cuticle"])
        kw = dict(eta=case["eta"], beta_deg=case["beta_deg"], cuticle=case["cuticle"], max_bounces=4096)
        for k in [0] + ks:                           # compile every kernel before timing
            tracer.trace(fs, 0.3, 0.2, 4096, seed=1, split=k, **kw)
        for j, (th, ph) in enumerate(dirs):
            t_i, p_i = math.radians(th), math.radians(ph)
            ref, e_ref2 = _plain_reference(lambda n, sd: tracer.trace(fs, t_i, p_i, n, seed=sd, **kw),
                                           30_000 + 10 * j, M, w)
            runs: dict[int, list] = {k: [] for k in [0] + ks}
            for rep_ in range(args.repeats):
                for k in runs:
                    t0, c0 = time.perf_counter(), time.process_time()
                    r = tracer.trace(fs, t_i, p_i, N, seed=40_000 + 100 * j + 10 * rep_ + k, split=k, **kw)
                    dt, dc = time.perf_counter() - t0, time.process_time() - c0
                    d = rel_l2(_p2(r), ref, w)
                    runs[k].append({"seconds": dt, "cpu": dc, "d": d, "e2": d * d - e_ref2})
            row = _row(name, th, ph, N, M, e_ref2)
            for k, rs in runs.items():
                row[f"K{k}"] = {"seconds": float(np.median([x["seconds"] for x in rs])),
                                "cpu": float(np.median([x["cpu"] for x in rs])),
                                "e": math.sqrt(max(float(np.mean([x["e2"] for x in rs])), 0.0)), "runs": rs}
            a = row["K0"]
            _ratios_to_plain(row, ks)
            print(f"{name:10s} theta {th:4.0f} phi {ph:4.0f}: plain {fmt_pct(a['e'])} {a['cpu']:.2f} s cpu; "
                  + "; ".join(f"K={k} {fmt_pct(row[f'K{k}']['e'])} var x{row[f'var_ratio_K{k}']:.2f} "
                              f"cpu x{row[f'cpu_ratio_K{k}']:.2f} gain {row[f'gain_K{k}']:.2f}" for k in ks), flush=True)
            out.append(row)
    return out


def _bin_levels(r, levels: np.ndarray) -> np.ndarray:
    """What a bake does with a traced batch (``DirectionStatistics.add``): weight and weight x L
    per 2 degree bin at every absorption level; returns p at zero absorption per steradian."""
    from usdfiber.bake.binning import DEFAULT_GRID
    from usdfiber.bake.statistics import level_histograms

    g = DEFAULT_GRID
    h, _ = level_histograms(r, g, levels)
    return (h[0] / max(r.n_hit, 1)).reshape(g.n_theta_o, g.n_phi_o) / solid_angles()


def expected_part(args, rec) -> list[dict]:
    from usdfiber.bake import tracer
    from usdfiber.bake.absorption import DEFAULT_LEVELS
    from usdfiber.bake.binning import DEFAULT_GRID

    dirs = [tuple(float(x) for x in d.split(",")) for d in args.directions.split(";") if d]
    ks = [int(k) for k in args.expected.split(",")]
    w = solid_angles()
    N, M = 1 << args.expected_photons_log2, (1 << args.expected_photons_log2) * args.ref_factor
    out = []
    for name in args.expected_fibers.split(","):
        case = fiber_case(name)
        fs = tracer.prepare(case["profile"], case["cuticle"])
        # The baker's levels: optical depths across the circumscribed diameter (1 um here).
        levels = np.asarray(DEFAULT_LEVELS, dtype=np.float64) / float(case["profile"].circumscribed_diameter)
        hist = tracer.ExitHistogram.for_grid(DEFAULT_GRID, levels)
        kw = dict(eta=case["eta"], beta_deg=case["beta_deg"], cuticle=case["cuticle"], max_bounces=4096)

        def run(k, th, ph, n, seed):
            return tracer.trace(fs, th, ph, n, seed=seed, expected=k, histogram=hist if k else None, **kw)

        for k in [0] + ks:                           # compile every kernel before timing
            run(k, 0.3, 0.2, 4096, 1)
        for j, (th, ph) in enumerate(dirs):
            t_i, p_i = math.radians(th), math.radians(ph)
            ref, e_ref2 = _plain_reference(lambda n, sd: run(0, t_i, p_i, n, sd), 50_000 + 10 * j, M, w)
            runs: dict[int, list] = {k: [] for k in [0] + ks}
            for rep_ in range(args.repeats):
                for k in runs:
                    t0, c0 = time.perf_counter(), time.process_time()
                    r = run(k, t_i, p_i, N, 60_000 + 100 * j + 10 * rep_ + k)
                    c1 = time.process_time()
                    p = _bin_levels(r, levels)
                    dt, dc, db = time.perf_counter() - t0, c1 - c0, time.process_time() - c1
                    d = rel_l2(p, ref, w)
                    dep = float(r.histogram[0, 0].sum()) if r.histogram is not None else 0.0
                    runs[k].append({"seconds": dt, "cpu_trace": dc, "cpu_bin": db, "cpu": dc + db, "d": d,
                                    "e2": d * d - e_ref2, "ev_fraction": dep / max(dep + float(r.exit_weights().sum()), 1e-300)})
            row = _row(name, th, ph, N, M, e_ref2)
            for k, rs in runs.items():
                row[f"K{k}"] = {c: float(np.median([x[c] for x in rs])) for c in ("seconds", "cpu", "cpu_trace", "cpu_bin")}
                row[f"K{k}"].update({"e": math.sqrt(max(float(np.mean([x["e2"] for x in rs])), 0.0)),
                                     "ev_fraction": float(np.mean([x["ev_fraction"] for x in rs])), "runs": rs})
            a = row["K0"]
            _ratios_to_plain(row, ks)
            for k in ks:
                row[f"trace_ratio_K{k}"] = row[f"K{k}"]["cpu_trace"] / a["cpu_trace"]
            print(f"{name:10s} theta {th:4.0f} phi {ph:4.0f}: plain {fmt_pct(a['e'])} {a['cpu_trace']:.2f}+"
                  f"{a['cpu_bin']:.2f} s cpu; "
                  + "; ".join(f"K={k} {fmt_pct(row[f'K{k}']['e'])} var x{row[f'var_ratio_K{k}']:.2f} "
                              f"cpu x{row[f'cpu_ratio_K{k}']:.2f} (trace x{row[f'trace_ratio_K{k}']:.2f}) "
                              f"gain {row[f'gain_K{k}']:.2f} ev {row[f'K{k}']['ev_fraction']:.3f}" for k in ks),
                  flush=True)
            out.append(row)
    return out


def _p_table(t) -> np.ndarray:
    """(n_ti, n_pi, n_theta_o, n_phi_o) p at zero absorption, per steradian."""
    g = t.grid
    out = np.zeros((g.n_theta_i, g.n_phi_i, g.n_theta_o, g.n_phi_o))
    for ti in range(g.n_theta_i):
        for pi in range(g.n_phi_i):
            b0 = int(t.band_start[ti, pi])
            out[ti, pi, b0:b0 + t.n_band] = t.arrays["p"][ti, pi, 0].astype(np.float64) * float(t.arrays["p_scale"][ti, pi, 0])
    return out


def table_part(args, rec) -> list[dict]:
    from usdfiber.bake.baker import bake_table
    from usdfiber.bake.grid import Grid
    from usdfiber.bake.settings import BakeSettings

    out = []
    n = args.table_photons
    for name in args.table_fibers.split(","):
        case = fiber_case(name)
        res = TABLE_CASES.get(name, 30.0)

        def bake(photons, seed, est, batches=4):
            st = BakeSettings(resolution_deg=res, photons=photons, batches=batches, seed=seed, incoming="box",
                              estimator=est)
            t0 = time.perf_counter()
            t = bake_table(case["profile"], case["eta"], case["beta_deg"], case["cuticle"], st)
            return t, time.perf_counter() - t0

        bake(1024, 99, ())                                 # compile
        # Reference: two independent plain bakes of half the photons each, with 64 batches (so
        # 64 stratified points of each incoming bin); half their distance is the noise of their
        # mean. (A box table's own rel_error counts the variation of p over the incoming bin
        # between its batches as noise, so it overstates the error: not used here.)
        halves = [_p_table(bake(n * args.ref_factor // 2, s, (), batches=64)[0]) for s in (1, 2)]
        ref = 0.5 * (halves[0] + halves[1])
        g = Grid(res, theta_symmetric=case["cuticle"] is None, phi_invariant=ref.shape[1] == 1)
        w = g.bin_solid_angles()
        den = (w * ref ** 2).sum(axis=(-2, -1))
        e_ref = np.sqrt((w * (halves[0] - halves[1]) ** 2).sum(axis=(-2, -1)) / den / 4.0)
        errs: dict[str, list] = {"plain": [], "reciprocity": []}
        secs: dict[str, list] = {"plain": [], "reciprocity": []}
        for k in range(args.repeats):
            for label, est in (("plain", ()), ("reciprocity", ("reciprocity",))):
                t, dt = bake(n, 100 + 2 * k + (label != "plain"), est)
                p = _p_table(t)
                d2 = (w * (p - ref) ** 2).sum(axis=(-2, -1)) / den
                errs[label].append(d2 - e_ref ** 2)
                secs[label].append(dt)
        e = {k: np.sqrt(np.maximum(np.mean(v, axis=0), 0.0)) for k, v in errs.items()}
        t_med = {k: float(np.median(v)) for k, v in secs.items()}
        d2 = {k: np.mean(v, axis=0) + e_ref ** 2 for k, v in errs.items()}
        with np.errstate(divide="ignore", invalid="ignore"):
            gain_dir = (t_med["plain"] * e["plain"] ** 2) / (t_med["reciprocity"] * e["reciprocity"] ** 2)
        # Raw distances (reference noise included on both sides): a lower bound of a gain > 1.
        gain_raw = (t_med["plain"] * d2["plain"]) / (t_med["reciprocity"] * d2["reciprocity"])
        row = {"fiber": name, "resolution_deg": res, "directions": int(g.n_theta_i * g.n_phi_i),
               "photons_per_direction": n, "ref_photons_per_direction": n * args.ref_factor,
               "seconds": t_med, "e_plain": e["plain"].tolist(), "e_reciprocity": e["reciprocity"].tolist(),
               "e_ref": e_ref.tolist(), "gain_per_direction": gain_dir.tolist(),
               "gain_raw_per_direction": gain_raw.tolist(),
               "gain_worst": float(gain_raw.min()), "gain_median": float(np.median(gain_raw)),
               "gain_corrected_median": float(np.nanmedian(gain_dir)),
               "rms_plain": float(np.sqrt(np.mean(e["plain"] ** 2))),
               "rms_reciprocity": float(np.sqrt(np.mean(e["reciprocity"] ** 2))),
               "rms_ref": float(np.sqrt(np.mean(e_ref ** 2)))}
        # Over the whole table (noise-corrected sums): the gain of the table's rms error.
        row["gain_rms"] = (t_med["plain"] * row["rms_plain"] ** 2) / (t_med["reciprocity"] * row["rms_reciprocity"] ** 2)
        print(f"{name:10s} {res:g} deg: plain rms {fmt_pct(row['rms_plain'])} {t_med['plain']:.1f} s, "
              f"reciprocity {fmt_pct(row['rms_reciprocity'])} {t_med['reciprocity']:.1f} s, "
              f"(reference {fmt_pct(row['rms_ref'])}), gain of the rms {row['gain_rms']:.2f}, raw-distance gain "
              f"worst {row['gain_worst']:.2f} median {row['gain_median']:.2f}", flush=True)
        out.append(row)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fibers", default="polyester,silk,cotton")
    ap.add_argument("--directions", default=DEFAULT_DIRECTIONS, help="'theta,phi;...' in degrees")
    ap.add_argument("--photons-log2", type=int, default=18)
    ap.add_argument("--ref-factor", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--table-fibers", default="polyester,silk,cotton")
    ap.add_argument("--table-photons", type=int, default=16384)
    ap.add_argument("--parts", default="direction,table", help="some of direction, split, expected, table")
    ap.add_argument("--split-fibers", default="polyester,silk,cotton")
    ap.add_argument("--splits", default="4,8", help="walks per split to measure")
    ap.add_argument("--split-photons-log2", type=int, default=16)
    ap.add_argument("--expected-fibers", default="polyester,silk,cotton,circle-smooth")
    ap.add_argument("--expected", default="2,4,8", help="normals per event to measure")
    ap.add_argument("--expected-photons-log2", type=int, default=16)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    if args.quick:
        args.photons_log2, args.repeats, args.table_photons = 14, 1, 1024
        args.directions = "40,25;75,65"
        args.split_photons_log2, args.splits, args.split_fibers = 12, "4", "polyester"
        args.expected_photons_log2, args.expected, args.expected_fibers = 12, "4", "polyester"
    rec = Record("estimators", args)
    results = {}
    if "direction" in args.parts:
        rows = direction_part(args, rec)
        results["direction"] = rows
        table = [[r["fiber"], f"{r['theta_i']:g}, {r['phi_i']:g}", fmt_pct(r["independent"]["e"]),
                  f"{r['independent']['seconds']:.2f}", fmt_pct(r["sobol"]["e"]), f"{r['sobol']['seconds']:.2f}",
                  fmt_pct(r["e_ref"]), f"{r['gain']:.2f}", f"{r['gain_raw']:.2f}"] for r in rows]
        print(md_table(["fiber", "theta_i, phi_i", "plain e", "plain s", "stratified e", "stratified s",
                        "ref noise", "gain", "gain (raw d)"], table))
    if "split" in args.parts:
        rows = split_part(args, rec)
        results["split"] = rows
        ks = [int(k) for k in args.splits.split(",")]
        print(md_table(["fiber", "theta_i, phi_i", "plain e", "plain cpu s"]
                       + [f"K={k} {c}" for k in ks for c in ("e", "var ratio", "cpu ratio", "gain")],
                       [[r["fiber"], f"{r['theta_i']:g}, {r['phi_i']:g}", fmt_pct(r["K0"]["e"]), f"{r['K0']['cpu']:.2f}"]
                        + [x for k in ks for x in (fmt_pct(r[f"K{k}"]["e"]), f"{r[f'var_ratio_K{k}']:.2f}",
                                                   f"{r[f'cpu_ratio_K{k}']:.2f}", f"{r[f'gain_K{k}']:.2f}")]
                        for r in rows]))
    if "expected" in args.parts:
        rows = expected_part(args, rec)
        results["expected"] = rows
        ks = [int(k) for k in args.expected.split(",")]
        print(md_table(["fiber", "theta_i, phi_i", "plain e", "plain cpu s (trace + bins)"]
                       + [f"K={k} {c}" for k in ks for c in ("e", "var ratio", "cpu ratio", "trace ratio", "gain")],
                       [[r["fiber"], f"{r['theta_i']:g}, {r['phi_i']:g}", fmt_pct(r["K0"]["e"]),
                         f"{r['K0']['cpu_trace']:.2f} + {r['K0']['cpu_bin']:.2f}"]
                        + [x for k in ks for x in (fmt_pct(r[f"K{k}"]["e"]), f"{r[f'var_ratio_K{k}']:.2f}",
                                                   f"{r[f'cpu_ratio_K{k}']:.2f}", f"{r[f'trace_ratio_K{k}']:.2f}",
                                                   f"{r[f'gain_K{k}']:.2f}")]
                        for r in rows]))
    if "table" in args.parts:
        results["table"] = table_part(args, rec)
    rec.doc["results"] = results
    rec.finish(RESULTS / ("estimators_quick.json" if args.quick else "estimators.json") if args.out is None
               else __import__("pathlib").Path(args.out))


if __name__ == "__main__":
    main()
