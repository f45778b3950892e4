"""Regression tests: the ways `usdfiber check` and the renderer used to disagree.

Each test names the defect it pins; tests/validation/test_agreement.py runs the invariant over the whole
corpus of tests/corpus/agreement/.
"""
from __future__ import annotations

import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

import usdfiber  # noqa: F401  (registers the schemas before any stage exists)
from pxr import Sdf, Usd, UsdGeom

from usdfiber.bake.cache import TableCache
from usdfiber.bake.settings import BakeSettings
from usdfiber.geometry.curves import UNIFORM_SCALE_RTOL, axis_scales, curves_from_prim
from usdfiber.stage_io import open_stage
from usdfiber.translators.mitsuba.errors import TranslateError
from usdfiber.translators.mitsuba.scene import SceneOptions, translate_stage
from usdfiber.validation.plugin import one_line_reason
from usdfiber.validation.runner import check_stage

AGREEMENT = Path(__file__).resolve().parents[1] / "corpus" / "agreement"
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def options(tmp_path_factory) -> SceneOptions:
    return SceneOptions(resolution=(8, 8), spp=1, cache=TableCache(tmp_path_factory.mktemp("defect_tables")),
                        bake=BakeSettings(resolution_deg=30, photons=200, batches=2))


def _translate(path: Path, options: SceneOptions):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return translate_stage(open_stage(path), options)


def _codes(path: Path, **kw) -> dict[str, str]:
    return {p.code: p.severity.value for p in check_stage(path, **kw).problems}


def test_broken_guide_curve_is_skipped_with_a_warning_not_a_refusal(options):
    tr = _translate(AGREEMENT / "guide_beside_fibers.usda", options)
    assert tr.counts["fiber_curves"] == 1 and tr.counts["curves_other"] == 0
    assert any(w.startswith("/World/Guide: BasisCurves without FiberAPI skipped:") for w in tr.warnings)
    codes = _codes(AGREEMENT / "guide_beside_fibers.usda")
    assert codes["PlainCurvesSkipped"] == "warning" and "error" not in codes.values()


def test_plain_curves_without_widths_are_skipped_by_both(options):
    tr = _translate(AGREEMENT / "bad_plain_no_widths.usda", options)
    assert tr.counts["curves_other"] == 0
    assert _codes(AGREEMENT / "bad_plain_no_widths.usda") == {"PlainCurves": "warning",
                                                                "PlainCurvesSkipped": "warning"}


def test_linear_curves_ignore_an_empty_basis():
    stage = open_stage(AGREEMENT / "maya_linear_empty_basis_fiber.usda")
    prim = stage.GetPrimAtPath("/World/curveShape1")
    assert UsdGeom.BasisCurves(prim).GetBasisAttr().Get() == ""
    geom = curves_from_prim(prim)
    assert geom.segment_count == 3 + 2 and geom.warnings == []
    assert check_stage(stage).errors == []


def test_one_width_without_interpolation_is_constant_with_a_note(options):
    path = AGREEMENT / "pixar_single_width_fiber.usda"
    assert _codes(path) == {"WidthsConstantAssumed": "warning"}
    stage = open_stage(path)
    prim = stage.GetPrimAtPath("/World/Curves")
    geom = curves_from_prim(prim)
    assert np.allclose(geom.radii, 0.005) and "read as constant" in geom.warnings[0]
    # Authored interpolation keeps its meaning: one vertex width for 9 points is an error.
    prim.GetAttribute("widths").SetMetadata("interpolation", "vertex")
    assert "WidthsCountMismatch" in {p.code for p in check_stage(stage).errors}


def test_zero_widths_taper_fibers_and_negative_widths_are_refused(options):
    path = AGREEMENT / "taper_zero_tips_bspline.usda"
    assert check_stage(path).problems == []
    tr = _translate(path, options)
    assert tr.counts["fiber_curves"] == 1
    assert _codes(AGREEMENT / "bad_fiber_negative_width.usda") == {"WidthNegative": "error"}


