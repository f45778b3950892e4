"""Stage walk: visibility, purpose, native instances and point instancers (transforms checked)."""
from __future__ import annotations

import numpy as np
import pytest

import usdfiber  # noqa: F401  (registers schemas before any stage is opened)
from pxr import Gf, Sdf, Usd, UsdGeom

from usdfiber.translators.mitsuba.stage_walk import Placement, walk


def mesh(stage, path, translate=None):
    m = UsdGeom.Mesh.Define(stage, path)
    if translate is not None:
        m.AddTranslateOp().Set(Gf.Vec3d(*translate))
    return m


def xform(stage, path, translate=None, scale=None):
    x = UsdGeom.Xform.Define(stage, path)
    if translate is not None:
        x.AddTranslateOp().Set(Gf.Vec3d(*translate))
    if scale is not None:
        x.AddScaleOp().Set(Gf.Vec3f(*scale))
    return x


def world_origin(p: Placement) -> np.ndarray:
    return (np.array([0, 0, 0, 1.0]) @ p.xform)[:3]


def quat_matrix(w, x, y, z):
    """Column-vector rotation matrix of a unit quaternion (textbook formula)."""
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def test_visibility_purpose_and_types():
    st = Usd.Stage.CreateInMemory()
    xform(st, "/W/A", translate=(1, 2, 3))
    mesh(st, "/W/A/m", translate=(0, 0, 1))
    xform(st, "/W/B")
    mesh(st, "/W/B/m")
    UsdGeom.Imageable(st.GetPrimAtPath("/W/B")).MakeInvisible()
    mesh(st, "/W/C")
    UsdGeom.Imageable(st.GetPrimAtPath("/W/C")).MakeInvisible()
    mesh(st, "/W/guide").CreatePurposeAttr("guide")
    mesh(st, "/W/proxy").CreatePurposeAttr("proxy")
    xform(st, "/W/R").CreatePurposeAttr("render")
    mesh(st, "/W/R/m")  # inherits purpose render
    UsdGeom.BasisCurves.Define(st, "/W/curves")
    st.DefinePrim("/W/plain")  # untyped: not a gprim
    paths = [p.path for p in walk(st)]
    assert paths == ["/W/A/m", "/W/R/m", "/W/curves"]
    a = next(p for p in walk(st) if p.path == "/W/A/m")
    np.testing.assert_allclose(world_origin(a), [1, 2, 4])
    assert a.instance_id == 0 and a.prim.GetPath() == Sdf.Path("/W/A/m")
    assert [p.path for p in walk(st, purposes=("proxy",))] == ["/W/proxy"]
    assert [p.path for p in walk(st, types=(UsdGeom.BasisCurves,))] == ["/W/curves"]
    # time-varying visibility
    vis = UsdGeom.Imageable(st.GetPrimAtPath("/W/curves")).GetVisibilityAttr()
    vis.Set("invisible", 2.0)
    vis.Set("inherited", 1.0)
    assert "/W/curves" in [p.path for p in walk(st, Usd.TimeCode(1.0))]
    assert "/W/curves" not in [p.path for p in walk(st, Usd.TimeCode(2.0))]


def test_native_instances_yield_proxies_with_world_transforms():
    st = Usd.Stage.CreateInMemory()
    xform(st, "/Lib")
    proto = xform(st, "/Lib/Asset", translate=(100, 0, 0))  # the source's own xform is overridden below
    mesh(st, "/Lib/Asset/geo", translate=(0, 1, 0))
    UsdGeom.Imageable(st.GetPrimAtPath("/Lib")).MakeInvisible()  # library hidden, instances not
    for i, (t, s) in enumerate([((5, 0, 0), 1.0), ((0, 0, -3), 2.0)]):
        inst = st.DefinePrim(f"/W/I{i}", "Xform")
        inst.GetReferences().AddInternalReference("/Lib/Asset")
        inst.SetInstanceable(True)
        x = UsdGeom.Xformable(inst)
        x.ClearXformOpOrder()
        x.AddTranslateOp(opSuffix="inst").Set(Gf.Vec3d(*t))
        x.AddScaleOp(opSuffix="inst").Set(Gf.Vec3f(s))
    assert proto.GetPrim().IsValid()
    got = {p.path: p for p in walk(st)}
    assert set(got) == {"/W/I0/geo", "/W/I1/geo"}
    assert got["/W/I0/geo"].prim.IsInstanceProxy()
    np.testing.assert_allclose(world_origin(got["/W/I0/geo"]), [5, 1, 0])
    np.testing.assert_allclose(world_origin(got["/W/I1/geo"]), [0, 2, -3])
    np.testing.assert_allclose(np.linalg.det(got["/W/I1/geo"].xform[:3, :3]), 8.0)


