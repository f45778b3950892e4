"""Write tests/corpus/agreement/: the stages on which `usdfiber check` and the renderer must agree.

    python tests/corpus/make_agreement_corpus.py     # rewrites agreement/*.usda and expected.json

Two kinds of stage, each a small text layer:

* generated: fiber curves (FiberAPI) and plain curves (no fiber API) of every curve type,
  basis, wrap and width interpolation of UsdGeomBasisCurves, valid, and broken in the ways
  that matter to a renderer (too few points, counts against points, NaN points, negative
  or mis-counted widths, unknown tokens, no widths);
* the patterns of real files, written here (not copied): Maya exports (linear curves with
  ``basis = ""``), Pixar's BasisCurves test stages (one width without interpolation
  metadata, zero widths at tapered tips, periodic and pinned curves, widths per vertex /
  varying / uniform), point instancers with half-float orientations and scales, native
  instances, references, variant sets, metersPerUnit and upAxis variations, animated-only
  and time-sampled stages, yarns, derived roughness, profiles authored with a wrong type.

``expected.json`` maps each file to its verdict: ``"check": "ok"`` (no check errors: the
renderer must translate it) or ``"error"`` (check must report errors: the renderer refuses
it), and ``codes``: problem codes check must report (errors or warnings).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

HERE = Path(__file__).resolve().parent
OUT = HERE / "agreement"

TYPES_BASES = [("linear", "bezier")] + [("cubic", b) for b in ("bezier", "bspline", "catmullRom")]
WRAPS = ("nonperiodic", "periodic", "pinned")
INTERPS = ("constant", "uniform", "varying", "vertex")
FIBER_WIDTH = 0.01  # scene units (mm): a 10 um fiber, the FiberAPI fallback diameter


# --- the UsdGeomBasisCurves rules, from its documentation ---------------------------------

def counts_for(ctype: str, basis: str, wrap: str) -> list[int]:
    """Two valid curve point counts for the kind."""
    if ctype == "linear":
        return [3, 5]
    if basis == "bezier":
        return [6, 9] if wrap == "periodic" else [4, 7]
    return [4, 6] if wrap != "pinned" else [2, 5]


def segments(n: int, ctype: str, basis: str, wrap: str) -> int:
    if ctype == "linear":
        return n if wrap == "periodic" else n - 1
    step = 3 if basis == "bezier" else 1
    if wrap == "periodic":
        return n // step
    if wrap == "pinned" and basis != "bezier":
        return n - 1
    return (n - 4) // step + 1


def widths_count(interp: str, counts: list[int], ctype: str, basis: str, wrap: str) -> int:
    if interp == "constant":
        return 1
    if interp == "uniform":
        return len(counts)
    if interp == "vertex":
        return sum(counts)
    return sum(segments(n, ctype, basis, wrap) + (wrap != "periodic") for n in counts)


# --- writing ------------------------------------------------------------------------------

def fmt(x: float) -> str:
    return "nan" if isinstance(x, float) and math.isnan(x) else f"{x:g}"


def points_for(counts: list[int], scale: float = 1.0, z: float = 0.0) -> list[tuple[float, float, float]]:
    """A wavy line per curve, 1 scene unit apart (every curve has length)."""
    out = []
    for c, n in enumerate(counts):
        for i in range(n):
            out.append((i * 0.5 * scale, 0.2 * math.sin(i) * scale, (c + z) * scale))
    return out


def pts_text(points) -> str:
    return "[" + ", ".join(f"({fmt(x)}, {fmt(y)}, {fmt(z)})" for x, y, z in points) + "]"


def arr(values) -> str:
    return "[" + ", ".join(fmt(v) if isinstance(v, float) else str(v) for v in values) + "]"


def header(mpu: float | str = 0.001, up: str = "Y", extra: str = "") -> str:
    return (f'#usda 1.0\n(\n    defaultPrim = "World"\n    metersPerUnit = {mpu}\n'
            f'    upAxis = "{up}"\n{extra})\n\n')


def curves_prim(name: str, *, fiber: bool = True, ctype: str = "cubic", basis: str | None = "bspline",
                wrap: str = "nonperiodic", counts=(4,), points=None, widths=None,
                interp: str | None = "constant", extra: str = "", indent: str = "    ",
                apis: str | None = None) -> str:
    """One BasisCurves prim (FiberAPI when ``fiber``)."""
    counts = list(counts)
    points = points if points is not None else points_for(counts)
    api = apis if apis is not None else ('["FiberAPI"]' if fiber else None)
    meta = f' (\n{indent}    prepend apiSchemas = {api}\n{indent})' if api else ""
    lines = [f'{indent}def BasisCurves "{name}"{meta}', f"{indent}{{"]
    lines.append(f'{indent}    uniform token type = "{ctype}"')
    if basis is not None:
        lines.append(f'{indent}    uniform token basis = "{basis}"')
    lines.append(f'{indent}    uniform token wrap = "{wrap}"')
    lines.append(f"{indent}    int[] curveVertexCounts = {arr(counts)}")
    lines.append(f"{indent}    point3f[] points = {pts_text(points)}")
    if widths is not None:
        if interp is None:
            lines.append(f"{indent}    float[] widths = {arr(widths)}")
        else:
            lines.append(f"{indent}    float[] widths = {arr(widths)} (\n{indent}        interpolation = "
                         f'"{interp}"\n{indent}    )')
    if extra:
        lines.extend(indent + "    " + ln for ln in extra.strip("\n").splitlines())
    lines.append(f"{indent}}}")
    return "\n".join(lines) + "\n"


def world(*prims: str, comment: str = "") -> str:
    head = f"    # {comment}\n" if comment else ""
    return 'def Xform "World"\n{\n' + head + "".join(prims) + "}\n"


class Corpus:
    def __init__(self) -> None:
        self.files: dict[str, str] = {}
        self.expected: dict[str, dict] = {}

    def add(self, name: str, text: str, check: str, codes: tuple[str, ...] = ()) -> None:
        assert name not in self.files, name
        assert check in ("ok", "error")
        self.files[name] = text
        self.expected[name] = {"check": check, "codes": sorted(set(codes))}

    def write(self, out: Path) -> None:
        out.mkdir(parents=True, exist_ok=True)
        for old in out.glob("*.usda"):
            old.unlink()
        for name, text in self.files.items():
            (out / name).write_text(text)
        (out / "expected.json").write_text(json.dumps(dict(sorted(self.expected.items())), indent=1) + "\n")


# --- generated stages ----------------------------------------------------------------------

def kind_name(ctype: str, basis: str, wrap: str) -> str:
    return f"linear_{wrap}" if ctype == "linear" else f"{basis}_{wrap}"


def every_kind(c: Corpus) -> None:
    """Fiber and plain curves of every type/basis/wrap and width interpolation (valid)."""
    for ctype, basis in TYPES_BASES:
        for wrap in WRAPS:
            counts = counts_for(ctype, basis, wrap)
            for interp in INTERPS:
                n = widths_count(interp, counts, ctype, basis, wrap)
                widths = [FIBER_WIDTH * (1 + 0.1 * (i % 3)) for i in range(n)]
                name = f"{kind_name(ctype, basis, wrap)}_{interp}"
                fiber = curves_prim("Fibers", ctype=ctype, basis=basis, wrap=wrap, counts=counts,
                                    widths=widths, interp=interp)
                c.add(f"gen_fiber_{name}.usda", header() + world(fiber), "ok")
                plain = curves_prim("Guides", fiber=False, ctype=ctype, basis=basis, wrap=wrap,
                                    counts=counts, widths=widths, interp=interp)
                c.add(f"gen_plain_{name}.usda", header() + world(plain), "ok", ("PlainCurves",))


def broken(c: Corpus) -> None:
    """What a renderer cannot draw: an error on fiber curves, a skip-with-warning on plain ones."""
    w = [FIBER_WIDTH]
    cases = {
        "too_few_points": dict(counts=[3], widths=w),
        "counts_mismatch": dict(counts=[4], points=points_for([5]), widths=w),
        "nan_point": dict(counts=[4], points=[(0, 0, 0), (1, float("nan"), 0), (2, 0, 0), (3, 1, 0)],
                          widths=w),
        "negative_width": dict(counts=[4], widths=[FIBER_WIDTH, -FIBER_WIDTH, FIBER_WIDTH, FIBER_WIDTH],
                               interp="vertex"),
        "widths_miscounted": dict(counts=[4, 4], widths=[FIBER_WIDTH] * 3, interp="vertex"),
        "nan_width": dict(counts=[4], widths=[float("nan")]),
        "bad_basis": dict(basis="hermite", counts=[4], widths=w),
        "bad_wrap": dict(wrap="closed", counts=[4], widths=w),
        "bezier_off_step": dict(basis="bezier", counts=[5], widths=w),
        # Finite but beyond float32's squares: the curve would silently disappear.
        "huge_point": dict(counts=[4], points=[(0, 0, 0), (1, 1e30, 0), (2, 0, 0), (3, 1, 0)], widths=w),
        "huge_width": dict(counts=[4], widths=[1e30]),
    }
    codes = {
        "too_few_points": "CurveTooFewPoints", "counts_mismatch": "CurvesCountsMismatch",
        "nan_point": "PointsNotFinite", "negative_width": "WidthNegative",
        "widths_miscounted": "WidthsCountMismatch", "nan_width": "WidthsNotFinite",
        "bad_basis": "CurveTypeInvalid", "bad_wrap": "CurveTypeInvalid",
        "bezier_off_step": "CurveBezierVertexCount", "huge_point": "PointsTooLarge",
        "huge_width": "WidthsTooLarge",
    }
    for name, kw in cases.items():
        kw = dict(kw)
        kw.setdefault("interp", "constant")
        c.add(f"bad_fiber_{name}.usda", header() + world(curves_prim("Fibers", **kw)), "error", (codes[name],))
        c.add(f"bad_plain_{name}.usda", header() + world(curves_prim("Guide", fiber=False, **kw)), "ok",
              ("PlainCurves", "PlainCurvesSkipped"))
    # Plain curves without widths: nothing to draw them with.
    c.add("bad_plain_no_widths.usda", header() + world(curves_prim("Guide", fiber=False)), "ok",
          ("PlainCurvesSkipped",))
    # One broken guide curve beside fibers must not stop the render.
    c.add("guide_beside_fibers.usda", header() + world(
        curves_prim("Fibers", widths=[FIBER_WIDTH]),
        curves_prim("Guide", fiber=False, counts=[4], points=points_for([5]), widths=[0.1])),
        "ok", ("PlainCurvesSkipped",))


# --- patterns of real files ----------------------------------------------------------------

def real_patterns(c: Corpus) -> None:
    fw = [FIBER_WIDTH]
    # Maya exports linear curves with an empty basis; USD ignores the basis of linear curves.
    for fiber in (True, False):
        kind = "fiber" if fiber else "plain"
        c.add(f"maya_linear_empty_basis_{kind}.usda", header(0.01, "Y") + world(curves_prim(
            "curveShape1", fiber=fiber, ctype="linear", basis="", counts=[4, 3],
            widths=[0.001] * 7, interp="vertex"), comment="Maya: linear curves with basis = \"\""), "ok")
        # Pixar's test stages author one width and no interpolation metadata (Storm: constant).
        c.add(f"pixar_single_width_{kind}.usda", header(0.001, "Y") + world(curves_prim(
            "Curves", fiber=fiber, basis="catmullRom", counts=[5, 4], widths=fw, interp=None)),
            "ok", ("WidthsConstantAssumed",) if fiber else ("PlainCurvesApproximated",))
    # Tapered tips: USD's basisCurves example narrows to 0 at the ends.
    for basis in ("bezier", "bspline", "catmullRom"):
        n = 7 if basis == "bezier" else 6
        widths = [FIBER_WIDTH * min(i, n - 1 - i) / 2 for i in range(n)]
        c.add(f"taper_zero_tips_{basis}.usda", header() + world(curves_prim(
            "Fibers", basis=basis, counts=[n], widths=widths, interp="vertex"),
            comment="fibers taper to 0 at the staple ends"), "ok")
    c.add("taper_zero_tips_linear_varying.usda", header() + world(curves_prim(
        "Fibers", ctype="linear", counts=[4], widths=[0, FIBER_WIDTH, FIBER_WIDTH, 0], interp="varying")), "ok")
    # Periodic rings and pinned strands (Pixar's curve tests).
    c.add("periodic_rings_bspline.usda", header() + world(curves_prim(
        "Rings", basis="bspline", wrap="periodic", counts=[8],
        points=[(math.cos(a), math.sin(a), 0) for a in (i * math.pi / 4 for i in range(8))], widths=fw)), "ok")
    c.add("pinned_catmull_strands.usda", header() + world(curves_prim(
        "Strands", basis="catmullRom", wrap="pinned", counts=[3, 2, 4], widths=fw)), "ok")
    c.add("primvars_widths_varying.usda", header() + world(curves_prim(
        "Fibers", basis="bspline", counts=[5], widths=None,
        extra=f'float[] primvars:widths = {arr([FIBER_WIDTH] * 3)} (\n    interpolation = "varying"\n)')),
        "ok")
    # Scene scale and axes.
    for mpu, up, ok in ((0.01, "Y", "ok"), (1.0, "Z", "ok"), (0.0254, "Z", "ok"), (0, "Y", "error"),
                        (-0.001, "Y", "error"), (0.001, "X", "error")):
        w = FIBER_WIDTH * 0.001 / mpu if mpu > 0 else FIBER_WIDTH
        code = () if ok == "ok" else ("MetersPerUnitInvalid",) if mpu <= 0 else ("UpAxisInvalid",)
        c.add(f"units_mpu_{str(mpu).replace('-', 'minus').replace('.', 'p')}_up{up}.usda",
              header(mpu, up) + world(curves_prim("Fibers", widths=[w])), ok, code)
    # A fiber curve without widths under a scaled transform: as wide as the fiber in the world.
    c.add("scaled_fibers_without_widths.usda", header() + 'def Xform "World"\n{\n'
          '    double3 xformOp:scale = (100, 100, 100)\n    uniform token[] xformOpOrder = ["xformOp:scale"]\n'
          + curves_prim("Fibers", counts=[4]) + "}\n", "ok", ("WidthsMissing",))
    c.add("rotated_nonuniform_scale.usda", header() + 'def Xform "World"\n{\n'
          '    double3 xformOp:scale = (1, 2, 1)\n    uniform token[] xformOpOrder = ["xformOp:scale"]\n'
          + curves_prim("Fibers", widths=fw) + "}\n", "ok", ("NonUniformScale",))
    # Point instancer with half-float orientations and float scales, rotated instances.
    quats = ["(0.7071, 0, 0.7071, 0)", "(0.9239, 0.3827, 0, 0)", "(0.5, 0.5, 0.5, 0.5)"]
    c.add("instancer_half_orientations.usda", header() + 'def Xform "World"\n{\n'
          '    def PointInstancer "Tufts"\n    {\n'
          '        rel prototypes = [</World/Tufts/Protos/Tuft>]\n'
          '        int[] protoIndices = [0, 0, 0]\n'
          '        point3f[] positions = [(0, 0, 0), (5, 0, 0), (10, 0, 0)]\n'
          f'        quath[] orientations = [{", ".join(quats)}]\n'
          '        float3[] scales = [(2, 2, 2), (2, 2, 2), (2, 2, 2)]\n'
          '        def Scope "Protos"\n        {\n'
          + curves_prim("Tuft", widths=[FIBER_WIDTH / 2], indent="            ")
          + "        }\n    }\n}\n", "ok")
    # Native instances of a referenced fiber prim.
    proto = curves_prim("Fiber", widths=fw, indent="        ")
    c.add("native_instances.usda", header() + 'def Xform "World"\n{\n'
          '    def Xform "Proto" (active = false)\n    {\n' + proto + "    }\n"
          + "".join(f'    def Xform "Inst{i}" (\n        instanceable = true\n        prepend references = </World/Proto>\n'
                    f'    )\n    {{\n        double3 xformOp:translate = ({i}, 0, 0)\n'
                    f'        uniform token[] xformOpOrder = ["xformOp:translate"]\n    }}\n' for i in range(3))
          + "}\n", "ok")
    # References to a file next to the stage, and a missing one.
    c.add("asset_fibers.usda", header() + world(curves_prim("Fibers", widths=fw)), "ok")
    c.add("reference_asset.usda", header() + 'def Xform "World"\n{\n'
          '    def "Cloth" (\n        prepend references = @./asset_fibers.usda@</World>\n    )\n    {\n    }\n}\n', "ok")
    c.add("reference_missing.usda", header() + 'def Xform "World"\n{\n'
          '    def "Cloth" (\n        prepend references = @./no_such_asset.usda@</World>\n    )\n    {\n    }\n}\n',
          "error", ("MissingReference",))
    # Variant sets: the selected one is checked (and rendered).
    variants = ('def Xform "World"\n{{\n    def BasisCurves "Fibers" (\n        prepend apiSchemas = ["FiberAPI"]\n'
                '        variants = {{\n            string shade = "{sel}"\n        }}\n'
                '        prepend variantSets = "shade"\n    )\n    {{\n'
                '        uniform token basis = "bspline"\n        int[] curveVertexCounts = [4]\n'
                f'        point3f[] points = {pts_text(points_for([4]))}\n'
                f'        float[] widths = [{FIBER_WIDTH}] (\n            interpolation = "constant"\n        )\n'
                '        token fiber:dye:class = "reactive"\n'
                '        variantSet "shade" = {{\n'
                '            "pale" {{\n                float fiber:dye:depthOfShade = 0.2\n            }}\n'
                '            "bad" {{\n                float fiber:dye:depthOfShade = 50\n            }}\n'
                '        }}\n    }}\n}}\n')
    c.add("variants_pale_selected.usda", header() + variants.format(sel="pale"), "ok")
    c.add("variants_bad_selected.usda", header() + variants.format(sel="bad"), "error", ("ValueOutOfRange",))
    # Time: animated-only points (no default value), and sampled points beside a default.
    anim = curves_prim("Fibers", widths=fw).replace(
        f"point3f[] points = {pts_text(points_for([4]))}",
        "point3f[] points.timeSamples = {\n"
        + "".join(f"        {t}: {pts_text(points_for([4], z=t))},\n" for t in (1, 2, 3)) + "    }")
    c.add("animated_only_points.usda", header(extra="    startTimeCode = 1\n    endTimeCode = 3\n")
          + world(anim), "ok", ("AnimatedOnly",))
    c.add("animated_with_default.usda", header() + world(anim.replace(
        "point3f[] points.timeSamples", f"point3f[] points = {pts_text(points_for([4]))}\n        point3f[] points.timeSamples")),
        "ok")
    # Roughness derived from Ra and the profile length (beta = arctan(Ra / l)).
    for name, plen, ok, code in (("derived_beta_ok", 2000, "ok", ()), ("derived_beta_90", 1e-30, "error", ("ValueOutOfRange",)),
                                 ("derived_beta_70", 30, "error", ("ValueOutOfRange",))):
        c.add(f"{name}.usda", header() + world(curves_prim("Fibers", widths=fw, extra=(
            'token fiber:roughness:source = "ra"\nfloat fiber:roughness:ra = 100\n'
            f"float fiber:roughness:profileLength = {plen}"))), ok, code)
    # A user cross section authored as float3 points: a type error, not an internal error.
    c.add("profile_points_float3.usda", header() + world(
        '    def Scope "Section" (\n        prepend apiSchemas = ["FiberProfileAPI"]\n    )\n    {\n'
        '        float3[] fiberProfile:points = [(0, 0, 0), (10, 0, 0), (0, 10, 0)]\n'
        '        int[] fiberProfile:loopVertexCounts = [3]\n    }\n',
        curves_prim("Fibers", widths=fw, extra='token fiber:profile = "user"\n'
                    "rel fiber:profile:sources = </World/Section>")), "error", ("WrongValueType",))
    # Yarns (FiberYarnAPI with FiberAPI): a short, thin yarn expanded into fibers.
    yarn_extra = ("uniform int yarn:plies = 2\nuniform int yarn:fibersPerPly = 6\n"
                  "uniform float yarn:ply:radius = 0.05")
    yarn_w = 0.2
    c.add("yarn_short.usda", header() + world(curves_prim(
        "Yarn", apis='["FiberAPI", "FiberYarnAPI"]', counts=[4], points=points_for([4], 0.5),
        widths=[yarn_w], extra=yarn_extra)), "ok")
    c.add("yarn_without_widths.usda", header() + world(curves_prim(
        "Yarn", apis='["FiberAPI", "FiberYarnAPI"]', counts=[4], points=points_for([4], 0.5),
        extra=yarn_extra)), "ok", ("WidthsMissing",))
    c.add("yarn_too_few_points.usda", header() + world(curves_prim(
        "Yarn", apis='["FiberAPI", "FiberYarnAPI"]', counts=[3], widths=[yarn_w], extra=yarn_extra)),
        "error", ("CurveTooFewPoints",))
    # Ribbons (authored normals) and faceVarying widths: drawn as round tubes / as varying.
    c.add("ribbons_normals.usda", header() + world(curves_prim(
        "Fibers", counts=[4], widths=fw, extra="normal3f[] normals = [(0, 0, 1)] (\n    interpolation = \"constant\"\n)")),
        "ok", ("NormalsIgnored",))
    c.add("widths_face_varying.usda", header() + world(curves_prim(
        "Fibers", counts=[5], widths=[FIBER_WIDTH] * 3, interp="faceVarying")), "ok", ("WidthsFaceVarying",))
    c.add("widths_empty.usda", header() + world(curves_prim("Fibers", counts=[4], widths=[], interp="vertex")),
          "ok", ("WidthsMissing",))


def build() -> Corpus:
    c = Corpus()
    every_kind(c)
    broken(c)
    real_patterns(c)
    return c


if __name__ == "__main__":
    corpus = build()
    corpus.write(OUT)
    print(f"wrote {len(corpus.files)} stages to {OUT}")
