"""UsdGeomBasisCurves -> Mitsuba B-spline curves: fidelity against an independent USD evaluation."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

import usdfiber  # noqa: F401  (registers schemas before any stage is opened)
from pxr import Gf, Sdf, Usd, UsdGeom, Vt

from usdfiber.backend import mitsuba
from usdfiber.translators.mitsuba import curves as C

# ---------------------------------------------------------------------------------------------
# Independent evaluation of the USD definition (UsdGeomBasisCurves docs), one curve at a time.
# Basis matrices for P(t) = [t^3, t^2, t, 1] @ M @ [P0, P1, P2, P3], written from the spec.
# ---------------------------------------------------------------------------------------------
SPEC = {
    "bezier": np.array([[-1, 3, -3, 1], [3, -6, 3, 0], [-3, 3, 0, 0], [1, 0, 0, 0]], float),
    "bspline": np.array([[-1, 3, -3, 1], [3, -6, 3, 0], [-3, 0, 3, 0], [1, 4, 1, 0]], float) / 6,
    "catmullRom": np.array([[-1, 3, -3, 1], [2, -5, 4, -1], [-1, 0, 1, 0], [0, 2, 0, 0]], float) / 2,
}
TYPES, BASES, WRAPS = ("linear", "cubic"), ("bezier", "bspline", "catmullRom"), ("nonperiodic", "periodic", "pinned")
INTERPS = ("constant", "uniform", "varying", "vertex")


def usd_segments(ctype, basis, wrap, counts, points, widths, interp):
    """Per segment, in USD order: a function t -> (local position (3,), width)."""
    segs, off, voff = [], 0, 0
    for ci, n in enumerate(counts):
        P = np.asarray(points[off:off + n], float)
        W = np.asarray(widths[off:off + n], float) if interp == "vertex" else None
        if ctype == "linear":
            m = n if wrap == "periodic" else n - 1
            ends = [(k, (k + 1) % n) for k in range(m)]
            seg_fns = [(lambda t, a=a, b=b, P=P, W=W: (
                P[a] * (1 - t) + P[b] * t, None if W is None else W[a] * (1 - t) + W[b] * t))
                for a, b in ends]
        else:
            vstep = 3 if basis == "bezier" else 1
            if wrap == "pinned" and basis != "bezier":  # phantom points, USD docs
                P = np.vstack([2 * P[0] - P[1], P, 2 * P[-1] - P[-2]])
                if W is not None:  # vertex widths extended by the same rule (module's choice)
                    W = np.r_[2 * W[0] - W[1], W, 2 * W[-1] - W[-2]]
            nn = len(P)
            if wrap == "periodic":
                m = nn // vstep
                win = [[(k * vstep + j) % nn for j in range(4)] for k in range(m)]
            else:
                m = (nn - 4) // vstep + 1
                win = [[k * vstep + j for j in range(4)] for k in range(m)]
            M = SPEC[basis]

            def fn(t, w, P=P, W=W, M=M):
                T = np.array([t**3, t**2, t, 1.0])
                return (T @ M @ P[w], None if W is None else T @ M @ W[w])

            seg_fns = [(lambda t, w=w, fn=fn: fn(t, w)) for w in win]
        nvary = m if wrap == "periodic" else m + 1
        for k, f in enumerate(seg_fns):
            def g(t, f=f, k=k, ci=ci, voff=voff, nvary=nvary):
                p, wv = f(t)
                if interp == "constant":
                    wv = widths[0]
                elif interp == "uniform":
                    wv = widths[ci]
                elif interp == "varying":
                    a, b = widths[voff + k], widths[voff + (k + 1) % nvary]
                    wv = a * (1 - t) + b * t
                return p, wv
            segs.append((ci, g))
        off += n
        voff += nvary
    return segs


def vertex_counts(ctype, basis, wrap):
    if ctype == "linear":
        return [4, 6] if wrap == "periodic" else [3, 5]
    if basis == "bezier":
        return [6, 9] if wrap == "periodic" else [4, 7]
    return {"nonperiodic": [4, 6], "periodic": [5, 7], "pinned": [2, 5]}[wrap]


def n_segments(ctype, basis, wrap, counts):
    if ctype == "linear":
        return [n if wrap == "periodic" else n - 1 for n in counts]
    v = 3 if basis == "bezier" else 1
    if wrap == "periodic":
        return [n // v for n in counts]
    if wrap == "pinned" and basis != "bezier":
        return [n - 1 for n in counts]
    return [(n - 4) // v + 1 for n in counts]


def curve_points(counts, periodic):
    pts = []
    for c, n in enumerate(counts):
        th = 2 * np.pi * np.arange(n) / n if periodic else 1.5 * np.pi * np.arange(n) / max(n - 1, 1)
        pts += [(2 * np.cos(a) + 6 * c, 2 * np.sin(a), 0.3 * np.sin(2 * a + c)) for a in th]
    return pts


def width_values(interp, ctype, basis, wrap, counts):
    nseg = n_segments(ctype, basis, wrap, counts)
    n = {"constant": 1, "uniform": len(counts), "vertex": sum(counts),
         "varying": sum(s if wrap == "periodic" else s + 1 for s in nseg)}[interp]
    # Alternating thin/thick: the linear-width extension then has negative radius controls.
    return [0.03 + 0.12 * (i % 2) if interp in ("varying", "vertex") else 0.06 + 0.03 * i for i in range(n)]


def define_curves(stage, path, ctype, basis, wrap, counts, points, widths, interp):
    bc = UsdGeom.BasisCurves.Define(stage, path)
    bc.CreateTypeAttr(ctype)
    bc.CreateBasisAttr(basis)
    bc.CreateWrapAttr(wrap)
    bc.CreateCurveVertexCountsAttr(counts)
    bc.CreatePointsAttr([Gf.Vec3f(*p) for p in points])
    if widths is not None:
        bc.CreateWidthsAttr(widths)
        bc.SetWidthsInterpolation(interp)
    return bc


COMBOS = list(itertools.product(TYPES, BASES, WRAPS, INTERPS))


@pytest.fixture(scope="module")
def mi():
    return mitsuba()


@pytest.fixture(scope="module")
def combo_stage():
    """One prim per combination, each under an Xform with translate, rotation and uniform scale."""
    stage = Usd.Stage.CreateInMemory()
    prims = []
    for i, (ctype, basis, wrap, interp) in enumerate(COMBOS):
        x = UsdGeom.Xform.Define(stage, f"/W/X{i}")
        # a compact grid keeps coordinates small: Mitsuba stores float32
        x.AddTranslateOp().Set(Gf.Vec3d(12.0 * (i % 4), 6.0 * (i // 4 % 6), 6.0 * (i // 24)))
        x.AddRotateXYZOp().Set(Gf.Vec3f(7.0 * i, 20.0, -35.0))
        x.AddScaleOp().Set(Gf.Vec3f(0.6 + 0.05 * (i % 5)))
        counts = vertex_counts(ctype, basis, wrap)
        pts = curve_points(counts, wrap == "periodic")
        w = width_values(interp, ctype, basis, wrap, counts)
        bc = define_curves(stage, f"/W/X{i}/c", ctype, basis, wrap, counts, pts, w, interp)
        # evaluate what the stage stores (float32), not the doubles it was authored from
        prims.append((bc.GetPrim(), counts, np.array(bc.GetPointsAttr().Get(), float),
                      np.array(bc.GetWidthsAttr().Get(), float)))
    return stage, prims


def usd_world_samples(prim, combo, counts, pts, w, ts):
    """World positions, radii and unit tangents from the independent USD evaluation."""
    ctype, basis, wrap, interp = combo
    m = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default()))
    scale = abs(np.linalg.det(m[:3, :3])) ** (1 / 3)
    segs = usd_segments(ctype, basis, wrap, counts, pts, w, interp)
    pos, rad, tan = [], [], []
    for _, f in segs:
        for t in ts:
            p, wv = f(t)
            dp = (f(t + 1e-6)[0] - f(t - 1e-6)[0])
            pos.append(np.r_[p, 1] @ m)
            rad.append(0.5 * wv * scale)
            tan.append(dp @ m[:3, :3])
    tan = np.array(tan)
    return (np.array(pos)[:, :3], np.array(rad), tan / np.linalg.norm(tan, axis=1)[:, None],
            len(segs))


def test_conversion_matrices_match_field_notes():
    """The derived basis changes equal the tables in the field notes, and the spec matrices."""
    np.testing.assert_allclose(C.TO_BSPLINE["bezier"],
                               [[6, -7, 2, 0], [0, 2, -1, 0], [0, -1, 2, 0], [0, 2, -7, 6]], atol=1e-12)
    np.testing.assert_allclose(C.TO_BSPLINE["catmullRom"] * 6,
                               [[7, -4, 5, -2], [-2, 11, -4, 1], [1, -4, 11, -2], [-2, 5, -4, 7]],
                               atol=1e-12)
    np.testing.assert_allclose(C.TO_BSPLINE["bspline"], np.eye(4), atol=1e-12)
    for k in SPEC:
        np.testing.assert_allclose(C.POWER_BASIS[k], SPEC[k], atol=1e-15)


def occluded(o, d, length, pos, rad, ray_seg, sample_seg):
    """Rays (o, d, length) that pass within reach of another segment of the same geometry.

    pos/rad: dense centerline samples (K, 3)/(K,) of the segments sample_seg (K,). Conservative:
    spheres around the samples, grown by the spacing of the samples.
    """
    v = pos[None, :, :] - o[:, None, :]
    h = np.clip(np.einsum("rkc,rc->rk", v, d), 0, length[:, None])
    dist = np.linalg.norm(v - h[..., None] * d[:, None, :], axis=2)
    same = sample_seg[1:] == sample_seg[:-1]
    gap = np.where(same, np.linalg.norm(np.diff(pos, axis=0), axis=1), 0)
    spacing = np.maximum(np.r_[gap, 0], np.r_[0, gap])
    near = dist < rad[None] * 1.001 + spacing[None]
    return np.any(near & (ray_seg[:, None] != sample_seg[None, :]), axis=1)


def test_every_combination_exact_and_hit_by_rays(mi, combo_stage):
    """All 72 type/basis/wrap/widths combinations: the B-spline evaluation equals USD's (1e-9)
    and rays cast perpendicular to the curve from 5r hit the Mitsuba shape at 4r (1e-3 r)."""
    stage, prims = combo_stage
    ts = np.array([0.1, 0.3, 0.5, 0.7, 0.9])
    dense = np.linspace(0, 1, 401)
    shapes, origins, dirs, expect, keep, radii_seen = {}, [], [], [], [], []
    for i, (combo, (prim, counts, pts, w)) in enumerate(zip(COMBOS, prims)):
        geom = C.curves_from_prim(prim)
        assert geom.warnings == [], combo
        pos, rad, tan, nseg = usd_world_samples(prim, combo, counts, pts, w, ts)
        assert geom.segment_count == nseg == sum(n_segments(*combo[:3], counts)), combo
        assert geom.curve_count == 2
        seg = np.repeat(np.arange(nseg), len(ts))
        gp, gr, _ = C.evaluate(geom, seg, np.tile(ts, nseg))
        np.testing.assert_allclose(gp, pos, rtol=0, atol=1e-9 * max(1, np.abs(pos).max()), err_msg=str(combo))
        np.testing.assert_allclose(gr, rad, rtol=0, atol=1e-12, err_msg=str(combo))
        assert np.all(np.diff(geom.segment_curve) >= 0) and geom.segment_curve[-1] == 1
        radii_seen.append(geom.radii.min())
        shapes[f"s{i}"] = C.make_curve_shape(geom, {"type": "diffuse"}, shape_id=f"s{i}")
        # dense centerline samples for the occlusion screen (the evaluation was just checked)
        dseg = np.repeat(np.arange(nseg), len(dense))
        dpos, drad, _ = C.evaluate(geom, dseg, np.tile(dense, nseg))
        # two directions perpendicular to the tangent: roughly world +z, and their cross product
        a = np.array([0.3, -0.2, 1.0]) - (tan @ [0.3, -0.2, 1.0])[:, None] * tan
        a /= np.linalg.norm(a, axis=1)[:, None]
        for d in (a, np.cross(tan, a)):
            o = pos + 5 * rad[:, None] * d
            origins.append(o)
            dirs.append(-d)
            expect.append(4 * rad)
            keep.append(~occluded(o, -d, 4 * rad, dpos, drad, seg, dseg))
    # the varying-width extension produced negative radius controls, and rays still hit exactly
    assert min(radii_seen) < 0
    scene = mi.load_dict({"type": "scene", **shapes})
    o, d, e, keep = np.vstack(origins), np.vstack(dirs), np.concatenate(expect), np.concatenate(keep)
    assert keep.mean() > 0.99  # only rays that graze a kinked neighbour segment are left out
    ray = mi.Ray3f(mi.Point3f(*(mi.Float(o[:, k]) for k in range(3))),
                   mi.Vector3f(*(mi.Float(d[:, k]) for k in range(3))))
    hit = np.array(scene.ray_intersect(ray).t)
    r = e / 4
    err = np.abs(hit - e)
    # 1e-3 r, plus float32 rounding of coordinates (Mitsuba's control points are float32)
    bad = keep & ~(err <= 1e-3 * r + 1e-6 * np.abs(o).max(axis=1))
    assert not bad.any(), f"{bad.sum()} of {keep.sum()} rays off; worst rel {np.nanmax(err[keep] / r[keep]):.3g}"


def test_transform_convention_and_nonuniform_scale():
    stage = Usd.Stage.CreateInMemory()
    x = UsdGeom.Xform.Define(stage, "/X")
    x.AddTranslateOp().Set(Gf.Vec3d(1, 2, 3))
    x.AddRotateZOp().Set(90.0)
    x.AddScaleOp().Set(Gf.Vec3f(2, 2, 2))
    bc = define_curves(stage, "/X/c", "linear", "bezier", "nonperiodic", [2],
                       [(1, 0, 0), (1, 1, 0)], [0.5], "constant")
    g = C.curves_from_prim(bc.GetPrim())
    # scale 2 then rotate +90 deg about z then translate: (1,0,0) -> (0,2,0) + t; (1,1,0) -> (-2,2,0) + t
    p0, r0, _ = C.evaluate(g, [0, 0], [0.0, 1.0])
    np.testing.assert_allclose(p0, [[1, 4, 3], [-1, 4, 3]], atol=1e-12)
    np.testing.assert_allclose(r0, [0.5, 0.5], atol=1e-12)  # 0.5 / 2 * 2
    assert g.warnings == []
    # an explicit xform overrides the prim's transform
    g2 = C.curves_from_prim(bc.GetPrim(), xform=np.diag([1.0, 1.0, 1.0, 1.0]))
    np.testing.assert_allclose(C.evaluate(g2, 0, 1.0)[0], [1, 1, 0], atol=1e-12)
    # non-uniform scale: positions exact, radius by the geometric mean, with a warning
    x.GetPrim().GetAttribute("xformOp:scale").Set(Gf.Vec3f(1, 2, 4))
    g3 = C.curves_from_prim(bc.GetPrim())
    np.testing.assert_allclose(C.evaluate(g3, 0, 1.0)[0], [1 - 2, 2 + 1, 3], atol=1e-12)
    np.testing.assert_allclose(g3.radii, 0.25 * 2.0, atol=1e-12)
    assert len(g3.warnings) == 1 and "/X/c" in g3.warnings[0] and "non-uniform scale" in g3.warnings[0]


def test_values_too_large_for_float32_in_world_space():
    """A transform that takes finite points or widths beyond the float32 bound is refused (the
    curve would vanish from the render), naming the prim; the authored values are fine."""
    stage = Usd.Stage.CreateInMemory()
    bc = define_curves(stage, "/X/c", "cubic", "bspline", "nonperiodic", [4], curve_points([4], False),
                       [0.5], "constant")
    xf = UsdGeom.Xform.Define(stage, "/X")
    xf.AddScaleOp().Set(Gf.Vec3f(1e19, 1e19, 1e19))
    with pytest.raises(C.CurveError, match=r"/X/c: in world space .* of magnitude 1e\+18 or more .*float32"):
        C.curves_from_prim(bc.GetPrim())
    # Zero widths stay valid at any scale; a zero scale too (both draw nothing, by design).
    bc.GetWidthsAttr().Set(Vt.FloatArray([0.0]))
    bc.GetPointsAttr().Set(Vt.Vec3fArray([(0, 0, 0), (0.01, 0, 0), (0.02, 0, 0), (0.03, 0, 0)]))
    assert C.curves_from_prim(bc.GetPrim()).segment_count == 1
    xf.GetPrim().GetAttribute("xformOp:scale").Set(Gf.Vec3f(0, 0, 0))
    assert C.curves_from_prim(bc.GetPrim()).segment_count == 1


def test_widths_sources_and_warnings():
    stage = Usd.Stage.CreateInMemory()
    pts = curve_points([4], False)
    bc = define_curves(stage, "/c", "cubic", "bspline", "nonperiodic", [4], pts, [9.0], "constant")
    pv = UsdGeom.PrimvarsAPI(bc.GetPrim()).CreatePrimvar("widths", Sdf.ValueTypeNames.FloatArray,
                                                         UsdGeom.Tokens.vertex)
    pv.Set([0.2, 0.4])
    pv.SetIndices(Vt.IntArray([0, 1, 1, 0]))  # indexed primvar, flattened
    g = C.curves_from_prim(bc.GetPrim())
    np.testing.assert_allclose(g.radii, [0.1, 0.2, 0.2, 0.1])  # primvars:widths wins over widths
    # missing widths: error unless a default is given
    bc2 = define_curves(stage, "/d", "cubic", "bspline", "nonperiodic", [4], pts, None, None)
    with pytest.raises(C.CurveError, match=r"/d\.widths: "):
        C.curves_from_prim(bc2.GetPrim())
    g2 = C.curves_from_prim(bc2.GetPrim(), default_width=0.3)
    np.testing.assert_allclose(g2.radii, 0.15)
    # ribbons
    bc2.CreateNormalsAttr([(0, 0, 1)] * 4)
    g3 = C.curves_from_prim(bc2.GetPrim(), default_width=0.3)
    assert any("/d" in w and "normals" in w and "round tubes" in w for w in g3.warnings)
    # Catmull-Rom vertex widths that dip below zero in USD's own interpolation
    bc4 = define_curves(stage, "/e", "cubic", "catmullRom", "nonperiodic", [4], pts,
                        [1.0, 0.0, 0.0, 1.0], "vertex")
    g4 = C.curves_from_prim(bc4.GetPrim())
    assert len(g4.warnings) == 1 and "/e" in g4.warnings[0] and "negative" in g4.warnings[0]
    assert "widths" in g4.warnings[0]


@pytest.mark.parametrize("case", [
    "sum", "bspline3", "bezier5", "bezier_periodic4", "pinned1", "linear1", "nan", "negcount",
    "widths_vertex", "widths_varying", "widths_uniform", "widths_constant", "widths_nan",
    "widths_negative", "type_token", "interp_token", "huge", "widths_huge",
])
def test_errors_name_prim_and_attribute(case):
    stage = Usd.Stage.CreateInMemory()
    args = dict(ctype="cubic", basis="bspline", wrap="nonperiodic", counts=[4, 5], interp="vertex")
    attr = "curveVertexCounts"
    if case == "bspline3":
        args["counts"] = [4, 3]
    elif case == "bezier5":
        args.update(basis="bezier", counts=[4, 5])
    elif case == "bezier_periodic4":
        args.update(basis="bezier", wrap="periodic", counts=[6, 4])
    elif case == "pinned1":
        args.update(wrap="pinned", counts=[1, 3])
    elif case == "linear1":
        args.update(ctype="linear", counts=[1, 3])
    elif case == "negcount":
        args["counts"] = [-1, 10]
    pts = curve_points([max(sum(args["counts"]), 0) + (case == "sum")], False)
    widths = [0.1] * len(pts)
    if case in ("nan", "huge"):
        pts[2] = (np.nan if case == "nan" else 1e30, 0, 0)
        attr = "points"
    if case.startswith("widths"):
        attr = "widths"
        kind = case.split("_")[1]
        args["interp"] = {"nan": "vertex", "negative": "vertex", "huge": "vertex"}.get(kind, kind)
        widths = {"vertex": [0.1] * 8, "varying": [0.1] * 4, "uniform": [0.1] * 3,
                  "constant": [0.1, 0.2], "nan": [0.1] * 8 + [np.nan], "negative": [0.1] * 8 + [-1],
                  "huge": [0.1] * 8 + [1e30]}[kind]
    bc = define_curves(stage, "/Root/bad", args["ctype"], args["basis"], args["wrap"], args["counts"],
                       pts, widths, args["interp"])
    if case == "type_token":
        bc.GetTypeAttr().Set("quadratic")
        attr = "type"
    if case == "interp_token":
        bc.GetWidthsAttr().SetMetadata("interpolation", "perPixel")
        attr = "widths"
    with pytest.raises(C.CurveError) as ei:
        C.curves_from_prim(bc.GetPrim())
    msg = str(ei.value)
    assert f"/Root/bad.{attr}: " in msg, msg
    assert isinstance(ei.value, ValueError)


def test_array_built_shape_matches_text_file(mi, tmp_path, combo_stage):
    """make_curve_shape (arrays) gives bit-identical hits to Mitsuba's own text-file loader."""
    _, prims = combo_stage
    for combo in [("cubic", "catmullRom", "periodic", "varying"), ("cubic", "bspline", "pinned", "vertex")]:
        geom = C.curves_from_prim(prims[COMBOS.index(combo)][0])
        if combo[1] == "bspline":  # shared control points: whole curves are contiguous runs
            starts = geom.segment_start
            runs = np.split(np.arange(len(starts)), np.flatnonzero(np.diff(starts) != 1) + 1)
            chunks = [np.arange(starts[r[0]], starts[r[-1]] + 4) for r in runs]
        else:
            chunks = [s + np.arange(4) for s in geom.segment_start]
        assert sum(len(c) - 3 for c in chunks) == geom.segment_count
        text = "\n".join("\n".join(f"{x:.9g} {y:.9g} {z:.9g} {r:.9g}" for (x, y, z), r in
                                   zip(np.float32(geom.points[c]), np.float32(geom.radii[c])))
                         + "\n" for c in chunks)
        (tmp_path / "c.txt").write_text(text)
        a = mi.load_dict({"type": "scene", "c": C.make_curve_shape(geom)})
        b = mi.load_dict({"type": "scene", "c": {"type": "bsplinecurve", "filename": str(tmp_path / "c.txt")}})
        rng = np.random.default_rng(1)
        tgt, _, _ = C.evaluate(geom, rng.integers(0, geom.segment_count, 4000), rng.random(4000))
        org = tgt + rng.normal(size=(4000, 3)) * 3
        d = tgt + rng.normal(size=(4000, 3)) * 0.05 - org
        d /= np.linalg.norm(d, axis=1)[:, None]
        ray = mi.Ray3f(mi.Point3f(*(mi.Float(org[:, k]) for k in range(3))),
                       mi.Vector3f(*(mi.Float(d[:, k]) for k in range(3))))
        sa, sb = a.ray_intersect(ray), b.ray_intersect(ray)
        ta, tb = np.array(sa.t), np.array(sb.t)
        assert np.isfinite(ta).mean() > 0.3
        np.testing.assert_array_equal(ta, tb)
        valid = np.isfinite(ta)
        np.testing.assert_array_equal(np.array(sa.prim_index)[valid], np.array(sb.prim_index)[valid])
        ua, ub = np.array(sa.uv)[:, valid], np.array(sb.uv)[:, valid]
        np.testing.assert_array_equal(ua[0], ub[0])
        # v runs over the whole shape, which has one unreachable guard segment more (see
        # make_curve_shape): the same curve parameter.
        n_seg = geom.segment_count
        np.testing.assert_allclose(ua[1] * (n_seg + 1), ub[1] * n_seg, rtol=1e-5, atol=1e-5 * n_seg)
        np.testing.assert_array_equal(np.array(sa.n)[:, valid], np.array(sb.n)[:, valid])


