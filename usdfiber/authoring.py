"""A small Python API for authoring usdFiber prims with plain pxr calls.

Values are given by Python-friendly names (``diameter=18``, ``depth_of_shade=1.5``,
``dye="reactiveRed"``); :data:`FIBER_NAMES` and :data:`YARN_NAMES` map them to schema
attributes. Units are those of the schema (fiber lengths um, yarn lengths mm, angles
degrees, depth of shade in percent).

Any non-uniform attribute (dye values, depth of shade) also accepts a ``{time: value}``
dict, authored as time samples.

Convenience rules of :func:`apply_fiber` (applied only when the governing attribute is not
itself given): ``ra``/``profile_length`` select ``fiber:roughness:source = "ra"`` and ``beta``
selects ``"beta"``; ``extinction`` / ``molar_extinction``+``molar_mass`` / ``spectrum_*``
select the matching ``fiber:dye:extinctionSource``, and a dye class of ``"none"`` becomes
``"custom"`` so the extinction takes effect; ``profile_sources`` selects
``fiber:profile = "user"``; ``ior`` sets both indices.
"""
from __future__ import annotations

import math
from typing import Any, Iterable, Mapping, Sequence

from pxr import Gf, Sdf, Usd, UsdGeom, Vt

from usdfiber import presets as _presets
from usdfiber.errors import PrimError
from usdfiber.spec.attributes import Fiber, Interval, Profile, Yarn, attribute
from usdfiber.spec.yarn import yarn_diameter


class AuthoringError(PrimError):
    """An invalid authoring request (a :class:`~usdfiber.errors.PrimError`: file, prim,
    attribute and what was expected)."""


# Python name -> schema attribute.
FIBER_NAMES: dict[str, str] = {
    "kind": Fiber.KIND,
    "profile": Fiber.PROFILE,
    "variant_count": Fiber.PROFILE_VARIANT_COUNT,
    "diameter": Fiber.DIAMETER,
    "density": Fiber.DENSITY,
    "ior_parallel": Fiber.IOR_PARALLEL,
    "ior_perpendicular": Fiber.IOR_PERPENDICULAR,
    "ior_effective": Fiber.IOR_EFFECTIVE,
    "roughness_source": Fiber.ROUGHNESS_SOURCE,
    "ra": Fiber.ROUGHNESS_RA,
    "profile_length": Fiber.ROUGHNESS_PROFILE_LENGTH,
    "beta": Fiber.ROUGHNESS_BETA,
    "cuticle_tilt": Fiber.CUTICLE_TILT,
    "cuticle_height": Fiber.CUTICLE_HEIGHT,
    "cuticle_spacing": Fiber.CUTICLE_SPACING,
    "dye_class": Fiber.DYE_CLASS,
    "extinction_source": Fiber.DYE_EXTINCTION_SOURCE,
    "extinction": Fiber.DYE_EXTINCTION,
    "molar_extinction": Fiber.DYE_MOLAR_EXTINCTION,
    "molar_mass": Fiber.DYE_MOLAR_MASS,
    "spectrum_wavelengths": Fiber.DYE_SPECTRUM_WAVELENGTHS,
    "spectrum_values": Fiber.DYE_SPECTRUM_VALUES,
    "depth_of_shade": Fiber.DYE_DEPTH_OF_SHADE,
    "random_rotation": Fiber.ROTATION_RANDOM,
    "rotation": Fiber.ROTATION,
    "seed": Fiber.SEED,
    "table": Fiber.TABLE,
}
# Names that are not one attribute.
FIBER_SPECIAL = ("dye", "ior", "profile_sources")

YARN_NAMES: dict[str, str] = {
    "plies": Yarn.PLIES,
    "fibers_per_ply": Yarn.FIBERS_PER_PLY,
    "linear_density": Yarn.PLY_LINEAR_DENSITY,
    "staple_length": Yarn.FIBER_STAPLE_LENGTH,
    "ply_twist": Yarn.PLY_TWIST,
    "ply_twist_direction": Yarn.PLY_TWIST_DIRECTION,
    "fiber_twist": Yarn.FIBER_TWIST,
    "fiber_twist_direction": Yarn.FIBER_TWIST_DIRECTION,
    "ply_radius": Yarn.PLY_RADIUS,
    "ply_compression": Yarn.PLY_COMPRESSION,
    "migration": Yarn.FIBER_MIGRATION,
    "migration_period": Yarn.FIBER_MIGRATION_PERIOD,
    "density_profile": Yarn.FIBER_DENSITY_PROFILE,
    "hair_density": Yarn.FLYAWAY_HAIR_DENSITY,
    "hair_length": Yarn.FLYAWAY_HAIR_LENGTH,
    "loop_density": Yarn.FLYAWAY_LOOP_DENSITY,
    "loop_height": Yarn.FLYAWAY_LOOP_HEIGHT,
    "seed": Yarn.SEED,
    "expand_fibers": Yarn.EXPAND_FIBERS,
}

