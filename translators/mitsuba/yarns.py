"""Procedural expansion of yarn centre lines into fiber curves (pure numpy, vectorized).

The model is the procedural yarn of Zhao, Luan and Bala 2016, "Fitting Procedural Yarn Models
for Realistic Cloth Rendering" (SIGGRAPH 2016, Section 4.1; after Schroeder et al. 2015), driven
by the values of FiberYarnAPI (``schema/schema.usda``). Equation numbers below are this module's
own (Zhao 2016's equation numbers are given where they exist: (1)-(4) of its Section 4.1).

Frames. The yarn centre line is a polyline C(s) over its arc length s in [0, L]. The yarn
cross section at s is spanned by a rotation-minimizing frame (n(s), b(s) = t(s) x n(s)),
computed by double reflection (Wang et al. 2008, via ``curves.reference_normals``) on the
sampling grid, so that (n, b, t) is right-handed and does not flip. A cross-section point
(x, y) lies at::

    P(s) = C(s) + k(s) (x n(s) + y b(s))                                              (Y1)

with k(s) = ``radius_scale`` (the authored curve width relative to the nominal yarn width, for
example). An angle that grows with s from n towards b is a right-handed helix: Z twist (the
schema's convention: S left-handed, Z right-handed); S twist is a negative signed twist.

Plies (Zhao 2016 eq. 1). Ply i of N sits at the angle and distance::

    phi_i(s) = 2 pi i / N + 2 pi T_ply s,    c_i(s) = d (cos phi_i, sin phi_i)        (Y2)

T_ply = signed ply twist in turns per scene unit (1 / alpha_ply). d = R_ply / sin(pi / N) puts
N circular plies of radius R_ply in contact (d = R_ply for 2 plies, 0 for 1): the same "touching
plies" rule as ``usdfiber.presets.yarn_diameter_mm`` and the validators' nominal yarn diameter
2 R_ply (1 + 1 / sin(pi / N)), so the nominal yarn radius is d + R_ply.

Fibers in a ply (Zhao 2016 eqs. 2-4). Fiber j has a rest radius R_j (fraction of R_ply) drawn
by Zhao's rejection sampler (his Algorithm 1: a point uniform in the unit disk is accepted with
probability p(R)), so p is a density per unit *area* of the ply cross section and the pdf of
R_j is proportional to R p(R)::

    p(R) = (1 - 2 eps) ((e - exp(R)) / (e - 1))^beta + eps,     R in [0, 1]           (Y3)

an initial angle theta_j (uniform) and a migration phase theta_mig,j (uniform). Along the yarn::

    theta_j(s) = theta_j + 2 pi T_fib s                                               (Y4)
    r_j(s) = R_j R_ply [rho_min + (rho_max - rho_min)
                        (cos(2 pi |T_fib| s / P_mig + theta_mig,j) + 1) / 2]                 (Y5)

(Y5) is Zhao's r(theta) = R_i [rho_min + (rho_max - rho_min)(cos(s theta + theta_i^mig) + 1)/2]
with s = 1 / P_mig (P_mig = yarn:fiber:migrationPeriod, in turns of fiber twist) and the
constant s theta_j absorbed into the random phase. The angle theta is measured in the ply's own
frame (radial = away from the yarn centre, tangential = +90 degrees), which rotates with phi_i;
the ply cross section is compressed to an ellipse there (Zhao 2016's e_N, e_T)::

    (x, y) = c_i + Rot(phi_i) (e_N r_j cos theta_j, e_T r_j sin theta_j)              (Y6)

Staple fibers. With yarn:fiber:stapleLength = l > 0 each fiber path is cut every l of yarn
length, starting at a random offset in [0, l) per fiber (continuous filament when l = 0).

Flyaways (Zhao 2016 Section 4.1, "Flyaway fibers"): extra curves, kind 1 (hair) and kind 2
(loop); their numbers are Poisson with mean density x L, per yarn.

- Hair: a fiber end that leaves the ply and ends free outside the yarn. Zhao's hair has linear
  r, z and theta along it; here theta_span = 0 and the ply twist is frozen at the exit point,
  which makes the hair a straight line in the cross-section frame of its exit point: it starts
  at a depth delta ~ U(0.2, 0.6) R_ply inside the ply, exits through the ply boundary at a
  random angle (on the outer side, |angle| < 60 degrees from the ply's radial direction, when
  N > 1), and extends for the hair length h ~ N(mean, std) (truncated at 0) beyond it, at an
  elevation alpha ~ U(15, 45) degrees from the yarn axis in a random axial direction, away
  from the yarn centre. The schema gives no elevation or depth: those ranges are ours.
- Loop: a stretch of a migrating ply fiber pulled out of the ply (Zhao: loops form where a
  migrating fiber is at its outermost). A random parent fiber of a random ply; the loop is
  centred at the parent's migration maximum nearest to a uniform random position (a uniform
  position when the fiber does not migrate), spans half a migration cycle P_mig / (2 |T_fib|)
  of yarn length, clamped to [2, 8] (R_ply + H), and rises to H ~ N(mean, std) (truncated at
  0) above the ply boundary at its middle::

      o_loop(s) = c_i(s) + (1 - w) o_j(s) + w Rot(phi_i(s)) (D + H) e_hat,  w = sin^2(pi u)   (Y7)

  with o_j the parent's offset from its ply centre (Y6), u in [0, 1] along the loop, e_hat the
  unit direction of (e_N cos theta_o, e_T sin theta_o) and D = R_ply |(e_N cos theta_o, e_T sin
  theta_o)| the ply boundary along it; theta_o is the parent's angle at the loop centre for one
  ply and uniform in +-45 degrees around the outward radial direction for N > 1 (loops stick
  out of the yarn, not into the neighbouring plies). The loop is a separate curve on top of its
  parent (Zhao edits the parent fiber itself): ply fibers are never changed by flyaways.

Sampling and B-splines. All ply fibers of a yarn are sampled on one arc-length grid with
``samples_per_turn`` samples per turn of the fastest component of (Y2)-(Y6),
f = |T_ply| + |T_fib| (+ |T_fib| / P_mig when migrating), and no coarser than the median
centre-line segment (and l / 4 for staple fibers). The control points are the samples X_i
corrected by one step towards interpolation, P_i = X_i - (X_{i-1} - 2 X_i + X_{i+1}) / 6, with
phantom end points by quadratic extrapolation (P_{-1} = 3 P_0 - 3 P_1 + P_2, likewise after the
last point; an end point's second difference is its neighbour's). The uniform cubic B-spline
then lies within O(h^4) of the model inside a curve and O(h^3) on its end segments, where raw
samples as control points give O(h^2) (the spline cuts every bend by |X''| h^2 / 6).
Measured on a 10 mm CNe 50 yarn at 12 samples per turn against a 128-per-turn expansion of the
same fibers: largest deviation 0.08 um (S ply / Z fiber twist) and 0.39 um (Z / Z twist with
migration (0.7, 1.2), the fiber circling its ply fastest), i.e. 1 % and 4 % of the cotton fiber
radius (9.25 um); raw samples as control points: 0.74 um and 2.5 um.
``ExpandedFibers.curve_points`` gives the B-spline at its knots (= the samples to O(h^4)).

Level of detail: ``fiber_fraction`` keeps the first round(fraction x count) fibers of a fixed
random permutation of all plies x fibersPerPly fibers (and likewise of the hairs and of the
loops): fewer fibers are always a subset of more, each with identical geometry.

Simplifications (beyond those above): the ply and fiber cross sections lie in the plane normal
to the yarn centre line (not to the ply's own helical axis; exact in the limit of small helix
angles); the staple length is the same for every fiber; the centre polyline is interpolated
linearly (its tangent, for the frames, is interpolated between vertex tangents); no collision
handling between fibers.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from usdfiber.translators.mitsuba.curves import CurveGeometry, reference_normals

__all__ = [
    "YarnError",
    "YarnParams",
    "ExpandedFibers",
    "CentreFrames",
    "expand_yarn",
    "centre_frames",
    "density_profile",
    "YARN_ATTRIBUTES",
]

_TWO_PI = 2.0 * math.pi
KIND_PLY, KIND_HAIR, KIND_LOOP = 0, 1, 2

# Every FiberYarnAPI attribute, in schema order.
YARN_ATTRIBUTES: tuple[str, ...] = (
    "yarn:plies",
    "yarn:fibersPerPly",
    "yarn:ply:linearDensity",
    "yarn:fiber:stapleLength",
    "yarn:ply:twist",
    "yarn:ply:twistDirection",
    "yarn:fiber:twist",
    "yarn:fiber:twistDirection",
    "yarn:ply:radius",
    "yarn:ply:compression",
    "yarn:fiber:migration",
    "yarn:fiber:migrationPeriod",
    "yarn:fiber:densityProfile",
    "yarn:flyaway:hairDensity",
    "yarn:flyaway:hairLength",
    "yarn:flyaway:loopDensity",
    "yarn:flyaway:loopHeight",
    "yarn:seed",
    "yarn:expandFibers",
)


class YarnError(ValueError):
    """A yarn value or input that cannot be used; names the prim and attribute when known."""

    def __init__(self, reason: str, prim: str | None = None, attribute: str | None = None) -> None:
        self.prim = prim
        self.attribute = attribute
        self.reason = reason
        where = ""
        if prim:
            where += f"{prim}: "
        if attribute:
            where += f"attribute '{attribute}': "
        super().__init__(where + reason)


# ---------------------------------------------------------------------------------------------
# Parameters
# ---------------------------------------------------------------------------------------------


def _schema_fallbacks() -> dict[str, Any]:
    from pxr import Usd

    d = Usd.SchemaRegistry().FindAppliedAPIPrimDefinition("FiberYarnAPI")
    if d is None:
        raise YarnError("FiberYarnAPI is not registered with USD (import usdfiber before opening "
                        "any stage)")
    out = {}
    for name in YARN_ATTRIBUTES:
        a = d.GetAttributeDefinition(name)
        out[name] = a.GetFallbackValue() if a else None
    return out


def _is_real(v: Any) -> bool:
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
            return YarnError(why, self.prim_path or None, attr)

        if not (isinstance(self.plies, (int, np.integer)) and self.plies >= 1):
            raise bad("plies", f"must be an integer >= 1, got {self.plies!r}")
        if not (isinstance(self.fibers_per_ply, (int, np.integer)) and self.fibers_per_ply >= 1):
            raise bad("fibers_per_ply", f"must be an integer >= 1, got {self.fibers_per_ply!r}")
        for name in ("ply_radius", "migration_period"):
            v = getattr(self, name)
            if not (_is_real(v) and math.isfinite(v) and v > 0):
                raise bad(name, f"must be finite and > 0, got {v!r}")
        for name in ("ply_twist", "fiber_twist"):
            v = getattr(self, name)
            if not (_is_real(v) and math.isfinite(v)):
                raise bad(name, f"must be finite, got {v!r}")
        for name in ("staple_length", "hair_density", "loop_density"):
            v = getattr(self, name)
            if not (_is_real(v) and math.isfinite(v) and v >= 0):
                raise bad(name, f"must be finite and >= 0, got {v!r}")
        for name in ("ply_compression", "migration", "density_profile", "hair_length", "loop_height"):
            v = getattr(self, name)
            if len(v) != 2 or not all(_is_real(c) and math.isfinite(c) and c >= 0 for c in v):
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
        return 0.0 if self.plies <= 1 else self.ply_radius / math.sin(math.pi / self.plies)

    @property
    def yarn_radius(self) -> float:
        """Nominal yarn radius d + R_ply (uncompressed, unmigrated), as the presets' yarn width."""
        return self.ply_distance + self.ply_radius

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
                        *, prim_path: str = "", fiber_diameter_um: float | None = None) -> "YarnParams":
        """Build from FiberYarnAPI values in schema units (missing names take the schema's
        fallbacks), converting to a stage of ``meters_per_unit``.

        Units (schema): yarn lengths mm (ply radius, hair length, loop height), staple length cm,
        twist turns/cm, flyaway densities per cm. Raises YarnError naming the attribute.
        """
        p = prim_path or None
        vals = _schema_fallbacks()
        if values:
            unknown = set(values) - set(YARN_ATTRIBUTES)
            if unknown:
                raise YarnError(f"unknown yarn attribute(s) {sorted(unknown)}", p)
            vals.update(values)
        mpu = meters_per_unit
        if not (_is_real(mpu) and math.isfinite(mpu) and mpu > 0):
            raise YarnError(f"stage metersPerUnit must be finite and > 0, got {mpu!r}", p,
                            "metersPerUnit")
        mpu = float(mpu)

        def get(name: str) -> Any:
            v = vals.get(name)
            if v is None:
                raise YarnError("has no value (and no schema fallback)", p, name)
            return v

        def integer(name: str, lo: int, hi: int | None = None) -> int:
            v = get(name)
            if not isinstance(v, (int, np.integer)) or isinstance(v, (bool, np.bool_)):
                raise YarnError(f"must be an integer, got {v!r}", p, name)
            v = int(v)
            if v < lo or (hi is not None and v > hi):
                raise YarnError(f"must be in [{lo}, {hi}], got {v}" if hi is not None else
                                f"must be >= {lo}, got {v}", p, name)
            return v

        def real(v: Any, name: str, lo: float, hi: float, lo_open: bool = False,
                 hi_open: bool = False, what: str = "", unit: str = "") -> float:
            if not _is_real(v):
                raise YarnError(f"must be a number, got {v!r}", p, name)
            v = float(v)
            ok = math.isfinite(v) and (v > lo if lo_open else v >= lo) and (
                v < hi if hi_open else v <= hi)
            if not ok:
                close = ")" if hi_open or math.isinf(hi) else "]"
                top = "inf" if math.isinf(hi) else format(hi, "g")
                rng = f"{'(' if lo_open else '['}{lo:g}, {top}{close}"
                label = f"{what} " if what else ""
                raise YarnError(f"{label}must be in {rng}{' ' + unit if unit else ''}, got {v:g}", p, name)
            return v

        def pair(name: str) -> tuple[Any, Any]:
            v = get(name)
            try:
                a, b = v
            except (TypeError, ValueError):
                raise YarnError(f"must be a pair of numbers, got {v!r}", p, name) from None
            return a, b

        def direction(name: str) -> float:
            v = str(get(name))
            if v not in ("S", "Z"):
                raise YarnError(f'must be "S" or "Z", got {v!r}', p, name)
            return 1.0 if v == "Z" else -1.0

        mm = 1e-3 / mpu           # scene units per mm
        cm = 1e-2 / mpu           # scene units per cm
        per_cm = mpu / 1e-2       # (per cm) -> (per scene unit)

        plies = integer("yarn:plies", 1, 12)
        fpp = integer("yarn:fibersPerPly", 1, 2000)
        dtex = real(get("yarn:ply:linearDensity"), "yarn:ply:linearDensity", 0, math.inf, unit="dtex")
        staple = real(get("yarn:fiber:stapleLength"), "yarn:fiber:stapleLength", 0, 100, unit="cm")
        ply_twist = real(get("yarn:ply:twist"), "yarn:ply:twist", 0, 100, unit="turns/cm")
        ply_dir = direction("yarn:ply:twistDirection")
        fib_twist = real(get("yarn:fiber:twist"), "yarn:fiber:twist", 0, 100, unit="turns/cm")
        fib_dir = direction("yarn:fiber:twistDirection")
        radius = real(get("yarn:ply:radius"), "yarn:ply:radius", 0, 10, lo_open=True, unit="mm")
        e_n, e_t = pair("yarn:ply:compression")
        e_n = real(e_n, "yarn:ply:compression", 0, 2, lo_open=True, what="e_N")
        e_t = real(e_t, "yarn:ply:compression", 0, 2, lo_open=True, what="e_T")
        rmin, rmax = pair("yarn:fiber:migration")
        rmin = real(rmin, "yarn:fiber:migration", 0, 2, what="rho_min")
        rmax = real(rmax, "yarn:fiber:migration", 0, 2, what="rho_max")
        if rmin > rmax:
            raise YarnError(f"needs rho_min <= rho_max, got ({rmin:g}, {rmax:g})", p,
                            "yarn:fiber:migration")
        period = real(get("yarn:fiber:migrationPeriod"), "yarn:fiber:migrationPeriod", 0, 1000,
                      lo_open=True, unit="turns")
        eps, beta = pair("yarn:fiber:densityProfile")
        eps = real(eps, "yarn:fiber:densityProfile", 0, 0.5, hi_open=True, what="epsilon")
        beta = real(beta, "yarn:fiber:densityProfile", 0, math.inf, what="beta")
        hair_d = real(get("yarn:flyaway:hairDensity"), "yarn:flyaway:hairDensity", 0, 1000, unit="per cm")
        hl_m, hl_s = pair("yarn:flyaway:hairLength")
        hl_m = real(hl_m, "yarn:flyaway:hairLength", 0, math.inf, what="mean", unit="mm")
        hl_s = real(hl_s, "yarn:flyaway:hairLength", 0, math.inf, what="std", unit="mm")
        loop_d = real(get("yarn:flyaway:loopDensity"), "yarn:flyaway:loopDensity", 0, 1000, unit="per cm")
        lh_m, lh_s = pair("yarn:flyaway:loopHeight")
        lh_m = real(lh_m, "yarn:flyaway:loopHeight", 0, math.inf, what="mean", unit="mm")
        lh_s = real(lh_s, "yarn:flyaway:loopHeight", 0, math.inf, what="std", unit="mm")
        seed = integer("yarn:seed", -(2**63))
        expand = get("yarn:expandFibers")
        if not isinstance(expand, (bool, np.bool_)):
            raise YarnError(f"must be a bool, got {expand!r}", p, "yarn:expandFibers")
        fdiam = None
        if fiber_diameter_um is not None:
            fdiam = real(fiber_diameter_um, "fiber:diameter", 0, math.inf, lo_open=True, unit="um")
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

        Raises YarnError (a ValueError) naming the prim and the attribute for unusable values
        (outside the schema's valid ranges, wrong types, unknown tokens).
        """
        from pxr import Usd, UsdGeom

        if time is None:
            time = Usd.TimeCode.Default()
        elif not isinstance(time, Usd.TimeCode):
            time = Usd.TimeCode(time)
        if not prim or not prim.IsValid():
            raise YarnError("not a valid prim", "<invalid prim>")
        path = str(prim.GetPath())
        if not prim.HasAPI("FiberYarnAPI"):
            raise YarnError("has no FiberYarnAPI (apply it with usdfiber.authoring.apply_yarn)", path)
        values: dict[str, Any] = {}
        for name in YARN_ATTRIBUTES:
            attr = prim.GetAttribute(name)
            v = attr.Get(time) if attr else None
            if v is not None:
                values[name] = v
        diam_attr = prim.GetAttribute("fiber:diameter")
        diam = diam_attr.Get(time) if diam_attr else None
        mpu = UsdGeom.GetStageMetersPerUnit(prim.GetStage())
        return cls.from_attributes(values, mpu, prim_path=path,
                                   fiber_diameter_um=None if diam is None else diam)


def density_profile(R: np.ndarray, eps: float, beta: float) -> np.ndarray:
    """Zhao 2016 eq. 4 (Y3): p(R) = (1 - 2 eps) ((e - exp(R)) / (e - 1))^beta + eps, for R the
    distance from the ply centre as a fraction of R_ply (fibers per unit cross-section area,
    unnormalized; p(0) = 1 - eps, p(1) = eps)."""
    R = np.clip(np.asarray(R, np.float64), 0.0, 1.0)
    base = np.maximum((math.e - np.exp(R)) / (math.e - 1.0), 0.0)
    return (1.0 - 2.0 * eps) * base**beta + eps


# ---------------------------------------------------------------------------------------------
# Centre line and frames
# ---------------------------------------------------------------------------------------------


@dataclass
class CentreFrames:
    """The yarn centre line sampled at arc lengths ``s``: positions and right-handed
    rotation-minimizing frames (normal, binormal = tangent x normal, tangent)."""

    s: np.ndarray          # (M,)
    position: np.ndarray   # (M, 3)
    tangent: np.ndarray    # (M, 3)
    normal: np.ndarray     # (M, 3)
    binormal: np.ndarray   # (M, 3)
    scale: np.ndarray      # (M,) radius_scale


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


class _Centre:
    """Arc-length parameterized polyline with smooth tangents and an RMF on a sample grid."""

    def __init__(self, centre: Any, radius_scale: Any) -> None:
        c = np.asarray(centre, dtype=np.float64)
        if c.ndim != 2 or c.shape[1] != 3 or len(c) < 2:
            raise YarnError(f"centre must be an (N >= 2, 3) array of points, got shape {c.shape}")
        if not np.all(np.isfinite(c)):
            raise YarnError("centre contains NaN or Inf")
        rs = np.asarray(radius_scale, dtype=np.float64)
        if rs.ndim == 0:
            rs = np.full(len(c), float(rs))
        elif rs.shape != (len(c),):
            raise YarnError(f"radius_scale must be a scalar or one value per centre point "
                            f"({len(c)}), got shape {rs.shape}")
        if not np.all(np.isfinite(rs)) or np.any(rs <= 0):
            raise YarnError("radius_scale must be finite and > 0")
        seg = np.linalg.norm(np.diff(c, axis=0), axis=1)
        keep = np.concatenate([[True], seg > 1e-12 * (1.0 + np.abs(c).max())])
        c, rs = c[keep], rs[keep]
        if len(c) < 2:
            raise YarnError("centre line has zero length")
        d = np.diff(c, axis=0)
        seg = np.linalg.norm(d, axis=1)
        u = d / seg[:, None]
        vt = np.empty_like(c)
        vt[0], vt[-1] = u[0], u[-1]
        mid = u[:-1] + u[1:]
        ok = np.linalg.norm(mid, axis=1) > 1e-6
        vt[1:-1] = np.where(ok[:, None], mid, u[1:])
        self.points = c
        self.cum = np.concatenate([[0.0], np.cumsum(seg)])
        self.length = float(self.cum[-1])
        self.vertex_tangent = _unit(vt)
        self.scale = rs
        self.median_segment = float(np.median(seg))
        self.grid: CentreFrames | None = None

    def _interp(self, s: np.ndarray, values: np.ndarray) -> np.ndarray:
        return np.stack([np.interp(s, self.cum, values[:, k]) for k in range(values.shape[1])], -1)

    def positions(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(position, unit tangent, scale) at arc lengths s (1-D), extrapolated beyond the ends
        along the end tangents."""
        sc = np.clip(s, 0.0, self.length)
        pos = self._interp(sc, self.points)
        tan = _unit(self._interp(sc, self.vertex_tangent))
        over = s - sc
        if np.any(over != 0):
            pos = pos + over[:, None] * tan
        return pos, tan, np.interp(sc, self.cum, self.scale)

    def build_grid(self, s: np.ndarray) -> CentreFrames:
        pos, tan, scale = self.positions(s)
        # One linear B-spline "segment" per sample whose midpoint is the sample and whose
        # derivative is the tangent: reference_normals then runs the double-reflection RMF
        # (Wang et al. 2008) over exactly these points and tangents, vectorized.
        m = len(s)
        cp = pos[:, None, :] + np.array([-1.5, -0.5, 0.5, 1.5])[None, :, None] * tan[:, None, :]
        geom = CurveGeometry(cp.reshape(-1, 3), np.zeros(4 * m), 4 * np.arange(m, dtype=np.int64),
                             np.zeros(m, np.int64), 1)
        nrm = reference_normals(geom)
        binrm = np.cross(tan, nrm)
        self.grid = CentreFrames(s, pos, tan, nrm, binrm, scale)
        return self.grid

    def frames(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(position, normal, binormal, scale) at arbitrary arc lengths (1-D), the normal
        interpolated from the RMF grid and re-orthogonalized against the tangent."""
        g = self.grid
        assert g is not None
        pos, tan, scale = self.positions(s)
        sc = np.clip(s, g.s[0], g.s[-1])
        n = np.stack([np.interp(sc, g.s, g.normal[:, k]) for k in range(3)], -1)
        n = _unit(n - np.einsum("ij,ij->i", n, tan)[:, None] * tan)
        return pos, n, np.cross(tan, n), scale


def centre_frames(centre: Any, s: Any = None, *, spacing: float | None = None,
                  radius_scale: Any = 1.0) -> CentreFrames:
    """Rotation-minimizing frames along a yarn centre polyline (double reflection, Wang et al.
    2008), at arc lengths ``s`` (increasing; default: a uniform grid of ``spacing``, or of the
    median segment length). These are the frames :func:`expand_yarn` uses (eq. Y1)."""
    c = _Centre(centre, radius_scale)
    if s is None:
        h = spacing if spacing is not None else c.median_segment
        m = max(2, int(math.ceil(c.length / h)) + 1)
        s = np.linspace(0.0, c.length, m)
    s = np.asarray(s, np.float64).reshape(-1)
    if len(s) < 1 or np.any(np.diff(s) <= 0):
        raise YarnError("arc lengths s must be strictly increasing")
    return c.build_grid(s)


# ---------------------------------------------------------------------------------------------
# Output
# ---------------------------------------------------------------------------------------------


def _curve_offsets(counts: np.ndarray) -> np.ndarray:
    return np.cumsum(counts) - counts


def _second_difference(x: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """X_{i-1} - 2 X_i + X_{i+1} within each curve. At curve ends the neighbour's value: the
    second difference with the quadratically extrapolated phantom point
    X_{-1} = 3 X_0 - 3 X_1 + X_2 (0 for curves of 2 points, whose phantom is 2 X_0 - X_1)."""
    out = np.empty_like(x)
    if len(x) < 3:
        out[:] = 0.0
        return out
    counts = np.asarray(counts, np.int64)
    d = np.diff(x, axis=0)
    np.subtract(d[1:], d[:-1], out=out[1:-1])
    off = _curve_offsets(counts)
    last = off + counts - 1
    three = counts >= 3
    out[off[three]] = out[off[three] + 1]
    out[last[three]] = out[last[three] - 1]
    out[off[~three]] = 0.0
    out[last[~three]] = 0.0
    return out


def _phantoms(p: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Phantom control points before and after each curve: quadratic extrapolation
    3 P_0 - 3 P_1 + P_2 (linear 2 P_0 - P_1 for curves of 2 points)."""
    off = _curve_offsets(counts)
    last = off + counts - 1
    before = 2.0 * p[off] - p[off + 1]
    after = 2.0 * p[last] - p[last - 1]
    three = counts >= 3
    o3, l3 = off[three], last[three]
    before[three] = 3.0 * p[o3] - 3.0 * p[o3 + 1] + p[o3 + 2]
    after[three] = 3.0 * p[l3] - 3.0 * p[l3 - 1] + p[l3 - 2]
    return before, after


@dataclass
class ExpandedFibers:
    """Fiber curves of one yarn. Curve f owns ``points[offsets[f] : offsets[f] + counts[f]]``.

    ``points`` are uniform cubic B-spline control points; :meth:`to_curve_geometry` adds the
    phantom end points (quadratic extrapolation), and the spline then follows the model's
    samples to O(h^4) (O(h^3) on end segments; module doc). :meth:`curve_points` gives the
    spline's value at each control point's knot. ``kind``: 0 ply fiber, 1 hair
    flyaway, 2 loop flyaway. ``fiber``: source fiber id (ply * fibersPerPly + j) of ply fibers
    (several curves per fiber with staple fibers) and of a loop's parent; -1 for hairs.
    ``arclength``: the yarn arc length whose cross section each point lies in.
    ``ply_centres`` (plies, M, 3): the ply centre lines on the sampling grid ``grid_s``.
    """

    points: np.ndarray
    counts: np.ndarray
    kind: np.ndarray
    ply: np.ndarray
    fiber: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    arclength: np.ndarray = field(default_factory=lambda: np.zeros(0))
    ply_centres: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 3)))
    grid_s: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def curve_count(self) -> int:
        return int(len(self.counts))

    @property
    def offsets(self) -> np.ndarray:
        return _curve_offsets(self.counts)

    def curve(self, f: int) -> np.ndarray:
        """Control points of curve ``f``."""
        o = int(self.offsets[f])
        return self.points[o:o + int(self.counts[f])]

    def curve_points(self) -> np.ndarray:
        """(P, 3) positions of the rendered B-spline curves at their knots (the point of each
        control point on its curve): P_i + (P_{i-1} - 2 P_i + P_{i+1}) / 6 with the phantoms
        of :meth:`to_curve_geometry` at the ends."""
        return self.points + _second_difference(self.points, self.counts) / 6.0

    def to_curve_geometry(self, fiber_diameter: float) -> CurveGeometry:
        """Uniform cubic B-spline segments for Mitsuba's ``bsplinecurve``: each curve of n points
        gets phantom end points 3 P_0 - 3 P_1 + P_2 and 3 P_{n-1} - 3 P_{n-2} + P_{n-3}
        (2 P_0 - P_1, 2 P_1 - P_0 for n = 2) and n - 1 segments, whose knots are
        :meth:`curve_points`; radius fiber_diameter / 2 everywhere; ``segment_curve`` is the
        curve index in this object (``counts`` order)."""
        d = float(fiber_diameter)
        if not (math.isfinite(d) and d > 0):
            raise YarnError(f"fiber_diameter must be finite and > 0, got {fiber_diameter!r}")
        counts = np.asarray(self.counts, np.int64)
        nc = len(counts)
        if nc and counts.min() < 2:
            raise YarnError("every fiber curve needs at least 2 points")
        ext_counts = counts + 2
        ext_off = _curve_offsets(ext_counts)
        pts = np.empty((int(ext_counts.sum()), 3))
        curve_of = np.repeat(np.arange(nc), counts)
        pts[np.arange(len(self.points)) + 2 * curve_of + 1] = self.points
        pts[ext_off], pts[ext_off + ext_counts - 1] = _phantoms(self.points, counts)
        nseg = counts - 1
        seg_curve = np.repeat(np.arange(nc, dtype=np.int64), nseg)
        seg_k = np.arange(len(seg_curve), dtype=np.int64) - _curve_offsets(nseg)[seg_curve]
        return CurveGeometry(pts, np.full(len(pts), 0.5 * d), ext_off[seg_curve] + seg_k,
                             seg_curve, nc, [])


