"""UsdLux lights -> Mitsuba 3 emitter / emissive-shape dicts.

Return convention: :func:`light_emitter` returns ``(entry, warnings)``: ``entry`` is a dict
for the Mitsuba scene dict (an emitter, or a shape carrying an ``area`` emitter) or ``None``
when the light is skipped; ``warnings`` are messages naming the prim (and attribute).
Errors that make the light meaningless raise :class:`TranslationError`.

Radiance (UsdLux ``LightAPI`` docs, "Quantities and Units"): a light's emission is
``L = intensity * 2^exposure * color * blackbody(colorTemperature)`` (the last factor only
when ``enableColorTemperature``), in units where a directly visible light of intensity 1
gives pixel value 1. Mitsuba's rgb variants render the same tristimulus units, so ``L`` is
passed as the Mitsuba ``radiance`` unchanged (scene units are kept; no photometric scale).
``inputs:normalize`` divides ``L`` by the light's ``sizeFactor``:

* Rect/Disk/Sphere lights: the world-space surface area (transform scale included):
  ``w h |Mx x My|``, ``pi r^2 |Mx x My|``, ``4 pi (r s)^2``.
* DistantLight: ``theta = clamp(radians(angle) / 2, 0, pi)``; ``sizeFactor = pi sin^2(theta)``
  (theta <= pi/2) or ``(2 - sin^2(theta)) pi``; 1 when theta = 0.
* DomeLight: ignored (sizeFactor 1).

DistantLight -> Mitsuba ``directional`` (a delta light), whose parameter is the irradiance
``E`` on a surface facing the light. A UsdLux distant light of angular radius theta and
radiance ``L`` delivers ``E = L * integral of cos over the cap = L pi sin^2(theta)``
(``L pi`` beyond a hemisphere). So:

* ``angle = 0``: ``E = intensity * 2^exposure * color`` (sizeFactor 1: the intensity is the
  irradiance, as for normalize; a parallel light has no radiance).
* ``angle > 0``, ``normalize`` on: ``E = intensity * ...`` (UsdLux: "intensity becomes a
  measure of the illuminance").
* ``angle > 0``, ``normalize`` off: ``E = L pi sin^2(theta)``; e.g. the schema defaults
  (intensity 50000, angle 0.53 deg) give E = 3.36. The disk's soft shadows are not
  reproduced (Mitsuba has no finite-angle distant light): a warning says so.

Orientation: Distant, Rect and Disk lights emit along their local -Z (UsdLux schema docs);
Mitsuba's ``rectangle``/``disk`` emit along local +Z, so they get a 180 degree turn about X.

DomeLight / DomeLight_1: the latlong texture's layout is the OpenEXR one (UsdLux DomeLight
docs): +Y is the top pole, longitude 0 (the image centre) looks along +Z, longitude +pi/2
(a quarter of the width from the left edge) along +X. Mitsuba's ``envmap`` was measured to use
the same layout (tests/mitsuba/test_translate_lights.py renders a one-texel map), so the image is
passed unchanged with ``to_world`` = the light's rotation. Mitsuba samples texel values at
grid vertices (column i at u = i/W, row j at v = j/(H-1)), like the OpenEXR definition
vertically; horizontally it differs by under one texel. DomeLight_1's ``poleAxis`` (``Z``, or
``scene`` on a Z-up stage) adds a +90 degree turn about X applied to the dome only (lat 0,
long 0 then points along -Y, as the schema says). Only ``latlong`` (or ``automatic`` with a
2:1 image) textures are supported; other formats and unreadable files raise. The colour,
intensity, exposure and temperature multiply the texels. No texture -> ``constant``.

SphereLight with ``treatAsPoint`` -> Mitsuba ``point`` with the far-field intensity of the
sphere it replaces, ``I = L pi r^2`` (W/sr-like units; with normalize ``I = intensity / 4``).

Unsupported (skipped with a warning naming the prim): CylinderLight, GeometryLight,
PortalLight, PluginLight, MeshLightAPI/VolumeLightAPI. Ignored with a warning: ShapingAPI
(cone, focus, IES), light filters, ``inputs:diffuse``/``inputs:specular`` != 1, RectLight
``texture:file``. Negative ``intensity`` (USD does not forbid it, but Mitsuba cannot emit
negative light) -> skipped with a warning; negative ``color`` components are clamped to 0
with a warning. Invisible lights are skipped silently.
"""
from __future__ import annotations

