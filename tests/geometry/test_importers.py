"""Curve file importers (usdfiber.importers, ``usdfiber import``): BCC and HAIR files.

Every file here is written by the test itself with ``struct.pack`` from the published
layouts (independently of the module under test), imported, and read back from USD.
"""
from __future__ import annotations

import struct
import time
from pathlib import Path

import numpy as np
import pytest

import usdfiber  # noqa: F401  (registers the schemas before any stage exists)
from pxr import Usd, UsdGeom

from usdfiber import authoring
from usdfiber.cli import main
from usdfiber.importers import CurveFileError, import_curves, read_bcc, read_curves, read_hair
from usdfiber.presets import YARN_PRESETS
from usdfiber.validation.runner import check_stage


# ------------------------------------------------------------------ independent writers
def bcc_bytes(curves, ctype: bytes = b"C0", up: int = 1, *, byte_count: int = 0x44,
              dims: int = 3, magic: bytes = b"BCC", curve_count: int | None = None,
              point_count: int | None = None, info: bytes = b"written by the test") -> bytes:
    """A BCC file: 64-byte header, then per curve int32 count (negative = closed) + xyz."""
    n_curves = len(curves) if curve_count is None else curve_count
    n_points = sum(len(p) for p, _ in curves) if point_count is None else point_count
    head = (magic + bytes([byte_count]) + ctype + bytes([dims, up])
            + struct.pack("<QQ", n_curves, n_points) + info.ljust(40, b"\0")[:40])
    assert len(head) == 64
    body = b""
    for pts, closed in curves:
        body += struct.pack("<i", -len(pts) if closed else len(pts))
        body += struct.pack(f"<{3 * len(pts)}f", *[c for p in pts for c in p])
    return head + body


def hair_bytes(strands, *, thickness=None, transparency=None, colours=None,
               segments_array: bool = True, default_segments: int = 0,
               default_thickness: float = 0.0, magic: bytes = b"HAIR",
               strand_count: int | None = None, point_count: int | None = None,
               flags_extra: int = 0, points_flag: bool = True) -> bytes:
    """A HAIR file: 128-byte header, then the flagged arrays in the documented order."""
    pts = [p for s in strands for p in s]
    flags = flags_extra
    flags |= 1 if segments_array else 0
    flags |= 2 if points_flag else 0
    flags |= 4 if thickness is not None else 0
    flags |= 8 if transparency is not None else 0
    flags |= 16 if colours is not None else 0
    head = (magic
            + struct.pack("<IIII", len(strands) if strand_count is None else strand_count,
                          len(pts) if point_count is None else point_count, flags,
                          default_segments)
            + struct.pack("<ff", default_thickness, 1.0) + struct.pack("<3f", 0.5, 0.4, 0.3)
            + b"test hair".ljust(88, b"\0"))
    assert len(head) == 128
    body = b""
    if segments_array:
        body += struct.pack(f"<{len(strands)}H", *[len(s) - 1 for s in strands])
    if points_flag:
        body += struct.pack(f"<{3 * len(pts)}f", *[c for p in pts for c in p])
    for arr in (thickness, transparency):
        if arr is not None:
            body += struct.pack(f"<{len(arr)}f", *arr)
    if colours is not None:
        body += struct.pack(f"<{3 * len(colours)}f", *[c for p in colours for c in p])
    return head + body


OPEN_A = [(0.0, 0.0, 0.0), (1.0, 0.5, 0.0), (2.0, 1.0, 0.25), (3.0, 0.5, 0.5), (4.0, 0.0, 0.5)]
OPEN_B = [(0.0, 2.0, 0.0), (1.0, 2.5, 0.0), (2.0, 2.0, 0.0), (3.0, 2.5, 0.0)]
CLOSED_C = [(5.0, 0.0, 0.0), (6.0, 1.0, 0.0), (5.0, 2.0, 0.0), (4.0, 1.0, 0.0)]
CLOSED_D = [(8.0, 0.0, 1.0), (9.0, 1.0, 1.0), (8.0, 2.0, 1.0)]


def write(tmp_path: Path, name: str, data: bytes) -> Path:
    p = tmp_path / name
    p.write_bytes(data)
    return p


