"""A USD stage -> a Mitsuba 3 scene (:func:`translate_stage`).

What is translated (everything visible, of the render purposes, at one time code, with
native instances and point instancers expanded by :mod:`usdfiber.translators.mitsuba.stage_walk`):

* fiber curves (BasisCurves with FiberAPI): one B-spline shape with one tabulated-BCSDF
  instance for all of them (:mod:`usdfiber.translators.mitsuba.fibers`); missing tables are baked first;
  yarn curves (FiberYarnAPI) are expanded into fibers where the camera sees them, at the
  detail it resolves (:mod:`usdfiber.translators.mitsuba.yarns`, :mod:`usdfiber.translators.mitsuba.lod`);
* other BasisCurves: B-spline curves with a grey diffuse BSDF (a warning names them);
* meshes with their UsdPreviewSurface materials (:mod:`usdfiber.translators.mitsuba.meshes`);
* UsdLux lights (:mod:`usdfiber.translators.mitsuba.lights`), or a documented default rig when the stage has
  none; the camera named by the options or the render settings, else the first camera of
  the stage, else one framing the visible geometry (:mod:`usdfiber.translators.mitsuba.camera`).

Other gprims (spheres, cubes, points, volumes...) are skipped with a warning.
"""
from __future__ import annotations

import time as _time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
from pxr import Sdf, Usd, UsdGeom, UsdLux

from usdfiber.backend import mitsuba
from usdfiber.bake.baker import BakeSettings
from usdfiber.bake.cache import TableCache

from usdfiber.translators.mitsuba.camera import camera_sensor, default_camera
from usdfiber.translators.mitsuba.curves import CurveError, concatenate, curves_from_prim, make_curve_shape
from usdfiber.translators.mitsuba.fiber_bsdf import fiber_bsdf
from usdfiber.translators.mitsuba.yarn_far_field import YarnBakeSettings
from usdfiber.translators.mitsuba.fibers import FiberTranslation, TranslateError, fiber_prim, translate_fibers
from usdfiber.translators.mitsuba.lights import default_light, light_emitter
from usdfiber.translators.mitsuba.lod import camera_view
from usdfiber.translators.mitsuba.meshes import mesh_shapes
from usdfiber.translators.mitsuba.render_settings import RenderSettingsInfo, TranslationError, read_render_settings, stage_bbox
from usdfiber.translators.mitsuba.stage_walk import walk

__all__ = ["RENDER_BAKE_SETTINGS", "SceneOptions", "Translation", "TranslateError", "fiber_integrator", "translate_stage"]

#: Bake settings for tables baked on demand by a render: a 6 degree grid (the renderer
#: interpolates between bins) and 100k photons per incoming direction (2.5-7 % relative L2
#: error per direction, rms over the table, for the presets: bench/REPORT.md, "grouping").
#: `usdfiber bake` makes the paper's 2 degree tables.
RENDER_BAKE_SETTINGS = BakeSettings(resolution_deg=6.0, photons=100_000, batches=4)

DEFAULT_RESOLUTION = (960, 540)
DEFAULT_SPP = 64


def fiber_integrator(mi: Any, bsdf: Any) -> str:
    """The integrator for a scene whose fibers use ``bsdf`` (None: no fibers).

    Fibers that let rays pass (a ``Null`` component: non-round profiles, W < D, and yarn far
    fields) render with ``usdfiber_path`` (:mod:`usdfiber.translators.mitsuba.integrator`, registered
    here), a path tracer whose shadow rays pass them through ``eval_null_transmission`` and
    whose pass-throughs are not bounces; Mitsuba's ``path`` treats the tubes as opaque to
    shadow rays. Everything else renders with ``path``.
    """
    if bsdf is not None and mi.has_flag(bsdf.flags(), mi.BSDFFlags.Null):
        from usdfiber.translators.mitsuba.integrator import PLUGIN_NAME, register

        register(mi)
        return PLUGIN_NAME
    return "path"


