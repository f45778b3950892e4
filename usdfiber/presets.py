"""Fiber, dye and yarn presets from Aliaga et al. 2017, "An Appearance Model for Textile Fibers".

Every preset keeps two things apart:

* ``published``: the values exactly as the paper prints them (ranges as ``(lo, hi)`` tuples;
  a single printed value ``v`` is ``(v, v)`` where the column holds ranges elsewhere).
* the *authored* values: the single numbers :func:`usdfiber.authoring.apply_fiber` and
  :func:`usdfiber.authoring.apply_yarn` write to a prim.

Rule for authored values: the midpoint ``(lo + hi) / 2`` of every published range.

Roughness: Table 1's beta column is not ``arctan(Ra / l)`` for every row (cotton agrees;
polyester, silk and wool do not), so presets author ``fiber:roughness:source = "beta"`` with
the midpoint of Table 1's beta, and also author Ra and l (midpoints) so both are on the prim.
``usdfiber presets`` shows the published beta next to ``arctan(Ra / l)``.

Units: diameters um, density g/cm^3, Ra and l nm, angles degrees, extinction per gram
L mg^-1 cm^-1, staple length cm, twist turns/cm, linear density dtex (g per 10 km), yarn
radii mm.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from usdfiber.spec.attributes import Fiber, Yarn
from usdfiber.spec.yarn import yarn_diameter

PAPER = 'Aliaga, Castillo, Gutierrez, Otaduy, Lopez-Moreno, Jarabo: "An Appearance Model for ' \
        'Textile Fibers", EGSR 2017 (Computer Graphics Forum 36(4))'

Range = tuple[float, float]


def midpoint(r: Range) -> float:
    """The authored value of a published range: its midpoint."""
    return (float(r[0]) + float(r[1])) / 2.0


# --------------------------------------------------------------------------------------
# Fibers (Table 1)
# --------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Table1Row:
    """One row of the paper's Table 1, as published."""

    fiber: str
    diameter_um: Range
    density_g_cm3: float
    eta_parallel: float
    eta_perpendicular: float
    ra_nm: Range
    profile_length_nm: float
    beta_deg: Range

    def beta_from_ra_deg(self) -> Range:
        """``arctan(Ra / l)`` in degrees for both ends of the Ra range (Section 3.1)."""
        lo, hi = self.ra_nm
        l = self.profile_length_nm
        return (math.degrees(math.atan(lo / l)), math.degrees(math.atan(hi / l)))


TABLE1_SOURCE = (
    f"{PAPER}, Table 1 (diameters from Trotman; density at 65% RH, 20 C, and IOR from Hearle & "
    f"Morton; Ra and l from [GK81, LXD08])"
)

TABLE1: dict[str, Table1Row] = {
    "polyester": Table1Row("Polyester", (10.0, 10.0), 1.39, 1.73, 1.54, (2.33, 5.0), 30.0, (2.7, 3.5)),
    "silk": Table1Row("Silk", (5.0, 10.0), 1.34, 1.591, 1.538, (8.0, 9.0), 30.0, (6.0, 7.0)),
    "cotton": Table1Row("Cotton", (17.0, 20.0), 1.52, 1.578, 1.532, (12.5, 15.8), 50.0, (14.0, 17.0)),
    "wool": Table1Row("Wool", (24.0, 40.0), 1.31, 1.553, 1.542, (6.0, 6.0), 50.0, (5.0, 5.0)),
}

# fiber:profile "auto" resolves to this built-in family per fiber:kind (schema doc of
# fiber:profile; paper Figure 2). Cotton's SEM sections are bean/kidney shaped with a lumen;
# the built-in cotton family is "kidney".
AUTO_PROFILE_FAMILY: dict[str, str] = {
    "polyester": "round",
    "silk": "roundedTriangle",
    "cotton": "kidney",
    "mercerizedCotton": "swollen",
    "wool": "elliptical",
}

# Wool cuticle scales: typical values from the textile-fiber literature (scale cells about
# 0.5-1 um thick, edges every 7-12 um along the fiber, tilted a few degrees against the
# axis). NOT from the paper, which models cuticles without giving numbers.
WOOL_CUTICLE_SOURCE = (
    "typical textile-literature values for wool cuticle scales (edge height ~0.5-1 um, spacing "
    "~7-12 um, tilt a few degrees); the paper models cuticles (Section 3.1, Fig. 2) but gives no values"
)


