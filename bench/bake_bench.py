"""Benchmarks of the BCSDF baker: speed, always next to the error it was reached at.

    python bench/bake_bench.py tracers  [--directions 35,25] [--fast-counts 16:21] ...
    python bench/bake_bench.py recolour [--full-size]
    python bench/bake_bench.py recolour_kernel
    python bench/bake_bench.py tables   [--resolution 15] [--probe-photons 18,21] ...
    python bench/bake_bench.py grouping [--fibers silk,cotton] [--sample 24]
    python bench/bake_bench.py lowrank  [--fiber silk] [--resolution 10] [--photons 800000]

Every sub-command prints markdown tables and writes ``bench/results/<command>.json`` with the
machine (CPU model, cores, RAM, Python, Mitsuba / Dr.Jit versions and variant), the load
average before and after, the git HEAD and the SHA-256 of the baker's sources, the settings,
and every measurement. ``--quick`` shrinks every count (a smoke test, not a benchmark).

Error metrics (all on 2 degree bins, per incoming direction):

* ``2D``: relative L2 error of the exit density p(theta_o, phi_o) over the sphere,
  ``sqrt(sum dOmega (p - p_ref)^2 / sum dOmega p_ref^2)`` (90 x 180 bins, the paper's grid).
* ``marg``: relative L2 (and L1) error of the azimuthal marginal (theta_o integrated) over
  phi_o - phi_i (180 bins), the quantity :func:`usdfiber.bake.exact.azimuthal_distribution`
  gives exactly for a smooth circle.

Against a high-photon reference run of M photons of the same tracer, the measured distance d
of a run of N photons contains the reference's own noise; both are Monte Carlo estimates
(variance proportional to 1/photons), so the error of the N-photon run is
``e = d * sqrt(M / (M + N))`` (reported next to the raw d).
"""
from __future__ import annotations

import argparse
import gc
import json
import math
import os
import shutil
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any, Callable

import numpy as np
import bench_common  # noqa: E402
from bench_common import Timer, json_default as _json_default, md_table, meminfo_gib  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))           # run from a checkout without installing

RESULTS = ROOT / "bench" / "results"
DEG = math.pi / 180.0
STEP = 2.0 * DEG                            # the paper's 2 degree bins
N_TH, N_PH = 90, 180
MAX_BOUNCES = 4096                          # BakeSettings' default, for both tracers
FAST_CHUNK = 1 << 21                        # photons per fast-tracer call (its own batch size)
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
SOURCES = ("usdfiber/bake/tracer.py", "usdfiber/bake/reference_tracer.py", "usdfiber/bake/baker.py",
           "usdfiber/bake/table.py", "usdfiber/bake/fiber_mesh.py", "usdfiber/bake/exact.py",
           "usdfiber/bake/recolour.py")


# ---------------------------------------------------------------------------------------------
# Environment record
# ---------------------------------------------------------------------------------------------

def machine() -> dict[str, Any]:
    import scipy

    return bench_common.machine(scipy=scipy.__version__,
                                ram_available_gib_at_start=round(meminfo_gib("MemAvailable") or 0.0, 1))


def git_state() -> dict[str, Any]:
    return bench_common.git_state(ROOT, SOURCES, ("usdfiber",))


class Record:
    """The JSON document of one run: environment, settings, results."""

    def __init__(self, command: str, args: argparse.Namespace):
        self.t0 = time.perf_counter()
        settings = {k: v for k, v in vars(args).items() if k not in ("func", "out")}
        self.doc: dict[str, Any] = {
            "command": command,
            "argv": [sys.executable.split("/")[-1], *sys.argv],
            "started": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
            "load_average_before": [round(x, 2) for x in os.getloadavg()],
            "machine": machine(),
            "git": git_state(),
            "settings": settings,
        }

    def finish(self, path: Path) -> None:
        g = git_state()
        self.doc["load_average_after"] = [round(x, 2) for x in os.getloadavg()]
        self.doc["wall_seconds"] = round(time.perf_counter() - self.t0, 1)
        changed = [s for s, h in g["sha256_16"].items() if h != self.doc["git"]["sha256_16"].get(s)]
        self.doc["sources_changed_during_run"] = changed
        if changed:
            print(f"WARNING: sources changed during the run: {changed}", file=sys.stderr)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.doc, indent=1, default=_json_default) + "\n")
        la = self.doc["load_average_before"], self.doc["load_average_after"]
        print(f"\nwrote {path.relative_to(ROOT) if path.is_relative_to(ROOT) else path} "
              f"({self.doc['wall_seconds']} s; load average before {la[0]}, after {la[1]})")





