"""Benchmark: what one normal of the expected-value estimator costs, part by part.

Three parts, each timed side by side in one process (best of 4 calls after a warm-up):

* ``deposits``: histogramming 22 float64 values per lane (weight and weight x L at 11
  absorption levels) into 4 directions' 2 deg bin-major histograms, 8 normals per lane, as
  single atomic adds, as packets of 8, and either way into a private copy per thread (Dr.Jit's
  ``ReduceMode.Expand``); every variant's sums against a float64 numpy reference.
* ``samplers``: a Beckmann visible normal (Mitsuba's sampler) against a normal from D(m)
  cos(theta_m) with its visibility weight, and other per-normal work (a Smith G1 like the
  escape probability's, the bin's arcsine, Fresnel, a frame), in ns per lane on all cores.
* ``variance``: one direction's expected value with visible normals and with normals from the
  distribution (``expected_sampler``) at the same K: CPU seconds, and the relative L2 spread of
  8 independent batches on the 2 deg bins at absorption 0.05/um (the same walks: only the
  normals differ).

    python bench/expected_normal_costs.py --out bench/results/expected_normal_costs.json
    python bench/expected_normal_costs.py --parts variance --cases silk:40:25,silk:75:115,cotton:40:25 --normals 32
"""
from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bake_common import Record, bench_parser  # noqa: E402

BETA = {"polyester": 3.1, "silk": 6.5, "cotton": 15.5, "mercerizedCotton": 7.0}


def _best(f, repeats: int = 4) -> float:
    import drjit as dr

    best = math.inf
    for _ in range(repeats):
        t = time.perf_counter()
        r = f()
        dr.eval(r)
        dr.sync_thread()
        best = min(best, time.perf_counter() - t)
    return best


def deposits(lanes: int) -> dict:
    import drjit as dr
    from drjit.llvm import ArrayXf64, Bool, Float, Float64, UInt32

    nbin, hn, stride = 90 * 180, 4, 24
    rng = np.random.default_rng(1)
    b = np.clip(rng.normal(8000, 800, lanes).astype(np.int64), 0, nbin - 1).astype(np.uint32)
    hb = rng.integers(0, hn, lanes).astype(np.uint32)
    w, L = rng.random(lanes).astype(np.float32), rng.random(lanes).astype(np.float32)
    keep = rng.random(lanes) < 0.7
    ref = np.zeros(hn * nbin * stride)
    for j in range(8):
        idx = (hb.astype(np.int64) * nbin + b + (j * 37) % 5)[keep]
        for k in range(11):
            wk = (w.astype(np.float64) * np.exp(-(0.1 * k + 0.01 * j) * L.astype(np.float64)))[keep]
            ref += np.bincount(idx * stride + 2 * k, weights=wk, minlength=ref.size)
            ref += np.bincount(idx * stride + 2 * k + 1, weights=wk * L[keep], minlength=ref.size)

    def run(packet: bool, mode) -> tuple[float, float]:
        bb, hbb, ww, LL, mk = UInt32(b), UInt32(hb), Float(w), Float(L), Bool(keep)
        dr.eval(bb, hbb, ww, LL, mk)

        def once():
            hist = dr.zeros(Float64, hn * nbin * stride)
            dr.make_opaque(hist)
            base = hbb * nbin + bb
            for j in range(8):
                bj = base + UInt32((j * 37) % 5)
                vals = []
                for k in range(11):
                    wk = ww * dr.exp(-(0.1 * k + 0.01 * j) * LL)
                    vals += [Float64(wk), Float64(wk * LL)]
                vals += [Float64(0.0)] * 2
                if packet:
                    for q in range(3):
                        dr.scatter_reduce(dr.ReduceOp.Add, hist, ArrayXf64(vals[8 * q:8 * q + 8]), bj * 3 + q, mk,
                                          mode=mode)
                else:
                    for i, v in enumerate(vals[:22]):
                        dr.scatter_reduce(dr.ReduceOp.Add, hist, v, bj * stride + i, mk, mode=mode)
            return hist

        seconds = _best(once)
        err = float(np.abs(once().numpy() - ref).max() / ref.max())
        return seconds, err

    out = {}
    for name, packet, mode in (("atomic", False, dr.ReduceMode.Direct), ("packets", True, dr.ReduceMode.Direct),
                               ("copies", False, dr.ReduceMode.Expand),
                               ("packets+copies", True, dr.ReduceMode.Expand)):
        s, e = run(packet, mode)
        out[name] = {"seconds": s, "max_rel_error_vs_numpy": e}
        print(f"deposits {name:15s} {s:.3f} s  (error {e:.1e})", flush=True)
    return {"lanes": lanes, "normals": 8, "values": 22, **out}


