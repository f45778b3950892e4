"""examples/make_paper_scenes.py: the stages after the paper's Figures 11, 7, 1 and 5.

The stages are written into tmp_path, checked (no errors, no warnings), their prims looked
at, and translated with tiny bake settings: Figure 5 whole (silk), the other stages with
only their silk pieces active so that every stage goes through the translator (yarn
expansion included) while one silk table set is baked for the whole module.
"""
from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

import usdfiber  # noqa: F401  (registers schemas first)
from pxr import Usd, UsdGeom, UsdLux, UsdShade

from usdfiber.bake.settings import BakeSettings
from usdfiber.bake.cache import TableCache
from usdfiber.translators.mitsuba.scene import SceneOptions, translate_stage
from usdfiber.translators.mitsuba.yarn_far_field import YarnBakeSettings
from usdfiber.validation.runner import check_stage

SCRIPT = Path(__file__).resolve().parents[2] / "examples" / "make_paper_scenes.py"
TINY = BakeSettings(resolution_deg=30, photons=500, batches=2)
STAGES = ("fig11_threads.usda", "fig7_swatches.usda", "fig1_satin_garter.usda",
          "fig5_dos_series.usda")


def _load_script():
    spec = importlib.util.spec_from_file_location("make_paper_scenes", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    out = tmp_path_factory.mktemp("paper-scenes")
    mod = _load_script()
    assert mod.main([str(out)]) == 0
    return mod, out


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    mp = pytest.MonkeyPatch()
    root = tmp_path_factory.mktemp("paper-scenes-cache")
    mp.setenv("USDFIBER_CACHE_DIR", str(root))
    yield TableCache(root)
    mp.undo()


def _open(out: Path, name: str) -> Usd.Stage:
    return Usd.Stage.Open(str(out / name))


@pytest.mark.parametrize("name", STAGES)
def test_stage_checks_clean_and_has_a_set(scenes, name):
    _, out = scenes
    assert (out / name).is_file()
    report = check_stage(out / name)
    assert not report.problems, [str(p) for p in report.problems]
    stage = _open(out, name)
    assert UsdGeom.GetStageMetersPerUnit(stage) == pytest.approx(0.001)
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    prims = list(stage.Traverse())
    assert sum(p.IsA(UsdGeom.Camera) for p in prims) == 1
    assert sum(p.IsA(UsdLux.DomeLight) for p in prims) == 1
    assert sum(p.IsA(UsdLux.DistantLight) for p in prims) == 1
    cards = [p for p in prims if p.IsA(UsdGeom.Mesh)]
    assert len(cards) == 1
    mat, _ = UsdShade.MaterialBindingAPI(cards[0]).ComputeBoundMaterial()
    assert mat and mat.GetSurfaceOutput().HasConnectedSource()


def test_fig11_four_threads_times_three_shades(scenes):
    mod, out = scenes
    stage = _open(out, "fig11_threads.usda")
    seen = set()
    for prim_name, preset, dye in mod.FIG11_THREADS:
        kids = stage.GetPrimAtPath(f"/Fig11/{prim_name}").GetChildren()
        assert [k.GetName() for k in kids] == [s for s, _ in mod.FIG11_SHADES]
        for kid, (_, dos) in zip(kids, mod.FIG11_SHADES):
            assert kid.HasAPI("FiberYarnAPI") and kid.HasAPI("FiberAPI")
            assert kid.GetAttribute("fiber:dye:depthOfShade").Get() == pytest.approx(dos)
            seen.add((preset, kid.GetAttribute("fiber:kind").Get(),
                      kid.GetAttribute("fiber:dye:class").Get()))
    assert seen == {("Skala 360", "polyester", "disperse"), ("ORA 120", "polyester", "disperse"),
                    ("CNe 50", "cotton", "reactive"), ("S 303", "silk", "reactive")}


def test_fig7_same_knit_four_fibers(scenes):
    mod, out = scenes
    stage = _open(out, "fig7_swatches.usda")
    shapes = []
    for kind in mod.FIG7_KINDS:
        rows = stage.GetPrimAtPath(f"/Fig7/{kind[0].upper()}{kind[1:]}/Rows")
        assert rows.HasAPI("FiberYarnAPI")
        assert rows.GetAttribute("fiber:kind").Get() == kind
        assert rows.GetAttribute("fiber:dye:depthOfShade").Get() == pytest.approx(mod.FIG7_DOS)
        assert rows.GetAttribute("yarn:plies").Get() == 1
        assert rows.GetAttribute("yarn:fibersPerPly").Get() == mod.fig7_fibers_per_ply(kind)
        shapes.append((len(rows.GetAttribute("points").Get()),
                       round(float(rows.GetAttribute("widths").Get()[0]), 6)))
    assert len(set(shapes)) == 1  # the same knitted geometry for every fiber


def test_fig1_satin_and_garter(scenes):
    _, out = scenes
    stage = _open(out, "fig1_satin_garter.usda")
    for part in ("Warp", "Weft"):
        p = stage.GetPrimAtPath(f"/Fig1/SilkSatin/{part}")
        assert p.GetAttribute("fiber:kind").Get() == "silk"
        assert len(p.GetAttribute("curveVertexCounts").Get()) == 20
    rows = stage.GetPrimAtPath("/Fig1/CottonGarter/Rows")
    assert rows.GetAttribute("fiber:kind").Get() == "cotton"
    assert len(rows.GetAttribute("curveVertexCounts").Get()) == 8


def test_fig5_silk_dos_series(scenes):
    mod, out = scenes
    stage = _open(out, "fig5_dos_series.usda")
    for name, dos in mod.FIG5_SHADES:
        p = stage.GetPrimAtPath(f"/Fig5/{name}")
        assert p.HasAPI("FiberAPI") and not p.HasAPI("FiberYarnAPI")
        assert p.GetAttribute("fiber:kind").Get() == "silk"
        assert p.GetAttribute("fiber:dye:depthOfShade").Get() == pytest.approx(dos)
        assert len(p.GetAttribute("curveVertexCounts").Get()) == 120
    assert len({stage.GetPrimAtPath(f"/Fig5/{n}").GetAttribute("fiber:dye:extinction").Get()
                for n, _ in mod.FIG5_SHADES}) == 1  # one dye


# Prims left active when translating: only the silk pieces (one table set for all stages).
SILK_ONLY = {
    "fig5_dos_series.usda": None,
    "fig11_threads.usda": ["/Fig11/Skala360", "/Fig11/ORA120", "/Fig11/CNe50"],
    "fig7_swatches.usda": ["/Fig7/Cotton", "/Fig7/Polyester", "/Fig7/Wool"],
    "fig1_satin_garter.usda": ["/Fig1/CottonGarter"],
}


@pytest.mark.parametrize("name", list(SILK_ONLY))
def test_translates(scenes, cache, name):
    _, out = scenes
    stage = _open(out, name)
    for path in SILK_ONLY[name] or ():
        stage.GetPrimAtPath(path).SetActive(False)
    # lod_scale 0: every fiber (at 16 x 16 px the yarns would be drawn with their far fields)
    tr = translate_stage(stage, SceneOptions(resolution=(16, 16), spp=1, bake=TINY, cache=cache, lod_scale=0.0,
                                             yarn_bake=YarnBakeSettings(30, photons=400, realizations=1)))
    assert tr.camera != "default"
    assert tr.counts["lights"] == 2 and tr.counts["meshes"] == 1
    assert tr.counts["fiber_curves"] > 0 and tr.counts["fiber_tables"] == 4  # silk's variants
    if name != "fig5_dos_series.usda":
        assert tr.counts["yarn_yarns"] > 0 and tr.counts["yarn_fibers"] > 0
    assert not [w for w in tr.warnings if "default" in w]