def fmt_pct(x: float | None, digits: int = 2) -> str | None:
    return None if x is None or not math.isfinite(x) else f"{100 * x:.{digits}f}%"


def fmt_time(s: float | None) -> str | None:
    if s is None or not math.isfinite(s):
        return None
    if s < 120:
        return f"{s:.3g} s"
    if s < 7200:
        return f"{s / 60:.3g} min"
    return f"{s / 3600:.3g} h"


def parse_counts(text: str) -> list[int]:
    """'16:21' -> 2^16 .. 2^21; '16,18,20' -> those powers of two."""
    if ":" in text:
        a, b = (int(x) for x in text.split(":"))
        return [1 << k for k in range(a, b + 1)]
    return [1 << int(x) for x in text.split(",") if x]


def parse_directions(text: str) -> list[tuple[float, float]]:
    out = []
    for part in text.split(";"):
        if part.strip():
            t, p = (float(x) for x in part.split(","))
            out.append((t, p))
    return out


# ---------------------------------------------------------------------------------------------
# Fibers
# ---------------------------------------------------------------------------------------------

#: Benchmark cases: name -> (preset, beta override, keep the cuticle, exact answer).
CASES: dict[str, tuple[str, float | None, bool, bool]] = {
    "circle-smooth": ("polyester", 0.0, False, True),
    "polyester": ("polyester", None, False, False),
    "silk": ("silk", None, False, False),
    "cotton": ("cotton", None, False, False),
    "mercerizedCotton": ("mercerizedCotton", None, False, False),
    "wool": ("wool", None, False, False),
    "wool-cuticle": ("wool", None, True, False),
}


def fiber_case(name: str) -> dict[str, Any]:
    """Profile (variant 0, circumscribed diameter 1 um, as the baker traces it) and optics."""
    from usdfiber.bake.baker import requests_from_preset

    preset, beta, keep_cut, exact = CASES[name]
    req = requests_from_preset(preset)[0]
    return {
        "name": name, "preset": preset, "profile": req.profile(), "eta": req.eta,
        "beta_deg": req.beta_deg if beta is None else beta,
        "cuticle": req.cuticle if keep_cut else None, "exact": exact,
    }


# ---------------------------------------------------------------------------------------------
# Histograms and errors
# ---------------------------------------------------------------------------------------------

_SOLID = None


def solid_angles() -> np.ndarray:
    global _SOLID
    if _SOLID is None:
        e = np.linspace(-0.5 * np.pi, 0.5 * np.pi, N_TH + 1)
        _SOLID = np.repeat(((np.sin(e[1:]) - np.sin(e[:-1])) * STEP)[:, None], N_PH, axis=1)
    return _SOLID


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


def rel_l2(p: np.ndarray, q: np.ndarray, w: np.ndarray | float = 1.0) -> float:
    den = float(np.sum(w * q * q))
    return math.sqrt(float(np.sum(w * (p - q) ** 2)) / den) if den > 0 else float("inf")


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


# ---------------------------------------------------------------------------------------------
# The two tracers behind one interface
# ---------------------------------------------------------------------------------------------

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


# ---------------------------------------------------------------------------------------------
# tracers
# ---------------------------------------------------------------------------------------------

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
    rec.finish(args.out or RESULTS / ("tracers_quick.json" if args.quick else "tracers.json"))
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


# ---------------------------------------------------------------------------------------------
# Table size model
# ---------------------------------------------------------------------------------------------

