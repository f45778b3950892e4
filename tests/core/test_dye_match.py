"""Dyes matched to a colour (usdfiber.dye_match, `usdfiber dye`): the matched fiber's colour,
computed independently through the table's recolouring, and rendered under a white dome."""
from __future__ import annotations

import math
import os
import stat

import numpy as np
import pytest

import usdfiber  # noqa: F401  (registers schemas first)
from pxr import Gf, Usd, UsdGeom, UsdLux

from usdfiber import dye_match as dm
from usdfiber.bake.cache import TableCache
from usdfiber.bake.requests import params_from_preset, requests_for_params
from usdfiber.bake.settings import BakeSettings
from usdfiber.cli import main
from usdfiber.colour import spectrum_to_rec709
from usdfiber.spec.fiber import FiberParams
from stage_util import single_fiber_stage

# The render tests' settings, so that the run's shared cache bakes the polyester table once.
FAST = ["--bake-resolution", "15", "--bake-photons", "4000"]
FAST_SETTINGS = BakeSettings(resolution_deg=15, photons=4000, batches=4)
DOS = 2.0


@pytest.fixture(autouse=True)
def _cache(table_cache_dir, monkeypatch):
    monkeypatch.setenv("USDFIBER_CACHE_DIR", str(table_cache_dir))
    return table_cache_dir


@pytest.fixture
def polyester(_cache):
    params = params_from_preset("polyester")
    cache = TableCache(_cache)
    tables = [cache.get_or_bake(r, FAST_SETTINGS).table for r in requests_for_params(params, "test")]
    return params, tables


def _reachable_target(fiber: dm.FiberColour, fractions=(0.15, 0.6, 0.85)) -> np.ndarray:
    """A target inside the disperse range's box: each channel part way from light to dark."""
    lo, hi = dm.extinction_range("disperse").lo, dm.extinction_range("disperse").hi
    light, dark = fiber.channel(lo), fiber.channel(hi)
    return np.array([light + f * (dark - light) for f in fractions])


def _independent_colour(tables, params: FiberParams, theta: float = 0.0) -> np.ndarray:
    """The fiber's colour from the prim's resolved mu_a and BcsdfTable.albedo (the public
    recolouring path), width-weighted over rotations: not the matcher's code."""
    phi = np.linspace(0.0, 2 * math.pi, 1440, endpoint=False)
    num = np.zeros(3)
    den = 0.0
    for t in tables:
        w = t.width(phi)
        alb = t.albedo(theta, phi, list(params.mu_a), diameter_scale=params.diameter / t.baked_diameter_um)
        num += (w[:, None] * alb).sum(axis=0)
        den += w.sum()
    return num / den


def _fiber_stage(path, kind="polyester"):
    return single_fiber_stage(path, kind, dye="disperseBlack", depth_of_shade=DOS)


def test_colour_parsing_and_lights():
    np.testing.assert_allclose(dm.parse_colour("#ffffff"), 1.0)
    np.testing.assert_allclose(dm.parse_colour("#000"), 0.0)
    np.testing.assert_allclose(dm.parse_colour("#808080"), 0.2158605, rtol=1e-5)   # sRGB 128 -> linear
    np.testing.assert_allclose(dm.parse_colour("0.4, 0.05,0.02"), [0.4, 0.05, 0.02])
    assert dm.srgb_hex(dm.parse_colour("#b0402a")) == "#b0402a"
    for bad in ("#12345", "red", "0.1,0.2", "1.5,0,0", "-0.1,0,0", "nan,0,0"):
        with pytest.raises(dm.DyeMatchError, match="colour"):
            dm.parse_colour(bad)
    np.testing.assert_allclose(dm.light_rgb("white"), 1.0)
    assert dm.light_rgb("6504K") @ [0.2126, 0.7152, 0.0722] == pytest.approx(1.0)
    for bad in ("0,1,1", "100K", "bright"):
        with pytest.raises(dm.DyeMatchError, match="light"):
            dm.light_rgb(bad)
    with pytest.raises(dm.DyeMatchError, match="dye class"):
        dm.extinction_range("acid")