_STAGES: list[Usd.Stage] = []  # prims are only valid while their stage lives


def curve_prims(path: Path) -> dict[str, Usd.Prim]:
    stage = Usd.Stage.Open(str(path))
    _STAGES.append(stage)
    root = stage.GetDefaultPrim()
    assert root and root.IsA(UsdGeom.Xform)
    return {c.GetName(): c for c in root.GetChildren()}


def arrays(prim: Usd.Prim):
    c = UsdGeom.BasisCurves(prim)
    return (np.array(c.GetPointsAttr().Get(), dtype=np.float64),
            list(c.GetCurveVertexCountsAttr().Get()),
            np.array(c.GetWidthsAttr().Get(), dtype=np.float64), c.GetWidthsInterpolation())


def assert_checks_clean(path: Path) -> None:
    report = check_stage(str(path))
    errors = [p for p in report.problems if p.severity.name == "ERROR"]
    assert not errors, report.to_text()


# ------------------------------------------------------------------ BCC round trips
def test_bcc_catmull_rom_open_curves_round_trip(tmp_path):
    src = write(tmp_path, "open.bcc", bcc_bytes([(OPEN_A, False), (OPEN_B, False)]))
    out = import_curves(src, tmp_path / "open.usda")
    assert out == tmp_path / "open.usda"
    prims = curve_prims(out)
    assert list(prims) == ["Curves"]
    prim = prims["Curves"]
    c = UsdGeom.BasisCurves(prim)
    assert (c.GetTypeAttr().Get(), c.GetBasisAttr().Get(), c.GetWrapAttr().Get()) == \
        ("cubic", "catmullRom", "nonperiodic")
    pts, counts, widths, interp = arrays(prim)
    np.testing.assert_allclose(pts, np.array(OPEN_A + OPEN_B), rtol=0, atol=1e-7)
    assert counts == [5, 4]
    # No thickness in BCC: the fiber's diameter (polyester 10 um) in mm.
    assert interp == "constant"
    np.testing.assert_allclose(widths, [0.010], rtol=1e-6)
    assert prim.HasAPI("FiberAPI") and not prim.HasAPI("FiberYarnAPI")
    assert prim.GetAttribute("fiber:kind").Get() == "polyester"
    extent = np.array(c.GetExtentAttr().Get())
    np.testing.assert_allclose(extent[0], np.array(OPEN_A + OPEN_B).min(0) - 0.005, atol=1e-6)
    np.testing.assert_allclose(extent[1], np.array(OPEN_A + OPEN_B).max(0) + 0.005, atol=1e-6)
    stage = Usd.Stage.Open(str(out))
    assert UsdGeom.GetStageMetersPerUnit(stage) == pytest.approx(0.001)
    assert UsdGeom.GetStageUpAxis(stage) == "Y"
    report = check_stage(str(out))
    assert report.ok(True), report.to_text()  # no errors and no warnings


def test_bcc_mixed_open_and_closed_curves(tmp_path):
    """Negative counts are closed curves -> a periodic prim; file order is recoverable."""
    curves = [(CLOSED_C, True), (OPEN_A, False), (CLOSED_D, True), (OPEN_B, False)]
    src = write(tmp_path, "mixed.bcc", bcc_bytes(curves))
    out = import_curves(src, tmp_path / "mixed.usda")
    prims = curve_prims(out)
    assert sorted(prims) == ["ClosedCurves", "Curves"]
    assert UsdGeom.BasisCurves(prims["ClosedCurves"]).GetWrapAttr().Get() == "periodic"
    assert UsdGeom.BasisCurves(prims["Curves"]).GetWrapAttr().Get() == "nonperiodic"
    rebuilt: dict[int, tuple[np.ndarray, bool]] = {}
    for name, prim in prims.items():
        pts, counts, _, _ = arrays(prim)
        index = list(UsdGeom.PrimvarsAPI(prim).GetPrimvar("sourceCurveIndex").Get())
        assert UsdGeom.PrimvarsAPI(prim).GetPrimvar("sourceCurveIndex").GetInterpolation() == "uniform"
        start = 0
        for i, n in zip(index, counts):
            rebuilt[i] = (pts[start:start + n], name == "ClosedCurves")
            start += n
    assert sorted(rebuilt) == [0, 1, 2, 3]
    for i, (pts, closed) in enumerate(curves):
        np.testing.assert_allclose(rebuilt[i][0], np.array(pts), atol=1e-7)
        assert rebuilt[i][1] == closed
    assert_checks_clean(out)