def bytes_per_direction(K: int, band: int, n_po: int, storage_bytes: int = 2) -> int:
    """Bytes of one incoming direction in the table layout (see usdfiber.bake.table):
    p and lbar (K x band x n_po each), p_scale / albedo / albedo_lbar (K float32 each),
    band_start (int16), rel_error (float32), photons (int64)."""
    return 2 * K * band * n_po * storage_bytes + 3 * 4 * K + 2 + 4 + 8


def fixed_bytes(K: int, n_width: int = 720) -> int:
    return 8 * K + 4 * n_width


def model_nbytes(n_dir: int, K: int, band: int, n_po: int) -> int:
    return n_dir * bytes_per_direction(K, band, n_po) + fixed_bytes(K)


def table_facts(table, path: Path | None = None) -> dict[str, Any]:
    g = table.grid
    K = len(table.levels)
    n_dir = g.n_theta_i * g.n_phi_i
    out = {
        "resolution_deg": g.resolution_deg, "incoming": [g.n_theta_i, g.n_phi_i], "directions": n_dir,
        "outgoing": [g.n_theta_o, g.n_phi_o], "levels": K, "band_rows": table.n_band,
        "nbytes": table.nbytes(), "model_nbytes": model_nbytes(n_dir, K, table.n_band, g.n_phi_o),
        "bytes_per_direction": bytes_per_direction(K, table.n_band, g.n_phi_o),
        "rel_error_rms": float(np.sqrt(np.mean(table.rel_error.astype(np.float64) ** 2))),
        "rel_error_max": float(table.rel_error.max()),
        "photons_per_direction": int(table.arrays["photons"].max()),
    }
    if path is not None:
        out["file_bytes"] = path.stat().st_size
    return out


# ---------------------------------------------------------------------------------------------
# recolour
# ---------------------------------------------------------------------------------------------

