"""Yarn far fields cost only what the image needs: traced once at absorption levels and
recoloured per dye, and not traced for yarns far outside the view; the render says what was
traced and why, and what the tables it bakes were estimated to cost."""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import usdfiber  # noqa: F401  (registers schemas first)
from usdfiber import presets
from usdfiber.backend import mitsuba
from usdfiber.bake.cache import TableCache
from usdfiber.bake.settings import BakeSettings
from usdfiber.spec.yarn import YarnParams
from usdfiber.translators.mitsuba.curves import reference_normals
from usdfiber.translators.mitsuba.fiber_bank import FiberBank, FiberSlot
from usdfiber.translators.mitsuba.fiber_bsdf import fiber_bsdf
from usdfiber.translators.mitsuba.lod import LodPolicy
from usdfiber.translators.mitsuba.yarn_far_field import (YARN_LEVELS, YarnBakeSettings, bake_yarn_far_field,
                                                         far_field_pieces, trace_far_field)

mi = mitsuba()

from stats_util import FALSE_FAILURE, z_limit  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
FIBER_D = 12e-4    # 12 um in cm
# One fiber placement per far field: these tests are about tracing only what contributes and
# recolouring, not the average over placements (tests/mitsuba/test_far_field_realizations.py).
ST = YarnBakeSettings(resolution_deg=15, photons=4000, batches=4, realizations=1)


def _small_yarn() -> YarnParams:
    attrs = presets.yarn_preset("ORA 120").yarn_attributes()
    attrs.update({"yarn:fibersPerPly": 24, "yarn:ply:radius": 0.06, "yarn:fiber:stapleLength": 0.0})
    return YarnParams.from_attributes(attrs, 0.01)


@pytest.fixture(scope="module")
def levels_far_field(silk_render_table):
    """The far field traced once at every absorption level."""
    return bake_yarn_far_field(_small_yarn(), FIBER_D, [FiberSlot(silk_render_table, (0.0, 0.0, 0.0))], ST)


def _direct(table, sigma, seed: int):
    """The far field traced in one colour (the tracer's own dyed weights), on the same pieces,
    fiber variants and rotations as :func:`bake_yarn_far_field` draws, with other photons."""
    yp = _small_yarn()
    pieces = far_field_pieces(yp, FIBER_D, ST)
    rng = np.random.default_rng([ST.seed, 0x7A22])
    bank = FiberBank.build([FiberSlot(table, tuple(sigma))])
    bsdfs = []
    for piece in pieces:
        geom = piece.geometry
        variant = rng.integers(0, 1, geom.curve_count)
        psi = rng.uniform(0.0, 2 * math.pi, geom.curve_count)
        bsdfs.append(fiber_bsdf(mi, bank, variant[geom.segment_curve], psi[geom.segment_curve],
                                reference_normals(geom)))
    return trace_far_field(pieces, bsdfs, replace(ST, seed=seed))


def test_furnace_at_zero_absorption(levels_far_field):
    """Undyed fibers absorb nothing: the far field recoloured to zero absorption (its first
    level) keeps all the scattered light, and every slice of p integrates to 1."""
    ff = levels_far_field
    assert ff.recolourable and len(ff.arrays["levels"]) == len(YARN_LEVELS)
    rec = ff.recolour(0.0)
    np.testing.assert_allclose(rec.albedo, 1.0, atol=1e-3)
    dom = np.repeat(ff.grid.solid_angles(), ff.grid.n_phi_o).reshape(ff.grid.n_theta_o, ff.grid.n_phi_o)
    np.testing.assert_allclose((rec.p[:, 0] * dom[None, :, :, None]).sum(axis=(1, 2)), 1.0, rtol=1e-5)
    # Absorption only removes light: deeper levels are darker, level by level, down to what
    # the fibers' surfaces reflect before any light enters them (the last levels agree).
    a = ff.arrays["albedo"][:, 0].mean(axis=0)
    assert np.all(np.diff(a) <= 1e-6) and np.all(np.diff(a[:5]) < -0.05), a


