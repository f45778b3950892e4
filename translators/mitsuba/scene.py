"""A USD stage -> a Mitsuba 3 scene (:func:`translate_stage`).

What is translated (everything visible, of the render purposes, at one time code, with
native instances and point instancers expanded by :mod:`usdfiber.translators.mitsuba.stage_walk`):

* fiber curves (BasisCurves with FiberAPI): one B-spline shape with one tabulated-BCSDF
  instance for all of them (:mod:`usdfiber.translators.mitsuba.fibers`); missing tables are baked first;
  yarn curves (FiberYarnAPI) are expanded into fibers where the camera sees them, at the
  detail it resolves (:mod:`usdfiber.geometry.yarn`, :mod:`usdfiber.translators.mitsuba.lod`);
* other BasisCurves: B-spline curves with a grey diffuse BSDF (a warning names them);
* meshes with their UsdPreviewSurface materials (:mod:`usdfiber.translators.mitsuba.meshes`);
* UsdLux lights (:mod:`usdfiber.translators.mitsuba.lights`), or a documented default rig when the stage has
  none; the camera named by the options or the render settings, else the first camera of
  the stage, else one framing the visible geometry (:mod:`usdfiber.translators.mitsuba.camera`).

Other gprims (spheres, cubes, points, volumes...) are skipped with a warning.
"""
from __future__ import annotations

import functools
import time as _time
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Union

import numpy as np
from pxr import Sdf, Usd, UsdGeom, UsdLux

from usdfiber.backend import mitsuba
from usdfiber.bake.settings import RENDER_BAKE_SETTINGS, BakeSettings
from usdfiber.bcsdf import render_settings_for
from usdfiber.bake.cache import TableCache
from usdfiber.memory_budget import MemoryBudget
from usdfiber.stage_io import default_render_time, stage_metrics_problems

from usdfiber.translators.mitsuba.camera import camera_sensor, default_camera, default_framing, validate_camera
from usdfiber.translators.mitsuba.curves import CurveError, concatenate, curves_from_prim, make_curve_shape
from usdfiber.translators.mitsuba.fiber_bsdf import fiber_bsdf
from usdfiber.translators.mitsuba.errors import TranslateError, TranslationError
from usdfiber.translators.mitsuba.fibers import FiberTranslation, fiber_prim, translate_fibers
from usdfiber.translators.mitsuba.fitted_models import check_render_model, fitted_fiber_shapes
from usdfiber.translators.mitsuba.lights import default_light, light_emitter
from usdfiber.translators.mitsuba.lod import LodPolicy, camera_view, default_view
from usdfiber.translators.mitsuba.meshes import mesh_shapes
from usdfiber.translators.mitsuba.profile import TranslationProfile
from usdfiber.translators.mitsuba.render_settings import RenderSettingsInfo, read_render_settings, stage_bbox
from usdfiber.translators.mitsuba.stage_walk import walk
from usdfiber.translators.mitsuba.yarn_far_field import YarnBakeSettings

__all__ = ["AOVS", "RENDER_BAKE_SETTINGS", "BakeChoice", "SceneOptions", "Translation", "aov_integrator",
           "bake_settings_for", "fiber_integrator", "render_bake",
           "translate_stage"]


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


#: The AOV layers a render can add to its image (``--aov``): layer name -> (Mitsuba ``aov``
#: integrator type, channel names in the image). ``albedo`` is the first surface's
#: reflectance (a fiber's: the BSDF's value towards its normal, times pi), ``normal`` its
#: shading normal and ``position`` its point in world space (Mitsuba's world: the stage's
#: with Z up), ``depth`` the distance along the camera ray (scene units, from the camera; from
#: the near clipping plane for orthographic cameras, where rays start); 0 where the ray meets
#: nothing. Like the colour, they are averaged over the pixel's samples with the film's filter.
AOVS: dict[str, tuple[str, tuple[str, ...]]] = {
    "albedo": ("albedo", ("albedo.R", "albedo.G", "albedo.B")),
    "normal": ("sh_normal", ("normal.X", "normal.Y", "normal.Z")),
    "depth": ("depth", ("depth.Z",)),
    "position": ("position", ("position.X", "position.Y", "position.Z")),
}


def aov_integrator(inner: dict[str, Any], aovs: tuple[str, ...]) -> dict[str, Any]:
    """Mitsuba's ``aov`` integrator around ``inner``, adding the layers ``aovs`` (keys of
    :data:`AOVS`, in that order in the image); ValueError names an unknown one."""
    unknown = [a for a in aovs if a not in AOVS]
    if unknown:
        raise ValueError(f"unknown AOV(s) {', '.join(unknown)}; valid: {', '.join(AOVS)}")
    spec = ",".join(f"{a}:{AOVS[a][0]}" for a in aovs)
    return {"type": "aov", "aovs": spec, "image": inner}


#: How missing fiber tables are baked: one :class:`BakeSettings` for every table, or a function
#: of the table request giving them (the default, :func:`usdfiber.bcsdf.render_settings_for`: per fiber).
BakeChoice = Union[BakeSettings, Callable[[Any], BakeSettings]]


