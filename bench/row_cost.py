"""The tracer's cost per photon by theta_i row, side by side for the bake's estimator and the
plain one, and what those rates make a whole 2 deg table.

    python bench/row_cost.py --fiber silk --schedule bench/results/reciprocity_2deg_schedule_silk.json \
        --out bench/results/row_cost_silk.json

Launches are shaped like a full 2 deg bake's: 64 directions of one theta_i row (spread over
phi_i) x 16,384 photons each, two batches. "expected" is the scheduled bake's estimator (the
expected value at K = 32 with box bins; its reciprocity averaging runs after the tracing and
is not timed here), "plain" the plain estimator at centre nodes. Each round traces every row
with one estimator, then every row with the other, each block after an untimed call (a bake
runs one estimator throughout; the first call of a process, or the first after the other
estimator's, is slower); every other round reverses the order of the estimators and of the
rows, so that a drift of the machine falls on both alike. Medians are quoted with their spread
over the rounds.

The whole-table projection interpolates each estimator's wall time per photon (tracing and the
per-direction statistics, as a bake spends it) linearly over theta_i between the measured
rows: the schedule's photons per direction for the expected value, 16M per direction for plain
(each row's 16M-photon error, the target of the schedule). Their ratio is the side-by-side
speed-up of the whole table, without the averaging (about 2 min on a full table,
``bench/REPORT.md`` section 7). The counts of expected-value events and normals per photon
come from the tracer's results.
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from bake_common import Record

PLAIN_PHOTONS = 16_000_000          # the plain estimator's photons per direction at the 16M-photon error


def settings(kind: str, per_batch: int, seed: int) -> Any:
    """Two batches of ``per_batch`` photons per direction, on the paper's 2 deg grid."""
    from usdfiber.bake.settings import BakeSettings

    st = BakeSettings(resolution_deg=2.0, photons=2 * per_batch, batches=2, seed=seed)
    if kind == "expected":
        st = replace(st, incoming="box", estimator=("expected", "reciprocity"))
    return st


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fiber", default="silk", help="a preset with a non-round cross section")
    ap.add_argument("--rows", default="0,4,8,12,16,20,24,28,32,36,40,44", help="theta_i rows of the 2 deg grid")
    ap.add_argument("--directions", type=int, default=64, help="directions per launch (the baker's group)")
    ap.add_argument("--per-batch", type=int, default=16384, help="photons per direction and launch")
    ap.add_argument("--phi", default="spread", choices=("spread", "block"),
                    help="a launch's directions: spread over the row (its mean), or consecutive phi_i from "
                         "the row's middle, as the baker groups them (the same within the rounds' spread here)")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--schedule", type=Path, help="a row schedule (JSON list): project a whole table")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()

    from usdfiber.bake import baker, tracer
    from usdfiber.bake.requests import requests_from_preset

    rec = Record("row_cost", args)
    req = requests_from_preset(args.fiber)[0]
    rows = [int(r) for r in args.rows.split(",")]
    kinds = ("expected", "plain")
    ctx = {k: baker.bake_context(req.profile(), req.eta, req.beta_deg, req.cuticle_scales,
                                 settings(k, args.per_batch, args.seed)) for k in kinds}
    grid = ctx["expected"].grid
    if args.phi == "spread":
        phis = np.linspace(0, grid.n_phi_i - 1, args.directions).round().astype(int)
    else:
        p0 = max(0, (grid.n_phi_i - args.directions) // 2)
        phis = np.arange(p0, min(grid.n_phi_i, p0 + args.directions))

    results: list = []                      # the tracer's results of the call in flight
    trace_many = tracer.trace_many

    def counted(*a: Any, **k: Any) -> Any:
        out = trace_many(*a, **k)
        results.extend(out)
        return out

    tracer.trace_many = counted

    def run(kind: str, ti: int) -> dict[str, float]:
        results.clear()
        dirs = [(ti, int(p)) for p in phis]
        c0, w0 = time.process_time(), time.perf_counter()
        out = baker.trace_directions(ctx[kind], dirs)
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        photons = sum(d["photons"] for d in out)
        return {"wall_ns": 1e9 * wall / photons, "cpu_ns": 1e9 * cpu / photons,
                "trace_ns": 1e9 * sum(d["seconds"] for d in out) / photons,
                "events": sum(int(r.extra.get("expected_events", 0)) for r in results) / photons,
                "normals": sum(int(r.extra.get("expected_normals", 0)) for r in results) / photons,
                "bounces": float(np.mean(np.concatenate([r.bounces for r in results])))}

    timed: dict[tuple[str, int], list[dict[str, float]]] = {(k, ti): [] for k in kinds for ti in rows}
    for r in range(args.rounds):
        for k in (kinds if r % 2 == 0 else kinds[::-1]):
            # One estimator's rows in a block after an untimed call: a call right after the
            # other estimator's is slower (1.3-1.4x for the expected value), which a bake,
            # one estimator throughout, never pays.
            run(k, rows[len(rows) // 2])
            for ti in (rows if r % 2 == 0 else rows[::-1]):
                timed[(k, ti)].append(run(k, ti))
                m = timed[(k, ti)][-1]
                print(f"round {r} {k:8s} theta_i {np.degrees(grid.theta_i_nodes()[ti]):4.0f} deg: "
                      f"{m['wall_ns']:6.0f} ns wall, {m['trace_ns']:6.0f} ns tracing per photon", flush=True)

    th_all = np.degrees(grid.theta_i_nodes())
    out_rows = []
    for ti in rows:
        row: dict[str, Any] = {"row": ti, "theta_i_deg": float(th_all[ti])}
        for k in kinds:
            v = timed[(k, ti)]
            row[k] = {q: float(np.median([x[q] for x in v])) for q in v[0]}
            row[k]["wall_ns_range"] = [float(min(x["wall_ns"] for x in v)), float(max(x["wall_ns"] for x in v))]
        row["expected_over_plain_per_photon"] = row["expected"]["wall_ns"] / row["plain"]["wall_ns"]
        out_rows.append(row)
    summary: dict[str, Any] = {}
    th = np.array([r["theta_i_deg"] for r in out_rows])
    for k in kinds:
        ns = np.array([r[k]["wall_ns"] for r in out_rows])
        summary[f"{k}_wall_ns_last_over_first_row"] = float(ns[-1] / ns[0])
    if args.schedule:
        sched = np.asarray(json.loads(args.schedule.read_text()), dtype=np.float64)
        if len(sched) != grid.n_theta_i:
            raise SystemExit(f"{args.schedule} has {len(sched)} rows, the grid {grid.n_theta_i}")
        ns = {k: np.interp(th_all, th, [r[k]["wall_ns"] for r in out_rows]) for k in kinds}
        h_ev = float((sched * grid.n_phi_i * ns["expected"]).sum() * 1e-9 / 3600)
        h_pl = float((PLAIN_PHOTONS * grid.n_phi_i * ns["plain"]).sum() * 1e-9 / 3600)
        # the same photons at one rate for every row (the mean over the measured rows at 15-75 deg),
        # as earlier projections assumed
        mid = (th >= 15) & (th <= 75)
        flat = {k: float(np.mean([r[k]["wall_ns"] for r, m in zip(out_rows, mid) if m])) for k in kinds}
        summary.update({
            "schedule": str(args.schedule), "schedule_photons": float(sched.sum() * grid.n_phi_i),
            "expected_hours_whole_table": h_ev, "plain_hours_whole_table_16m": h_pl,
            "speedup_whole_table": h_pl / h_ev,
            "expected_hours_at_mid_rows_rate": float(sched.sum() * grid.n_phi_i * flat["expected"] * 1e-9 / 3600),
            "plain_hours_at_mid_rows_rate": float(PLAIN_PHOTONS * grid.n_theta_i * grid.n_phi_i
                                                  * flat["plain"] * 1e-9 / 3600),
        })
    print(json.dumps(summary, indent=1))
    rec.doc["results"] = {"rows": out_rows, "summary": summary}
    rec.finish(args.out)


if __name__ == "__main__":
    main()
