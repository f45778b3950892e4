"""Benchmark: the cost probe of ``usdfiber.bake.cost`` (the estimate printed before a bake).

    python bench/bake_cost.py rate [--cases polyester:bake,silk:render] [--rounds 3]
    python bench/bake_cost.py estimates [--before OLD_COST_PY] [--tables fig11:0,silk:15/100000/4,...]
    python bench/bake_cost.py --quick rate; python bench/bake_cost.py --quick estimates   # smoke tests

``rate``: the time of a tracer launch (binning included; wall and process CPU time) against
its size, shaped as the probe shapes its timed launch (:func:`usdfiber.bake.cost.launch_shape`:
the bake's photons per batch, as many directions as make the size, at most a group), up to a
full group (what a bake launches); cases at the default ``usdfiber bake`` settings (2 deg, 1M
photons in 8 batches) or the render's (6 deg, 100k photons in 4 batches). For each size, the
probe's model (:func:`usdfiber.bake.cost.launch_model`: the line through it and the size
below) predicts the full group's launch. Shapes interleaved over ``--rounds`` rounds, so that
every size sees the same load.

``estimates``: for each table, the probe's estimate (time and size on disk, and the probe's
own time) and then the real bake of the table into a fresh cache, side by side in one run;
``--before`` also estimates with another version of ``cost.py`` (a file, e.g. ``git show
HEAD~1:usdfiber/bake/cost.py > /tmp/cost_before.py``), in the same run, just before.
Tables: ``fig11:I`` is the I-th table of ``examples/fig11_threads.usda`` at the render's bake
settings, ``PRESET:DEG`` a preset's first variant at the ``usdfiber bake`` defaults on a DEG
degree grid (``PRESET:DEG/PHOTONS/BATCHES``: with those photons per direction and batches).
The error each bake reached is the table's own estimate (rms and max over its directions).

Writes ``bench/results/cost_rate.json`` or ``bench/results/cost_estimates.json``
(``--out`` names another file); what the record holds: :mod:`bake_common`.
"""
from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from bench_common import Timer, md_table
from bake_common import RESULTS, ROOT, Record, bench_parser

PRESET_OF = {"polyester": "polyester", "silk": "silk", "cotton": "cotton", "wool": "wool"}


def _settings(which: str):
    from usdfiber.bake.settings import RENDER_BAKE_SETTINGS, BakeSettings

    return BakeSettings() if which == "bake" else RENDER_BAKE_SETTINGS