# ---------------------------------------------------------------------------------------------
# Random streams
# ---------------------------------------------------------------------------------------------

_STREAM_FIBERS, _STREAM_ORDER, _STREAM_HAIR, _STREAM_LOOP = 1, 2, 3, 4


def _rng(seed: int, seed_offset: int, stream: int) -> np.random.Generator:
    ss = np.random.SeedSequence([int(seed) % 2**64, int(seed_offset) % 2**64, stream, 0x59A2])
    return np.random.Generator(np.random.PCG64(ss))


def _sample_rest_radius(rng: np.random.Generator, n: int, eps: float, beta: float) -> np.ndarray:
    """Zhao 2016 Algorithm 1: points uniform in the unit disk, accepted with probability p(R)."""
    out = np.empty(n)
    filled = 0
    while filled < n:
        m = int(min(max(256, 3 * (n - filled)), 1 << 22))
        r = np.sqrt(rng.random(m))
        acc = r[rng.random(m) < density_profile(r, eps, beta)][: n - filled]
        out[filled:filled + len(acc)] = acc
        filled += len(acc)
    return out


def _truncated_normal(rng: np.random.Generator, n: int, mean: float, std: float) -> np.ndarray:
    """N(mean, std) conditioned on >= 0 (rejection; std == 0 gives the mean)."""
    if std <= 0:
        return np.full(n, max(mean, 0.0))
    out = rng.normal(mean, std, n)
    for _ in range(1000):
        bad = out < 0
        if not bad.any():
            return out
        out[bad] = rng.normal(mean, std, int(bad.sum()))
    return np.maximum(out, 0.0)


