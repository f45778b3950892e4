"""The memory budget: sizes, estimates before allocation, and the guards of yarn expansion,
cloth generation, imports and bakes (each with a small budget)."""
from __future__ import annotations

import math
import struct
import tracemalloc

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom

import usdfiber  # noqa: F401 - registers the schemas
from usdfiber import authoring, cloth, presets
from usdfiber.bake.settings import BakeSettings
from usdfiber.cli import main
from usdfiber.geometry.yarn import BYTES_PER_POINT, estimate_expansion, expand_yarn
from usdfiber.geometry.yarn_centre import CentreLine
from usdfiber.importers import import_curves
from usdfiber.memory_budget import BUDGET_ENV, MemoryBudget, MemoryBudgetError, machine_memory, parse_size
from usdfiber.spec.yarn import YarnParams
from stage_util import add_camera


@pytest.mark.parametrize("text, size", [("1000", 1000), ("8G", 8 << 30), ("512MiB", 512 << 20), ("1.5GB", 3 << 29),
                                        ("2k", 2048), ("64 KiB", 64 << 10), ("1e6", 10 ** 6)])
def test_sizes(text, size):
    assert parse_size(text) == size


@pytest.mark.parametrize("text", ["", "-1", "0", "1Q", "abc", "nan", "inf", "8 GG", "0.1"])
def test_bad_sizes_are_one_line_errors(text):
    with pytest.raises(MemoryBudgetError, match="memory size|at least 1 byte") as info:
        parse_size(text)
    assert "\n" not in str(info.value)


def test_budget_sources(monkeypatch):
    monkeypatch.delenv(BUDGET_ENV, raising=False)
    default = MemoryBudget.resolve()
    assert 0 < default.bytes <= machine_memory() and "machine" in default.source
    monkeypatch.setenv(BUDGET_ENV, "3G")
    assert MemoryBudget.resolve() == MemoryBudget(3 << 30, f"${BUDGET_ENV}")
    assert MemoryBudget.resolve("1M").bytes == 1 << 20          # the option wins
    monkeypatch.setenv(BUDGET_ENV, "lots")
    with pytest.raises(MemoryBudgetError, match=BUDGET_ENV):
        MemoryBudget.resolve()
    budget = MemoryBudget(1000, "test")
    assert budget.scale_to_fit(500) == 1.0 and budget.scale_to_fit(4000) == 0.25
    with pytest.raises(MemoryBudgetError, match=r"work needs about 1.95 KiB, more than the memory budget of "
                                                r"1000 B \(test\).*--memory-budget"):
        budget.require(2000, "work")


# ---- yarn expansion ----------------------------------------------------------------------------

def _yarn(name: str, **kw) -> YarnParams:
    attrs = presets.yarn_preset(name).yarn_attributes()
    attrs.update(kw)
    return YarnParams.from_attributes(attrs, 0.001)


@pytest.mark.parametrize("name, kw", [("ORA 120", {"yarn:fibersPerPly": 60}),
                                      ("ORA 120", {"yarn:fiber:stapleLength": 0.0, "yarn:fibersPerPly": 60}),
                                      ("CNe 50", {"yarn:fibersPerPly": 40, "yarn:flyaway:hairDensity": 20.0,
                                                  "yarn:flyaway:loopDensity": 5.0})])
def test_expansion_estimate_bounds_the_expansion(name, kw):
    """The estimate (made without allocating) is an upper bound of the points and curves the
    expansion makes, close for filaments, and BYTES_PER_POINT bounds its peak memory."""
    params = _yarn(name, **kw)
    z = np.linspace(0.0, 8.0, 40)
    centre = np.stack([0.2 * np.sin(z), 0 * z, z], 1)
    line = CentreLine(centre, 1.0)
    for fraction in (1.0, 0.5):
        est = estimate_expansion(params, line.length, line.median_segment, fiber_fraction=fraction)
        tracemalloc.start()
        ex = expand_yarn(centre, 1.0, params, fiber_fraction=fraction)
        geom = ex.to_curve_geometry(0.01)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        points = len(geom.points)
        assert ex.curve_count <= est.curves and points <= est.points
        if params.staple_length == 0 and params.hair_density == 0:
            assert est.points == points
        assert peak <= BYTES_PER_POINT * points


