"""Presets against the paper (Aliaga et al. 2017): Table 1, Section 3.1, Table 3, Figure 5.

The expected values are typed in here from the paper, independently of usdfiber.presets.
"""
from __future__ import annotations

import argparse
import json
import math

import pytest

import usdfiber  # noqa: F401  (registers the schema before any stage is made)
from pxr import Usd, UsdGeom

from usdfiber import presets as P
from usdfiber.authoring import apply_fiber
from usdfiber.spec.fiber import FiberParams
from usdfiber.spec.yarn import yarn_diameter

# Table 1: type, diameter um, density g/cm3, (eta_par, eta_perp), Ra nm (l nm), beta deg.
PAPER_TABLE1 = {
    "polyester": ((10, 10), 1.39, (1.73, 1.54), (2.33, 5), 30, (2.7, 3.5)),
    "silk": ((5, 10), 1.34, (1.591, 1.538), (8, 9), 30, (6, 7)),
    "cotton": ((17, 20), 1.52, (1.578, 1.532), (12.5, 15.8), 50, (14, 17)),
    "wool": ((24, 40), 1.31, (1.553, 1.542), (6, 6), 50, (5, 5)),
}

# Table 3: sample, composition, fiber length cm (None = continuous), twist, fibers/ply, plies,
# dtex (caption: 74 x 1; 140 x 2; 90 x 3; 90 x 3).
PAPER_TABLE3 = {
    "Skala 360": ("Polyester", None, 5, 24, 1, 74),
    "ORA 120": ("Polyester", (3, 4), 8.8, 90, 2, 140),
    "CNe 50": ("Cotton", (3, 4), 12.8, 70, 3, 90),
    "S 303": ("Silk", (5, 8), 9, 90, 3, 90),
}


@pytest.mark.parametrize("name", list(PAPER_TABLE1))
def test_table1_published_values(name):
    diam, rho, (eta_par, eta_perp), ra, l, beta = PAPER_TABLE1[name]
    row = P.FIBER_PRESETS[name].published
    assert row.diameter_um == diam
    assert row.density_g_cm3 == rho
    assert row.eta_parallel == eta_par
    assert row.eta_perpendicular == eta_perp
    assert row.ra_nm == ra
    assert row.profile_length_nm == l
    assert row.beta_deg == beta
    assert P.TABLE1[name] is row
    assert "Table 1" in P.FIBER_PRESETS[name].source


def test_table1_has_exactly_the_paper_rows():
    assert set(P.TABLE1) == set(PAPER_TABLE1)
    assert set(P.FIBER_PRESETS) == set(PAPER_TABLE1) | {"mercerizedCotton"}


@pytest.mark.parametrize("name", list(PAPER_TABLE1))
def test_authored_values_are_midpoints(name):
    diam, rho, (eta_par, eta_perp), ra, l, beta = PAPER_TABLE1[name]
    attrs = P.FIBER_PRESETS[name].fiber_attributes()
    assert attrs["fiber:kind"] == name
    assert attrs["fiber:diameter"] == pytest.approx((diam[0] + diam[1]) / 2)
    assert attrs["fiber:density"] == rho
    assert attrs["fiber:ior:parallel"] == eta_par
    assert attrs["fiber:ior:perpendicular"] == eta_perp
    assert attrs["fiber:roughness:source"] == "beta"
    assert attrs["fiber:roughness:beta"] == pytest.approx((beta[0] + beta[1]) / 2)
    assert attrs["fiber:roughness:ra"] == pytest.approx((ra[0] + ra[1]) / 2)
    assert attrs["fiber:roughness:profileLength"] == l


def test_table1_beta_vs_arctan_ra_over_l():
    # Cotton's beta column is arctan(Ra / l); polyester, silk and wool are not.
    def arctan_deg(ra, l):
        return math.degrees(math.atan(ra / l))

    for name, (_, _, _, ra, l, beta) in PAPER_TABLE1.items():
        lo, hi = arctan_deg(ra[0], l), arctan_deg(ra[1], l)
        got = P.TABLE1[name].beta_from_ra_deg()
        assert got == pytest.approx((lo, hi))
        matches = abs(lo - beta[0]) < 0.6 and abs(hi - beta[1]) < 0.6
        assert matches == (name == "cotton"), name


def test_mercerized_cotton_is_cotton_optics_with_swollen_section():
    m, c = P.FIBER_PRESETS["mercerizedCotton"], P.FIBER_PRESETS["cotton"]
    assert m.published == c.published
    assert m.profile_family == "swollen"
    assert "Figure 3" in m.note and "Table 1" in m.note
    mattrs, cattrs = m.fiber_attributes(), c.fiber_attributes()
    assert mattrs.pop("fiber:kind") == "mercerizedCotton"
    cattrs.pop("fiber:kind")
    assert mattrs == cattrs


def test_builtin_families_and_cuticle():
    fam = {k: p.profile_family for k, p in P.FIBER_PRESETS.items()}
    assert fam == {"polyester": "round", "silk": "roundedTriangle", "cotton": "kidney",
                   "mercerizedCotton": "swollen", "wool": "elliptical"}
    wool = P.FIBER_PRESETS["wool"].cuticle
    assert (wool.tilt_deg, wool.height_um, wool.spacing_um) == (3.0, 0.7, 10.0)
    assert "not from the paper" in wool.source or "gives no values" in wool.source
    for k in ("polyester", "silk", "cotton", "mercerizedCotton"):
        assert P.FIBER_PRESETS[k].cuticle.height_um == 0


