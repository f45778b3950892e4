"""Direct tests of the curve topology checks (validation.topology) and the profile and
table asset checks (validation.assets)."""
from __future__ import annotations

import itertools
import math
import time

import numpy as np
import pytest

import usdfiber  # noqa: F401  (registers the schemas before any stage exists)
from pxr import Gf, Sdf, Usd, UsdGeom, Vt

from usdfiber.spec.yarn import yarn_diameter
from usdfiber.validation import TimeSelection, selected_times
from usdfiber.validation import assets, topology
from usdfiber.validation.problems import CHECKS, Severity
from usdfiber.validation.topology import (
    check_curves_prim,
    expected_widths_count,
    segment_counts,
    varying_counts,
    vertex_count_rule,
)

NAN, INF = float("nan"), float("inf")


# --------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------


def new_stage(mpu: float = 1e-6) -> Usd.Stage:
    """In-memory stage; the default micrometre units make a 10 um fiber 10 units wide."""
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, mpu)
    return stage


def curve_points(counts) -> np.ndarray:
    """Distinct, wiggly points for curves of the given counts (one curve per z)."""
    pts = []
    for i, n in enumerate(counts):
        k = np.arange(max(n, 0), dtype=np.float32)
        pts.append(np.stack([k * 10.0, np.sin(k) * 3.0, np.full_like(k, 20.0 * i)], axis=1))
    return np.concatenate(pts) if pts else np.zeros((0, 3), np.float32)


def add_curves(stage, path, counts, *, curve_type="cubic", basis="bspline",
               wrap="nonperiodic", points=None, widths="auto", interpolation=None,
               apis=("FiberAPI",)) -> Usd.Prim:
    """Fiber (or yarn) curves; ``widths="auto"``: one constant width that matches the schema's
    fallback fiber diameter (10 um) or yarn diameter (2 plies of 0.1 mm: 0.4 mm) at the
    stage's micrometre units; ``widths=None``: no widths authored."""
    if isinstance(widths, str) and widths == "auto":
        widths, interpolation = ([400.0] if "FiberYarnAPI" in apis else [10.0]), "constant"
    curves = UsdGeom.BasisCurves.Define(stage, path)
    prim = curves.GetPrim()
    for api in apis:
        prim.ApplyAPI(api)
    curves.CreateTypeAttr(curve_type)
    curves.CreateBasisAttr(basis)
    curves.CreateWrapAttr(wrap)
    curves.CreateCurveVertexCountsAttr(Vt.IntArray([int(c) for c in counts]))
    pts = curve_points(counts) if points is None else np.asarray(points, np.float32)
    curves.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts))
    if widths is not None:
        curves.CreateWidthsAttr(Vt.FloatArray([float(w) for w in widths]))
        if interpolation:
            curves.SetWidthsInterpolation(interpolation)
    return prim


def codes(problems) -> list[str]:
    return sorted(p.code for p in problems)


def only(problems, code):
    found = [p for p in problems if p.code == code]
    assert len(found) == 1, problems
    return found[0]


# --------------------------------------------------------------------------------------
# USD's rules
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("curve_type,basis,wrap,valid,invalid", [
    ("linear", "bezier", "nonperiodic", [2, 3, 10], [1]),
    ("linear", "bspline", "pinned", [2, 5], [1]),
    ("linear", "bezier", "periodic", [3, 4], [1, 2]),
    ("cubic", "bezier", "nonperiodic", [4, 7, 10], [1, 3, 5, 6, 8]),
    ("cubic", "bezier", "pinned", [4, 7], [3, 5]),
    ("cubic", "bezier", "periodic", [3, 6, 9], [1, 2, 4, 5, 7]),
    ("cubic", "bspline", "nonperiodic", [4, 5, 6], [1, 2, 3]),
    ("cubic", "bspline", "periodic", [3, 4], [1, 2]),
    ("cubic", "bspline", "pinned", [2, 3], [1]),
    ("cubic", "catmullRom", "nonperiodic", [4, 9], [3]),
    ("cubic", "catmullRom", "periodic", [3, 8], [2]),
    ("cubic", "catmullRom", "pinned", [2, 4], [1]),
])
def test_vertex_count_rules(curve_type, basis, wrap, valid, invalid):
    rule = vertex_count_rule(curve_type, basis, wrap)
    assert rule.valid(np.array(valid)).all()
    assert not rule.valid(np.array(invalid)).any()


@pytest.mark.parametrize("curve_type,basis,wrap,counts,segments,varying", [
    # The worked example table of the UsdGeomBasisCurves documentation.
    ("linear", "bezier", "nonperiodic", [2, 3, 2, 5], [1, 2, 1, 4], [2, 3, 2, 5]),
    ("cubic", "bezier", "nonperiodic", [4, 7, 10, 4, 7], [1, 2, 3, 1, 2], [2, 3, 4, 2, 3]),
    ("cubic", "bspline", "nonperiodic", [5, 4, 6, 7], [2, 1, 3, 4], [3, 2, 4, 5]),
    ("cubic", "bezier", "periodic", [6, 9, 6], [2, 3, 2], [2, 3, 2]),
    ("linear", "bezier", "periodic", [3, 7], [3, 7], [3, 7]),
    # Pinned bspline/catmullRom: (n - 2) + 1 segments, + 1 varying; pinned bezier is
    # nonperiodic.
    ("cubic", "bspline", "pinned", [2, 5], [1, 4], [2, 5]),
    ("cubic", "catmullRom", "pinned", [3], [2], [3]),
    ("cubic", "bezier", "pinned", [4, 7], [1, 2], [2, 3]),
    ("cubic", "catmullRom", "periodic", [3, 5], [3, 5], [3, 5]),
])
def test_segment_and_varying_counts_follow_the_usd_docs(curve_type, basis, wrap, counts,
                                                        segments, varying):
    assert segment_counts(np.array(counts), curve_type, basis, wrap).tolist() == segments
    assert varying_counts(np.array(counts), curve_type, basis, wrap).tolist() == varying
    assert expected_widths_count("varying", counts, curve_type, basis, wrap) == sum(varying)
    assert expected_widths_count("vertex", counts, curve_type, basis, wrap) == sum(counts)
    assert expected_widths_count("uniform", counts, curve_type, basis, wrap) == len(counts)
    assert expected_widths_count("constant", counts, curve_type, basis, wrap) == 1


