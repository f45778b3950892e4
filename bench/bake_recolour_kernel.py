"""Benchmark: recolouring in the Dr.Jit kernel against the float64 numpy path, up to full 2 deg tables.

    python bench/bake_recolour_kernel.py [--quick]

Writes ``bench/results/recolour_kernel.json`` (``--out`` names another file); what it records and
the error metrics: :mod:`bake_common`.
"""
from __future__ import annotations

import argparse
import gc
import sys
from typing import Any

import numpy as np

from bench_common import Timer, meminfo_gib
from bake_common import Record, bench_parser, model_nbytes, results_path, synthetic_table, table_facts


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
    rec.finish(results_path(args, "recolour_kernel"))
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser(__doc__)
    return cmd_recolour_kernel(ap.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