def _kept(count: int, fraction: float, rng: np.random.Generator, minimum: int = 0) -> np.ndarray:
    """Sorted indices of the first max(minimum, round(fraction * count)) of a random
    permutation of range(count) (so smaller fractions give subsets)."""
    order = rng.permutation(count)
    k = min(count, max(minimum, int(round(fraction * count))))
    return np.sort(order[:k])


# ---------------------------------------------------------------------------------------------
# The model
# ---------------------------------------------------------------------------------------------


@dataclass
class _FiberSet:
    ply: np.ndarray        # (F,) int
    rest: np.ndarray       # (F,) R_j as a fraction of R_ply
    theta0: np.ndarray     # (F,)
    theta_mig: np.ndarray  # (F,)
    staple_offset: np.ndarray  # (F,)


def _fiber_set(params: YarnParams, seed_offset: int) -> _FiberSet:
    n = params.fiber_count
    rng = _rng(params.seed, seed_offset, _STREAM_FIBERS)
    eps, beta = params.density_profile
    rest = _sample_rest_radius(rng, n, eps, beta)
    theta0 = rng.random(n) * _TWO_PI
    theta_mig = rng.random(n) * _TWO_PI
    staple = rng.random(n) * params.staple_length
    ply = np.repeat(np.arange(params.plies), params.fibers_per_ply)
    return _FiberSet(ply, rest, theta0, theta_mig, staple)