def cmd_rate(args: argparse.Namespace) -> int:
    """Launch time against its size, and the probe's prediction of a full group's launch
    (module docstring)."""
    from usdfiber.bake.baker import bake_context, table_directions, trace_directions
    from usdfiber.bake.cost import launch_model, launch_shape
    from usdfiber.bake.requests import requests_from_preset
    from usdfiber.bake.settings import directions_per_group

    rec = Record("rate", args)
    sizes = [1 << int(e) for e in args.sizes.split(",")]
    results = []
    for case in args.cases.split(","):
        fiber, which = case.split(":")
        req = requests_from_preset(PRESET_OF[fiber])[0]
        st = _settings(which)
        dirs_all = table_directions(req, st)
        full = (min(directions_per_group(st), len(dirs_all)), st.photons_per_batch)
        shapes = sorted({launch_shape(st, len(dirs_all), s) for s in sizes} | {full}, key=lambda km: km[0] * km[1])
        ctx = bake_context(req.profile(), req.eta, req.beta_deg, req.cuticle_scales, replace(st, target_error=None))

        def run(k: int, m: int) -> tuple[float, float]:
            spread = [dirs_all[min(len(dirs_all) - 1, int((j + 0.5) * len(dirs_all) / k))] for j in range(k)]
            c2 = replace(ctx, settings=replace(st, photons=2 * m, batches=2, target_error=None))
            with Timer() as t:
                trace_directions(c2, spread)
            return t.wall / 2, t.cpu / 2

        run(1, 256)                                            # compile, untimed
        times: dict[tuple[int, int], list[tuple[float, float]]] = {s: [] for s in shapes}
        for r in range(args.rounds):
            for s in (shapes if r % 2 == 0 else shapes[::-1]):
                times[s].append(run(*s))
        wall = {s: float(np.median([w for w, _ in v])) for s, v in times.items()}
        cpu = {s: float(np.median([c for _, c in v])) for s, v in times.items()}
        n_full = full[0] * full[1]
        for i, (k, m) in enumerate(shapes):
            e = {"fiber": fiber, "settings": which, "directions": k, "photons_per_direction": m, "photons": k * m,
                 "wall_s": [w for w, _ in times[(k, m)]], "cpu_s": [c for _, c in times[(k, m)]],
                 "full_group": list(full), "full_wall_s": wall[full], "full_cpu_s": cpu[full]}
            if i > 0:
                # The probe's line through this size and the one below it, at a full group.
                lo = shapes[i - 1]
                for name, t in (("wall", wall), ("cpu", cpu)):
                    a, rate = launch_model(lo[0] * lo[1], t[lo], k * m, t[(k, m)])
                    e[f"predicted_full_{name}_s"] = a + n_full / rate
                    e[f"predicted_over_measured_{name}"] = (a + n_full / rate) / t[full]
            results.append(e)
            pred = (f"; line from the size below: full group x{e['predicted_over_measured_wall']:.2f} (wall), "
                    f"x{e['predicted_over_measured_cpu']:.2f} (CPU)") if i > 0 else ""
            print(f"[{fiber} {which}] {k:3d} x {m:7d} = {k * m:8d} photons: wall {wall[(k, m)]:.3f} s, "
                  f"CPU {cpu[(k, m)]:.3f} s ({k * m / cpu[(k, m)] / 1e6:.3f} M/CPU-s){pred}", flush=True)
    rec.doc["results"] = results
    print()
    print(md_table(["fiber", "settings", "launch (directions x photons)", "photons", "wall s", "CPU s",
                    "M photons per CPU-s", "full group from the line to the size below: wall, CPU"],
                   [[e["fiber"], e["settings"], f"{e['directions']} x {e['photons_per_direction']:,}",
                     f"{e['photons']:,}", f"{np.median(e['wall_s']):.3f}", f"{np.median(e['cpu_s']):.3f}",
                     f"{e['photons'] / np.median(e['cpu_s']) / 1e6:.3f}",
                     (f"x{e['predicted_over_measured_wall']:.2f}, x{e['predicted_over_measured_cpu']:.2f}"
                      if "predicted_over_measured_wall" in e else "")] for e in results]))
    rec.finish(args.out or RESULTS / "cost_rate.json")
    return 0