def test_fiber_width_under_a_scaled_transform_is_the_fiber_diameter_in_the_world(options):
    # A fiber curve without widths under scale 100 is drawn as wide as the fiber (10 um =
    # 0.01 mm scene units): check's rule, not 100x too thick.
    tr = _translate(AGREEMENT / "scaled_fibers_without_widths.usda", options)
    geom = tr.fibers.geometry
    mids = np.einsum("j,sj->s", np.array([1, 4, 1]) / 6, geom.radii[geom.segment_start[:, None] + np.arange(3)])
    assert np.allclose(mids, 0.005, rtol=1e-6)
    report = check_stage(AGREEMENT / "scaled_fibers_without_widths.usda")
    missing = [p for p in report.problems if p.code == "WidthsMissing"]
    assert len(missing) == 1 and "about 0.0001 scene units" in missing[0].message  # 0.01 / 100
    # Authored widths of 0.01 local units under scale 100 are 100x the fiber: check warns.
    stage = open_stage(AGREEMENT / "scaled_fibers_without_widths.usda")
    UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Fibers")).CreateWidthsAttr([0.01])
    stage.GetPrimAtPath("/World/Fibers").GetAttribute("widths").SetMetadata("interpolation", "constant")
    assert "WidthMismatch" in {p.code for p in check_stage(stage).warnings}


def test_half_float_instance_rotations_are_a_uniform_scale(options):
    tr = _translate(AGREEMENT / "instancer_half_orientations.usda", options)
    assert tr.counts["fiber_curves"] == 3
    assert not [w for w in tr.warnings if "non-uniform" in w]
    # The tolerance: half-float rotations are orthogonal to a few 2^-11, a real non-uniform
    # scale of 1 % is still reported.
    q = np.array([0.7071, 0.0, 0.7071, 0.0], np.float16).astype(np.float64)
    rot = Gf_rotation(q) * 2.0
    assert not axis_scales(rot)[2]
    assert axis_scales(np.diag([1.0, 1.01, 1.0]))[2]
    assert 2.0 ** -11 < UNIFORM_SCALE_RTOL < 0.01


def Gf_rotation(q: np.ndarray) -> np.ndarray:
    """The rotation matrix USD builds from an unnormalized quaternion (w, x, y, z)."""
    from pxr import Gf

    m = Gf.Matrix4d().SetRotate(Gf.Quatd(*map(float, q)))
    return np.array(m)[:3, :3]


@pytest.mark.parametrize("name, code", [("units_mpu_0_upY.usda", "MetersPerUnitInvalid"),
                                        ("units_mpu_minus0p001_upY.usda", "MetersPerUnitInvalid"),
                                        ("units_mpu_0p001_upX.usda", "UpAxisInvalid")])
def test_bad_meters_per_unit_and_up_axis_name_the_file_in_check_and_render(name, code, options):
    report = check_stage(AGREEMENT / name)
    (problem,) = report.errors
    assert problem.code == code and name in problem.message
    with pytest.raises(TranslateError) as exc:
        _translate(AGREEMENT / name, options)
    assert str(exc.value) == problem.message


def test_derived_beta_is_checked():
    (p,) = check_stage(AGREEMENT / "derived_beta_90.usda").errors
    assert p.attribute == "fiber:roughness:profileLength" and "beta = arctan(Ra / l) = 90 deg" in p.message
    (p,) = check_stage(AGREEMENT / "derived_beta_70.usda").errors
    assert "expected a slope angle beta in [0, 60] deg" in p.message
    assert check_stage(AGREEMENT / "derived_beta_ok.usda").errors == []


def test_animated_only_stage_renders_its_start_frame_with_a_warning(options):
    path = AGREEMENT / "animated_only_points.usda"
    tr = _translate(path, options)
    assert tr.time == 1.0 and tr.counts["fiber_curves"] == 1
    assert any("rendering frame 1, the stage's startTimeCode" in w for w in tr.warnings)
    assert _codes(path) == {"AnimatedOnly": "warning"}
    # A stage with default values renders at the default time, without a note.
    tr = _translate(AGREEMENT / "animated_with_default.usda", options)
    assert tr.time is None and not [w for w in tr.warnings if "no frame given" in w]


def test_all_variants_mode_checks_unselected_variants(tmp_path):
    path = AGREEMENT / "variants_pale_selected.usda"
    assert check_stage(path).problems == []
    (p,) = check_stage(path, all_variants=True).errors
    assert p.code == "ValueOutOfRange" and "(with variant set 'shade' of /World/Fibers = 'bad')" in p.message
    # The stage's own selection is left as it was.
    stage = open_stage(path)
    check_stage(stage, all_variants=True)
    vset = stage.GetPrimAtPath("/World/Fibers").GetVariantSets().GetVariantSet("shade")
    assert vset.GetVariantSelection() == "pale"
    spec = stage.GetSessionLayer().GetPrimAtPath("/World/Fibers")
    assert spec is None or "shade" not in dict(spec.variantSelections)
    out = subprocess.run([sys.executable, "-m", "usdfiber", "check", "--all-variants", str(path)],
                         capture_output=True, text=True)
    assert out.returncode == 1 and "'bad'" in out.stdout