def synthetic_table(res_deg: float, theta_symmetric: bool, band: int | None, seed: int = 0):
    """A table with the real layout and random contents (timing only)."""
    from usdfiber.bake.table import DEFAULT_LEVELS, LAYOUT, LAYOUT_VERSION, BcsdfTable, Grid

    g = Grid(res_deg, theta_symmetric, False)
    K = len(DEFAULT_LEVELS)
    B = g.n_theta_o if band is None else min(band, g.n_theta_o)
    n_ti, n_pi, n_po = g.n_theta_i, g.n_phi_i, g.n_phi_o
    rng = np.random.default_rng(seed)
    shape = (n_ti, n_pi, K, B, n_po)
    p = np.empty(shape, dtype=np.float16)
    lb = np.empty(shape, dtype=np.float16)
    for ti in range(n_ti):          # slice by slice: no float64 temporaries of the full size
        p[ti] = rng.random((n_pi, K, B, n_po), dtype=np.float32)
        lb[ti] = rng.random((n_pi, K, B, n_po), dtype=np.float32) * 3.0
    lv = np.asarray(DEFAULT_LEVELS)
    alb = np.broadcast_to(np.exp(-lv * 0.8), (n_ti, n_pi, K)).astype(np.float32)
    arrays = {
        "p": p, "p_scale": np.ones((n_ti, n_pi, K), np.float32), "lbar": lb,
        "band_start": np.full((n_ti, n_pi), (g.n_theta_o - B) // 2, np.int16),
        "albedo": alb, "albedo_lbar": np.full((n_ti, n_pi, K), 0.8, np.float32), "levels": lv,
        "width": np.ones(720, np.float32), "rel_error": np.zeros((n_ti, n_pi), np.float32),
        "photons": np.zeros((n_ti, n_pi), np.int64),
    }
    header = {"layout": {"name": LAYOUT, "version": LAYOUT_VERSION}, "resolution": g.to_header(),
              "baked_diameter_um": 1.0}
    return BcsdfTable(header=header, arrays=arrays)


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
    """As tests/test_table.py: the recoloured table against the bake's own photons weighted by
    exp(-sigma_a L) (same photons: interpolation + float16 only), and against an independent
    trace with that absorption (noise of both)."""
    from usdfiber.bake import binning, tracer
    from usdfiber.bake.baker import _batch_seed

    g = table.grid
    xg = binning.ExitGrid(g.n_theta_o, g.n_phi_o)
    w = xg.solid_angle
    fs = tracer.prepare(case["profile"])
    n_b = int(math.ceil(settings.photons / settings.batches))
    out = []
    for (ti, pi) in nodes:
        th, ph = float(g.theta_i_nodes()[ti]), float(g.phi_i_nodes()[pi])
        same = [tracer.trace(fs, th, ph, n_b, eta=case["eta"], beta_deg=case["beta_deg"],
                             max_bounces=settings.max_bounces, seed=_batch_seed(settings.seed, b))
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
    from usdfiber.bake.baker import BakeSettings, bake_table

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
    # 3. Error against direct traces (as in tests/test_table.py).
    sigmas = [(0.3, 1.0), (1.5, 2.0), (3.0, 1.0), (5.0, 1.0), (20.0, 1.0), (100.0, 1.0)]
    for name, (tab, case, st) in real.items():
        nodes = [(0, 0), (1, 5), (2, 9)]
        errs = recolour_error(tab, case, st, sigmas, nodes, 4096 if args.quick else 4 * args.photons)
        for e in errs:
            e["table"] = f"{name} 30 deg"
        out["error"] += errs
    rec.doc["results"] = out
    print_recolour(out)
    rec.finish(args.out or RESULTS / ("recolour_quick.json" if args.quick else "recolour.json"))
    return 0


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
    rec.finish(args.out or RESULTS / ("recolour_kernel_quick.json" if args.quick else "recolour_kernel.json"))
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


# ---------------------------------------------------------------------------------------------
# tables
# ---------------------------------------------------------------------------------------------

def probe(fs, case: dict[str, Any], grid, theta: float, phi: float, n: int, batches: int,
          levels_um: np.ndarray, warm: set[int]) -> dict[str, Any]:
    """One incoming direction traced and binned the way the baker does it (batches with the
    baker's seeds, K absorption levels with path-length moments, batch-variance error)."""
    from usdfiber.bake import tracer
    from usdfiber.bake.table import band_rows

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
    from usdfiber.bake.baker import BakeSettings, bake_table, is_rotationally_symmetric
    from usdfiber.bake.table import DEFAULT_LEVELS, Grid

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
    rec.finish(args.out or RESULTS / ("tables_quick.json" if args.quick else "tables.json"))
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


# ---------------------------------------------------------------------------------------------
# main
# ---------------------------------------------------------------------------------------------

def cmd_grouping(args: argparse.Namespace) -> int:
    """Directions traced together vs one at a time, at the renderer's bake settings.

    Per fiber: a sample of incoming directions is traced both ways (``baker._trace_directions``
    with all of them, and with one at a time, which is how every direction was traced before
    grouping); both must give identical histograms. Then the whole table is baked with the
    default grouping. The table's own error estimate is the error the time was reached at.
    """
    from usdfiber.bake import baker
    from usdfiber.translators.mitsuba.scene import RENDER_BAKE_SETTINGS

    rec = Record("grouping", args)
    st = RENDER_BAKE_SETTINGS if not args.quick else baker.BakeSettings(resolution_deg=30, photons=4000, batches=4)
    if args.resolution:
        st = baker.BakeSettings(resolution_deg=args.resolution, photons=st.photons, batches=st.batches)
    rec.doc["bake_settings"] = st.result_inputs()
    results = []
    for kind in args.fibers.split(","):
        case = fiber_case("wool-cuticle" if kind == "wool" else kind)
        prof, cut = case["profile"], case["cuticle"]
        ctx = baker._context(prof, case["eta"], case["beta_deg"], cut, st)
        g = ctx.grid
        dirs = [(ti, pi) for ti in range(g.n_theta_i) for pi in range(g.n_phi_i)]
        step = max(1, len(dirs) // args.sample)
        sample = dirs[::step][:args.sample]
        baker._trace_directions(ctx, sample[:2])          # compile the kernel once, untimed
        with Timer() as ta:
            alone = [baker._trace_directions(ctx, [d])[0] for d in sample]
        with Timer() as tg:
            grouped = baker._trace_directions(ctx, sample)
        same = all(np.array_equal(a["H"], b["H"]) and np.array_equal(a["G"], b["G"]) and a["rows"] == b["rows"]
                   for a, b in zip(alone, grouped))
        load0 = os.getloadavg()[0]
        with Timer() as tt:
            tab = baker.bake_table(prof, case["eta"], case["beta_deg"], cut, st)
        err = tab.rel_error.astype(np.float64)
        e = {"fiber": kind, "directions": len(dirs), "sample": len(sample), "identical": same,
             "alone_s_per_direction": ta.wall / len(sample), "alone_cores": ta.cores,
             "grouped_s_per_direction": tg.wall / len(sample), "grouped_cores": tg.cores,
             "speedup_sample": ta.wall / tg.wall,
             "table_wall_s": tt.wall, "table_cores": tt.cores, "table_s_per_direction": tt.wall / len(dirs),
             "table_photons_per_s": float(tab.arrays["photons"].sum()) / tt.wall,
             "alone_table_estimate_s": ta.wall / len(sample) * len(dirs),
             "rel_error_rms": float(np.sqrt(np.mean(err ** 2))), "rel_error_max": float(err.max()),
             "load_before_table": round(load0, 2), "load_after_table": round(os.getloadavg()[0], 2)}
        results.append(e)
        print(f"[{kind}] {len(dirs)} directions; sample of {len(sample)}: alone {e['alone_s_per_direction']:.3f} s/dir "
              f"({ta.cores:.2f} cores), grouped {e['grouped_s_per_direction']:.3f} s/dir ({tg.cores:.2f} cores), "
              f"x{e['speedup_sample']:.1f}, identical={same}; whole table {tt.wall:.1f} s ({tt.cores:.2f} cores; "
              f"one at a time ~{e['alone_table_estimate_s']:.0f} s) at rel L2 rms {100 * e['rel_error_rms']:.1f} % / "
              f"max {100 * e['rel_error_max']:.1f} %; load {e['load_before_table']} -> {e['load_after_table']}",
              flush=True)
    rec.doc["results"] = results
    print()
    print(md_table(["fiber", "directions", "one at a time s/dir (cores)", "together s/dir (cores)", "speed-up",
                    "identical", "whole table s (cores)", "one at a time, est. s", "table rel L2 rms / max",
                    "load"],
                   [[e["fiber"], e["directions"], f"{e['alone_s_per_direction']:.3f} ({e['alone_cores']:.2f})",
                     f"{e['grouped_s_per_direction']:.3f} ({e['grouped_cores']:.2f})", f"{e['speedup_sample']:.1f}x",
                     e["identical"], f"{e['table_wall_s']:.1f} ({e['table_cores']:.2f})",
                     f"{e['alone_table_estimate_s']:.0f}",
                     f"{100 * e['rel_error_rms']:.1f}% / {100 * e['rel_error_max']:.1f}%",
                     f"{e['load_before_table']} -> {e['load_after_table']}"] for e in results]))
    rec.finish(args.out or RESULTS / "grouping.json")
    return 0 if all(e["identical"] for e in results) else 1


def _banded(table, k: int, relative_phi: bool) -> tuple[np.ndarray, np.ndarray]:
    """p at level k as (n_ti, n_pi, band x n_po) in band rows (aligned with -theta_i), and
    the solid angles of its bins; with ``relative_phi``, phi_o measured from phi_i."""
    p = table.level_p(k).astype(np.float64)
    d = table.domega_band()
    n_ti, n_pi, nb, n_po = p.shape
    if relative_phi:
        step = n_po // n_pi
        for j in range(n_pi):
            p[:, j] = np.roll(p[:, j], -j * step, axis=-1)
    w = np.repeat(d[..., None], n_po, axis=-1)
    return p.reshape(n_ti, n_pi, nb * n_po), w.reshape(n_ti, n_pi, nb * n_po)


def _rms_rel_l2(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> float:
    e = np.sqrt(((x - y) ** 2 * w).sum(-1) / (y ** 2 * w).sum(-1))
    return float(np.sqrt(np.mean(e ** 2)))


def cmd_lowrank(args: argparse.Namespace) -> int:
    """Is a table low-rank over its incoming directions? (a compression candidate)

    Two tables of the same fiber are baked with independent seeds (noise about 1 %). Each
    level's p, in band rows (aligned with the specular cone) and optionally with phi_o taken
    from phi_i, is approximated by a truncated SVD (weighted by solid angle), over all
    directions or per theta_i over phi_i. The rank-r table is compared with itself (what
    truncation loses) and with the independent table (against which plain noise scores
    sqrt(2) x the table's own): a compression must lose less than about 1 %.
    """
    from usdfiber.bake.baker import BakeSettings, bake_table

    rec = Record("lowrank", args)
    res, photons = (30.0, 20000) if args.quick else (args.resolution, args.photons)
    case = fiber_case(args.fiber)
    tabs = []
    for seed in (0, 1):
        st = BakeSettings(resolution_deg=res, photons=photons, batches=8, seed=seed)
        with Timer() as t:
            tabs.append(bake_table(case["profile"], case["eta"], case["beta_deg"], case["cuticle"], st))
        err = tabs[-1].rel_error.astype(np.float64)
        print(f"[{args.fiber}] seed {seed}: {res:g} deg, {photons} photons/direction in {t.wall:.0f} s "
              f"({t.cores:.2f} cores), rel L2 rms {100 * np.sqrt(np.mean(err ** 2)):.2f} %", flush=True)
    A, B = tabs
    rows = []
    for k in args.levels:
        for rel in (False, True):
            a, w = _banded(A, k, rel)
            b, _ = _banded(B, k, rel)
            n_ti, n_pi, nc = a.shape
            noise = _rms_rel_l2(a, b, w)
            for mode in ("all directions", "per theta_i"):
                for r in args.ranks:
                    if mode == "all directions":
                        x = (a * np.sqrt(w)).reshape(n_ti * n_pi, nc)
                        u, sv, vt = np.linalg.svd(x, full_matrices=False)
                        ar = ((u[:, :r] * sv[:r]) @ vt[:r]).reshape(a.shape) / np.sqrt(w)
                        ratio = n_ti * n_pi * nc / (r * (n_ti * n_pi + nc))
                    else:
                        ar = np.empty_like(a)
                        for i in range(n_ti):
                            u, sv, vt = np.linalg.svd(a[i] * np.sqrt(w[i]), full_matrices=False)
                            ar[i] = ((u[:, :r] * sv[:r]) @ vt[:r]) / np.sqrt(w[i])
                        ratio = n_pi * nc / (r * (n_pi + nc))
                    rows.append({"level": k, "phi_o_from_phi_i": rel, "mode": mode, "rank": r,
                                 "size_ratio": ratio, "loss_vs_itself": _rms_rel_l2(ar, a, w),
                                 "vs_independent": _rms_rel_l2(ar, b, w), "independent_noise": noise})
    rec.doc["tables"] = [{"seed": s, "rel_error_rms": float(np.sqrt(np.mean(t.rel_error.astype(np.float64) ** 2))),
                          "shape": list(t.arrays["p"].shape)} for s, t in zip((0, 1), tabs)]
    rec.doc["results"] = rows
    print(md_table(["level", "phi_o from phi_i", "SVD over", "rank", "smaller by", "lost (vs itself)",
                    "vs independent table", "independent tables differ by"],
                   [[r["level"], r["phi_o_from_phi_i"], r["mode"], r["rank"], f"{r['size_ratio']:.1f}x",
                     f"{100 * r['loss_vs_itself']:.2f}%", f"{100 * r['vs_independent']:.2f}%",
                     f"{100 * r['independent_noise']:.2f}%"] for r in rows]))
    rec.finish(args.out or RESULTS / "lowrank.json")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    sub = ap.add_subparsers(dest="command", required=True)

    p = sub.add_parser("tracers", help="fast vs reference tracer: photons/s and error vs photons")
    p.add_argument("--cases", default=",".join(CASES), help=f"comma list of {', '.join(CASES)}")
    p.add_argument("--directions", default="35,25",
                   help="theta_i,phi_i in degrees; several separated by ';' (default 35,25: a node of "
                        "both the 2 and 10 deg grids, off every 2 deg bin edge)")
    p.add_argument("--fast-counts", default="16:22", help="photon ladder of the fast tracer, powers of 2 (a:b or a,b,c)")
    p.add_argument("--ref-counts", default="14:19", help="photon ladder of the reference tracer")
    p.add_argument("--fast-ref", type=int, default=24, help="log2 photons of the fast tracer's high-photon run")
    p.add_argument("--ref-ref", type=int, default=21, help="log2 photons of the reference tracer's high-photon run")
    p.add_argument("--fast-only", action="store_true")
    p.add_argument("--quick", action="store_true", help="tiny counts (smoke test)")
    p.add_argument("--out", type=Path)
    p.set_defaults(func=cmd_tracers)

    p = sub.add_parser("recolour", help="BcsdfTable.recolour time and error against direct traces")
    p.add_argument("--photons", type=int, default=1 << 16, help="photons per direction of the real tables")
    p.add_argument("--full-size", action="store_true",
                   help="also time a synthetic full 2 deg silk/cotton layout (needs ~15 GB of memory)")
    p.add_argument("--quick", action="store_true")
    p.add_argument("--out", type=Path)
    p.set_defaults(func=cmd_recolour)

    p = sub.add_parser("recolour_kernel", help="recolouring in the Dr.Jit kernel vs numpy, up to full 2 deg tables")
    p.add_argument("--quick", action="store_true")
    p.add_argument("--out", type=Path)
    p.set_defaults(func=cmd_recolour_kernel)

    p = sub.add_parser("tables", help="bake time and size per fiber, extrapolated to 2 deg")
    p.add_argument("--fibers", default="polyester,silk,cotton,mercerizedCotton,wool",
                   help="presets (wool with its cuticle scales, as the paper's wool table)")
    p.add_argument("--resolution", type=float, default=15.0, help="resolution of the real bakes (deg)")
    p.add_argument("--photons", type=int, default=1 << 16, help="photons per direction of the real bakes")
    p.add_argument("--batches", type=int, default=4, help="batches per direction of the real bakes")
    p.add_argument("--probe-photons", default="18,21", help="photons per 2 deg probe direction, powers of 2")
    p.add_argument("--probe-batches", type=int, default=8, help="batches per probe direction (BakeSettings default)")
    p.add_argument("--round-photons", type=int, default=1 << 18,
                   help="photons per direction of the real 2 deg bake of round fibers")
    p.add_argument("--quick", action="store_true")
    p.add_argument("--out", type=Path)
    p.set_defaults(func=cmd_tables)

    p = sub.add_parser("grouping", help="bake at render settings: directions together vs one at a time")
    p.add_argument("--fibers", default="polyester,silk,cotton,mercerizedCotton,wool",
                   help="presets (wool with its cuticle scales)")
    p.add_argument("--sample", type=int, default=24, help="directions traced both ways per fiber")
    p.add_argument("--resolution", type=float, default=None, help="override the render bake resolution (deg)")
    p.add_argument("--quick", action="store_true")
    p.add_argument("--out", type=Path)
    p.set_defaults(func=cmd_grouping)

    p = sub.add_parser("lowrank", help="is a table low-rank over incoming directions? (compression study)")
    p.add_argument("--fiber", default="silk")
    p.add_argument("--resolution", type=float, default=10.0)
    p.add_argument("--photons", type=int, default=800_000, help="photons per direction (about 1 %% noise for silk at 10 deg)")
    p.add_argument("--levels", type=lambda t: [int(x) for x in t.split(",")], default=[0, 8])
    p.add_argument("--ranks", type=lambda t: [int(x) for x in t.split(",")], default=[4, 8, 16, 32])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--out", type=Path)
    p.set_defaults(func=cmd_lowrank)

    args = ap.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
