"""Two source trees of the baker side by side: a scheduled bake's tracing time per photon by row.

    git worktree add /tmp/base d1c453b
    python bench/tracer_ab.py --trees /tmp/base . --rows 0,20,40 --rounds 4 \
        --schedule bench/results/reciprocity_2deg_schedule_silk_unbiased.json \
        --out bench/results/tracer_ab_silk.json

Each measurement is a process of its own that imports ``usdfiber`` from one tree (the tree
first on the import path, an editable install's redirect removed) and traces, for every row of
``--rows``, one group of a scheduled bake: ``--directions`` directions of that theta_i row
(spread over phi_i), each with its row's scheduled photons in batches of at most
``--per-batch``, through the baker's own ``trace_directions`` at the end-to-end bake's
settings (the expected value at K = 32, box bins, reciprocity's own streams), after one untimed
direction (the kernels' compilation). The wall time per photon includes the statistics, as a
bake spends it. Rounds alternate which tree goes first; each round's ratio (first tree's time
over the second's, per row) is a pair measured back to back, and the medians and ranges of
the times and ratios over the rounds are reported.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from bake_common import Record
from bench_common import use_source_tree


def child(tree: str, fiber: str, rows: list[int], n_dirs: int, schedule: str, per_batch: int) -> None:
    """Time one group per row with ``usdfiber`` imported from ``tree``; print one JSON line."""
    use_source_tree(tree, bench=True)
    from dataclasses import replace

    import usdfiber
    from usdfiber.bake import baker
    from usdfiber.bake.requests import requests_from_preset
    from usdfiber.bake.settings import BakeSettings

    if not Path(usdfiber.__file__).resolve().is_relative_to(Path(tree).resolve()):
        raise SystemExit(f"usdfiber came from {usdfiber.__file__}, not from {tree}")
    req = requests_from_preset(fiber)[0]
    sched = json.loads(Path(schedule).read_text())
    st = BakeSettings(resolution_deg=2.0, photons=per_batch * 4, batches=4, seed=2, incoming="box",
                      estimator=("expected", "reciprocity"), row_photons=tuple(int(x) for x in sched))
    ctx = baker.bake_context(req.profile(), req.eta, req.beta_deg, req.cuticle_scales, st)
    n_phi = ctx.grid.n_phi_i
    baker.trace_directions(ctx, [(rows[0], n_phi - 3)])           # compile, untimed
    out = {}
    for r in rows:
        dirs = [(r, p) for p in range(0, n_phi, max(1, n_phi // n_dirs))][:n_dirs]
        w0 = time.perf_counter()
        res = baker.trace_directions(ctx, dirs)
        dt = time.perf_counter() - w0
        out[str(r)] = 1e9 * dt / sum(o["photons"] for o in res)
    print("RESULT " + json.dumps({"tree": tree, "usdfiber": usdfiber.__file__, "ns_per_photon": out}), flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trees", nargs=2, required=True, help="two source trees (checkouts or worktrees)")
    ap.add_argument("--fiber", default="silk")
    ap.add_argument("--rows", default="0,20,40")
    ap.add_argument("--directions", type=int, default=32, help="directions per group (a bake's at 65,536 per batch)")
    ap.add_argument("--schedule", default="bench/results/reciprocity_2deg_schedule_silk_unbiased.json")
    ap.add_argument("--per-batch", type=int, default=65536)
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--out")
    args = ap.parse_args()
    rows = [int(r) for r in args.rows.split(",")]
    if args.child:
        child(args.child, args.fiber, rows, args.directions, args.schedule, args.per_batch)
        return
    if not args.out:
        ap.error("--out is required")
    trees = [str(Path(t).resolve()) for t in args.trees]
    rec = Record("tracer_ab", args)
    runs: list[dict[str, Any]] = []
    for rnd in range(args.rounds):
        pair = {}
        for t in (trees if rnd % 2 == 0 else trees[::-1]):
            cmd = [sys.executable, str(Path(__file__).resolve()), "--trees", *trees, "--child", t, "--fiber", args.fiber,
                   "--rows", args.rows, "--directions", str(args.directions), "--schedule", args.schedule,
                   "--per-batch", str(args.per_batch)]
            p = subprocess.run(cmd, capture_output=True, text=True)
            line = [x for x in p.stdout.splitlines() if x.startswith("RESULT ")]
            if p.returncode or not line:
                raise SystemExit(f"{t}: the timing process failed:\n{p.stderr[-2000:]}")
            pair[t] = json.loads(line[0][7:])
            print(f"round {rnd} {t}: {pair[t]['ns_per_photon']}", flush=True)
        runs.append({"round": rnd, "first": trees[0] if rnd % 2 == 0 else trees[1], **{f"tree{i}": pair[t]
                                                                                        for i, t in enumerate(trees)}})
    summary = {}
    for r in map(str, rows):
        a = np.array([x["tree0"]["ns_per_photon"][r] for x in runs])
        b = np.array([x["tree1"]["ns_per_photon"][r] for x in runs])
        summary[r] = {"tree0_ns": [float(np.median(a)), float(a.min()), float(a.max())],
                      "tree1_ns": [float(np.median(b)), float(b.min()), float(b.max())],
                      "ratio_tree0_over_tree1": [float(np.median(a / b)), float((a / b).min()), float((a / b).max())]}
        print(f"row {r}: {summary[r]}")
    rec.doc["results"] = {"trees": trees, "rounds": runs, "rows": summary}
    rec.finish(Path(args.out))


if __name__ == "__main__":
    main()
