"""Time ``usdfiber check`` on large stages.

    python bench/check_bench.py [--curves 100000] [--out bench/results/check.json]

Two layouts of the same number of fiber curves: all curves in one BasisCurves prim (how
fiber-level cloth is normally authored) and one prim per curve (the worst case: USD's
per-prim cost dominates). Each run is checked for the exact set of problems seeded into the
stage, so the timing is of a correct result.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def one_prim_stage(path: Path, n: int) -> None:
    import usdfiber  # noqa: F401
    from pxr import Usd, UsdGeom, Vt

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    c = UsdGeom.BasisCurves.Define(stage, "/World/Fibers")
    c.GetPrim().ApplyAPI("FiberAPI")
    c.GetPrim().GetAttribute("fiber:diameter").Set(18.0)
    c.CreateBasisAttr("bspline")
    rng = np.random.default_rng(1)
    base = rng.uniform(-10, 10, (n, 1, 3)).astype(np.float32)
    pts = base + np.linspace(0, 1, 8, dtype=np.float32)[None, :, None] * np.float32([0, 5, 0])
    pts[n // 2, 3] = np.nan  # one seeded error
    c.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts.reshape(-1, 3)))
    c.CreateCurveVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(n, 8, np.int32)))
    c.CreateWidthsAttr(Vt.FloatArray([0.018]))
    c.SetWidthsInterpolation(UsdGeom.Tokens.constant)
    stage.Save()


def many_prims_stage(path: Path, n: int) -> None:
    parts = ['#usda 1.0\n(\n    metersPerUnit = 0.001\n)\ndef Xform "World"\n{\n']
    body = """    def BasisCurves "F{i}" (prepend apiSchemas = ["FiberAPI"])
    {{
        uniform token basis = "bspline"
        int[] curveVertexCounts = [4]
        point3f[] points = [(0, 0, {i}), (1, 1, {i}), (2, 1, {i}), (3, 0, {i})]
        float[] widths = [0.018] (interpolation = "constant")
        uniform float fiber:diameter = 18
        float fiber:dye:depthOfShade = {shade}
        token fiber:dye:class = "reactive"
    }}
"""
    for i in range(n):
        parts.append(body.format(i=i, shade=12 if i == n // 2 else 1 + i % 4))  # one seeded error
    parts.append("}\n")
    path.write_text("".join(parts))


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
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for layout, make, ext in (("one prim", one_prim_stage, "usdc"),
                                  ("one prim per curve", many_prims_stage, "usda")):
            path = Path(tmp) / f"stage.{ext}"
            make(path, args.curves)
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
