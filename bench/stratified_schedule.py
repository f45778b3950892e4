"""Stratified photons on top of the expected value, on full 2 deg tables: each row's variance
per photon against the expected value alone, and a row schedule moved to it.

    python bench/reciprocity_2deg.py bake --fiber silk --seed 0 --photons 10000 --stratified --dir /tmp/box3/silk-0
    python bench/reciprocity_2deg.py bake --fiber silk --seed 1 --photons 10000 --stratified --dir /tmp/box3/silk-1
    python bench/stratified_schedule.py --base /tmp/box2/silk-0 /tmp/box2/silk-1 \\
        --new /tmp/box3/silk-0 /tmp/box3/silk-1 \\
        --schedule bench/results/reciprocity_2deg_schedule_silk_unbiased.json \\
        --schedule-out bench/results/reciprocity_2deg_schedule_silk_stratified.json \\
        --out bench/results/stratified_schedule_silk.json

``--base``: bakes of one full table with the expected value (``reciprocity_2deg.py bake``),
``--new``: the same with ``--stratified`` (the photons' first numbers from scrambled Sobol
points, one scrambling per direction and batch, so that the batches stay independent). Every
chunk holds its direction's relative L2 error of p from the spread of its batches, ``e``, at
``N`` photons; its noise over the table's norm is ``e^2 / (1 - e^2)`` (the norm of a noisy
estimate holds its own noise: ``reciprocity_2deg.py``'s ``e16_unbiased``), so a row's variance
per photon is the mean over its directions and bakes of ``N e^2 / (1 - e^2)``, and the gain at
equal photons is the ratio of the two (with two standard errors from the directions' scatter).
At equal cost per photon (measured side by side in ``row_estimators.py``) that is the gain at
equal error. ``--schedule`` (photons per direction of each row, at each row's 16M-photon error
with the expected value and reciprocity averaging) is divided by it row by row and rounded to
whole batches, as ``reciprocity_2deg.py reschedule`` moves a schedule to other targets; the
averaging mixes a row mostly with its own and its mirror's (a fiber whose light stays near
the specular cone), so the per-row scaling is first-order, to be checked end to end.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bake_common import Record  # noqa: E402


def variance_per_photon(directory: Path) -> np.ndarray:
    """(n_theta_i, n_phi_i) ``N e^2 / (1 - e^2)`` of every direction of a finished bake, from
    its chunks' scalars alone (verified: ``ResumeDirectory.load_scalars``)."""
    from usdfiber.bake.chunks import ResumeDirectory
    from usdfiber.bake.grid import Grid

    fp = json.loads(Path(directory, "bake.json").read_text())
    grid = Grid.from_header(fp["grid"])
    rd = ResumeDirectory(directory, fp)
    out = np.empty((grid.n_theta_i, grid.n_phi_i))
    for ti in range(grid.n_theta_i):
        for pi in range(grid.n_phi_i):
            sc = rd.load_scalars(ti, pi)
            if sc is None:
                raise SystemExit(f"{rd.chunk_path(ti, pi)}: missing or unusable (see the warning): finish the bake first")
            photons, e = sc["photons"], sc["rel_error"]
            if not 0.0 <= e < 1.0:
                raise SystemExit(f"{rd.chunk_path(ti, pi)}: relative error {e} gives no variance")
            out[ti, pi] = photons * e * e / (1.0 - e * e)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", type=Path, nargs="+", required=True, help="bakes with the expected value")
    ap.add_argument("--new", type=Path, nargs="+", required=True, help="the same with --stratified")
    ap.add_argument("--schedule", type=Path, required=True, help="the base's row schedule, a JSON list")
    ap.add_argument("--per-batch", type=int, default=16384)
    ap.add_argument("--rounding", choices=("nearest", "up"), default="nearest")
    ap.add_argument("--schedule-out", type=Path, help="where to write the moved schedule (a JSON list)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    rec = Record("stratified_schedule", args)
    base = np.stack([variance_per_photon(p) for p in args.base])
    new = np.stack([variance_per_photon(p) for p in args.new])
    if base.shape[1:] != new.shape[1:]:
        raise SystemExit(f"the bakes' grids differ: {base.shape[1:]} against {new.shape[1:]}")
    old = np.asarray(json.loads(Path(args.schedule).read_text()), dtype=np.float64)
    if len(old) != base.shape[1]:
        raise SystemExit(f"{args.schedule} has {len(old)} rows, the bakes {base.shape[1]}")
    # Per row: every direction's mean over the bakes, then the rows' means and their scatter.
    vb, vn = base.mean(axis=0), new.mean(axis=0)
    n_pi = vb.shape[1]
    mb, mn = vb.mean(axis=1), vn.mean(axis=1)
    ratio = mb / mn
    se = ratio * np.sqrt((vb.std(axis=1, ddof=1) / mb) ** 2 / n_pi + (vn.std(axis=1, ddof=1) / mn) ** 2 / n_pi)
    rnd = np.ceil if args.rounding == "up" else np.round
    moved = np.maximum(rnd(old / ratio / args.per_batch), 1) * args.per_batch
    out: dict[str, Any] = {
        "rows": [{"row": i, "variance_per_photon_base": float(mb[i]), "variance_per_photon_new": float(mn[i]),
                  "gain_equal_photons": float(ratio[i]), "gain_two_se": float(2 * se[i]),
                  "photons_old": int(old[i]), "photons_new": int(moved[i])} for i in range(len(old))],
        "photons_total_old": float(old.sum() * n_pi), "photons_total_new": float(moved.sum() * n_pi),
        "per_batch": args.per_batch, "rounding": args.rounding,
    }
    out["photons_old_over_new"] = out["photons_total_old"] / out["photons_total_new"]
    if args.schedule_out:
        Path(args.schedule_out).write_text(json.dumps([int(x) for x in moved]) + "\n")
    rec.doc["results"] = out
    rec.finish(args.out)
    print(json.dumps({k: v for k, v in out.items() if k != "rows"}, indent=1))
    for r in out["rows"]:
        print(r["row"], f"{r['gain_equal_photons']:.3f} +- {r['gain_two_se']:.3f}", r["photons_old"], r["photons_new"])


if __name__ == "__main__":
    main()
