"""Write the example stages (fibers.usda, threads.usda, demo.usda) with usdfiber's authoring API.

    python examples/make_examples.py [OUTPUT_DIR]

Scene units are millimetres (metersPerUnit = 0.001), Y up. Fiber curves are uniform cubic
B-splines whose width is the fiber diameter; thread curves are yarn centre lines whose
width is the yarn diameter (touching circular plies, see usdfiber.presets).
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

try:
    import usdfiber  # noqa: F401  (registers the schema plugin before any stage is made)
except ImportError:  # running from a source checkout without an install
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    import usdfiber  # noqa: F401

from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdShade, Vt

from usdfiber import authoring as A
from usdfiber.presets import FIBER_PRESETS, YARN_PRESETS

MM_PER_UM = 1e-3
CLASS_ROOT = "/_fiberClasses"


def new_stage(doc: str, default: str) -> Usd.Stage:
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    stage.GetRootLayer().documentation = doc
    root = UsdGeom.Xform.Define(stage, default).GetPrim()
    stage.SetDefaultPrim(root)
    return stage


def _fiber_curves(stage: Usd.Stage, path: str, count: int, z0: float, diameter_um: float,
                  length_mm: float = 1.0, points_per_curve: int = 6, wave_mm: float = 0.01) -> Usd.Prim:
    """``count`` gently waving parallel fibers along +x, spaced three diameters apart in z."""
    curves = UsdGeom.BasisCurves.Define(stage, path)
    curves.CreateTypeAttr(UsdGeom.Tokens.cubic)
    curves.CreateBasisAttr(UsdGeom.Tokens.bspline)
    curves.CreateWrapAttr(UsdGeom.Tokens.nonperiodic)
    width = diameter_um * MM_PER_UM
    pts = []
    for i in range(count):
        z = z0 + i * 3 * width
        for j in range(points_per_curve):
            x = length_mm * j / (points_per_curve - 1)
            y = wave_mm * math.sin(2 * math.pi * x / length_mm + i)
            pts.append(Gf.Vec3f(x, y, z))
    curves.CreatePointsAttr(Vt.Vec3fArray(pts))
    curves.CreateCurveVertexCountsAttr(Vt.IntArray([points_per_curve] * count))
    curves.CreateWidthsAttr(Vt.FloatArray([width]))
    curves.SetWidthsInterpolation(UsdGeom.Tokens.constant)
    curves.CreateExtentAttr(UsdGeom.Curves.ComputeExtent(curves.GetPointsAttr().Get(),
                                                         curves.GetWidthsAttr().Get()))
    return curves.GetPrim()


def make_fibers(out: Path) -> Path:
    stage = new_stage(
        "Textile fibers of the five built-in kinds (Aliaga et al. 2017, Table 1). Each kind is a "
        "class prim with FiberAPI inherited by its fiber curves; cotton carries a depth-of-shade "
        "variant set; one fiber uses a user-drawn cross section. Units: mm.",
        "/Fibers")
    dyes = {"polyester": "disperseBlue", "silk": "reactiveOrange", "cotton": "reactiveRed",
            "mercerizedCotton": "reactiveRed", "wool": "reactiveGreen"}
    classes = {}
    for kind in FIBER_PRESETS:
        cls_path = f"{CLASS_ROOT}/{kind[0].upper()}{kind[1:]}"
        classes[kind] = A.define_fiber_class(stage, cls_path, kind, dye=dyes[kind], depth_of_shade=1.0)
    A.add_depth_of_shade_variants(classes["cotton"], {"pale": 0.1, "medium": 1.0, "deep": 4.0},
                                  default="medium")

    z = 0.0
    for kind, preset in FIBER_PRESETS.items():
        prim = _fiber_curves(stage, f"/Fibers/{kind[0].upper()}{kind[1:]}", 8, z, preset.diameter_um)
        A.inherit(prim, classes[kind].GetPath())
        z += 8 * 3 * preset.diameter_um * MM_PER_UM + 0.05

    # A per-prim override wins over the class: a deep shade picked from the variant set.
    deep = _fiber_curves(stage, "/Fibers/CottonDeep", 4, z, FIBER_PRESETS["cotton"].diameter_um)
    A.inherit(deep, classes["cotton"].GetPath())
    deep.GetVariantSet("depthOfShade").SetVariantSelection("deep")
    z += 4 * 3 * FIBER_PRESETS["cotton"].diameter_um * MM_PER_UM + 0.05

    # A finer silk: diameter overridden per prim; its width follows.
    fine = _fiber_curves(stage, "/Fibers/SilkFine", 4, z, 6.0)
    A.inherit(fine, classes["silk"].GetPath())
    A.apply_fiber(fine, None, diameter=6.0)
    z += 4 * 3 * 6.0 * MM_PER_UM + 0.05

    # A user cross section (a bean with its lumen, um), used by one fiber.
    outer = [(9.0 * math.cos(t), 4.5 * math.sin(t) - 1.2 * math.cos(2 * t) + 1.2)
             for t in (2 * math.pi * k / 24 for k in range(24))]
    lumen = [(3.0 * math.cos(t), 0.8 * math.sin(t) + 0.6) for t in (2 * math.pi * k / 12 for k in range(12))]
    A.define_profile(stage, "/Fibers/Profiles/CottonBean", [outer, lumen], smooth=True)
    user = _fiber_curves(stage, "/Fibers/CottonUserSection", 1, z, FIBER_PRESETS["cotton"].diameter_um)
    A.inherit(user, classes["cotton"].GetPath())
    A.set_profile_sources(user, ["/Fibers/Profiles/CottonBean"])

    path = out / "fibers.usda"
    stage.GetRootLayer().Export(str(path))
    return path


def _yarn_curve(stage: Usd.Stage, path: str, z: float, diameter_mm: float,
                length_mm: float = 10.0, n: int = 12) -> Usd.Prim:
    """One gently arched yarn centre line along +x (uniform cubic B-spline, vertex widths)."""
    curves = UsdGeom.BasisCurves.Define(stage, path)
    curves.CreateTypeAttr(UsdGeom.Tokens.cubic)
    curves.CreateBasisAttr(UsdGeom.Tokens.bspline)
    curves.CreateWrapAttr(UsdGeom.Tokens.nonperiodic)
    pts = [Gf.Vec3f(length_mm * j / (n - 1), 0.4 * math.sin(math.pi * j / (n - 1)), z) for j in range(n)]
    curves.CreatePointsAttr(Vt.Vec3fArray(pts))
    curves.CreateCurveVertexCountsAttr(Vt.IntArray([n]))
    curves.CreateWidthsAttr(Vt.FloatArray([diameter_mm] * n))
    curves.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
    curves.CreateExtentAttr(UsdGeom.Curves.ComputeExtent(curves.GetPointsAttr().Get(),
                                                         curves.GetWidthsAttr().Get()))
    return curves.GetPrim()


def make_threads(out: Path) -> Path:
    stage = new_stage(
        "The four Guetermann sewing threads of Aliaga et al. 2017, Table 3, as yarn centre "
        "lines with FiberYarnAPI and FiberAPI; widths are the yarn diameters. Units: mm.",
        "/Threads")
    dyes = {"Skala 360": ("disperseRed", 1.0), "ORA 120": ("disperseBlue", 2.0),
            "CNe 50": ("reactiveGreen", 1.5), "S 303": ("reactiveOrange", 0.5)}
    z = 0.0
    for name, yp in YARN_PRESETS.items():
        prim_name = name.replace(" ", "")
        prim = _yarn_curve(stage, f"/Threads/{prim_name}", z, yp.yarn_diameter_mm)
        dye, dos = dyes[name]
        A.apply_yarn(prim, name, dye=dye, depth_of_shade=dos)
        z += 1.0
    path = out / "threads.usda"
    stage.GetRootLayer().Export(str(path))
    return path


def make_demo(out: Path) -> Path:
    """The demo render: three tufts of dyed polyester fibers on a grey card, one camera,
    a dome and a key light. Polyester's round cross section bakes in seconds."""
    stage = new_stage(
        "Demo: tufts of polyester fibers dyed with disperse red, yellow and blue at three depths "
        "of shade (Aliaga et al. 2017, Section 3.1), lying on a grey card. "
        "Render: usdfiber render examples/demo.usda -o demo.exr. Units: mm.",
        "/Demo")
    cls = A.define_fiber_class(stage, f"{CLASS_ROOT}/Polyester", "polyester")
    d_mm = FIBER_PRESETS["polyester"].diameter_um * MM_PER_UM
    tufts = [("Red", "disperseRed", 0.5, -0.35), ("Yellow", "disperseYellow", 1.0, 0.0),
             ("Blue", "disperseBlue", 2.0, 0.35)]
    for name, dye, dos, z0 in tufts:
        curves = UsdGeom.BasisCurves.Define(stage, f"/Demo/Tuft{name}")
        curves.CreateTypeAttr(UsdGeom.Tokens.cubic)
        curves.CreateBasisAttr(UsdGeom.Tokens.bspline)
        n_fib, n_pts = 48, 8
        pts = []
        for i in range(n_fib):
            # Fibers fan out from a bundle: a deterministic spread in z and height, gentle waves.
            u = (i + 0.5) / n_fib
            z = z0 + 0.22 * (u - 0.5) + 0.01 * math.sin(37.0 * u)
            y = d_mm * (1.0 + 3.0 * abs(math.sin(13.0 * u)))
            for j in range(n_pts):
                x = -0.9 + 1.8 * j / (n_pts - 1)
                pts.append(Gf.Vec3f(x, y + 0.012 * math.sin(3.0 * x + 5.0 * u), z + 0.03 * math.sin(2.0 * x + 9.0 * u)))
        curves.CreatePointsAttr(Vt.Vec3fArray(pts))
        curves.CreateCurveVertexCountsAttr(Vt.IntArray([n_pts] * n_fib))
        curves.CreateWidthsAttr(Vt.FloatArray([d_mm]))
        curves.SetWidthsInterpolation(UsdGeom.Tokens.constant)
        curves.CreateExtentAttr(UsdGeom.Curves.ComputeExtent(curves.GetPointsAttr().Get(),
                                                             curves.GetWidthsAttr().Get()))
        A.inherit(curves.GetPrim(), cls.GetPath())
        A.apply_fiber(curves.GetPrim(), None, dye=dye, depth_of_shade=dos)

    # A grey card under the fibers (UsdPreviewSurface).
    card = UsdGeom.Mesh.Define(stage, "/Demo/Card")
    card.CreatePointsAttr([(-1.5, 0.0, -1.0), (1.5, 0.0, -1.0), (1.5, 0.0, 1.0), (-1.5, 0.0, 1.0)])
    card.CreateFaceVertexCountsAttr([4])
    card.CreateFaceVertexIndicesAttr([0, 3, 2, 1])
    card.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    card.CreateExtentAttr([(-1.5, 0.0, -1.0), (1.5, 0.0, 1.0)])
    mat = UsdShade.Material.Define(stage, "/Demo/Looks/Card")
    sh = UsdShade.Shader.Define(stage, "/Demo/Looks/Card/Surface")
    sh.CreateIdAttr("UsdPreviewSurface")
    sh.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0.35, 0.35, 0.35))
    sh.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.8)
    mat.CreateSurfaceOutput().ConnectToSource(sh.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(card.GetPrim()).Bind(mat)

    cam = UsdGeom.Camera.Define(stage, "/Demo/Camera")
    cam.CreateFocalLengthAttr(50.0)
    cam.CreateHorizontalApertureAttr(36.0)
    cam.CreateVerticalApertureAttr(20.25)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.1, 100.0))
    eye, target = Gf.Vec3d(0.0, 1.6, 3.2), Gf.Vec3d(0.0, 0.0, 0.0)
    view = Gf.Matrix4d().SetLookAt(eye, target, Gf.Vec3d(0.0, 1.0, 0.0))
    cam.AddTransformOp().Set(view.GetInverse())

    dome = UsdLux.DomeLight.Define(stage, "/Demo/Lights/Sky")
    dome.CreateIntensityAttr(0.4)
    key = UsdLux.DistantLight.Define(stage, "/Demo/Lights/Key")
    key.CreateIntensityAttr(2.5)
    key.CreateAngleAttr(0.0)
    # Distant lights shine along their -Z: aim from the upper left front.
    aim = Gf.Matrix4d().SetLookAt(Gf.Vec3d(-1.0, 2.0, 1.5), Gf.Vec3d(0.0, 0.0, 0.0), Gf.Vec3d(0.0, 1.0, 0.0))
    UsdGeom.Xformable(key.GetPrim()).AddTransformOp().Set(aim.GetInverse())

    path = out / "demo.usda"
    stage.GetRootLayer().Export(str(path))
    return path


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    out = Path(argv[0]) if argv else Path(__file__).resolve().parent
    out.mkdir(parents=True, exist_ok=True)
    for p in (make_fibers(out), make_threads(out), make_demo(out)):
        print(p)
    return 0


if __name__ == "__main__":
    sys.exit(main())