def build_instancer(st):
    """Instancer at (10, 0, 0) with 2 prototypes (one under an `over`, one outside, under an
    invisible scope) and 4 instances of known position / orientation / scale."""
    pi = UsdGeom.PointInstancer.Define(st, "/W/PI")
    pi.AddTranslateOp().Set(Gf.Vec3d(10, 0, 0))
    xform(st, "/W/PI/Protos/A", translate=(0, 1, 0))  # root local xform: included per instance
    mesh(st, "/W/PI/Protos/A/m", translate=(0, 0, 1))
    st.GetRootLayer().GetPrimAtPath("/W/PI/Protos").specifier = Sdf.SpecifierOver
    xform(st, "/Hidden")
    UsdGeom.Imageable(st.GetPrimAtPath("/Hidden")).MakeInvisible()
    xform(st, "/Hidden/B", translate=(50, 50, 50))  # ancestors of a root do not count, nor does
    UsdGeom.Xformable(st.GetPrimAtPath("/Hidden")).AddTranslateOp().Set(Gf.Vec3d(7, 7, 7))  # this
    UsdGeom.BasisCurves.Define(st, "/Hidden/B/c")
    pi.CreatePrototypesRel().SetTargets([Sdf.Path("/W/PI/Protos/A"), Sdf.Path("/Hidden/B")])
    data = dict(
        protoIndices=[0, 1, 0, 1],
        positions=[(1, 0, 0), (0, 2, 0), (0, 0, 3), (4, 4, 4)],
        # (w, x, y, z), exact in half precision: 120 deg about (1,1,1), 180 deg about z, 180 about x
        orientations=[(0.5, 0.5, 0.5, 0.5), (0, 0, 0, 1), (1, 0, 0, 0), (0, 1, 0, 0)],
        scales=[(2, 2, 2), (1, 3, 1), (1, 1, 1), (1, 1, 1)],
    )
    pi.CreateProtoIndicesAttr(data["protoIndices"])
    pi.CreatePositionsAttr([Gf.Vec3f(*p) for p in data["positions"]])
    pi.CreateOrientationsAttr([Gf.Quath(*q) for q in data["orientations"]])
    pi.CreateScalesAttr([Gf.Vec3f(*s) for s in data["scales"]])
    return pi, data


def expected_world(data, i, local_in_root, root_translate, instancer_translate=(10, 0, 0)):
    """Spec order: prototype root xform, then scale, orientation, position, instancer xform."""
    p = np.asarray(local_in_root, float) + root_translate
    r = quat_matrix(*data["orientations"][i])
    return r @ (np.asarray(data["scales"][i]) * p) + data["positions"][i] + instancer_translate


def test_point_instancer_positions_orientations_scales_and_masks():
    st = Usd.Stage.CreateInMemory()
    pi, data = build_instancer(st)
    mesh(st, "/W/other")
    pls = list(walk(st))
    paths = [p.path for p in pls]
    # prototypes are not drawn in place; every instance yields its prototype's gprims
    assert "/W/other" in paths and "/Hidden/B/c" not in paths and "/W/PI/Protos/A/m" not in paths
    inst = {p.path: p for p in pls if p.path.startswith("/W/PI[")}
    assert set(inst) == {"/W/PI[0]/W/PI/Protos/A/m", "/W/PI[1]/Hidden/B/c",
                         "/W/PI[2]/W/PI/Protos/A/m", "/W/PI[3]/Hidden/B/c"}
    for path, p in inst.items():
        i = int(path[len("/W/PI["):path.index("]")])
        assert p.instance_id == i
        if p.prim.GetPath() == Sdf.Path("/W/PI/Protos/A/m"):
            local, root = (0, 0, 1), (0, 1, 0)
        else:
            local, root = (0, 0, 0), (50, 50, 50)
        # several points of the prim's local space, not only its origin
        for q in ([0, 0, 0], [1, 0, 0], [0, 0.5, -2]):
            got = (np.r_[q, 1.0] @ p.xform)[:3]
            want = expected_world(data, i, np.add(local, q), root)
            np.testing.assert_allclose(got, want, atol=1e-6, err_msg=path)
    # masks: invisibleIds (animatable) and inactiveIds (metadata) drop instances, keep indices
    pi.InvisIds([2], Usd.TimeCode.Default())
    pi.DeactivateId(1)
    inst = sorted(p.path for p in walk(st) if p.path.startswith("/W/PI["))
    assert inst == ["/W/PI[0]/W/PI/Protos/A/m", "/W/PI[3]/Hidden/B/c"]
    # the instancer itself invisible: nothing
    pi.MakeInvisible()
    assert not [p for p in walk(st) if p.path.startswith("/W/PI")]


