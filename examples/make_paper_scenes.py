"""Write example stages that follow the figures of Aliaga et al. 2017 (EGSR, "An Appearance
Model for Textile Fibers") with usdfiber's authoring API and cloth generators.

    python examples/make_paper_scenes.py [OUTPUT_DIR]

Writes into OUTPUT_DIR (default: this directory):

* ``fig11_threads.usda``   Figure 11 / Table 3: the four Guetermann sewing threads (Skala 360,
  ORA 120, CNe 50, S 303) as short yarn pieces, each at three depths of shade (0.5, 1, 2 %).
* ``fig7_swatches.usda``   Figure 7: the same stockinette swatch in cotton, polyester, silk
  and wool at the same dye and depth of shade.
* ``fig1_satin_garter.usda`` Figure 1: a silk satin and a cotton garter.
* ``fig5_dos_series.usda`` Figure 5: tufts of plain silk fibers (FiberAPI) dyed with one
  reactive orange dye at depths of shade 0.1, 0.5, 1, 2 and 4 %.

Every stage: millimetres (metersPerUnit = 0.001), Y up, a UsdGeom.Camera, a dome light and a
distant key light (UsdLux), and a grey card (a mesh with a UsdPreviewSurface), like
``make_examples.make_demo``. Render commands and timings: examples/README.md.
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
from usdfiber import cloth
from usdfiber.presets import FIBER_PRESETS, YARN_PRESETS

# The example stages share one stage layout (mm, Y up, a default prim): make_examples.py's.
sys.path.insert(0, str(Path(__file__).resolve().parent))
from make_examples import CLASS_ROOT, MM_PER_UM, new_stage  # noqa: E402

# Horizontal field of view of every camera here: focal length 50, aperture 36 (a 36 mm
# "full frame" back; only the ratio matters), so the view is 2 * 0.36 units wide per unit
# of distance.
FOCAL = 50.0
H_APERTURE = 36.0

#: Figure 11: (prim name, Table 3 preset, dye) per thread; the depths of shade of each.
FIG11_THREADS = (("Skala360", "Skala 360", "disperseRed"),
                 ("ORA120", "ORA 120", "disperseBlue"),
                 ("CNe50", "CNe 50", "reactiveGreen"),
                 ("S303", "S 303", "reactiveOrange"))
FIG11_SHADES = (("DoS0p5", 0.5), ("DoS1", 1.0), ("DoS2", 2.0))

#: Figure 7: fiber kinds, left to right as in the paper, and the one dye and depth of shade.
FIG7_KINDS = ("cotton", "polyester", "silk", "wool")
FIG7_DYE, FIG7_DOS = "reactiveRed", 2.0
#: Figure 7's yarn: one ply, five twists per cm (the figure's caption), the same ply radius
#: for every fiber kind so that the four swatches are the same knitted pattern; the fibers
#: per ply fill the ply at a packing fraction of 0.6 for each fiber diameter.
FIG7_PLY_RADIUS_MM = 0.1
FIG7_TWIST = 5.0
FIG7_PACKING = 0.6

#: Figure 1: depths of shade of the silk satin (reactive orange) and the cotton garter
#: (reactive blue).
FIG1_SATIN_DOS, FIG1_GARTER_DOS = 2.0, 1.0

#: Figure 5: depths of shade of the silk tufts and their one reactive dye (the figure's dye
#: is orange).
FIG5_SHADES = (("DoS0p1", 0.1), ("DoS0p5", 0.5), ("DoS1", 1.0), ("DoS2", 2.0), ("DoS4", 4.0))
FIG5_DYE = "reactiveOrange"


# ------------------------------------------------------------------------------- helpers
def _set_extent(curves: UsdGeom.BasisCurves) -> None:
    curves.CreateExtentAttr(UsdGeom.Curves.ComputeExtent(curves.GetPointsAttr().Get(),
                                                         curves.GetWidthsAttr().Get()))


def _card(stage: Usd.Stage, root: str, corners: list[tuple[float, float, float]],
          grey: float = 0.35) -> None:
    """A grey quad (UsdPreviewSurface), corners counter-clockwise seen from its front."""
    card = UsdGeom.Mesh.Define(stage, f"{root}/Card")
    card.CreatePointsAttr([Gf.Vec3f(*c) for c in corners])
    card.CreateFaceVertexCountsAttr([4])
    card.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    card.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    card.CreateExtentAttr(UsdGeom.Mesh.ComputeExtent(card.GetPointsAttr().Get()))
    mat = UsdShade.Material.Define(stage, f"{root}/Looks/Card")
    sh = UsdShade.Shader.Define(stage, f"{root}/Looks/Card/Surface")
    sh.CreateIdAttr("UsdPreviewSurface")
    sh.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(grey, grey, grey))
    sh.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.8)
    mat.CreateSurfaceOutput().ConnectToSource(sh.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(card.GetPrim()).Bind(mat)


def _floor(stage: Usd.Stage, root: str, x0: float, x1: float, z0: float, z1: float) -> None:
    _card(stage, root, [(x0, 0.0, z0), (x0, 0.0, z1), (x1, 0.0, z1), (x1, 0.0, z0)])


def _backdrop(stage: Usd.Stage, root: str, x0: float, x1: float, y0: float, y1: float, z: float) -> None:
    _card(stage, root, [(x0, y0, z), (x1, y0, z), (x1, y1, z), (x0, y1, z)])


def _camera(stage: Usd.Stage, path: str, eye: tuple[float, float, float],
            target: tuple[float, float, float], aspect: float) -> None:
    cam = UsdGeom.Camera.Define(stage, path)
    cam.CreateFocalLengthAttr(FOCAL)
    cam.CreateHorizontalApertureAttr(H_APERTURE)
    cam.CreateVerticalApertureAttr(H_APERTURE / aspect)
    dist = (Gf.Vec3d(*eye) - Gf.Vec3d(*target)).GetLength()
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.05 * dist, 20.0 * dist))
    up = Gf.Vec3d(0.0, 1.0, 0.0)
    view = Gf.Matrix4d().SetLookAt(Gf.Vec3d(*eye), Gf.Vec3d(*target), up)
    cam.AddTransformOp().Set(view.GetInverse())


def _distance_for_width(width: float) -> float:
    """Camera distance at which the view is ``width`` scene units wide."""
    return width / (H_APERTURE / FOCAL)


def _lights(stage: Usd.Stage, root: str, key_from: tuple[float, float, float],
            dome: float = 0.4, key: float = 2.5) -> None:
    """A dome (sky) and a distant key light shining from direction ``key_from``."""
    sky = UsdLux.DomeLight.Define(stage, f"{root}/Lights/Sky")
    sky.CreateIntensityAttr(dome)
    k = UsdLux.DistantLight.Define(stage, f"{root}/Lights/Key")
    k.CreateIntensityAttr(key)
    k.CreateAngleAttr(0.0)
    # Distant lights shine along their -Z.
    aim = Gf.Matrix4d().SetLookAt(Gf.Vec3d(*key_from), Gf.Vec3d(0.0, 0.0, 0.0), Gf.Vec3d(0.0, 1.0, 0.0))
    UsdGeom.Xformable(k.GetPrim()).AddTransformOp().Set(aim.GetInverse())


def _yarn_piece(stage: Usd.Stage, path: str, x: float, z0: float, z1: float, diameter: float,
                arch: float, n: int = 10) -> UsdGeom.BasisCurves:
    """A yarn centre line along +z at ``x`` resting on the floor (y = radius at the ends)
    and arched up by ``arch`` in the middle (uniform cubic B-spline, constant width)."""
    curves = UsdGeom.BasisCurves.Define(stage, path)
    curves.CreateTypeAttr(UsdGeom.Tokens.cubic)
    curves.CreateBasisAttr(UsdGeom.Tokens.bspline)
    curves.CreateWrapAttr(UsdGeom.Tokens.nonperiodic)
    r = 0.5 * diameter
    pts = []
    for j in range(n):
        u = j / (n - 1)
        pts.append(Gf.Vec3f(x + 0.04 * math.sin(2.0 * math.pi * u), r + arch * math.sin(math.pi * u),
                            z0 + (z1 - z0) * u))
    curves.CreatePointsAttr(Vt.Vec3fArray(pts))
    curves.CreateCurveVertexCountsAttr(Vt.IntArray([n]))
    curves.CreateWidthsAttr(Vt.FloatArray([diameter]))
    curves.SetWidthsInterpolation(UsdGeom.Tokens.constant)
    return curves


# ------------------------------------------------------------------------------- Figure 11
def make_fig11(out: Path) -> Path:
    """Figure 11: the four Table 3 threads side by side, each at three depths of shade."""
    stage = new_stage(
        "Aliaga et al. 2017, Figure 11 / Table 3: the four Guetermann sewing threads (Skala 360 "
        "and ORA 120 polyester with disperse dyes, CNe 50 cotton and S 303 silk with reactive "
        "dyes) as 4 mm yarn pieces (FiberYarnAPI + FiberAPI from the Table 3 presets) lying on "
        "a grey card, each at depths of shade 0.5, 1 and 2 % (left to right within a group). "
        "Render command and timing: examples/README.md. Units: mm.",
        "/Fig11")
    length, pitch, group_gap = 4.0, 0.55, 0.55
    x = 0.0
    xs = []
    for prim_name, preset, dye in FIG11_THREADS:
        UsdGeom.Xform.Define(stage, f"/Fig11/{prim_name}")
        for k, (shade_name, dos) in enumerate(FIG11_SHADES):
            path = f"/Fig11/{prim_name}/{shade_name}"
            diameter = YARN_PRESETS[preset].yarn_diameter_mm
            curves = _yarn_piece(stage, path, x, -0.5 * length, 0.5 * length, diameter,
                                 arch=0.15 + 0.05 * k)
            A.apply_yarn(curves.GetPrim(), preset, dye=dye, depth_of_shade=dos, seed=7 * k + 1)
            diameter = A.yarn_diameter_mm(curves.GetPrim())
            curves.GetWidthsAttr().Set(Vt.FloatArray([diameter]))
            _set_extent(curves)
            xs.append(x)
            x += pitch
        x += group_gap
    # Centre the row of threads on x = 0.
    shift = -0.5 * (xs[0] + xs[-1])
    for prim_name, _, _ in FIG11_THREADS:
        UsdGeom.Xformable(stage.GetPrimAtPath(f"/Fig11/{prim_name}")).AddTranslateOp().Set(
            Gf.Vec3d(shift, 0.0, 0.0))
    width = xs[-1] - xs[0] + 0.7
    _floor(stage, "/Fig11", -0.5 * width - 4.0, 0.5 * width + 4.0, -0.5 * length - 3.0, 0.5 * length + 3.0)
    # Seen from the front and above, the thread ends towards the viewer.
    aspect = 16.0 / 9.0
    d = _distance_for_width(width)
    elev = math.radians(55.0)
    eye = (0.0, d * math.sin(elev), d * math.cos(elev))
    _camera(stage, "/Fig11/Camera", eye, (0.0, 0.1, 0.15), aspect)
    _lights(stage, "/Fig11", key_from=(-1.0, 2.0, 1.5))
    path = out / "fig11_threads.usda"
    stage.GetRootLayer().Export(str(path))
    return path


def _hanging_scene(stage: Usd.Stage, root: str, path: Path, width: float, height: float, depth: float, *,
                   margin: float, card_gap: float, aspect: float, width_fill: float) -> Path:
    """Cloth centred on the origin in front of a card: card, a camera framing the cloth
    (``width_fill`` of its width, 1.1 of its height), lights; export to ``path``."""
    _backdrop(stage, root, -0.5 * width - margin, 0.5 * width + margin, -0.5 * height - margin,
              0.5 * height + margin, -depth - card_gap)
    d = _distance_for_width(max(width * width_fill, height * aspect * 1.1))
    _camera(stage, f"{root}/Camera", (0.0, 0.0, d), (0.0, 0.0, 0.0), aspect)
    _lights(stage, root, key_from=(-1.0, 1.5, 2.0))
    stage.GetRootLayer().Export(str(path))
    return path


# ------------------------------------------------------------------------------- Figure 7
def fig7_fibers_per_ply(kind: str) -> int:
    """Fibers filling a ply of FIG7_PLY_RADIUS_MM at FIG7_PACKING for ``kind``'s diameter."""
    r_fiber_mm = 0.5 * FIBER_PRESETS[kind].diameter_um * MM_PER_UM
    return max(1, round(FIG7_PACKING * (FIG7_PLY_RADIUS_MM / r_fiber_mm) ** 2))