DOS_VARIANT_SET = "depthOfShade"


# -------------------------------------------------------------------- low level
def _prim_desc(prim: Usd.Prim) -> str:
    return str(prim.GetPath()) if prim else "<invalid prim>"


def _attr_def(api: str, name: str):
    d = Usd.SchemaRegistry().FindAppliedAPIPrimDefinition(api)
    if d is None:
        raise AuthoringError(None, None, None,
                             f"{api} is not registered with USD (import usdfiber before opening stages)")
    a = d.GetAttributeDefinition(name)
    if not a:
        raise AuthoringError(None, None, name, f"is not an attribute of {api}")
    return a


def _convert(prim: Usd.Prim, name: str, type_name: Sdf.ValueTypeName, allowed, value: Any) -> Any:
    """Convert a Python value to the attribute's USD type; AuthoringError when impossible."""
    t = str(type_name)
    try:
        if t == "token":
            v = str(value)
            if allowed and v not in allowed:
                raise AuthoringError.at(prim, name,
                                        f"{v!r} is not one of {', '.join(map(str, allowed))}")
            return v
        if t == "float":
            v = float(value)
            if not math.isfinite(v):
                raise AuthoringError.at(prim, name, f"{v} is not finite")
            return v
        if t == "int":
            if isinstance(value, bool) or int(value) != value:
                raise TypeError
            return int(value)
        if t == "bool":
            if not isinstance(value, bool):
                raise TypeError
            return value
        if t == "color3f":
            x, y, z = (float(c) for c in value)
            return Gf.Vec3f(x, y, z)
        if t == "float2":
            x, y = (float(c) for c in value)
            return Gf.Vec2f(x, y)
        if t == "float[]":
            return Vt.FloatArray([float(v) for v in value])
        if t == "float2[]":
            return Vt.Vec2fArray([Gf.Vec2f(float(p[0]), float(p[1])) for p in value])
        if t == "int[]":
            return Vt.IntArray([int(v) for v in value])
        if t == "asset":
            return Sdf.AssetPath(str(value))
    except AuthoringError:
        raise
    except (TypeError, ValueError) as exc:
        raise AuthoringError.at(prim, name, f"cannot use {value!r} as {t}") from exc
    raise AuthoringError.at(prim, name, f"unsupported type {t}")


def _in_range(prim: Usd.Prim, name: str, value: Any) -> Any:
    """``value`` if it lies in the schema's valid range of ``name`` (the validators' rule,
    :mod:`usdfiber.spec.attributes`; each component of a vector, each element of an array),
    else AuthoringError saying the range."""
    try:
        spec = attribute(name)
    except KeyError:
        return value
    if spec.valid is None and spec.component_valid is None:
        return value
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        comps = [float(value)]
    elif isinstance(value, (Gf.Vec2f, Gf.Vec3f)):
        comps = [float(c) for c in value]
    elif isinstance(value, (Vt.FloatArray, Vt.IntArray)):
        comps = [float(c) for c in value]
    else:
        return value
    ranges = (spec.component_ranges(len(comps)) if isinstance(value, (Gf.Vec2f, Gf.Vec3f))
              else tuple(spec.valid or Interval() for _ in comps))
    unit = f" {spec.unit}" if spec.unit and spec.unit != "1" else ""
    for i, (c, rng) in enumerate(zip(comps, ranges)):
        if c not in rng:
            where = "" if len(comps) == 1 else f" (component {i})"
            raise AuthoringError.at(prim, name, f"{value!r}{where} is out of range; expected a value in {rng}{unit}")
    return value


