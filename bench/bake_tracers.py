"""Benchmark: the fast tracer against the float64 reference tracer, photons/s and error vs photons.

    python bench/bake_tracers.py [--directions 35,25] [--fast-counts 16:22] [--cases ...] [--quick]

Writes ``bench/results/tracers.json`` (``--out`` names another file); what it records and
the error metrics: :mod:`bake_common`.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import warnings
from typing import Any

import numpy as np

from bench_common import Timer, md_table
from bake_common import (
    CASES, DEG, MAX_BOUNCES, N_PH, N_TH, Record, STEP, bench_parser, fiber_case, fmt_pct, fmt_time,
    parse_counts, rel_l2, results_path, solid_angles)


FAST_CHUNK = 1 << 21                        # photons per fast-tracer call (its own batch size)


def parse_directions(text: str) -> list[tuple[float, float]]:
    out = []
    for part in text.split(";"):
        if part.strip():
            t, p = (float(x) for x in part.split(","))
            out.append((t, p))
    return out


class Hist:
    """2D (theta_o, phi_o) and azimuthal-marginal (phi_o - phi_i) counts, 2 degree bins."""

    def __init__(self, phi_i: float):
        self.phi_i = phi_i
        self.h2 = np.zeros(N_TH * N_PH)
        self.hm = np.zeros(N_PH)
        self.norm = 0.0          # photons that met the fiber
        self.escaped = 0

    def add(self, dirs: np.ndarray, norm: float) -> None:
        d = np.asarray(dirs, dtype=np.float64)
        th = np.arcsin(np.clip(d[:, 2], -1.0, 1.0))
        ph = np.mod(np.arctan2(d[:, 1], d[:, 0]), 2 * np.pi)
        it = np.clip(np.floor((th + 0.5 * np.pi) / STEP).astype(np.int64), 0, N_TH - 1)
        ip = np.floor(ph / STEP).astype(np.int64) % N_PH
        self.h2 += np.bincount(it * N_PH + ip, minlength=N_TH * N_PH)
        im = np.floor(np.mod(ph - self.phi_i, 2 * np.pi) / STEP).astype(np.int64) % N_PH
        self.hm += np.bincount(im, minlength=N_PH)
        self.norm += float(norm)
        self.escaped += len(d)

    def merge(self, other: "Hist") -> None:
        self.h2 += other.h2
        self.hm += other.hm
        self.norm += other.norm
        self.escaped += other.escaped

    def p2(self) -> np.ndarray:
        return self.h2.reshape(N_TH, N_PH) / max(self.norm, 1.0) / solid_angles()

    def marg(self) -> np.ndarray:
        return self.hm / max(self.norm, 1.0) / STEP

    @property
    def albedo(self) -> float:
        return self.escaped / max(self.norm, 1.0)


def rel_l1(p: np.ndarray, q: np.ndarray, w: np.ndarray | float = 1.0) -> float:
    den = float(np.sum(w * np.abs(q)))
    return float(np.sum(w * np.abs(p - q))) / den if den > 0 else float("inf")


def fit_sqrt(ns: list[int], errs: list[float]) -> dict[str, float]:
    """e = c / sqrt(N) fitted in log space (slope fixed), and the free slope as a check."""
    n = np.asarray(ns, dtype=np.float64)
    e = np.asarray(errs, dtype=np.float64)
    ok = np.isfinite(e) & (e > 0)
    if ok.sum() == 0:
        return {"c": float("nan"), "slope": float("nan")}
    c = float(np.exp(np.mean(np.log(e[ok]) + 0.5 * np.log(n[ok]))))
    slope = float(np.polyfit(np.log(n[ok]), np.log(e[ok]), 1)[0]) if ok.sum() >= 2 else float("nan")
    return {"c": c, "slope": slope}


class FastRunner:
    """usdfiber.bake.tracer (Dr.Jit / Mitsuba). Each new seed value compiles a kernel once; the
    first call of a seed is a warm-up (untimed, 1024 photons), so timed calls are warm."""

    name = "fast"

    def __init__(self, case: dict[str, Any]):
        from usdfiber.bake import tracer

        self.tracer = tracer
        self.case = case
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            with Timer() as t:
                self.fs = tracer.prepare(case["profile"], case["cuticle"])
        self.prepare_seconds = t.wall
        # A seed value never used before: its kernel is compiled now (not in Dr.Jit's disk cache).
        cold = int.from_bytes(os.urandom(6), "little") + (1 << 50)
        with Timer() as t:
            tracer.trace(self.fs, 0.3, 0.2, 1024, eta=case["eta"], beta_deg=case["beta_deg"],
                         max_bounces=MAX_BOUNCES, seed=cold, cuticle=case["cuticle"])
        self.cold_compile_seconds = t.wall
        self.warm: set[int] = set()
        self.warmup_seconds = 0.0
        self.first_call_seconds: float | None = None
        self.leaks = 0
        self.cut = 0

    def _call(self, th: float, ph: float, n: int, seed: int):
        c = self.case
        return self.tracer.trace(self.fs, th, ph, n, eta=c["eta"], beta_deg=c["beta_deg"],
                                 max_bounces=MAX_BOUNCES, seed=seed, cuticle=c["cuticle"], batch=FAST_CHUNK)

    def _warm(self, th: float, ph: float, seed: int) -> None:
        if seed in self.warm:
            return
        with Timer() as t:
            self._call(th, ph, 1024, seed)
        if self.first_call_seconds is None:
            self.first_call_seconds = t.wall
        self.warmup_seconds += t.wall
        self.warm.add(seed)

    def run(self, th: float, ph: float, n: int, seed: int, hist: Hist) -> tuple[float, float]:
        """Trace n photons (chunks of FAST_CHUNK, seeds seed, seed+1, ...); (wall, cpu) seconds."""
        wall = cpu = 0.0
        for j, first in enumerate(range(0, n, FAST_CHUNK)):
            m = min(FAST_CHUNK, n - first)
            s = seed + j
            self._warm(th, ph, s)
            with Timer() as t:
                r = self._call(th, ph, m, s)
            wall += t.wall
            cpu += t.cpu
            alive = ~np.asarray(r.cut, dtype=bool)
            hist.add(r.directions[alive], r.n_hit)
            self.leaks += int(r.extra.get("leaks", 0))
            self.cut += int(r.n_cut)
        return wall, cpu


class RefRunner:
    """usdfiber.bake.reference_tracer (float64 numpy, 2 worker threads by default)."""

    name = "reference"
    CHUNK = 1 << 20

    def __init__(self, case: dict[str, Any]):
        from usdfiber.bake import reference_tracer

        self.rt = reference_tracer
        self.case = case
        self.prepare_seconds = 0.0
        self.warmup_seconds = 0.0
        self.first_call_seconds: float | None = None
        self.leaks = 0
        self.cut = 0

    def run(self, th: float, ph: float, n: int, seed: int, hist: Hist) -> tuple[float, float]:
        c = self.case
        if self.first_call_seconds is None:
            with Timer() as t:
                self.rt.trace(c["profile"], th, ph, eta=c["eta"], beta=c["beta_deg"] * DEG, n_photons=1024,
                              seed=10**6, max_bounces=MAX_BOUNCES)
            self.first_call_seconds = self.warmup_seconds = t.wall
        wall = cpu = 0.0
        for j, first in enumerate(range(0, n, self.CHUNK)):
            m = min(self.CHUNK, n - first)
            with Timer() as t:
                r = self.rt.trace(c["profile"], th, ph, eta=c["eta"], beta=c["beta_deg"] * DEG, n_photons=m,
                                  seed=seed + j, max_bounces=MAX_BOUNCES)
            wall += t.wall
            cpu += t.cpu
            hist.add(r.direction[r.escaped], r.n_photons)
            self.leaks += int(r.n_lost)
            self.cut += int(r.n_cut)
        return wall, cpu


def bench_tracer(runner, th: float, ph: float, counts: list[int], ref_photons: int,
                 exact_marg: np.ndarray | None) -> dict[str, Any]:
    # High-photon reference of the same tracer (independent seeds).
    ref = Hist(ph)
    w_ref, c_ref = runner.run(th, ph, ref_photons, 50_000, ref)
    p_ref, m_ref = ref.p2(), ref.marg()
    dom = solid_angles()
    out: dict[str, Any] = {
        "tracer": runner.name,
        "prepare_seconds": round(runner.prepare_seconds, 3),
        "reference_run": {"photons": ref_photons, "seconds": round(w_ref, 3),
                          "photons_per_s": ref_photons / w_ref, "cores_used": round(c_ref / w_ref, 2),
                          "albedo": ref.albedo},
    }
    if exact_marg is not None:
        out["reference_run"]["marg_l2_vs_exact"] = rel_l2(m_ref, exact_marg)
        out["reference_run"]["marg_l1_vs_exact"] = rel_l1(m_ref, exact_marg)
    ladder = []
    for j, n in enumerate(counts):
        h = Hist(ph)
        wall, cpu = runner.run(th, ph, n, 1000 + 64 * j, h)
        corr = math.sqrt(ref_photons / (ref_photons + n))
        row = {
            "photons": n, "seconds": wall, "photons_per_s": n / wall, "cores_used": cpu / wall,
            "l2_2d_raw": rel_l2(h.p2(), p_ref, dom), "l2_2d": rel_l2(h.p2(), p_ref, dom) * corr,
            "l2_marg_raw": rel_l2(h.marg(), m_ref), "l2_marg": rel_l2(h.marg(), m_ref) * corr,
            "l1_marg_raw": rel_l1(h.marg(), m_ref),
        }
        if exact_marg is not None:
            row["l2_marg_exact"] = rel_l2(h.marg(), exact_marg)
            row["l1_marg_exact"] = rel_l1(h.marg(), exact_marg)
        ladder.append(row)
    out["ladder"] = ladder
    out["warmup_seconds_total"] = round(runner.warmup_seconds, 3)
    out["first_call_seconds"] = None if runner.first_call_seconds is None else round(runner.first_call_seconds, 3)
    if hasattr(runner, "cold_compile_seconds"):
        out["cold_compile_seconds"] = round(runner.cold_compile_seconds, 3)
    out["lost_or_leaked_photons"] = runner.leaks
    out["cut_photons"] = runner.cut
    ns = [r["photons"] for r in ladder]
    fits = {"l2_2d": fit_sqrt(ns, [r["l2_2d"] for r in ladder]),
            "l2_marg": fit_sqrt(ns, [r["l2_marg"] for r in ladder])}
    if exact_marg is not None:
        fits["l2_marg_exact"] = fit_sqrt(ns, [r["l2_marg_exact"] for r in ladder])
    rate = out["reference_run"]["photons_per_s"]           # steady state: the longest run
    for f in fits.values():
        f["photons_for_1pct"] = (f["c"] / 0.01) ** 2
        f["seconds_for_1pct"] = f["photons_for_1pct"] / rate
        f["error_after_1s"] = f["c"] / math.sqrt(rate * 1.0)
        f["error_after_60s"] = f["c"] / math.sqrt(rate * 60.0)
    out["fit"] = fits
    out["_hist"] = ref
    return out


def cmd_tracers(args: argparse.Namespace) -> int:
    from usdfiber.bake import exact

    rec = Record("tracers", args)
    fast_counts = parse_counts(args.fast_counts)
    ref_counts = parse_counts(args.ref_counts)
    fast_ref, ref_ref = 1 << args.fast_ref, 1 << args.ref_ref
    if args.quick:
        fast_counts, ref_counts, fast_ref, ref_ref = [1 << 12, 1 << 13], [1 << 10, 1 << 11], 1 << 15, 1 << 13
    rec.doc["settings"].update({"fast_counts_resolved": fast_counts, "ref_counts_resolved": ref_counts,
                                "fast_reference_photons": fast_ref, "ref_reference_photons": ref_ref,
                                "max_bounces": MAX_BOUNCES, "bins_deg": 2})
    results = []
    for (td, pd) in parse_directions(args.directions):
        th, ph = td * DEG, pd * DEG
        for name in args.cases.split(","):
            case = fiber_case(name)
            ex = None
            if case["exact"]:
                ex = exact.azimuthal_distribution(th, case["eta"], n_bins=N_PH)
            entry: dict[str, Any] = {"case": name, "preset": case["preset"], "theta_i_deg": td, "phi_i_deg": pd,
                                     "eta": case["eta"], "beta_deg": case["beta_deg"], "cuticle": case["cuticle"],
                                     "profile": case["profile"].name}
            print(f"[{name} theta_i={td:g} phi_i={pd:g}] fast ...", flush=True)
            entry["fast"] = bench_tracer(FastRunner(case), th, ph, fast_counts, fast_ref, ex)
            if case["cuticle"] is None and not args.fast_only:
                print(f"[{name} theta_i={td:g} phi_i={pd:g}] reference ...", flush=True)
                entry["reference"] = bench_tracer(RefRunner(case), th, ph, ref_counts, ref_ref, ex)
                f, r = entry["fast"], entry["reference"]
                hf, hr = f.pop("_hist"), r.pop("_hist")
                cmp = {}
                for key, a, b, w in (("2d", hf.p2(), hr.p2(), solid_angles()), ("marg", hf.marg(), hr.marg(), 1.0)):
                    d = rel_l2(a, b, w)
                    # noise of the difference of two independent estimates
                    noise = math.sqrt(f["fit"][f"l2_{key}"]["c"] ** 2 / fast_ref + r["fit"][f"l2_{key}"]["c"] ** 2 / ref_ref)
                    cmp[f"l2_{key}"] = d
                    cmp[f"l2_{key}_expected_from_noise"] = noise
                    cmp[f"l2_{key}_ratio"] = d / noise if noise > 0 else float("inf")
                cmp["l1_marg"] = rel_l1(hf.marg(), hr.marg())
                cmp["albedo_fast"] = hf.albedo
                cmp["albedo_reference"] = hr.albedo
                entry["fast_vs_reference"] = cmp
            else:
                entry["fast"].pop("_hist")
            results.append(entry)
            print_tracer_entry(entry)
    rec.doc["results"] = results
    print_tracer_summary(results)
    rec.finish(results_path(args, "tracers"))
    return 0


def print_tracer_entry(e: dict[str, Any]) -> None:
    rows = []
    for key in ("fast", "reference"):
        if key not in e:
            continue
        t = e[key]
        for r in t["ladder"]:
            rows.append([key, r["photons"], f"{r['seconds']:.3f}", f"{r['photons_per_s'] / 1e3:.0f}k",
                         f"{r['cores_used']:.2f}", fmt_pct(r["l2_2d"]), fmt_pct(r["l2_marg"]),
                         fmt_pct(r["l1_marg_raw"]), fmt_pct(r.get("l2_marg_exact")), fmt_pct(r.get("l1_marg_exact"))])
        rr = t["reference_run"]
        rows.append([f"{key} (reference run)", rr["photons"], f"{rr['seconds']:.2f}", f"{rr['photons_per_s'] / 1e3:.0f}k",
                     f"{rr['cores_used']:.2f}", "(ref)", "(ref)", "(ref)", fmt_pct(rr.get("marg_l2_vs_exact")),
                     fmt_pct(rr.get("marg_l1_vs_exact"))])
    print(f"\n### {e['case']} (eta {e['eta']:g}, beta {e['beta_deg']:g} deg"
          f"{', cuticle ' + str(e['cuticle']) if e['cuticle'] else ''}), theta_i {e['theta_i_deg']:g} deg, "
          f"phi_i {e['phi_i_deg']:g} deg\n")
    print(md_table(["tracer", "photons", "s", "photons/s", "cores", "2D L2", "marg L2", "marg L1 (raw)",
                    "marg L2 vs exact", "marg L1 vs exact"], rows))
    f = e["fast"]
    print(f"\nfast tracer: mesh + scene {f['prepare_seconds']:.3f} s; kernel compile of a new seed "
          f"{f.get('cold_compile_seconds', float('nan')):.3f} s; untimed warm-up calls {f['warmup_seconds_total']:.2f} s "
          f"in all; photons lost (leaks) {f['lost_or_leaked_photons']}, cut {f['cut_photons']}")
    if "fast_vs_reference" in e:
        c = e["fast_vs_reference"]
        print(f"\nfast vs reference at the largest counts: 2D L2 {fmt_pct(c['l2_2d'])} (noise alone "
              f"{fmt_pct(c['l2_2d_expected_from_noise'])}, ratio {c['l2_2d_ratio']:.2f}); marginal L2 "
              f"{fmt_pct(c['l2_marg'])} (noise {fmt_pct(c['l2_marg_expected_from_noise'])}, ratio "
              f"{c['l2_marg_ratio']:.2f}); albedo {c['albedo_fast']:.5f} vs {c['albedo_reference']:.5f}", flush=True)


def print_tracer_summary(results: list[dict[str, Any]]) -> None:
    rows = []
    for e in results:
        f = e["fast"]
        r = e.get("reference")
        c = e.get("fast_vs_reference", {})
        rf = f["reference_run"]["photons_per_s"]
        rr = r["reference_run"]["photons_per_s"] if r else None
        rows.append([
            e["case"], f"{e['theta_i_deg']:g},{e['phi_i_deg']:g}",
            f"{rf / 1e3:.0f}k", None if rr is None else f"{rr / 1e3:.1f}k",
            None if rr is None else f"{rf / rr:.1f}x",
            f"{f['fit']['l2_2d']['c']:.0f}", None if r is None else f"{r['fit']['l2_2d']['c']:.0f}",
            f"{f['fit']['l2_2d']['slope']:.2f}", None if r is None else f"{r['fit']['l2_2d']['slope']:.2f}",
            fmt_time(f["fit"]["l2_2d"]["seconds_for_1pct"]),
            None if r is None else fmt_time(r["fit"]["l2_2d"]["seconds_for_1pct"]),
            fmt_time(f["fit"]["l2_marg"]["seconds_for_1pct"]),
            None if r is None else fmt_time(r["fit"]["l2_marg"]["seconds_for_1pct"]),
            None if not c else f"{fmt_pct(c['l2_2d'])} ({c['l2_2d_ratio']:.2f})",
            None if not c else f"{fmt_pct(c['l2_marg'])} ({c['l2_marg_ratio']:.2f})",
        ])
    print("\n### Summary (c: relative L2 = c / sqrt(photons); time for 1% at the steady rate)\n")
    print(md_table(["case", "dir (deg)", "fast ph/s", "ref ph/s", "speed-up", "c 2D fast", "c 2D ref",
                    "slope fast", "slope ref", "1% 2D fast", "1% 2D ref", "1% marg fast", "1% marg ref",
                    "fast-ref 2D (/noise)", "fast-ref marg (/noise)"], rows))
    ex = [e for e in results if "l2_marg_exact" in e["fast"]["fit"]]
    if ex:
        rows = []
        for e in ex:
            for key in ("fast", "reference"):
                if key in e:
                    f = e[key]["fit"]["l2_marg_exact"]
                    rows.append([e["case"], key, f"{f['c']:.2f}", f"{f['slope']:.2f}", fmt_time(f["seconds_for_1pct"]),
                                 fmt_pct(f["error_after_1s"]), fmt_pct(f["error_after_60s"])])
        print("\n### Against the exact smooth-circle far field (azimuthal marginal, 2 deg bins)\n")
        print(md_table(["case", "tracer", "c", "slope", "time to 1%", "error after 1 s", "error after 60 s"], rows))


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser(__doc__, quick_help="tiny counts (smoke test)")
    ap.add_argument("--cases", default=",".join(CASES), help=f"comma list of {', '.join(CASES)}")
    ap.add_argument("--directions", default="35,25",
                    help="theta_i,phi_i in degrees; several separated by ';' (default 35,25: a node of "
                        "both the 2 and 10 deg grids, off every 2 deg bin edge)")
    ap.add_argument("--fast-counts", default="16:22", help="photon ladder of the fast tracer, powers of 2 (a:b or a,b,c)")
    ap.add_argument("--ref-counts", default="14:19", help="photon ladder of the reference tracer")
    ap.add_argument("--fast-ref", type=int, default=24, help="log2 photons of the fast tracer's high-photon run")
    ap.add_argument("--ref-ref", type=int, default=21, help="log2 photons of the reference tracer's high-photon run")
    ap.add_argument("--fast-only", action="store_true")
    return cmd_tracers(ap.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
