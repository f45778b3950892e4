"""Benchmark: baking at render settings, directions traced together vs one at a time.

    python bench/bake_grouping.py [--fibers silk,cotton] [--sample 24] [--quick]

Writes ``bench/results/grouping.json`` (``--out`` names another file); what it records and
the error metrics: :mod:`bake_common`.
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np

from bench_common import Timer, md_table
from bake_common import RESULTS, Record, bench_parser, fiber_case


def cmd_grouping(args: argparse.Namespace) -> int:
    """Directions traced together vs one at a time, at the renderer's bake settings.

    Per fiber: a sample of incoming directions is traced both ways (``baker.trace_directions``
    with all of them, and with one at a time, which is how every direction was traced before
    grouping); both must give identical histograms. Then the whole table is baked with the
    default grouping. The table's own error estimate is the error the time was reached at.
    """
    from usdfiber.bake import baker
    from usdfiber.bake.settings import BakeSettings
    from usdfiber.translators.mitsuba.scene import RENDER_BAKE_SETTINGS

    rec = Record("grouping", args)
    st = RENDER_BAKE_SETTINGS if not args.quick else BakeSettings(resolution_deg=30, photons=4000, batches=4)
    if args.resolution:
        st = BakeSettings(resolution_deg=args.resolution, photons=st.photons, batches=st.batches)
    rec.doc["bake_settings"] = st.result_inputs()
    results = []
    for kind in args.fibers.split(","):
        case = fiber_case("wool-cuticle" if kind == "wool" else kind)
        prof, cut = case["profile"], case["cuticle"]
        ctx = baker.bake_context(prof, case["eta"], case["beta_deg"], cut, st)
        g = ctx.grid
        dirs = [(ti, pi) for ti in range(g.n_theta_i) for pi in range(g.n_phi_i)]
        step = max(1, len(dirs) // args.sample)
        sample = dirs[::step][:args.sample]
        baker.trace_directions(ctx, sample[:2])          # compile the kernel once, untimed
        with Timer() as ta:
            alone = [baker.trace_directions(ctx, [d])[0] for d in sample]
        with Timer() as tg:
            grouped = baker.trace_directions(ctx, sample)
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


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser(__doc__)
    ap.add_argument("--fibers", default="polyester,silk,cotton,mercerizedCotton,wool",
                    help="presets (wool with its cuticle scales)")
    ap.add_argument("--sample", type=int, default=24, help="directions traced both ways per fiber")
    ap.add_argument("--resolution", type=float, default=None, help="override the render bake resolution (deg)")
    return cmd_grouping(ap.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