def test_bcc_closed_only_is_one_periodic_prim(tmp_path):
    src = write(tmp_path, "loops.bcc", bcc_bytes([(CLOSED_C, True), (CLOSED_D, True)]))
    prims = curve_prims(import_curves(src, tmp_path / "loops.usda"))
    assert list(prims) == ["ClosedCurves"]
    assert not UsdGeom.PrimvarsAPI(prims["ClosedCurves"]).HasPrimvar("sourceCurveIndex")
    assert arrays(prims["ClosedCurves"])[1] == [4, 3]


@pytest.mark.parametrize("ctype, usd_type, basis", [(b"PL", "linear", None),
                                                      (b"BS", "cubic", "bspline")])
def test_bcc_polyline_and_bspline_types(tmp_path, ctype, usd_type, basis):
    short = [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0)]
    curves = [(OPEN_A, False)] + ([(short, False)] if ctype == b"PL" else [])
    src = write(tmp_path, "t.bcc", bcc_bytes(curves, ctype))
    prim = curve_prims(import_curves(src, tmp_path / "t.usda"))["Curves"]
    c = UsdGeom.BasisCurves(prim)
    assert c.GetTypeAttr().Get() == usd_type
    if basis:
        assert c.GetBasisAttr().Get() == basis
    assert arrays(prim)[1] == [len(p) for p, _ in curves]
    assert_checks_clean(tmp_path / "t.usda")


def test_bcc_units_up_axis_and_root(tmp_path):
    src = write(tmp_path, "scaled.bcc", bcc_bytes([(OPEN_A, False)], up=2))
    out = import_curves(src, tmp_path / "scaled.usdc", units_per_file_unit=0.5,
                        meters_per_unit=0.01, root="Yarn")
    stage = Usd.Stage.Open(str(out))
    assert UsdGeom.GetStageUpAxis(stage) == "Z"
    assert UsdGeom.GetStageMetersPerUnit(stage) == pytest.approx(0.01)
    assert stage.GetDefaultPrim().GetName() == "Yarn"
    pts, _, widths, _ = arrays(stage.GetPrimAtPath("/Yarn/Curves"))
    np.testing.assert_allclose(pts, 0.5 * np.array(OPEN_A), atol=1e-7)
    np.testing.assert_allclose(widths, [10e-6 / 0.01], rtol=1e-6)  # 10 um in cm
    assert_checks_clean(out)


def test_bcc_as_yarn_with_dye(tmp_path):
    src = write(tmp_path, "yarn.bcc", bcc_bytes([(OPEN_A, False), (OPEN_B, False)]))
    out = import_curves(src, tmp_path / "yarn.usda", yarn="CNe 50", dye="reactiveRed",
                        depth_of_shade=2.0)
    prim = curve_prims(out)["Curves"]
    assert prim.HasAPI("FiberYarnAPI") and prim.HasAPI("FiberAPI")
    assert prim.GetAttribute("fiber:kind").Get() == "cotton"  # the yarn's composition
    assert prim.GetAttribute("yarn:plies").Get() == 3
    assert prim.GetAttribute("fiber:dye:class").Get() == "reactive"
    assert prim.GetAttribute("fiber:dye:depthOfShade").Get() == pytest.approx(2.0)
    _, _, widths, _ = arrays(prim)
    np.testing.assert_allclose(widths, [YARN_PRESETS["CNe 50"].yarn_diameter_mm], rtol=1e-6)
    assert check_stage(str(out)).ok(True)

    # An explicit fiber preset overrides the yarn's fibers (and so its ply radius).
    out2 = import_curves(src, tmp_path / "yarn2.usda", yarn="CNe 50", preset="polyester")
    prim2 = curve_prims(out2)["Curves"]
    assert prim2.GetAttribute("fiber:kind").Get() == "polyester"
    np.testing.assert_allclose(arrays(prim2)[2], [authoring.yarn_diameter_mm(prim2)], rtol=1e-6)


