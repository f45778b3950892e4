"""What a bake spends beside its tracer on each group of directions: the statistics of the
group's batches, and writing and reading its resume chunks at each zlib level.

    python bench/chunk_io_cost.py --fiber silk --rows 10,35 \\
        --schedule bench/results/reciprocity_2deg_schedule_silk.json --dir /tmp/chunk-io \\
        --out bench/results/chunk_io_cost_silk.json

One group of directions of each row (the baker's group size) is traced with the scheduled
bake's settings (``reciprocity_2deg.py bake --schedule``: the expected value, box bins,
reciprocity) through ``trace_directions``, the baker's own call: its wall time against the
tracer's own seconds gives the statistics' share. The group's chunks are then written and read
back (``ResumeDirectory.save`` and the verifying ``load``, the product's path) at each
``--levels`` zlib level, in rotating order over ``--rounds``; medians are reported with the
bytes on disk. With ``--table`` (a table file or cache directory), that table is also saved
(``BcsdfTable.save``'s path, ``write_table``) and loaded (the verifying ``read_table``) at each
level.
"""
from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bake_common import Record  # noqa: E402
from reciprocity_2deg import settings  # noqa: E402


def table_io(path: Path, levels: list[int], rounds: int, scratch: Path) -> dict:
    """Seconds to save and load the table at ``path`` at each zlib level (medians of ``rounds``)."""
    from full_bake_2deg import load_table

    from usdfiber import table_format
    from usdfiber.bake.storage import write_table_file

    table, src = load_table(path)
    scratch.mkdir(parents=True, exist_ok=True)
    out: dict[str, Any] = {"source": str(src), "array_bytes": int(sum(a.nbytes for a in table.arrays.values())),
                           "levels": {}}
    times: dict[int, dict[str, list[float]]] = {lv: {"write": [], "read": [], "bytes": []} for lv in levels}
    for r in range(rounds):
        for lv in levels[r % len(levels):] + levels[:r % len(levels)]:
            f = scratch / f"table{lv}.npz"
            t0 = time.perf_counter()
            write_table_file(f, table.header, table.arrays, compress=lv)
            t1 = time.perf_counter()
            table_format.read_table(f)      # every array read and its checksum verified
            t2 = time.perf_counter()
            times[lv]["write"].append(t1 - t0)
            times[lv]["read"].append(t2 - t1)
            times[lv]["bytes"].append(float(f.stat().st_size))
            f.unlink()
    for lv, v in times.items():
        out["levels"][str(lv)] = {"write_s": statistics.median(v["write"]), "read_s": statistics.median(v["read"]),
                                  "bytes": statistics.median(v["bytes"]), "write_all": v["write"], "read_all": v["read"]}
        print(f"table, level {lv}: write {out['levels'][str(lv)]['write_s']:.1f} s, "
              f"read {out['levels'][str(lv)]['read_s']:.1f} s, {out['levels'][str(lv)]['bytes'] / 1e9:.2f} GB", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fiber", default="silk")
    ap.add_argument("--rows", default="10,35", help="theta_i rows (2 deg grid) to trace a group of")
    ap.add_argument("--schedule", type=Path, required=True, help="photons per direction of each row (a JSON list)")
    ap.add_argument("--per-batch", type=int, default=16_384)
    ap.add_argument("--levels", default="6,1,0", help="zlib levels to write the chunks at (0: stored)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--dir", type=Path, required=True, help="scratch directory (emptied)")
    ap.add_argument("--table", type=Path, help="a finished table to save and load at each level")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    from usdfiber.bake.baker import bake_context, resume_fingerprint, trace_directions
    from usdfiber.bake.chunks import ResumeDirectory
    from usdfiber.bake.requests import requests_from_preset
    from usdfiber.bake.settings import directions_per_group

    rec = Record("bake_io_cost", args)
    rows_photons = [int(n) for n in json.loads(args.schedule.read_text())]
    st = settings(args.per_batch * 4, args.seed)
    st = replace(st, row_photons=tuple(rows_photons), estimator=("expected", "reciprocity"))
    req = requests_from_preset(args.fiber)[0]
    profile, eta, beta_deg, cut = req.profile(), req.eta, req.beta_deg, req.cuticle_scales
    shutil.rmtree(args.dir, ignore_errors=True)
    ctx = bake_context(profile, eta, beta_deg, cut, st, args.dir / "ctx")
    fp = resume_fingerprint(ctx, profile)
    group = directions_per_group(st)
    levels = [int(x) for x in args.levels.split(",")]
    out_rows = []
    for row in (int(r) for r in args.rows.split(",")):
        dirs = [(row, pi) for pi in range(group)]
        t0 = time.perf_counter()
        data = trace_directions(ctx, dirs)
        wall = time.perf_counter() - t0
        tracer = sum(float(d["seconds"]) for d in data)
        photons = sum(int(d["photons"]) for d in data)
        io: dict[int, dict[str, list[float]]] = {lv: {"write": [], "read": [], "bytes": []} for lv in levels}
        for r in range(args.rounds):
            for lv in levels[r % len(levels):] + levels[:r % len(levels)]:
                d = args.dir / f"level{lv}"
                shutil.rmtree(d, ignore_errors=True)
                rd = ResumeDirectory(d, fp)
                rd.compress = lv
                t1 = time.perf_counter()
                for (ti, pi), x in zip(dirs, data):
                    rd.save(ti, pi, x)
                t2 = time.perf_counter()
                for ti, pi in dirs:
                    if rd.load(ti, pi) is None:
                        raise SystemExit(f"chunk ({ti}, {pi}) at level {lv} did not load")
                t3 = time.perf_counter()
                io[lv]["write"].append(t2 - t1)
                io[lv]["read"].append(t3 - t2)
                io[lv]["bytes"].append(float(sum(f.stat().st_size for f in d.glob("d*.npz"))))
        res = {"row": row, "directions": len(dirs), "photons": photons, "trace_directions_wall": wall,
               "tracer_seconds": tracer, "statistics_seconds": wall - tracer,
               "raw_bytes": sum(int(x["H"].nbytes + x["G"].nbytes) for x in data),
               "levels": {str(lv): {"write_s": statistics.median(v["write"]), "read_s": statistics.median(v["read"]),
                                    "bytes": statistics.median(v["bytes"]), "write_all": v["write"],
                                    "read_all": v["read"]} for lv, v in io.items()}}
        out_rows.append(res)
        print(f"row {row}: {len(dirs)} directions, {photons / 1e6:.1f}M photons, trace_directions {wall:.1f} s "
              f"(tracer {tracer:.1f} s), raw {res['raw_bytes'] / 1e6:.0f} MB; " + "; ".join(
                  f"level {lv}: write {x['write_s']:.2f} s, read {x['read_s']:.2f} s, {x['bytes'] / 1e6:.0f} MB"
                  for lv, x in res["levels"].items()), flush=True)
    tables = table_io(args.table, levels, args.rounds, args.dir) if args.table else None
    rec.doc["results"] = {"rows": out_rows, "group": group, "table": tables}
    rec.finish(args.out)
    shutil.rmtree(args.dir, ignore_errors=True)


if __name__ == "__main__":
    main()