def test_nominal_yarn_diameter():
    assert yarn_diameter(1, 0.1) == pytest.approx(0.2)
    assert yarn_diameter(2, 0.1) == pytest.approx(0.4)  # two touching plies
    # Three touching plies: centres at r / sin(60 deg) from the yarn axis.
    assert yarn_diameter(3, 1.0) == pytest.approx(2 * (1 + 2 / math.sqrt(3)))


# --------------------------------------------------------------------------------------
# Valid curves
# --------------------------------------------------------------------------------------

_VALID_COUNTS = {
    ("linear", "nonperiodic"): [2, 5], ("linear", "periodic"): [3, 6], ("linear", "pinned"): [2, 4],
    ("bezier", "nonperiodic"): [4, 10], ("bezier", "periodic"): [3, 9], ("bezier", "pinned"): [7, 4],
    ("bspline", "nonperiodic"): [4, 9], ("bspline", "periodic"): [3, 5], ("bspline", "pinned"): [2, 6],
    ("catmullRom", "nonperiodic"): [4, 5], ("catmullRom", "periodic"): [3, 4],
    ("catmullRom", "pinned"): [2, 3],
}


def _valid_cases():
    for (kind, wrap), counts in _VALID_COUNTS.items():
        curve_type, basis = ("linear", "bezier") if kind == "linear" else ("cubic", kind)
        for interp in ("constant", "uniform", "varying", "vertex"):
            yield curve_type, basis, wrap, counts, interp


@pytest.mark.parametrize("curve_type,basis,wrap,counts,interp", list(_valid_cases()))
def test_valid_curves_of_every_kind_have_no_problems(curve_type, basis, wrap, counts, interp):
    stage = new_stage()
    n = expected_widths_count(interp, counts, curve_type, basis, wrap)
    widths = np.linspace(9.0, 11.0, n)  # around the 10 um default diameter
    prim = add_curves(stage, "/F", counts, curve_type=curve_type, basis=basis, wrap=wrap,
                      widths=widths, interpolation=interp)
    assert check_curves_prim(prim) == []


def test_widths_not_authored_warn_and_empty_prim_is_fine():
    stage = new_stage()
    missing = check_curves_prim(add_curves(stage, "/F", [4, 5], widths=None))
    assert codes(missing) == ["WidthsMissing"]
    assert missing[0].severity is Severity.WARNING and missing[0].attribute == "widths"
    assert "about 10 scene units" in missing[0].message  # fiber:diameter 10 um, metersPerUnit 1e-6
    assert check_curves_prim(add_curves(stage, "/E", [])) == []


def test_only_non_abstract_fiber_basis_curves_are_checked():
    stage = new_stage()
    bad = dict(points=curve_points([4])[:3])  # counts/points mismatch
    assert check_curves_prim(add_curves(stage, "/Plain", [4], apis=(), **bad)) == []
    assert codes(check_curves_prim(add_curves(stage, "/Yarn", [4], apis=("FiberYarnAPI",), **bad))) \
        == ["CurvesCountsMismatch"]
    cls = stage.CreateClassPrim("/_class")
    curves = UsdGeom.BasisCurves.Define(stage, "/_class/F")
    curves.GetPrim().ApplyAPI("FiberAPI")
    curves.CreateCurveVertexCountsAttr([4])
    assert cls.IsAbstract() and check_curves_prim(curves.GetPrim()) == []
    mesh = UsdGeom.Mesh.Define(stage, "/Mesh").GetPrim()
    mesh.ApplyAPI("FiberAPI")
    assert check_curves_prim(mesh) == []


def test_checks_are_registered():
    assert {"fiberCurves", "fiberProfile", "fiberTable"} <= set(CHECKS)


# --------------------------------------------------------------------------------------
# Topology problems
# --------------------------------------------------------------------------------------


def test_counts_mismatch():
    stage = new_stage()
    prim = add_curves(stage, "/F", [4, 4], points=curve_points([4, 3]))
    p = only(check_curves_prim(prim), "CurvesCountsMismatch")
    assert p.severity is Severity.ERROR and p.attribute == "curveVertexCounts"
    assert "sum to 8" in p.message and "7" in p.message
    assert p.prim == "/F" and p.layer == stage.GetRootLayer().identifier and p.time is None