def test_nested_point_instancers_compose():
    st = Usd.Stage.CreateInMemory()
    outer = UsdGeom.PointInstancer.Define(st, "/W/Outer")
    outer.AddTranslateOp().Set(Gf.Vec3d(0, 0, 100))
    inner = UsdGeom.PointInstancer.Define(st, "/W/Outer/Protos/Inner")
    inner.AddTranslateOp().Set(Gf.Vec3d(0, 5, 0))  # prototype root xform of the outer instancer
    mesh(st, "/W/Outer/Protos/Inner/Protos/leaf", translate=(1, 0, 0))
    inner.CreatePrototypesRel().SetTargets([Sdf.Path("/W/Outer/Protos/Inner/Protos/leaf")])
    inner.CreateProtoIndicesAttr([0, 0])
    inner.CreatePositionsAttr([Gf.Vec3f(0, 0, 0), Gf.Vec3f(0, 0, 1)])
    outer.CreatePrototypesRel().SetTargets([Sdf.Path("/W/Outer/Protos/Inner")])
    outer.CreateProtoIndicesAttr([0, 0, 0])
    outer.CreatePositionsAttr([Gf.Vec3f(10, 0, 0), Gf.Vec3f(20, 0, 0), Gf.Vec3f(30, 0, 0)])
    outer.CreateScalesAttr([Gf.Vec3f(1), Gf.Vec3f(2), Gf.Vec3f(1)])
    got = {p.path: p for p in walk(st)}
    assert len(got) == 6
    for i, (x, s) in enumerate([(10, 1), (20, 2), (30, 1)]):
        for j in range(2):
            p = got[f"/W/Outer[{i}]/W/Outer/Protos/Inner[{j}]/W/Outer/Protos/Inner/Protos/leaf"]
            # leaf (1,0,0) + inner position (0,0,j) + inner root xform (0,5,0), scaled by s, moved
            want = s * (np.array([1, 0, j]) + [0, 5, 0]) + [x, 0, 100]
            np.testing.assert_allclose(world_origin(p), want, atol=1e-9)
            assert p.instance_id == i * 2 + j
    # a cycle is an error, not an endless recursion
    inner.GetPrototypesRel().SetTargets([inner.GetPath()])
    with pytest.raises(ValueError, match="instances itself"):
        list(walk(st))


def test_native_instance_inside_point_instancer_prototype():
    st = Usd.Stage.CreateInMemory()
    xform(st, "/Lib")
    mesh(st, "/Lib/Asset/geo", translate=(0, 0, 2))
    UsdGeom.Imageable(st.GetPrimAtPath("/Lib")).MakeInvisible()
    pi = UsdGeom.PointInstancer.Define(st, "/W/PI")
    ref = st.DefinePrim("/W/PI/Protos/P", "Xform")
    ref.GetReferences().AddInternalReference("/Lib/Asset")
    ref.SetInstanceable(True)
    pi.CreatePrototypesRel().SetTargets([ref.GetPath()])
    pi.CreateProtoIndicesAttr([0, 0])
    pi.CreatePositionsAttr([Gf.Vec3f(1, 0, 0), Gf.Vec3f(-1, 0, 0)])
    got = sorted((p.path, tuple(np.round(world_origin(p), 9))) for p in walk(st))
    assert got == [("/W/PI[0]/W/PI/Protos/P/geo", (1, 0, 2)), ("/W/PI[1]/W/PI/Protos/P/geo", (-1, 0, 2))]
