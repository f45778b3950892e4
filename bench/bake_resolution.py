"""Resolution matched to content: interpolation error of coarser grids against 2 degree bins.

For each fiber and probe direction omega_i (theta_i, phi_i in degrees), photons are traced in
``--batches`` batches (common random numbers: batch b of every direction is one seed, as in
the baker) at the probe itself and at the incoming nodes a coarser incoming grid of spacing
D_i interpolates from at its worst point, the middle of a cell: theta_i +- D_i/2 and (fibers
that are not round) phi_i +- D_i/2, weights 1/2 (1/4). Near grazing incidence, where
theta_i + D_i/2 > 90, the grid's outermost node 90 - D_i/2 is used alone (the lookup's
constant extrapolation). Exits are binned at 1 degree, from which every coarser outgoing grid
D_o (dividing 90) is summed. A coarse table is evaluated at the 2 degree bins by AVERAGING its
own bilinear interpolant (between bin centres, periodic in phi, constant beyond the outermost
theta centres: ``usdfiber.bake.lookup``) over each 2 degree bin (8 x 8 points uniform in solid
angle); D_o = 2 is the histogram itself.

Error (relative L2 of p over the sphere at the 2 degree bins, ``bench/REPORT.md``, "Error
metrics") separated into interpolation bias and noise: with per-batch differences
``d_b = C_b - R_b`` (coarse estimate minus the 2 degree histogram at the probe), ``|bias|^2 =
|mean d|^2 - sum Var_b(d) / B`` (unbiased), with a jackknife standard error over batches;
the noise constant of the coarse table, ``c_coarse = sqrt(N) x rel L2 noise`` at a node, from
the spread of its batches. Round fibers are mirror-averaged about phi_i, as the baker does.
Fibers with cuticles: p conditional on a hit (as in section 2's probes).

Cost: for each (D_o, D_i) whose bias (estimate + 2 standard errors) is at most half of each
probe's target, the plain 2 degree table's error there at 16M photons (``c_dir / 4000``; also
at 1M and 100k), the photons per direction that give the target in total,
``N = c_coarse^2 / (target^2 - bias^2)`` (worst probe), and the full-table time
``n_dir (a + N / rate)`` with section 2's per-direction fit (a, rate), against the plain 2
degree table. Incoming spacings measured: 3 and 6 deg (``INCOMING``); outgoing bins 2-18 deg.

    python bench/bake_resolution.py                  # 5 fibers, 6 probes: 47 min at load 15-20 on 2 cores
    python bench/bake_resolution.py --quick          # smoke test
"""
from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from bake_common import Record, bench_parser, fiber_case, fmt_pct, fmt_time, results_path
from bench_common import json_default, md_table

DEFAULT_PROBES = "0,25;20,115;40,25;60,205;75,65;85,155"
INCOMING = (3, 6)                           # incoming node spacings measured (deg)
OUTGOING = (2, 3, 5, 6, 9, 10, 18)           # outgoing bin sizes measured (deg)
#: c of the plain estimator at 2 deg (bench/REPORT.md section 2, the theta_i = 35 deg probe):
#: the 16M-photon noise target is c / 4000.
C_PLAIN = {"polyester": 21.0, "silk": 43.0, "cotton": 64.0, "mercerizedCotton": 50.0, "wool-cuticle": 21.0}
#: Per-direction time t(N) = a + N / rate on 2 cores (bench/REPORT.md section 2).
TIME_FIT = {"polyester": (1.672, 680e3), "silk": (0.585, 734e3), "cotton": (0.382, 549e3),
            "mercerizedCotton": (0.149, 702e3), "wool-cuticle": (0.466, 492e3)}
PLAIN_PHOTONS = 16e6
SUB = 8                                     # sub-samples per 2 degree bin and axis


def _rows_solid(d: float) -> np.ndarray:
    e = np.radians(np.arange(-90.0, 90.0 + 1e-9, d))
    return np.radians(d) * (np.sin(e[1:]) - np.sin(e[:-1]))