def test_width_options(tmp_path):
    src = write(tmp_path, "w.bcc", bcc_bytes([(OPEN_A, False)]))
    prim = curve_prims(import_curves(src, tmp_path / "w1.usda", width=0.02, preset="wool"))["Curves"]
    assert prim.GetAttribute("fiber:kind").Get() == "wool"
    np.testing.assert_allclose(arrays(prim)[2], [0.02], rtol=1e-6)
    with pytest.raises(ValueError, match="width"):
        import_curves(src, tmp_path / "w2.usda", width=-1.0)
    with pytest.raises(ValueError, match="units_per_file_unit"):
        import_curves(src, tmp_path / "w3.usda", units_per_file_unit=float("nan"))
    with pytest.raises(ValueError, match="usda"):
        import_curves(src, tmp_path / "w4.txt")


def test_output_is_overwritten(tmp_path):
    src = write(tmp_path, "a.bcc", bcc_bytes([(OPEN_A, False)]))
    out = tmp_path / "a.usda"
    out.write_text("not usd at all")
    import_curves(src, out)
    assert arrays(curve_prims(out)["Curves"])[1] == [5]
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


# ------------------------------------------------------------------ HAIR round trips
STRANDS = [[(0.0, 0.0, 0.0), (0.0, 1.0, 0.1), (0.1, 2.0, 0.2)],
           [(1.0, 0.0, 0.0), (1.0, 1.0, 0.0)],
           [(2.0, 0.0, 0.0), (2.1, 0.5, 0.0), (2.2, 1.0, 0.1), (2.3, 1.5, 0.2)]]


def test_hair_with_every_array_round_trip(tmp_path):
    n = sum(len(s) for s in STRANDS)
    thick = [0.01 + 0.001 * i for i in range(n)]
    data = hair_bytes(STRANDS, thickness=thick, transparency=[0.5] * n,
                      colours=[(0.9, 0.1, 0.1)] * n)
    src = write(tmp_path, "full.hair", data)
    curves = read_curves(src)
    assert curves.format == "hair"
    assert any("colour" in note and "dye" in note for note in curves.notes)
    out = import_curves(src, tmp_path / "full.usda")
    prims = curve_prims(out)
    assert list(prims) == ["Curves"]
    c = UsdGeom.BasisCurves(prims["Curves"])
    assert c.GetTypeAttr().Get() == "linear"
    assert c.GetWrapAttr().Get() == "nonperiodic"
    pts, counts, widths, interp = arrays(prims["Curves"])
    np.testing.assert_allclose(pts, np.array([p for s in STRANDS for p in s]), atol=1e-7)
    assert counts == [3, 2, 4]
    assert interp == "vertex"
    np.testing.assert_allclose(widths, thick, rtol=1e-6)  # thickness is the width (diameter)
    assert "colour array is not imported" in Usd.Stage.Open(str(out)).GetRootLayer().documentation
    assert_checks_clean(out)


def test_hair_default_segments_and_thickness(tmp_path):
    strands = [[(float(i), 0.0, 0.0), (float(i), 1.0, 0.0), (float(i), 2.0, 0.5)] for i in range(4)]
    data = hair_bytes(strands, segments_array=False, default_segments=2, default_thickness=0.02)
    src = write(tmp_path, "default.hair", data)
    out = import_curves(src, tmp_path / "default.usda", units_per_file_unit=0.5)
    pts, counts, widths, interp = arrays(curve_prims(out)["Curves"])
    assert counts == [3, 3, 3, 3]
    np.testing.assert_allclose(pts, 0.5 * np.array([p for s in strands for p in s]), atol=1e-7)
    assert interp == "constant"
    np.testing.assert_allclose(widths, [0.01], rtol=1e-6)
    assert_checks_clean(out)