@dataclass
class SceneOptions:
    """How to translate: time code, image, camera, integrator and table settings."""

    time: float | None = None
    resolution: tuple[int, int] | None = None   # None: render settings, else DEFAULT_RESOLUTION
    spp: int | None = None                      # None: render settings, else DEFAULT_SPP
    camera: str | None = None                   # camera prim path; None: settings or first camera
    render_settings: str | None = None          # RenderSettings prim path; None: the stage's
    seed: int = 0
    max_depth: int = 32
    purposes: tuple[str, ...] | None = None     # None: render settings' includedPurposes
    bake: BakeSettings = RENDER_BAKE_SETTINGS
    bake_missing: bool = True
    cache: TableCache | None = None
    pass_through: bool = True
    lod_scale: float = 1.0                      # yarn level of detail (lod.py); 0: every fiber
    yarn_bake: YarnBakeSettings = field(default_factory=YarnBakeSettings)  # far fields of small yarns


@dataclass
class Translation:
    """A translated stage: the Mitsuba scene and what went into it."""

    scene: Any
    resolution: tuple[int, int]
    spp: int
    camera: str                      # camera prim path, or "default"
    fibers: FiberTranslation | None
    counts: dict[str, int] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    times: dict[str, float] = field(default_factory=dict)


def _timecode(t: float | None) -> Usd.TimeCode:
    return Usd.TimeCode.Default() if t is None else Usd.TimeCode(t)


def _find_camera(stage: Usd.Stage, wanted: str | None, settings: RenderSettingsInfo) -> Usd.Prim | None:
    if wanted:
        prim = stage.GetPrimAtPath(wanted) if Sdf.Path.IsValidPathString(wanted) else Usd.Prim()
        if not prim or not prim.IsA(UsdGeom.Camera):
            cams = [str(p.GetPath()) for p in stage.Traverse() if p.IsA(UsdGeom.Camera)]
            raise TranslateError(f"{wanted}: no camera at this path (cameras on the stage: "
                                 f"{', '.join(cams) or 'none'})")
        return prim
    if settings.camera is not None:
        prim = stage.GetPrimAtPath(settings.camera)
        if prim and prim.IsA(UsdGeom.Camera):
            return prim
        raise TranslateError(f"{settings.path}.camera: targets {settings.camera}, which is not a camera")
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.Camera):
            return prim
    return None