@dataclass(frozen=True)
class Cuticle:
    """Cuticle scales (wool): tilt in degrees, edge height and spacing in um."""

    tilt_deg: float = 0.0
    height_um: float = 0.0
    spacing_um: float = 10.0
    source: str = ""


@dataclass(frozen=True)
class FiberPreset:
    """A textile fiber: Table 1's published row plus the single values the preset authors."""

    name: str                 # preset name == fiber:kind token
    published: Table1Row      # as printed in the paper (mercerized cotton: cotton's row)
    profile_family: str       # built-in cross-section family fiber:profile "auto" resolves to
    cuticle: Cuticle
    source: str
    note: str = ""

    # Authored values (midpoint rule, see module docstring).
    @property
    def diameter_um(self) -> float:
        return midpoint(self.published.diameter_um)

    @property
    def density_g_cm3(self) -> float:
        return self.published.density_g_cm3

    @property
    def ior_parallel(self) -> float:
        return self.published.eta_parallel

    @property
    def ior_perpendicular(self) -> float:
        return self.published.eta_perpendicular

    @property
    def ra_nm(self) -> float:
        return midpoint(self.published.ra_nm)

    @property
    def profile_length_nm(self) -> float:
        return self.published.profile_length_nm

    @property
    def beta_deg(self) -> float:
        return midpoint(self.published.beta_deg)

    def fiber_attributes(self) -> dict[str, Any]:
        """The FiberAPI attribute values this preset authors (schema name -> value)."""
        return {
            Fiber.KIND: self.name,
            Fiber.PROFILE: "auto",
            Fiber.DIAMETER: self.diameter_um,
            Fiber.DENSITY: self.density_g_cm3,
            Fiber.IOR_PARALLEL: self.ior_parallel,
            Fiber.IOR_PERPENDICULAR: self.ior_perpendicular,
            Fiber.IOR_EFFECTIVE: "mean",
            Fiber.ROUGHNESS_SOURCE: "beta",
            Fiber.ROUGHNESS_RA: self.ra_nm,
            Fiber.ROUGHNESS_PROFILE_LENGTH: self.profile_length_nm,
            Fiber.ROUGHNESS_BETA: self.beta_deg,
            Fiber.CUTICLE_TILT: self.cuticle.tilt_deg,
            Fiber.CUTICLE_HEIGHT: self.cuticle.height_um,
            Fiber.CUTICLE_SPACING: self.cuticle.spacing_um,
        }


_NO_CUTICLE = Cuticle()

FIBER_PRESETS: dict[str, FiberPreset] = {
    "polyester": FiberPreset("polyester", TABLE1["polyester"], "round", _NO_CUTICLE, TABLE1_SOURCE),
    "silk": FiberPreset("silk", TABLE1["silk"], "roundedTriangle", _NO_CUTICLE, TABLE1_SOURCE),
    "cotton": FiberPreset("cotton", TABLE1["cotton"], "kidney", _NO_CUTICLE, TABLE1_SOURCE),
    "mercerizedCotton": FiberPreset(
        "mercerizedCotton", TABLE1["cotton"], "swollen", _NO_CUTICLE,
        TABLE1_SOURCE + "; cross section after Figure 3's caption",
        note="Not a row of Table 1: cotton's optical and physical values with the swollen "
             "cross section of mercerized cotton (paper Figure 3 caption: its cross section "
             "is very different from untreated cotton).",
    ),
    "wool": FiberPreset(
        "wool", TABLE1["wool"], "elliptical",
        Cuticle(tilt_deg=3.0, height_um=0.7, spacing_um=10.0, source=WOOL_CUTICLE_SOURCE),
        TABLE1_SOURCE + "; cuticle: " + WOOL_CUTICLE_SOURCE,
    ),
}
assert all(AUTO_PROFILE_FAMILY[k] == p.profile_family for k, p in FIBER_PRESETS.items())


# --------------------------------------------------------------------------------------
# Dyes (Section 3.1)
# --------------------------------------------------------------------------------------