def test_hair_without_thickness_uses_fiber_diameter(tmp_path):
    src = write(tmp_path, "thin.hair", hair_bytes(STRANDS, default_thickness=0.0))
    prim = curve_prims(import_curves(src, tmp_path / "thin.usda", preset="cotton"))["Curves"]
    np.testing.assert_allclose(arrays(prim)[2], [18.5e-3], rtol=1e-6)  # cotton 18.5 um, in mm
    # width="fiber" ignores the file's thickness.
    n = sum(len(s) for s in STRANDS)
    src2 = write(tmp_path, "thick.hair", hair_bytes(STRANDS, thickness=[1.0] * n))
    prim2 = curve_prims(import_curves(src2, tmp_path / "thick.usda", width="fiber"))["Curves"]
    assert arrays(prim2)[3] == "constant"
    np.testing.assert_allclose(arrays(prim2)[2], [0.01], rtol=1e-6)


def test_many_curves_import_quickly(tmp_path):
    rng = np.random.default_rng(7)
    counts = rng.integers(4, 12, size=20000)
    closed = rng.random(20000) < 0.3
    pts = rng.normal(size=(int(counts.sum()), 3)).astype(np.float32)
    body = bytearray()
    start = 0
    for n, c in zip(counts, closed):
        body += struct.pack("<i", -int(n) if c else int(n))
        body += pts[start:start + n].astype("<f4").tobytes()
        start += n
    head = (b"BCC\x44C0\x03\x01" + struct.pack("<QQ", len(counts), int(counts.sum()))
            + b"\0" * 40)
    src = write(tmp_path, "big.bcc", head + bytes(body))
    t0 = time.perf_counter()
    out = import_curves(src, tmp_path / "big.usdc")
    elapsed = time.perf_counter() - t0
    prims = curve_prims(out)
    total = sum(len(arrays(p)[1]) for p in prims.values())
    assert total == 20000
    closed_pts, closed_counts, _, _ = arrays(prims["ClosedCurves"])
    assert closed_counts == [int(n) for n in counts[closed]]
    assert elapsed < 20, elapsed  # vectorized: about a second on 2 cores


# ------------------------------------------------------------------ malformed files
GOOD_BCC = bcc_bytes([(OPEN_A, False), (OPEN_B, False), (CLOSED_D, True)])


def _three_of_ten() -> bytes:
    return bcc_bytes([(OPEN_A, False), (OPEN_B, False), (CLOSED_D, True)], curve_count=10,
                     point_count=12)


NAN_CURVE = [(0.0, 0.0, 0.0), (1.0, float("nan"), 0.0), (2.0, 0.0, 0.0), (3.0, 0.0, 0.0)]
INF_CURVE = [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (2.0, 0.0, float("inf")), (3.0, 0.0, 0.0)]

BAD_BCC = {
    "empty": (b"", "empty file"),
    "short-header": (b"BCC\x44C0\x03\x01" + b"\0" * 10, "truncated header"),
    "wrong-magic": (b"BCX" + GOOD_BCC[3:], "not a BCC or HAIR file: starts with b'BCXD'"),
    "byte-count": (GOOD_BCC[:3] + b"\x48" + GOOD_BCC[4:], "byte count 0x48"),
    "curve-type": (GOOD_BCC[:4] + b"XX" + GOOD_BCC[6:], "curve type b'XX'"),
    "two-dimensions": (GOOD_BCC[:6] + b"\x02" + GOOD_BCC[7:], "2 dimensions"),
    "ends-early": (_three_of_ten(), "header says 10 curves but the file ends after 3"),
    "zero-curves": (bcc_bytes([], curve_count=0), "0 curves"),
    "count-zero": (bcc_bytes([([], False)]), "curve 0 has 0 control points"),
    "count-one": (bcc_bytes([(OPEN_A, False), ([(1.0, 2.0, 3.0)], False)]),
                  "curve 1 has 1 control point"),
    "open-three": (bcc_bytes([(OPEN_A[:3], False)]), "needs at least 4"),
    "closed-two": (bcc_bytes([(OPEN_A[:2], True)]), "closed uniform Catmull-Rom curve needs at least 3"),
    "nan": (bcc_bytes([(OPEN_A, False), (NAN_CURVE, False)]), "curve 1 point 1 has a non-finite"),
    "inf": (bcc_bytes([(INF_CURVE, False)]), "curve 0 point 2 has a non-finite"),
    "inside-curve": (GOOD_BCC[:-20], "ends inside curve 2"),
    "point-total": (bcc_bytes([(OPEN_A, False)], point_count=7), "header says 7 control points"),
    "trailing": (GOOD_BCC + b"\0" * 16, "16 bytes after the last"),
}