def _converted(prim: Usd.Prim, api: str, name: str, value: Any):
    """(definition, converted value or {time: value}) for the schema attribute ``name``."""
    a = _attr_def(api, name)
    type_name = a.GetTypeName()
    allowed = a.GetMetadata("allowedTokens")
    if isinstance(value, Mapping):
        if a.GetVariability() == Sdf.VariabilityUniform:
            raise AuthoringError.at(prim, name, "is uniform and cannot be time-sampled")
        try:
            return a, {float(t): _in_range(prim, name, _convert(prim, name, type_name, allowed, v))
                       for t, v in value.items()}
        except (TypeError, ValueError) as exc:
            if isinstance(exc, AuthoringError):
                raise
            raise AuthoringError.at(prim, name, "time codes must be numbers") from exc
    return a, _in_range(prim, name, _convert(prim, name, type_name, allowed, value))


def _set(prim: Usd.Prim, api: str, name: str, value: Any) -> None:
    """Author ``value`` on the schema attribute ``name`` (dict -> time samples)."""
    a, v = _converted(prim, api, name, value)
    attr = prim.CreateAttribute(name, a.GetTypeName(), False, a.GetVariability())
    if isinstance(v, dict):
        for t, x in v.items():
            attr.Set(x, Usd.TimeCode(t))
    else:
        attr.Set(v)


def _author_all(prim: Usd.Prim, api: str, values: Mapping[str, Any]) -> None:
    """Validate every value first, then apply ``api`` and author them (no half-done prims)."""
    for name, value in values.items():
        if name == Fiber.PROFILE_SOURCES:
            _check_targets(prim, value)
        else:
            _converted(prim, api, name, value)
    prim.ApplyAPI(api)
    for name, value in values.items():
        if name == Fiber.PROFILE_SOURCES:
            prim.CreateRelationship(name, False).SetTargets(_check_targets(prim, value))
        else:
            _set(prim, api, name, value)


def _check_curves(prim: Usd.Prim, api: str) -> None:
    if not prim or not prim.IsValid():
        raise AuthoringError(None, _prim_desc(prim), None, f"cannot apply {api}: not a valid prim")
    if not prim.IsA(UsdGeom.BasisCurves):
        type_name = prim.GetTypeName() or "untyped"
        raise AuthoringError.at(
            prim, None, f"cannot apply {api}: it is a {type_name} prim, {api} applies to "
                        f"BasisCurves only")


def _unknown(prim: Usd.Prim, bad: Iterable[str], valid: Iterable[str]) -> AuthoringError:
    return AuthoringError.at(prim, None, f"unknown parameter(s) {', '.join(sorted(bad))}; "
                                         f"valid: {', '.join(sorted(valid))}")


# -------------------------------------------------------------------- fibers
def apply_fiber(prim: Usd.Prim, preset: str | None = "cotton", **overrides: Any) -> Usd.Prim:
    """Apply FiberAPI to a BasisCurves prim, author ``preset``'s values, then ``overrides``.

    ``preset=None`` authors nothing but the overrides. ``dye`` takes a dye preset or named
    colour of :mod:`usdfiber.presets` (sets class, extinction source and extinction).
    Raises AuthoringError for non-curves prims, unknown names or invalid values.
    """
    _check_curves(prim, Fiber.API)
    valid = set(FIBER_NAMES) | set(FIBER_SPECIAL)
    bad = set(overrides) - valid
    if bad:
        raise _unknown(prim, bad, valid)
    values: dict[str, Any] = {}
    if preset is not None:
        try:
            values.update(_presets.fiber_preset(preset).fiber_attributes())
        except KeyError as exc:
            raise AuthoringError.at(prim, None, exc.args[0]) from None
    values.update(_fiber_override_values(prim, overrides))
    _author_all(prim, Fiber.API, values)
    return prim