SECTION31_SOURCE = f"{PAPER}, Section 3.1 (extinction ranges from [OEAA*14, HHR15])"


@dataclass(frozen=True)
class DyePreset:
    """A dye class with the paper's range of extinction per gram (L mg^-1 cm^-1)."""

    name: str
    dye_class: str            # fiber:dye:class token
    epsilon_range: Range      # published, L mg^-1 cm^-1
    used_for: str
    source: str = SECTION31_SOURCE

    @property
    def extinction(self) -> tuple[float, float, float]:
        """Authored extinction: the range midpoint in every channel (a neutral grey dye)."""
        m = midpoint(self.epsilon_range)
        return (m, m, m)


DYE_PRESETS: dict[str, DyePreset] = {
    "reactive": DyePreset("reactive", "reactive", (0.005, 0.0158), "cotton, silk, wool"),
    "disperse": DyePreset("disperse", "disperse", (0.045, 0.246), "polyester and other synthetics"),
}


@dataclass(frozen=True)
class DyeColour:
    """A named colour of a dye class: per-channel extinction inside the class's range.

    ``fractions`` place each linear Rec.709 channel in the class's published range
    (0 = low end, 1 = high end). The per-channel split is ILLUSTRATIVE; only the magnitude
    range comes from the paper. A dye looks red because it absorbs green and blue.
    """

    name: str
    dye: str                               # DYE_PRESETS key
    fractions: tuple[float, float, float]  # position of R, G, B in the range

    @property
    def dye_class(self) -> str:
        return DYE_PRESETS[self.dye].dye_class

    @property
    def extinction(self) -> tuple[float, float, float]:
        """Extinction per gram per channel, L mg^-1 cm^-1."""
        lo, hi = DYE_PRESETS[self.dye].epsilon_range
        return tuple(lo + f * (hi - lo) for f in self.fractions)  # type: ignore[return-value]

    @property
    def source(self) -> str:
        return (f"magnitudes within the {self.dye} range of {SECTION31_SOURCE}; "
                f"per-channel split illustrative")


DYE_COLOURS: dict[str, DyeColour] = {c.name: c for c in (
    DyeColour("reactiveRed", "reactive", (0.0, 1.0, 0.85)),
    DyeColour("reactiveOrange", "reactive", (0.0, 0.55, 1.0)),
    DyeColour("reactiveYellow", "reactive", (0.0, 0.12, 1.0)),
    DyeColour("reactiveGreen", "reactive", (1.0, 0.1, 0.8)),
    DyeColour("reactiveBlue", "reactive", (1.0, 0.75, 0.0)),
    DyeColour("disperseRed", "disperse", (0.0, 1.0, 0.8)),
    DyeColour("disperseYellow", "disperse", (0.0, 0.1, 1.0)),
    DyeColour("disperseBlue", "disperse", (1.0, 0.7, 0.0)),
    DyeColour("disperseBlack", "disperse", (1.0, 1.0, 1.0)),
)}


def dye_values(name: str) -> tuple[str, tuple[float, float, float]]:
    """``(dye class token, per-channel extinction)`` of a dye preset or named colour."""
    if name in DYE_COLOURS:
        c = DYE_COLOURS[name]
        return c.dye_class, c.extinction
    if name in DYE_PRESETS:
        d = DYE_PRESETS[name]
        return d.dye_class, d.extinction
    raise KeyError(name)


# --------------------------------------------------------------------------------------
# Yarns (Table 3)
# --------------------------------------------------------------------------------------

TABLE3_SOURCE = f"{PAPER}, Table 3 (Guetermann sewing threads; dtex from its caption)"

# Fraction of a ply's cross section filled by fiber. Typical of twisted staple and filament
# yarns (about 0.5-0.7 in the textile literature); one value for every preset.
PACKING_FRACTION = 0.6


@dataclass(frozen=True)
class Table3Row:
    """One row of the paper's Table 3, as published (dtex from the caption)."""

    sample: str
    composition: str
    fiber_length_cm: Range | None   # None: continuous filament
    twist: float                    # turns per cm
    fibers_per_ply: int
    plies: int
    dtex: float                     # linear density of one ply, g / 10 km