def assert_refused(tmp_path, name: str, data: bytes, expected: str) -> None:
    """Importing file ``name`` holding ``data`` fails with one line naming the file and saying
    ``expected``, and writes no stage."""
    src = write(tmp_path, name, data)
    with pytest.raises(CurveFileError) as info:
        import_curves(src, tmp_path / "out.usda")
    msg = str(info.value)
    assert msg.startswith(f"{name}: "), msg
    assert expected in msg, msg
    assert "\n" not in msg
    assert not (tmp_path / "out.usda").exists()


@pytest.mark.parametrize("case", sorted(BAD_BCC))
def test_malformed_bcc(tmp_path, case):
    assert_refused(tmp_path, f"bad-{case}.bcc", *BAD_BCC[case])


N_PTS = sum(len(s) for s in STRANDS)
GOOD_HAIR = hair_bytes(STRANDS, thickness=[0.01] * N_PTS)
NAN_STRANDS = [STRANDS[0], [(1.0, 0.0, 0.0), (1.0, float("nan"), 0.0)]]

BAD_HAIR = {
    "short-header": (b"HAIR" + b"\0" * 50, "truncated header"),
    "wrong-magic": (b"HAIX" + GOOD_HAIR[4:], "not a BCC or HAIR file: starts with b'HAIX'"),
    "negative-strands": (hair_bytes(STRANDS, strand_count=2 ** 32 - 1), "strand count"),
    "negative-points": (hair_bytes(STRANDS, point_count=2 ** 32 - 5), "negative"),
    "zero-strands": (hair_bytes([], strand_count=0), "0 strands"),
    "no-points": (hair_bytes(STRANDS, points_flag=False), "no points array"),
    "point-sum": (hair_bytes(STRANDS, point_count=N_PTS + 1),
                  f"header says {N_PTS + 1} points but the strands' segment counts add up to {N_PTS}"),
    "zero-segments": (hair_bytes([STRANDS[0], [(1.0, 1.0, 1.0)]]), "strand 1 has 0 segments"),
    "default-segments-zero": (hair_bytes(STRANDS, segments_array=False, default_segments=0,
                                         point_count=N_PTS), "default segment count of 0"),
    "default-segments-mismatch": (hair_bytes(STRANDS, segments_array=False, default_segments=3),
                                  "header says 9 points but 3 strands of 3 default segments have 12 points"),
    "huge-counts-tiny-file": (hair_bytes([], segments_array=False, default_segments=1,
                                         strand_count=10 ** 8, point_count=2 * 10 ** 8),
                              "ends inside the points array"),
    "points-truncated": (hair_bytes(STRANDS)[:-8], "ends inside the points array"),
    "thickness-truncated": (GOOD_HAIR[:-4], "ends inside the thickness array"),
    "segments-truncated": (hair_bytes(STRANDS)[:129], "ends inside the segments array"),
    "negative-thickness": (hair_bytes(STRANDS, thickness=[0.01, -0.5] + [0.01] * (N_PTS - 2)),
                           "thickness of point 1 is -0.5"),
    "nan-point": (hair_bytes(NAN_STRANDS), "strand 1 point 1 has a non-finite"),
}


@pytest.mark.parametrize("case", sorted(BAD_HAIR))
def test_malformed_hair(tmp_path, case):
    assert_refused(tmp_path, f"bad-{case}.hair", *BAD_HAIR[case])


def test_missing_file_and_directory(tmp_path):
    with pytest.raises(CurveFileError, match=r"^nothere\.bcc: no such file"):
        read_curves(tmp_path / "nothere.bcc")
    (tmp_path / "dir.hair").mkdir()
    with pytest.raises(CurveFileError, match=r"^dir\.hair: is a directory"):
        read_curves(tmp_path / "dir.hair")