def _yarn_stage(cam_z: float | None, yarns: int = 1, fibers_per_ply: int | None = None) -> Usd.Stage:
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    c = UsdGeom.BasisCurves.Define(stage, "/Y/Yarns")
    c.CreateTypeAttr("cubic")
    c.CreateBasisAttr("bspline")
    pts = [Gf.Vec3f(x, 0.4 * k, 0) for k in range(yarns) for x in (-1.0, -0.5, 0.0, 0.5, 1.0)]
    c.CreatePointsAttr(pts)
    c.CreateCurveVertexCountsAttr([5] * yarns)
    c.CreateWidthsAttr([0.2415])
    c.SetWidthsInterpolation("constant")
    authoring.apply_yarn(c.GetPrim(), "CNe 50", fiber_preset="polyester")
    if fibers_per_ply is not None:
        c.GetPrim().GetAttribute("yarn:fibersPerPly").Set(fibers_per_ply)
    if cam_z is not None:
        add_camera(stage, cam_z)
    return stage


@pytest.fixture(scope="module")
def render_options(tmp_path_factory):
    from usdfiber.bake.cache import TableCache
    from usdfiber.translators.mitsuba.yarn_far_field import YarnBakeSettings

    cache = TableCache(tmp_path_factory.mktemp("cache"))
    return dict(resolution=(64, 64), spp=1, bake=BakeSettings(resolution_deg=30, photons=2000, batches=2),
                yarn_bake=YarnBakeSettings(30, photons=600, realizations=1), cache=cache)  # one placement: budgets, not far-field bias