def fig7_linear_density(kind: str) -> float:
    """dtex (g per 10 km) of one ply of fig7_fibers_per_ply(kind) fibers."""
    p = FIBER_PRESETS[kind]
    r_cm = 0.5 * p.diameter_um * 1e-4
    return fig7_fibers_per_ply(kind) * math.pi * r_cm ** 2 * p.density_g_cm3 * 1e6


def make_fig7(out: Path) -> Path:
    """Figure 7: one stockinette swatch per fiber kind, same dye and depth of shade."""
    stage = new_stage(
        "Aliaga et al. 2017, Figure 7: the same stockinette (plain knit) swatch, 7 rows of 5 "
        "loops, with cotton, polyester, silk and wool fibers (left to right), all dyed "
        f"{FIG7_DYE} at a depth of shade of {FIG7_DOS:g} %. The yarn is the figure's (one "
        f"ply, {FIG7_TWIST:g} twists per cm) with one ply radius ({FIG7_PLY_RADIUS_MM} mm) "
        "for every fiber, so the knitted geometry is identical; the fibers per ply fill the "
        "ply at a packing fraction of 0.6 for each fiber's diameter. The swatches hang in "
        "front of a grey card. Render command and timing: examples/README.md. Units: mm.",
        "/Fig7")
    gap = 1.0
    x = 0.0
    bounds = []
    for kind in FIG7_KINDS:
        name = kind[0].upper() + kind[1:]
        root = cloth.stockinette(stage, f"/Fig7/{name}", rows=7, loops=5, yarn="CNe 50",
                                 fiber=kind, dye=FIG7_DYE, depth_of_shade=FIG7_DOS)
        rows = stage.GetPrimAtPath(f"/Fig7/{name}/Rows")
        A.apply_yarn(rows, None, plies=1, fibers_per_ply=fig7_fibers_per_ply(kind),
                     linear_density=fig7_linear_density(kind), ply_radius=FIG7_PLY_RADIUS_MM,
                     ply_twist=FIG7_TWIST, fiber_twist=FIG7_TWIST)
        diameter = A.yarn_diameter_mm(rows)
        curves = UsdGeom.BasisCurves(rows)
        scale = diameter / curves.GetWidthsAttr().Get()[0]
        # The generator sized the loops for CNe 50's diameter: rescale to this yarn's.
        pts = curves.GetPointsAttr().Get()
        curves.GetPointsAttr().Set(Vt.Vec3fArray([Gf.Vec3f(p * scale) for p in pts]))
        curves.GetWidthsAttr().Set(Vt.FloatArray([diameter]))
        _set_extent(curves)
        lo, hi = curves.GetExtentAttr().Get()
        UsdGeom.Xformable(root).AddTranslateOp().Set(Gf.Vec3d(x - lo[0], -lo[1], 0.0))
        bounds.append((x, x + hi[0] - lo[0], hi[1] - lo[1], hi[2]))
        x += hi[0] - lo[0] + gap
    width = bounds[-1][1]
    height = max(b[2] for b in bounds)
    depth = max(b[3] for b in bounds)
    # Centre on x = 0 / y = 0 by moving the whole set.
    for kind in FIG7_KINDS:
        name = kind[0].upper() + kind[1:]
        op = UsdGeom.Xformable(stage.GetPrimAtPath(f"/Fig7/{name}")).GetOrderedXformOps()[0]
        op.Set(op.Get() - Gf.Vec3d(0.5 * width, 0.5 * height, 0.0))
    return _hanging_scene(stage, "/Fig7", out / "fig7_swatches.usda", width, height, depth,
                          margin=6.0, card_gap=0.6, aspect=8.0 / 3.0, width_fill=1.05)


