"""Procedural cloth (usdfiber.cloth, ``usdfiber cloth``): knits and weaves.

Geometry is read back from USD and evaluated here with an independent uniform cubic
B-spline evaluator; distances between yarns are measured on the evaluated curves.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

import usdfiber  # noqa: F401  (registers the schemas before any stage exists)
from pxr import Usd, UsdGeom

from usdfiber import authoring, cloth
from usdfiber.cli import main
from usdfiber.presets import YARN_PRESETS
from usdfiber.validation.runner import check_stage

CNE50_D = YARN_PRESETS["CNe 50"].yarn_diameter_mm

# Uniform cubic B-spline basis matrix (rows: powers u^0..u^3 of the blending functions).
BSPLINE = np.array([[1, 4, 1, 0], [-3, 0, 3, 0], [3, -6, 3, 0], [-1, 3, -3, 1]]) / 6.0


def evaluate(ctrl: np.ndarray, per_segment: int = 24) -> np.ndarray:
    ctrl = np.asarray(ctrl, dtype=np.float64)
    u = np.linspace(0, 1, per_segment, endpoint=False)
    powers = np.stack([np.ones_like(u), u, u * u, u ** 3], axis=1) @ BSPLINE
    segs = [powers @ ctrl[i:i + 4] for i in range(len(ctrl) - 3)]
    end = ((ctrl[-3] + 4 * ctrl[-2] + ctrl[-1]) / 6.0)[None, :]
    return np.vstack(segs + [end])


def new_stage() -> Usd.Stage:
    return Usd.Stage.CreateInMemory()


def yarns(prim: Usd.Prim) -> list[np.ndarray]:
    """Control points of every curve of a BasisCurves prim."""
    c = UsdGeom.BasisCurves(prim)
    assert c.GetTypeAttr().Get() == "cubic"
    assert c.GetBasisAttr().Get() == "bspline"
    assert c.GetWrapAttr().Get() == "nonperiodic"
    pts = np.array(c.GetPointsAttr().Get(), dtype=np.float64)
    out, start = [], 0
    for n in c.GetCurveVertexCountsAttr().Get():
        out.append(pts[start:start + n])
        start += n
    assert start == len(pts)
    return out


def min_distance(curves: list[np.ndarray]) -> float:
    """Smallest distance between points of different (evaluated) curves."""
    best = math.inf
    for i in range(len(curves)):
        tree = cKDTree(curves[i])
        for j in range(i + 1, len(curves)):
            best = min(best, float(tree.query(curves[j])[0].min()))
    return best


def width(prim: Usd.Prim) -> float:
    c = UsdGeom.BasisCurves(prim)
    assert c.GetWidthsInterpolation() == "constant"
    (w,) = c.GetWidthsAttr().Get()
    return float(w)


def assert_clean(stage: Usd.Stage) -> None:
    report = check_stage(stage)
    assert report.ok(True), report.to_text()  # no errors, no warnings


def assert_extent(prim: Usd.Prim) -> None:
    c = UsdGeom.BasisCurves(prim)
    lo, hi = (np.array(v) for v in c.GetExtentAttr().Get())
    pts = np.array(c.GetPointsAttr().Get())
    w = width(prim)
    np.testing.assert_allclose(lo, pts.min(0) - w / 2, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(hi, pts.max(0) + w / 2, rtol=1e-5, atol=1e-6)


# ------------------------------------------------------------------ knits
@pytest.mark.parametrize("gen", [cloth.stockinette, cloth.garter])
def test_knit_structure(gen):
    stage = new_stage()
    root = gen(stage, "/Knit", rows=5, loops=6)
    assert root.IsA(UsdGeom.Xform) and root.GetPath() == "/Knit"
    rows = stage.GetPrimAtPath("/Knit/Rows")
    assert [c.GetName() for c in root.GetChildren()] == ["Rows"]
    assert rows.HasAPI("FiberYarnAPI") and rows.HasAPI("FiberAPI")
    assert rows.GetAttribute("fiber:kind").Get() == "cotton"
    assert UsdGeom.GetStageMetersPerUnit(stage) == pytest.approx(0.001)
    ctrl = yarns(rows)
    assert len(ctrl) == 5
    assert len({len(c) for c in ctrl}) == 1
    assert width(rows) == pytest.approx(CNE50_D, rel=1e-6)
    assert_extent(rows)
    assert_clean(stage)


@pytest.mark.parametrize("gen", [cloth.stockinette, cloth.garter])
def test_knit_rows_repeat_every_loop(gen):
    """Each row is the same loop repeated: control points shift by one loop width."""
    stage = new_stage()
    loops = 5
    gen(stage, "/K", rows=3, loops=loops, samples_per_loop=12)
    for c in yarns(stage.GetPrimAtPath("/K/Rows")):
        n = (len(c) - 3) // loops
        assert len(c) == n * loops + 3 and n == 12
        shift = c[n:] - c[:-n]
        loop_width = shift[0, 0]
        assert loop_width > 0
        np.testing.assert_allclose(shift, np.tile([loop_width, 0.0, 0.0], (len(shift), 1)),
                                   atol=1e-5)
        # The evaluated curve too: sample the same phase in consecutive loops.
        e = evaluate(c, 8)
        per_loop = n * 8
        np.testing.assert_allclose(e[per_loop:2 * per_loop] - e[:per_loop],
                                   np.tile([loop_width, 0, 0], (per_loop, 1)), atol=1e-5)


def test_stockinette_rows_are_translates_and_garter_alternates_depth():
    st = new_stage()
    cloth.stockinette(st, "/S", rows=4, loops=3)
    s = yarns(st.GetPrimAtPath("/S/Rows"))
    dy = s[1][0, 1] - s[0][0, 1]
    assert dy > 0
    for r in range(1, 4):
        np.testing.assert_allclose(s[r] - s[0], np.tile([0, r * dy, 0], (len(s[0]), 1)), atol=1e-5)
    gt = new_stage()
    cloth.garter(gt, "/G", rows=4, loops=3)
    g = yarns(gt.GetPrimAtPath("/G/Rows"))
    for r in range(1, 4):
        # Purl rows are the knit loop mirrored in depth; knit rows repeat.
        sign = -1 if r % 2 else 1
        np.testing.assert_allclose(g[r][:, 0], g[0][:, 0], atol=1e-6)
        np.testing.assert_allclose(g[r][:, 2], sign * g[0][:, 2], atol=1e-6)
    assert np.ptp(g[0][:, 2]) > 0


def _crossings(a: np.ndarray, b: np.ndarray) -> list[float]:
    """z(a) - z(b) at every crossing of the xy projections of polylines a and b."""
    p, r = a[:-1, :2], a[1:, :2] - a[:-1, :2]
    q, s = b[:-1, :2], b[1:, :2] - b[:-1, :2]
    cross = r[:, None, 0] * s[None, :, 1] - r[:, None, 1] * s[None, :, 0]
    qp = q[None, :, :] - p[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (qp[..., 0] * s[None, :, 1] - qp[..., 1] * s[None, :, 0]) / cross
        u = (qp[..., 0] * r[:, None, 1] - qp[..., 1] * r[:, None, 0]) / cross
    hit = (cross != 0) & (t >= 0) & (t < 1) & (u >= 0) & (u < 1)
    out = []
    for i, j in zip(*np.nonzero(hit)):
        za = a[i, 2] + t[i, j] * (a[i + 1, 2] - a[i, 2])
        zb = b[j, 2] + u[i, j] * (b[j + 1, 2] - b[j, 2])
        out.append(za - zb)
    return out


@pytest.mark.parametrize("gen", [cloth.stockinette, cloth.garter])
def test_adjacent_rows_interlock(gen):
    """Adjacent rows overlap in height and cross each other both in front and behind
    (seen from the face), the same number of times in every loop: they interlock
    instead of lying one on the other."""
    stage = new_stage()
    loops = 4
    gen(stage, "/K", rows=3, loops=loops)
    rows = [evaluate(c, 12) for c in yarns(stage.GetPrimAtPath("/K/Rows"))]
    for r in range(2):
        a, b = rows[r], rows[r + 1]
        assert a[:, 1].max() > b[:, 1].min() + 0.5 * CNE50_D  # loops reach into the next row
        dz = _crossings(a, b)
        front = sum(1 for d in dz if d > 0)
        back = sum(1 for d in dz if d < 0)
        assert front >= loops and back >= loops, (front, back)
        # Crossings are well separated in depth (no near-intersections).
        assert min(abs(d) for d in dz) > 0.5 * CNE50_D


@pytest.mark.parametrize("gen, kw", [
    (cloth.stockinette, {}),
    (cloth.garter, {}),
    (cloth.stockinette, {"yarn": "Skala 360", "loop_size": 1.3}),
    (cloth.garter, {"yarn": "ORA 120", "spacing_scale": 1.1}),
    (cloth.stockinette, {"fiber": "wool", "loop_size": 1.5, "spacing_scale": 1.2}),
])
def test_knit_yarns_do_not_pass_through_each_other(gen, kw):
    stage = new_stage()
    gen(stage, "/K", rows=5, loops=5, **kw)
    prim = stage.GetPrimAtPath("/K/Rows")
    d = width(prim)
    assert d == pytest.approx(authoring.yarn_diameter_mm(prim), rel=1e-6)
    dist = min_distance([evaluate(c) for c in yarns(prim)])
    assert dist >= 0.8 * d, dist / d
    if not kw:  # at the default size the yarns just touch
        assert dist == pytest.approx(d, rel=0.02)


def test_knit_refuses_interpenetrating_parameters():
    stage = new_stage()
    with pytest.raises(cloth.ClothError, match="pass through each other"):
        cloth.stockinette(stage, "/K", rows=3, loops=3, loop_size=0.5)
    assert not stage.GetPrimAtPath("/K")  # nothing half-made left behind
    with pytest.raises(cloth.ClothError, match="pass through each other"):
        cloth.garter(stage, "/K", rows=3, loops=3, spacing_scale=0.6)
    # min_clearance=0 disables the check.
    cloth.stockinette(stage, "/K", rows=3, loops=3, loop_size=0.5, min_clearance=0)
    assert len(yarns(stage.GetPrimAtPath("/K/Rows"))) == 3


# ------------------------------------------------------------------ weaves
def _z_at(curve: np.ndarray, axis: int, where: float) -> float:
    order = np.argsort(curve[:, axis])
    return float(np.interp(where, curve[order, axis], curve[order, 2]))


def _crossing_heights(stage, path, warps, wefts):
    warp = [evaluate(c, 32) for c in yarns(stage.GetPrimAtPath(f"{path}/Warp"))]
    weft = [evaluate(c, 32) for c in yarns(stage.GetPrimAtPath(f"{path}/Weft"))]
    assert len(warp) == warps and len(weft) == wefts
    xs = [float(np.mean(w[:, 0])) for w in warp]
    ys = [float(np.mean(w[:, 1])) for w in weft]
    zw = np.array([[_z_at(warp[i], 1, ys[j]) for j in range(wefts)] for i in range(warps)])
    zf = np.array([[_z_at(weft[j], 0, xs[i]) for j in range(wefts)] for i in range(warps)])
    return warp, weft, xs, ys, zw, zf


def test_plain_weave_over_under():
    stage = new_stage()
    root = cloth.plain_weave(stage, "/W", warps=6, wefts=7)
    assert sorted(c.GetName() for c in root.GetChildren()) == ["Warp", "Weft"]
    warp, weft, xs, ys, zw, zf = _crossing_heights(stage, "/W", 6, 7)
    d = CNE50_D
    np.testing.assert_allclose(np.diff(xs), 2.5 * d, rtol=1e-6)  # default spacing
    np.testing.assert_allclose(np.diff(ys), 2.5 * d, rtol=1e-6)
    assert all(np.ptp(w[:, 0]) < 1e-9 for w in warp)  # warps run straight along y
    for i in range(6):
        for j in range(7):
            over = (i + j) % 2 == 0
            assert (zw[i, j] > zf[i, j]) == over
            # Centre lines are one yarn diameter apart in depth at every crossing.
            assert abs(zw[i, j] - zf[i, j]) == pytest.approx(d, rel=0.02)
    assert min_distance(warp + weft) >= 0.95 * d
    for child in root.GetChildren():
        assert_extent(child)
        assert child.HasAPI("FiberYarnAPI")
    assert_clean(stage)


def test_satin_floats_and_step():
    stage = new_stage()
    cloth.satin(stage, "/S", warps=10, wefts=10, dye="reactiveBlue", depth_of_shade=1.5)
    warp, weft, xs, ys, zw, zf = _crossing_heights(stage, "/S", 10, 10)
    over = zw > zf
    np.testing.assert_allclose(np.abs(zw - zf), CNE50_D, rtol=0.03)
    for i in range(10):
        # Each warp floats over 4 wefts, under 1: the 5-harness satin.
        under = [j for j in range(10) if not over[i, j]]
        assert len(under) == 2 and under[1] - under[0] == 5
        assert under[0] == (2 * i) % 5  # move number 2
    for j in range(10):
        assert sum(not over[i, j] for i in range(10)) == 2  # each weft shows twice per 10
    assert min_distance(warp + weft) >= 0.8 * CNE50_D
    # Floats are flat: along an over-float the warp keeps its height.
    assert np.ptp(zw[over]) < 0.05 * CNE50_D
    prim = stage.GetPrimAtPath("/S/Warp")
    assert prim.GetAttribute("fiber:dye:class").Get() == "reactive"
    assert_clean(stage)


def test_satin_variants_and_errors():
    assert cloth.satin_step(4) == 2
    assert cloth.satin_step(7) == 3
    stage = new_stage()
    cloth.satin(stage, "/S8", warps=8, wefts=8, floats=7, step=3)
    _, _, _, _, zw, zf = _crossing_heights(stage, "/S8", 8, 8)
    assert ((zw > zf).sum(axis=1) == 7).all()
    for floats in (1, 2, 3, 5):
        with pytest.raises(cloth.ClothError, match="satin"):
            cloth.satin(stage, "/X", floats=floats)
    with pytest.raises(cloth.ClothError, match="move number"):
        cloth.satin(stage, "/X", floats=4, step=4)
    assert not stage.GetPrimAtPath("/X")


@pytest.mark.parametrize("gen", [cloth.plain_weave, cloth.satin])
def test_weave_spacing_crimp_and_clearance(gen):
    stage = new_stage()
    d = CNE50_D
    gen(stage, "/W", warps=6, wefts=6, spacing=1.0, crimp=1.2)
    _, _, xs, _, zw, zf = _crossing_heights(stage, "/W", 6, 6)
    np.testing.assert_allclose(np.diff(xs), 1.0, rtol=1e-6)
    np.testing.assert_allclose(np.abs(zw - zf), 1.2 * d, rtol=0.03)
    with pytest.raises(cloth.ClothError, match="pass through each other"):
        gen(stage, "/T", warps=6, wefts=6, spacing=1.2 * d)
    assert not stage.GetPrimAtPath("/T")
    gen(stage, "/T", warps=3, wefts=3, spacing=1.2 * d, min_clearance=0)


# ------------------------------------------------------------------ common behaviour
GENERATORS = [
    (cloth.stockinette, {"rows": 4, "loops": 4}),
    (cloth.garter, {"rows": 4, "loops": 4}),
    (cloth.plain_weave, {"warps": 6, "wefts": 5}),
    (cloth.satin, {"warps": 7, "wefts": 6}),
]


@pytest.mark.parametrize("gen, kw", GENERATORS)
def test_deterministic(gen, kw):
    texts = []
    for _ in range(2):
        stage = new_stage()
        UsdGeom.SetStageMetersPerUnit(stage, 0.001)
        gen(stage, "/C", **kw)
        texts.append(stage.GetRootLayer().ExportToString())
    assert texts[0] == texts[1]


@pytest.mark.parametrize("gen, kw", GENERATORS)
def test_stage_units(gen, kw):
    mm = new_stage()
    gen(mm, "/C", **kw)
    assert UsdGeom.GetStageMetersPerUnit(mm) == pytest.approx(0.001)  # set when missing
    cm = new_stage()
    UsdGeom.SetStageMetersPerUnit(cm, 0.01)
    gen(cm, "/C", **kw)
    assert UsdGeom.GetStageMetersPerUnit(cm) == pytest.approx(0.01)  # kept
    for a, b in zip(mm.GetPrimAtPath("/C").GetChildren(), cm.GetPrimAtPath("/C").GetChildren()):
        np.testing.assert_allclose(np.vstack(yarns(b)), 0.1 * np.vstack(yarns(a)), rtol=1e-5,
                                   atol=1e-7)
        assert width(b) == pytest.approx(0.1 * width(a), rel=1e-6)
    assert_clean(cm)


@pytest.mark.parametrize("gen, kw", GENERATORS)
def test_fiber_override_and_dye(gen, kw):
    stage = new_stage()
    gen(stage, "/C", yarn="S 303", fiber="polyester", dye="disperseRed", depth_of_shade=2, **kw)
    for prim in stage.GetPrimAtPath("/C").GetChildren():
        assert prim.GetAttribute("fiber:kind").Get() == "polyester"
        assert prim.GetAttribute("yarn:plies").Get() == 3
        assert prim.GetAttribute("fiber:dye:depthOfShade").Get() == pytest.approx(2)
        assert width(prim) == pytest.approx(authoring.yarn_diameter_mm(prim), rel=1e-6)
    assert_clean(stage)


@pytest.mark.parametrize("call, error, match", [
    (lambda s: cloth.stockinette(s, "/C", rows=0), cloth.ClothError, "rows"),
    (lambda s: cloth.garter(s, "/C", loops=2.5), cloth.ClothError, "loops"),
    (lambda s: cloth.stockinette(s, "/C", loop_size=-1), cloth.ClothError, "loop_size"),
    (lambda s: cloth.plain_weave(s, "/C", warps=0), cloth.ClothError, "warps"),
    (lambda s: cloth.plain_weave(s, "/C", spacing=float("nan")), cloth.ClothError, "spacing"),
    (lambda s: cloth.satin(s, "/C", crimp=0), cloth.ClothError, "crimp"),
    (lambda s: cloth.stockinette(s, "/C", yarn="CNe 99"), cloth.ClothError, "unknown yarn preset"),
    (lambda s: cloth.plain_weave(s, "/C", fiber="nylon"), cloth.ClothError, "unknown fiber preset"),
    (lambda s: cloth.garter(s, "/C", dye="purple"), authoring.AuthoringError, "unknown dye"),
    (lambda s: cloth.stockinette(s, "relative/path"), cloth.ClothError, "absolute prim path"),
])
def test_bad_parameters(call, error, match):
    stage = new_stage()
    with pytest.raises(error, match=match):
        call(stage)
    assert not stage.GetPrimAtPath("/C")


# ------------------------------------------------------------------ command line
@pytest.mark.parametrize("args", [
    ["stockinette", "--rows", "3", "--loops", "4"],
    ["garter", "--rows", "4", "--loops", "3", "--fiber-kind", "wool"],
    ["plain", "--warps", "5", "--wefts", "6", "--dye", "reactiveRed", "--depth-of-shade", "1"],
    ["satin", "--warps", "6", "--wefts", "6", "--yarn", "ORA 120", "--spacing", "1.0"],
])
def test_cli_cloth(tmp_path, capsys, args):
    out = tmp_path / "c.usda"
    assert main(["cloth", *args, "-o", str(out)]) == 0
    assert "wrote" in capsys.readouterr().out
    stage = Usd.Stage.Open(str(out))
    assert stage.GetDefaultPrim().GetPath() == "/Cloth"
    assert UsdGeom.GetStageMetersPerUnit(stage) == pytest.approx(0.001)
    assert UsdGeom.GetStageUpAxis(stage) == "Y"
    assert main(["check", str(out)]) == 0


@pytest.mark.parametrize("args, expected", [
    (["stockinette", "--warps", "4"], "--warps does not apply to knits"),
    (["plain", "--rows", "3", "--loops", "2"], "--rows, --loops do not apply to weaves"),
    (["plain", "--floats", "4"], "--floats"),
    (["satin", "--floats", "3"], "no regular satin"),
    (["garter", "--yarn", "CNe 99"], "unknown yarn preset"),
    (["stockinette", "--loop-size", "0.4"], "pass through each other"),
])
def test_cli_cloth_errors(tmp_path, capsys, args, expected):
    out = tmp_path / "c.usda"
    assert main(["cloth", *args, "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("usdfiber: error: ") and expected in err, err
    assert len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_cli_cloth_argparse_errors(tmp_path, capsys):
    for args in (["twill"], ["plain", "--warps", "0"], ["plain"]):
        with pytest.raises(SystemExit) as info:
            main(["cloth", *args] + (["-o", str(tmp_path / "c.usda")] if args != ["plain"] else []))
        assert info.value.code == 2
    capsys.readouterr()