def test_format_is_chosen_by_content_not_name(tmp_path):
    src = write(tmp_path, "really-bcc.hair", GOOD_BCC)
    assert read_curves(src).format == "bcc"
    with pytest.raises(CurveFileError, match=r"^really-bcc\.hair: not a HAIR file: starts with b'BCC"):
        read_hair(src)
    with pytest.raises(CurveFileError, match=r"^h\.bcc: not a BCC file: starts with b'HAI'"):
        read_bcc(write(tmp_path, "h.bcc", GOOD_HAIR))
    with pytest.raises(CurveFileError, match="not a BCC or HAIR file"):
        read_curves(write(tmp_path, "text.bcc", b"hello world, not curves"))


# ------------------------------------------------------------------ command line
def test_cli_import_bcc(tmp_path, capsys):
    src = write(tmp_path, "cli.bcc", GOOD_BCC)
    out = tmp_path / "cli.usda"
    rc = main(["import", str(src), "-o", str(out), "--yarn", "S 303", "--dye", "reactiveBlue",
               "--depth-of-shade", "1", "--units-per-file-unit", "0.1"])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert "wrote" in cap.out and "3" in cap.out
    prims = curve_prims(out)
    assert prims["Curves"].GetAttribute("fiber:kind").Get() == "silk"
    assert prims["ClosedCurves"].HasAPI("FiberYarnAPI")
    assert main(["check", str(out)]) == 0


def test_cli_import_hair_prints_notes(tmp_path, capsys):
    src = write(tmp_path, "cli.hair", hair_bytes(STRANDS, colours=[(1.0, 0.0, 0.0)] * N_PTS,
                                                 default_thickness=0.01))
    rc = main(["import", str(src), "-o", str(tmp_path / "h.usda"), "--preset", "silk"])
    cap = capsys.readouterr()
    assert rc == 0
    assert "note: the colour array is not imported" in cap.err


@pytest.mark.parametrize("case", ["ends-early", "wrong-magic", "nan"])
def test_cli_malformed_file_exits_2(tmp_path, capsys, case):
    src = write(tmp_path, f"bad-{case}.bcc", BAD_BCC[case][0])
    rc = main(["import", str(src), "-o", str(tmp_path / "o.usda")])
    cap = capsys.readouterr()
    assert rc == 2
    lines = cap.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"usdfiber: error: bad-{case}.bcc: ")
    assert BAD_BCC[case][1] in lines[0]
    assert "Traceback" not in cap.err
    assert not (tmp_path / "o.usda").exists()


@pytest.mark.parametrize("extra, expected", [
    (["--preset", "nylon"], "unknown fiber preset 'nylon'"),
    (["--yarn", "CNe 99"], "unknown yarn preset 'CNe 99'"),
    (["--dye", "purple"], "unknown dye 'purple'"),
    (["--root", "1 bad"], "--root"),
])
def test_cli_bad_options_exit_2(tmp_path, capsys, extra, expected):
    src = write(tmp_path, "ok.bcc", GOOD_BCC)
    rc = main(["import", str(src), "-o", str(tmp_path / "o.usda"), *extra])
    cap = capsys.readouterr()
    assert rc == 2
    assert cap.err.startswith("usdfiber: error: ") and expected in cap.err
    assert not (tmp_path / "o.usda").exists()


def test_cli_missing_file_and_bad_numbers(tmp_path, capsys):
    assert main(["import", str(tmp_path / "none.hair"), "-o", str(tmp_path / "o.usda")]) == 2
    assert "none.hair: no such file" in capsys.readouterr().err
    src = write(tmp_path, "ok.bcc", GOOD_BCC)
    for bad in (["--units-per-file-unit", "-2"], ["--meters-per-unit", "nan"], ["--width", "x"]):
        with pytest.raises(SystemExit) as info:
            main(["import", str(src), "-o", str(tmp_path / "o.usda"), *bad])
        assert info.value.code == 2
    capsys.readouterr()