def test_hits_at_the_end_of_a_long_shape_get_no_nan_from_the_fiber_bsdf(mi):
    """With many segments, the float32 curve parameter of a hit near the end of a shape's last
    segment rounds into the guard segment (make_curve_shape) and Mitsuba 3.9.1 gives the hit a
    NaN shading frame (seen as NaN pixels at yarn ends under volpath). The fiber BSDF treats
    such hits as absorbing: every output finite, nothing scattered or passed."""
    import drjit as dr

    from usdfiber.bake import profiles
    from usdfiber.bake.baker import bake_table
    from usdfiber.bake.settings import BakeSettings
    from usdfiber.translators.mitsuba.fiber_bank import FiberBank, FiberSlot
    from usdfiber.translators.mitsuba.fiber_bsdf import fiber_bsdf

    n = 200_000
    x = np.arange(n + 3, dtype=float)              # unit segments: rays meet few of them
    geom = C.CurveGeometry(np.stack([x, 0 * x, 0 * x], 1), np.full(n + 3, 0.2), np.arange(n),
                           np.zeros(n, np.int64), 1)
    end, _, _ = C.evaluate(geom, np.array([n - 1]), np.array([1.0]))
    rng = np.random.default_rng(3)
    m = 20000
    org = end[0] + np.stack([rng.uniform(-0.05, 0.2, m), rng.uniform(-0.2, 0.2, m), np.ones(m)], 1)
    # A flat silk profile: the BSDF has pass-through (Null), as under volpath.
    table = bake_table(profiles.builtin_profiles("silk", 1)[0], 1.55, 8.0, None,
                       BakeSettings(resolution_deg=30, photons=500, batches=2))
    bsdf = fiber_bsdf(mi, FiberBank.build([FiberSlot(table, (0.1, 0.1, 0.1))]), np.zeros(n, np.int64),
                      np.zeros(n), np.tile([0.0, 0.0, 1.0], (n, 1)))
    scene = mi.load_dict({"type": "scene", "c": C.make_curve_shape(geom, bsdf)})
    si = scene.ray_intersect(mi.Ray3f(mi.Point3f(*(mi.Float(org[:, k]) for k in range(3))),
                                      mi.Vector3f(0.0, 0.0, -1.0)))
    valid = np.array(si.is_valid())
    bad = valid & ~np.isfinite(np.array(si.sh_frame.t)).all(axis=0)
    assert bad.sum() > 100             # the upstream behaviour this guards against
    ctx = mi.BSDFContext()
    wo = mi.Vector3f(0.3, 0.4, 0.866)
    f, pdf = bsdf.eval_pdf(ctx, si, wo, si.is_valid())
    bs, w = bsdf.sample(ctx, si, mi.Float(rng.random(m).astype(np.float32)),
                        mi.Point2f(mi.Float(rng.random(m).astype(np.float32)),
                                   mi.Float(rng.random(m).astype(np.float32))), si.is_valid())
    tr = bsdf.eval_null_transmission(si, si.is_valid())
    dr.eval(f, pdf, bs, w, tr)
    for name, a in (("eval", f), ("pdf", pdf), ("sample weight", w), ("sample pdf", bs.pdf),
                    ("null transmission", tr)):
        arr = np.array(a)
        assert np.isfinite(arr).all(), name
        assert not np.any(arr.reshape(-1, m)[:, bad]), name     # absorbed
    # and the well-framed hits scatter as usual
    assert np.array(bs.pdf)[valid & ~bad].min() > 0