def samplers(lanes: int) -> dict:
    from usdfiber.backend import mitsuba

    mi = mitsuba()
    import drjit as dr

    F, V3 = mi.Float, mi.Vector3f
    rng = np.random.default_rng(0)
    alpha = math.tan(math.radians(BETA["silk"]))
    distr = mi.MicrofacetDistribution(mi.MicrofacetType.Beckmann, alpha, True)
    wz, ph = rng.uniform(0.05, 1.0, lanes), rng.uniform(0.0, 2 * math.pi, lanes)
    wi = V3(F(np.sqrt(1 - wz ** 2) * np.cos(ph)), F(np.sqrt(1 - wz ** 2) * np.sin(ph)), F(wz))
    u1, u2 = F(rng.random(lanes)), F(rng.random(lanes))
    dr.eval(wi, u1, u2)

    def ndf():
        cos_m = dr.rsqrt(dr.fma(-alpha * alpha, dr.log(1.0 - u1), 1.0))
        sin_m = dr.sqrt(dr.maximum(dr.fma(-cos_m, cos_m, 1.0), 0.0))
        s, c = dr.sincos((2.0 * math.pi) * u2)
        m = V3(sin_m * c, sin_m * s, cos_m)
        return m * (dr.maximum(dr.dot(wi, m), 0.0) / cos_m)

    parts = {"visible normal (Mitsuba)": lambda: distr.sample(wi, mi.Point2f(u1, u2))[0],
             "normal from D cos + weight": ndf,
             "Smith G1 (Mitsuba; the escape probability's kind)":
                 lambda: distr.smith_g1(wi, dr.normalize(V3(u1 - 0.5, u2 - 0.5, 2.0))),
             "bin arcsine (float64)": lambda: dr.asin(dr.clip(mi.Float64(wi.z), -1.0, 1.0)),
             "Fresnel": lambda: mi.fresnel(dr.abs(wi.z), 1.55)[0],
             "frame to world": lambda: mi.Frame3f(dr.normalize(V3(u1, u2, 1.0))).to_world(wi),
             "a multiply-add (floor)": lambda: wi.x * u1 + u2}
    out = {}
    for name, f in parts.items():
        s = _best(f)
        out[name] = s / lanes * 1e9
        print(f"samplers {name:50s} {out[name]:.2f} ns per lane", flush=True)
    return {"lanes": lanes, "ns_per_lane": out}


def variance(cases: list[str], photons: int, normals: int) -> list[dict]:
    from usdfiber.bake.binning import bin_direct
    from usdfiber.bake.grid import Grid
    from usdfiber.bake.profiles import builtin_profiles_um
    from usdfiber.bake.tracer import ExitHistogram, prepare, trace_many

    grid, sigma, seeds = Grid(2.0), 0.05, list(range(100, 108))
    hist = ExitHistogram.for_grid(grid, [0.0, sigma])
    rows = []
    for case in cases:
        fiber, th, ph = case.split(":")
        fs = prepare(builtin_profiles_um(fiber, 1)[0])
        d = (math.radians(float(th)), math.radians(float(ph)))
        kw = dict(eta=1.55, beta_deg=BETA[fiber], expected=normals, histogram=hist)
        res = {}
        for sampler in ("visible", "ndf"):
            trace_many(fs, [d] * 2, 5000, seed=[1, 2], expected_sampler=sampler, **kw)     # compile
        for sampler in ("visible", "ndf") * 3:                                        # alternating
            c = time.process_time()
            r = trace_many(fs, [d] * len(seeds), photons, seed=seeds, expected_sampler=sampler, **kw)
            cpu = time.process_time() - c
            dens = np.array([bin_direct(x, sigma, grid).ravel() for x in r])
            spread = math.sqrt(dens.var(axis=0, ddof=1).sum() / (dens.mean(axis=0) ** 2).sum())
            res.setdefault(sampler, []).append((cpu, spread))
        row = {"case": case, "photons": photons, "batches": len(seeds), "normals": normals,
               **{s: {"cpu": float(np.median([x[0] for x in v])), "rel_spread": v[0][1]} for s, v in res.items()}}
        vis, ndf_ = row["visible"], row["ndf"]
        row["variance_ratio"] = (ndf_["rel_spread"] / vis["rel_spread"]) ** 2
        row["cpu_ratio"] = ndf_["cpu"] / vis["cpu"]
        row["gain"] = 1.0 / (row["variance_ratio"] * row["cpu_ratio"])
        print(f"variance {case}: visible {vis['cpu']:.2f} s at {100 * vis['rel_spread']:.2f} %, ndf "
              f"{ndf_['cpu']:.2f} s at {100 * ndf_['rel_spread']:.2f} %: variance x{row['variance_ratio']:.2f}, "
              f"cpu x{row['cpu_ratio']:.2f}, gain {row['gain']:.2f}", flush=True)
        rows.append(row)
    return rows


def main() -> None:
    ap = bench_parser(__doc__, "smaller sizes")
    ap.add_argument("--parts", default="deposits,samplers,variance")
    ap.add_argument("--cases", default="silk:40:25,silk:75:115,cotton:40:25",
                    help="FIBER:THETA_I:PHI_I (degrees) of the variance part, comma separated")
    ap.add_argument("--normals", type=int, default=32, help="K of the variance part")
    args = ap.parse_args()
    rec = Record("expected_normal_costs", args)
    parts = args.parts.split(",")
    lanes = 1 << (18 if args.quick else 21)
    results: dict = {}
    if "deposits" in parts:
        results["deposits"] = deposits(lanes)
    if "samplers" in parts:
        results["samplers"] = samplers(2 * lanes)
    if "variance" in parts:
        results["variance"] = variance(args.cases.split(","), 20_000 if args.quick else 200_000, args.normals)
    rec.doc["results"] = results
    rec.finish(args.out or Path("bench/results/expected_normal_costs.json"))


if __name__ == "__main__":
    main()