def translate_stage(stage: Usd.Stage, options: SceneOptions | None = None,
                    progress: Callable[..., Any] | None = None) -> Translation:
    """Translate ``stage`` into a loaded Mitsuba scene (see the module docstring).

    ``progress``: passed to the baker for tables baked on demand. Raises TranslateError
    (or TranslationError) naming the prim and attribute for anything that cannot be rendered.
    """
    mi = mitsuba()
    opt = options or SceneOptions()
    tc = _timecode(opt.time)
    warnings: list[str] = []
    times: dict[str, float] = {}
    try:
        settings = read_render_settings(stage, opt.render_settings)
    except TranslationError as exc:
        raise TranslateError(str(exc)) from None
    warnings.extend(settings.warnings)
    purposes = opt.purposes or settings.included_purposes
    if settings.path is not None:
        resolution = opt.resolution or settings.resolution
        spp = opt.spp or settings.samples_per_pixel or DEFAULT_SPP
    else:
        resolution = opt.resolution or DEFAULT_RESOLUTION
        spp = opt.spp or DEFAULT_SPP

    # ---- geometry -------------------------------------------------------------------------
    t0 = _time.perf_counter()
    fiber_placements, other_curves, meshes, skipped = [], [], [], []
    for pl in walk(stage, tc, purposes, (UsdGeom.Gprim,)):
        if fiber_prim(pl.prim):
            fiber_placements.append(pl)
        elif pl.prim.IsA(UsdGeom.BasisCurves):
            other_curves.append(pl)
        elif pl.prim.IsA(UsdGeom.Mesh):
            meshes.append(pl)
        else:
            skipped.append(pl)
    for pl in skipped:
        warnings.append(f"{pl.path}: {pl.prim.GetTypeName()} prims are not translated; skipped")

    entries: dict[str, Any] = {"type": "scene"}
    cam = _find_camera(stage, opt.camera, settings)
    w, h = resolution
    view = camera_view(cam, tc, w, h) if cam is not None else None
    fibers = translate_fibers(fiber_placements, stage, tc, settings=opt.bake, cache=opt.cache,
                              bake_missing=opt.bake_missing, progress=progress, view=view,
                              lod_scale=opt.lod_scale, yarn_settings=opt.yarn_bake)
    times["tables"] = fibers.table_seconds if fibers is not None else 0.0
    counts = {"fiber_prims": len(fiber_placements), "fiber_curves": 0, "fiber_segments": 0,
              "curves_other": 0, "meshes": 0, "lights": 0}
    if fibers is not None:
        warnings.extend(fibers.warnings)
        bsdf = fiber_bsdf(mi, fibers.bank, fibers.seg_slot, fibers.seg_psi, fibers.seg_ref,
                          pass_through=opt.pass_through)
        entries["fibers"] = make_curve_shape(fibers.geometry, bsdf, "fibers")
        counts["fiber_curves"] = fibers.curve_count
        counts["fiber_segments"] = fibers.segment_count
        counts["fiber_slots"] = len(fibers.bank.slots)
        counts["fiber_tables"] = len(fibers.tables)
        for k, v in fibers.yarns.items():
            counts[f"yarn_{k}"] = v
    if other_curves:
        parts = []
        for pl in other_curves:
            try:
                g = curves_from_prim(pl.prim, tc, pl.xform)
            except CurveError as exc:
                raise TranslateError(str(exc)) from None
            warnings.extend(g.warnings)
            parts.append(g)
            warnings.append(f"{pl.path}: BasisCurves without FiberAPI rendered with a grey diffuse BSDF")
        geom = concatenate(parts)
        if geom.segment_count:
            entries["curves"] = make_curve_shape(
                geom, mi.load_dict({"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.18}}), "curves")
            counts["curves_other"] = geom.curve_count
    for k, pl in enumerate(meshes):
        try:
            shapes, mesh_warnings = mesh_shapes(pl.prim, pl.xform, tc)
        except TranslationError as exc:
            raise TranslateError(str(exc)) from None
        warnings.extend(mesh_warnings)
        for j, sh in enumerate(shapes):
            entries[f"mesh_{k}_{j}"] = sh
        counts["meshes"] += 1

    # ---- lights ---------------------------------------------------------------------------
    n_lights = 0
    for k, pl in enumerate(walk(stage, tc, purposes, (UsdLux.BoundableLightBase, UsdLux.NonboundableLightBase))):
        try:
            entry, light_warnings = light_emitter(pl.prim, pl.xform, tc)
        except TranslationError as exc:
            raise TranslateError(str(exc)) from None
        warnings.extend(light_warnings)
        if entry is not None:
            entries[f"light_{k}"] = entry
            n_lights += 1
    counts["lights"] = n_lights
    # The stage's bounds only matter to the defaults: no traversal for them otherwise.
    if n_lights == 0 or cam is None:
        bbox = stage_bbox(stage, tc, purposes)
        lo, hi = bbox if bbox is not None else (np.full(3, -1.0), np.full(3, 1.0))
    up = UsdGeom.GetStageUpAxis(stage)
    if n_lights == 0:
        for k, e in enumerate(default_light(lo, hi, up_axis=up)):
            entries[f"default_light_{k}"] = e
        warnings.append("the stage has no lights: using the default rig (a white dome of radiance 0.5 "
                        "and a distant key light of irradiance pi)")

    # ---- camera ---------------------------------------------------------------------------
    if cam is not None:
        xf = np.array(UsdGeom.Xformable(cam).ComputeLocalToWorldTransform(tc), dtype=np.float64)
        try:
            entries["sensor"] = camera_sensor(cam, xf, tc, w, h, spp=spp, seed=opt.seed,
                                              conform_policy=settings.aspect_ratio_conform_policy,
                                              depth_of_field=not settings.disable_depth_of_field)
        except TranslationError as exc:
            raise TranslateError(str(exc)) from None
        cam_name = str(cam.GetPath())
    else:
        entries["sensor"] = default_camera(lo, hi, w, h, spp=spp, seed=opt.seed, up_axis=up)
        cam_name = "default"
        warnings.append("the stage has no camera: using a default camera that frames the visible geometry")
    entries["integrator"] = {"type": fiber_integrator(mi, bsdf if fibers is not None else None),
                             "max_depth": int(opt.max_depth)}
    scene = mi.load_dict(entries)
    times["translate"] = _time.perf_counter() - t0 - times["tables"]
    return Translation(scene=scene, resolution=(w, h), spp=int(spp), camera=cam_name, fibers=fibers,
                       counts=counts, warnings=warnings, times=times)
