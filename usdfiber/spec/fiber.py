"""The physical parameters of a fiber prim, resolved and unit-converted.

:class:`FiberParams` reads every ``fiber:*`` value of a prim with FiberAPI (composition
applied: class inheritance, variants, references) at one time code and derives what the
baker and the renderer need:

* effective index of refraction ``eta`` (``fiber:ior:effective``: mean, parallel or
  perpendicular);
* roughness ``beta`` in degrees: ``arctan(Ra / l)`` or the authored beta (paper Sec. 3.1);
* the dye's extinction per gram per linear Rec.709 channel in L mg^-1 cm^-1;
* the absorption coefficient ``mu_a`` per channel in 1/um:
  ``mu_a = rho * (zeta / 100) * epsilon`` with rho in g/cm^3 -> g/L (x 1000),
  epsilon in L mg^-1 cm^-1 -> L g^-1 cm^-1 (x 1000), 1/cm -> 1/um (x 1e-4);
* the cross-section source (built-in family or user loops), the variant count, cuticle and
  seed.

Spectral extinction ("spectrum" source) is reduced to Rec.709 channels by
:func:`usdfiber.colour.spectrum_to_rec709` (a weighted average over the CIE 1931 observer).

Attribute names come from :mod:`usdfiber.spec.attributes`. Values that cannot be resolved
raise :class:`FiberParamsError` (a :class:`~usdfiber.errors.PrimError`: file, prim, attribute
and what was expected).
"""
from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass
from typing import Any

from pxr import Sdf, Usd

from usdfiber.colour import spectrum_to_rec709
from usdfiber.errors import PrimError
from usdfiber.presets import AUTO_PROFILE_FAMILY
from usdfiber.spec.attributes import Fiber, Profile, spectrum_coverage


class FiberParamsError(PrimError):
    """A fiber value that cannot be resolved (a :class:`~usdfiber.errors.PrimError`)."""


def mu_a_per_um(density_g_cm3: float, depth_of_shade_percent: float, epsilon_l_mg_cm: float) -> float:
    """Absorption coefficient in 1/um: mu_a = kappa * epsilon, kappa = rho * zeta (Sec. 3.1)."""
    kappa_g_per_l = density_g_cm3 * 1000.0 * (depth_of_shade_percent / 100.0)  # g/cm^3 -> g/L
    epsilon_l_g_cm = epsilon_l_mg_cm * 1000.0                                  # per mg -> per g
    mu_a_per_cm = kappa_g_per_l * epsilon_l_g_cm
    return mu_a_per_cm * 1e-4                                                  # 1/cm -> 1/um


# Units of the values in FiberParams.to_dict() / geometry_inputs().
UNITS: dict[str, str] = {
    "diameter": "um",
    "density": "g/cm^3",
    "ior_parallel": "1",
    "ior_perpendicular": "1",
    "eta": "1",
    "ra": "nm",
    "profile_length": "nm",
    "beta": "deg",
    "cuticle_tilt": "deg",
    "cuticle_height": "um",
    "cuticle_spacing": "um",
    "cuticle_height_rel": "fraction of diameter",
    "cuticle_spacing_rel": "fraction of diameter",
    "extinction": "L mg^-1 cm^-1 (linear Rec.709 R, G, B)",
    "depth_of_shade": "% on weight of fiber",
    "mu_a": "1/um (linear Rec.709 R, G, B)",
    "rotation": "deg",
    "profile_points": "um",
}


@dataclass(frozen=True)
class UserProfile:
    """One user cross section (FiberProfileAPI prim): its loops in um."""

    path: str
    loops: tuple[tuple[tuple[float, float], ...], ...]
    smooth: bool