def test_match_hits_target_through_the_recolouring(polyester, tmp_path):
    params, tables = polyester
    fiber = dm.FiberColour(tables, params.density, params.diameter, DOS)
    target = _reachable_target(fiber)
    m = dm.match_dye(fiber, target, "disperse")
    assert m.in_reach and m.dye_class == "disperse"
    lo, hi = m.range
    assert all(lo <= e <= hi for e in m.extinction)
    # A darker channel needs more dye.
    assert m.extinction[0] < m.extinction[1] < m.extinction[2]
    # Written on a prim, read back by the spec reader, evaluated by BcsdfTable.albedo.
    stage, prim = _fiber_stage(tmp_path / "f.usda")
    dm.author_dye(prim, m)
    got = _independent_colour(tables, FiberParams.from_prim(prim))
    # Root find 1e-6 relative; the float32 extinction and albedo round at ~1e-7.
    np.testing.assert_allclose(got, target, rtol=2e-5)
    # Under a warm light the same target needs a different dye, and reaches it.
    warm = dm.light_rgb("4000K")
    mw = dm.match_dye(fiber, target * warm / warm.max(), "disperse", warm)
    np.testing.assert_allclose(fiber.colour(mw.extinction, warm), target * warm / warm.max(), rtol=1e-5)


def test_match_over_all_views(polyester):
    params, tables = polyester
    fiber = dm.FiberColour(tables, params.density, params.diameter, DOS, theta_deg=None)
    target = _reachable_target(fiber, (0.5, 0.5, 0.2))
    m = dm.match_dye(fiber, target, "disperse")
    # Independently: W cos^2(theta) weights over the incoming nodes of BcsdfTable.albedo.
    t = tables[0]
    g = t.grid
    th, ph = np.meshgrid(g.theta_i_nodes(), g.phi_i_nodes(), indexing="ij")
    mu = [params.density * 1000 * DOS / 100 * e * 1000 * 1e-4 for e in m.extinction]
    alb = t.albedo(th, ph, mu, diameter_scale=params.diameter / t.baked_diameter_um)
    w = t.width(ph) * np.cos(th) ** 2
    np.testing.assert_allclose((w[..., None] * alb).sum(axis=(0, 1)) / w.sum(), target, rtol=2e-5)


def test_out_of_reach_names_the_nearest_colour(polyester):
    params, tables = polyester
    fiber = dm.FiberColour(tables, params.density, params.diameter, DOS)
    lo, hi = dm.extinction_range("disperse").lo, dm.extinction_range("disperse").hi
    light, dark = fiber.channel(lo), fiber.channel(hi)
    inside = 0.5 * (light + dark)
    target = np.array([min(1.0, light * 1.5), inside, dark * 0.5])   # R too light, B too dark
    with pytest.raises(dm.ColourOutOfReach, match="nearest reachable colour #") as info:
        dm.match_dye(fiber, target, "disperse")
    m = info.value.match
    assert m.reachable == (False, True, False)
    assert m.extinction[0] == lo and m.extinction[2] == hi
    np.testing.assert_allclose(m.colour, [light, inside, dark], rtol=1e-6)
    assert "channel(s) R, B" in str(info.value)
    # The schema's valid range reaches the light red the industry range cannot.
    custom = dm.match_dye(fiber, [light * 1.5, inside, inside], "custom")
    assert custom.extinction[0] < lo
    with pytest.raises(dm.DyeMatchError, match="depth of shade 0"):
        dm.match_dye(dm.FiberColour(tables, params.density, params.diameter, 0.0), target, "disperse")


def test_spectral_dye_reduces_to_the_matched_extinction(polyester, tmp_path):
    params, tables = polyester
    fiber = dm.FiberColour(tables, params.density, params.diameter, DOS)
    m = dm.match_dye(fiber, _reachable_target(fiber), "disperse")
    wl, values = dm.spectral_extinction(m.extinction)
    assert wl[0] <= 400 and wl[-1] >= 700 and min(values) >= 0
    np.testing.assert_allclose(spectrum_to_rec709(wl, values), m.extinction, rtol=1e-4)
    stage, prim = _fiber_stage(tmp_path / "s.usda")
    dm.author_dye(prim, m, spectral=True)
    p = FiberParams.from_prim(prim)
    assert p.extinction_source == "spectrum"
    np.testing.assert_allclose(p.extinction, m.extinction, rtol=1e-4)
    np.testing.assert_allclose(_independent_colour(tables, p), m.target, rtol=2e-4)
    # A pure blue absorber: the red channel's weights overlap blue (x_bar's short lobe).
    with pytest.raises(dm.DyeMatchError, match="no smooth non-negative spectrum"):
        dm.spectral_extinction((0.0, 0.0, 1.0))