def ply_radius_mm(dtex: float, density_g_cm3: float,
                  packing_fraction: float = PACKING_FRACTION) -> float:
    """Radius (mm) of a circular ply of linear density ``dtex`` made of fibers of density rho.

    Fiber area A_f = (dtex * 1e-4 g/m) / (rho * 1e6 g/m^3); ply area = A_f / packing fraction.
    """
    fiber_area_m2 = (dtex * 1e-4) / (density_g_cm3 * 1e6)
    ply_area_m2 = fiber_area_m2 / packing_fraction
    return math.sqrt(ply_area_m2 / math.pi) * 1e3


@dataclass(frozen=True)
class YarnPreset:
    """A Table 3 thread: the published row plus what :func:`~usdfiber.authoring.apply_yarn` authors."""

    name: str
    published: Table3Row
    fiber_preset: str
    source: str = TABLE3_SOURCE
    note: str = ("Table 3's twist is authored as both the ply twist and the fiber twist within "
                 "each ply (the table gives one twist); twist directions keep the schema's "
                 "fallbacks (ply S, fiber Z).")

    @property
    def staple_length_cm(self) -> float:
        r = self.published.fiber_length_cm
        return 0.0 if r is None else midpoint(r)

    @property
    def ply_radius_mm(self) -> float:
        return ply_radius_mm(self.published.dtex, FIBER_PRESETS[self.fiber_preset].density_g_cm3)

    @property
    def yarn_diameter_mm(self) -> float:
        """Nominal yarn diameter (mm) of touching plies (:func:`usdfiber.spec.yarn.yarn_diameter`)."""
        return yarn_diameter(self.published.plies, self.ply_radius_mm)

    def yarn_attributes(self) -> dict[str, Any]:
        """The FiberYarnAPI attribute values this preset authors (schema name -> value)."""
        p = self.published
        return {
            Yarn.PLIES: p.plies,
            Yarn.FIBERS_PER_PLY: p.fibers_per_ply,
            Yarn.PLY_LINEAR_DENSITY: p.dtex,
            Yarn.FIBER_STAPLE_LENGTH: self.staple_length_cm,
            Yarn.PLY_TWIST: p.twist,
            Yarn.FIBER_TWIST: p.twist,
            Yarn.PLY_RADIUS: self.ply_radius_mm,
        }


YARN_PRESETS: dict[str, YarnPreset] = {y.name: y for y in (
    YarnPreset("Skala 360", Table3Row("Skala 360", "Polyester", None, 5.0, 24, 1, 74.0), "polyester"),
    YarnPreset("ORA 120", Table3Row("ORA 120", "Polyester", (3.0, 4.0), 8.8, 90, 2, 140.0), "polyester"),
    YarnPreset("CNe 50", Table3Row("CNe 50", "Cotton", (3.0, 4.0), 12.8, 70, 3, 90.0), "cotton"),
    YarnPreset("S 303", Table3Row("S 303", "Silk", (5.0, 8.0), 9.0, 90, 3, 90.0), "silk"),
)}


def fiber_preset(name: str) -> FiberPreset:
    """The fiber preset ``name``; KeyError listing valid names otherwise."""
    try:
        return FIBER_PRESETS[name]
    except KeyError:
        raise KeyError(f"unknown fiber preset {name!r}; valid: {', '.join(FIBER_PRESETS)}") from None


def yarn_preset(name: str) -> YarnPreset:
    """The yarn preset ``name``; KeyError listing valid names otherwise."""
    try:
        return YARN_PRESETS[name]
    except KeyError:
        raise KeyError(f"unknown yarn preset {name!r}; valid: {', '.join(YARN_PRESETS)}") from None


__all__ = [
    "AUTO_PROFILE_FAMILY", "Cuticle", "DYE_COLOURS", "DYE_PRESETS", "DyeColour", "DyePreset",
    "FIBER_PRESETS", "FiberPreset", "PACKING_FRACTION", "TABLE1", "Table1Row", "Table3Row",
    "YARN_PRESETS", "YarnPreset", "dye_values", "fiber_preset", "midpoint", "ply_radius_mm",
    "yarn_preset",
]
