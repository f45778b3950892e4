"""Small USD scenes the tests build again and again: a single straight fiber, plain curves, a
perspective camera, a grey card lit by a dome and a key light.

Each builder authors into a stage the caller made (or makes one where named), so tests keep
their own units and prim layout around it.
"""
from __future__ import annotations

from pathlib import Path

import usdfiber  # noqa: F401  (registers schemas first)
from pxr import Gf, Usd, UsdGeom, UsdLux, Vt

from usdfiber import authoring


def single_fiber_stage(path: str | Path, kind: str, dye: str, depth_of_shade: float) -> tuple[Usd.Stage, Usd.Prim]:
    """A new stage in micrometres (Y up) at ``path`` holding one straight 120 um fiber along x
    at the origin, 10 um wide (the curve as wide as the fiber), with preset ``kind`` and ``dye``."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 1e-6)
    UsdGeom.SetStageUpAxis(stage, "Y")
    curves = UsdGeom.BasisCurves.Define(stage, "/World/Fiber")
    curves.CreateTypeAttr("linear")
    curves.CreatePointsAttr(Vt.Vec3fArray([Gf.Vec3f(-60, 0, 0), Gf.Vec3f(60, 0, 0)]))
    curves.CreateCurveVertexCountsAttr(Vt.IntArray([2]))
    curves.CreateWidthsAttr(Vt.FloatArray([10.0]))
    curves.SetWidthsInterpolation("constant")
    authoring.apply_fiber(curves.GetPrim(), kind, dye=dye, depth_of_shade=depth_of_shade)
    return stage, curves.GetPrim()


def straight_curves(stage: Usd.Stage, path: str, width: float) -> Usd.Prim:
    """One plain 4-point curve along x at ``path``, of constant ``width``."""
    c = UsdGeom.BasisCurves.Define(stage, path)
    c.CreateCurveVertexCountsAttr([4])
    c.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (2, 0, 0), (3, 0, 0)])
    c.CreateWidthsAttr([width])
    return c.GetPrim()


def add_side_camera(stage: Usd.Stage, path: str = "/World/Cam") -> UsdGeom.Camera:
    """An orthographic camera 100 um above the single fiber (:func:`single_fiber_stage`),
    looking down -z over 800 x 400 um (2 um per pixel at 400 x 200)."""
    cam = UsdGeom.Camera.Define(stage, path)
    cam.CreateProjectionAttr("orthographic")
    cam.CreateHorizontalApertureAttr(800.0)
    cam.CreateVerticalApertureAttr(400.0)
    cam.AddTranslateOp().Set(Gf.Vec3d(0, 0, 100))
    return cam


def add_camera(stage: Usd.Stage, z: float, path: str = "/Cam") -> UsdGeom.Camera:
    """A 50 mm camera with a square 36 mm aperture (field of view 36/50 across) at height
    ``z`` on the z axis, looking down -z."""
    cam = UsdGeom.Camera.Define(stage, path)
    cam.CreateFocalLengthAttr(50.0)
    cam.CreateHorizontalApertureAttr(36.0)
    cam.CreateVerticalApertureAttr(36.0)
    cam.AddTranslateOp().Set(Gf.Vec3d(0.0, 0.0, z))
    return cam


def add_lit_card(stage: Usd.Stage, half_width: float, card_z: float, camera_z: float) -> None:
    """A grey (0.5) square card of half side ``half_width`` in the plane z = ``card_z``, the
    camera of :func:`add_camera` at ``camera_z`` above it, a dome (0.5) and a key distant
    light (2.0, rotated 35 and 20 degrees about x and y)."""
    card = UsdGeom.Mesh.Define(stage, "/Card")
    h = half_width
    card.CreatePointsAttr(Vt.Vec3fArray([Gf.Vec3f(sx * h, sy * h, card_z)
                                         for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))]))
    card.CreateFaceVertexCountsAttr([4])
    card.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    card.CreateDisplayColorAttr(Vt.Vec3fArray([Gf.Vec3f(0.5, 0.5, 0.5)]))
    add_camera(stage, camera_z)
    UsdLux.DomeLight.Define(stage, "/Sky").CreateIntensityAttr(0.5)
    key = UsdLux.DistantLight.Define(stage, "/Key")
    key.CreateIntensityAttr(2.0)
    key.AddRotateXYZOp().Set(Gf.Vec3f(35.0, 20.0, 0.0))