def test_bezier_counts():
    stage = new_stage()
    few = check_curves_prim(add_curves(stage, "/A", [4, 3], basis="bezier"))
    assert codes(few) == ["CurveTooFewPoints"]
    assert "curve 1" in few[0].message and "4 + 3k" in few[0].message
    off = check_curves_prim(add_curves(stage, "/B", [4, 5, 8, 7], basis="bezier"))
    assert codes(off) == ["CurveBezierVertexCount"]
    assert "2 curves (1, 2)" in off[0].message
    periodic = check_curves_prim(add_curves(stage, "/C", [6, 4], basis="bezier", wrap="periodic"))
    assert codes(periodic) == ["CurveBezierVertexCount"] and "3k" in periodic[0].message


def test_bspline_too_few_and_nonpositive_counts():
    stage = new_stage()
    p = only(check_curves_prim(add_curves(stage, "/A", [4, 3])), "CurveTooFewPoints")
    assert "at least 4" in p.message
    pinned = check_curves_prim(add_curves(stage, "/P", [2, 1], wrap="pinned"))
    assert codes(pinned) == ["CurveTooFewPoints"] and "at least 2" in pinned[0].message
    prim = add_curves(stage, "/Z", [4, 0, -2], points=curve_points([4]))
    got = codes(check_curves_prim(prim))
    assert "CurveVertexCountNotPositive" in got and "CurvesCountsMismatch" in got


def test_invalid_tokens():
    stage = new_stage()
    prim = add_curves(stage, "/F", [4])
    prim.GetAttribute("basis").Set("hermite")
    p = only(check_curves_prim(prim), "CurveTypeInvalid")
    assert p.attribute == "basis" and "bspline" in p.message
    # The basis does not matter for linear curves.
    prim.GetAttribute("type").Set("linear")
    assert check_curves_prim(prim) == []


@pytest.mark.parametrize("interp,count,expected", [
    ("constant", 2, 1), ("uniform", 3, 2), ("varying", 9, 5), ("vertex", 5, 9),
])
def test_widths_count_mismatch(interp, count, expected):
    stage = new_stage()
    # bspline nonperiodic [4, 5]: 1 + 2 segments, varying 2 + 3 = 5, vertex 9.
    prim = add_curves(stage, "/F", [4, 5], widths=[10.0] * count, interpolation=interp)
    p = only(check_curves_prim(prim), "WidthsCountMismatch")
    assert p.attribute == "widths" and f"expected {expected}" in p.message


def test_widths_interpolation_invalid():
    stage = new_stage()
    prim = add_curves(stage, "/F", [4], widths=[10.0] * 4)
    prim.GetAttribute("widths").SetMetadata("interpolation", "perPixel")
    assert codes(check_curves_prim(prim)) == ["WidthsInterpolationInvalid"]


def test_face_varying_widths_are_read_as_varying():
    # faceVarying is not defined for curves; the renderer reads it as varying (2 values here).
    stage = new_stage()
    prim = add_curves(stage, "/F", [4], widths=[10.0] * 2, interpolation="faceVarying")
    assert codes(check_curves_prim(prim)) == ["WidthsFaceVarying"]
    prim = add_curves(stage, "/G", [4], widths=[10.0] * 4, interpolation="faceVarying")
    assert codes(check_curves_prim(prim)) == ["WidthsCountMismatch", "WidthsFaceVarying"]


def test_primvars_widths_take_precedence():
    stage = new_stage()
    prim = add_curves(stage, "/F", [4, 4], widths=[10.0], interpolation="constant")
    pv = UsdGeom.PrimvarsAPI(prim).CreatePrimvar("widths", Sdf.ValueTypeNames.FloatArray,
                                                 UsdGeom.Tokens.uniform)
    pv.Set(Vt.FloatArray([10.0]))
    pv.SetIndices(Vt.IntArray([0, 0]))  # indexed: flattened to one per curve
    assert check_curves_prim(prim) == []
    pv.SetIndices(Vt.IntArray([0, 0, 0]))
    p = only(check_curves_prim(prim), "WidthsCountMismatch")
    assert p.attribute == "primvars:widths"


# --------------------------------------------------------------------------------------
# Values
# --------------------------------------------------------------------------------------


def test_non_finite_points_and_widths():
    stage = new_stage()
    pts = curve_points([4, 4])
    pts[5, 1] = NAN
    pts[6, 0] = INF
    prim = add_curves(stage, "/F", [4, 4], points=pts, widths=[10, NAN, 10, -1, 0, 10, 10, 10],
                      interpolation="vertex")
    probs = check_curves_prim(prim)
    assert codes(probs) == ["PointsNotFinite", "WidthNegative", "WidthsNotFinite"]
    assert "2 points (5, 6)" in only(probs, "PointsNotFinite").message
    assert "width 3 has" in only(probs, "WidthNegative").message  # 0 (index 4) is a taper


def test_points_and_widths_too_large_for_float32():
    """Finite values whose squares overflow float32 (1e30) make the curve vanish from the
    render: errors naming the attribute and the bound; values just below it, and zero widths,
    pass."""
    from usdfiber.geometry.curves import MAX_COORDINATE

    stage = new_stage()
    pts = curve_points([4, 4])
    pts[6, 1] = -1e30
    prim = add_curves(stage, "/F", [4, 4], points=pts, widths=[10, 10, 0, 10, 10, 1e30, 10, 10],
                      interpolation="vertex")
    probs = check_curves_prim(prim)
    assert codes(probs) == ["PointsTooLarge", "WidthsTooLarge"]
    p = only(probs, "PointsTooLarge")
    assert p.severity is Severity.ERROR and p.attribute == "points"
    assert "point 6 has" in p.message and "below 1e+18" in p.message
    w = only(probs, "WidthsTooLarge")
    assert w.attribute == "widths" and "width 5 has" in w.message and "1e+30" in w.message
    below = float(np.nextafter(np.float32(MAX_COORDINATE), np.float32(0)))
    pts[6, 1] = -below
    ok = add_curves(stage, "/G", [4, 4], points=pts, widths=[0, 10, 10, 10, 10, 10, 10, 0],
                    interpolation="vertex")
    # No error; 10 units wide next to a coordinate of 1e18 is below float32's precision there.
    assert codes(check_curves_prim(ok)) == ["WidthBelowPrecision"]


