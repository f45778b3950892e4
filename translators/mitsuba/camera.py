"""UsdGeom.Camera -> Mitsuba 3 sensor dicts.

Conventions (all lengths stay in scene units; nothing is converted to metres):

* Frames. A USD camera looks down its local -Z with +Y up and +X to the image right. A
  Mitsuba sensor looks down its local +Z with +Y up and +X to the image *left* (its
  ``look_at`` builds the frame (left, up, forward)). Both frames are right-handed and differ
  by a 180 degree turn about Y, so ``to_world = M_usd^T @ diag(-1, 1, -1, 1)``.
  Scale and shear in the camera's world transform are removed (polar decomposition), as
  ``GfFrustum`` does; Mitsuba's perspective sensors refuse scaled transforms.
* Units. Per ``GfCamera::APERTURE_UNIT`` / ``FOCAL_LENGTH_UNIT`` the apertures, their offsets
  and the focal length are in tenths of a scene unit (mm for a cm scene); ``focusDistance``
  and ``clippingRange`` are in scene units.
* Aspect ratio. When the aperture's aspect (horizontalAperture / verticalAperture) differs
  from the image's, the aperture is conformed to the image with UsdRender's
  ``aspectRatioConformPolicy`` (CameraUtilConformWindow): the default ``expandAperture`` is
  CameraUtil's *Fit*: the aperture grows in one direction so that the whole authored
  aperture stays visible; ``cropAperture`` (Crop), ``adjustApertureWidth`` (MatchVertically)
  and ``adjustApertureHeight`` (MatchHorizontally) are supported too; ``adjustPixelAspectRatio``
  needs non-square pixels, which Mitsuba lacks: it falls back to ``expandAperture`` with a
  warning. The window keeps its centre (offsets are not scaled), as in CameraUtil.
* Perspective: ``fov = 2 atan(hA / 2f)`` with ``fov_axis = "x"`` (hA conformed). The aperture
  offsets shift the window; Mitsuba's ``principal_point_offset_x/y`` are fractions of the film
  width/height with +x towards the image right and +y towards the image *bottom*, so
  ``ppo_x = hOffset / hA`` and ``ppo_y = -vOffset / vA``.
* Orthographic: Mitsuba's ``orthographic`` sees [-1, 1] x [-1/aspect, 1/aspect] in its local
  frame; the to_world scale is half the conformed horizontal aperture in scene units
  (``0.1 * hA / 2``) and the offsets become a translation of the window (Mitsuba's
  orthographic sensor has no principal point offset).
* Depth of field: ``fStop > 0`` and ``focusDistance > 0`` -> ``thinlens`` with
  ``aperture_radius = 0.1 * focalLength / (2 fStop)`` scene units. Mitsuba's thin lens has no
  principal point offset: authored offsets are dropped with a warning.

Problems that do not stop the translation are reported with :func:`warnings.warn`
(category :class:`CameraWarning`); the message names the prim and attribute.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
from pxr import Usd, UsdGeom

from usdfiber.geometry.curves import too_large_text
from usdfiber.translators.mitsuba.errors import TranslationError
from usdfiber.translators.mitsuba.render_settings import as_timecode, to_mi_transform

__all__ = ["CameraWarning", "CONFORM_POLICIES", "DefaultFraming", "MAX_APERTURE_RATIO", "camera_sensor", "conform_aperture", "default_camera",
           "validate_camera",
           "default_framing"]

# Gf.Camera.APERTURE_UNIT / FOCAL_LENGTH_UNIT: tenths of a scene unit.
_UNIT = 0.1

#: UsdRender aspectRatioConformPolicy tokens understood by :func:`conform_aperture`.
CONFORM_POLICIES = ("expandAperture", "cropAperture", "adjustApertureWidth",
                    "adjustApertureHeight", "adjustPixelAspectRatio")

# USD camera frame (x right, y up, looks down -z) -> Mitsuba sensor frame (x left, y up, +z).
_USD_FROM_MI = np.diag([-1.0, 1.0, -1.0, 1.0])


class CameraWarning(UserWarning):
    """A camera feature that Mitsuba cannot represent exactly."""


def conform_aperture(h_ap: float, v_ap: float, aspect: float,
                     policy: str = "expandAperture") -> tuple[float, float]:
    """Conform (horizontal, vertical) aperture to the image ``aspect`` (width / height).

    Mirrors CameraUtilConformWindow for the UsdRender policies: ``expandAperture`` (Fit),
    ``cropAperture`` (Crop), ``adjustApertureWidth``, ``adjustApertureHeight``.
    """
    if policy == "adjustApertureWidth":
        return v_ap * aspect, v_ap
    if policy == "adjustApertureHeight":
        return h_ap, h_ap / aspect
    wider = h_ap / v_ap > aspect  # the aperture is wider than the image
    if policy == "cropAperture":
        return (v_ap * aspect, v_ap) if wider else (h_ap, h_ap / aspect)
    # expandAperture (and the fallback for adjustPixelAspectRatio)
    return (h_ap, h_ap / aspect) if wider else (v_ap * aspect, v_ap)


def _rigid(xform: np.ndarray, where: str) -> np.ndarray:
    """Rotation + translation of a row-vector transform (scale/shear removed), row-vector form."""
    m = np.asarray(xform, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"{where}: expected a (4, 4) transform, got shape {m.shape}")
    lin = m[:3, :3]
    u, _, vt = np.linalg.svd(lin)
    rot = u @ vt
    if np.linalg.det(rot) < 0:
        warnings.warn(f"{where}: the camera transform mirrors (negative determinant); "
                      "Mitsuba cannot mirror a sensor, the image is rendered unmirrored",
                      CameraWarning, stacklevel=3)
        u[:, 2] *= -1.0
        rot = u @ vt
    out = np.eye(4)
    out[:3, :3] = rot
    out[3, :3] = m[3, :3]
    return out


def _film(width: int, height: int, film_extra: dict | None) -> dict:
    if width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    film: dict[str, Any] = {
        "type": "hdrfilm",
        "width": int(width),
        "height": int(height),
        "rfilter": {"type": "gaussian"},
        "pixel_format": "rgb",
        "component_format": "float32",
    }
    film.update(film_extra or {})
    return film


def _sampler(spp: int, seed: int) -> dict:
    if spp <= 0:
        raise ValueError(f"spp must be positive, got {spp}")
    return {"type": "independent", "sample_count": int(spp), "seed": int(seed)}


#: Largest aperture / focal length of a perspective camera (a field of view of 179.9999 degrees):
#: a wider one rounds to 180 degrees, which Mitsuba refuses, once conformed to the image's aspect.
MAX_APERTURE_RATIO = 1e6


def _fov(aperture: float, focal: float) -> float:
    return math.degrees(2.0 * math.atan(0.5 * aperture / focal))


def validate_camera(prim: Usd.Prim, xform: np.ndarray, time: Usd.TimeCode | float | None) -> None:
    """Raise :class:`TranslationError` for a camera that cannot be rendered: not a camera;
    apertures, offsets, focal length or clipping range that are not finite or out of range; a
    world transform that is not finite or has no orientation (a scale of 0). (Lens attributes
    authored with another type than the schema's are ``usdfiber check`` errors of their own.)"""
    if not prim or not prim.IsA(UsdGeom.Camera):
        raise TranslationError(prim.GetPath() if prim else "<invalid prim>", None,
                               "is not a UsdGeom.Camera")
    where = str(prim.GetPath())
    tc = as_timecode(time)
    cam = UsdGeom.Camera(prim)
    gf = cam.GetCamera(tc)
    h_ap, v_ap = float(gf.horizontalAperture), float(gf.verticalAperture)
    for name, value in (("horizontalAperture", h_ap), ("verticalAperture", v_ap)):
        if not 0 < value < math.inf:
            raise TranslationError(where, name, f"must be > 0 and finite, got {value}")
    for name, value in (("horizontalApertureOffset", gf.horizontalApertureOffset),
                        ("verticalApertureOffset", gf.verticalApertureOffset), ("fStop", gf.fStop),
                        ("focusDistance", gf.focusDistance)):
        if not math.isfinite(float(value)):
            raise TranslationError(where, name, f"must be finite, got {float(value)}")
    near, far = float(gf.clippingRange.min), float(gf.clippingRange.max)
    if not 0 < near < far < math.inf:
        raise TranslationError(where, "clippingRange", f"needs 0 < near < far (finite), got ({near}, {far})")
    if gf.projection != gf.Orthographic and not 0 < float(gf.focalLength) < math.inf:
        raise TranslationError(where, "focalLength", f"must be > 0 and finite for a perspective camera, "
                               f"got {float(gf.focalLength)}")
    if gf.projection != gf.Orthographic:
        focal = float(gf.focalLength)
        for name, value in (("horizontalAperture", h_ap), ("verticalAperture", v_ap)):
            if value / focal > MAX_APERTURE_RATIO:
                raise TranslationError(where, name, f"{value:g} over focalLength {focal:g} is a field of view of "
                                       f"{_fov(value, focal):.6f} degrees; expected aperture / focalLength up to "
                                       f"{MAX_APERTURE_RATIO:g} (a field of view under {_fov(MAX_APERTURE_RATIO, 1):.4f} "
                                       f"degrees: Mitsuba needs one below 180)")
    m = np.asarray(xform, dtype=np.float64)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise TranslationError(where, "xformOpOrder", "the camera's world transform is not finite")
    if not abs(np.linalg.det(m[:3, :3])) > 0:
        raise TranslationError(where, "xformOpOrder", "the camera's world transform is singular (a scale of 0)")
    huge = too_large_text(m[3:, :3], "the camera's world position")
    if huge:
        raise TranslationError(where, "xformOpOrder", huge)


def camera_sensor(
    prim: Usd.Prim,
    xform: np.ndarray,
    time: Usd.TimeCode | float | None,
    width: int,
    height: int,
    *,
    spp: int,
    seed: int = 0,
    film_extra: dict | None = None,
    conform_policy: str = "expandAperture",
    depth_of_field: bool = True,
) -> dict:
    """Mitsuba sensor dict (``perspective``, ``thinlens`` or ``orthographic``) for a UsdGeom.Camera.

    ``xform`` is the camera's local-to-world matrix (USD row-vector convention) computed by
    the caller; the camera's own xformOps are not read. ``film_extra`` entries update the
    ``hdrfilm`` dict (e.g. ``{"rfilter": {"type": "box"}}``). ``conform_policy`` is a UsdRender
    ``aspectRatioConformPolicy`` token (see the module docstring); ``depth_of_field=False``
    (UsdRender ``disableDepthOfField``) always gives a pinhole. Raises
    :class:`TranslationError` for a prim that is not a camera or for invalid apertures,
    focal length or clipping range.
    """
    cam = UsdGeom.Camera(prim)
    validate_camera(prim, xform, time)
    where = str(prim.GetPath())
    tc = as_timecode(time)
    gf = cam.GetCamera(tc)  # reads every lens attribute with its fallback

    h_ap, v_ap = float(gf.horizontalAperture), float(gf.verticalAperture)
    h_off, v_off = float(gf.horizontalApertureOffset), float(gf.verticalApertureOffset)
    focal = float(gf.focalLength)
    near, far = float(gf.clippingRange.min), float(gf.clippingRange.max)

    aspect = width / height
    if conform_policy not in CONFORM_POLICIES:
        raise ValueError(f"unknown aspectRatioConformPolicy {conform_policy!r}; one of {CONFORM_POLICIES}")
    if conform_policy == "adjustPixelAspectRatio":
        warnings.warn(f"{where}: aspectRatioConformPolicy 'adjustPixelAspectRatio' needs non-square "
                      "pixels; Mitsuba has none: using 'expandAperture'", CameraWarning, stacklevel=2)
    h_ap, v_ap = conform_aperture(h_ap, v_ap, aspect, conform_policy)

    rigid = _rigid(xform, where)
    if cam.GetExposureAttr().HasAuthoredValue() or any(
            a.HasAuthoredValue() for a in (cam.GetExposureFStopAttr(), cam.GetExposureIsoAttr(),
                                           cam.GetExposureTimeAttr(), cam.GetExposureResponsivityAttr())):
        scale = float(cam.ComputeLinearExposureScale(tc))
        if abs(scale - 1.0) > 1e-6:
            warnings.warn(f"{where}: camera exposure (linear scale {scale:g}) is not applied to the "
                          "film; scale the image afterwards", CameraWarning, stacklevel=2)

    common = {
        "near_clip": near,
        "far_clip": far,
        "film": _film(width, height, film_extra),
        "sampler": _sampler(spp, seed),
    }

    if gf.projection == gf.Orthographic:
        half_w = 0.5 * h_ap * _UNIT
        offset = np.eye(4)
        offset[3, :2] = (h_off * _UNIT, v_off * _UNIT)  # window centre, USD camera frame
        # Mitsuba local -> scale to the window -> USD camera frame -> shift -> world.
        local = np.diag([half_w, half_w, 1.0, 1.0]) @ _USD_FROM_MI @ offset @ rigid
        return {"type": "orthographic", "to_world": to_mi_transform(local), **common}

    fov = _fov(h_ap, focal)
    if not fov < 180.0:  # an extreme image aspect conformed into the aperture
        raise TranslationError(where, "horizontalAperture", f"conformed to the image's aspect ratio {aspect:g} "
                               f"it is a field of view of 180 degrees; expected a narrower one")
    to_world = to_mi_transform(_USD_FROM_MI @ rigid)
    sensor: dict[str, Any] = {"fov": fov, "fov_axis": "x", "to_world": to_world, **common}

    f_stop, focus = float(gf.fStop), float(gf.focusDistance)
    if depth_of_field and f_stop > 0:
        if not focus > 0:
            warnings.warn(f"{where}.focusDistance: fStop is {f_stop:g} but focusDistance is "
                          f"{focus:g}; rendering without depth of field", CameraWarning, stacklevel=2)
        else:
            if h_off or v_off:
                warnings.warn(f"{where}: Mitsuba's thinlens has no principal point offset; "
                              "horizontal/verticalApertureOffset are ignored", CameraWarning, stacklevel=2)
            return {"type": "thinlens",
                    "aperture_radius": focal * _UNIT / (2.0 * f_stop),
                    "focus_distance": focus, **sensor}
    sensor["type"] = "perspective"
    if h_off:
        sensor["principal_point_offset_x"] = h_off / h_ap
    if v_off:
        sensor["principal_point_offset_y"] = -v_off / v_ap
    return sensor


@dataclass(frozen=True)
class DefaultFraming:
    """Where the default camera (:func:`default_camera`) stands and looks: world-space eye,
    target and up vector, the field of view (degrees, along the smaller image axis) and the
    clipping range. Level of detail uses it as the view of a stage without a camera."""

    eye: np.ndarray
    target: np.ndarray
    up: np.ndarray
    fov: float
    near: float
    far: float


def default_framing(bbox_min: np.ndarray, bbox_max: np.ndarray, *, up_axis: str = "Y", fov: float = 30.0,
                    elevation: float = 15.0) -> DefaultFraming:
    """The framing of the world box [bbox_min, bbox_max] by the default camera.

    The camera looks at the box centre from the front, raised by ``elevation`` degrees:
    from +Z for a Y-up stage, from -Y for a Z-up stage (``up_axis``). It fits the box's
    bounding sphere (radius r = half the diagonal) in a ``fov``-degree cone along the smaller
    image axis: distance ``r / sin(fov / 2)``. Clipping planes bracket the sphere. A degenerate
    box gets r = 1.
    """
    lo, hi = np.asarray(bbox_min, np.float64), np.asarray(bbox_max, np.float64)
    centre = 0.5 * (lo + hi)
    radius = 0.5 * float(np.linalg.norm(hi - lo))
    if not radius > 0 or not math.isfinite(radius):
        radius = 1.0
    dist = radius / math.sin(math.radians(fov) / 2.0)
    el = math.radians(elevation)
    if up_axis.upper() == "Z":
        view_from, up = np.array([0.0, -math.cos(el), math.sin(el)]), np.array([0.0, 0.0, 1.0])
    elif up_axis.upper() == "Y":
        view_from, up = np.array([0.0, math.sin(el), math.cos(el)]), np.array([0.0, 1.0, 0.0])
    else:
        raise ValueError(f"up_axis must be 'Y' or 'Z', got {up_axis!r}")
    return DefaultFraming(eye=centre + dist * view_from, target=centre, up=up, fov=float(fov),
                          near=max(1e-4 * dist, 0.5 * (dist - radius)), far=2.0 * (dist + radius))


def default_camera(
    bbox_min: np.ndarray,
    bbox_max: np.ndarray,
    width: int,
    height: int,
    *,
    spp: int,
    seed: int = 0,
    up_axis: str = "Y",
    fov: float = 30.0,
    elevation: float = 15.0,
    film_extra: dict | None = None,
) -> dict:
    """A perspective sensor framing the world box [bbox_min, bbox_max] (no camera on the
    stage), as :func:`default_framing` places it."""
    f = default_framing(bbox_min, bbox_max, up_axis=up_axis, fov=fov, elevation=elevation)
    from usdfiber.backend import mitsuba

    mi = mitsuba()
    return {
        "type": "perspective",
        "fov": f.fov,
        "fov_axis": "smaller",
        "to_world": mi.ScalarTransform4f().look_at(origin=f.eye.tolist(), target=f.target.tolist(),
                                                   up=f.up.tolist()),
        "near_clip": f.near,
        "far_clip": f.far,
        "film": _film(width, height, film_extra),
        "sampler": _sampler(spp, seed),
    }