def test_concatenate_offsets_and_provenance():
    stage = Usd.Stage.CreateInMemory()
    a = define_curves(stage, "/a", "cubic", "bspline", "nonperiodic", [4, 5], curve_points([4, 5], False),
                      [0.1], "constant")
    b = define_curves(stage, "/b", "linear", "bspline", "nonperiodic", [3], curve_points([3], False),
                      [0.1], "constant")
    ga, gb = C.curves_from_prim(a.GetPrim()), C.curves_from_prim(b.GetPrim())
    g = C.concatenate([ga, gb])
    assert g.curve_count == 3 and g.segment_count == ga.segment_count + gb.segment_count
    np.testing.assert_array_equal(g.segment_part, [0] * ga.segment_count + [1] * gb.segment_count)
    np.testing.assert_array_equal(g.segment_curve, np.r_[ga.segment_curve, gb.segment_curve + 2])
    ts = np.linspace(0, 1, 7)
    for part, sub in ((0, ga), (1, gb)):
        off = 0 if part == 0 else ga.segment_count
        for s in range(sub.segment_count):
            np.testing.assert_array_equal(C.evaluate(g, off + s, ts)[0], C.evaluate(sub, s, ts)[0])
    np.testing.assert_allclose(C.reference_normals(g), np.vstack([C.reference_normals(ga),
                                                                  C.reference_normals(gb)]), atol=1e-12)