def test_validators_load_in_a_plain_usd_program(tmp_path):
    """PXR_PLUGINPATH_NAME=$(usdfiber plugin-path), as the README advises for usdview and
    DCCs, without `import usdfiber` in the program."""
    paths = subprocess.run([sys.executable, "-m", "usdfiber", "plugin-path"], capture_output=True,
                           text=True, check=True).stdout.strip()
    program = (
        "import sys\n"
        "from pxr import Usd, UsdValidation\n"
        f"stage = Usd.Stage.Open({str(AGREEMENT / 'bad_fiber_negative_width.usda')!r})\n"
        "ctx = UsdValidation.ValidationContext(keywords=['usdFiber'], includeAllAncestors=False)\n"
        "names = sorted({e.GetName() for e in ctx.Validate(stage)})\n"
        "print(names, 'usdfiber' in sys.modules)\n")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["PXR_PLUGINPATH_NAME"] = paths
    out = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, env=env,
                         cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert "'WidthNegative'" in out.stdout


def test_internal_errors_are_one_line_and_keep_the_other_findings(monkeypatch):
    from pxr import Tf

    try:
        Sdf.Layer.CreateAnonymous(".usda").ImportFromString("#usda 1.0\ndef X \"a\" {")
    except Tf.ErrorException as exc:
        reason = one_line_reason(exc)
    assert "\n" not in reason and "Error in" not in reason and reason
    # A check that fails reports one line on the prim; the other checks still report.
    def boom(prim):
        raise RuntimeError("first line\nsecond line")

    import usdfiber.validation.assets as assets

    monkeypatch.setattr(assets, "check_profile_prim", boom)  # what the fiberProfile validator calls
    report = check_stage(AGREEMENT / "bad_fiber_negative_width.usda")
    failed = [p for p in report.problems if p.code == "CheckFailed"]
    assert failed and all("\n" not in p.message for p in failed)
    assert "first line second line" in failed[0].message
    assert "WidthNegative" in {p.code for p in report.problems}
    # Profile points authored as float3: a type error, no internal error.
    monkeypatch.undo()
    codes = _codes(AGREEMENT / "profile_points_float3.usda")
    assert codes.get("WrongValueType") == "error" and "CheckFailed" not in codes


def test_corrupt_table_asset_is_a_check_error_and_bake_rebakes_it(tmp_path, options):
    """A fiber:table whose arrays fail their checksums: check reports it (the renderer cannot
    use it, so render refuses with check's message) and `usdfiber bake` bakes the prim's
    tables instead of saying there is nothing to bake."""
    from usdfiber.bake.requests import tables_for_stage
    from usdfiber.bcsdf import tables_for_prim
    from usdfiber.spec.fiber import FiberParams

    stage_path = tmp_path / "cloth.usda"
    stage_path.write_text((AGREEMENT / "gen_fiber_bspline_nonperiodic_constant.usda").read_text())
    stage = open_stage(stage_path)
    prim = stage.GetPrimAtPath("/World/Fibers")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        (table,) = tables_for_prim(prim, options.bake, cache=options.cache)
    good = tmp_path / "fibers.npz"
    table.save(good)
    assert table.geometry_key == FiberParams.from_prim(prim).geometry_key()
    prim.GetAttribute("fiber:table").Set(Sdf.AssetPath("./fibers.npz"))
    stage.GetRootLayer().Save()
    assert check_stage(stage_path).errors == []
    assert tables_for_stage(open_stage(stage_path)) == []  # a good table needs no bake

    # Same header, one array changed: only the checksums tell.
    with np.load(good) as z:
        arrays = {k: z[k] for k in z.files}
    name = max((k for k in arrays if arrays[k].dtype.kind == "f"), key=lambda k: arrays[k].size)
    arrays[name] = arrays[name] + np.ones_like(arrays[name])
    with open(good, "wb") as f:
        np.savez(f, **arrays)
    (p,) = check_stage(stage_path).errors
    assert p.code == "TableUnreadable" and "checksum mismatch" in p.message and "usdfiber bake" in p.message
    with pytest.warns(RuntimeWarning, match="baking from the fiber's parameters"):
        assert len(tables_for_stage(open_stage(stage_path))) == 1
