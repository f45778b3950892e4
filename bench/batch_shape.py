"""The expected value's tracing time per photon against its batch size, side by side.

    python bench/batch_shape.py --rows 0,20,40 --shapes 64x16384,16x65536 --rounds 4 \
        --out bench/results/batch_shape_silk.json

A shape ``DxN`` is D directions of one theta_i row (consecutive phi_i from the row's start),
each traced as two batches of N photons through the baker's own ``trace_directions`` at
the scheduled bake's settings (the expected value at K = 32, box bins, 11 absorption levels).
Every shape holds the same photons (2 x D x N), so the shapes differ only in how many photons each
(direction, batch) has: each pays a fixed cost (its in-kernel histograms, 24 values per 2 deg
bin, float32 now, float64 when bench/REPORT.md measured the shapes; zeroed, reduced over the
threads' copies, read back and rearranged; and its share of the launches), which more photons
per batch spread thinner. The row's statistics (binning every
batch into the direction's sums) are timed with it, as a bake spends them. Rounds alternate the
order of the shapes and rows; medians with their range.

With ``--schedule`` (a row schedule, a JSON list of photons per direction of each row) a shape
``DxN`` is D directions each traced with its row's scheduled photons, exactly, in batches of at
most N (``BakeSettings.row_photons``, shared evenly among at least 4 batches): the same
photons, hence the same error, in either shape; the time per photon a scheduled bake spends on
those rows at either batch size, side by side:

    python bench/batch_shape.py --rows 0,20,40 --shapes 16x16384,16x65536 --rounds 2 \
        --schedule bench/results/reciprocity_2deg_schedule_silk_unbiased.json \
        --out bench/results/batch_shape_schedule_silk.json
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fiber", default="silk", help="a preset with a non-round cross section")
    ap.add_argument("--rows", default="0,40", help="theta_i rows of the 2 deg grid")
    ap.add_argument("--shapes", default="64x16384,16x65536", help="DIRECTIONSxPHOTONS, equal products")
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--schedule", help="a row schedule (JSON list): each direction its row's photons, "
                                       "in batches of at most N")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()

    from usdfiber.bake import baker
    from usdfiber.bake.requests import requests_from_preset
    from usdfiber.bake.settings import BakeSettings

    shapes = [tuple(int(v) for v in s.split("x")) for s in args.shapes.split(",")]
    schedule = tuple(json.loads(Path(args.schedule).read_text())) if args.schedule else None
    if schedule is None and len({d * n for d, n in shapes}) != 1:
        raise SystemExit("--shapes must hold the same photons (directions x photons)")
    if schedule is not None and len({d for d, _ in shapes}) != 1:
        raise SystemExit("with --schedule, --shapes must have the same directions")
    rows = [int(r) for r in args.rows.split(",")]
    rec = Record("batch_shape", args)
    req = requests_from_preset(args.fiber)[0]
    # Two batches of N per direction; with a schedule, each row's photons in batches of at most N.
    nb = 2 if schedule is None else 4
    base = BakeSettings(resolution_deg=2.0, batches=nb, photons=nb * shapes[0][1], seed=args.seed, incoming="box",
                        estimator=("expected",), row_photons=schedule)
    ctx = {n: baker.bake_context(req.profile(), req.eta, req.beta_deg, req.cuticle_scales,
                                 replace(base, photons=nb * n)) for _, n in shapes}

    def run(shape: tuple[int, int], ti: int, rnd: int) -> float:
        d, n = shape
        c = ctx[n]
        # another phi_i block each round: fresh streams, the same row
        p0 = (rnd * d) % c.grid.n_phi_i
        dirs = [(ti, (p0 + k) % c.grid.n_phi_i) for k in range(d)]
        w0 = time.perf_counter()
        out = baker.trace_directions(c, dirs)
        return 1e9 * (time.perf_counter() - w0) / sum(o["photons"] for o in out)

    for s in shapes:                        # compile each shape's kernels once, untimed
        run(s, rows[0], 0)
    timed: dict[tuple[tuple[int, int], int], list[float]] = {(s, ti): [] for s in shapes for ti in rows}
    for r in range(args.rounds):
        for ti in (rows if r % 2 == 0 else rows[::-1]):
            for s in (shapes if r % 2 == 0 else shapes[::-1]):
                timed[(s, ti)].append(run(s, ti, r + 1))
                print(f"round {r} row {ti} {s[0]}x{s[1]}: {timed[(s, ti)][-1]:6.0f} ns per photon", flush=True)
    out_rows: list[dict[str, Any]] = []
    for ti in rows:
        row: dict[str, Any] = {"row": ti, "theta_i_deg": 2.0 * ti + 1.0}
        if schedule is not None:
            row["photons_per_direction"] = schedule[ti]
            row["batches"] = {f"{d}x{n}": ctx[n].settings.row_batches(ti) for d, n in shapes}
        for s in shapes:
            v = timed[(s, ti)]
            row[f"{s[0]}x{s[1]}"] = {"wall_ns_per_photon": float(np.median(v)), "range": [min(v), max(v)]}
        first = row[f"{shapes[0][0]}x{shapes[0][1]}"]["wall_ns_per_photon"]
        for s in shapes[1:]:
            row[f"{shapes[0][0]}x{shapes[0][1]}_over_{s[0]}x{s[1]}"] = first / row[f"{s[0]}x{s[1]}"]["wall_ns_per_photon"]
        out_rows.append(row)
    print(json.dumps(out_rows, indent=1))
    rec.doc["results"] = {"rows": out_rows}
    rec.finish(Path(args.out))


if __name__ == "__main__":
    main()