def test_reference_normals_in_chunks_of_whole_curves_are_the_same(monkeypatch):
    """Long geometry is framed in chunks of whole curves (bounded memory): the same values, a
    chunk boundary never splits a curve's frame."""
    from usdfiber.geometry import curves as geometry_curves

    rng = np.random.default_rng(1)
    stage = Usd.Stage.CreateInMemory()
    counts = [5, 40, 7, 300, 4, 60]
    pts = np.cumsum(rng.normal(size=(sum(counts), 3)), axis=0)
    g = C.curves_from_prim(define_curves(stage, "/c", "cubic", "bspline", "pinned", counts, pts.tolist(),
                                         [0.1], "constant").GetPrim())
    whole = C.reference_normals(g)
    for chunk in (1, 16, 100):
        monkeypatch.setattr(geometry_curves, "NORMALS_CHUNK", chunk)
        np.testing.assert_array_equal(C.reference_normals(g), whole)


def _helix_geometry(n=4000, turns=12.0):
    stage = Usd.Stage.CreateInMemory()
    th = np.linspace(0, 2 * np.pi * turns, n)
    pts = np.c_[np.cos(th), np.sin(th), 0.15 * th]
    bc = define_curves(stage, "/h", "cubic", "bspline", "pinned", [n], pts.tolist(), [0.01], "constant")
    return C.curves_from_prim(bc.GetPrim())