import math
import os
from typing import Any

import numpy as np
from pxr import Usd, UsdGeom, UsdLux

from usdfiber.colour import blackbody_rgb
from usdfiber.geometry.curves import MAX_COORDINATE, TOO_LARGE_EXPECTED

from usdfiber.translators.mitsuba.errors import TranslationError
from usdfiber.translators.mitsuba.images import load_image
from usdfiber.translators.mitsuba.render_settings import as_timecode, to_mi_transform

__all__ = [
    "default_light",
    "light_emitter",
    "light_radiance",
]

# 180 degrees about X: Mitsuba's +Z-facing rectangle/disk -> UsdLux's -Z emission.
_FLIP_Z = np.diag([1.0, -1.0, -1.0, 1.0])
# DomeLight_1 poleAxis Z: +Y pole -> +Z, +Z (long 0) -> -Y (row-vector form of +90 deg about X).
_POLE_Y_TO_Z = np.array([[1.0, 0.0, 0.0, 0.0],
                         [0.0, 0.0, 1.0, 0.0],
                         [0.0, -1.0, 0.0, 0.0],
                         [0.0, 0.0, 0.0, 1.0]])


#: Most stops of ``inputs:exposure`` (2^128 overflows float32; photographic exposures are
#: within +-30 stops).
_MAX_EXPOSURE = 100.0
#: Most radiance (per channel) of a light: beyond float32's range Mitsuba's sums overflow to
#: infinity and the image is refused after the whole render.
_MAX_RADIANCE = 1e30


def _get(attr: Usd.Attribute, tc: Usd.TimeCode, default: Any = None) -> Any:
    value = attr.Get(tc) if attr else None
    return default if value is None else value


def light_radiance(prim: Usd.Prim, time: Usd.TimeCode | float | None = None) -> tuple[np.ndarray, list[str]]:
    """``intensity * 2^exposure * color * blackbody`` of a UsdLux light (before ``normalize``).

    Returns (rgb, warnings). Negative colour components are clamped to 0 (warning).
    """
    tc = as_timecode(time)
    light = UsdLux.LightAPI(prim)
    where = str(prim.GetPath())
    warns: list[str] = []
    intensity = float(_get(light.GetIntensityAttr(), tc, 1.0))
    exposure = float(_get(light.GetExposureAttr(), tc, 0.0))
    color = np.array(_get(light.GetColorAttr(), tc, (1.0, 1.0, 1.0)), dtype=np.float64)
    # A NaN or infinite radiance renders black or NaN pixels far from its cause: refused here.
    if not math.isfinite(intensity):
        raise TranslationError(where, "inputs:intensity", f"must be finite, got {intensity:g}")
    if not -_MAX_EXPOSURE <= exposure <= _MAX_EXPOSURE:
        raise TranslationError(where, "inputs:exposure", f"must be within +-{_MAX_EXPOSURE:g} stops, got {exposure:g}")
    if color.shape != (3,) or not np.all(np.isfinite(color)):
        raise TranslationError(where, "inputs:color", f"must be three finite numbers, got {tuple(color.ravel())}")
    if (color < 0).any():
        warns.append(f"{where}.inputs:color: negative components {tuple(color)} clamped to 0")
        color = np.maximum(color, 0.0)
    if _get(light.GetEnableColorTemperatureAttr(), tc, False):
        kelvin = float(_get(light.GetColorTemperatureAttr(), tc, 6500.0))
        if not 1000.0 <= kelvin <= 10000.0:
            clamped = min(max(kelvin, 1000.0), 10000.0)
            warns.append(f"{where}.inputs:colorTemperature: {kelvin:g} K is outside UsdLux's "
                         f"1000-10000 K; using {clamped:g} K")
            kelvin = clamped
        color = color * blackbody_rgb(kelvin)
    radiance = intensity * 2.0 ** exposure * color
    if not np.all(np.isfinite(radiance)) or radiance.max() > _MAX_RADIANCE:
        raise TranslationError(where, "inputs:intensity", f"intensity x 2^exposure x color is {tuple(radiance)}; "
                               f"expected finite values up to {_MAX_RADIANCE:g} (half-float images hold 65504)")
    return radiance, warns


