"""What to bake: the mapping from fibers (USD prims, presets, parameter files) to tables.

A :class:`TableRequest` is one table: cross-section ``variant`` of a fiber with its
parameters (:class:`usdfiber.spec.fiber.FiberParams`), and the prims that use it. Only the
fiber's geometry inputs (everything that changes traced photon paths: cross section, index
of refraction, roughness, cuticles) select a table; dye, depth of shade and diameter
recolour it. So prims that differ only in those share requests, as do curves inheriting one
class and yarns made of the same fiber.

* :func:`tables_for_stage`: EXACTLY the distinct tables a stage needs;
* :func:`requests_for_prim`, :func:`requests_for_params`: the tables of one fiber;
* :func:`requests_from_preset`, :func:`requests_from_params`: of a fiber preset or a JSON
  parameter file (:func:`params_from_mapping` describes the format);
* :func:`resolve_table_asset`: the file named by a prim's ``fiber:table``;
* :func:`profile_for`: the cross section a request traces (built-in families through
  :data:`FAMILY_KINDS`, user loops as given), centred, at circumscribed diameter 1 um.
"""
from __future__ import annotations

import json
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np
from pxr import Sdf, Usd

from usdfiber.bake import profiles
from usdfiber.bake.settings import BUILTIN_PROFILE_VERTICES, BakeError
from usdfiber.spec.fiber import FiberParams, FiberParamsError
from usdfiber.table_format import TableError, read_header

__all__ = [
    "FAMILY_KINDS",
    "TableRequest",
    "fiber_prims",
    "params_from_mapping",
    "params_from_preset",
    "profile_for",
    "requests_for_params",
    "requests_for_prim",
    "requests_from_params",
    "requests_from_preset",
    "resolve_table_asset",
    "tables_for_stage",
]

#: Built-in cross-section family (fiber:profile token) -> profiles.builtin_profiles kind.
FAMILY_KINDS: dict[str, str] = {
    "round": "polyester",
    "roundedTriangle": "silk",
    "kidney": "cotton",
    "bean": "cotton",
    "swollen": "mercerizedCotton",
    "elliptical": "wool",
}


def profile_for(params: Any, variant: int) -> Any:
    """The cross section of ``variant`` of a fiber, centred, at circumscribed diameter 1 um."""
    fam = params.profile_family
    if fam == "user":
        if not 0 <= variant < len(params.user_profiles):
            raise BakeError(f"{params.prim_path}: no user cross section {variant}")
        up = params.user_profiles[variant]
        try:
            prof = profiles.profile_from_polygons([np.asarray(l, dtype=np.float64) for l in up.loops],
                                           name=up.path, smooth=up.smooth)
        except profiles.ProfileError as exc:
            raise BakeError(f"{up.path}: invalid cross section: {exc}") from None
    else:
        kind = FAMILY_KINDS.get(fam)
        if kind is None:
            raise BakeError(f"{params.prim_path}: unknown cross-section family {fam!r}")
        if not 0 <= variant < max(1, params.variant_count):
            raise BakeError(f"{params.prim_path}: variant {variant} out of range")
        prof = profiles.builtin_profiles(kind, variant + 1, seed=params.seed if fam != "round" else 0,
                                  n=BUILTIN_PROFILE_VERTICES)[variant]
    return prof.centered().scaled_to_diameter(1.0)


@dataclass
class TableRequest:
    """One table to bake: cross-section ``variant`` of a fiber with these parameters.

    ``prims`` lists the prims (or sources) that use it. The traced profile is at
    circumscribed diameter 1 um; cuticle height and spacing are relative to the diameter.
    """

    params: Any
    variant: int
    prims: list[str] = field(default_factory=list)

    @property
    def geometry_key(self) -> str:
        """The fiber's geometry key (what the traced photon paths depend on)."""
        return self.params.geometry_key()

    @property
    def inputs(self) -> dict[str, Any]:
        """The fiber's canonical geometry inputs (part of the cache key)."""
        return self.params.geometry_inputs()

    # The traced values are the canonical (rounded) geometry inputs, so that equal keys
    # always mean equal traces.
    @property
    def eta(self) -> float:
        return float(self.inputs["eta"])

    @property
    def beta_deg(self) -> float:
        return float(self.inputs["beta"])

    @property
    def cuticle(self) -> tuple[float, float, float] | None:
        c = self.inputs.get("cuticle")
        if not c:
            return None
        return (float(c["tilt"]), float(c["height_rel"]), float(c["spacing_rel"]))

    @property
    def cuticle_scales(self) -> tuple[float, float, float] | None:
        """:attr:`cuticle` where its scales have a height (what the baker traces), else None."""
        c = self.cuticle
        return c if c is not None and c[1] > 0.0 else None

    def profile(self) -> Any:
        """The cross section traced, at circumscribed diameter 1 um."""
        return profile_for(self.params, self.variant)

    @property
    def label(self) -> str:
        """A short human name: kind/family variant n."""
        return f"{self.params.kind}/{self.params.profile_family} variant {self.variant}"

    def header(self) -> dict[str, Any]:
        """Header entries identifying the table (and the first fiber that asked for it)."""
        p = self.params
        return {
            "geometry_key": self.geometry_key,
            "inputs": self.inputs,
            "variant": int(self.variant),
            "variant_count": int(p.variant_count),
            "kind": p.kind,
            "profile_family": p.profile_family,
            "fiber": {"prim": self.prims[0] if self.prims else p.prim_path, "diameter_um": p.diameter,
                      "density_g_cm3": p.density, "mu_a_per_um": list(p.mu_a), "extinction": list(p.extinction),
                      "depth_of_shade": p.depth_of_shade, "dye_class": p.dye_class},
            "prims": list(self.prims[:16]),
        }


