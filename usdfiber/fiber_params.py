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

Spectral extinction ("spectrum" source) is reduced to Rec.709 channels as a weighted average:
``eps_c = sum_l eps(l) w_c(l) / sum_l w_c(l)`` with ``w_c = max(0, (M_709 . xyz_bar)(l)_c)``,
the CIE 1931 2-degree colour matching functions (10 nm, 380-780 nm, embedded below) taken to
linear Rec.709 by the XYZ -> linear sRGB (D65) matrix and clipped at zero. A flat spectrum gives
equal channels. The curve is interpolated linearly and held constant beyond its ends.

This module only imports the standard library and ``pxr``.
"""
from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass
from typing import Any

from pxr import Sdf, Usd

from usdfiber.presets import AUTO_PROFILE_FAMILY


class FiberParamsError(ValueError):
    """A fiber value that cannot be resolved; names the prim and the attribute."""

    def __init__(self, prim: str, attribute: str | None, reason: str) -> None:
        self.prim = prim
        self.attribute = attribute
        where = f"{prim}.{attribute}" if attribute else prim
        super().__init__(f"{where}: {reason}")


# CIE 1931 2-degree colour matching functions, 380..780 nm every 10 nm (x_bar, y_bar, z_bar).
_CIE_START_NM = 380.0
_CIE_STEP_NM = 10.0
_CIE_1931 = (
    (0.001368, 0.000039, 0.006450), (0.004243, 0.000120, 0.020050),
    (0.014310, 0.000396, 0.067850), (0.043510, 0.001210, 0.207400),
    (0.134380, 0.004000, 0.645600), (0.283900, 0.011600, 1.385600),
    (0.348280, 0.023000, 1.747060), (0.336200, 0.038000, 1.772110),
    (0.290800, 0.060000, 1.669200), (0.195360, 0.090980, 1.287640),
    (0.095640, 0.139020, 0.812950), (0.032010, 0.208020, 0.465180),
    (0.004900, 0.323000, 0.272000), (0.009300, 0.503000, 0.158200),
    (0.063270, 0.710000, 0.078250), (0.165500, 0.862000, 0.042160),
    (0.290400, 0.954000, 0.020300), (0.433450, 0.994950, 0.008750),
    (0.594500, 0.995000, 0.003900), (0.762100, 0.952000, 0.002100),
    (0.916300, 0.870000, 0.001650), (1.026300, 0.757000, 0.001100),
    (1.062200, 0.631000, 0.000800), (1.002600, 0.503000, 0.000340),
    (0.854450, 0.381000, 0.000190), (0.642400, 0.265000, 0.000050),
    (0.447900, 0.175000, 0.000020), (0.283500, 0.107000, 0.000000),
    (0.164900, 0.061000, 0.000000), (0.087400, 0.032000, 0.000000),
    (0.046770, 0.017000, 0.000000), (0.022700, 0.008210, 0.000000),
    (0.011359, 0.004102, 0.000000), (0.005790, 0.002091, 0.000000),
    (0.002899, 0.001047, 0.000000), (0.001440, 0.000520, 0.000000),
    (0.000690, 0.000249, 0.000000), (0.000332, 0.000120, 0.000000),
    (0.000166, 0.000060, 0.000000), (0.000083, 0.000030, 0.000000),
    (0.000042, 0.000015, 0.000000),
)
# CIE XYZ -> linear Rec.709 / sRGB primaries, D65 white (IEC 61966-2-1).
_XYZ_TO_REC709 = (
    (3.2404542, -1.5371385, -0.4985314),
    (-0.9692660, 1.8760108, 0.0415560),
    (0.0556434, -0.2040259, 1.0572252),
)


def _rec709_weights() -> list[tuple[float, float, float]]:
    out = []
    for xyz in _CIE_1931:
        out.append(tuple(max(0.0, sum(m * v for m, v in zip(row, xyz))) for row in _XYZ_TO_REC709))
    return out  # type: ignore[return-value]


_REC709_WEIGHTS = _rec709_weights()


def _interp(x: float, xs: list[float], ys: list[float]) -> float:
    """Piecewise-linear interpolation, constant beyond the ends (like numpy.interp)."""
    if x <= xs[0]:
        return ys[0]
    if x >= xs[-1]:
        return ys[-1]
    lo, hi = 0, len(xs) - 1
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if xs[mid] <= x:
            lo = mid
        else:
            hi = mid
    t = (x - xs[lo]) / (xs[hi] - xs[lo])
    return ys[lo] + t * (ys[hi] - ys[lo])


def spectrum_to_rec709(wavelengths_nm: list[float], values: list[float]) -> tuple[float, float, float]:
    """Reduce a spectral extinction curve to linear Rec.709 channels (see module docstring)."""
    sums = [0.0, 0.0, 0.0]
    norms = [0.0, 0.0, 0.0]
    for i, w in enumerate(_REC709_WEIGHTS):
        eps = _interp(_CIE_START_NM + i * _CIE_STEP_NM, wavelengths_nm, values)
        for c in range(3):
            sums[c] += eps * w[c]
            norms[c] += w[c]
    return (sums[0] / norms[0], sums[1] / norms[1], sums[2] / norms[2])


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
            raise FiberParamsError(path, None, "not a valid prim")
        if not prim.HasAPI("FiberAPI"):
            raise FiberParamsError(path, None, "has no FiberAPI (apply it or inherit a fiber class)")

        def get(name: str) -> Any:
            attr = prim.GetAttribute(name)
            value = attr.Get(time) if attr else None
            if value is None:
                raise FiberParamsError(path, name, "has no value (and no schema fallback)")
            return value

        def num(name: str, *, positive: bool = False, nonneg: bool = False, minimum: float | None = None) -> float:
            v = float(get(name))
            if not math.isfinite(v):
                raise FiberParamsError(path, name, f"is not finite ({v})")
            if positive and v <= 0:
                raise FiberParamsError(path, name, f"must be > 0, got {v:g}")
            if nonneg and v < 0:
                raise FiberParamsError(path, name, f"must be >= 0, got {v:g}")
            if minimum is not None and v < minimum:
                raise FiberParamsError(path, name, f"must be >= {minimum:g}, got {v:g}")
            return v

        kind = str(get("fiber:kind"))
        profile = str(get("fiber:profile"))

        # Cross section.
        user_profiles: tuple[UserProfile, ...] = ()
        if profile == "auto":
            family = AUTO_PROFILE_FAMILY.get(kind)
            if family is None:
                raise FiberParamsError(
                    path, "fiber:profile",
                    f'"auto" has no built-in family for fiber:kind "{kind}"; name a family or "user"')
        else:
            family = profile
        if family == "user":
            user_profiles = _read_user_profiles(prim, path)
            variant_count = len(user_profiles)
        elif family == "round":
            variant_count = 1  # a circle is rotation invariant: one variant is exact
        else:
            variant_count = int(get("fiber:profile:variantCount"))
            if variant_count < 1:
                raise FiberParamsError(path, "fiber:profile:variantCount", f"must be >= 1, got {variant_count}")

        diameter = num("fiber:diameter", positive=True)
        density = num("fiber:density", positive=True)
        ior_par = num("fiber:ior:parallel", minimum=1.0)
        ior_perp = num("fiber:ior:perpendicular", minimum=1.0)
        ior_eff = str(get("fiber:ior:effective"))
        if ior_eff == "mean":
            eta = 0.5 * (ior_par + ior_perp)
        elif ior_eff == "parallel":
            eta = ior_par
        elif ior_eff == "perpendicular":
            eta = ior_perp
        else:
            raise FiberParamsError(path, "fiber:ior:effective", f'unknown token "{ior_eff}"')

        rsrc = str(get("fiber:roughness:source"))
        ra = num("fiber:roughness:ra", nonneg=True)
        plen = num("fiber:roughness:profileLength")
        if rsrc == "ra":
            if plen <= 0:
                raise FiberParamsError(path, "fiber:roughness:profileLength",
                                       f"must be > 0 to compute beta = arctan(Ra / l), got {plen:g}")
            beta = math.degrees(math.atan(ra / plen))
        elif rsrc == "beta":
            beta = num("fiber:roughness:beta", nonneg=True)
        else:
            raise FiberParamsError(path, "fiber:roughness:source", f'unknown token "{rsrc}"')

        cut_tilt = num("fiber:cuticle:tilt")
        cut_height = num("fiber:cuticle:height", nonneg=True)
        cut_spacing = num("fiber:cuticle:spacing")
        if cut_height > 0 and cut_spacing <= 0:
            raise FiberParamsError(path, "fiber:cuticle:spacing", f"must be > 0 with cuticles, got {cut_spacing:g}")

        dye_class = str(get("fiber:dye:class"))
        ext_src = str(get("fiber:dye:extinctionSource"))
        dos = num("fiber:dye:depthOfShade", nonneg=True)
        if dye_class == "none":
            extinction = (0.0, 0.0, 0.0)
        else:
            extinction = _read_extinction(prim, path, ext_src, time, get)
        mu_a = tuple(mu_a_per_um(density, dos, e) for e in extinction)

        table = get("fiber:table")
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
            rotation_random=bool(get("fiber:rotation:random")), rotation=num("fiber:rotation"),
            seed=int(get("fiber:seed")), table=table_path,
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
            raise FiberParamsError(path, name, f"values must be finite and >= 0, got {list(out)}")
        return out

    if source == "perGram":
        return finite_nonneg("fiber:dye:extinction", get("fiber:dye:extinction"))  # type: ignore[return-value]
    if source == "molar":
        eps_m = finite_nonneg("fiber:dye:molarExtinction", get("fiber:dye:molarExtinction"))
        w_m = float(get("fiber:dye:molarMass"))
        if not (math.isfinite(w_m) and w_m > 0):
            raise FiberParamsError(path, "fiber:dye:molarMass",
                                   f'must be > 0 g/mol with extinctionSource "molar", got {w_m:g}')
        # epsilon_m [L mol^-1 cm^-1] / w_m [g mol^-1] = [L g^-1 cm^-1]; / 1000 -> [L mg^-1 cm^-1]
        return tuple(e / w_m / 1000.0 for e in eps_m)  # type: ignore[return-value]
    if source == "spectrum":
        wl_attr = prim.GetAttribute("fiber:dye:spectrum:wavelengths")
        val_attr = prim.GetAttribute("fiber:dye:spectrum:values")
        wl = list(wl_attr.Get(time) or []) if wl_attr else []
        vals = list(val_attr.Get(time) or []) if val_attr else []
        if len(wl) < 2:
            raise FiberParamsError(path, "fiber:dye:spectrum:wavelengths",
                                   'needs at least 2 wavelengths with extinctionSource "spectrum"')
        if len(vals) != len(wl):
            raise FiberParamsError(path, "fiber:dye:spectrum:values",
                                   f"has {len(vals)} values for {len(wl)} wavelengths")
        wl = [float(w) for w in wl]
        if any(b <= a for a, b in zip(wl, wl[1:])) or not all(math.isfinite(w) for w in wl):
            raise FiberParamsError(path, "fiber:dye:spectrum:wavelengths", "must be finite and strictly increasing")
        if wl[0] > 400.0 or wl[-1] < 700.0:
            raise FiberParamsError(path, "fiber:dye:spectrum:wavelengths",
                                   f"must cover 400-700 nm, covers {wl[0]:g}-{wl[-1]:g} nm")
        v = list(finite_nonneg("fiber:dye:spectrum:values", vals))
        return spectrum_to_rec709(wl, v)
    raise FiberParamsError(path, "fiber:dye:extinctionSource", f'unknown token "{source}"')


def _read_user_profiles(prim: Usd.Prim, path: str) -> tuple[UserProfile, ...]:
    rel_name = "fiber:profile:sources"
    rel = prim.GetRelationship(rel_name)
    targets = rel.GetForwardedTargets() if rel else []
    if not targets:
        raise FiberParamsError(path, rel_name, 'fiber:profile is "user" but no profile prims are targeted')
    stage = prim.GetStage()
    out = []
    for t in targets:
        tp = stage.GetPrimAtPath(t)
        if not tp or not tp.HasAPI("FiberProfileAPI"):
            raise FiberParamsError(path, rel_name, f"target {t} is not a prim with FiberProfileAPI")
        pts = tp.GetAttribute("fiberProfile:points").Get() or []
        counts = [int(c) for c in (tp.GetAttribute("fiberProfile:loopVertexCounts").Get() or [])]
        if not counts or any(c < 3 for c in counts) or sum(counts) != len(pts):
            raise FiberParamsError(
                str(t), "fiberProfile:loopVertexCounts",
                f"counts {counts} must each be >= 3 and sum to the {len(pts)} points (profile of {path})")
        loops, i = [], 0
        for c in counts:
            loops.append(tuple((float(p[0]), float(p[1])) for p in pts[i:i + c]))
            i += c
        out.append(UserProfile(str(t), tuple(loops), bool(tp.GetAttribute("fiberProfile:smooth").Get())))
    return tuple(out)


__all__ = ["FiberParams", "FiberParamsError", "UNITS", "UserProfile", "mu_a_per_um", "spectrum_to_rec709"]