def _rgb(v: np.ndarray) -> dict:
    return {"type": "rgb", "value": [float(c) for c in v]}


def _lin(xform: np.ndarray) -> np.ndarray:
    return np.asarray(xform, dtype=np.float64)[:3, :3]


def _rotation(xform: np.ndarray) -> np.ndarray:
    """Nearest rotation (row-vector 4x4, no translation) of a transform's linear part."""
    u, _, vt = np.linalg.svd(_lin(xform))
    out = np.eye(4)
    out[:3, :3] = u @ vt
    return out


_UNSUPPORTED = ("CylinderLight", "GeometryLight", "PortalLight", "PluginLight")


def _size_in_range(where: str, attribute: str, size: float) -> None:
    """Refuse a light whose size in world space is infinite or beyond float32's squares (its area
    overflows: the light, and the image, would go black)."""
    if not size < MAX_COORDINATE:
        raise TranslationError(where, attribute, f"makes the light {size:g} across in world space; {TOO_LARGE_EXPECTED}")


def light_emitter(prim: Usd.Prim, xform: np.ndarray,
                  time: Usd.TimeCode | float | None = None) -> tuple[dict | None, list[str]]:
    """Translate one UsdLux light (see the module docstring); ``xform`` is its local-to-world.

    Returns ``(entry, warnings)``; ``entry`` is ``None`` for skipped lights.
    """
    tc = as_timecode(time)
    where = str(prim.GetPath())
    xform = np.asarray(xform, dtype=np.float64)
    if xform.shape != (4, 4):
        raise ValueError(f"{where}: expected a (4, 4) transform, got shape {xform.shape}")
    type_name = str(prim.GetTypeName())
    if type_name in _UNSUPPORTED or prim.HasAPI(UsdLux.MeshLightAPI) or prim.HasAPI(UsdLux.VolumeLightAPI):
        kind = type_name if type_name in _UNSUPPORTED else "MeshLightAPI/VolumeLightAPI"
        return None, [f"{where}: {kind} is not supported by the Mitsuba translator; light skipped"]
    if not prim.HasAPI(UsdLux.LightAPI):
        return None, [f"{where}: not a UsdLux light (type {type_name!r}); skipped"]
    img = UsdGeom.Imageable(prim)
    if img and img.ComputeVisibility(tc) == UsdGeom.Tokens.invisible:
        return None, []

    light = UsdLux.LightAPI(prim)
    radiance, warns = light_radiance(prim, tc)
    if float(_get(light.GetIntensityAttr(), tc, 1.0)) < 0:
        return None, warns + [f"{where}.inputs:intensity: negative intensity cannot be rendered "
                              "by Mitsuba; light skipped"]
    for name, getter in (("diffuse", light.GetDiffuseAttr), ("specular", light.GetSpecularAttr)):
        if abs(float(_get(getter(), tc, 1.0)) - 1.0) > 1e-6:
            warns.append(f"{where}.inputs:{name}: non-physical multiplier ignored")
    if prim.HasAPI(UsdLux.ShapingAPI):
        warns.append(f"{where}: ShapingAPI (cone/focus/IES) is not supported; emission unshaped")
    if light.GetFiltersRel().GetForwardedTargets():
        warns.append(f"{where}.light:filters: light filters are not supported; ignored")
    normalize = bool(_get(light.GetNormalizeAttr(), tc, False))
    m = _lin(xform)

    if prim.IsA(UsdLux.DistantLight):
        angle = float(_get(UsdLux.DistantLight(prim).GetAngleAttr(), tc, 0.53))
        theta = min(max(math.radians(angle) / 2.0, 0.0), math.pi)
        if theta > 0:
            s2 = math.sin(theta) ** 2
            size = math.pi * s2 if theta <= math.pi / 2 else (2.0 - s2) * math.pi
            cap = math.pi * s2 if theta <= math.pi / 2 else math.pi  # integral of cos over the cap
            irradiance = radiance / (size if normalize else 1.0) * cap
            warns.append(f"{where}.inputs:angle: {angle:g} deg rendered as a parallel light "
                         "(Mitsuba has no finite-angle distant light): irradiance kept, shadows hard")
        else:
            irradiance = radiance
        direction = np.array([0.0, 0.0, -1.0]) @ m
        n = np.linalg.norm(direction)
        if not n > 0:
            raise TranslationError(where, "xformOpOrder", "degenerate transform (no light direction)")
        return {"type": "directional", "direction": (direction / n).tolist(),
                "irradiance": _rgb(irradiance)}, warns

    if prim.IsA(UsdLux.DomeLight) or prim.IsA(UsdLux.DomeLight_1):
        return _dome(prim, xform, tc, radiance, warns)

    black = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}}
    if prim.IsA(UsdLux.RectLight):
        rect = UsdLux.RectLight(prim)
        w = float(_get(rect.GetWidthAttr(), tc, 1.0))
        h = float(_get(rect.GetHeightAttr(), tc, 1.0))
        if not (w > 0 and h > 0):
            raise TranslationError(where, "inputs:width", f"width and height must be > 0, got {w} x {h}")
        _size_in_range(where, "inputs:width", w * float(np.linalg.norm(m[0])))
        _size_in_range(where, "inputs:height", h * float(np.linalg.norm(m[1])))
        tex = rect.GetTextureFileAttr()
        if tex and tex.Get(tc) and tex.Get(tc).path:
            warns.append(f"{where}.inputs:texture:file: RectLight textures are not supported; "
                         "uniform colour used")
        area = w * h * float(np.linalg.norm(np.cross(m[0], m[1])))
        local = np.diag([w / 2.0, h / 2.0, 1.0, 1.0]) @ _FLIP_Z
        L = radiance / area if normalize else radiance
        return {"type": "rectangle", "to_world": to_mi_transform(local @ xform), "bsdf": black,
                "emitter": {"type": "area", "radiance": _rgb(L)}}, warns

    if prim.IsA(UsdLux.DiskLight):
        r = float(_get(UsdLux.DiskLight(prim).GetRadiusAttr(), tc, 0.5))
        if not r > 0:
            raise TranslationError(where, "inputs:radius", f"must be > 0, got {r}")
        _size_in_range(where, "inputs:radius", 2 * r * float(max(np.linalg.norm(m[0]), np.linalg.norm(m[1]))))
        area = math.pi * r * r * float(np.linalg.norm(np.cross(m[0], m[1])))
        local = np.diag([r, r, 1.0, 1.0]) @ _FLIP_Z
        L = radiance / area if normalize else radiance
        return {"type": "disk", "to_world": to_mi_transform(local @ xform), "bsdf": black,
                "emitter": {"type": "area", "radiance": _rgb(L)}}, warns

    if prim.IsA(UsdLux.SphereLight):
        sph = UsdLux.SphereLight(prim)
        r = float(_get(sph.GetRadiusAttr(), tc, 0.5))
        scales = np.linalg.svd(m, compute_uv=False)
        if scales.max() - scales.min() > 1e-5 * scales.max():
            warns.append(f"{where}: non-uniform scale {tuple(np.round(scales, 6))} on a SphereLight; "
                         "rendered as a sphere of the mean scale")
        s = float(np.cbrt(np.prod(scales)))
        radius = r * s
        centre = xform[3, :3].tolist()
        area = 4.0 * math.pi * radius * radius
        point = bool(_get(sph.GetTreatAsPointAttr(), tc, False))
        if point:
            L = radiance / area if (normalize and area > 0) else radiance
            return {"type": "point", "position": centre,
                    "intensity": _rgb(L * math.pi * radius * radius)}, warns
        if not radius > 0:
            raise TranslationError(where, "inputs:radius", f"must be > 0 (or set treatAsPoint), got {r}")
        _size_in_range(where, "inputs:radius", 2 * radius)
        L = radiance / area if normalize else radiance
        return {"type": "sphere", "center": centre, "radius": radius, "bsdf": black,
                "emitter": {"type": "area", "radiance": _rgb(L)}}, warns

    return None, warns + [f"{where}: light type {type_name!r} is not supported; skipped"]