def test_widths_below_the_float32_precision_of_their_position():
    """A 10 um fiber 1 km from the origin (1e9 units) is narrower than 2^-22 of its coordinates
    (238 units): it renders with holes or vanishes. A warning in check, the same warning from the
    renderer's conversion; 1 m away (1e6: 0.24 units) it is fine, and zero-width tips never warn.
    (Points a centimetre apart, which float32 still tells apart at 1e9.)"""
    from usdfiber.geometry.curves import curves_from_prim

    stage = new_stage()
    far = add_curves(stage, "/Far", [4], points=curve_points([4]) * np.float32(1000) + np.float32([1e9, 0, 0]),
                     widths=[0, 10, 10, 0], interpolation="vertex")
    probs = check_curves_prim(far)
    assert codes(probs) == ["WidthBelowPrecision"]
    w = only(probs, "WidthBelowPrecision")
    assert w.severity is Severity.WARNING and w.attribute == "widths"
    assert "2 widths narrower than 238.4" in w.message and "(1.00003e+09)" in w.message
    assert "nearer the origin" in w.message
    geom = curves_from_prim(far, Usd.TimeCode.Default(), None)
    assert sum("narrower than 238.4" in text for text in geom.warnings) == 1
    near = add_curves(stage, "/Near", [4], points=curve_points([4]) + np.float32([1e6, 0, 0]))
    assert check_curves_prim(near) == []
    assert not any("narrower than" in text for text in curves_from_prim(near, Usd.TimeCode.Default(), None).warnings)
    # Moved there by a transform: the same, in world space.
    xf = UsdGeom.Xform.Define(stage, "/Moved")
    xf.AddTranslateOp().Set(Gf.Vec3d(0, 0, -1e9))
    moved = add_curves(stage, "/Moved/F", [4])
    assert codes(check_curves_prim(moved)) == ["WidthBelowPrecision"]


def test_points_and_widths_too_large_in_world_space():
    """An ancestor's scale or translation that takes the curves beyond the bound."""
    stage = new_stage()
    xf = UsdGeom.Xform.Define(stage, "/Far")
    op = xf.AddScaleOp()
    op.Set(Gf.Vec3f(1e18, 1e18, 1e18))
    prim = add_curves(stage, "/Far/F", [4])
    probs = check_curves_prim(prim)
    assert {"PointsTooLarge", "WidthsTooLarge"} <= set(codes(probs))
    p = only(probs, "PointsTooLarge")
    assert p.message.startswith("in world space") and "(e.g. (1e+19, " in p.message
    assert only(probs, "WidthsTooLarge").message.startswith("in world space")
    op.Set(Gf.Vec3f(1, 1, 1))
    xf.AddTranslateOp().Set(Gf.Vec3d(0, 0, -1e30))
    assert "PointsTooLarge" in codes(check_curves_prim(prim))
    assert "WidthsTooLarge" not in codes(check_curves_prim(prim))
    # A finite matrix that takes finite points past float64 (Inf in world space) is beyond too.
    far = UsdGeom.Xform.Define(stage, "/Farther")
    far.AddTransformOp().Set(Gf.Matrix4d(Gf.Vec4d(1e300, 1e300, 1e300, 1)))
    pts = curve_points([4])
    pts[2, 0] = 1e10
    p = only(check_curves_prim(add_curves(stage, "/Farther/F", [4], points=pts)), "PointsTooLarge")
    assert p.message.startswith("in world space") and "3 points (1, 2, 3) have" in p.message


def test_zero_length_curve():
    stage = new_stage()
    pts = curve_points([4, 4, 4])
    pts[4:8] = (1e6, 2e6, 3e6)  # equal points far from the origin
    p = only(check_curves_prim(add_curves(stage, "/F", [4, 4, 4], points=pts)), "CurveZeroLength")
    assert p.severity is Severity.WARNING and "curve 1" in p.message
    # A curve 1 um long at 1 m from the origin (float32 resolves ~0.06 um there) is real.
    pts = curve_points([4])
    pts[:] = (1e6, 0, 0)
    pts[3, 0] += 1.0
    assert check_curves_prim(add_curves(stage, "/G", [4], points=pts)) == []


def test_time_sampled_points_are_checked_at_every_sample():
    stage = new_stage()
    prim = add_curves(stage, "/F", [4, 4])
    attr = prim.GetAttribute("points")
    good = curve_points([4, 4])
    attr.Clear()
    for t in (1.0, 2.0, 3.0, 4.0):
        pts = good.copy()
        if t in (2.0, 4.0):
            pts[3, 2] = NAN
        attr.Set(Vt.Vec3fArray.FromNumpy(pts), t)
    p = only(check_curves_prim(prim), "PointsNotFinite")
    assert p.time == 2.0 and "at 2 time samples, first at time 2" in p.message
    # A static problem beside sampled data carries no time.
    prim.GetAttribute("curveVertexCounts").Set(Vt.IntArray([4, 3]))
    p = only(check_curves_prim(prim), "CurveTooFewPoints")
    assert p.time is None