def test_reference_normals_rmf_on_helix():
    g = _helix_geometry()
    n = C.reference_normals(g)
    _, _, d = C.evaluate(g, np.arange(g.segment_count), 0.5)
    t = d / np.linalg.norm(d, axis=1)[:, None]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1, atol=1e-12)
    assert np.abs(np.einsum("ij,ij->i", n, t)).max() < 1e-9
    assert np.einsum("ij,ij->i", n[1:], n[:-1]).min() > 0.9
    # equal to a straightforward sequential double-reflection (Wang et al. 2008) propagation
    x, _, _ = C.evaluate(g, np.arange(g.segment_count), 0.5)
    r = [n[0]]
    for i in range(len(x) - 1):
        v1 = x[i + 1] - x[i]
        c1 = v1 @ v1
        rl = r[-1] - 2 / c1 * (v1 @ r[-1]) * v1
        tl = t[i] - 2 / c1 * (v1 @ t[i]) * v1
        v2 = t[i + 1] - tl
        c2 = v2 @ v2
        r.append(rl - 2 / c2 * (v2 @ rl) * v2 if c2 > 1e-24 else rl)
    np.testing.assert_allclose(n, np.array(r), atol=1e-8)
    # deterministic first normal: world +z projected on the normal plane
    z = np.array([0, 0, 1.0]) - t[0, 2] * t[0]
    np.testing.assert_allclose(n[0], z / np.linalg.norm(z), atol=1e-12)