def _dome(prim: Usd.Prim, xform: np.ndarray, tc: Usd.TimeCode, radiance: np.ndarray,
          warns: list[str]) -> tuple[dict, list[str]]:
    where = str(prim.GetPath())
    dome = UsdLux.DomeLight(prim) if prim.IsA(UsdLux.DomeLight) else UsdLux.DomeLight_1(prim)
    if dome.GetPortalsRel().GetForwardedTargets():
        warns.append(f"{where}.portals: portals are not supported; ignored")
    pole = np.eye(4)
    if prim.IsA(UsdLux.DomeLight_1):
        axis = str(UsdLux.DomeLight_1(prim).GetPoleAxisAttr().Get() or "scene")
        if axis == "Z" or (axis == "scene" and UsdGeom.GetStageUpAxis(prim.GetStage()) == UsdGeom.Tokens.z):
            pole = _POLE_Y_TO_Z
    to_world = to_mi_transform(pole @ _rotation(xform))

    asset = dome.GetTextureFileAttr().Get(tc)
    if asset is None or not asset.path:
        return {"type": "constant", "radiance": _rgb(radiance)}, warns
    path = asset.resolvedPath
    if not path or not os.path.isfile(path):
        raise TranslationError(where, "inputs:texture:file", f"texture {asset.path!r} not found")
    fmt = str(dome.GetTextureFormatAttr().Get(tc) or "automatic")
    data = load_image(path, "auto", where=f"{where}.inputs:texture:file")
    height, width = data.shape[:2]
    if fmt not in ("latlong", "automatic"):
        raise TranslationError(where, "inputs:texture:format",
                               f"{fmt!r} is not supported (only 'latlong')")
    if fmt == "automatic" and width != 2 * height:
        raise TranslationError(where, "inputs:texture:format",
                               f"'automatic' with a {width}x{height} image: only 2:1 latlong maps "
                               "are supported (author 'latlong' to force it)")
    if fmt == "latlong" and width != 2 * height:
        warns.append(f"{where}.inputs:texture:file: latlong map is {width}x{height}, not 2:1")
    channels = data.shape[2]
    rgb = np.repeat(data[..., :1], 3, axis=2) if channels < 3 else data[..., :3]
    rgb = np.ascontiguousarray(rgb * radiance.astype(np.float32)[None, None, :], dtype=np.float32)
    from usdfiber.backend import mitsuba

    mi = mitsuba()
    return {"type": "envmap", "bitmap": mi.Bitmap(rgb), "to_world": to_world}, warns


