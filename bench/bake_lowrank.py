"""Benchmark: is a table low-rank over its incoming directions? (a compression study)

    python bench/bake_lowrank.py [--fiber silk] [--resolution 10] [--photons 800000] [--quick]

Writes ``bench/results/lowrank.json`` (``--out`` names another file); what it records and
the error metrics: :mod:`bake_common`.
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from bench_common import Timer, md_table
from bake_common import RESULTS, Record, bench_parser, fiber_case


def _banded(table, k: int, relative_phi: bool) -> tuple[np.ndarray, np.ndarray]:
    """p at level k as (n_ti, n_pi, band x n_po) in band rows (aligned with -theta_i), and
    the solid angles of its bins; with ``relative_phi``, phi_o measured from phi_i."""
    p = table.level_p(k).astype(np.float64)
    d = table.domega_band()
    n_ti, n_pi, nb, n_po = p.shape
    if relative_phi:
        step = n_po // n_pi
        for j in range(n_pi):
            p[:, j] = np.roll(p[:, j], -j * step, axis=-1)
    w = np.repeat(d[..., None], n_po, axis=-1)
    return p.reshape(n_ti, n_pi, nb * n_po), w.reshape(n_ti, n_pi, nb * n_po)


def _rms_rel_l2(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> float:
    e = np.sqrt(((x - y) ** 2 * w).sum(-1) / (y ** 2 * w).sum(-1))
    return float(np.sqrt(np.mean(e ** 2)))


def cmd_lowrank(args: argparse.Namespace) -> int:
    """Is a table low-rank over its incoming directions? (a compression candidate)

    Two tables of the same fiber are baked with independent seeds (noise about 1 %). Each
    level's p, in band rows (aligned with the specular cone) and optionally with phi_o taken
    from phi_i, is approximated by a truncated SVD (weighted by solid angle), over all
    directions or per theta_i over phi_i. The rank-r table is compared with itself (what
    truncation loses) and with the independent table (against which plain noise scores
    sqrt(2) x the table's own): a compression must lose less than about 1 %.
    """
    from usdfiber.bake.baker import bake_table
    from usdfiber.bake.settings import BakeSettings

    rec = Record("lowrank", args)
    res, photons = (30.0, 20000) if args.quick else (args.resolution, args.photons)
    case = fiber_case(args.fiber)
    tabs = []
    for seed in (0, 1):
        st = BakeSettings(resolution_deg=res, photons=photons, batches=8, seed=seed)
        with Timer() as t:
            tabs.append(bake_table(case["profile"], case["eta"], case["beta_deg"], case["cuticle"], st))
        err = tabs[-1].rel_error.astype(np.float64)
        print(f"[{args.fiber}] seed {seed}: {res:g} deg, {photons} photons/direction in {t.wall:.0f} s "
              f"({t.cores:.2f} cores), rel L2 rms {100 * np.sqrt(np.mean(err ** 2)):.2f} %", flush=True)
    A, B = tabs
    rows = []
    for k in args.levels:
        for rel in (False, True):
            a, w = _banded(A, k, rel)
            b, _ = _banded(B, k, rel)
            n_ti, n_pi, nc = a.shape
            noise = _rms_rel_l2(a, b, w)
            for mode in ("all directions", "per theta_i"):
                for r in args.ranks:
                    if mode == "all directions":
                        x = (a * np.sqrt(w)).reshape(n_ti * n_pi, nc)
                        u, sv, vt = np.linalg.svd(x, full_matrices=False)
                        ar = ((u[:, :r] * sv[:r]) @ vt[:r]).reshape(a.shape) / np.sqrt(w)
                        ratio = n_ti * n_pi * nc / (r * (n_ti * n_pi + nc))
                    else:
                        ar = np.empty_like(a)
                        for i in range(n_ti):
                            u, sv, vt = np.linalg.svd(a[i] * np.sqrt(w[i]), full_matrices=False)
                            ar[i] = ((u[:, :r] * sv[:r]) @ vt[:r]) / np.sqrt(w[i])
                        ratio = n_pi * nc / (r * (n_pi + nc))
                    rows.append({"level": k, "phi_o_from_phi_i": rel, "mode": mode, "rank": r,
                                 "size_ratio": ratio, "loss_vs_itself": _rms_rel_l2(ar, a, w),
                                 "vs_independent": _rms_rel_l2(ar, b, w), "independent_noise": noise})
    rec.doc["tables"] = [{"seed": s, "rel_error_rms": float(np.sqrt(np.mean(t.rel_error.astype(np.float64) ** 2))),
                          "shape": list(t.arrays["p"].shape)} for s, t in zip((0, 1), tabs)]
    rec.doc["results"] = rows
    print(md_table(["level", "phi_o from phi_i", "SVD over", "rank", "smaller by", "lost (vs itself)",
                    "vs independent table", "independent tables differ by"],
                    [[r["level"], r["phi_o_from_phi_i"], r["mode"], r["rank"], f"{r['size_ratio']:.1f}x",
                     f"{100 * r['loss_vs_itself']:.2f}%", f"{100 * r['vs_independent']:.2f}%",
                     f"{100 * r['independent_noise']:.2f}%"] for r in rows]))
    rec.finish(args.out or RESULTS / "lowrank.json")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser(__doc__)
    ap.add_argument("--fiber", default="silk")
    ap.add_argument("--resolution", type=float, default=10.0)
    ap.add_argument("--photons", type=int, default=800_000, help="photons per direction (about 1 %% noise for silk at 10 deg)")
    ap.add_argument("--levels", type=lambda t: [int(x) for x in t.split(",")], default=[0, 8])
    ap.add_argument("--ranks", type=lambda t: [int(x) for x in t.split(",")], default=[4, 8, 16, 32])
    return cmd_lowrank(ap.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
