"""Benchmark: whole table bakes with the plain and the expected-value estimator, side by side.

The per-direction comparison of ``bake_estimators.py`` times one direction per call; a bake
traces many directions per launch, with the baker's grouping, tail phases and binning. This
bakes real tables of a preset's first cross-section variant through the cache, alternating the
two estimators, and reports each bake's process CPU time and the table's own error estimate
(the spread of its independent batches, relative L2 of p per direction: rms, 95th percentile
and max over the directions). gain = (cpu_plain x e_plain^2) / (cpu_expected x e_expected^2)
for the rms and for the max. ``--variants`` chooses the bakes: plain, and the expected value
with its normals shared uniformly (K per event) or adaptively (1 to K per event, the default),
drawn from the normal distribution and weighted by visibility (the default) or from the visible
normals (``NAME/visible``).

    python bench/bake_estimator_bakes.py --out bench/results/estimator_bakes.json
    python bench/bake_estimator_bakes.py --cases silk:15:100000:15000 --rounds 1 --out /tmp/x.json
    python bench/bake_estimator_bakes.py --variants plain,uniform,adaptive --cases silk:6:100000:15000 \
        --out bench/results/estimator_bakes_allocation.json
    python bench/bake_estimator_bakes.py --variants plain,adaptive/visible@16,adaptive@16,adaptive@32 \
        --cases silk:2:1000000:200000:30 --out /tmp/x.json
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bake_common import Record  # noqa: E402


def bake(fiber: str, resolution: float, photons: int, expected: int, root: str,
         allocation: str = "uniform", incoming: float | None = None, sampler: str = "ndf") -> dict:
    """One bake of the preset's first variant into an empty cache under ``root``."""
    from usdfiber.bake.cache import TableCache
    from usdfiber.bake.requests import requests_from_preset
    from usdfiber.bake.settings import BakeSettings

    kw: dict = dict(resolution_deg=resolution, photons=photons, batches=4, incoming_deg=incoming)
    if expected:
        kw.update(estimator=("expected",), expected_normals=expected, expected_allocation=allocation,
                  expected_sampler=sampler)
    req = requests_from_preset(fiber)[0]
    c0, w0 = time.process_time(), time.perf_counter()
    res = TableCache(tempfile.mkdtemp(dir=root)).get_or_bake(req, BakeSettings(**kw))
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    rel = np.asarray(res.table.arrays["rel_error"], dtype=np.float64).ravel()
    rel = rel[np.isfinite(rel) & (rel > 0)]
    return {"fiber": fiber, "resolution_deg": resolution, "incoming_deg": incoming, "photons": photons,
            "expected_normals": expected,
            "variant": allocation if expected else "plain",
            "cpu": cpu, "wall": wall, "rel_rms": float(np.sqrt(np.mean(rel ** 2))),
            "rel_p95": float(np.percentile(rel, 95)), "rel_max": float(rel.max()), "directions": int(rel.size)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="polyester:2:100000:15000,silk:15:100000:15000,silk:6:100000:15000",
                    help="FIBER:RESOLUTION:PLAIN_PHOTONS:EXPECTED_PHOTONS[:INCOMING_DEG], comma separated "
                         "(INCOMING_DEG: coarser incoming nodes, fewer directions on the same bins)")
    ap.add_argument("--normals", type=int, default=8, help="K of the expected-value estimator")
    ap.add_argument("--rounds", type=int, default=1, help="alternating rounds of the bakes")
    ap.add_argument("--variants", default="plain,uniform",
                    help="bakes of each case, alternating: plain, uniform, adaptive (comma separated; "
                         "NAME@K: K normals instead of --normals; NAME/visible: visible normals)")
    ap.add_argument("--out", default="bench/results/estimator_bakes.json")
    args = ap.parse_args()
    rec = Record("estimator_bakes", args)
    rows = []
    with tempfile.TemporaryDirectory() as root:
        variants = args.variants.split(",")
        def normals(v: str) -> tuple[str, int, str]:
            name, _, k = v.partition("@")
            name, _, sampler = name.partition("/")
            return name, 0 if name == "plain" else int(k or args.normals), sampler or "ndf"

        for v in variants:                                        # compile the kernels first
            name, k, sampler = normals(v)
            bake("polyester", 30.0, 1000, k, root, name, sampler=sampler)
        for case in args.cases.split(","):
            fiber, res, n_plain, n_ev, *inc = case.split(":")
            for r in range(args.rounds):
                for v in variants:
                    name, k, sampler = normals(v)
                    n = int(n_plain) if name == "plain" else int(n_ev)
                    row = bake(fiber, float(res), n, k, root, name, float(inc[0]) if inc else None, sampler)
                    row["variant"] = v
                    row["round"] = r
                    row["load"] = [round(x, 2) for x in os.getloadavg()]
                    rows.append(row)
                    print(json.dumps(row), flush=True)
    out = []
    for case in args.cases.split(","):
        fiber, res, _, _, *inc = case.split(":")
        sel = [x for x in rows if x["fiber"] == fiber and x["resolution_deg"] == float(res)
               and x["incoming_deg"] == (float(inc[0]) if inc else None)]
        by = {v: [x for x in sel if x["variant"] == v] for v in variants}
        cpu = {v: float(np.median([x["cpu"] for x in xs])) for v, xs in by.items()}
        rms = {v: float(np.sqrt(np.mean([x["rel_rms"] ** 2 for x in xs]))) for v, xs in by.items()}
        mx = {v: float(np.max([x["rel_max"] for x in xs])) for v, xs in by.items()}
        base = variants[0]
        summary = {"fiber": fiber, "resolution_deg": float(res), "incoming_deg": float(inc[0]) if inc else None,
                   "baseline": base, "cpu": cpu, "rel_rms": rms,
                   "rel_max": mx,
                   "gain_rms": {v: cpu[base] * rms[base] ** 2 / (cpu[v] * rms[v] ** 2) for v in variants},
                   "gain_max": {v: cpu[base] * mx[base] ** 2 / (cpu[v] * mx[v] ** 2) for v in variants}}
        out.append(summary)
        print(f"{fiber} {res} deg{' / ' + inc[0] if inc else ''}: " + "; ".join(
            f"{v} {cpu[v]:.1f} s cpu at {100 * rms[v]:.2f} % rms, gain {summary['gain_rms'][v]:.2f} (rms) "
            f"{summary['gain_max'][v]:.2f} (max)" for v in variants), flush=True)
    rec.doc["results"] = {"bakes": rows, "summary": out}
    rec.finish(Path(args.out))


if __name__ == "__main__":
    main()
