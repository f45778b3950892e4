"""Large fiber stages for ``usdfiber check``: the test suite's 100k-curve runs
(``test_check_cli.py``) and the timings of ``bench/check_bench.py`` (which loads this file by
path) use the same stages.

Two layouts of ``n`` fiber curves: all curves in one BasisCurves prim (how fiber-level cloth
is normally authored) and one prim per curve (the worst case: USD's per-prim cost dominates).
Each can carry seeded errors, so that a run is checked for exactly the problems it must find.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

HEAD = """#usda 1.0
(
    metersPerUnit = 0.001
    upAxis = "Y"
)
"""

#: The depth of shade of the seeded out-of-range fibers (percent; the valid range ends at 10).
BAD_DEPTH_OF_SHADE = 12


def curves_in_one_prim(path: Path, n: int, nan_curve: int | None = None) -> None:
    """``n`` straight 8-point B-spline fibers in one BasisCurves prim at ``/World/Fibers``,
    saved to ``path`` (a ``.usdc`` keeps it small); ``nan_curve``: that curve gets a NaN point
    (one ``PointsNotFinite`` error)."""
    import usdfiber  # noqa: F401  (registers the schemas before any stage exists)
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
    if nan_curve is not None:
        pts[nan_curve, 3] = np.nan
    c.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts.reshape(-1, 3)))
    c.CreateCurveVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(n, 8, np.int32)))
    c.CreateWidthsAttr(Vt.FloatArray([0.018]))
    c.SetWidthsInterpolation(UsdGeom.Tokens.constant)
    stage.Save()


def curves_as_prims(path: Path, n: int, bad_every: int | None = None) -> None:
    """``n`` cotton fibers, one BasisCurves prim each (``/World/F<i>``), written as ``.usda``
    text to ``path``; with ``bad_every``, fibers ``i % bad_every == bad_every - 1`` have an
    out-of-range depth of shade (``n // bad_every`` ``ValueOutOfRange`` errors)."""
    parts = [HEAD, 'def Xform "World"\n{\n']
    body = """    def BasisCurves "F{i}" (
        prepend apiSchemas = ["FiberAPI"]
    )
    {{
        uniform token basis = "bspline"
        int[] curveVertexCounts = [4]
        point3f[] points = [(0, 0, {i}), (1, 1, {i}), (2, 1, {i}), (3, 0, {i})]
        float[] widths = [0.018] (
            interpolation = "constant"
        )
        uniform token fiber:kind = "cotton"
        uniform float fiber:diameter = 18
        token fiber:dye:class = "reactive"
        color3f fiber:dye:extinction = (0.001, 0.012, 0.012)
        float fiber:dye:depthOfShade = {shade}
    }}
"""
    for i in range(n):
        bad = bad_every is not None and i % bad_every == bad_every - 1
        parts.append(body.format(i=i, shade=BAD_DEPTH_OF_SHADE if bad else 1 + (i % 4)))
    parts.append("}\n")
    Path(path).write_text("".join(parts))