# ------------------------------------------------------------------------------- Figure 1
def make_fig1(out: Path) -> Path:
    """Figure 1: a silk satin and a cotton garter."""
    stage = new_stage(
        "Aliaga et al. 2017, Figure 1: a warp-faced 5-harness satin of silk thread (S 303, "
        f"reactive orange, {FIG1_SATIN_DOS:g} %; 20 x 20 yarns 1.4 yarn diameters apart) next to "
        f"a garter knit of cotton thread (CNe 50, reactive blue, {FIG1_GARTER_DOS:g} %; 8 rows "
        "of 6 loops), generated by usdfiber.cloth, hanging in front of a grey card. (The figure's "
        "third piece, a polyester garter, is left out.) Render command and timing: "
        "examples/README.md. Units: mm.",
        "/Fig1")
    # A satin is dense: 1.4 yarn diameters between neighbouring yarns (the generator's
    # clearance check allows it: satin floats are flat), not the generator's default 2.5.
    d_silk = YARN_PRESETS["S 303"].yarn_diameter_mm
    sat = cloth.satin(stage, "/Fig1/SilkSatin", warps=20, wefts=20, yarn="S 303",
                      spacing=1.4 * d_silk, dye="reactiveOrange", depth_of_shade=FIG1_SATIN_DOS)
    gar = cloth.garter(stage, "/Fig1/CottonGarter", rows=8, loops=6, yarn="CNe 50",
                       dye="reactiveBlue", depth_of_shade=FIG1_GARTER_DOS)
    cache = UsdGeom.BBoxCache(Usd.TimeCode.Default(), [UsdGeom.Tokens.default_])
    gap = 1.5
    r_sat = cache.ComputeWorldBound(sat).ComputeAlignedRange()
    r_gar = cache.ComputeWorldBound(gar).ComputeAlignedRange()
    w_sat, w_gar = r_sat.GetSize()[0], r_gar.GetSize()[0]
    width = w_sat + gap + w_gar
    height = max(r_sat.GetSize()[1], r_gar.GetSize()[1])
    depth = max(r_sat.GetMax()[2], r_gar.GetMax()[2])
    x0 = -0.5 * width
    UsdGeom.Xformable(sat).AddTranslateOp().Set(
        Gf.Vec3d(x0 - r_sat.GetMin()[0], -r_sat.GetMidpoint()[1], 0.0))
    UsdGeom.Xformable(gar).AddTranslateOp().Set(
        Gf.Vec3d(x0 + w_sat + gap - r_gar.GetMin()[0], -r_gar.GetMidpoint()[1], 0.0))
    return _hanging_scene(stage, "/Fig1", out / "fig1_satin_garter.usda", width, height, depth,
                          margin=8.0, card_gap=0.8, aspect=16.0 / 9.0, width_fill=1.06)