def _load_cost(path: Path) -> Any:
    spec = importlib.util.spec_from_file_location("cost_before", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod           # dataclasses look their module up
    spec.loader.exec_module(mod)  # type: ignore[union-attr]
    return mod


def _tables(spec: str) -> list[tuple[str, Any, Any]]:
    from pxr import Usd

    from usdfiber.bake.requests import requests_from_preset, tables_for_stage
    from usdfiber.bake.settings import RENDER_BAKE_SETTINGS, BakeSettings

    out = []
    fig11 = None
    for item in spec.split(","):
        name, arg = item.split(":", 1)
        if name == "fig11":
            if fig11 is None:
                fig11 = tables_for_stage(Usd.Stage.Open(str(ROOT / "examples" / "fig11_threads.usda")))
            req = fig11[int(arg)]
            out.append((f"fig11 {req.label}", req, RENDER_BAKE_SETTINGS))
        else:
            deg, *rest = arg.split("/")
            st = BakeSettings(resolution_deg=float(deg))
            if rest:
                st = BakeSettings(resolution_deg=float(deg), photons=int(rest[0]), batches=int(rest[1]))
            req = requests_from_preset(name)[0]
            out.append((f"{req.label} at {deg} deg, {st.photons:,} photons in {st.batches} batches", req, st))
    return out


def cmd_estimates(args: argparse.Namespace) -> int:
    """Estimates against real bakes (module docstring)."""
    from usdfiber.bake import cost
    from usdfiber.bake.cache import TableCache

    rec = Record("estimates", args)
    before = _load_cost(args.before) if args.before else None
    results = []
    with tempfile.TemporaryDirectory(prefix="usdfiber-cost-bench-") as tmp:
        for label, req, st in _tables(args.tables):
            row: dict[str, Any] = {"table": label, "settings": st.result_inputs()}
            for name, mod in (("before", before), ("after", cost)):
                if mod is None:
                    continue
                cache = TableCache(Path(tmp) / name)      # a fresh probe
                with Timer() as t:
                    est = mod.estimate_request(req, st, cache)
                row[name] = {"estimate_s": est.seconds, "disk_bytes": est.disk_bytes, "probe_wall_s": t.wall,
                             "probe_cores": t.cores, "directions": est.directions, "photons": est.photons}
                print(f"[{label}] {name}: estimate {est.seconds:.1f} s, {est.disk_bytes / 1e6:.2f} MB; "
                      f"probe {t.wall:.2f} s ({t.cores:.2f} cores)", flush=True)
            load0 = os.getloadavg()[0]
            with Timer() as tb:
                res = TableCache(Path(tmp) / "bake").get_or_bake(req, st)
            err = np.asarray(res.table.rel_error, dtype=np.float64)
            row.update({"bake_s": tb.wall, "bake_cores": tb.cores, "file_bytes": os.path.getsize(res.path),
                        "rel_error_rms": float(np.sqrt(np.mean(err ** 2))), "rel_error_max": float(err.max()),
                        "load_before_bake": round(load0, 2), "load_after_bake": round(os.getloadavg()[0], 2)})
            for name in ("before", "after"):
                if name in row:
                    row[name]["time_ratio"] = row[name]["estimate_s"] / tb.wall
                    row[name]["size_ratio"] = row[name]["disk_bytes"] / row["file_bytes"]
            print(f"[{label}] bake {tb.wall:.1f} s ({tb.cores:.2f} cores), {row['file_bytes'] / 1e6:.2f} MB, "
                  f"rel L2 rms {100 * row['rel_error_rms']:.1f} % / max {100 * row['rel_error_max']:.1f} %; "
                  + "; ".join(f"{n}: estimate / real x{row[n]['time_ratio']:.2f}" for n in ("before", "after")
                              if n in row), flush=True)
            results.append(row)
    rec.doc["results"] = results
    names = [n for n in ("before", "after") if any(n in r for r in results)]
    print()
    print(md_table(["table", "directions", "bake s (cores)", "table rel L2 rms / max"]
                   + [f"{n}: estimate s (x real)" for n in names] + [f"{n}: probe s" for n in names]
                   + [f"{n}: size x file" for n in names] + ["load"],
                   [[r["table"], r["after"]["directions"], f"{r['bake_s']:.1f} ({r['bake_cores']:.2f})",
                     f"{100 * r['rel_error_rms']:.1f} % / {100 * r['rel_error_max']:.1f} %"]
                    + [f"{r[n]['estimate_s']:.1f} (x{r[n]['time_ratio']:.2f})" for n in names]
                    + [f"{r[n]['probe_wall_s']:.2f}" for n in names]
                    + [f"{r[n]['size_ratio']:.3f}" for n in names]
                    + [f"{r['load_before_bake']} -> {r['load_after_bake']}"] for r in results]))
    rec.finish(args.out or RESULTS / "cost_estimates.json")
    return 0


def main() -> int:
    ap = bench_parser(__doc__)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("rate", help="the rate against the timed launch's size")
    r.add_argument("--cases", default="polyester:bake,silk:render",
                   help="FIBER:SETTINGS, SETTINGS bake (2 deg, 1M photons) or render (6 deg, 100k)")
    r.add_argument("--rounds", type=int, default=3)
    r.add_argument("--sizes", default="14,16,17,18,19,20", help="log2 of the timed launch sizes")
    r.set_defaults(func=cmd_rate)
    e = sub.add_parser("estimates", help="estimates against real bakes")
    e.add_argument("--before", type=Path, default=None, help="another cost.py to estimate with, side by side")
    e.add_argument("--tables", default="fig11:0,silk:15/100000/4,cotton:15/100000/4,polyester:2/250000/8")
    e.set_defaults(func=cmd_estimates)
    args = ap.parse_args()
    if args.quick:   # a smoke test, not a benchmark
        args.cases, args.rounds, args.sizes, args.tables = "polyester:render", 1, "16", "polyester:30"
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
