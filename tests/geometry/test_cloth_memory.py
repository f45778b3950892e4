"""Procedural cloth at garment scale: yarn-by-yarn generation in bounded memory.

The generators make one yarn at a time straight into each prim's float32 scene points, so a
cloth costs USD's 12 bytes per control point plus one prim's float32 copy while it is
authored (``cloth.memory_estimate``). These tests hold the output to what the whole-cloth
generator wrote before, the NumPy side's peak to one prim's float32 points, and the
estimate to the process's measured peak memory.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

import usdfiber  # noqa: F401  (registers the schemas before any stage exists)
from pxr import Usd, UsdGeom

from usdfiber import cloth
from usdfiber.cli import main
from usdfiber.memory_budget import MemoryBudget, MemoryBudgetError

# Points written by the generator before it worked yarn by yarn (commit 7e56143: every yarn's
# float64 control points, stacked, scaled to the stage's unit, rounded to float32), for the
# cases below, in millimetre and centimetre stages; keys "case/metersPerUnit/prim".
GOLDEN = Path(__file__).parent / "data" / "cloth_points.npz"
CASES = {
    "plain_3x4": (cloth.plain_weave, dict(warps=3, wefts=4)),
    "satin_6x5_skala": (cloth.satin, dict(warps=6, wefts=5, yarn="Skala 360")),
    "stockinette_3x2": (cloth.stockinette, dict(rows=3, loops=2)),
    "garter_3x2_wool": (cloth.garter, dict(rows=3, loops=2, fiber="wool", loop_size=1.2)),
}


def weave_points(warps: int, wefts: int) -> list[int]:
    """Control points of a weave's Warp and Weft prims (4 per crossing plus 3 per yarn)."""
    return [warps * (4 * wefts + 3), wefts * (4 * warps + 3)]


@pytest.mark.parametrize("case", sorted(CASES))
@pytest.mark.parametrize("mpu", [0.001, 0.01])
def test_points_equal_the_whole_cloth_generator(case, mpu):
    """The same float32 points as before, to one unit in the last place (the float64
    trigonometry and FFT may differ in their last bit between SIMD widths; before rounding
    to float32 that moves a point by at most one float32 ulp)."""
    gen, kw = CASES[case]
    golden = np.load(GOLDEN)
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, mpu)
    root = gen(stage, "/C", **kw)
    children = root.GetChildren()
    assert children
    for child in children:
        pts = np.array(child.GetAttribute("points").Get(), np.float32)
        np.testing.assert_array_max_ulp(pts, golden[f"{case}/{mpu:g}/{child.GetName()}"], maxulp=1)


def test_numpy_peak_is_one_prims_float32_points():
    """While a 300 x 300 weave (721,800 control points) is generated, NumPy's peak allocation
    is one prim's float32 points (the array USD copies) plus yarn-sized temporaries: not the
    float64 copies of the whole cloth that the generator made before (about 48 bytes per
    control point)."""
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    cloth.plain_weave(stage, "/Warm", warps=2, wefts=2)           # imports and caches first
    largest = max(weave_points(300, 300))
    tracemalloc.start()
    try:
        cloth.plain_weave(stage, "/C", warps=300, wefts=300, yarn="Skala 360")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert cloth.POINT_BYTES * largest <= peak <= cloth.POINT_BYTES * largest + (1 << 20), peak
    assert len(stage.GetPrimAtPath("/C/Warp").GetAttribute("points").Get()) == largest


def test_memory_estimate():
    panel = weave_points(2500, 2500)
    assert sum(panel) == 50_015_000
    # USD's points plus the larger prim's float32 copy: 0.84 GiB for the shirt panel.
    assert cloth.memory_estimate(panel) == 12 * sum(panel) + 12 * max(panel)
    assert cloth.memory_estimate(panel) / 2**30 == pytest.approx(0.838, abs=0.001)
    assert cloth.memory_estimate(panel, "usdc") == cloth.memory_estimate(panel)
    assert cloth.memory_estimate(panel, "usda") == (12 + 64) * sum(panel)
    assert cloth.memory_estimate([1000]) == 24 * 1000                      # a knit: one prim
    with pytest.raises(cloth.ClothError, match="write_format"):
        cloth.memory_estimate(panel, "obj")


