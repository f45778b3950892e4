"""Benchmark: the baker's end-to-end throughput, one source tree against another, side by side.

    git archive HEAD | tar -x -C /tmp/tp_base          # the code to compare against
    python bench/bake_throughput.py --base /tmp/tp_base [--cases silk,cotton,circle-smooth]
                                    [--photons 1000000] [--directions 16] [--rounds 2] [--quick]

Each call bakes ``--directions`` incoming directions of a fiber's 2 degree table (spread over
the grid, traced together as one group of ``baker.trace_directions``, as ``bake_table`` does:
``--photons`` per direction in the settings' 8 batches, launches of about 2M photons) with
the plain estimator, end to end: tracing, binning at the 11 absorption levels, the error
estimate, the direction's result. Calls of the two trees alternate (old, new, then new, old,
...), each in a fresh process that imports only its tree (the editable install's finder is
removed), after an untimed warm-up call that compiles the kernels. Reported per call: wall
and CPU seconds (all threads) and photons per CPU-second; on a shared machine the CPU time is
the figure to compare (the 1-minute load average is recorded before and after each call).
Both trees must give identical results for the same seeds: the SHA-256 of every direction's
histograms is compared.

Writes ``bench/results/bake_throughput.json`` (``--out`` names another file); what a
record holds: :mod:`bake_common`.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from bench_common import use_source_tree

#: Directions and photons of the paper's full 2 degree tables (silk, cotton: 45 x 180).
FULL_DIRECTIONS = 45 * 180
FULL_PHOTONS = 16_000_000


def _worker(args: argparse.Namespace) -> int:
    """One timed call in this process, with ``--root``'s usdfiber; prints one JSON line."""
    root = str(Path(args.root).resolve())
    use_source_tree(root)
    bench_dir = str(Path(__file__).resolve().parent)
    if bench_dir not in sys.path:
        sys.path.append(bench_dir)
    import numpy as np

    import usdfiber
    from bake_common import fiber_case
    from usdfiber.bake import baker
    from usdfiber.bake.settings import BakeSettings

    if not str(Path(usdfiber.__file__).resolve()).startswith(root + os.sep):
        raise SystemExit(f"imported {usdfiber.__file__}, not the tree {root}")
    case = fiber_case(args.case)
    st = BakeSettings(photons=args.photons)
    ctx = baker.bake_context(case["profile"], case["eta"], case["beta_deg"], case["cuticle"], st)
    g = ctx.grid
    dirs = [(ti, pi) for ti in range(g.n_theta_i) for pi in range(g.n_phi_i)]
    sample = dirs[::max(1, len(dirs) // args.directions)][:args.directions]
    warm = baker.bake_context(case["profile"], case["eta"], case["beta_deg"], case["cuticle"],
                              BakeSettings(photons=max(8, args.photons // 16)))
    baker.trace_directions(warm, sample[:2])          # compiles the kernels, untimed
    load0 = os.getloadavg()[0]
    w0, c0 = time.perf_counter(), time.process_time()
    out = baker.trace_directions(ctx, sample)
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    h = hashlib.sha256()
    for d in out:
        h.update(repr((d["rows"], d["photons"], d["n_hit"], d["n_cut"])).encode())
        h.update(np.ascontiguousarray(d["H"]).tobytes())
        h.update(np.ascontiguousarray(d["G"]).tobytes())
    err = np.array([d["rel_error"] for d in out])
    print(json.dumps({
        "tree": root, "case": args.case, "directions": len(sample), "photons": int(sum(d["photons"] for d in out)),
        "wall_s": wall, "cpu_s": cpu, "load_before": load0, "load_after": os.getloadavg()[0],
        "sha256": h.hexdigest(), "rel_error_median": float(np.median(err)), "rel_error_max": float(err.max()),
        "theta_i_deg": [round(math.degrees(d["theta_i"]), 2) for d in out],
    }))
    return 0


def _call(tree: Path, case: str, args: argparse.Namespace) -> dict[str, Any]:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", "--root", str(tree), "--case", case,
           "--photons", str(args.photons), "--directions", str(args.directions)]
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=str(tree))
    if p.returncode != 0:
        raise SystemExit(f"worker failed ({tree}, {case}):\n{p.stderr[-4000:]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def cmd_throughput(args: argparse.Namespace) -> int:
    from bake_common import ROOT, Record, fmt_pct, results_path
    from bench_common import md_table

    if args.quick:
        args.photons, args.directions, args.rounds = 64_000, 4, 1
    base = Path(args.base).resolve()
    if not (base / "usdfiber" / "bake" / "baker.py").is_file():
        raise SystemExit(f"{base}: not a usdfiber source tree (git archive HEAD | tar -x -C {base})")
    rec = Record("bake_throughput", args)
    head = base / ".head"
    rec.doc["base_tree"] = {"path": str(base), "head": head.read_text().strip() if head.exists() else None}
    trees = {"old": base, "new": ROOT}
    calls: list[dict[str, Any]] = []
    for rnd in range(args.rounds):
        for case in args.cases.split(","):
            order = ("old", "new") if rnd % 2 == 0 else ("new", "old")
            for which in order:
                r = _call(trees[which], case, args)
                r.update({"which": which, "round": rnd})
                calls.append(r)
                print(f"round {rnd} {case:14s} {which}: {r['photons'] / r['cpu_s'] / 1e6:.3f} M photons per CPU-s, "
                      f"cpu {r['cpu_s']:.1f} s, wall {r['wall_s']:.1f} s, load {r['load_before']:.2f} -> "
                      f"{r['load_after']:.2f}", flush=True)
    rec.doc["calls"] = calls
    rows, summary = [], {}
    for case in args.cases.split(","):
        cs = {w: [c for c in calls if c["case"] == case and c["which"] == w] for w in ("old", "new")}
        cpu = {w: sum(c["cpu_s"] for c in v) for w, v in cs.items()}
        wall = {w: sum(c["wall_s"] for c in v) for w, v in cs.items()}
        ph = {w: sum(c["photons"] for c in v) for w, v in cs.items()}
        rate = {w: ph[w] / cpu[w] for w in cs}
        ratios = [o["cpu_s"] / n["cpu_s"] for o, n in zip(cs["old"], cs["new"])]
        same = len({c["sha256"] for c in cs["old"] + cs["new"]}) == 1
        n_dir = cs["new"][0]["directions"]
        full = {w: FULL_DIRECTIONS * FULL_PHOTONS / rate[w] / 3600.0 for w in cs}
        summary[case] = {"rate_old": rate["old"], "rate_new": rate["new"], "ratio": rate["new"] / rate["old"],
                         "ratio_per_round": ratios, "identical": same,
                         "cpu_s_per_direction_old": cpu["old"] / (n_dir * len(cs["old"])),
                         "cpu_s_per_direction_new": cpu["new"] / (n_dir * len(cs["new"])),
                         "wall_s_old": wall["old"], "wall_s_new": wall["new"],
                         "full_table_cpu_hours_old": full["old"], "full_table_cpu_hours_new": full["new"],
                         "rel_error_median": cs["new"][0]["rel_error_median"],
                         "rel_error_max": cs["new"][0]["rel_error_max"]}
        s = summary[case]
        rows.append([case, n_dir, f"{args.photons:,}", f"{s['cpu_s_per_direction_old']:.2f}",
                     f"{s['cpu_s_per_direction_new']:.2f}", f"{rate['old'] / 1e6:.3f}", f"{rate['new'] / 1e6:.3f}",
                     f"{s['ratio']:.2f}x ({', '.join(f'{x:.2f}' for x in ratios)})", "yes" if same else "NO",
                     f"{fmt_pct(s['rel_error_median'])} / {fmt_pct(s['rel_error_max'])}",
                     f"{full['old']:.1f} -> {full['new']:.1f}"])
    rec.doc["summary"] = summary
    print()
    print(md_table(["case", "directions", "photons/dir", "CPU s/dir old", "CPU s/dir new", "M photons/CPU-s old",
                    "M photons/CPU-s new", "ratio (per round)", "identical", "rel L2 median / max",
                    "full 2 deg table, CPU h old -> new"], rows))
    rec.finish(results_path(args, "bake_throughput"))
    return 0 if all(s["identical"] for s in summary.values()) else 1


def main() -> int:
    bench_dir = str(Path(__file__).resolve().parent)
    if bench_dir not in sys.path:
        sys.path.insert(0, bench_dir)
    from bake_common import bench_parser

    ap = bench_parser(__doc__, "4 directions, 64k photons, one round (a smoke test)")
    ap.add_argument("--base", default="/tmp/tp_base", help="the source tree to compare against")
    ap.add_argument("--cases", default="silk,cotton,circle-smooth")
    ap.add_argument("--photons", type=int, default=1_000_000, help="photons per direction")
    ap.add_argument("--directions", type=int, default=16)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--root", help=argparse.SUPPRESS)
    ap.add_argument("--case", help=argparse.SUPPRESS)
    args = ap.parse_args()
    return _worker(args) if args.worker else cmd_throughput(args)


if __name__ == "__main__":
    sys.exit(main())