def _ply_angle(params: YarnParams, ply: Any, s: Any) -> np.ndarray:
    """phi_i(s), eq. Y2."""
    return _TWO_PI * (np.asarray(ply) / params.plies + params.ply_twist * np.asarray(s))


def _migrating(params: YarnParams) -> bool:
    return params.migration[0] != params.migration[1]


def _fiber_offset(params: YarnParams, rest: Any, theta0: Any, theta_mig: Any, s: Any
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Fiber offset from its ply centre in the ply frame (radial, tangential), eqs. Y4-Y6
    before the rotation by phi: (e_N r cos theta, e_T r sin theta)."""
    theta = theta0 + _TWO_PI * params.fiber_twist * s
    rmin, rmax = params.migration
    if _migrating(params):
        mig = rmin + (rmax - rmin) * 0.5 * (
            np.cos(_TWO_PI * abs(params.fiber_twist) * s / params.migration_period + theta_mig) + 1.0)
    else:
        mig = rmin
    r = rest * params.ply_radius * mig
    e_n, e_t = params.ply_compression
    return e_n * r * np.cos(theta), e_t * r * np.sin(theta)


def _to_cross_section(params: YarnParams, phi: np.ndarray, a: np.ndarray, b: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """c_i + Rot(phi) (a, b): yarn cross-section coordinates (eq. Y6)."""
    cp, sp = np.cos(phi), np.sin(phi)
    d = params.ply_distance
    return d * cp + a * cp - b * sp, d * sp + a * sp + b * cp


def _grid_spacing(params: YarnParams, centre: _Centre, samples_per_turn: int) -> float:
    f = abs(params.ply_twist) + abs(params.fiber_twist)
    if _migrating(params):
        f += abs(params.fiber_twist) / params.migration_period
    h = min(centre.length, centre.median_segment)
    if f > 0:
        h = min(h, 1.0 / (samples_per_turn * f))
    if params.staple_length > 0:
        h = min(h, params.staple_length / 4.0)
    return h


def _ply_fibers(params: YarnParams, centre: _Centre, grid: CentreFrames, fs: _FiberSet,
                ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Samples of the kept ply fibers on the grid, cut into staples.

    Eqs. Y1-Y6 separate into per-fiber coefficients times per-sample vectors: with
    U = k (cos phi n + sin phi b), V = k (-sin phi n + cos phi b), W = C + d U (the ply centre),
    A = e_N cos(w s) U + e_T sin(w s) V, B = -e_N sin(w s) U + e_T cos(w s) V (w = 2 pi T_fib)
    and the migration factor c0 + c1 cos(nu s + theta_mig),
        P(s) = W + R_j R_ply (c0 + c1 cos(nu s + theta_mig)) (cos theta_j A + sin theta_j B),
    i.e. one (fibers x 6) @ (6 x 3M) matrix product per ply (2 rows without migration).

    Returns (samples (P, 3), counts, fiber id per curve, arclength per point, ply centres
    (plies, M, 3)).
    """
    s = grid.s
    m = len(s)
    k = len(ids)
    pts = np.empty((k, m, 3))
    rmin, rmax = params.migration
    c0, c1 = 0.5 * (rmin + rmax), 0.5 * (rmax - rmin)
    e_n, e_t = params.ply_compression
    om = _TWO_PI * params.fiber_twist * s
    cw, sw = np.cos(om)[:, None], np.sin(om)[:, None]
    sc = grid.scale[:, None]
    nu = _TWO_PI * abs(params.fiber_twist) / params.migration_period * s
    cnu, snu = np.cos(nu)[:, None], np.sin(nu)[:, None]
    migrating = _migrating(params) and c1 != 0.0
    ply_of = fs.ply[ids]
    centres = np.empty((params.plies, m, 3))
    for i in range(params.plies):
        phi = _ply_angle(params, i, s)
        cp, sp = np.cos(phi)[:, None], np.sin(phi)[:, None]
        U = sc * (cp * grid.normal + sp * grid.binormal)
        V = sc * (cp * grid.binormal - sp * grid.normal)
        W = grid.position + params.ply_distance * U
        centres[i] = W
        sel = np.flatnonzero(ply_of == i)
        if len(sel) == 0:
            continue
        A = e_n * cw * U + e_t * sw * V
        B = e_t * cw * V - e_n * sw * U
        f = ids[sel]
        rr = fs.rest[f] * params.ply_radius
        ct, st = rr * np.cos(fs.theta0[f]), rr * np.sin(fs.theta0[f])
        if migrating:
            cm, sm = np.cos(fs.theta_mig[f]), np.sin(fs.theta_mig[f])
            coef = np.stack([c0 * ct, c0 * st, c1 * cm * ct, c1 * cm * st,
                             -c1 * sm * ct, -c1 * sm * st], axis=1)
            basis = np.stack([A, B, cnu * A, cnu * B, snu * A, snu * B]).reshape(6, 3 * m)
        else:
            coef = np.stack([rmin * ct, rmin * st], axis=1)
            basis = np.stack([A, B]).reshape(2, 3 * m)
        lo, hi = int(sel[0]), int(sel[-1]) + 1   # ids are sorted, so a ply's fibers are contiguous
        out = pts[lo:hi].reshape(hi - lo, 3 * m)
        np.matmul(coef, basis, out=out)
        out += W.reshape(1, 3 * m)
    pts = pts.reshape(-1, 3)
    arclen = np.tile(s, k)
    if params.staple_length > 0 and k > 0:
        # Cuts at off_j + q l (q = 0, 1, ...): a piece starts at the first sample at or after a cut.
        l = params.staple_length
        nq = int(math.ceil(centre.length / l)) + 1
        cuts = fs.staple_offset[ids, None] + l * np.arange(nq)[None, :]
        bounds = np.concatenate([np.zeros((k, 1), np.int64), np.searchsorted(s, cuts),
                                 np.full((k, 1), m, np.int64)], axis=1)
        counts = np.diff(bounds, axis=1)                      # (k, nq + 1), zeros included
        starts = (bounds[:, :-1] + (np.arange(k) * m)[:, None]).reshape(-1)
        counts = counts.reshape(-1)
        fiber_of_curve = np.repeat(ids, nq + 1)
        nonempty = counts > 0
        starts, counts, fiber_of_curve = starts[nonempty], counts[nonempty], fiber_of_curve[nonempty]
        good = counts >= 2
        if not good.all():
            keep_pt = np.repeat(good, counts)
            pts, arclen = pts[keep_pt], arclen[keep_pt]
            counts, fiber_of_curve = counts[good], fiber_of_curve[good]
    else:
        counts = np.full(k, m, np.int64)
        fiber_of_curve = ids.astype(np.int64)
    return pts, counts.astype(np.int64), fiber_of_curve.astype(np.int64), arclen, centres


def _hairs(params: YarnParams, centre: _Centre, h: float, fraction: float, seed_offset: int):
    L = centre.length
    rng = _rng(params.seed, seed_offset, _STREAM_HAIR)
    n = int(rng.poisson(params.hair_density * L)) if params.hair_density > 0 else 0
    if n == 0:
        return None
    N = params.plies
    ply = rng.integers(0, N, n)
    s_exit = rng.random(n) * L
    if N > 1:
        theta = (rng.random(n) * 2.0 - 1.0) * (math.pi / 3.0)
    else:
        theta = rng.random(n) * _TWO_PI
    length = _truncated_normal(rng, n, *params.hair_length)
    alpha = np.radians(15.0 + 30.0 * rng.random(n))
    sign = np.where(rng.random(n) < 0.5, -1.0, 1.0)
    depth = (0.2 + 0.4 * rng.random(n)) * params.ply_radius
    kept = _kept(n, fraction, rng)
    if len(kept) == 0:
        return None
    ply, s_exit, theta, length = ply[kept], s_exit[kept], theta[kept], length[kept]
    alpha, sign, depth = alpha[kept], sign[kept], depth[kept]
    # Exit point on the (compressed) ply boundary, in cross-section coordinates.
    e_n, e_t = params.ply_compression
    phi = _ply_angle(params, ply, s_exit)
    ex, ey = _to_cross_section(params, phi, e_n * params.ply_radius * np.cos(theta),
                               e_t * params.ply_radius * np.sin(theta))
    g = np.stack([ex, ey], -1)
    g = g / np.maximum(np.linalg.norm(g, axis=-1, keepdims=True), 1e-300)
    u_in = depth / np.sin(alpha)                    # along-line length inside the ply
    total = u_in + length
    npts = np.maximum(6, np.ceil(total * np.cos(alpha) / h).astype(np.int64) + 1)
    npts = np.minimum(npts, 4096)
    cidx = np.repeat(np.arange(len(kept)), npts)
    t = (np.arange(len(cidx)) - _curve_offsets(npts)[cidx]) / (npts[cidx] - 1.0)
    u = -u_in[cidx] + t * total[cidx]               # signed distance from the exit point
    s = s_exit[cidx] + sign[cidx] * u * np.cos(alpha[cidx])
    x = ex[cidx] + u * np.sin(alpha[cidx]) * g[cidx, 0]
    y = ey[cidx] + u * np.sin(alpha[cidx]) * g[cidx, 1]
    pos, nrm, bin_, sc = centre.frames(s)
    pts = pos + (sc * x)[:, None] * nrm + (sc * y)[:, None] * bin_
    return pts, npts, np.full(len(kept), -1, np.int64), ply, s


def _loops(params: YarnParams, centre: _Centre, fs: _FiberSet, h: float, fraction: float,
           seed_offset: int):
    L = centre.length
    rng = _rng(params.seed, seed_offset, _STREAM_LOOP)
    n = int(rng.poisson(params.loop_density * L)) if params.loop_density > 0 else 0
    if n == 0:
        return None
    N, fpp, R = params.plies, params.fibers_per_ply, params.ply_radius
    parent = rng.integers(0, N, n) * fpp + rng.integers(0, fpp, n)
    s0 = rng.random(n) * L
    height = _truncated_normal(rng, n, *params.loop_height)
    theta_out = (rng.random(n) * 2.0 - 1.0) * (math.pi / 4.0)
    kept = _kept(n, fraction, rng)
    if len(kept) == 0:
        return None
    parent, s0, height, theta_out = parent[kept], s0[kept], height[kept], theta_out[kept]
    k = len(kept)
    tf = abs(params.fiber_twist)
    lo_span, hi_span = 2.0 * (R + height), 8.0 * (R + height)
    if tf > 0:
        span = np.clip(params.migration_period / (2.0 * tf), lo_span, hi_span)
    else:
        span = 4.0 * (R + height)
    if _migrating(params) and tf > 0:
        # Nearest migration maximum of the parent: 2 pi tf s / P + theta_mig = 2 pi m.
        cyc = params.migration_period / tf
        m = np.round((s0 / cyc) + fs.theta_mig[parent] / _TWO_PI)
        s_c = (m - fs.theta_mig[parent] / _TWO_PI) * cyc
        s_c = np.where((s_c < 0) | (s_c > L), s0, s_c)
    else:
        s_c = s0
    span = np.minimum(span, L)
    s_c = np.clip(s_c, 0.5 * span, L - 0.5 * span)
    npts = np.maximum(13, np.ceil(span / h).astype(np.int64) + 1)
    npts = npts + (npts % 2 == 0)                   # odd: a sample at the loop's middle
    npts = np.minimum(npts, 4097)
    cidx = np.repeat(np.arange(k), npts)
    u = (np.arange(len(cidx)) - _curve_offsets(npts)[cidx]) / (npts[cidx] - 1.0)
    s = s_c[cidx] + (u - 0.5) * span[cidx]
    p = parent[cidx]
    ply = fs.ply[parent]
    a, b = _fiber_offset(params, fs.rest[p], fs.theta0[p], fs.theta_mig[p], s)
    e_n, e_t = params.ply_compression
    if N == 1:
        theta_o = fs.theta0[parent] + _TWO_PI * params.fiber_twist * s_c
    else:
        theta_o = theta_out
    dx, dy = e_n * np.cos(theta_o), e_t * np.sin(theta_o)
    dn = np.hypot(dx, dy)
    peak = R * dn + height                          # D + H (eq. Y7)
    pa, pb = (peak * dx / dn)[cidx], (peak * dy / dn)[cidx]
    w = np.sin(np.pi * u) ** 2
    phi = _ply_angle(params, ply[cidx], s)
    x, y = _to_cross_section(params, phi, (1 - w) * a + w * pa, (1 - w) * b + w * pb)
    pos, nrm, bin_, sc = centre.frames(s)
    pts = pos + (sc * x)[:, None] * nrm + (sc * y)[:, None] * bin_
    return pts, npts, parent.astype(np.int64), ply, s


def expand_yarn(centre: Any, radius_scale: Any = 1.0, params: YarnParams | None = None, *,
                fiber_fraction: float = 1.0, samples_per_turn: int = 12,
                seed_offset: int = 0) -> ExpandedFibers:
    """Expand one yarn centre line into fiber curves (Zhao et al. 2016; module doc, eqs. Y1-Y7).

    ``centre``: (N, 3) polyline of the yarn centre in world space. ``radius_scale``: scale of
    the whole cross section (eq. Y1), a scalar or one value per centre point (for example the
    authored width over ``2 * params.yarn_radius``; flyaway heights and lengths scale with it
    radially, the axial extents of flyaways do not). ``fiber_fraction`` in (0, 1] keeps that
    fraction of the fibers and flyaways, always a subset of larger fractions.
    ``samples_per_turn``: samples per turn of the fastest helix component. The result depends
    only on (params, centre, radius_scale, samples_per_turn, seed, seed_offset) and the
    fraction. ``expand_yarn(centre, params)`` is accepted for radius_scale 1.
    """
    if params is None and isinstance(radius_scale, YarnParams):
        params, radius_scale = radius_scale, 1.0
    if not isinstance(params, YarnParams):
        raise TypeError(f"params must be a YarnParams, got {type(params).__name__}")
    if not (_is_real(fiber_fraction) and 0.0 < fiber_fraction <= 1.0):
        raise YarnError(f"fiber_fraction must be in (0, 1], got {fiber_fraction!r}",
                        params.prim_path or None)
    if int(samples_per_turn) != samples_per_turn or samples_per_turn < 3:
        raise YarnError(f"samples_per_turn must be an integer >= 3, got {samples_per_turn!r}",
                        params.prim_path or None)
    c = _Centre(centre, radius_scale)
    h = _grid_spacing(params, c, int(samples_per_turn))
    m = max(2, int(math.ceil(c.length / h - 1e-9)) + 1)
    s = np.linspace(0.0, c.length, m)
    h = c.length / (m - 1)
    grid = c.build_grid(s)

    fs = _fiber_set(params, seed_offset)
    ids = _kept(params.fiber_count, float(fiber_fraction),
                _rng(params.seed, seed_offset, _STREAM_ORDER), minimum=1)
    parts = []
    pts, counts, fib, arc, ply_centres = _ply_fibers(params, c, grid, fs, ids)
    parts.append((pts, counts, np.full(len(counts), KIND_PLY), fs.ply[fib], fib, arc))
    for kind, res in ((KIND_HAIR, _hairs(params, c, h, float(fiber_fraction), seed_offset)),
                      (KIND_LOOP, _loops(params, c, fs, h, float(fiber_fraction), seed_offset))):
        if res is not None:
            p_, n_, f_, ply_, s_ = res
            parts.append((p_, n_, np.full(len(n_), kind), ply_, f_, s_))

    points = parts[0][0] if len(parts) == 1 else np.concatenate([p[0] for p in parts])
    counts = np.concatenate([p[1] for p in parts]).astype(np.int64)
    # One correction step towards interpolation (module doc): P = X - (second difference) / 6.
    corr = _second_difference(points, counts)
    corr *= 1.0 / 6.0
    points -= corr
    del corr

    return ExpandedFibers(
        points=points,
        counts=counts,
        kind=np.concatenate([p[2] for p in parts]).astype(np.int8),
        ply=np.concatenate([p[3] for p in parts]).astype(np.int64),
        fiber=np.concatenate([p[4] for p in parts]).astype(np.int64),
        arclength=np.concatenate([p[5] for p in parts]),
        ply_centres=ply_centres,
        grid_s=s,
    )
