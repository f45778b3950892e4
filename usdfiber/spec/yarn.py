"""The yarn spec: a FiberYarnAPI prim's values, resolved, checked and in scene units.

:class:`YarnParams` holds what the procedural yarn (:mod:`usdfiber.geometry.yarn`, Zhao et al.
2016) needs: plies with their radius, twist and compression, fibers with their density
profile, migration and staple length, hair and loop flyaways, and the seed. It is read from a
prim (:meth:`YarnParams.from_prim`) or from schema values (:meth:`YarnParams.from_attributes`);
names, fallbacks and valid ranges are the schema's (:mod:`usdfiber.spec.attributes`).

The yarn's size is defined here once: N circular plies of radius r touch around the yarn
centre, so their centres lie at ``d = r / sin(pi / N)`` (0 for one ply,
:func:`ply_distance`) and the yarn's nominal diameter is ``2 (d + r)`` (:func:`yarn_diameter`).
The presets' yarn width, the validators' width check and the generator all use these.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from usdfiber.errors import PrimError
from usdfiber.spec.attributes import Fiber, Interval, Yarn, attribute, attributes
from usdfiber.spec.schema_data import PROPERTIES

__all__ = ["YarnError", "YarnParams", "is_real", "ply_distance", "yarn_diameter"]


class YarnError(PrimError):
    """A yarn value or input that cannot be used (a :class:`~usdfiber.errors.PrimError`)."""


def ply_distance(plies: int, ply_radius: float) -> float:
    """Distance of the ply centres from the yarn centre: ``r / sin(pi / N)`` for N touching
    circular plies of radius r (0 for one ply). Any length unit."""
    return 0.0 if plies <= 1 else ply_radius / math.sin(math.pi / plies)


def yarn_diameter(plies: int, ply_radius: float) -> float:
    """Nominal yarn diameter ``2 (d + r)``: the circle enclosing N touching circular plies of
    radius r, ``2 r (1 + 1 / sin(pi / N))`` (``2 r`` for one ply). Same unit as ``ply_radius``."""
    return 2.0 * (ply_distance(plies, ply_radius) + ply_radius)


def is_real(v: Any) -> bool:
    """A real number (not a bool)."""
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


@dataclass(frozen=True)
class YarnParams:
    """Every FiberYarnAPI value of a yarn, resolved and converted to scene units.

    Lengths are in scene units (stage units: ``metersPerUnit`` metres), twists in signed turns
    per scene unit (Z > 0, S < 0), densities in flyaways per scene unit of yarn length.
    """

    plies: int
    fibers_per_ply: int
    ply_radius: float                      # R_ply, scene units (before compression)
    ply_twist: float                       # T_ply, signed turns / scene unit (Z > 0, S < 0)
    fiber_twist: float                     # T_fib, signed turns / scene unit, within the ply frame
    ply_compression: tuple[float, float]   # (e_N radial, e_T tangential), dimensionless
    migration: tuple[float, float]         # (rho_min, rho_max), dimensionless
    migration_period: float                # P_mig, turns of fiber twist per migration cycle
    density_profile: tuple[float, float]   # (eps, beta) of p(R), Zhao 2016 eq. 4
    staple_length: float = 0.0             # scene units; 0 = continuous filament
    hair_density: float = 0.0              # hairs per scene unit of yarn
    hair_length: tuple[float, float] = (0.0, 0.0)   # (mean, std) beyond the ply, scene units
    loop_density: float = 0.0              # loops per scene unit of yarn
    loop_height: tuple[float, float] = (0.0, 0.0)   # (mean, std) above the ply, scene units
    seed: int = 0
    expand: bool = True                    # yarn:expandFibers
    linear_density: float = 0.0            # dtex, informational (not used by the expansion)
    fiber_diameter: float | None = None    # scene units, from fiber:diameter when authored
    meters_per_unit: float = 0.01          # of the stage the values were converted for
    prim_path: str = ""

    def __post_init__(self) -> None:
        def bad(attr: str, why: str) -> YarnError:
            return YarnError(None, self.prim_path or None, attr, why)

        if not (isinstance(self.plies, (int, np.integer)) and self.plies >= 1):
            raise bad("plies", f"must be an integer >= 1, got {self.plies!r}")
        if not (isinstance(self.fibers_per_ply, (int, np.integer)) and self.fibers_per_ply >= 1):
            raise bad("fibers_per_ply", f"must be an integer >= 1, got {self.fibers_per_ply!r}")
        for name in ("ply_radius", "migration_period"):
            v = getattr(self, name)
            if not (is_real(v) and math.isfinite(v) and v > 0):
                raise bad(name, f"must be finite and > 0, got {v!r}")
        for name in ("ply_twist", "fiber_twist"):
            v = getattr(self, name)
            if not (is_real(v) and math.isfinite(v)):
                raise bad(name, f"must be finite, got {v!r}")
        for name in ("staple_length", "hair_density", "loop_density"):
            v = getattr(self, name)
            if not (is_real(v) and math.isfinite(v) and v >= 0):
                raise bad(name, f"must be finite and >= 0, got {v!r}")
        for name in ("ply_compression", "migration", "density_profile", "hair_length", "loop_height"):
            v = getattr(self, name)
            if len(v) != 2 or not all(is_real(c) and math.isfinite(c) and c >= 0 for c in v):
                raise bad(name, f"must be two finite values >= 0, got {v!r}")
        if min(self.ply_compression) <= 0:
            raise bad("ply_compression", f"must be > 0, got {self.ply_compression!r}")
        if self.migration[0] > self.migration[1]:
            raise bad("migration", f"needs rho_min <= rho_max, got {self.migration!r}")
        if self.density_profile[0] >= 0.5:
            raise bad("density_profile", f"epsilon must be < 0.5, got {self.density_profile[0]!r}")

    # ---------------------------------------------------------------- derived
    @property
    def ply_distance(self) -> float:
        """Distance d of the ply centres from the yarn centre (touching plies, eq. Y2)."""
        return ply_distance(self.plies, self.ply_radius)

    @property
    def yarn_radius(self) -> float:
        """Nominal yarn radius d + R_ply (uncompressed, unmigrated), as the presets' yarn width."""
        return 0.5 * yarn_diameter(self.plies, self.ply_radius)

    @property
    def max_fiber_distance(self) -> float:
        """Bound on the distance of a ply fiber's centre line from the yarn centre:
        d + R_ply max(e_N, e_T) rho_max (radius_scale 1)."""
        return self.ply_distance + self.ply_radius * max(self.ply_compression) * max(
            self.migration[1], 0.0)

    @property
    def fiber_count(self) -> int:
        return int(self.plies) * int(self.fibers_per_ply)

    # ---------------------------------------------------------------- construction
    @classmethod
    def from_attributes(cls, values: Mapping[str, Any] | None = None, meters_per_unit: float = 0.01,
                        *, prim_path: str = "", fiber_diameter_um: float | None = None,
                        prim: Any = None) -> "YarnParams":
        """Build from FiberYarnAPI values in schema units (missing names take the schema's
        fallbacks), converting to a stage of ``meters_per_unit``.

        Units (schema): yarn lengths mm (ply radius, hair length, loop height), staple length cm,
        twist turns/cm, flyaway densities per cm. Valid ranges are the schema's
        (:mod:`usdfiber.spec.attributes`). Raises YarnError naming the attribute (and, given the
        ``prim`` the values were read from, its file).
        """
        p = prim_path or None

        def fail(name: str | None, why: str) -> YarnError:
            if prim is not None:
                return YarnError.at(prim, name, why)
            return YarnError(None, p, name, why)

        specs = attributes(Yarn.API)
        vals = {n: s.fallback for n, s in specs.items()}
        if values:
            unknown = set(values) - set(specs)
            if unknown:
                raise fail(None, f"unknown yarn attribute(s) {sorted(unknown)}")
            vals.update(values)
        mpu = meters_per_unit
        if not (is_real(mpu) and math.isfinite(mpu) and mpu > 0):
            raise fail("metersPerUnit", f"stage metersPerUnit must be finite and > 0, got {mpu!r}")
        mpu = float(mpu)

        def get(name: str) -> Any:
            v = vals.get(name)
            if v is None:
                raise fail(name, "has no value (and no schema fallback)")
            return v

        def integer(name: str, lo: int | None = None) -> int:
            v = get(name)
            if not isinstance(v, (int, np.integer)) or isinstance(v, (bool, np.bool_)):
                raise fail(name, f"must be an integer, got {v!r}")
            v = int(v)
            rng = specs[name].valid
            if rng is not None and v not in rng:
                raise fail(name, f"must be in {rng}, got {v}")
            if lo is not None and v < lo:
                raise fail(name, f"must be >= {lo}, got {v}")
            return v

        def check(v: Any, name: str, rng: Interval, what: str = "", unit: str = "") -> float:
            if not is_real(v):
                raise fail(name, f"must be a number, got {v!r}")
            v = float(v)
            if not (math.isfinite(v) and v in rng):
                label = f"{what} " if what else ""
                raise fail(name, f"{label}must be in {rng}{' ' + unit if unit else ''}, got {v:g}")
            return v

        def real(name: str) -> float:
            s = specs[name]
            return check(get(name), name, s.valid or Interval(), unit=s.unit)

        def pair(name: str) -> tuple[float, float]:
            v = get(name)
            try:
                a, b = v
            except (TypeError, ValueError):
                raise fail(name, f"must be a pair of numbers, got {v!r}") from None
            s = specs[name]
            labels = s.components or ("", "")
            r0, r1 = s.component_ranges(2)
            return (check(a, name, r0, labels[0], s.unit), check(b, name, r1, labels[1], s.unit))

        def direction(name: str) -> float:
            v = str(get(name))
            if v not in (specs[name].allowed_tokens or ()):
                raise fail(name, f'must be "S" or "Z", got {v!r}')
            return 1.0 if v == "Z" else -1.0

        mm = 1e-3 / mpu           # scene units per mm
        cm = 1e-2 / mpu           # scene units per cm
        per_cm = mpu / 1e-2       # (per cm) -> (per scene unit)

        plies = integer(Yarn.PLIES)
        fpp = integer(Yarn.FIBERS_PER_PLY)
        dtex = real(Yarn.PLY_LINEAR_DENSITY)
        staple = real(Yarn.FIBER_STAPLE_LENGTH)
        ply_twist = real(Yarn.PLY_TWIST)
        ply_dir = direction(Yarn.PLY_TWIST_DIRECTION)
        fib_twist = real(Yarn.FIBER_TWIST)
        fib_dir = direction(Yarn.FIBER_TWIST_DIRECTION)
        radius = real(Yarn.PLY_RADIUS)
        e_n, e_t = pair(Yarn.PLY_COMPRESSION)
        rmin, rmax = pair(Yarn.FIBER_MIGRATION)
        if rmin > rmax:
            raise fail(Yarn.FIBER_MIGRATION, f"needs rho_min <= rho_max, got ({rmin:g}, {rmax:g})")
        period = real(Yarn.FIBER_MIGRATION_PERIOD)
        eps, beta = pair(Yarn.FIBER_DENSITY_PROFILE)
        hair_d = real(Yarn.FLYAWAY_HAIR_DENSITY)
        hl_m, hl_s = pair(Yarn.FLYAWAY_HAIR_LENGTH)
        loop_d = real(Yarn.FLYAWAY_LOOP_DENSITY)
        lh_m, lh_s = pair(Yarn.FLYAWAY_LOOP_HEIGHT)
        seed = integer(Yarn.SEED, -(2**63))
        expand = get(Yarn.EXPAND_FIBERS)
        if not isinstance(expand, (bool, np.bool_)):
            raise fail(Yarn.EXPAND_FIBERS, f"must be a bool, got {expand!r}")
        fdiam = None
        if fiber_diameter_um is not None:
            d = attribute(Fiber.DIAMETER)
            fdiam = check(fiber_diameter_um, Fiber.DIAMETER, d.valid or Interval(), unit=d.unit)
            fdiam *= 1e-6 / mpu

        return cls(
            plies=plies, fibers_per_ply=fpp, ply_radius=radius * mm,
            ply_twist=ply_dir * ply_twist * per_cm, fiber_twist=fib_dir * fib_twist * per_cm,
            ply_compression=(e_n, e_t), migration=(rmin, rmax), migration_period=period,
            density_profile=(eps, beta), staple_length=staple * cm,
            hair_density=hair_d * per_cm, hair_length=(hl_m * mm, hl_s * mm),
            loop_density=loop_d * per_cm, loop_height=(lh_m * mm, lh_s * mm),
            seed=seed, expand=bool(expand), linear_density=dtex, fiber_diameter=fdiam,
            meters_per_unit=mpu, prim_path=prim_path,
        )

    @classmethod
    def from_prim(cls, prim: Any, time: Any = None) -> "YarnParams":
        """Resolve the FiberYarnAPI values of ``prim`` at ``time`` (composition applied) and
        convert them with the stage's metersPerUnit. ``fiber_diameter`` comes from
        ``fiber:diameter`` (um) when the prim has a value for it.

        Raises YarnError (a :class:`~usdfiber.errors.PrimError`) naming the file, prim and
        attribute for unusable values (outside the schema's valid ranges, wrong types, unknown
        tokens).
        """
        from pxr import Usd, UsdGeom

        if time is None:
            time = Usd.TimeCode.Default()
        elif not isinstance(time, Usd.TimeCode):
            time = Usd.TimeCode(time)
        if not prim or not prim.IsValid():
            raise YarnError(None, "<invalid prim>", None, "not a valid prim")
        path = str(prim.GetPath())
        if not prim.HasAPI(Yarn.API):
            raise YarnError.at(prim, None,
                               "has no FiberYarnAPI (apply it with usdfiber.authoring.apply_yarn)")
        values: dict[str, Any] = {}
        for name in PROPERTIES[Yarn.API]:
            attr = prim.GetAttribute(name)
            v = attr.Get(time) if attr else None
            if v is not None:
                values[name] = v
        diam_attr = prim.GetAttribute(Fiber.DIAMETER)
        diam = diam_attr.Get(time) if diam_attr else None
        mpu = UsdGeom.GetStageMetersPerUnit(prim.GetStage())
        return cls.from_attributes(values, mpu, prim_path=path,
                                   fiber_diameter_um=None if diam is None else diam, prim=prim)