def _collect(params_list: Iterable[tuple[Any, str]]) -> list[TableRequest]:
    """One request per distinct (geometry key, variant), listing every source that uses it."""
    seen: dict[tuple[str, int], TableRequest] = {}
    for params, source in params_list:
        gk = params.geometry_key()
        for v in range(max(1, int(params.variant_count))):
            req = seen.get((gk, v))
            if req is None:
                req = seen[(gk, v)] = TableRequest(params, v, [])
            if source not in req.prims:
                req.prims.append(source)
    return list(seen.values())


def requests_for_params(params: Any, source: str | None = None) -> list[TableRequest]:
    """The tables of one fiber (one per cross-section variant)."""
    return _collect([(params, source or params.prim_path)])


def _explicit_table_ok(prim: Any, params: Any) -> bool:
    """Whether ``fiber:table`` names a readable table baked for these parameters."""
    path = resolve_table_asset(prim)
    if not path:
        return False
    try:
        hdr = read_header(path, verify=True)  # damaged arrays too: the renderer cannot use them
    except TableError as exc:
        warnings.warn(f"{prim.GetPath()}: fiber:table {exc}; baking from the fiber's parameters",
                      RuntimeWarning, stacklevel=3)
        return False
    if hdr.get("geometry_key") != params.geometry_key():
        warnings.warn(f"{prim.GetPath()}: fiber:table {path} was baked for other parameters; "
                      f"baking from the fiber's parameters", RuntimeWarning, stacklevel=3)
        return False
    return True


def resolve_table_asset(prim: Any) -> str | None:
    """The file named by a prim's ``fiber:table`` (resolved), or None when empty."""
    attr = prim.GetAttribute("fiber:table")
    if not attr:
        return None
    v = attr.Get()
    if v is None:
        return None
    raw = v.path if isinstance(v, Sdf.AssetPath) else str(v)
    if not raw:
        return None
    resolved = v.resolvedPath if isinstance(v, Sdf.AssetPath) else ""
    if resolved:
        return resolved
    if os.path.isabs(raw):
        return raw
    stack = attr.GetPropertyStack()
    layer = stack[0].layer if stack else prim.GetStage().GetRootLayer()
    base = layer.realPath or ""
    return os.path.normpath(os.path.join(os.path.dirname(base), raw)) if base else raw


def fiber_prims(stage: Any) -> list[Any]:
    """Concrete prims with FiberAPI (instance proxies included; class prims are not rendered)."""
    out = []
    for prim in Usd.PrimRange.Stage(stage, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)):
        if prim.HasAPI("FiberAPI"):
            out.append(prim)
    return out


def tables_for_stage(stage: Any, time: Any = None, *, include_explicit: bool = False) -> list[TableRequest]:
    """EXACTLY the distinct tables a stage needs: one per (geometry key, variant).

    Every concrete prim with FiberAPI (fiber curves and yarn curves alike: a yarn's fibers
    take its FiberAPI values) contributes its variants; prims sharing a definition (a class,
    a reference, equal values) share requests. Abstract class prims are not rendered and
    need nothing themselves. A prim whose ``fiber:table`` names a valid table for its
    parameters needs no bake (unless ``include_explicit``); a missing, damaged or stale one
    is warned about and its tables are requested. Raises BakeError naming the prim when
    its values cannot be resolved.
    """
    t = Usd.TimeCode.Default() if time is None else time
    items = []
    for prim in fiber_prims(stage):
        try:
            params = FiberParams.from_prim(prim, t)
        except FiberParamsError as exc:
            raise BakeError(str(exc)) from None
        if params.table and not include_explicit and _explicit_table_ok(prim, params):
            continue
        items.append((params, str(prim.GetPath())))
    return _collect(items)