@pytest.mark.parametrize("sigma", [(0.5, 1.0, 4.0), (0.35, 1.4, 3.0)], ids=["at-levels", "between-levels"])
def test_recoloured_matches_a_direct_trace(levels_far_field, silk_render_table, sigma):
    """The far field recoloured to a dye against one traced in that dye with other photons:
    the albedo (mean over theta_i, per channel) agrees within noise. Each estimate averages
    N scattered photons' weights in [0, ~1.1], whose variance is at most mu (1.1 - mu); the
    two are independent. Two dyes x 3 channels share the false-failure probability of 1e-4.
    Between levels the log-Hermite interpolation adds at most 1 % (measured 0.1-1.4 % of the
    noise here; the fiber tables' interpolation is within 0.9 %)."""
    ff = levels_far_field
    rec = ff.recolour(list(sigma)).albedo[:, 0]
    direct = _direct(silk_render_table, sigma, seed=11)
    dir_a = direct.arrays["albedo"][:, 0]
    n = [float((f.arrays["photons"][:, 0] * f.coverage).sum()) for f in (ff, direct)]
    for c in range(3):
        mu_r, mu_d = float(rec[:, c].mean()), float(dir_a[:, c].mean())
        sd = math.sqrt(max(mu_d, 1e-3) * (1.1 - mu_d) * (1 / n[0] + 1 / n[1]))
        tol = z_limit(FALSE_FAILURE / 6) * sd + 0.01 * mu_d
        assert abs(mu_r - mu_d) < tol, (c, mu_r, mu_d, tol)


def test_one_trace_serves_every_colour(tmp_path, silk_render_table):
    """The cache key holds the structure and the levels, not the colour or the seed: a second
    dye of the same yarn finds the far field traced for the first, and recolouring it is what
    changes; another structure is another far field."""
    from usdfiber.translators.mitsuba.yarn_far_field import YarnFarFieldCache

    cache = YarnFarFieldCache(TableCache(tmp_path))
    st = YarnBakeSettings(resolution_deg=30, photons=400, batches=2, realizations=1)
    yp = _small_yarn()
    red = [FiberSlot(silk_render_table, (0.1, 2.0, 2.0))]
    blue = [FiberSlot(silk_render_table, (2.0, 2.0, 0.1))]
    ff, traced = cache.get_or_bake(yp, FIBER_D, red, st)
    again, traced2 = cache.get_or_bake(yp, FIBER_D, blue, st)
    assert traced and not traced2 and len(list((tmp_path / "yarns").glob("*.npz"))) == 1
    # Nor the yarn's seed: the far field is a statistic of the structure.
    assert cache.get_or_bake(replace(yp, seed=99), FIBER_D, red, st, bake_missing=False)[0] is not None
    assert cache.get_or_bake(replace(yp, ply_radius=0.05), FIBER_D, red, st, bake_missing=False)[0] is None
    a_red = again.recolour([0.1, 2.0, 2.0]).albedo.mean(axis=(0, 1))
    a_blue = again.recolour([2.0, 2.0, 0.1]).albedo.mean(axis=(0, 1))
    assert a_red[0] > a_red[2] and a_blue[2] > a_blue[0]
    np.testing.assert_allclose(a_red[[0, 2]], a_blue[[2, 0]], rtol=1e-6)   # the same channel maths


def _two_yarn_stage(path: Path) -> None:
    """Two small far-field yarns (mm) on the x axis, one under the camera and one 60 mm away
    (far outside the view), with a key light."""
    from pxr import Gf, Usd, UsdGeom, UsdLux

    from usdfiber import authoring as A

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    for name, x, ply_radius in (("Near", 0.0, 0.06), ("Far", 60.0, 0.05)):
        c = UsdGeom.BasisCurves.Define(stage, f"/World/{name}")
        c.CreateTypeAttr("linear")
        c.CreatePointsAttr([Gf.Vec3f(x - 1.0, 0.0, 0.0), Gf.Vec3f(x + 1.0, 0.0, 0.0)])
        c.CreateCurveVertexCountsAttr([2])
        A.apply_yarn(c.GetPrim(), "ORA 120", fiber_preset="polyester", fibers_per_ply=12, ply_radius=ply_radius,
                     staple_length=0.0, expand_fibers=False, dye="disperseBlue", depth_of_shade=1.0)
    cam = UsdGeom.Camera.Define(stage, "/Cam")
    cam.CreateFocalLengthAttr(50.0)
    cam.CreateHorizontalApertureAttr(36.0)
    cam.CreateVerticalApertureAttr(36.0)
    cam.AddTranslateOp().Set(Gf.Vec3d(0.0, 0.0, 3.0))
    UsdLux.DistantLight.Define(stage, "/Key").CreateIntensityAttr(2.0)
    stage.GetRootLayer().Save()


