"""``usdfiber render --frames``: a frame range of an animated stage, and a rerun after deleting frames."""
from __future__ import annotations

import json

import pytest

import usdfiber  # noqa: F401
from farm_util import run_usdfiber
from pxr import Usd, UsdGeom

from usdfiber import authoring
from usdfiber import image_output

FAST = ["--resolution", "16x12", "--spp", "1", "--bake-resolution", "30", "--bake-photons", "2000", "--no-png",
        "--no-progress", "--json"]


@pytest.fixture(scope="module")
def animated(tmp_path_factory):
    """Fiber curves that move, with a time-sampled depth of shade."""
    d = tmp_path_factory.mktemp("anim")
    path = d / "anim.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(4)
    c = UsdGeom.BasisCurves.Define(stage, "/World/Fibers")
    c.CreateCurveVertexCountsAttr([4, 4])
    c.CreateWidthsAttr([0.02])
    c.SetWidthsInterpolation(UsdGeom.Tokens.constant)
    pts = c.CreatePointsAttr()
    for t in range(1, 5):
        dx = 0.1 * t
        pts.Set([(dx, 0, 0), (dx + 1, 0.2, 0), (dx + 2, 0, 0), (dx + 3, 0.2, 0),
                 (dx, 0.5, 0), (dx + 1, 0.7, 0), (dx + 2, 0.5, 0), (dx + 3, 0.7, 0)], t)
    authoring.apply_fiber(c.GetPrim(), "polyester", dye="disperseRed", depth_of_shade=1.0)
    dos = c.GetPrim().GetAttribute("fiber:dye:depthOfShade")
    for t in range(1, 5):
        dos.Set(0.5 * t, t)
    stage.GetRootLayer().Save()
    return path


def test_frame_range_renders_every_frame_and_a_rerun_only_the_missing(animated, tmp_path):
    cache = tmp_path / "cache"
    pattern = tmp_path / "out" / "shot.####.exr"
    pattern.parent.mkdir()
    r = run_usdfiber("render", animated, "--frames", "1-4", "-o", pattern, *FAST, cache=cache, timeout=600)
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert [f["frame"] for f in s["frames"]] == [1, 2, 3, 4] and {f["status"] for f in s["frames"]} == {"rendered"}
    # Each frame carries the single-frame summary of `render --json`.
    assert all(f["path"] in f["render"]["files"] and f["render"]["resolution"] == [16, 12] for f in s["frames"])
    files = [tmp_path / "out" / f"shot.{f:04d}.exr" for f in range(1, 5)]
    images = [image_output.read_exr(f) for f in files]
    assert all(meta.get("usdfiber:frame") in (str(float(f)), str(f), f"{float(f):g}")
               for f, (_, meta) in zip(range(1, 5), images)), [m.get("usdfiber:frame") for _, m in images]
    assert not (images[0][0] == images[3][0]).all()          # the fibers moved and changed colour
    files[1].unlink()
    files[3].unlink()
    again = run_usdfiber("render", animated, "--frames", "1-4", "-o", pattern, *FAST, cache=cache, timeout=600)
    assert again.returncode == 0, again.stderr
    s2 = json.loads(again.stdout)
    assert {f["frame"]: f["status"] for f in s2["frames"]} == {1: "skipped", 2: "rendered", 3: "skipped",
                                                                4: "rendered"}
    assert all(f.exists() for f in files)


def test_bad_frame_ranges_are_one_line(animated, tmp_path):
    for frames, words in (("", "empty frame range"), ("10-1", "empty frame range"), ("1-3", "frame placeholder")):
        out = tmp_path / ("shot.exr" if frames == "1-3" else "shot.####.exr")
        r = run_usdfiber("render", animated, "--frames", frames, "-o", out, "--no-progress")
        assert r.returncode == 2 and r.stderr.count("\n") == 1 and words in r.stderr, r.stderr


def _statuses(run) -> dict[int, str]:
    assert run.returncode == 0, run.stderr
    return {int(f["frame"]): f["status"] for f in json.loads(run.stdout)["frames"]}


@pytest.mark.slow
def test_frame_range_on_a_local_cluster_and_a_rerun_only_the_missing(animated, tmp_path):
    cache = tmp_path / "cache"
    pattern = tmp_path / "out" / "shot.####.exr"
    pattern.parent.mkdir()
    r = run_usdfiber("render", animated, "--frames", "1-4", "-o", pattern, "--scheduler", "local:2", *FAST,
                     cache=cache, timeout=900)
    s = json.loads(r.stdout) if r.returncode == 0 else None
    assert _statuses(r) == {1: "rendered", 2: "rendered", 3: "rendered", 4: "rendered"}
    assert s["engine"] == "dask" and s["workers"] == 2 and s["tasks"]["run"] == 4 and s["ok"]
    assert len(s["frames"]) == 4                                     # each frame once
    files = [tmp_path / "out" / f"shot.{f:04d}.exr" for f in range(1, 5)]
    for f, path in zip(range(1, 5), files):
        assert float(image_output.read_exr(path)[1]["usdfiber:frame"]) == f
    files[0].unlink()
    files[2].unlink()
    again = run_usdfiber("render", animated, "--frames", "1-4", "-o", pattern, "--scheduler", "local:2", *FAST,
                         cache=cache, timeout=900)
    assert _statuses(again) == {1: "rendered", 2: "skipped", 3: "rendered", 4: "skipped"}
    assert all(f.exists() for f in files)


@pytest.mark.slow
def test_frame_range_as_shards_renders_each_frame_once(animated, tmp_path):
    cache = tmp_path / "cache"
    pattern = tmp_path / "out" / "shot.####.exr"
    pattern.parent.mkdir()

    def shard(spec):
        return _statuses(run_usdfiber("render", animated, "--frames", "1-4", "-o", pattern, "--shard", spec, *FAST,
                                      cache=cache, timeout=900))

    second, first = shard("2/2"), shard("1/2")        # any order
    assert first == {1: "rendered", 3: "rendered"} and second == {2: "rendered", 4: "rendered"}
    files = {f: tmp_path / "out" / f"shot.{f:04d}.exr" for f in range(1, 5)}
    assert all(p.exists() for p in files.values())
    files[2].unlink()
    files[3].unlink()
    assert shard("1/2") == {1: "skipped", 3: "rendered"}
    assert shard("2/2") == {2: "rendered", 4: "skipped"}
    assert all(p.exists() for p in files.values())