def test_section31_dye_ranges():
    assert P.DYE_PRESETS["reactive"].epsilon_range == (0.005, 0.0158)
    assert P.DYE_PRESETS["disperse"].epsilon_range == (0.045, 0.246)
    for c in P.DYE_COLOURS.values():
        lo, hi = P.DYE_PRESETS[c.dye].epsilon_range
        assert all(lo - 1e-12 <= e <= hi + 1e-12 for e in c.extinction), c.name
    r, g, b = P.DYE_COLOURS["reactiveRed"].extinction
    assert g > r and b > r  # a red dye absorbs green and blue


@pytest.mark.parametrize("name", list(PAPER_TABLE3))
def test_table3_published_values(name):
    comp, length, twist, fpp, plies, dtex = PAPER_TABLE3[name]
    y = P.YARN_PRESETS[name]
    t = y.published
    assert (t.sample, t.composition, t.fiber_length_cm, t.twist, t.fibers_per_ply, t.plies, t.dtex) == \
        (name, comp, length, twist, fpp, plies, dtex)
    assert y.fiber_preset == comp.lower()
    attrs = y.yarn_attributes()
    assert attrs["yarn:plies"] == plies
    assert attrs["yarn:fibersPerPly"] == fpp
    assert attrs["yarn:ply:linearDensity"] == dtex
    assert attrs["yarn:ply:twist"] == twist
    assert attrs["yarn:fiber:stapleLength"] == (0.0 if length is None else (length[0] + length[1]) / 2)
    # Ply radius: dtex g/10 km, fiber density, packing fraction 0.6.
    rho = PAPER_TABLE1[comp.lower()][1]
    grams_per_mm = dtex / 10_000.0 / 1000.0     # dtex = g per 10 km
    grams_per_mm3 = rho / 1000.0                 # 1 cm^3 = 1000 mm^3
    area_mm2 = grams_per_mm / grams_per_mm3 / 0.6
    assert P.PACKING_FRACTION == 0.6
    assert attrs["yarn:ply:radius"] == pytest.approx(math.sqrt(area_mm2 / math.pi), rel=1e-9)


def test_yarn_diameter_encloses_plies():
    assert yarn_diameter(1, 0.1) == pytest.approx(0.2)
    assert yarn_diameter(2, 0.1) == pytest.approx(0.4)
    assert yarn_diameter(3, 0.1) == pytest.approx(0.2 * (1 + 2 / math.sqrt(3)))
    for y in P.YARN_PRESETS.values():  # the presets' yarn width is the same formula
        assert y.yarn_diameter_mm == yarn_diameter(y.published.plies, y.ply_radius_mm)


def test_figure5_silk_deep_shade_mu_a():
    # Figure 5: silk (rho 1.34), epsilon 0.0158 L mg^-1 cm^-1, zeta 4 % -> 84.68 mm^-1.
    stage = Usd.Stage.CreateInMemory()
    prim = UsdGeom.BasisCurves.Define(stage, "/silk").GetPrim()
    apply_fiber(prim, "silk", dye_class="reactive", extinction=(0.0158, 0.0158, 0.0158), depth_of_shade=4.0)
    fp = FiberParams.from_prim(prim)
    for mu_per_um in fp.mu_a:
        assert mu_per_um * 1000.0 == pytest.approx(84.68, abs=0.01)


def _presets_cmd(capsys, *argv):
    from usdfiber.commands import presets as cmd

    parser = argparse.ArgumentParser()
    cmd.register(parser.add_subparsers())
    args = parser.parse_args(["presets", *argv])
    rc = args.func(args)
    return rc, capsys.readouterr().out


def test_presets_command_json_lists_everything(capsys):
    rc, out = _presets_cmd(capsys, "--json")
    assert rc == 0
    items = json.loads(out)
    names = {d["name"] for d in items}
    assert set(P.FIBER_PRESETS) | set(P.DYE_PRESETS) | set(P.DYE_COLOURS) | set(P.YARN_PRESETS) <= names
    silk = next(d for d in items if d["name"] == "silk")
    assert silk["published"]["beta_deg"] == [6.0, 7.0]
    assert silk["authored"]["fiber:roughness:beta"] == 6.5
    assert silk["derived"]["beta_from_ra_deg"][0] == pytest.approx(14.93, abs=0.01)


def test_presets_command_text_and_unknown(capsys):
    rc, out = _presets_cmd(capsys)
    assert rc == 0
    assert "atan(Ra/l)" in out and "beta deg" in out and "Skala 360" in out and "reactiveRed" in out
    rc, out = _presets_cmd(capsys, "CNe 50")
    assert "CNe 50" in out and "Skala 360" not in out and "FIBERS" not in out
    from usdfiber.cli import UsageError

    with pytest.raises(UsageError, match="unknown preset 'nylon'.*valid: polyester"):
        _presets_cmd(capsys, "nylon")