def test_time_selection_limits_the_samples():
    stage = new_stage()
    prim = add_curves(stage, "/F", [4])
    attr = prim.GetAttribute("widths") or UsdGeom.Curves(prim).CreateWidthsAttr()
    UsdGeom.Curves(prim).SetWidthsInterpolation("constant")
    attr.Set(Vt.FloatArray([10.0]), 1.0)
    attr.Set(Vt.FloatArray([-1.0]), 5.0)
    assert codes(check_curves_prim(prim)) == ["WidthNegative"]
    with selected_times(TimeSelection(1.0, 1.0)):
        assert check_curves_prim(prim) == []
    with selected_times(TimeSelection(4.0, 6.0, include_default=False)):
        assert only(check_curves_prim(prim), "WidthNegative").time == 5.0


def test_default_value_checked_beside_samples_only_when_authored():
    stage = new_stage()
    prim = add_curves(stage, "/F", [4])
    attr = prim.GetAttribute("points")
    bad = curve_points([4])
    bad[0, 0] = NAN
    attr.Set(Vt.Vec3fArray.FromNumpy(bad))  # default value
    attr.Set(Vt.Vec3fArray.FromNumpy(curve_points([4])), 1.0)
    p = only(check_curves_prim(prim), "PointsNotFinite")
    assert p.time is None and "default value" in p.message


def test_inf_in_a_time_sampled_ancestor_transform():
    stage = new_stage()
    xf = UsdGeom.Xform.Define(stage, "/Cloth")
    op = xf.AddTranslateOp()
    op.Set(Gf.Vec3d(0, 0, 0), 1.0)
    op.Set(Gf.Vec3d(INF, 0, 0), 2.0)
    op.Set(Gf.Vec3d(0, 0, 0), 3.0)
    prim = add_curves(stage, "/Cloth/F", [4])
    p = only(check_curves_prim(prim), "TransformNotFinite")
    assert p.time == 2.0 and "/Cloth" in p.message and p.attribute is None
    op.Set(Gf.Vec3d(0, 0, 0), 2.0)
    assert check_curves_prim(prim) == []


def test_transform_cache_sees_later_edits():
    stage = new_stage()
    xf = UsdGeom.Xform.Define(stage, "/Cloth")
    prim = add_curves(stage, "/Cloth/F", [4])
    assert check_curves_prim(prim) == []
    op = xf.AddScaleOp()                     # new, animated op on the ancestor
    op.Set(Gf.Vec3f(1, 1, 1), 1.0)
    op.Set(Gf.Vec3f(1, NAN, 1), 7.0)
    assert only(check_curves_prim(prim), "TransformNotFinite").time == 7.0
    stage.RemovePrim("/Cloth")
    stage.DefinePrim("/Cloth", "Xform")
    prim = add_curves(stage, "/Cloth/F", [4])
    assert check_curves_prim(prim) == []


def test_non_finite_matrix_entries_make_the_determinant_non_finite():
    """The fast transform test relies on this for every entry position."""
    rng = np.random.default_rng(0)
    bases = [Gf.Matrix4d(1), Gf.Matrix4d(0), Gf.Matrix4d().SetScale(Gf.Vec3d(0, 1, 2)),
             Gf.Matrix4d().SetTranslate(Gf.Vec3d(4, 5, 6)),
             Gf.Matrix4d(*rng.random(16).tolist())]
    for base, i, j, v in itertools.product(bases, range(4), range(4), (INF, -INF, NAN)):
        m = Gf.Matrix4d(base)
        m[i, j] = v
        assert not topology._finite_matrix(m), (base, i, j, v)
    assert topology._finite_matrix(Gf.Matrix4d(1e100))  # det overflows, entries finite


# --------------------------------------------------------------------------------------
# Widths against the fiber and yarn sizes
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("mpu,width,flagged", [
    (1e-6, 10.0, False), (1e-6, 14.0, False), (1e-6, 7.0, False),   # 10 um in um
    (1e-6, 16.0, True), (1e-6, 6.0, True),                          # beyond a factor 1.5
    (1e-3, 0.01, False), (1e-3, 10.0, True),                        # mm stage, um values
    (1.0, 1e-5, False), (1.0, 0.01, True),                          # m stage, mm values
    (0.01, 1e-3, False),                                            # cm (USD's fallback)
])
def test_fiber_width_mismatch(mpu, width, flagged):
    stage = new_stage(mpu)
    prim = add_curves(stage, "/F", [4], widths=[width], interpolation="constant")
    probs = check_curves_prim(prim)
    assert codes(probs) == (["WidthMismatch"] if flagged else [])
    if flagged:
        assert probs[0].severity is Severity.WARNING and "fiber:diameter 10 um" in probs[0].message


