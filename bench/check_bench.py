"""Time ``usdfiber check`` on large stages.

    python bench/check_bench.py [--curves 100000] [--out bench/results/check.json]

Two layouts of the same number of fiber curves: all curves in one BasisCurves prim (how
fiber-level cloth is normally authored) and one prim per curve (the worst case: USD's
per-prim cost dominates). Each run is checked for the exact set of problems seeded into the
stage, so the timing is of a correct result.
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _stages():
    """The stage builders the test suite's 100k-curve runs use (``tests/validation/large_stages.py``,
    loaded by path: the benchmarks do not import the tests as a package)."""
    path = Path(__file__).resolve().parent.parent / "tests" / "validation" / "large_stages.py"
    spec = importlib.util.spec_from_file_location("large_stages", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)  # type: ignore[union-attr]
    return mod


def run_check(path: Path) -> tuple[float, dict]:
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "usdfiber", "check", "--json", str(path)],
                         capture_output=True, text=True)
    wall = time.perf_counter() - t0
    report = json.loads(res.stdout)
    return wall, report


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--curves", type=int, default=100_000)
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "check.json")
    args = ap.parse_args()
    stages = _stages()
    n = args.curves
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        # One seeded error in each stage: a NaN point, an out-of-range depth of shade.
        for layout, make, ext in (("one prim", lambda p: stages.curves_in_one_prim(p, n, nan_curve=n // 2), "usdc"),
                                  ("one prim per curve", lambda p: stages.curves_as_prims(p, n, bad_every=n), "usda")):
            path = Path(tmp) / f"stage.{ext}"
            make(path)
            wall, report = run_check(path)
            problems = report["stages"][0]["problems"]
            codes = sorted({p["code"] for p in problems})
            assert len(problems) == 1, problems  # exactly the seeded error was found
            rows.append({"layout": layout, "curves": args.curves, "seconds": round(wall, 2),
                         "found": codes})
            print(f"{layout:>20}: {args.curves} curves, {wall:6.2f} s  (found {codes})")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    machine = {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
               "python": platform.python_version(), "load": os.getloadavg()}
    args.out.write_text(json.dumps({"machine": machine, "runs": rows}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