@dataclass(frozen=True)
class FiberParams:
    """Every fiber value of a prim at one time code, resolved (see module docstring)."""

    prim_path: str
    time: float | None                      # None: the default time code
    kind: str
    profile: str                            # fiber:profile as authored ("auto", family, "user")
    profile_family: str                     # resolved built-in family, or "user"
    user_profiles: tuple[UserProfile, ...]  # fiber:profile:sources when "user", else ()
    variant_count: int                      # cross-section variants (tables) used
    diameter: float                         # um
    density: float                          # g/cm^3
    ior_parallel: float
    ior_perpendicular: float
    ior_effective: str                      # "mean" | "parallel" | "perpendicular"
    eta: float                              # the isotropic index traced
    roughness_source: str                   # "ra" | "beta"
    ra: float                               # nm
    profile_length: float                   # nm
    beta: float                             # degrees, effective
    cuticle_tilt: float                     # degrees
    cuticle_height: float                   # um; 0 = no cuticle
    cuticle_spacing: float                  # um
    dye_class: str
    extinction_source: str
    extinction: tuple[float, float, float]  # L mg^-1 cm^-1, effective (0 when dye_class none)
    depth_of_shade: float                   # percent
    mu_a: tuple[float, float, float]        # 1/um
    rotation_random: bool
    rotation: float                         # degrees
    seed: int
    table: str                              # fiber:table asset path ("" when unset)

    # ---------------------------------------------------------------- construction
    @classmethod
    def from_prim(cls, prim: Usd.Prim, time: Usd.TimeCode | float = Usd.TimeCode.Default()) -> "FiberParams":
        """Resolve the FiberAPI values of ``prim`` at ``time``.

        Raises FiberParamsError (naming prim and attribute) when a value cannot be resolved.
        """
        if not isinstance(time, Usd.TimeCode):
            time = Usd.TimeCode(time)
        path = str(prim.GetPath()) if prim else "<invalid prim>"
        if not prim or not prim.IsValid():
            raise FiberParamsError(None, path, None, "not a valid prim")
        if not prim.HasAPI("FiberAPI"):
            raise FiberParamsError.at(prim, None, "has no FiberAPI (apply it or inherit a fiber class)")

        def get(name: str) -> Any:
            attr = prim.GetAttribute(name)
            value = attr.Get(time) if attr else None
            if value is None:
                raise FiberParamsError.at(prim, name, "has no value (and no schema fallback)")
            return value

        def num(name: str, *, positive: bool = False, nonneg: bool = False, minimum: float | None = None) -> float:
            v = float(get(name))
            if not math.isfinite(v):
                raise FiberParamsError.at(prim, name, f"is not finite ({v})")
            if positive and v <= 0:
                raise FiberParamsError.at(prim, name, f"must be > 0, got {v:g}")
            if nonneg and v < 0:
                raise FiberParamsError.at(prim, name, f"must be >= 0, got {v:g}")
            if minimum is not None and v < minimum:
                raise FiberParamsError.at(prim, name, f"must be >= {minimum:g}, got {v:g}")
            return v

        kind = str(get(Fiber.KIND))
        profile = str(get(Fiber.PROFILE))

        # Cross section.
        user_profiles: tuple[UserProfile, ...] = ()
        if profile == "auto":
            family = AUTO_PROFILE_FAMILY.get(kind)
            if family is None:
                raise FiberParamsError.at(prim, Fiber.PROFILE,
                    f'"auto" has no built-in family for fiber:kind "{kind}"; name a family or "user"')
        else:
            family = profile
        if family == "user":
            user_profiles = _read_user_profiles(prim, path)
            variant_count = len(user_profiles)
        elif family == "round":
            variant_count = 1  # a circle is rotation invariant: one variant is exact
        else:
            variant_count = int(get(Fiber.PROFILE_VARIANT_COUNT))
            if variant_count < 1:
                raise FiberParamsError.at(prim, Fiber.PROFILE_VARIANT_COUNT, f"must be >= 1, got {variant_count}")

        diameter = num(Fiber.DIAMETER, positive=True)
        density = num(Fiber.DENSITY, positive=True)
        ior_par = num(Fiber.IOR_PARALLEL, minimum=1.0)
        ior_perp = num(Fiber.IOR_PERPENDICULAR, minimum=1.0)
        ior_eff = str(get(Fiber.IOR_EFFECTIVE))
        if ior_eff == "mean":
            eta = 0.5 * (ior_par + ior_perp)
        elif ior_eff == "parallel":
            eta = ior_par
        elif ior_eff == "perpendicular":
            eta = ior_perp
        else:
            raise FiberParamsError.at(prim, Fiber.IOR_EFFECTIVE, f'unknown token "{ior_eff}"')

        rsrc = str(get(Fiber.ROUGHNESS_SOURCE))
        ra = num(Fiber.ROUGHNESS_RA, nonneg=True)
        plen = num(Fiber.ROUGHNESS_PROFILE_LENGTH)
        if rsrc == "ra":
            if plen <= 0:
                raise FiberParamsError.at(prim, Fiber.ROUGHNESS_PROFILE_LENGTH,
                                       f"must be > 0 to compute beta = arctan(Ra / l), got {plen:g}")
            beta = math.degrees(math.atan(ra / plen))
        elif rsrc == "beta":
            beta = num(Fiber.ROUGHNESS_BETA, nonneg=True)
        else:
            raise FiberParamsError.at(prim, Fiber.ROUGHNESS_SOURCE, f'unknown token "{rsrc}"')

        cut_tilt = num(Fiber.CUTICLE_TILT)
        cut_height = num(Fiber.CUTICLE_HEIGHT, nonneg=True)
        cut_spacing = num(Fiber.CUTICLE_SPACING)
        if cut_height > 0 and cut_spacing <= 0:
            raise FiberParamsError.at(prim, Fiber.CUTICLE_SPACING, f"must be > 0 with cuticles, got {cut_spacing:g}")

        dye_class = str(get(Fiber.DYE_CLASS))
        ext_src = str(get(Fiber.DYE_EXTINCTION_SOURCE))
        dos = num(Fiber.DYE_DEPTH_OF_SHADE, nonneg=True)
        if dye_class == "none":
            extinction = (0.0, 0.0, 0.0)
        else:
            extinction = _read_extinction(prim, path, ext_src, time, get)
        mu_a = tuple(mu_a_per_um(density, dos, e) for e in extinction)

        table = get(Fiber.TABLE)
        table_path = table.path if isinstance(table, Sdf.AssetPath) else str(table)

        return cls(
            prim_path=path,
            time=None if time.IsDefault() else float(time.GetValue()),
            kind=kind, profile=profile, profile_family=family, user_profiles=user_profiles,
            variant_count=variant_count, diameter=diameter, density=density,
            ior_parallel=ior_par, ior_perpendicular=ior_perp, ior_effective=ior_eff, eta=eta,
            roughness_source=rsrc, ra=ra, profile_length=plen, beta=beta,
            cuticle_tilt=cut_tilt, cuticle_height=cut_height, cuticle_spacing=cut_spacing,
            dye_class=dye_class, extinction_source=ext_src, extinction=extinction,  # type: ignore[arg-type]
            depth_of_shade=dos, mu_a=mu_a,  # type: ignore[arg-type]
            rotation_random=bool(get(Fiber.ROTATION_RANDOM)), rotation=num(Fiber.ROTATION),
            seed=int(get(Fiber.SEED)), table=table_path,
        )

    # ---------------------------------------------------------------- derived
    @property
    def has_cuticle(self) -> bool:
        return self.cuticle_height > 0.0

    @property
    def roughness_alpha(self) -> float:
        """Beckmann width alpha = tan(beta)."""
        return math.tan(math.radians(self.beta))

    def geometry_inputs(self) -> dict[str, Any]:
        """The values that change traced photon paths, in canonical form (with units).

        Dye, depth of shade and diameter are left out: they only scale absorption. Floats are
        rounded to 6 decimals (float32 attributes carry ~7 digits), so the same physical value
        authored two ways (mean of two indices vs. one explicit index) gives the same key.
        Cuticle height and spacing are relative to the diameter because the trace is done
        at unit size; they appear only when the fiber has cuticles. The seed matters only
        for built-in families with random variants.
        """
        def r(x: float) -> float:
            return round(float(x), 6) + 0.0  # + 0.0: no "-0.0" in the JSON

        d: dict[str, Any] = {"profile_family": self.profile_family}
        if self.profile_family == "user":
            d["user_profiles"] = [
                {"loops": [[[r(x), r(y)] for x, y in loop] for loop in up.loops], "smooth": up.smooth}
                for up in self.user_profiles
            ]
        else:
            d["variant_count"] = self.variant_count
            if self.profile_family != "round":
                d["seed"] = self.seed
        d["eta"] = r(self.eta)
        d["beta"] = r(self.beta)
        if self.has_cuticle:
            d["cuticle"] = {
                "tilt": r(self.cuticle_tilt),
                "height_rel": r(self.cuticle_height / self.diameter),
                "spacing_rel": r(self.cuticle_spacing / self.diameter),
            }
        d["units"] = {"eta": UNITS["eta"], "beta": UNITS["beta"], "cuticle.tilt": UNITS["cuticle_tilt"],
                      "cuticle.height_rel": UNITS["cuticle_height_rel"],
                      "cuticle.spacing_rel": UNITS["cuticle_spacing_rel"],
                      "user_profiles.loops": UNITS["profile_points"]}
        return d

    def geometry_key(self) -> str:
        """sha256 hex digest of the canonical JSON of :meth:`geometry_inputs`."""
        blob = json.dumps(self.geometry_inputs(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(blob.encode("utf-8")).hexdigest()

    def to_dict(self) -> dict[str, Any]:
        """All values as plain JSON-able Python types, plus a ``units`` map."""
        d = asdict(self)
        d["user_profiles"] = [
            {"path": up.path, "loops": [[list(p) for p in loop] for loop in up.loops], "smooth": up.smooth}
            for up in self.user_profiles
        ]
        d["extinction"] = list(self.extinction)
        d["mu_a"] = list(self.mu_a)
        d["geometry_key"] = self.geometry_key()
        d["units"] = dict(UNITS)
        return d


# -------------------------------------------------------------------- helpers
def _read_extinction(prim: Usd.Prim, path: str, source: str, time: Usd.TimeCode, get) -> tuple[float, float, float]:
    def finite_nonneg(name: str, vals) -> tuple[float, ...]:
        out = tuple(float(v) for v in vals)
        if any(not math.isfinite(v) or v < 0 for v in out):
            raise FiberParamsError.at(prim, name, f"values must be finite and >= 0, got {list(out)}")
        return out

    if source == "perGram":
        return finite_nonneg(Fiber.DYE_EXTINCTION, get(Fiber.DYE_EXTINCTION))  # type: ignore[return-value]
    if source == "molar":
        eps_m = finite_nonneg(Fiber.DYE_MOLAR_EXTINCTION, get(Fiber.DYE_MOLAR_EXTINCTION))
        w_m = float(get(Fiber.DYE_MOLAR_MASS))
        if not (math.isfinite(w_m) and w_m > 0):
            raise FiberParamsError.at(prim, Fiber.DYE_MOLAR_MASS,
                                   f'must be > 0 g/mol with extinctionSource "molar", got {w_m:g}')
        # epsilon_m [L mol^-1 cm^-1] / w_m [g mol^-1] = [L g^-1 cm^-1]; / 1000 -> [L mg^-1 cm^-1]
        return tuple(e / w_m / 1000.0 for e in eps_m)  # type: ignore[return-value]
    if source == "spectrum":
        wl_attr = prim.GetAttribute(Fiber.DYE_SPECTRUM_WAVELENGTHS)
        val_attr = prim.GetAttribute(Fiber.DYE_SPECTRUM_VALUES)
        wl = list(wl_attr.Get(time) or []) if wl_attr else []
        vals = list(val_attr.Get(time) or []) if val_attr else []
        if len(wl) < 2:
            raise FiberParamsError.at(prim, Fiber.DYE_SPECTRUM_WAVELENGTHS,
                                   'needs at least 2 wavelengths with extinctionSource "spectrum"')
        if len(vals) != len(wl):
            raise FiberParamsError.at(prim, Fiber.DYE_SPECTRUM_VALUES,
                                   f"has {len(vals)} values for {len(wl)} wavelengths")
        wl = [float(w) for w in wl]
        if any(b <= a for a, b in zip(wl, wl[1:])) or not all(math.isfinite(w) for w in wl):
            raise FiberParamsError.at(prim, Fiber.DYE_SPECTRUM_WAVELENGTHS, "must be finite and strictly increasing")
        cover = spectrum_coverage()
        if wl[0] > cover.lo or wl[-1] < cover.hi:
            raise FiberParamsError.at(prim, Fiber.DYE_SPECTRUM_WAVELENGTHS,
                                      f"must cover {cover.lo:g}-{cover.hi:g} nm, covers "
                                      f"{wl[0]:g}-{wl[-1]:g} nm")
        v = list(finite_nonneg(Fiber.DYE_SPECTRUM_VALUES, vals))
        return spectrum_to_rec709(wl, v)
    raise FiberParamsError.at(prim, Fiber.DYE_EXTINCTION_SOURCE, f'unknown token "{source}"')


def _read_user_profiles(prim: Usd.Prim, path: str) -> tuple[UserProfile, ...]:
    rel_name = Fiber.PROFILE_SOURCES
    rel = prim.GetRelationship(rel_name)
    targets = rel.GetForwardedTargets() if rel else []
    if not targets:
        raise FiberParamsError.at(prim, rel_name, 'fiber:profile is "user" but no profile prims are targeted')
    stage = prim.GetStage()
    out = []
    for t in targets:
        tp = stage.GetPrimAtPath(t)
        if not tp or not tp.HasAPI("FiberProfileAPI"):
            raise FiberParamsError.at(prim, rel_name, f"target {t} is not a prim with FiberProfileAPI")
        pts = tp.GetAttribute(Profile.POINTS).Get() or []
        counts = [int(c) for c in (tp.GetAttribute(Profile.LOOP_VERTEX_COUNTS).Get() or [])]
        if not counts or any(c < 3 for c in counts) or sum(counts) != len(pts):
            raise FiberParamsError.at(
                tp, Profile.LOOP_VERTEX_COUNTS,
                f"counts {counts} must each be >= 3 and sum to the {len(pts)} points (profile of {path})")
        loops, i = [], 0
        for c in counts:
            loops.append(tuple((float(p[0]), float(p[1])) for p in pts[i:i + c]))
            i += c
        out.append(UserProfile(str(t), tuple(loops), bool(tp.GetAttribute(Profile.SMOOTH).Get())))
    return tuple(out)


__all__ = ["FiberParams", "FiberParamsError", "UNITS", "UserProfile", "mu_a_per_um"]