def test_width_mismatch_uses_diameter_median_and_transform_scale():
    stage = new_stage(1e-6)
    prim = add_curves(stage, "/F", [4, 4], widths=[30.0] * 8, interpolation="vertex")
    prim.GetAttribute("fiber:diameter").Set(30.0)
    assert check_curves_prim(prim) == []
    # Tapered tips (a quarter of the widths near zero) do not move the median.
    prim.GetAttribute("widths").Set(Vt.FloatArray([30, 30, 30, 0.1, 30, 30, 30, 0.1]))
    assert check_curves_prim(prim) == []
    # Widths in mm under a 1000x scaling transform are right in world space.
    stage2 = new_stage(1e-6)
    xf = UsdGeom.Xform.Define(stage2, "/S")
    xf.AddScaleOp().Set(Gf.Vec3f(1000, 1000, 1000))
    prim2 = add_curves(stage2, "/S/F", [4], widths=[0.01], interpolation="constant")
    assert check_curves_prim(prim2) == []
    prim2.GetAttribute("widths").Set(Vt.FloatArray([10.0]))
    assert "transform scale 1000" in only(check_curves_prim(prim2), "WidthMismatch").message


def test_unauthored_meters_per_unit_is_named_in_the_message():
    stage = Usd.Stage.CreateInMemory()  # metersPerUnit falls back to 0.01
    prim = add_curves(stage, "/F", [4], widths=[1e-5], interpolation="constant")
    p = only(check_curves_prim(prim), "WidthMismatch")
    assert "not authored" in p.message and "0.001 scene units" in p.message


@pytest.mark.parametrize("mpu,width,flagged", [
    (1e-3, 0.4, False), (1e-3, 1.2, False), (1e-3, 0.15, False),   # 2 plies x 0.1 mm: 0.4 mm
    (1e-3, 2.0, True), (1e-3, 0.05, True),                         # beyond a factor 4
    (1.0, 0.4, True), (1.0, 4e-4, False),                          # mm values in a m stage
])
def test_yarn_width_mismatch(mpu, width, flagged):
    stage = new_stage(mpu)
    prim = add_curves(stage, "/Y", [4], widths=[width], interpolation="constant",
                      apis=("FiberAPI", "FiberYarnAPI"))
    probs = check_curves_prim(prim)
    assert codes(probs) == (["WidthMismatch"] if flagged else [])
    if flagged:
        assert "nominal yarn diameter 0.4 mm" in probs[0].message


# --------------------------------------------------------------------------------------
# Scale
# --------------------------------------------------------------------------------------


def test_one_prim_with_100k_curves():
    n, k = 100_000, 6
    rng = np.random.default_rng(1)
    base = np.repeat(rng.random((n, 3)).astype(np.float32) * 1e4, k, axis=0)
    pts = base + rng.random((n * k, 3)).astype(np.float32) * 100.0
    pts[54321 * k:(54321 + 1) * k] = pts[54321 * k]   # zero-length curve 54321
    pts[77777 * k + 2, 1] = NAN                       # NaN in curve 77777
    widths = np.full(n * k, 10.0, np.float32)
    widths[99999 * k + 5] = -1.0                      # one negative width
    stage = new_stage()
    curves = UsdGeom.BasisCurves.Define(stage, "/Big")
    curves.GetPrim().ApplyAPI("FiberAPI")
    curves.CreateBasisAttr("catmullRom")
    curves.CreateCurveVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(n, k, np.int32)))
    curves.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts))
    curves.CreateWidthsAttr(Vt.FloatArray.FromNumpy(widths))

    t0, c0 = time.perf_counter(), time.process_time()
    probs = check_curves_prim(curves.GetPrim())
    elapsed, cpu = time.perf_counter() - t0, time.process_time() - c0
    print(f"\n100k curves ({n * k} points) in one prim: {elapsed * 1e3:.1f} ms wall, "
          f"{cpu * 1e3:.1f} ms CPU")
    assert codes(probs) == ["CurveZeroLength", "PointsNotFinite", "WidthNegative"]
    assert "curve 54321 " in only(probs, "CurveZeroLength").message
    assert f"point {77777 * k + 2} " in only(probs, "PointsNotFinite").message
    assert f"width {99999 * k + 5} " in only(probs, "WidthNegative").message

    # Topology errors on many curves are summarized in one problem.
    counts = np.full(n, k, np.int32)
    counts[::2] = 3
    counts[1::2] = 9
    curves.GetCurveVertexCountsAttr().Set(Vt.IntArray.FromNumpy(counts))
    t0 = time.perf_counter()
    probs = check_curves_prim(curves.GetPrim())
    print(f"100k curves, 50k of them too short: {(time.perf_counter() - t0) * 1e3:.1f} ms")
    p = only(probs, "CurveTooFewPoints")
    assert "50000 curves (0, 2, 4, 6, 8, ...)" in p.message