# ------------------------------------------------------------------------------- Figure 5
def make_fig5(out: Path) -> Path:
    """Figure 5: silk fiber tufts at five depths of shade of one reactive dye."""
    stage = new_stage(
        "Aliaga et al. 2017, Figure 5 (second row) and Section 3.1: tufts of 120 plain silk "
        f"fibers (BasisCurves with FiberAPI, inheriting a silk class) dyed {FIG5_DYE} at "
        "depths of shade 0.1, 0.5, 1, 2 and 4 % (left to right), lying on a grey card. One "
        "fiber barely absorbs; the colour builds up over the fibers of a tuft. Render command "
        "and timing: examples/README.md. Units: mm.",
        "/Fig5")
    cls = A.define_fiber_class(stage, f"{CLASS_ROOT}/Silk", "silk", dye=FIG5_DYE)
    d_mm = FIBER_PRESETS["silk"].diameter_um * MM_PER_UM
    n_fib, n_pts, length = 120, 8, 1.8
    tuft_w, pitch = 0.36, 0.5
    xs = [pitch * (k - 0.5 * (len(FIG5_SHADES) - 1)) for k in range(len(FIG5_SHADES))]
    for (name, dos), x0 in zip(FIG5_SHADES, xs):
        curves = UsdGeom.BasisCurves.Define(stage, f"/Fig5/{name}")
        curves.CreateTypeAttr(UsdGeom.Tokens.cubic)
        curves.CreateBasisAttr(UsdGeom.Tokens.bspline)
        curves.CreateWrapAttr(UsdGeom.Tokens.nonperiodic)
        pts = []
        for i in range(n_fib):
            # A flat bundle along z: a deterministic spread across x and in height, gentle waves.
            u = (i + 0.5) / n_fib
            x = x0 + tuft_w * (u - 0.5) + 0.008 * math.sin(53.0 * u)
            y = d_mm * (0.6 + 5.0 * abs(math.sin(17.0 * u)))
            for j in range(n_pts):
                t = j / (n_pts - 1)
                z = -0.5 * length + length * t
                pts.append(Gf.Vec3f(x + 0.015 * math.sin(2.5 * z + 7.0 * u) * (1.0 + t),
                                    y + 0.006 * math.sin(3.0 * z + 5.0 * u),
                                    z))
        curves.CreatePointsAttr(Vt.Vec3fArray(pts))
        curves.CreateCurveVertexCountsAttr(Vt.IntArray([n_pts] * n_fib))
        curves.CreateWidthsAttr(Vt.FloatArray([d_mm]))
        curves.SetWidthsInterpolation(UsdGeom.Tokens.constant)
        _set_extent(curves)
        A.inherit(curves.GetPrim(), cls.GetPath())
        A.apply_fiber(curves.GetPrim(), None, depth_of_shade=dos)
    width = xs[-1] - xs[0] + tuft_w + 0.3
    _floor(stage, "/Fig5", -0.5 * width - 2.0, 0.5 * width + 2.0, -0.5 * length - 2.0, 0.5 * length + 2.0)
    aspect = 16.0 / 9.0
    d = _distance_for_width(1.15 * width)
    elev = math.radians(50.0)
    _camera(stage, "/Fig5/Camera", (0.0, d * math.sin(elev), d * math.cos(elev)), (0.0, 0.0, 0.1), aspect)
    _lights(stage, "/Fig5", key_from=(-1.0, 2.0, 1.5))
    path = out / "fig5_dos_series.usda"
    stage.GetRootLayer().Export(str(path))
    return path


MAKERS = (make_fig11, make_fig7, make_fig1, make_fig5)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    out = Path(argv[0]) if argv else Path(__file__).resolve().parent
    out.mkdir(parents=True, exist_ok=True)
    for make in MAKERS:
        print(make(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