def requests_for_prim(prim: Any, time: Any = None) -> list[TableRequest]:
    """The tables (one per cross-section variant) a fiber prim uses, from its parameters."""
    try:
        params = FiberParams.from_prim(prim, Usd.TimeCode.Default() if time is None else time)
    except FiberParamsError as exc:
        raise BakeError(str(exc)) from None
    return requests_for_params(params, str(prim.GetPath()))


# ---------------------------------------------------------------------------------------------
# Presets and parameter files
# ---------------------------------------------------------------------------------------------

def params_from_mapping(values: Mapping[str, Any], name: str = "params") -> Any:
    """FiberParams from a mapping (the JSON parameter file format).

    Keys: ``"preset"`` (optional fiber preset to start from, see ``usdfiber presets``); any
    FiberAPI value by its Python name (``usdfiber.authoring.FIBER_NAMES``, e.g.
    ``"diameter"``, ``"beta"``, ``"dye"``) or attribute name (``"fiber:diameter"``); and
    ``"profiles"``: user cross sections, a list of ``{"loops": [[[x, y], ...], ...],
    "smooth": false}`` in um (outer loop first, then holes). Raises BakeError.
    """
    import usdfiber  # noqa: F401 - registers the schema before the stage is made
    from pxr import UsdGeom

    from usdfiber import authoring

    if not isinstance(values, Mapping):
        raise BakeError(f"{name}: expected a JSON object of fiber values")
    values = dict(values)
    preset = values.pop("preset", None)
    user_loops = values.pop("profiles", None)
    by_attr = {v: k for k, v in authoring.FIBER_NAMES.items()}
    kw: dict[str, Any] = {}
    for k, v in values.items():
        key = by_attr.get(k, k)
        if key not in authoring.FIBER_NAMES and key not in authoring.FIBER_SPECIAL:
            valid = sorted(authoring.FIBER_NAMES) + list(authoring.FIBER_SPECIAL) + ["preset", "profiles"]
            raise BakeError(f"{name}: unknown fiber value {k!r}; valid: {', '.join(valid)}")
        kw[key] = v
    stage = Usd.Stage.CreateInMemory()
    prim = UsdGeom.BasisCurves.Define(stage, "/Fiber").GetPrim()
    try:
        if user_loops is not None:
            if not isinstance(user_loops, list) or not user_loops:
                raise BakeError(f"{name}: 'profiles' must be a non-empty list of cross sections")
            paths = []
            for i, pr in enumerate(user_loops):
                if not isinstance(pr, Mapping) or "loops" not in pr:
                    raise BakeError(f"{name}: profiles[{i}] must be an object with 'loops'")
                path = f"/Profiles/P{i}"
                authoring.define_profile(stage, path, pr["loops"], smooth=bool(pr.get("smooth", False)))
                paths.append(path)
            kw["profile_sources"] = paths
        authoring.apply_fiber(prim, preset, **kw)
        return FiberParams.from_prim(prim)
    except (authoring.AuthoringError, FiberParamsError) as exc:
        msg = str(exc).replace("/Fiber", name, 1)
        raise BakeError(msg) from None
    except (TypeError, ValueError) as exc:
        raise BakeError(f"{name}: {exc}") from None


def params_from_preset(name: str) -> Any:
    """FiberParams of a fiber preset (``usdfiber presets``)."""
    from usdfiber import presets

    if name not in presets.FIBER_PRESETS:
        raise BakeError(f"unknown fiber preset {name!r}; valid: {', '.join(presets.FIBER_PRESETS)}")
    return params_from_mapping({"preset": name}, name=f"preset {name}")


def requests_from_preset(name: str) -> list[TableRequest]:
    """The tables of a fiber preset."""
    return requests_for_params(params_from_preset(name), source=f"preset:{name}")


def requests_from_params(path: str | os.PathLike[str]) -> list[TableRequest]:
    """The tables of the fiber described by a JSON parameter file (see params_from_mapping)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise BakeError(f"{p}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise BakeError(f"{p}: cannot read: {exc}") from None
    try:
        values = json.loads(text)
    except json.JSONDecodeError as exc:
        raise BakeError(f"{p}: not JSON: {exc.msg} (line {exc.lineno}, column {exc.colno})") from None
    return requests_for_params(params_from_mapping(values, name=str(p)), source=str(p))