def default_light(bbox_min: np.ndarray, bbox_max: np.ndarray, *, up_axis: str = "Y") -> list[dict]:
    """Lights for a stage without any: a white ``constant`` dome of radiance 0.5 plus a key
    ``directional`` light of irradiance pi (a white Lambertian surface facing it has radiance
    1 from it), coming from the front-right-top: towards ``-(1, 2, 2)/3`` in a Y-up frame
    (``-(1, -2, 2)/3`` with ``up_axis="Z"``: from -Y front, +Z up).

    Both lights are infinitely far away, so the box only checks that the frame is valid; it is
    part of the signature so that callers need not special-case a future local default light.
    """
    lo, hi = np.asarray(bbox_min, np.float64), np.asarray(bbox_max, np.float64)
    if lo.shape != (3,) or hi.shape != (3,):
        raise ValueError("bbox_min/bbox_max must be 3-vectors")
    if up_axis.upper() == "Y":
        towards = -np.array([1.0, 2.0, 2.0]) / 3.0
    elif up_axis.upper() == "Z":
        towards = -np.array([1.0, -2.0, 2.0]) / 3.0
    else:
        raise ValueError(f"up_axis must be 'Y' or 'Z', got {up_axis!r}")
    return [
        {"type": "constant", "radiance": {"type": "rgb", "value": [0.5, 0.5, 0.5]}},
        {"type": "directional", "direction": towards.tolist(),
         "irradiance": {"type": "rgb", "value": [math.pi] * 3}},
    ]