def test_time_samples_shape_inputs_and_empty(mi):
    stage = Usd.Stage.CreateInMemory()
    bc = define_curves(stage, "/c", "linear", "bezier", "nonperiodic", [2], [(0, 0, 0), (1, 0, 0)],
                       [0.2], "constant")
    bc.GetPointsAttr().Set([Gf.Vec3f(0, 0, 0), Gf.Vec3f(1, 0, 0)], 1.0)
    bc.GetPointsAttr().Set([Gf.Vec3f(0, 0, 0), Gf.Vec3f(3, 0, 0)], 2.0)
    end = [C.evaluate(C.curves_from_prim(bc.GetPrim(), Usd.TimeCode(t)), 0, 1.0)[0] for t in (1.0, 1.5, 2.0)]
    np.testing.assert_allclose(end, [[1, 0, 0], [2, 0, 0], [3, 0, 0]], atol=1e-12)
    g = C.curves_from_prim(bc.GetPrim(), Usd.TimeCode(1.0))
    shape = C.make_curve_shape(g, mi.load_dict({"type": "diffuse"}), shape_id="fibers")
    assert shape.id() == "fibers" and shape.bsdf() is not None
    empty = define_curves(stage, "/e", "cubic", "bspline", "nonperiodic", [], [], [0.1], "constant")
    ge = C.curves_from_prim(empty.GetPrim())
    assert ge.segment_count == 0 and ge.curve_count == 0 and C.reference_normals(ge).shape == (0, 3)
    with pytest.raises(ValueError, match="no curve segments"):
        C.make_curve_shape(ge)
    assert C.concatenate([]).segment_count == 0
    with pytest.raises(C.CurveError, match="/W.*not a BasisCurves"):
        C.curves_from_prim(UsdGeom.Xform.Define(stage, "/W").GetPrim())