def test_20k_prims():
    stage = new_stage()
    layer = stage.GetRootLayer()
    m = 20_000
    bad = {123: "CurvesCountsMismatch", 4567: "PointsNotFinite", 19999: "WidthMismatch"}
    with Sdf.ChangeBlock():
        root = Sdf.CreatePrimInLayer(layer, "/Cloth")
        root.specifier = Sdf.SpecifierDef
        root.typeName = "Xform"
        for i in range(m):
            spec = Sdf.PrimSpec(root, f"F{i}", Sdf.SpecifierDef, "BasisCurves")
            spec.SetInfo("apiSchemas", Sdf.TokenListOp.CreateExplicit(["FiberAPI"]))
            pts = [(0, 0, i), (10, 2, i), (20, -2, i), (30, 0, i)]
            counts = [4]
            w = 10.0
            if bad.get(i) == "CurvesCountsMismatch":
                counts = [5]
            elif bad.get(i) == "PointsNotFinite":
                pts[1] = (NAN, 0, 0)
            elif bad.get(i) == "WidthMismatch":
                w = 1e4
            Sdf.AttributeSpec(spec, "curveVertexCounts", Sdf.ValueTypeNames.IntArray).default = \
                Vt.IntArray(counts)
            Sdf.AttributeSpec(spec, "points", Sdf.ValueTypeNames.Point3fArray).default = \
                Vt.Vec3fArray(pts)
            wa = Sdf.AttributeSpec(spec, "widths", Sdf.ValueTypeNames.FloatArray)
            wa.default = Vt.FloatArray([w])
            wa.SetInfo("interpolation", "constant")
            basis = Sdf.AttributeSpec(spec, "basis", Sdf.ValueTypeNames.Token,
                                      Sdf.VariabilityUniform)
            basis.default = "bspline"
    prims = [p for p in stage.Traverse() if p.IsA(UsdGeom.BasisCurves)]
    assert len(prims) == m
    t0, c0 = time.perf_counter(), time.process_time()
    found = {}
    for prim in prims:
        for p in check_curves_prim(prim):
            found[p.prim] = p.code
    elapsed, cpu = time.perf_counter() - t0, time.process_time() - c0
    print(f"\n{m} fiber prims: {elapsed:.2f} s wall, {cpu:.2f} s CPU "
          f"({cpu / m * 1e6:.0f} us CPU per prim)")
    assert found == {f"/Cloth/F{i}": code for i, code in bad.items()}


# --------------------------------------------------------------------------------------
# Profiles (FiberProfileAPI)
# --------------------------------------------------------------------------------------

SQUARE = [(0, 0), (10, 0), (10, 10), (0, 10)]


def add_profile(stage, path, points, counts) -> Usd.Prim:
    prim = stage.DefinePrim(path, "Scope")
    prim.ApplyAPI("FiberProfileAPI")
    prim.GetAttribute("fiberProfile:points").Set(
        Vt.Vec2fArray([Gf.Vec2f(float(x), float(y)) for x, y in points]))
    prim.GetAttribute("fiberProfile:loopVertexCounts").Set(Vt.IntArray(counts))
    return prim


@pytest.mark.parametrize("points,counts", [
    (SQUARE, [4]),
    (SQUARE + [(0, 0)], [5]),                                   # repeated closing point
    (SQUARE[::-1], [4]),                                        # any orientation
    (SQUARE + [(4, 4), (6, 4), (6, 6), (4, 6)], [4, 4]),        # with a hole
    (SQUARE + [(4, 4), (6, 4), (6, 6), (4, 6), (4, 4)], [4, 5]),
])
def test_valid_profiles(points, counts):
    stage = new_stage()
    assert assets.check_profile_prim(add_profile(stage, "/P", points, counts)) == []


@pytest.mark.parametrize("points,counts,code,attribute", [
    ([(0, 0), (10, 10), (10, 0), (0, 6)], [4], "ProfileSelfIntersecting", "fiberProfile:points"),
    ([(0, 0), (5, 0), (10, 0)], [3], "ProfileZeroArea", "fiberProfile:points"),
    (SQUARE + [(20, 2), (22, 2), (21, 4)], [4, 3], "ProfileHoleOutside", "fiberProfile:points"),
    (SQUARE + [(5, 4), (15, 4), (15, 6), (5, 6)], [4, 4], "ProfileLoopsIntersect",
     "fiberProfile:points"),
    (SQUARE + [(2, 2), (5, 2), (5, 5), (2, 5), (3, 3), (4, 3), (4, 4)], [4, 4, 3],
     "ProfileHoleOutside", "fiberProfile:points"),             # a hole inside a hole
    (SQUARE + [(4, 4), (6, 6)], [4, 2], "ProfileTooFewPoints", "fiberProfile:loopVertexCounts"),
    ([(0, 0), (10, 0), (0, 0)], [3], "ProfileTooFewPoints", "fiberProfile:loopVertexCounts"),
    (SQUARE, [5], "ProfileCountsMismatch", "fiberProfile:loopVertexCounts"),
    ([(0, 0), (10, 0), (10, NAN), (0, 10)], [4], "ProfilePointsNotFinite", "fiberProfile:points"),
    ([(4, 4), (6, 4), (6, 6)] + SQUARE, [3, 4], "ProfileOuterNotFirst", "fiberProfile:points"),
])
def test_bad_profiles(points, counts, code, attribute):
    stage = new_stage()
    probs = assets.check_profile_prim(add_profile(stage, "/P", points, counts))
    assert [(p.code, p.attribute) for p in probs] == [(code, attribute)], probs
    expected = Severity.WARNING if code == "ProfileOuterNotFirst" else Severity.ERROR
    assert probs[0].severity is expected and probs[0].prim == "/P"


def test_profile_without_points():
    stage = new_stage()
    prim = stage.DefinePrim("/P", "Scope")
    prim.ApplyAPI("FiberProfileAPI")
    assert codes(assets.check_profile_prim(prim)) == ["ProfileMissingPoints"]
    assert assets.check_profile_prim(stage.DefinePrim("/Q", "Scope")) == []