def test_yarn_expansion_is_reduced_to_fit_the_budget(render_options):
    """Over the budget, every expanded yarn keeps the same smaller share of its fibers, with a
    warning saying how much; the geometry made fits the budget."""
    from usdfiber.translators.mitsuba.fibers import RENDER_BYTES_PER_SEGMENT
    from usdfiber.translators.mitsuba.scene import SceneOptions, translate_stage

    full = translate_stage(_yarn_stage(1.0, yarns=3), SceneOptions(**render_options,
                                                                    memory_budget=MemoryBudget(1 << 40)))
    n_full = full.counts["yarn_fibers"]
    assert not any("memory budget" in w for w in full.warnings)
    budget = MemoryBudget(full.fibers.segment_count * RENDER_BYTES_PER_SEGMENT // 4, "test")
    small = translate_stage(_yarn_stage(1.0, yarns=3), SceneOptions(**render_options, memory_budget=budget))
    (warning,) = [w for w in small.warnings if "memory budget" in w]
    assert "--memory-budget" in warning and "of the fibers of each expanded yarn" in warning
    assert small.counts["yarn_fibers"] < n_full / 3
    assert small.fibers.segment_count * RENDER_BYTES_PER_SEGMENT <= budget.bytes


def test_yarn_expansion_refuses_when_one_fiber_per_yarn_does_not_fit(render_options):
    from usdfiber.translators.mitsuba.scene import SceneOptions, translate_stage

    with pytest.raises(MemoryBudgetError, match=r"yarn fibers of 2 expanded yarns \(one fiber per yarn.*"
                                                r"memory budget of 1000 B \(test\)"):
        translate_stage(_yarn_stage(1.0, yarns=3), SceneOptions(**render_options,
                                                                memory_budget=MemoryBudget(1000, "test")))


def test_a_stage_without_a_camera_gets_level_of_detail_from_the_default_framing(render_options):
    """The default camera frames the 2 mm yarns from about 8 mm: they are a few pixels wide at
    64 px, so fewer fibers are kept (level of detail was off without a camera)."""
    from usdfiber.translators.mitsuba.scene import SceneOptions, translate_stage

    tr = translate_stage(_yarn_stage(None, yarns=2), SceneOptions(**render_options))
    c = tr.counts
    assert tr.camera == "default" and c["yarn_yarns"] == 2 and c["yarn_culled"] == 0
    assert c["yarn_far"] == 2 or c["yarn_fibers"] < c["yarn_fibers_full"]
    off = translate_stage(_yarn_stage(None, yarns=2), SceneOptions(**render_options, lod_scale=0.0))
    assert off.counts["yarn_fibers"] == off.counts["yarn_fibers_full"] > c["yarn_fibers"]


# ---- cloth, imports, bakes -----------------------------------------------------------------------

def test_cloth_is_refused_before_allocation(capsys):
    stage = Usd.Stage.CreateInMemory()
    tracemalloc.start()
    with pytest.raises(MemoryBudgetError, match=r"cloth stockinette of 1000000 rows x 1000000 loops "
                                                r"\(16000003000000 control points\) needs about"):
        cloth.stockinette(stage, "/Cloth", rows=1_000_000, loops=1_000_000, memory_budget=MemoryBudget(1 << 30))
    assert tracemalloc.get_traced_memory()[1] < 50 << 20
    tracemalloc.stop()
    assert not stage.GetPrimAtPath("/Cloth")
    with pytest.raises(MemoryBudgetError, match="cloth satin of 20 warps x 20 wefts"):
        cloth.satin(stage, "/Satin", memory_budget=MemoryBudget(10_000, "test"))
    cloth.plain_weave(stage, "/Plain", warps=2, wefts=2, memory_budget=MemoryBudget(1 << 20))
    assert stage.GetPrimAtPath("/Plain/Warp")


def test_cloth_command_default_budget_refuses_a_huge_cloth(tmp_path, capsys):
    rc = main(["cloth", "stockinette", "--rows", "1000000", "--loops", "1000000", "-o", str(tmp_path / "c.usda")])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "needs about" in err and "--memory-budget" in err
    assert not (tmp_path / "c.usda").exists()


def _bcc(path, n_curves: int, n_points: int, scale: float = 1.0) -> None:
    head = b"BCC" + bytes([0x44]) + b"PL" + bytes([3, 1]) + struct.pack("<QQ", n_curves, n_curves * n_points)
    body = b""
    for k in range(n_curves):
        pts = np.stack([np.arange(n_points), np.full(n_points, k), np.zeros(n_points)], 1) * scale
        body += struct.pack("<i", n_points) + pts.astype("<f4").tobytes()
    path.write_bytes(head + b"\0" * 40 + body)


def test_import_is_refused_over_the_budget(tmp_path):
    src = tmp_path / "c.bcc"
    _bcc(src, 10, 100)
    with pytest.raises(MemoryBudgetError, match=r"c.bcc: importing a curve file of \d+ bytes"):
        import_curves(src, tmp_path / "o.usda", memory_budget=MemoryBudget(1000, "test"))
    assert not (tmp_path / "o.usda").exists()
    import_curves(src, tmp_path / "o.usda", memory_budget=MemoryBudget(1 << 22, "test"))
    assert (tmp_path / "o.usda").exists()


def test_bake_is_refused_over_the_budget(tmp_path, capsys):
    rc = main(["bake", "--preset", "silk", "--resolution", "10", "--memory-budget", "1M",
               "--cache-dir", str(tmp_path)])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1
    assert "baking 1 table at a time at --resolution 10 needs about" in err and "1 MiB (--memory-budget)" in err
    assert not (tmp_path / "tables").exists()
    s = BakeSettings(resolution_deg=0.5)
    assert s.table_bytes() > 1 << 40 > BakeSettings().table_bytes()


def test_reference_normals_of_many_segments_peak_in_chunks():
    """The reference frames of expanded yarns (millions of segments) are formed in chunks of
    whole curves: the peak stays near a chunk's, not about 600 bytes per segment of the whole
    (the 9M segments of a long yarn at full detail took 5 GB and broke the memory budget)."""
    import tracemalloc

    from usdfiber.geometry.curves import NORMALS_CHUNK, CurveGeometry, reference_normals

    n_curves, per_curve = 20, 50_000                  # 1M segments, 20 curves
    rng = np.random.default_rng(0)
    n_pts = per_curve + 3
    pts = np.cumsum(rng.normal(size=(n_curves * n_pts, 3)), axis=0)
    starts = (np.arange(n_curves)[:, None] * n_pts + np.arange(per_curve)).ravel()
    geom = CurveGeometry(pts, np.ones(len(pts)), starts, np.repeat(np.arange(n_curves), per_curve), n_curves)
    tracemalloc.start()
    try:
        out = reference_normals(geom)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert out.shape == (n_curves * per_curve, 3) and np.all(np.isfinite(out))
    # The output (24 B per segment) and the curve marks, plus one chunk of whole curves (at
    # most NORMALS_CHUNK + one curve, 312k segments) at about 600 B per segment: under 300 MB;
    # all 1M segments at once peaked at 620 MB.
    assert NORMALS_CHUNK + per_curve < 320_000
    assert peak < 300e6, peak