def test_out_of_view_yarn_is_not_traced(tmp_path):
    """A yarn far outside the view is left out: its far field is not traced, and the
    translation reports it as skipped and why; kept as a proxy (an infinite margin, the
    former behaviour) it would have been traced."""
    from pxr import Usd

    from usdfiber.translators.mitsuba.scene import SceneOptions, translate_stage

    path = tmp_path / "two.usda"
    _two_yarn_stage(path)
    opts = SceneOptions(resolution=(16, 16), spp=1, bake=BakeSettings(resolution_deg=30, photons=1000, batches=2),
                        yarn_bake=YarnBakeSettings(resolution_deg=30, photons=400, batches=2, realizations=1),
                        cache=TableCache(tmp_path / "cache"))
    tr = translate_stage(Usd.Stage.Open(str(path)), opts)
    rep = {f["prim"]: f for f in tr.fibers.far_fields}
    assert rep["/World/Near"]["far_field"] == "traced" and rep["/World/Near"]["in_view"] == 1
    assert rep["/World/Far"]["far_field"] == "not needed" and rep["/World/Far"]["skipped"] == 1
    assert "far outside the view" in rep["/World/Far"]["reason"]
    assert tr.counts["yarn_skipped"] == 1 and tr.counts["yarn_far"] == 1 and tr.counts["yarn_culled"] == 0
    assert len(list((tmp_path / "cache" / "yarns").glob("*.npz"))) == 1
    keep = translate_stage(Usd.Stage.Open(str(path)), replace(opts, lod=LodPolicy(proxy_margin_diameters=math.inf)))
    far = {f["prim"]: f for f in keep.fibers.far_fields}["/World/Far"]
    assert far["far_field"] == "traced" and far["proxies"] == 1 and keep.counts["yarn_skipped"] == 0


@pytest.mark.slow
def test_render_summary_names_far_fields_and_bake_estimates(tmp_path):
    """``usdfiber render --json`` lists the tables it baked with their estimates and each far
    field traced, cached or skipped with the reason; the text summary says the same."""
    path = tmp_path / "two.usda"
    _two_yarn_stage(path)
    env = dict(os.environ, USDFIBER_CACHE_DIR=str(tmp_path / "cache"))
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    args = [sys.executable, "-m", "usdfiber", "render", str(path), "-o", str(tmp_path / "a.exr"), "--no-png",
            "--resolution", "16x16", "--spp", "1", "--no-progress", "--bake-resolution", "30",
            "--bake-photons", "1000", "--yarn-bake-resolution", "30", "--yarn-bake-photons", "400"]
    out = subprocess.run(args + ["--json"], capture_output=True, text=True, env=env, timeout=600)
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout)
    assert [b["label"] for b in summary["bakes"]] == ["polyester/round variant 0"]
    assert summary["bakes"][0]["seconds"] > 0 and summary["bakes"][0]["disk_bytes"] > 0
    assert "tables: to bake polyester/round variant 0: about" in out.stderr    # before baking
    states = {f["prim"]: f["far_field"] for f in summary["far_fields"]}
    assert states == {"/World/Near": "traced", "/World/Far": "not needed"}
    text = subprocess.run(args, capture_output=True, text=True, env=env, timeout=600)
    assert text.returncode == 0, text.stderr
    assert "far field /World/Near: cached (1 in view" in text.stdout
    assert "far field /World/Far: not needed (1 far outside the view, left out)" in text.stdout
    assert "1 far outside the view left out" in text.stdout