def _lerp_matrix(points: np.ndarray, centres: np.ndarray, step: float, periodic: bool) -> np.ndarray:
    """(len(points), len(centres)) linear interpolation weights between centres."""
    n = len(centres)
    u = (points - centres[0]) / step
    if periodic:
        k0 = np.floor(u).astype(int)
        t = u - k0
        k0, k1 = k0 % n, (k0 + 1) % n
    else:
        u = np.clip(u, 0.0, n - 1.0)
        k0 = np.minimum(np.floor(u).astype(int), n - 1)
        t = u - k0
        k1 = np.minimum(k0 + 1, n - 1)
    m = np.zeros((len(points), n))
    np.add.at(m, (np.arange(len(points)), k0), 1.0 - t)
    np.add.at(m, (np.arange(len(points)), k1), t)
    return m


def outgoing_operator(d_o: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(A_theta (90, n_to), A_phi (180, n_po)): a D_o table's bilinear interpolant averaged over
    each 2 degree bin is ``A_theta @ p @ A_phi.T``. None for D_o = 2 (the histogram itself)."""
    if d_o == 2:
        return None
    e2 = np.radians(np.arange(-90.0, 90.0 + 1e-9, 2.0))
    s = (np.arange(SUB) + 0.5) / SUB
    sin_pts = np.sin(e2[:-1, None]) + s[None, :] * (np.sin(e2[1:]) - np.sin(e2[:-1]))[:, None]
    th_pts = np.arcsin(sin_pts).ravel()
    step = math.radians(d_o)
    th_c = -0.5 * math.pi + step * (np.arange(int(180 / d_o)) + 0.5)
    a_th = _lerp_matrix(th_pts, th_c, step, False).reshape(90, SUB, -1).mean(axis=1)
    ph_pts = (np.radians(2.0) * (np.arange(180)[:, None] + s[None, :])).ravel()
    ph_c = step * (np.arange(int(360 / d_o)) + 0.5)
    a_ph = _lerp_matrix(ph_pts, ph_c, step, True).reshape(180, SUB, -1).mean(axis=1)
    return a_th, a_ph


def to_grid(mass1: np.ndarray, d_o: int, ops: dict) -> np.ndarray:
    """p on the 2 degree bins of a D_o table made of 1 degree bin masses (..., 180, 360)."""
    sh = mass1.shape[:-2]
    m = mass1.reshape(sh + (180 // d_o, d_o, 360 // d_o, d_o)).sum(axis=(-3, -1))
    p = m / _rows_solid(d_o)[:, None]
    op = ops[d_o]
    if op is None:
        return p
    a_th, a_ph = op
    return np.einsum("rk,...kc,pc->...rp", a_th, p, a_ph)


def incoming_nodes(theta: float, phi: float, d_i: int, round_: bool, symmetric: bool) -> list[tuple[float, float, float]]:
    """Nodes (theta, phi, weight) that a D_i incoming grid interpolates from at its worst point."""
    # Below theta_i = 0 an extruded table mirrors its first node: the same as tracing there.
    if theta + 0.5 * d_i > 90.0 - 1e-9:
        ths = [(90.0 - 0.5 * d_i, 1.0)]
    else:
        ths = [(theta - 0.5 * d_i, 0.5), (theta + 0.5 * d_i, 0.5)]
    phs = [(phi, 1.0)] if round_ else [((phi - 0.5 * d_i) % 360.0, 0.5), ((phi + 0.5 * d_i) % 360.0, 0.5)]
    return [(t, p, wt * wp) for t, wt in ths for p, wp in phs]


def bias_and_noise(C: np.ndarray, R: np.ndarray, w: np.ndarray) -> dict[str, float]:
    """Relative L2 bias of C against R (both (B, 90, 180) per batch), its jackknife standard
    error, over the norm of mean R."""
    B = C.shape[0]
    d = C - R
    den = float(np.sum(w * R.mean(axis=0) ** 2))

    def b2(dd: np.ndarray) -> float:
        n = dd.shape[0]
        return float(np.sum(w * dd.mean(axis=0) ** 2) - np.sum(w * dd.var(axis=0, ddof=1)) / n) / den

    est = b2(d)
    jk = np.array([b2(np.delete(d, k, axis=0)) for k in range(B)])
    se = float(math.sqrt((B - 1) / B * np.sum((jk - jk.mean()) ** 2)))
    return {"bias2": est, "bias2_se": se, "bias": math.sqrt(max(est, 0.0)),
            "bias_hi": math.sqrt(max(est + 2 * se, 0.0))}


def noise_constant(C: np.ndarray, w: np.ndarray, photons: int) -> float:
    """c = sqrt(N) x relative L2 noise of the batch mean of C (B, 90, 180), N photons in all."""
    B = C.shape[0]
    m = C.mean(axis=0)
    var = np.sum(w * C.var(axis=0, ddof=1)) / B
    return math.sqrt(photons * var / np.sum(w * m ** 2))


def probe_fiber(name: str, probes: list[tuple[float, float]], n_b: int, batches: int, ops: dict) -> dict[str, Any]:
    from usdfiber.bake import tracer
    from usdfiber.bake.baker import is_rotationally_symmetric

    case = fiber_case(name)
    round_ = is_rotationally_symmetric(case["profile"])
    symmetric = case["cuticle"] is None
    fs = tracer.prepare(case["profile"], case["cuticle"])
    kw = dict(eta=case["eta"], beta_deg=case["beta_deg"], cuticle=case["cuticle"], max_bounces=4096)
    w2 = np.repeat(_rows_solid(2.0)[:, None], 180, axis=1)
    out = {"fiber": name, "beta_deg": case["beta_deg"], "round": round_, "cuticle": case["cuticle"] is not None,
           "photons_per_direction": n_b * batches, "batches": batches, "probes": []}
    t_fiber = time.perf_counter()
    for theta, phi in probes:
        nodes = {d: incoming_nodes(theta, phi, d, round_, symmetric) for d in INCOMING}
        dirs = sorted({(theta, phi)} | {(t, p) for ns in nodes.values() for t, p, _ in ns})
        mass = {dd: np.zeros((batches, 180, 360)) for dd in dirs}
        t0 = time.perf_counter()
        for b in range(batches):
            res = tracer.trace_many(fs, [(math.radians(t), math.radians(p)) for t, p in dirs], n_b,
                                    seed=[1000 + b] * len(dirs), **kw)
            for dd, r in zip(dirs, res):
                v = r.directions[~np.asarray(r.cut, dtype=bool)].astype(np.float64)
                th = np.degrees(np.arcsin(np.clip(v[:, 2], -1, 1)))
                ph = np.degrees(np.mod(np.arctan2(v[:, 1], v[:, 0]), 2 * math.pi))
                row = np.clip(np.floor(th + 90.0).astype(int), 0, 179)
                col = np.floor(ph).astype(int) % 360
                m = np.bincount(row * 360 + col, minlength=180 * 360).reshape(180, 360) / max(int(r.n_hit), 1)
                if round_:      # mirror about phi_i (an integer number of degrees), as the baker does
                    m = 0.5 * (m + m[:, (2 * int(round(dd[1])) - 1 - np.arange(360)) % 360])
                mass[dd][b] = m
        seconds = time.perf_counter() - t0
        R = to_grid(mass[(theta, phi)], 2, ops)
        N = n_b * batches
        row = {"theta_i": theta, "phi_i": phi, "directions_traced": len(dirs), "seconds": round(seconds, 1),
               "c_2deg": noise_constant(R, w2, N), "outgoing": {}, "pairs": {}}
        node_grids = {}
        for d_o in OUTGOING:
            Cn = to_grid(mass[(theta, phi)], d_o, ops)
            node_grids[d_o] = Cn
            row["outgoing"][str(d_o)] = {"c_coarse": noise_constant(Cn, w2, N),
                                         **({"bias": 0.0, "bias_hi": 0.0} if d_o == 2 else bias_and_noise(Cn, R, w2))}
        for d_i in INCOMING:
            for d_o in OUTGOING:
                if d_i % d_o:
                    continue
                C = sum(wt * (node_grids[d_o] if (t, p) == (theta, phi) else to_grid(mass[(t, p)], d_o, ops))
                        for t, p, wt in nodes[d_i])
                row["pairs"][f"{d_o}/{d_i}"] = bias_and_noise(C, R, w2)
        out["probes"].append(row)
        print(f"{name:16s} theta {theta:3.0f} phi {phi:4.0f}: c(2 deg) {row['c_2deg']:5.1f}, "
              f"bias out 6 {fmt_pct(row['outgoing']['6']['bias'])}, in 6 {fmt_pct(row['pairs']['2/6']['bias'])}, "
              f"in 3 {fmt_pct(row['pairs']['3/3']['bias'])} ({len(dirs)} dirs, {seconds:.0f} s, "
              f"load {os.getloadavg()[0]:.1f})", flush=True)
    out["seconds"] = round(time.perf_counter() - t_fiber, 1)
    return out


def n_directions(d_i: int, round_: bool, symmetric: bool) -> int:
    n_t = int(90 / d_i) * (1 if symmetric else 2)
    return n_t * (1 if round_ else int(360 / d_i))


def costs(fib: dict[str, Any], plain_photons: float = PLAIN_PHOTONS) -> dict[str, Any]:
    """Feasible (D_o, D_i) pairs, photons per direction and extrapolated full-table time, for
    the error of the plain 2 degree table at ``plain_photons`` per direction."""
    name = fib["fiber"]
    # Each probe direction's target: its own plain 2 degree error at plain_photons (the issue's
    # protocol); C_PLAIN's (section 2, theta_i = 35 deg) is shown for reference.
    targets = [p["c_2deg"] / math.sqrt(plain_photons) for p in fib["probes"]]
    target = C_PLAIN[name] / math.sqrt(plain_photons)
    a, rate = TIME_FIT[name]
    sym = not fib["cuticle"]
    plain_t = n_directions(2, fib["round"], sym) * (a + plain_photons / rate)
    pairs: dict[str, Any] = {}
    keys = ["2/2"] + sorted({k for p in fib["probes"] for k in p["pairs"]},
                            key=lambda k: tuple(int(x) for x in k.split("/")))
    for key in keys:
        d_o, d_i = (int(x) for x in key.split("/"))
        if key == "2/2":
            bias = [0.0 for _ in fib["probes"]]
            bias_hi = bias
        else:
            bias = [p["pairs"][key]["bias"] for p in fib["probes"]]
            bias_hi = [p["pairs"][key]["bias_hi"] for p in fib["probes"]]
        c_co = [p["outgoing"][str(d_o)]["c_coarse"] for p in fib["probes"]]
        feasible = all(b <= 0.5 * t for b, t in zip(bias_hi, targets))
        # Photons for the target in total in every probe direction (noise gets what bias leaves).
        need = [c * c / (t ** 2 - b * b) if b < t else math.inf for c, b, t in zip(c_co, bias, targets)]
        N = max(need)
        n_dir = n_directions(d_i, fib["round"], sym)
        T = n_dir * (a + N / rate)
        pairs[key] = {"bias_worst": max(bias), "bias_hi_worst": max(bias_hi), "c_coarse_worst": max(c_co),
                      "bias_hi_per_c": max(b / p["c_2deg"] for b, p in zip(bias_hi, fib["probes"])),
                      "noise_ratio": max(c / p["c_2deg"] for c, p in zip(c_co, fib["probes"])),
                      "feasible": feasible, "photons_per_direction": N, "directions": n_dir,
                      "hours": T / 3600.0, "speedup": plain_t / T}
    best = min((k for k, v in pairs.items() if v["feasible"]), key=lambda k: pairs[k]["hours"])
    return {"plain_photons": plain_photons, "target": target, "targets": targets, "plain_hours": plain_t / 3600.0,
            "pairs": pairs, "best": best}


#: Errors the cost is reported for: the plain 2 degree table's at these photons per direction
#: (16M: the paper's; 1M: `usdfiber bake`'s default; 100k: the renderer's on-demand tables).
PLAIN_TARGETS = (16e6, 1e6, 1e5)


def report(fibers: list[dict[str, Any]]) -> None:
    """Markdown tables: every pair at the 16M target, then the best pair per target."""
    rows = []
    for f in fibers:
        c = f["cost"]
        for key, v in c["pairs"].items():
            rows.append([f["fiber"], key, fmt_pct(v["bias_worst"]), fmt_pct(v["bias_hi_worst"]), fmt_pct(c["target"]),
                         "yes" if v["feasible"] else "no", f"{v['c_coarse_worst']:.1f}",
                         f"{v['photons_per_direction'] / 1e6:.2f}M" if math.isfinite(v["photons_per_direction"]) else "-",
                         v["directions"], fmt_time(3600 * v["hours"]) or "-",
                         (f"{v['speedup']:.2f}x" if v["feasible"] else "-") + (" **best**" if key == c["best"] else "")])
    print(md_table(["fiber", "D_o/D_i", "bias (worst)", "bias + 2 se", "target (35 deg)", "bias + 2 se <= target/2",
                    "c_coarse", "photons/dir", "directions", "full table", "vs plain 2 deg"], rows))
    rows = []
    for f in fibers:
        for n in PLAIN_TARGETS:
            c = costs(f, n)
            b = c["pairs"][c["best"]]
            rows.append([f["fiber"], f"{n / 1e6:g}M", fmt_pct(c["target"]), c["best"], fmt_pct(b["bias_hi_worst"]),
                         f"{b['photons_per_direction'] / 1e6:.3g}M", b["directions"], fmt_time(3600 * c["plain_hours"]),
                         fmt_time(3600 * b["hours"]), f"{b['speedup']:.2f}x"])
    print(md_table(["fiber", "plain photons/dir", "target (rel L2)", "best D_o/D_i", "bias + 2 se",
                    "photons/dir", "directions", "plain 2 deg table", "best table", "speedup"], rows))


def main() -> None:
    ap = bench_parser(__doc__, "2 fibers, 2 probes, few photons")
    ap.add_argument("--fibers", default="silk,cotton,mercerizedCotton,wool-cuticle,polyester")
    ap.add_argument("--probes", default=DEFAULT_PROBES, help="theta_i,phi_i;... in degrees")
    ap.add_argument("--photons-log2", type=int, default=15, help="photons per batch per direction, log2")
    ap.add_argument("--round-extra-log2", type=int, default=1,
                    help="round fibers trace 2^this times more photons (they trace few directions)")
    ap.add_argument("--batches", type=int, default=8)
    ap.add_argument("--from-json", type=Path, help="print the tables of an earlier run's results (no tracing)")
    args = ap.parse_args()
    if args.from_json:
        report([{**f, "cost": costs(f)} for f in json.loads(args.from_json.read_text())["fibers"]])
        return
    if args.quick:
        args.fibers, args.probes, args.photons_log2, args.batches = "polyester,silk", "20,115;60,205", 13, 4
    rec = Record("bake_resolution", args)
    ops = {d: outgoing_operator(d) for d in OUTGOING}
    probes = [tuple(float(x) for x in p.split(",")) for p in args.probes.split(";") if p]
    fibers = []
    for name in args.fibers.split(","):
        case_round = name == "polyester"
        n_b = 1 << (args.photons_log2 + (args.round_extra_log2 if case_round else 0))
        fib = probe_fiber(name, probes, n_b, args.batches, ops)
        fib["cost"] = costs(fib)
        fibers.append(fib)
        rec.doc["fibers"] = fibers      # kept as it goes: a run cut short keeps its finished fibers
        out = results_path(args, "bake_resolution").with_suffix(".partial.json")
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(rec.doc, indent=1, default=json_default) + "\n")
    rec.doc["fibers"] = fibers
    report(fibers)
    rec.finish(results_path(args, "bake_resolution"))


if __name__ == "__main__":
    main()
