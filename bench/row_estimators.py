"""Estimator variants on rows of a full 2 deg box table: variance and time per photon, side by side.

    python bench/row_estimators.py --rows 0,10,20,30,40,44 --phis 7,50,100,150 --batches 32 \
        --photons 65536 --variants expected,expected+stratified --out bench/results/row_estimators_silk.json

A variant is the baker's estimators joined by ``+`` (``expected``, ``stratified``), optionally
with ``:K`` for the expected value's normals per event (``expected:16``). Each variant traces
the same directions (``--phis`` of each theta_i row, box bins) through the baker's own
``trace_directions``, ``--batches`` batches of ``--photons`` each, with its own random streams.
A direction's variance per photon is ``e^2 N`` (``e``: the relative L2 error of p at
sigma_a = 0 from the spread between its batches, the estimate a bake plans with; ``N``: its
photons); a row's is the mean over its directions, with ``D (B - 1)`` degrees of freedom. The
variance ratio of a variant is the first variant's variance per photon over its own (above 1:
it needs fewer photons for the same error), given with two standard errors from those degrees of
freedom (chi-square, each variance's relative standard error sqrt(2 / dof)). Time per photon
is the tracer's wall time, its statistics included, rounds alternating the order of the
variants, after one untimed call per variant (its kernels' compilation); the gain at equal
error is the variance ratio over the time ratio.
"""
from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from bake_common import Record


def parse_variant(spec: str) -> tuple[tuple[str, ...], int | None]:
    """``expected+stratified:16`` -> (("expected", "stratified"), 16)."""
    names, _, k = spec.partition(":")
    return tuple(n for n in names.split("+") if n and n != "plain"), (int(k) if k else None)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fiber", default="silk", help="a preset with a non-round cross section")
    ap.add_argument("--rows", default="0,20,40", help="theta_i rows of the 2 deg grid")
    ap.add_argument("--phis", default="7,50,100,150", help="phi_i columns of every row")
    ap.add_argument("--batches", type=int, default=32)
    ap.add_argument("--photons", type=int, default=65536, help="photons per batch")
    ap.add_argument("--variants", default="expected,expected+stratified")
    ap.add_argument("--rounds", type=int, default=1, help="timed rounds (the variance pools them)")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--out", required=True)
    args = ap.parse_args()

    from usdfiber.bake import baker
    from usdfiber.bake.requests import requests_from_preset
    from usdfiber.bake.settings import BakeSettings

    rows = [int(r) for r in args.rows.split(",")]
    phis = [int(p) for p in args.phis.split(",")]
    variants = args.variants.split(",")
    rec = Record("row_estimators", args)
    req = requests_from_preset(args.fiber)[0]
    base = BakeSettings(resolution_deg=2.0, batches=args.batches, photons=args.batches * args.photons,
                        seed=args.seed, incoming="box", estimator=("expected",))
    ctx = {}
    for v in variants:
        est, k = parse_variant(v)
        st = replace(base, estimator=est, **({"expected_normals": k} if k else {}))
        ctx[v] = baker.bake_context(req.profile(), req.eta, req.beta_deg, req.cuticle_scales, st)
        baker.trace_directions(ctx[v], [(rows[0], (phis[0] + 1) % ctx[v].grid.n_phi_i)])   # compile, untimed

    var: dict[tuple[str, int], list[float]] = {(v, r): [] for v in variants for r in rows}
    sec: dict[tuple[str, int], list[float]] = {(v, r): [] for v in variants for r in rows}
    for rnd in range(args.rounds):
        for r in (rows if rnd % 2 == 0 else rows[::-1]):
            for v in (variants if rnd % 2 == 0 else variants[::-1]):
                c = ctx[v]
                # each round other phi_i columns of the row: fresh directions, the same row
                dirs = [(r, (p + 97 * rnd) % c.grid.n_phi_i) for p in phis]
                w0 = time.perf_counter()
                out = baker.trace_directions(c, dirs)
                dt = time.perf_counter() - w0
                n = sum(o["photons"] for o in out)
                var[(v, r)] += [o["rel_error"] ** 2 * o["photons"] for o in out]
                sec[(v, r)].append(1e9 * dt / n)
                print(f"round {rnd} row {r} {v}: variance per photon "
                      f"{np.mean(var[(v, r)][-len(dirs):]):.1f}, {sec[(v, r)][-1]:.0f} ns per photon", flush=True)

    out_rows: list[dict[str, Any]] = []
    first = variants[0]
    for r in rows:
        row: dict[str, Any] = {"row": r, "theta_i_deg": 2.0 * r + 1.0}
        for v in variants:
            dof = len(var[(v, r)]) * (args.batches - 1)
            row[v] = {"variance_per_photon": float(np.mean(var[(v, r)])), "dof": dof,
                      "per_direction": var[(v, r)], "wall_ns_per_photon": float(np.median(sec[(v, r)])),
                      "wall_range": [min(sec[(v, r)]), max(sec[(v, r)])]}
        for v in variants[1:]:
            ratio = row[first]["variance_per_photon"] / row[v]["variance_per_photon"]
            se = ratio * math.sqrt(2.0 / row[first]["dof"] + 2.0 / row[v]["dof"])
            t = row[v]["wall_ns_per_photon"] / row[first]["wall_ns_per_photon"]
            row[f"{v}_vs_{first}"] = {"variance_ratio": ratio, "two_standard_errors": 2.0 * se,
                                     "time_ratio": t, "gain": ratio / t}
        out_rows.append(row)
    for row in out_rows:
        print(row["row"], {k: {kk: round(vv, 3) for kk, vv in x.items()} for k, x in row.items() if "_vs_" in k})
    rec.doc["results"] = {"rows": out_rows}
    rec.finish(Path(args.out))


if __name__ == "__main__":
    main()
