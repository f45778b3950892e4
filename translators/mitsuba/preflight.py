"""What the Mitsuba bridge refuses, reported by ``usdfiber check`` (entry point ``usdfiber.checks``).

``usdfiber render`` refuses a stage whose render settings, cameras, lights, meshes or point
instancers cannot be translated. The core's validators know the fiber schema, not these, so
without this module a stage could pass ``check`` and be refused by ``render``.
:func:`stage_problems` runs the translation's own functions on those prims
(:func:`~usdfiber.translators.mitsuba.render_settings.read_render_settings`,
:func:`~usdfiber.translators.mitsuba.camera.validate_camera`,
:func:`~usdfiber.translators.mitsuba.lights.light_emitter`,
:func:`~usdfiber.translators.mitsuba.meshes.mesh_shapes` and the stage walk, which expands
instancers and refuses non-finite transforms) at the time a render would use, and reports
each refusal as an error, so that ``check`` and ``render`` agree by construction. Fibers are
not translated here: their values are the core validators'.

Codes (errors, but for two warnings): ``RenderSettingsInvalid``, ``CameraInvalid``, ``LightInvalid``,
``MeshInvalid``, ``PlacementInvalid`` (an instancer that cannot be expanded, a transform that
is not finite, fiber curves a PointInstancer places beyond the float32 bound of
:data:`~usdfiber.geometry.curves.MAX_COORDINATE`: the curves' own check sees their prototype,
not its instances); the warning ``PlainCurvesSkipped`` for plain curves placed so (the render
skips them), and ``LightSkipped`` for a light the render leaves out (a negative intensity, a light
type without a Mitsuba emitter).
"""
from __future__ import annotations

from typing import Iterator

import numpy as np
from pxr import Sdf, Usd, UsdGeom, UsdLux, UsdRender

from usdfiber.errors import layer_path
from usdfiber.geometry.curves import too_large_text, world_points_near_limit
from usdfiber.spec.attributes import Fiber, Yarn
from usdfiber.stage_io import default_render_time
from usdfiber.validation.problems import Problem, Severity

from usdfiber.translators.mitsuba.camera import validate_camera
from usdfiber.translators.mitsuba.errors import TranslationError
from usdfiber.translators.mitsuba.lights import light_emitter
from usdfiber.translators.mitsuba.meshes import mesh_shapes
from usdfiber.translators.mitsuba.render_settings import read_render_settings
from usdfiber.translators.mitsuba.stage_walk import Placement, walk

__all__ = ["stage_problems"]

_LIGHTS = (UsdLux.BoundableLightBase, UsdLux.NonboundableLightBase)
#: Most time samples of one camera or light checked (check without ``--time``).
_MAX_TIMES = 10_000


def _problem(code: str, stage: Usd.Stage, prim: str, attribute: str | None, message: str,
             time: Usd.TimeCode, severity: Severity = Severity.ERROR) -> Problem:
    p = stage.GetPrimAtPath(prim) if Sdf.Path.IsValidPathString(prim) else Usd.Prim()
    layer = layer_path(p, attribute) if p else None
    return Problem(code, severity, prim, attribute, message, layer=layer,
                   time=None if time.IsDefault() else float(time.GetValue()))


def _from_refusal(code: str, stage: Usd.Stage, exc: ValueError, time: Usd.TimeCode) -> Problem:
    """The problem of a translation's refusal at ``time``: a TranslationError's fields, or the
    "<prim path>: <what>" of other refusals (the walk's instance paths carry "[i]")."""
    if isinstance(exc, TranslationError):
        return _problem(code, stage, str(exc.prim), exc.attribute, str(exc.expected), time)
    prim, _, what = str(exc).partition(": ")
    return _problem(code, stage, prim.split("[", 1)[0] if what else "/", None, what or str(exc), time)


def _placements(stage: Usd.Stage, tc: Usd.TimeCode, purposes: tuple[str, ...], types: tuple,
                problems: list[Problem]) -> Iterator[Placement]:
    """The walk's placements; its first refusal becomes a problem (the walk cannot go on)."""
    try:
        yield from walk(stage, tc, purposes, types)
    except ValueError as exc:
        problems.append(_from_refusal("PlacementInvalid", stage, exc, tc))