def test_cli_match_write_and_errors(polyester, tmp_path, capsys):
    params, tables = polyester
    fiber = dm.FiberColour(tables, params.density, params.diameter, DOS)
    target = _reachable_target(fiber)
    hexcol = dm.srgb_hex(target)
    stage, prim = _fiber_stage(tmp_path / "c.usda")
    stage.GetRootLayer().Save()
    path = str(tmp_path / "c.usda")
    rc = main(["dye", "--match", hexcol, "--stage", path, "--prim", "/World/Fiber", "--write", "--json", *FAST])
    out = capsys.readouterr()
    assert rc == 0, out.err
    reread = Usd.Stage.Open(path)
    p = FiberParams.from_prim(reread.GetPrimAtPath("/World/Fiber"))
    assert p.dye_class == "disperse" and p.depth_of_shade == pytest.approx(DOS)
    # The hex code rounds the target to 8 bits: compare with the colour it encodes.
    np.testing.assert_allclose(_independent_colour(tables, p), dm.parse_colour(hexcol), rtol=2e-5)

    rc = main(["dye", "--match", "#ffffff", "--fiber", "polyester", "--depth-of-shade", "2", *FAST])
    err = capsys.readouterr().err
    assert rc == 1 and "out of reach" in err and "nearest reachable colour #" in err and err.count("\n") == 1
    for argv, msg in ((["--match", "#12", "--fiber", "polyester"], "expected an sRGB hex colour"),
                      (["--match", "#808080"], "give either --fiber"),
                      (["--match", "#808080", "--fiber", "nylon"], "unknown fiber preset"),
                      (["--match", "#808080", "--stage", path, "--prim", "/Nope"], "no prim at /Nope"),
                      (["--match", "#808080", "--fiber", "polyester", "--light", "0,1,1"], "every channel"),
                      (["--match", "#808080", "--fiber", "polyester", "--depth-of-shade", "0"], "depth-of-shade")):
        assert main(["dye", *argv, *FAST]) == 2
        err = capsys.readouterr().err
        assert msg in err and err.count("\n") == 1, err
    os.chmod(path, stat.S_IRUSR)
    try:
        assert main(["dye", "--match", hexcol, "--stage", path, "--prim", "/World/Fiber", "--write", *FAST]) == 2
        assert "read-only" in capsys.readouterr().err
    finally:
        os.chmod(path, stat.S_IRUSR | stat.S_IWUSR)


def test_render_under_white_dome_reproduces_the_target(polyester, tmp_path):
    """A wide, straight polyester fiber seen perpendicular (orthographic camera) under a white
    dome of radiance 1: each pixel inside the fiber estimates Lambda(omega_o), the colour
    matched."""
    from usdfiber.image_output import read_exr

    params, tables = polyester
    fiber = dm.FiberColour(tables, params.density, params.diameter, DOS)
    target = _reachable_target(fiber, (0.2, 0.55, 0.9))
    m = dm.match_dye(fiber, target, "disperse")
    stage, prim = _fiber_stage(tmp_path / "r.usda")
    dm.author_dye(prim, m)
    dome = UsdLux.DomeLight.Define(stage, "/World/Dome")
    dome.CreateIntensityAttr(1.0)
    cam = UsdGeom.Camera.Define(stage, "/World/Cam")
    cam.CreateProjectionAttr("orthographic")
    cam.CreateHorizontalApertureAttr(400.0)   # 40 um wide window: the fiber is 20 pixels tall
    cam.CreateVerticalApertureAttr(200.0)
    cam.AddTranslateOp().Set(Gf.Vec3d(0, 0, 100))
    stage.GetRootLayer().Save()
    out = tmp_path / "r.exr"
    assert main(["render", str(tmp_path / "r.usda"), "-o", str(out), "--no-png", "--resolution", "80x40",
                 "--spp", "64", "--no-progress", "--float", *FAST]) == 0
    img = read_exr(out)[0][..., :3].astype(np.float64)
    # Rows well inside the fiber (rows 10-29 are the fiber; the gaussian filter blurs 2 px).
    band = img[14:26]
    # Columns 4 apart are independent (the filter's support is under 4 pixels): 20 columns,
    # each the mean of its 12 rows; the standard error of their mean from their scatter
    # (19 degrees of freedom).
    cols = band[:, 2::4].mean(axis=0)                  # (20, 3)
    mean = cols.mean(axis=0)
    se = cols.std(axis=0, ddof=1) / math.sqrt(len(cols))
    # Bound: 1.5 % for the renderer's float16 nodes and its interpolation in theta_o, plus
    # 6 standard errors (Student t, 19 dof: two-sided false failure below 1e-5 per channel).
    tol = 0.015 * target + 6 * se
    assert np.all(np.abs(mean - target) < tol), (mean, target, se)
