"""What a bake spends after its last traced direction: reading the chunks, the reciprocity
averaging, the assembly and the table's save, timed, with the process's memory sampled.

    python bench/bake_assembly_cost.py /tmp/e2e/silk --fiber silk \
        --schedule bench/results/reciprocity_2deg_schedule_silk.json \
        --out bench/results/bake_assembly_cost_silk.json

The directory is a finished scheduled bake's (``bench/reciprocity_2deg.py bake --schedule``,
every chunk present): the baker's resume finds every direction traced, so nothing is traced
and the run is the path from chunks to file, the product's own (``bake_request`` on the
directory, then ``BcsdfTable.save`` to a scratch file next to it). Each mode of ``--checksum``
runs in turn: ``inplace``, today's checksum of the table's arrays, and ``copy``, the former one
(the digest of ``tobytes()``, a copy of each array), for the memory that copy cost. Memory is
the process's anonymous resident set (``RssAnon``), sampled every 0.5 s.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from bake_common import Record
from bench_common import RssSampler
from reciprocity_2deg import settings


def copy_checksum(a: np.ndarray) -> str:
    """The former digest: the same value, through a copy of the array's bytes."""
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()


def timed(owner: Any, name: str, marks: list[tuple[str, float]]) -> Callable[[], None]:
    """Record the start and end of every call of ``owner.name``; returns the undo."""
    f = getattr(owner, name)

    def g(*a: Any, **k: Any) -> Any:
        marks.append((name + " start", time.perf_counter()))
        try:
            return f(*a, **k)
        finally:
            marks.append((name + " end", time.perf_counter()))
    setattr(owner, name, g)
    return lambda: setattr(owner, name, f)


def run(directory: Path, st: Any, fiber: str, checksum: str) -> dict[str, Any]:
    import usdfiber.bake.baker as baker
    import usdfiber.table_format as table_format
    from usdfiber.bake.reciprocity import ReciprocalAverage
    from usdfiber.bake.requests import requests_from_preset

    marks: list[tuple[str, float]] = []
    spent = [0.0]
    digest = table_format.array_checksum if checksum == "inplace" else copy_checksum

    def counted(a: np.ndarray) -> str:
        t = time.perf_counter()
        try:
            return digest(a)
        finally:
            spent[0] += time.perf_counter() - t

    undo = [timed(baker, "assemble", marks), timed(ReciprocalAverage, "finish", marks),
            timed(table_format, "save_npz_atomic", marks)]
    former, table_format.array_checksum = table_format.array_checksum, counted
    out = directory.parent / f".{directory.name}-assembly-cost.npz"
    sampler = RssSampler("RssAnon", period=0.5)
    sampler.start()
    t0 = time.perf_counter()
    try:
        table = baker.bake_request(requests_from_preset(fiber)[0], st, resume_dir=directory)
        marks.append(("bake_request end", time.perf_counter()))
        table.save(out)
        marks.append(("save end", time.perf_counter()))
    finally:
        sampler.stop = True
        sampler.join()
        table_format.array_checksum = former
        for u in undo:
            u()
        out.unlink(missing_ok=True)
    at = dict((k, t - t0) for k, t in marks)
    return {"checksum": checksum,
            "seconds": {"chunks_read_and_added": at["finish start"],
                        "averaging": at["finish end"] - at["finish start"],
                        "assembly": at["assemble end"] - at["assemble start"],
                        "checksums": spent[0],
                        "npz_write": at["save_npz_atomic end"] - at["save_npz_atomic start"],
                        "total": at["save end"]},
            "peak_anon_bytes": int(sampler.peak * 2**20), "peak_at_seconds": sampler.peak_at - t0,
            "table_arrays_bytes": int(sum(a.nbytes for a in table.arrays.values())),
            "checksums_of_table": table.header["checksums"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("directory", type=Path, help="a finished bake --schedule directory (every chunk present)")
    ap.add_argument("--fiber", default="silk")
    ap.add_argument("--seed", type=int, default=2, help="the bake's seed (its chunks' key)")
    ap.add_argument("--schedule", type=Path, required=True, help="the bake's schedule, a JSON list of photons per row")
    ap.add_argument("--per-batch", type=int, default=16384)
    ap.add_argument("--resolution", type=float, default=2.0, help="the bake's resolution, deg (coarser: a smoke run)")
    ap.add_argument("--checksum", default="inplace,copy", help="modes, in order (inplace, copy)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    rec = Record("bake_assembly_cost", args)
    st = settings(10_000, args.seed, args.resolution)
    rows = [int(n) for n in json.loads(args.schedule.read_text())]
    st = replace(st, photons=args.per_batch * st.batches, row_photons=tuple(rows),
                 estimator=("expected", "reciprocity"))
    runs = []
    for mode in args.checksum.split(","):
        r = run(args.directory, st, args.fiber, mode.strip())
        print(json.dumps({k: v for k, v in r.items() if k != "checksums_of_table"}, indent=1))
        runs.append(r)
    same = all(r["checksums_of_table"] == runs[0]["checksums_of_table"] for r in runs)
    rec.doc["results"] = {"runs": runs, "same_table": same}
    rec.finish(args.out)


if __name__ == "__main__":
    main()