def stage_problems(stage: Usd.Stage, time: float | None = None) -> list[Problem]:
    """Everything ``usdfiber render`` would refuse in the stage's render settings, cameras,
    lights, meshes and instancers at ``time`` (default: the time a render picks), as errors."""
    tc = Usd.TimeCode.Default() if time is None else Usd.TimeCode(float(time))
    if time is None:
        picked = default_render_time(stage)
        if picked is not None:
            tc = Usd.TimeCode(picked[0])
    problems: list[Problem] = []
    purposes: tuple[str, ...] = ("default", "render")
    settings_paths: list[Sdf.Path | None] = [None]
    settings_paths += [p.GetPath() for p in stage.Traverse() if p.IsA(UsdRender.Settings)]
    for path in settings_paths:
        try:
            info = read_render_settings(stage, path)
        except ValueError as exc:  # TranslationError included
            problems.append(_from_refusal("RenderSettingsInvalid", stage, exc, tc))
            continue
        if path is None:
            purposes = info.included_purposes
        if info.camera is not None:
            cam = stage.GetPrimAtPath(info.camera)
            if not cam or not cam.IsA(UsdGeom.Camera):
                problems.append(_problem("RenderSettingsInvalid", stage, str(info.path), "camera",
                                         f"targets {info.camera}, which is not a camera", tc))
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.Camera):
            for t in _times(prim, tc, time is None):
                try:
                    validate_camera(prim, np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(t)), t)
                except ValueError as exc:  # TranslationError included
                    problems.append(_from_refusal("CameraInvalid", stage, exc, t))
                    break
    cache: dict = {}
    curves: dict = {}
    for pl in _placements(stage, tc, purposes, (UsdGeom.Gprim,), problems):
        if pl.prim.IsA(UsdGeom.Mesh):
            try:
                mesh_shapes(pl.prim, pl.xform, tc, material_cache=cache)
            except ValueError as exc:  # TranslationError included
                problems.append(_from_refusal("MeshInvalid", stage, exc, tc))
        elif pl.prim.IsA(UsdGeom.BasisCurves) and "[" in pl.path:   # placed by a PointInstancer
            why = _instanced_curves_beyond(pl, tc, curves)
            if why:
                # Fiber curves refuse the render; plain ones are skipped with a warning.
                fiber = bool({Fiber.API, Yarn.API} & set(pl.prim.GetAppliedSchemas()))
                problems.append(_problem("PlacementInvalid" if fiber else "PlainCurvesSkipped", stage,
                                         pl.path.split("[", 1)[0], None,
                                         f"{pl.path}: {why}" + ("" if fiber else "; the renderer skips these"),
                                         tc, Severity.ERROR if fiber else Severity.WARNING))
    for pl in _placements(stage, tc, purposes, _LIGHTS, problems):
        for t in _times(pl.prim, tc, time is None):
            xform = pl.xform if t == tc else np.array(UsdGeom.Xformable(pl.prim).ComputeLocalToWorldTransform(t))
            try:
                entry, warns = light_emitter(pl.prim, xform, t)
            except ValueError as exc:  # TranslationError included
                problems.append(_from_refusal("LightInvalid", stage, exc, t))
                break
            if entry is None and warns:  # the render leaves the light out, with this warning
                problems.append(_skipped_light(stage, str(pl.prim.GetPath()), warns[-1], t))
                break
    return problems


def _instanced_curves_beyond(pl: Placement, tc: Usd.TimeCode, seen: dict) -> str | None:
    """Why the curves a PointInstancer places at ``pl`` are beyond the float32 bound in world
    space (the render's curve conversion refuses them), or None. The prototype's points and
    largest width are read once (``seen``); each instance costs a bound on its transform."""
    key = pl.prim.GetPath()
    if key not in seen:
        pts = UsdGeom.BasisCurves(pl.prim).GetPointsAttr().Get(tc)
        pv = UsdGeom.PrimvarsAPI(pl.prim).GetPrimvar("widths")
        widths = (pv.ComputeFlattened(tc) if pv and pv.HasAuthoredValue()
                  else UsdGeom.Curves(pl.prim).GetWidthsAttr().Get(tc))
        w = np.asarray(widths if widths is not None else [], dtype=np.float64)
        seen[key] = (np.asarray(pts if pts is not None else np.zeros((0, 3)), dtype=np.float64).reshape(-1, 3),
                     float(w.max()) if w.size else 0.0)
    points, wmax = seen[key]
    where = "in world space (after the PointInstancer's transform) "
    huge = too_large_text(world_points_near_limit(points, pl.xform), "point")
    if huge:
        return where + huge
    if wmax > 0:
        scale = abs(float(np.linalg.det(np.asarray(pl.xform)[:3, :3]))) ** (1.0 / 3.0)
        huge = too_large_text(np.array([wmax * scale]), "the widest width")
        if huge:
            return where + huge
    return None


def _skipped_light(stage: Usd.Stage, prim: str, warning: str, time: Usd.TimeCode) -> Problem:
    """``LightSkipped`` (a warning) from the render's "<prim>[.<attribute>]: <why>" for a light it
    leaves out (a negative intensity, a light type Mitsuba has no emitter for)."""
    rest = warning[len(prim):] if warning.startswith(prim) else ": " + warning
    attribute, _, why = rest[1:].partition(": ") if rest.startswith(".") else (None, "", rest[2:])
    return _problem("LightSkipped", stage, prim, attribute, why, time,
                    Severity.WARNING)


def _times(prim: Usd.Prim, tc: Usd.TimeCode, every: bool) -> list[Usd.TimeCode]:
    """``tc``, and with ``every`` the time samples of the prim's own attributes (a camera's or a
    light's values are cheap to check at each; at most _MAX_TIMES of them)."""
    out = [tc]
    if every:
        samples: set[float] = set()
        for attr in prim.GetAuthoredAttributes():
            samples.update(attr.GetTimeSamples())
            if len(samples) > _MAX_TIMES:
                break
        out += [Usd.TimeCode(t) for t in sorted(samples)[:_MAX_TIMES]]
    return out
