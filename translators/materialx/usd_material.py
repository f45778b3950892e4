"""Fiber looks as ``UsdShade.Material`` prims on the stage, bound to the curves.

For each distinct look (:mod:`~usdfiber.translators.materialx.looks`) one Material under
``<default prim>/FiberLooks`` (``/FiberLooks`` without a default prim), named after the
fiber kind and the look's key, holding (the form UsdMtlx writes, which Hydra render
delegates and Omniverse read)::

    Material  outputs:mtlx:surface -> Surface.outputs:out      outputs:surface -> PreviewSurface
      Shader ChiangHair      info:id = "ND_chiang_hair_bsdf"   the fitted inputs; outputs:out (token)
      Shader Surface         info:id = "ND_surface"            inputs:bsdf -> ChiangHair.outputs:out
      Shader PreviewSurface  info:id = "UsdPreviewSurface"     diffuseColor = the mean colour (Storm)

Every fiber and yarn prim (``FiberAPI``) is bound to its Material with
``UsdShadeMaterialBindingAPI`` and gets ``primvars:displayColor`` (constant, the mean
colour). Names follow the looks, so running again updates the same prims; Materials under
``FiberLooks`` that no prim uses any more are removed (the scope belongs to this writer).

Time samples: when a prim's fiber attributes are animated, its look is computed at each of
their time samples; the Material's inputs and the display colour are written at those times
(one Material per prim animation). Variants: a variant set on the prim whose variants give
different looks (a depth-of-shade set, ``usdfiber.authoring.add_depth_of_shade_variants``)
gets its binding and display colour inside each variant, so switching the variant switches
the material; a prim with no selection in such a set gets no binding of its own (a binding
outside the variants would override theirs).
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from typing import Any, Callable

from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, Vt

from usdfiber.bcsdf import BakeError, BakeSettings, MissingTableError, TableCache, tables_for_prim
from usdfiber.spec.fiber import FiberParams, FiberParamsError
from usdfiber.fit import FitCache
from usdfiber.translators.materialx.looks import MATERIAL_BAKE_SETTINGS, Look, LookError, look_of_tables

__all__ = ["LOOKS_SCOPE", "MaterialReport", "author_materials", "fiber_prims"]

LOOKS_SCOPE = "FiberLooks"
_MTLX_TYPES = {"color3": Sdf.ValueTypeNames.Color3f, "vector2": Sdf.ValueTypeNames.Float2,
               "vector3": Sdf.ValueTypeNames.Float3, "float": Sdf.ValueTypeNames.Float}
#: MaterialX type of each chiang_hair_bsdf input written.
CHIANG_INPUT_TYPES = {"tint_R": "color3", "tint_TT": "color3", "tint_TRT": "color3", "ior": "float",
                      "roughness_R": "vector2", "roughness_TT": "vector2", "roughness_TRT": "vector2",
                      "cuticle_angle": "float", "absorption_coefficient": "vector3"}


@dataclass
class MaterialReport:
    """What :func:`author_materials` wrote: Material paths, looks by name, bound prims."""

    materials: list[str] = field(default_factory=list)
    looks: dict[str, list[tuple[float | None, Look]]] = field(default_factory=dict)
    bound: list[str] = field(default_factory=list)
    removed: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def fiber_prims(stage: Usd.Stage) -> list[Usd.Prim]:
    """The fiber and yarn curves of the stage (prims with FiberAPI, classes excluded)."""
    return [p for p in stage.Traverse() if p.HasAPI("FiberAPI") and p.IsA(UsdGeom.BasisCurves)]


def _fiber_times(prim: Usd.Prim) -> list[float]:
    times: set[float] = set()
    for a in prim.GetAttributes():
        if a.GetName().startswith("fiber:"):
            times.update(a.GetTimeSamples())
    return sorted(times)


def _value(mtype: str, v: Any) -> Any:
    if mtype == "color3":
        return Gf.Vec3f(*v)
    if mtype == "vector2":
        return Gf.Vec2f(*v)
    if mtype == "vector3":
        return Gf.Vec3f(*v)
    return float(v)


class _Writer:
    def __init__(self, stage: Usd.Stage, cache: TableCache, settings: BakeSettings, bake_missing: bool,
                 progress: Callable[[str], None] | None) -> None:
        self.stage = stage
        self.cache = cache
        self.fits = FitCache(cache.root / "fits")
        self.settings = settings
        self.bake_missing = bake_missing
        self.progress = progress
        dp = stage.GetDefaultPrim()
        self.scope = (dp.GetPath() if dp else Sdf.Path.absoluteRootPath).AppendChild(LOOKS_SCOPE)
        self.report = MaterialReport()

    # ---- looks ------------------------------------------------------------------------------
    def look(self, prim: Usd.Prim, time: float | None) -> Look:
        tc = Usd.TimeCode.Default() if time is None else Usd.TimeCode(time)
        try:
            params = FiberParams.from_prim(prim, tc)
            tables = tables_for_prim(prim, self.settings, self.bake_missing, cache=self.cache, time=tc)
        except (FiberParamsError, BakeError, MissingTableError) as exc:
            raise LookError(str(exc)) from None
        if self.progress:
            self.progress(f"{prim.GetPath()}: fitting {params.kind}" + ("" if time is None else f" at {time:g}"))
        return look_of_tables(tables, params.kind, params.mu_a, params.diameter, self.fits)

    def looks_over_time(self, prim: Usd.Prim) -> list[tuple[float | None, Look]]:
        times = _fiber_times(prim)
        if len(times) <= 1:
            return [(None, self.look(prim, times[0] if times else None))]
        return [(t, self.look(prim, t)) for t in times]

    # ---- materials --------------------------------------------------------------------------
    def material(self, samples: list[tuple[float | None, Look]]) -> UsdShade.Material:
        keys = "|".join(lk.key for _, lk in samples) + "|" + ",".join(str(t) for t, _ in samples)
        tag = hashlib.sha256(keys.encode()).hexdigest()[:10]
        name = f"{prim_name(samples[0][1].kind)}_{tag}"
        path = self.scope.AppendChild(name)
        if str(path) in self.report.looks:
            return UsdShade.Material(self.stage.GetPrimAtPath(path))
        UsdGeom.Scope.Define(self.stage, self.scope)
        mat = UsdShade.Material.Define(self.stage, path)
        hair = UsdShade.Shader.Define(self.stage, path.AppendChild("ChiangHair"))
        hair.CreateIdAttr("ND_chiang_hair_bsdf")
        hair_out = hair.CreateOutput("out", Sdf.ValueTypeNames.Token)
        surf = UsdShade.Shader.Define(self.stage, path.AppendChild("Surface"))
        surf.CreateIdAttr("ND_surface")
        surf.CreateInput("bsdf", Sdf.ValueTypeNames.Token).ConnectToSource(hair_out)
        surf_out = surf.CreateOutput("out", Sdf.ValueTypeNames.Token)
        mat.CreateSurfaceOutput("mtlx").ConnectToSource(surf_out)
        prev = UsdShade.Shader.Define(self.stage, path.AppendChild("PreviewSurface"))
        prev.CreateIdAttr("UsdPreviewSurface")
        prev_out = prev.CreateOutput("surface", Sdf.ValueTypeNames.Token)
        mat.CreateSurfaceOutput().ConnectToSource(prev_out)
        diffuse = prev.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f)
        rough = prev.CreateInput("roughness", Sdf.ValueTypeNames.Float)
        inputs = {n: hair.CreateInput(n, _MTLX_TYPES[t]) for n, t in CHIANG_INPUT_TYPES.items()}
        for attr in [diffuse.GetAttr(), rough.GetAttr()] + [i.GetAttr() for i in inputs.values()]:
            attr.Clear()                 # a rerun replaces earlier values and time samples
        for t, lk in samples:
            tc = Usd.TimeCode.Default() if t is None else Usd.TimeCode(t)
            values = lk.params.to_materialx()
            for n, inp in inputs.items():
                inp.Set(_value(CHIANG_INPUT_TYPES[n], values[n]), tc)
            diffuse.Set(Gf.Vec3f(*lk.colour), tc)
            rough.Set(float(min(1.0, max(0.0, lk.params.beta_m))), tc)
        doc = (f"usdfiber look: Chiang et al. 2016 fitted to the fiber's tables ({samples[0][1].kind}); "
               f"relative L2 error of the fit per channel "
               + ", ".join(f"{e:.3f}" for e in samples[0][1].rel_l2))
        mat.GetPrim().SetDocumentation(doc)
        self.report.looks[str(path)] = samples
        self.report.materials.append(str(path))
        return mat

    def bind(self, prim: Usd.Prim, mat: UsdShade.Material, samples: list[tuple[float | None, Look]]) -> None:
        UsdShade.MaterialBindingAPI.Apply(prim).Bind(mat)
        pv = UsdGeom.PrimvarsAPI(prim).CreatePrimvar("displayColor", Sdf.ValueTypeNames.Color3fArray,
                                                      UsdGeom.Tokens.constant)
        pv.GetAttr().Clear()
        pv.SetInterpolation(UsdGeom.Tokens.constant)
        for t, lk in samples:
            tc = Usd.TimeCode.Default() if t is None else Usd.TimeCode(t)
            pv.Set(Vt.Vec3fArray([Gf.Vec3f(*lk.colour)]), tc)

    # ---- prims ------------------------------------------------------------------------------
    def author_prim(self, prim: Usd.Prim) -> None:
        for set_name in prim.GetVariantSets().GetNames():
            vset = prim.GetVariantSets().GetVariantSet(set_name)
            names = vset.GetVariantNames()
            if len(names) < 2:
                continue
            had = vset.HasAuthoredVariantSelection()
            original = vset.GetVariantSelection()
            per_variant = {}
            try:
                for v in names:
                    vset.SetVariantSelection(v)
                    per_variant[v] = self.looks_over_time(prim)
            finally:
                if had:
                    vset.SetVariantSelection(original)
                else:
                    vset.ClearVariantSelection()
            if len({tuple(lk.key for _, lk in s) for s in per_variant.values()}) < 2:
                continue                 # the set does not change the look
            for v, samples in per_variant.items():
                mat = self.material(samples)
                vset.SetVariantSelection(v)
                with vset.GetVariantEditContext():
                    self.bind(prim, mat, samples)
            if had:
                vset.SetVariantSelection(original)
            else:
                vset.ClearVariantSelection()
                self.report.notes.append(f"{prim.GetPath()}: no {set_name} variant selected; bound per variant")
            self.report.bound.append(str(prim.GetPath()))
            return
        samples = self.looks_over_time(prim)
        self.bind(prim, self.material(samples), samples)
        self.report.bound.append(str(prim.GetPath()))

    def remove_stale(self) -> None:
        scope = self.stage.GetPrimAtPath(self.scope)
        if not scope:
            return
        for child in scope.GetChildren():
            if child.IsA(UsdShade.Material) and str(child.GetPath()) not in self.report.looks:
                self.stage.RemovePrim(child.GetPath())
                self.report.removed.append(str(child.GetPath()))


def prim_name(name: str) -> str:
    """A prim name from ``name`` (letters, digits and underscores, not starting with a digit)."""
    out = "".join(c if (c.isalnum() and c.isascii()) or c == "_" else "_" for c in name) or "fiber"
    return out if not out[0].isdigit() else "_" + out


def author_materials(stage: Usd.Stage, *, cache: TableCache | None = None, settings: BakeSettings | None = None,
                     bake_missing: bool = True, progress: Callable[[str], None] | None = None) -> MaterialReport:
    """Write a Material per distinct fiber look and bind it to every fiber and yarn prim
    (module docstring), in the stage's current edit target.

    Tables come from ``cache`` (default: the user's table cache), baked with ``settings``
    (default :data:`MATERIAL_BAKE_SETTINGS`) when missing unless ``bake_missing`` is False;
    fits are cached beside them. Raises LookError (one line) for a stage without fiber prims
    or a prim whose look cannot be made.
    """
    prims = fiber_prims(stage)
    if not prims:
        layer = stage.GetRootLayer()
        where = layer.realPath or layer.identifier
        raise LookError(f"{where}: no fiber or yarn curves (BasisCurves with FiberAPI) to make materials for")
    w = _Writer(stage, cache or TableCache(), settings or MATERIAL_BAKE_SETTINGS, bake_missing, progress)
    for prim in prims:
        w.author_prim(prim)
    w.remove_stale()
    return w.report