def test_profile_error_messages_are_classified():
    """Pins the ProfileError wording the mapping relies on."""
    from usdfiber.bake.profiles import ProfileError, profile_from_polygons

    cases = {
        "ProfileSelfIntersecting": [[(0, 0), (10, 10), (10, 0), (0, 6)]],
        "ProfileZeroArea": [[(0, 0), (5, 0), (10, 0)]],
        "ProfileHoleOutside": [SQUARE, [(20, 2), (22, 2), (21, 4)]],
        "ProfileLoopsIntersect": [SQUARE, [(5, 4), (15, 4), (15, 6), (5, 6)]],
        "ProfileTooFewPoints": [SQUARE, [(1, 1), (2, 2), (1, 1)]],
        "ProfilePointsNotFinite": [[(0, 0), (1, NAN), (0, 1)]],
    }
    for code, loops in cases.items():
        with pytest.raises(ProfileError) as info:
            profile_from_polygons([np.array(l, float) for l in loops], name="t")
        assert assets.classify_profile_error(str(info.value))[0] == code, str(info.value)
    assert assets.classify_profile_error("something new")[0] == "ProfileInvalid"


# --------------------------------------------------------------------------------------
# Tables (fiber:table)
# --------------------------------------------------------------------------------------


def _table_stage(tmp_path, asset: str):
    stage = Usd.Stage.CreateNew(str(tmp_path / "scene.usda"))
    UsdGeom.SetStageMetersPerUnit(stage, 1e-6)
    prim = add_curves(stage, "/F", [4], widths=[10.0], interpolation="constant")
    if asset:
        prim.GetAttribute("fiber:table").Set(Sdf.AssetPath(asset))
    return stage, prim


def _write(path, key, inputs=None):
    from usdfiber.table_format import write_table

    write_table(path, {"geometry_key": key, "inputs": inputs or {}, "resolution": [1],
                       "photons": 0, "error_estimate": 0}, {"t": np.zeros(2, np.float32)})


def test_table_checks(tmp_path):
    from usdfiber.spec.fiber import FiberParams

    _, prim = _table_stage(tmp_path, "")
    assert assets.check_table_prim(prim) == []  # unset: cache lookup, nothing to check

    prim.GetAttribute("fiber:table").Set(Sdf.AssetPath("tables/missing.npz"))
    p = only(assets.check_table_prim(prim), "TableMissing")
    assert p.severity is Severity.ERROR and p.attribute == "fiber:table"

    (tmp_path / "corrupt.npz").write_bytes(b"PK\x03\x04 truncated")
    prim.GetAttribute("fiber:table").Set(Sdf.AssetPath("corrupt.npz"))
    p = only(assets.check_table_prim(prim), "TableUnreadable")
    assert "corrupt" in p.message

    key = FiberParams.from_prim(prim).geometry_key()
    inputs = FiberParams.from_prim(prim).geometry_inputs()
    _write(tmp_path / "good.npz", key, inputs)
    prim.GetAttribute("fiber:table").Set(Sdf.AssetPath("./good.npz"))
    assert assets.check_table_prim(prim) == []

    # Another eta traces other paths: stale, and re-baked.
    prim.GetAttribute("fiber:ior:parallel").Set(1.6)
    p = only(assets.check_table_prim(prim), "TableStale")
    assert p.severity is Severity.WARNING and "re-baked" in p.message and "eta" in p.message
    # Dye and diameter only recolour: the table stays valid.
    prim.GetAttribute("fiber:ior:parallel").Set(1.73)
    prim.GetAttribute("fiber:diameter").Set(12.0)
    prim.GetAttribute("fiber:dye:depthOfShade").Set(2.0)
    assert assets.check_table_prim(prim) == []


def test_rewritten_table_is_read_again(tmp_path):
    from usdfiber.spec.fiber import FiberParams

    _, prim = _table_stage(tmp_path, "t.npz")
    _write(tmp_path / "t.npz", "0" * 64)
    assert codes(assets.check_table_prim(prim)) == ["TableStale"]
    time.sleep(0.01)  # a new mtime even on coarse clocks with the size unchanged
    _write(tmp_path / "t.npz", FiberParams.from_prim(prim).geometry_key())
    assert assets.check_table_prim(prim) == []


def test_table_on_unresolvable_params_reports_only_the_table(tmp_path):
    _, prim = _table_stage(tmp_path, "t.npz")
    _write(tmp_path / "t.npz", "0" * 64)
    prim.GetAttribute("fiber:profile").Set("user")  # no sources: FiberParamsError
    assert assets.check_table_prim(prim) == []


def test_every_kind_combination_is_covered():
    # Guard for the parametrized valid-curve test above: all 3 x 3 kinds (+ linear).
    kinds = {k for k, _ in _VALID_COUNTS}
    wraps = {w for _, w in _VALID_COUNTS}
    assert set(itertools.product(kinds, wraps)) == set(_VALID_COUNTS)


def test_corpus_stale_table_is_a_valid_table_for_other_parameters():
    """tests/corpus/assets/stale_table.npz must stay readable and stale for
    tests/corpus/bad/table_stale.usda (rewrite it with table_format.write_table, keeping a
    geometry_key that differs from the prim's, if the table format changes)."""
    from pathlib import Path

    from usdfiber.spec.fiber import FiberParams
    from usdfiber.table_format import read_header

    corpus = Path(__file__).resolve().parents[1] / "corpus"
    header = read_header(corpus / "assets" / "stale_table.npz", verify=True)
    stage = Usd.Stage.Open(str(corpus / "bad" / "table_stale.usda"))
    prim = stage.GetPrimAtPath("/World/Fibers")
    assert header["geometry_key"] != FiberParams.from_prim(prim).geometry_key()
    assert codes(assets.check_table_prim(prim)) == ["TableStale"]