def render_bake(resolution_deg: float | None = None, photons: int | None = None) -> BakeChoice:
    """The render's bake choice: per fiber (:func:`usdfiber.bcsdf.render_settings_for`), with
    the bin size and photons given (``--bake-resolution``, ``--bake-photons``) for every fiber.
    Raises BakeError for values no bake accepts, before any table is looked up."""
    replace(RENDER_BAKE_SETTINGS, **({} if resolution_deg is None else {"resolution_deg": float(resolution_deg)}),
            **({} if photons is None else {"photons": int(photons)}))       # validates
    if resolution_deg is None and photons is None:
        return render_settings_for
    return functools.partial(render_settings_for, resolution_deg=resolution_deg, photons=photons)


def bake_settings_for(choice: BakeChoice, request: Any) -> BakeSettings:
    """The settings ``choice`` gives the table ``request``."""
    return choice(request) if callable(choice) else choice


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
    bake: BakeChoice = render_settings_for        # missing tables: per fiber (render_settings_for) or fixed
    bake_missing: bool = True
    cache: TableCache | None = None
    pass_through: bool = True
    lod_scale: float = 1.0                      # yarn level of detail (lod.py); 0: every fiber
    yarn_bake: YarnBakeSettings = field(default_factory=YarnBakeSettings)  # far fields of small yarns
    lod: LodPolicy = field(default_factory=LodPolicy)  # the level-of-detail steps' numbers
    profile: TranslationProfile | None = None   # times the steps; None: a fresh profile
    cloth: str = "fibers"                       # fibers | volume | auto (volume/scene.py)
    voxels_per_pixel: float = 1.0               # volumes: voxels per pixel footprint
    voxel_size: float | None = None             # volumes: voxel edge (scene units), overrides the footprint
    volume_brick: int = 8                       # volumes: voxels per brick side (volume/medium.py); 0: one medium
    memory_budget: MemoryBudget | None = None   # yarn expansion's budget; None: MemoryBudget.resolve()
    alpha: bool = False                         # film with an alpha channel (R, G, B, A)
    aovs: tuple[str, ...] = ()                  # AOV layers (AOVS), after R, G, B(, A)
    model: str = "table"                        # fiber model: table | chiang | khungurn (fitted_models.py)


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
    profile: TranslationProfile = field(default_factory=TranslationProfile)  # time per step
    time: float | None = None        # the time code translated (None: the default time)


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
    try:
        check_render_model(opt.model)
    except ValueError as exc:
        raise TranslateError(str(exc)) from None
    prof = opt.profile or TranslationProfile()
    tc = _timecode(opt.time)
    warnings: list[str] = []
    times: dict[str, float] = {}
    for problem in stage_metrics_problems(stage):  # what `usdfiber check` says of them
        raise TranslateError(problem.message)
    if opt.time is None:
        picked = default_render_time(stage)  # an animated-only stage shows nothing at default
        if picked is not None:
            tc = Usd.TimeCode(picked[0])
            warnings.append(picked[1])
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
    up = UsdGeom.GetStageUpAxis(stage)
    if cam is not None:
        cam_xf = np.array(UsdGeom.Xformable(cam).ComputeLocalToWorldTransform(tc), dtype=np.float64)
        try:  # before the view is computed from it
            validate_camera(cam, cam_xf, tc)
        except TranslationError as exc:
            raise TranslateError(str(exc)) from None
        view = camera_view(cam, tc, w, h)
    else:
        # No camera: the default camera frames the visible geometry, and level of detail
        # follows that framing as it would an authored camera's.
        bbox = stage_bbox(stage, tc, purposes)
        lo, hi = bbox if bbox is not None else (np.full(3, -1.0), np.full(3, 1.0))
        view = default_view(default_framing(lo, hi, up_axis=up), w, h)
    # ---- volumetric cloth (--cloth volume|auto): volume/scene.py --------------------------
    volumes = None
    if opt.cloth != "fibers":
        from usdfiber.translators.mitsuba.volume.scene import split_cloth, translate_volumes

        vol_placements, fiber_placements, choices = split_cloth(fiber_placements, opt.cloth, view, tc, opt.lod_scale)
        warnings.extend(f"cloth: {c}" for c in choices)
        if vol_placements:
            volumes, kept = translate_volumes(mi, vol_placements, stage, tc, settings=opt.bake, cache=opt.cache,
                                              bake_missing=opt.bake_missing, progress=progress, view=view,
                                              voxels_per_pixel=opt.voxels_per_pixel, voxel_size=opt.voxel_size,
                                              brick_voxels=opt.volume_brick)
            fiber_placements = fiber_placements + kept
            entries.update(volumes.entries)
            warnings.extend(volumes.warnings)
    fibers = translate_fibers(fiber_placements, stage, tc, settings=opt.bake, cache=opt.cache,
                              bake_missing=opt.bake_missing, progress=progress, view=view,
                              lod_scale=opt.lod_scale, yarn_settings=opt.yarn_bake, lod=opt.lod, profile=prof,
                              memory_budget=opt.memory_budget, warnings_out=warnings)
    times["tables"] = fibers.table_seconds if fibers is not None else 0.0
    if volumes is not None:
        times["tables"] += volumes.table_seconds
    counts = {"fiber_prims": len(fiber_placements), "fiber_curves": 0, "fiber_segments": 0,
              "curves_other": 0, "meshes": 0, "lights": 0}
    if volumes is not None:
        counts.update(volumes.counts)
    if fibers is not None:
        warnings.extend(fibers.warnings)
        if opt.model == "table":
            # The bank's host nodes are dropped as they reach the device (2 deg tables would not
            # fit twice); only its slots are read after this.
            bsdf = prof.call("bsdf", fiber_bsdf, mi, fibers.bank, fibers.seg_slot, fibers.seg_psi, fibers.seg_ref,
                             pass_through=opt.pass_through, release_host=True)
            entries["fibers"] = prof.call("curve_shape", make_curve_shape, fibers.geometry, bsdf, "fibers")
        else:
            # A fitted standard model instead of the table (Aliaga et al. Figures 9, 10).
            t_fit = _time.perf_counter()
            shapes, _ = fitted_fiber_shapes(mi, fibers, opt.model)
            times["tables"] += _time.perf_counter() - t_fit
            entries.update(shapes)
            bsdf = None   # opaque fitted models: the plain path tracer
        counts["fiber_curves"] = fibers.curve_count
        counts["fiber_segments"] = fibers.segment_count
        counts["fiber_slots"] = len(fibers.bank.slots)
        counts["fiber_tables"] = len(fibers.tables)
        for k, v in fibers.yarns.items():
            counts[f"yarn_{k}"] = v
    if other_curves:
        parts = []
        for pl in other_curves:
            # Plain curves (guides, hair) are extras: one that cannot be drawn is skipped with a
            # warning, as `usdfiber check` warns (usdfiber.validation.plain_curves).
            try:
                g = curves_from_prim(pl.prim, tc, pl.xform)
            except (CurveError, ValueError) as exc:
                warnings.append(f"{pl.path}: BasisCurves without FiberAPI skipped: {exc}")
                continue
            warnings.extend(g.warnings)
            parts.append(g)
            warnings.append(f"{pl.path}: BasisCurves without FiberAPI rendered with a grey diffuse BSDF")
        geom = concatenate(parts)
        if geom.segment_count:
            entries["curves"] = prof.call("curve_shape", make_curve_shape, geom, mi.load_dict(
                {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.18}}), "curves")
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
    if n_lights == 0 and cam is not None:
        bbox = stage_bbox(stage, tc, purposes)
        lo, hi = bbox if bbox is not None else (np.full(3, -1.0), np.full(3, 1.0))
    if n_lights == 0:
        for k, e in enumerate(default_light(lo, hi, up_axis=up)):
            entries[f"default_light_{k}"] = e
        warnings.append("the stage has no lights: using the default rig (a white dome of radiance 0.5 "
                        "and a distant key light of irradiance pi)")

    # ---- camera ---------------------------------------------------------------------------
    film_extra = {"pixel_format": "rgba"} if opt.alpha or opt.aovs else None
    if cam is not None:
        try:
            entries["sensor"] = camera_sensor(cam, cam_xf, tc, w, h, spp=spp, seed=opt.seed, film_extra=film_extra,
                                              conform_policy=settings.aspect_ratio_conform_policy,
                                              depth_of_field=not settings.disable_depth_of_field)
        except TranslationError as exc:
            raise TranslateError(str(exc)) from None
        cam_name = str(cam.GetPath())
    else:
        entries["sensor"] = default_camera(lo, hi, w, h, spp=spp, seed=opt.seed, up_axis=up, film_extra=film_extra)
        cam_name = "default"
        warnings.append("the stage has no camera: using a default camera that frames the visible geometry")
    entries["integrator"] = {"type": fiber_integrator(mi, bsdf if fibers is not None else None),
                             "max_depth": int(opt.max_depth)}
    if volumes is not None:
        # Media need volpath (it also passes shadow rays through non-round fibers).
        entries["integrator"]["type"] = "volpath"
    if opt.aovs:
        entries["integrator"] = aov_integrator(entries["integrator"], opt.aovs)
    try:
        scene = prof.call("scene", mi.load_dict, entries)
    except RuntimeError as exc:
        # A value the checks above let through and Mitsuba refuses: one line, not a traceback.
        why = " ".join(str(exc).split())
        raise TranslateError(f"Mitsuba could not build the scene: {why[:500]}") from None
    times["translate"] = _time.perf_counter() - t0 - times["tables"]
    return Translation(scene=scene, resolution=(w, h), spp=int(spp), camera=cam_name, fibers=fibers,
                       counts=counts, warnings=warnings, times=times, profile=prof,
                       time=None if tc.IsDefault() else tc.GetValue())
