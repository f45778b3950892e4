"""Compositing outputs of `usdfiber render`: alpha, AOV layers in the EXR, the JSON summary."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

import usdfiber  # noqa: F401  (registers schemas first)
from pxr import Gf, UsdGeom, UsdLux

from usdfiber.cli import main
from usdfiber.image_output import ImageOutputError, read_exr, read_exr_channels, write_exr
from stage_util import single_fiber_stage

FAST = ["--bake-resolution", "15", "--bake-photons", "4000"]


@pytest.fixture(autouse=True)
def _cache(table_cache_dir, monkeypatch):
    monkeypatch.setenv("USDFIBER_CACHE_DIR", str(table_cache_dir))


def test_exr_layers_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    rgb = rng.random((6, 5, 3)).astype(np.float32)
    alpha = rng.random((6, 5)).astype(np.float32)
    normal = rng.random((6, 5, 3)).astype(np.float32)
    depth = rng.random((6, 5)).astype(np.float32)
    path = tmp_path / "l.exr"
    write_exr(path, rgb, half=False, extra_channels={"A": alpha, "normal": normal, "depth": depth},
              channel_names={"A": ("A",), "normal": ("normal.X", "normal.Y", "normal.Z"), "depth": ("depth.Z",)})
    ch = read_exr_channels(path)
    assert set(ch) == {"R", "G", "B", "A", "normal.X", "normal.Y", "normal.Z", "depth.Z"}
    np.testing.assert_array_equal(ch["A"], alpha)
    np.testing.assert_array_equal(np.stack([ch["normal.X"], ch["normal.Y"], ch["normal.Z"]], -1), normal)
    np.testing.assert_array_equal(ch["depth.Z"], depth)
    np.testing.assert_array_equal(read_exr(path)[0], rgb)
    with pytest.raises(ImageOutputError, match="3 channel\\(s\\) but 2 name\\(s\\)"):
        write_exr(path, rgb, extra_channels={"normal": normal}, channel_names={"normal": ("N.X", "N.Y")})


def _stage(path, dome: bool = False):
    stage, _ = single_fiber_stage(path, "polyester", dye="disperseRed", depth_of_shade=1.0)
    if dome:
        UsdLux.DomeLight.Define(stage, "/World/Dome").CreateIntensityAttr(1.0)
    else:
        light = UsdLux.DistantLight.Define(stage, "/World/Key")
        light.CreateIntensityAttr(1.0)
        light.CreateNormalizeAttr(True)
    cam = UsdGeom.Camera.Define(stage, "/World/Cam")
    cam.CreateProjectionAttr("orthographic")
    cam.CreateHorizontalApertureAttr(400.0)   # 40 um: 1 pixel per um at 40x20
    cam.CreateVerticalApertureAttr(200.0)
    cam.AddTranslateOp().Set(Gf.Vec3d(0, 0, 100))
    stage.GetRootLayer().Save()
    return str(path)


def test_render_writes_alpha_and_aovs(tmp_path, capsys):
    path = _stage(tmp_path / "a.usda")
    out = tmp_path / "a.exr"
    rc = main(["render", path, "-o", str(out), "--no-png", "--resolution", "40x20", "--spp", "8", "--no-progress",
               "--float", "--aov", "albedo,normal,depth,position", "--json", *FAST])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    summary = json.loads(captured.out)              # stdout is the JSON summary alone
    assert summary["files"] == [str(out)] and summary["resolution"] == [40, 20] and summary["spp"] == 8
    assert summary["aovs"] == ["albedo", "normal", "depth", "position"]
    assert summary["counts"]["fiber_curves"] == 1 and "render" in summary["times_s"]
    ch = read_exr_channels(out)
    assert set(summary["exr_channels"]) == set(ch)
    assert {"A", "albedo.R", "albedo.G", "albedo.B", "normal.X", "normal.Y", "normal.Z", "depth.Z",
            "position.X", "position.Y", "position.Z"} <= set(ch)
    # The fiber spans y in [-5, 5] um: rows 5-14 of 20 (1 um per pixel, +y up). The film's
    # filter blurs about 2 pixels; rows 0-1 and 18-19 see nothing, rows 8-11 only the fiber.
    a = ch["A"]
    assert np.all(a[:2] == 0) and np.all(a[-2:] == 0)
    np.testing.assert_allclose(a[8:12], 1.0, atol=1e-6)
    y = 10 - (np.arange(20) + 0.5)                  # pixel centres, um
    for row in (8, 9, 10, 11):
        # Orthographic rays along -z from the near plane (z = 100 - 1, USD's default clipping
        # range) meet the tube at z = sqrt(25 - y^2); the filter spreads each pixel over +-2
        # pixels of y, hence the tolerances.
        z = math.sqrt(25 - y[row] ** 2)
        np.testing.assert_allclose(ch["depth.Z"][row], 99 - z, atol=0.6)
        np.testing.assert_allclose(ch["position.Z"][row], z, atol=0.6)
        np.testing.assert_allclose(ch["position.Y"][row], y[row], atol=0.6)
        np.testing.assert_allclose(ch["normal.Z"][row], z / 5, atol=0.15)
    np.testing.assert_allclose(ch["position.X"][10], (np.arange(40) + 0.5) - 20, atol=0.6)
    assert np.all(ch["depth.Z"][:2] == 0)           # nothing there
    alb = np.stack([ch["albedo.R"], ch["albedo.G"], ch["albedo.B"]], -1)
    assert np.all(np.isfinite(alb)) and np.all(alb[8:12] > 0) and np.all(alb[:2] == 0)
    # R, G, B are the image itself.
    rgb = read_exr(out)[0]
    assert rgb[10].mean() > 0 and np.all(rgb[:2] == 0)


def test_visible_dome_is_opaque_and_no_aovs_by_default(tmp_path, capsys):
    path = _stage(tmp_path / "d.usda", dome=True)
    out = tmp_path / "d.exr"
    assert main(["render", path, "-o", str(out), "--no-png", "--resolution", "20x10", "--spp", "2",
                 "--no-progress", *FAST]) == 0
    capsys.readouterr()
    ch = read_exr_channels(out)
    assert set(ch) == {"R", "G", "B", "A"}
    np.testing.assert_allclose(ch["A"], 1.0)       # the dome is what the camera sees behind


def test_bad_aov_is_one_line(tmp_path, capsys):
    path = _stage(tmp_path / "b.usda")
    assert main(["render", path, "--aov", "albedo,motion", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "unknown AOV(s) motion" in err and "valid: albedo, normal, depth, position" in err
    assert err.count("\n") == 1


def test_albedo_aov_is_the_fibers_albedo(tmp_path, table_cache_dir, capsys):
    """The albedo layer on a dyed fiber is its table's albedo Lambda(omega_v), recoloured,
    for the viewer's direction (here perpendicular to the fiber: theta_v = 0). Exact up to
    the renderer's float16 nodes (2^-11 relative) and float32 sums: bound 2e-3."""
    from pxr import Usd

    from usdfiber.bcsdf import BakeSettings, TableCache, tables_for_prim
    from usdfiber.spec.fiber import FiberParams

    path = _stage(tmp_path / "alb.usda")
    out = tmp_path / "alb.exr"
    assert main(["render", path, "-o", str(out), "--no-png", "--resolution", "40x20", "--spp", "4",
                 "--no-progress", "--float", "--aov", "albedo", *FAST]) == 0
    capsys.readouterr()
    ch = read_exr_channels(out)
    alb = np.stack([ch["albedo.R"], ch["albedo.G"], ch["albedo.B"]], -1)[8:12].reshape(-1, 3)   # fiber only
    stage = Usd.Stage.Open(path)
    prim = stage.GetPrimAtPath("/World/Fiber")
    params = FiberParams.from_prim(prim)
    (table,) = tables_for_prim(prim, BakeSettings(resolution_deg=15, photons=4000), bake_missing=False,
                               cache=TableCache(table_cache_dir))
    want = table.albedo(0.0, 0.0, list(table.sigma_for(params.mu_a, params.diameter)))
    print(f"\n[aov] albedo layer {alb.mean(axis=0)}, table {want}")
    assert want[0] > want[1] + 0.05                     # dyed: the check tells colours apart
    np.testing.assert_allclose(alb, np.broadcast_to(want, alb.shape), rtol=2e-3)
