"""Peak memory of tracing one group of directions, against the number of batches per direction.

    python bench/bake_group_memory.py --batches 4,18,54 --out bench/results/bake_group_memory_silk.json

A bake traces its directions in groups (``directions_per_group``: 64 at 2 deg) and keeps each
direction's statistics until the group is written. This script traces one group of a 2 deg silk
table's row (``--row``, default 44: the schedule's grazing row, 54 batches there) with the
scheduled bake's estimators (the expected value, box bins) and few photons per batch
(``--per-batch``: the memory held per batch does not depend on it), each batch count in a fresh
process, and reports the peak anonymous memory (``RssAnon``, sampled every 10 ms) over the
call, less the memory before it. ``--checkouts`` names repository roots whose bakers are
measured side by side (each child imports ``usdfiber`` from its root, ahead of an installed
one); by default, this script's own.

    python bench/bake_group_memory.py --checkouts /tmp/before,. --batches 4,18,54 \
        --out bench/results/bake_group_memory_silk.json

``--table-resolution R`` measures a whole bake instead: a silk table at R deg with the expected
value, box bins and reciprocity averaging (``--per-batch`` photons x 4 batches per direction),
from its first direction to its saved file (``--keep DIR`` holds the chunks and the table), in a
fresh process whose peak resident memory (``VmHWM``: anonymous and file-backed pages) is held
against ``BakeSettings.table_bytes``.

    python bench/bake_group_memory.py --table-resolution 3 --per-batch 4096 --keep /tmp/bake3 \
        --out bench/results/bake_memory_3deg_silk.json
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "bench"))

# A child's first lines: usdfiber from the checkout given, not from an editable install's
# redirecting import hook (which would find this checkout's whatever the path says).
_BOOT = """import sys
sys.meta_path[:] = [f for f in sys.meta_path if 'Redirecting' not in type(f).__name__
                    and 'editable' not in type(f).__module__.lower()]
sys.path[:0] = [{root!r}, {bench!r}]
sys.argv = [{script!r}] + {argv!r}
import runpy
runpy.run_path({script!r}, run_name='__main__')
"""


def child(row: int, batches: int, per_batch: int) -> dict:
    import time

    from bench_common import RssSampler, proc_status_mib

    import usdfiber.bake.baker as baker
    from usdfiber.bake.requests import requests_from_preset
    from usdfiber.bake.settings import BakeSettings, directions_per_group

    rows = [per_batch * batches] * 45
    st = BakeSettings(resolution_deg=2, photons=per_batch * 4, batches=4, seed=2, incoming="box",
                      estimator=("expected",), row_photons=tuple(rows))
    req = requests_from_preset("silk")[0]
    profile, eta, beta, cut = req.profile(), req.eta, req.beta_deg, req.cuticle_scales
    ctx = baker.bake_context(profile, eta, beta, cut, st)
    dirs = [(row, pi) for pi in range(directions_per_group(st))]
    baker.trace_directions(ctx, dirs[:2])              # compile the kernels first
    before = proc_status_mib("RssAnon") or 0.0
    s = RssSampler("RssAnon", period=0.01)
    s.start()
    t0 = time.perf_counter()
    data = baker.trace_directions(ctx, dirs)
    wall = time.perf_counter() - t0
    s.stop = True
    s.join()
    return {"row": row, "batches": batches, "directions": len(dirs), "per_batch": per_batch,
            "baker": str(Path(baker.__file__).resolve()), "rss_anon_before_mib": before,
            "peak_rss_anon_mib": s.peak, "peak_over_before_mib": s.peak - before, "wall_s": wall,
            "photons": int(sum(d["photons"] for d in data))}


def whole_bake(resolution: float, per_batch: int, keep: Path) -> dict:
    """A whole table baked and saved in this process: its peak memory against its bound."""
    import time

    from bench_common import RssSampler, proc_status_mib

    from usdfiber.bake.baker import bake_request
    from usdfiber.bake.requests import requests_from_preset
    from usdfiber.bake.settings import BakeSettings

    st = BakeSettings(resolution_deg=resolution, photons=per_batch * 4, batches=4, seed=2, incoming="box",
                      estimator=("expected", "reciprocity"))
    s = RssSampler("RssAnon", period=0.05)
    s.start()
    t0 = time.perf_counter()
    table = bake_request(requests_from_preset("silk")[0], st, resume_dir=keep / "chunks")
    table.save(keep / "table.npz")
    wall = time.perf_counter() - t0
    s.stop = True
    s.join()
    return {"resolution_deg": resolution, "per_batch": per_batch, "directions": int(table.arrays["photons"].size),
            "wall_s": wall, "table_bytes": st.table_bytes(), "vm_hwm_bytes": int((proc_status_mib("VmHWM") or 0) * 2**20),
            "peak_rss_anon_bytes": int(s.peak * 2**20),
            "table_array_bytes": int(sum(a.nbytes for a in table.arrays.values())), "table": str(keep / "table.npz")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batches", default="4,18,54")
    ap.add_argument("--row", type=int, default=44)
    ap.add_argument("--per-batch", type=int, default=1024)
    ap.add_argument("--checkouts", default=str(ROOT), help="repository roots, comma-separated")
    ap.add_argument("--table-resolution", type=float, help="measure a whole bake at this resolution instead")
    ap.add_argument("--keep", type=Path, help="with --table-resolution: the bake's directory (kept)")
    ap.add_argument("--out", type=Path)
    ap.add_argument("--child", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child is not None:
        print(json.dumps(child(args.row, args.child, args.per_batch)))
        return
    from bake_common import Record

    rec = Record("bake_group_memory", args)
    if args.table_resolution:
        if args.keep is None:
            raise SystemExit("--table-resolution needs --keep DIR")
        r = whole_bake(args.table_resolution, args.per_batch, args.keep)
        print(f"{r['directions']} directions at {r['resolution_deg']:g} deg: VmHWM {r['vm_hwm_bytes'] / 1e9:.2f} GB "
              f"(anonymous {r['peak_rss_anon_bytes'] / 1e9:.2f} GB) against table_bytes {r['table_bytes'] / 1e9:.2f} GB "
              f"({r['wall_s']:.0f} s)", flush=True)
        if args.out:
            rec.doc["results"] = {"whole_bake": r}
            rec.finish(args.out)
        return
    runs = []
    for b in (int(x) for x in args.batches.split(",")):
        for root in (str(Path(c).resolve()) for c in args.checkouts.split(",")):
            boot = _BOOT.format(root=root, bench=str(ROOT / "bench"), script=str(Path(__file__).resolve()),
                                argv=["--child", str(b), "--row", str(args.row), "--per-batch", str(args.per_batch)])
            out = subprocess.run([sys.executable, "-c", boot], capture_output=True, text=True)
            if out.returncode != 0:
                raise SystemExit(f"{root}, {b} batches: {out.stderr[-2000:]}")
            r = json.loads(out.stdout.strip().splitlines()[-1])
            r["checkout"] = root
            print(f"{b} batches, {root}: peak {r['peak_over_before_mib']:.0f} MiB over "
                  f"{r['rss_anon_before_mib']:.0f} MiB ({r['wall_s']:.1f} s; {r['baker']})", flush=True)
            runs.append(r)
    if args.out:
        rec.doc["results"] = {"runs": runs}
        rec.finish(args.out)


if __name__ == "__main__":
    main()