def _fiber_override_values(prim: Usd.Prim, ov: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    ov = dict(ov)
    if "dye" in ov:
        name = ov.pop("dye")
        try:
            dye_class, ext = _presets.dye_values(name)
        except KeyError:
            valid = list(_presets.DYE_PRESETS) + list(_presets.DYE_COLOURS)
            raise AuthoringError.at(prim, None,
                                    f"unknown dye {name!r}; valid: {', '.join(valid)}") from None
        out.update({Fiber.DYE_CLASS: dye_class, Fiber.DYE_EXTINCTION_SOURCE: "perGram",
                    Fiber.DYE_EXTINCTION: ext})
    if "ior" in ov:
        if "ior_parallel" in ov or "ior_perpendicular" in ov:
            raise AuthoringError.at(prim, None, "give either ior or ior_parallel/ior_perpendicular")
        ior = ov.pop("ior")
        out[Fiber.IOR_PARALLEL] = ior
        out[Fiber.IOR_PERPENDICULAR] = ior
    if "profile_sources" in ov:
        out[Fiber.PROFILE_SOURCES] = ov.pop("profile_sources")
        if "profile" not in ov:
            out[Fiber.PROFILE] = "user"
    # Roughness: the values given decide which source applies, unless it is given.
    if "roughness_source" not in ov:
        by_ra = "ra" in ov or "profile_length" in ov
        if by_ra and "beta" in ov:
            raise AuthoringError.at(prim, None, "both Ra/l and beta given; pass "
                                                "roughness_source='ra' or 'beta'")
        if by_ra:
            out[Fiber.ROUGHNESS_SOURCE] = "ra"
        elif "beta" in ov:
            out[Fiber.ROUGHNESS_SOURCE] = "beta"
    # Extinction: the values given decide the source, unless it is given.
    src = None
    if "extinction" in ov:
        src = "perGram"
    if "molar_extinction" in ov or "molar_mass" in ov:
        src = "molar" if src is None else "ambiguous"
    if "spectrum_wavelengths" in ov or "spectrum_values" in ov:
        src = "spectrum" if src is None else "ambiguous"
    if src == "ambiguous" and "extinction_source" not in ov:
        raise AuthoringError.at(prim, None, "extinction given several ways; pass extinction_source")
    if src and src != "ambiguous" and "extinction_source" not in ov:
        out[Fiber.DYE_EXTINCTION_SOURCE] = src
    if src and "dye_class" not in ov and Fiber.DYE_CLASS not in out:
        # An extinction on an undyed fiber would be ignored: make the dye "custom".
        current = prim.GetAttribute(Fiber.DYE_CLASS)
        if (current.Get() if current else None) in (None, "none"):
            out[Fiber.DYE_CLASS] = "custom"
    for k, v in ov.items():
        out[FIBER_NAMES[k]] = v
    return out


def _check_targets(prim: Usd.Prim, paths: Sequence[str | Sdf.Path]) -> list[Sdf.Path]:
    if isinstance(paths, (str, Sdf.Path)):
        paths = [paths]
    stage = prim.GetStage()
    targets = []
    for p in paths:
        sp = Sdf.Path(str(p))
        if not sp.IsAbsolutePath():
            raise AuthoringError.at(prim, None, f"profile source {p} must be an absolute path")
        tp = stage.GetPrimAtPath(sp)
        if not tp or not tp.HasAPI(Profile.API):
            raise AuthoringError.at(prim, None, f"profile source {sp} is not a prim with "
                                                f"FiberProfileAPI (create it with define_profile)")
        targets.append(sp)
    if not targets:
        raise AuthoringError.at(prim, None, "profile sources must name at least one profile prim")
    return targets


def set_profile_sources(prim: Usd.Prim, paths: Sequence[str | Sdf.Path]) -> None:
    """Target FiberProfileAPI prims from ``fiber:profile:sources`` and set profile "user"."""
    if not prim or not prim.HasAPI(Fiber.API):
        raise AuthoringError.at(prim, None, "has no FiberAPI; call apply_fiber first")
    prim.CreateRelationship(Fiber.PROFILE_SOURCES, False).SetTargets(_check_targets(prim, paths))
    _set(prim, Fiber.API, Fiber.PROFILE, "user")


def define_profile(stage: Usd.Stage, path: str | Sdf.Path,
                   loops: Sequence[Sequence[Sequence[float]]], smooth: bool = False) -> Usd.Prim:
    """Define a Scope with FiberProfileAPI holding ``loops`` (outer boundary first, then holes, um).

    A closing point equal to the first is dropped (loops close implicitly).
    """
    prim = UsdGeom.Scope.Define(stage, Sdf.Path(str(path))).GetPrim()
    points: list[tuple[float, float]] = []
    counts: list[int] = []
    for i, loop in enumerate(loops):
        pts = [(float(p[0]), float(p[1])) for p in loop]
        if len(pts) > 1 and pts[0] == pts[-1]:
            pts = pts[:-1]
        if len(pts) < 3:
            raise AuthoringError.at(prim, None, f"loop {i} has {len(pts)} points; at least 3 needed")
        if not all(math.isfinite(c) for p in pts for c in p):
            raise AuthoringError.at(prim, None, f"loop {i} has non-finite coordinates")
        points.extend(pts)
        counts.append(len(pts))
    if not counts:
        raise AuthoringError.at(prim, None, "a profile needs at least one loop")
    prim.ApplyAPI(Profile.API)
    _set(prim, Profile.API, Profile.POINTS, points)
    _set(prim, Profile.API, Profile.LOOP_VERTEX_COUNTS, counts)
    _set(prim, Profile.API, Profile.SMOOTH, bool(smooth))
    return prim


# -------------------------------------------------------------------- classes, variants
def define_fiber_class(stage: Usd.Stage, path: str | Sdf.Path, preset: str | None = "cotton",
                       **overrides: Any) -> Usd.Prim:
    """Create a class prim (typed BasisCurves) holding a fiber definition for curves to inherit."""
    sp = Sdf.Path(str(path))
    # Missing ancestors become classes too: a typeless "def" parent would be traversed
    # as a concrete (empty) prim.
    for anc in sp.GetParentPath().GetPrefixes():
        if not stage.GetPrimAtPath(anc):
            stage.CreateClassPrim(anc)
    prim = stage.CreateClassPrim(sp)
    # Typed BasisCurves so that FiberAPI's "applies to BasisCurves" holds on the class too.
    prim.SetTypeName("BasisCurves")
    return apply_fiber(prim, preset, **overrides)


def inherit(prim: Usd.Prim, class_path: str | Sdf.Path) -> Usd.Prim:
    """Make ``prim`` inherit the class at ``class_path`` (which must exist on the stage)."""
    cp = Sdf.Path(str(class_path))
    if not prim or not prim.IsValid():
        raise AuthoringError(None, _prim_desc(prim), None, f"cannot inherit {cp}: not a valid prim")
    if not prim.GetStage().GetPrimAtPath(cp):
        raise AuthoringError.at(prim, None, f"cannot inherit {cp}: no prim there")
    prim.GetInherits().AddInherit(cp)
    return prim


def add_depth_of_shade_variants(prim: Usd.Prim, shades: Mapping[str, float | Mapping[float, float]],
                                default: str | None = None,
                                set_name: str = DOS_VARIANT_SET) -> Usd.VariantSet:
    """Add a variant set switching ``fiber:dye:depthOfShade`` (percent) on a fiber prim or class.

    A local opinion on the depth of shade in the edit target is stronger than any variant,
    so it is removed from the edit target's layer here (its value would hide the variants).
    """
    if not prim or not prim.HasAPI(Fiber.API):
        raise AuthoringError.at(prim, None, "has no FiberAPI; apply it (or define the class) first")
    if not shades:
        raise AuthoringError.at(prim, None, "no shades given")
    if default is not None and default not in shades:
        raise AuthoringError.at(prim, None, f"default variant {default!r} not in {list(shades)}")
    name = Fiber.DYE_DEPTH_OF_SHADE
    attr = prim.GetAttribute(name)
    spec = prim.GetStage().GetEditTarget().GetPropertySpecForScenePath(attr.GetPath())
    if spec is not None:
        prim.RemoveProperty(name)
    for value in shades.values():  # every value checked before anything is authored
        _converted(prim, Fiber.API, name, value)
    vset = prim.GetVariantSets().AddVariantSet(set_name)
    kept = vset.GetVariantSelection()  # a selection made before (by an earlier call) stays
    for variant, value in shades.items():
        vset.AddVariant(variant)
        vset.SetVariantSelection(variant)
        with vset.GetVariantEditContext():
            _set(prim, Fiber.API, name, value)
    if default is not None:
        vset.SetVariantSelection(default)
    elif kept:
        vset.SetVariantSelection(kept)
    else:
        vset.ClearVariantSelection()
    return vset


# -------------------------------------------------------------------- yarns
def apply_yarn(prim: Usd.Prim, preset: str | None = "CNe 50", fiber_preset: str | None = None,
               **overrides: Any) -> Usd.Prim:
    """Apply FiberYarnAPI and FiberAPI to yarn centre-line curves.

    The yarn preset (Table 3) authors the yarn values; the fibers get ``fiber_preset`` or, by
    default, the preset's composition. Overrides take yarn names (:data:`YARN_NAMES`; ``seed``
    is the yarn seed) or fiber names (:data:`FIBER_NAMES`, ``fiber_seed`` for the fiber seed).
    ``packing_fraction`` re-derives the ply radius from the linear density.
    """
    _check_curves(prim, Yarn.API)
    fiber_names = (set(FIBER_NAMES) - {"seed"}) | set(FIBER_SPECIAL) | {"fiber_seed"}
    valid = set(YARN_NAMES) | fiber_names | {"packing_fraction"}
    bad = set(overrides) - valid
    if bad:
        raise _unknown(prim, bad, valid)
    yp = None
    if preset is not None:
        try:
            yp = _presets.yarn_preset(preset)
        except KeyError as exc:
            raise AuthoringError.at(prim, None, exc.args[0]) from None
    fiber_ov = {k: v for k, v in overrides.items() if k in fiber_names}
    if "fiber_seed" in fiber_ov:
        fiber_ov["seed"] = fiber_ov.pop("fiber_seed")
    fp = fiber_preset or (yp.fiber_preset if yp else None)

    values: dict[str, Any] = dict(yp.yarn_attributes()) if yp else {}
    if (yp is not None and (fp != yp.fiber_preset or "density" in fiber_ov)
            and "ply_radius" not in overrides):
        # Another fiber has another density: the same dtex fills another ply radius.
        values[Yarn.PLY_RADIUS] = _presets.ply_radius_mm(
            yp.published.dtex, _fiber_density(prim, fp, fiber_ov))
    for k, v in overrides.items():
        if k in YARN_NAMES:
            values[YARN_NAMES[k]] = v
    if "packing_fraction" in overrides and "ply_radius" not in overrides:
        try:
            pf = float(overrides["packing_fraction"])
        except (TypeError, ValueError):
            pf = float("nan")
        if not 0 < pf <= 1:
            raise AuthoringError.at(prim, None, f"packing_fraction must be in (0, 1], got {overrides['packing_fraction']!r}")
        dtex = float(values.get(Yarn.PLY_LINEAR_DENSITY, 0.0))
        if dtex <= 0:
            raise AuthoringError.at(prim, None, "packing_fraction needs a linear density (dtex)")
        values[Yarn.PLY_RADIUS] = _presets.ply_radius_mm(dtex, _fiber_density(prim, fp, fiber_ov), pf)
    for name, value in values.items():  # validate before authoring anything
        _converted(prim, Yarn.API, name, value)
    apply_fiber(prim, fp, **fiber_ov)
    _author_all(prim, Yarn.API, values)
    return prim


def _fiber_density(prim: Usd.Prim, fiber_preset: str | None, fiber_ov: Mapping[str, Any]) -> float:
    """The fiber density (g/cm^3) the yarn will have once its fiber values are authored."""
    if "density" in fiber_ov:
        return float(fiber_ov["density"])
    if fiber_preset is not None:
        try:
            return _presets.fiber_preset(fiber_preset).density_g_cm3
        except KeyError as exc:
            raise AuthoringError.at(prim, None, exc.args[0]) from None
    attr = prim.GetAttribute(Fiber.DENSITY)
    value = attr.Get() if attr else None
    return float(value if value is not None else _attr_def(Fiber.API, Fiber.DENSITY).GetFallbackValue())


def yarn_diameter_mm(prim: Usd.Prim) -> float:
    """Diameter in mm of the yarn authored on ``prim`` (touching circular plies)."""
    plies = int(prim.GetAttribute(Yarn.PLIES).Get())
    radius = float(prim.GetAttribute(Yarn.PLY_RADIUS).Get())
    return yarn_diameter(plies, radius)


__all__ = [
    "AuthoringError", "DOS_VARIANT_SET", "FIBER_NAMES", "YARN_NAMES", "add_depth_of_shade_variants",
    "apply_fiber", "apply_yarn", "define_fiber_class", "define_profile", "inherit",
    "set_profile_sources", "yarn_diameter_mm",
]