def test_the_shirt_panel_fits_the_default_budget_of_a_small_machine():
    """Refused before it was generated yarn by yarn (256 bytes per point: 12 GiB); now 2 GiB
    are enough to generate it (checked before any allocation: the budget alone is tested)."""
    stage = Usd.Stage.CreateInMemory()
    with pytest.raises(MemoryBudgetError, match=r"cloth plain weave of 2500 warps x 2500 wefts \(50015000 control "
                                                r"points, written as usda\) needs about 3.54 GiB"):
        cloth.plain_weave(stage, "/C", warps=2500, wefts=2500, yarn="Skala 360",
                          memory_budget=MemoryBudget(2 << 30, "test"), write_format="usda")
    assert not stage.GetPrimAtPath("/C")
    with pytest.raises(MemoryBudgetError, match=r"needs about 859 MiB"):
        cloth.plain_weave(stage, "/C", warps=2500, wefts=2500, yarn="Skala 360",
                          memory_budget=MemoryBudget(800 << 20, "test"))


MEASURE = textwrap.dedent("""
    import json, sys
    import usdfiber
    from pxr import Usd, UsdGeom
    from usdfiber import cloth
    from usdfiber.memory_budget import MemoryBudget

    def kib(key):
        with open("/proc/self/status") as f:
            return next(int(line.split()[1]) for line in f if line.startswith(key))

    def reset_peak():
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")                       # VmHWM := VmRSS

    warm = Usd.Stage.CreateInMemory()
    cloth.plain_weave(warm, "/W", warps=2, wefts=2)
    cloth.stockinette(warm, "/K", rows=2, loops=2)
    warm.GetRootLayer().Export(sys.argv[1] + ".usda")
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    reset_peak()
    before = kib("VmRSS")
    if sys.argv[2] == "weave":
        cloth.plain_weave(stage, "/C", warps=400, wefts=400, memory_budget=MemoryBudget(1 << 40))
    else:
        cloth.stockinette(stage, "/C", rows=160, loops=250, memory_budget=MemoryBudget(1 << 40))
    out = {sys.argv[2]: (kib("VmHWM") - before) * 1024}
    if sys.argv[2] == "weave":
        reset_peak()
        stage.GetRootLayer().Export(sys.argv[1] + ".usda")
        out["weave_usda"] = (kib("VmHWM") - before) * 1024
    print(json.dumps(out))
""")


@pytest.mark.skipif(not os.access("/proc/self/clear_refs", os.W_OK), reason="needs Linux's /proc/self/clear_refs")
def test_estimate_matches_the_measured_peak(tmp_path):
    """In fresh processes, the peak resident memory of generating a 400 x 400 weave (1.28 M
    control points, two prims), a 160-row knit (640,480 control points, one prim) and of
    writing the weave as .usda lies between 0.8 and 1.1 times cloth.memory_estimate (plus
    2 MiB for the interpreter's own allocations): the budget check refuses what would not
    fit and no more."""
    measured = {}
    for case in ("weave", "knit"):
        proc = subprocess.run([sys.executable, "-c", MEASURE, str(tmp_path / case), case], capture_output=True,
                              text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr
        measured.update(json.loads(proc.stdout.strip().splitlines()[-1]))
    expected = {"weave": cloth.memory_estimate(weave_points(400, 400)),
                "knit": cloth.memory_estimate([160 * (16 * 250 + 3)]),
                "weave_usda": cloth.memory_estimate(weave_points(400, 400), "usda")}
    for name, estimate in expected.items():
        assert 0.8 * estimate <= measured[name] <= 1.1 * estimate + (2 << 20), (name, measured[name], estimate)


def test_cli_counts_the_writers_memory(tmp_path, capsys):
    """A 100 x 100 weave needs 1.4 MB to generate, 6.1 MB to write as .usda text: a 3 MB budget
    takes .usdc (and .usd, crate) but refuses .usda, before anything is generated."""
    for name, rc in (("c.usdc", 0), ("c.usd", 0), ("c.usda", 2)):
        out = tmp_path / name
        assert main(["cloth", "plain", "--warps", "100", "--wefts", "100", "--memory-budget", "3MB",
                     "-o", str(out)]) == rc
        err = capsys.readouterr().err
        assert out.exists() == (rc == 0)
        if rc:
            assert "written as usda" in err and "needs about 5.84 MiB" in err and len(err.strip().splitlines()) == 1
