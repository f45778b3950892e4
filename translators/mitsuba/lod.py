"""Level of detail for yarns: what the camera can see, at the detail it can resolve.

"Model only what a scene needs". Three steps, each measured against full expansion
(``lod_scale`` 0) on a plain weave of ORA 120 (bench/REPORT.md, "Yarns, cloth and level of
detail"):

* **Culling**: a yarn curve whose bounding box (grown by its radius) misses the camera's
  view frustum produces no fibers. Within :data:`PROXY_MARGIN_DIAMETERS` of its own diameters
  of the frustum it stays as a far-field proxy (below), so that it still shadows and lights
  the view (+0.3 % in the image mean on a weave, where dropping them was +6.4 %); farther out
  it is left out, and its far field is not traced (:meth:`LodPolicy.out_of_view`).
The numbers of the steps are a :class:`LodPolicy` (carried in the scene options,
:class:`~usdfiber.translators.mitsuba.scene.SceneOptions` ``lod``); its defaults are the
measured constants below, and benchmarks try other policies through it.

* **Far yarns**: a yarn narrower than :data:`FAR_YARN_PIXELS` / ``lod_scale`` pixels is not
  expanded at all: it is drawn as one curve with the yarn's far field, traced once through its
  fibers (:mod:`.yarn_far_field`; +2.8 % in the mean at 0.9 px, -0.1 % at 2.8 px).
* **Fewer fibers** (the middle step, yarns of :data:`FAR_YARN_PIXELS` / ``lod_scale`` pixels
  and more): a yarn whose diameter covers ``n_px`` pixels keeps the fraction
  ``min(1, max(MIN_FIBER_FRACTION, lod_scale * FIBERS_PER_PIXEL * n_px / fibers))`` of its
  fibers (and at least ``min_fibers``, :meth:`LodPolicy.fiber_fraction`), a deterministic subset
  (``expand_yarn``'s ``fiber_fraction``); flyaways follow the same fraction. Kept fibers are widened by
  ``fraction ** -WIDEN_EXPONENT`` (:meth:`LodPolicy.fiber_widening`); their optics (diameter, absorption,
  tables) are unchanged. With the floor of half the fibers and widening by ``1 / fraction``
  the yarn keeps its coverage; what it loses is some of the light scattered between its
  fibers, so the image is slightly too bright: +3.8 % in the mean at 6.3 px and +1.1 % at
  3.5 px, where 4 fibers per pixel (8-21 % of them) widened by ``1 / sqrt(fraction)`` were +30 %
  and +40 %. The bound is checked in every test run (tests/mitsuba/test_lod_bound.py: a patch of
  5-pixel yarns within 5 % in the mean and 10 % on 4 x 4 pixel blocks).

``lod_scale = 0`` turns the reduction off (every fiber is expanded; culling stays).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pxr import Gf, Usd, UsdGeom

from usdfiber.translators.mitsuba.camera import DefaultFraming

__all__ = ["CameraView", "FAR_YARN_PIXELS", "FIBERS_PER_PIXEL", "LodPolicy", "MIN_FIBER_FRACTION",
           "PROXY_MARGIN_DIAMETERS", "WIDEN_EXPONENT", "camera_view", "default_view"]

#: Fibers kept per pixel of yarn diameter at lod_scale 1 (a pixel resolves about this many
#: fiber highlights across a yarn).
FIBERS_PER_PIXEL = 4.0

#: Yarns narrower than this many pixels (at lod_scale 1) are drawn with their far field. Measured
#: on a plain weave (bench/REPORT.md, section 4): at 2.1 px the far field is +0.2 % in the mean
#: (pixel bias 0.20), half the fibers +0.8 % (0.04) for 460x the segments; at 3.5 px the far
#: field is -1.3 % but 0.36 per pixel, half the fibers +2.4 % and 0.08.
FAR_YARN_PIXELS = 3.0

#: The middle step never keeps fewer than this fraction of a yarn's fibers. Measured on the
#: plain weave at 6.3 px (image mean against full expansion with the same culling, fibers widened
#: by 1 / fraction): 35 % kept: +5.3 %; 50 %: +3.6 %; 70 %: +2.5 %; 4 fibers per pixel (21 %)
#: widened by 1 / sqrt(fraction): +30 % (bench/REPORT.md, section 4).
MIN_FIBER_FRACTION = 0.5

#: Kept fibers are widened by ``fraction ** -WIDEN_EXPONENT``: 1 keeps the yarn's summed projected
#: fiber width, and with it the yarn's coverage at fractions of 0.5 and more (0.603 against 0.604
#: at 6.3 px); 0.5, the summed cross-section, lost coverage (0.584) and was +11 % too bright at
#: half the fibers.
WIDEN_EXPONENT = 1.0

#: A yarn outside the view frustum is kept as a far-field proxy when its box, grown by this many
#: of its diameters, meets the frustum: the shadow of a yarn lying on a surface reaches its
#: height over the tangent of the light's elevation, a few diameters, and light it reflects
#: into the view falls with the square of its distance. Farther yarns are left out (and their
#: far fields not traced). Measured on the Figure 11 close-up (bench/REPORT.md, "Far fields
#: only where they contribute").
PROXY_MARGIN_DIAMETERS = 8.0


@dataclass(frozen=True)
class CameraView:
    """What level of detail needs from the render camera (world space)."""

    frustum: Gf.Frustum
    position: np.ndarray
    forward: np.ndarray
    pixel_angle: float        # radians per pixel (perspective); 0 for orthographic
    pixel_size: float         # scene units per pixel (orthographic); 0 for perspective

    def visible(self, lo: np.ndarray, hi: np.ndarray) -> bool:
        """Whether the world box [lo, hi] meets the view frustum."""
        box = Gf.BBox3d(Gf.Range3d(Gf.Vec3d(*map(float, lo)), Gf.Vec3d(*map(float, hi))))
        return bool(self.frustum.Intersects(box))

    def pixels(self, size: float, points: np.ndarray) -> float:
        """Largest number of pixels ``size`` (scene units) covers at any of ``points``."""
        if self.pixel_size > 0:
            return size / self.pixel_size
        depth = (np.asarray(points, np.float64) - self.position) @ self.forward
        near = float(np.min(depth)) if len(depth) else 0.0
        # A yarn reaching behind the camera plane is as close as can be: full detail.
        return size / (near * self.pixel_angle) if near > 1e-9 else math.inf


def camera_view(cam_prim: Usd.Prim, time: Usd.TimeCode, width: int, height: int) -> CameraView:
    """The view of a UsdGeom.Camera rendered at ``width`` x ``height`` pixels."""
    return _view_of(UsdGeom.Camera(cam_prim).GetCamera(time), width, height)


def default_view(framing: DefaultFraming, width: int, height: int) -> CameraView:
    """The view of the default camera of a stage without one (``camera.default_framing``):
    level of detail applies to it as to an authored camera."""
    gc = Gf.Camera()
    gc.transform = Gf.Matrix4d().SetLookAt(Gf.Vec3d(*map(float, framing.eye)), Gf.Vec3d(*map(float, framing.target)),
                                           Gf.Vec3d(*map(float, framing.up))).GetInverse()
    # The field of view spans the smaller image axis.
    direction = Gf.Camera.FOVHorizontal if width <= height else Gf.Camera.FOVVertical
    gc.SetPerspectiveFromAspectRatioAndFieldOfView(width / height, framing.fov, direction)
    gc.clippingRange = Gf.Range1f(float(framing.near), float(framing.far))
    return _view_of(gc, width, height)


def _view_of(gc: Gf.Camera, width: int, height: int) -> CameraView:
    frustum = gc.frustum
    # The image's aspect ratio decides the window: grow the aperture to fit it, as the
    # camera translator's default conform policy (expandAperture) does.
    wnd = frustum.GetWindow()
    ar = width / height
    w_min, w_max = wnd.GetMin(), wnd.GetMax()
    cw = (w_max[0] - w_min[0]) / 2.0
    ch = (w_max[1] - w_min[1]) / 2.0
    cx, cy = (w_max[0] + w_min[0]) / 2.0, (w_max[1] + w_min[1]) / 2.0
    if cw / ch < ar:
        cw = ch * ar
    else:
        ch = cw / ar
    frustum.SetWindow(Gf.Range2d(Gf.Vec2d(cx - cw, cy - ch), Gf.Vec2d(cx + cw, cy + ch)))
    pos = np.array(frustum.GetPosition(), np.float64)
    rot = frustum.GetRotation()
    fwd = np.array(rot.TransformDir(Gf.Vec3d(0.0, 0.0, -1.0)), np.float64)
    fwd /= np.linalg.norm(fwd)
    if frustum.GetProjectionType() == Gf.Frustum.Orthographic:
        return CameraView(frustum, pos, fwd, 0.0, 2.0 * cw / width)
    # Window half-width cw is tan(fov/2) at unit distance for Gf.Frustum's perspective window.
    return CameraView(frustum, pos, fwd, 2.0 * cw / width, 0.0)


@dataclass(frozen=True)
class LodPolicy:
    """The numbers of the level-of-detail steps (module docstring); the defaults are the
    measured constants of this module. ``lod_scale`` (``usdfiber render --lod-scale``) is
    the user's knob on top of a policy; 0 turns the reduction off."""

    fibers_per_pixel: float = FIBERS_PER_PIXEL       # fibers kept per pixel of yarn diameter
    far_yarn_pixels: float = FAR_YARN_PIXELS         # narrower yarns are drawn with their far field
    min_fiber_fraction: float = MIN_FIBER_FRACTION   # the middle step's floor
    widen_exponent: float = WIDEN_EXPONENT           # kept fibers are widened by fraction ** -exponent
    proxy_margin_diameters: float = PROXY_MARGIN_DIAMETERS  # out-of-view yarns this near stay as proxies

    def __post_init__(self) -> None:
        if not (self.fibers_per_pixel > 0 and self.far_yarn_pixels >= 0 and 0 < self.min_fiber_fraction <= 1
                and math.isfinite(self.widen_exponent) and self.proxy_margin_diameters >= 0):
            raise ValueError(f"LodPolicy: expected fibers_per_pixel > 0, far_yarn_pixels >= 0, "
                             f"0 < min_fiber_fraction <= 1, a finite widen_exponent and "
                             f"proxy_margin_diameters >= 0 (inf keeps every yarn), got {self}")

    def out_of_view(self, view: CameraView, lo: np.ndarray, hi: np.ndarray, diameter: float) -> str:
        """Where a yarn of bounding box [lo, hi] (grown by its radius) and ``diameter`` stands:
        ``"visible"`` (its box meets the frustum), ``"proxy"`` (outside, but within
        ``proxy_margin_diameters`` diameters of it: kept with its far field, for the shadows and
        light it casts into the view) or ``"skip"`` (left out)."""
        if view.visible(lo, hi):
            return "visible"
        m = self.proxy_margin_diameters * float(diameter)
        if not math.isfinite(m) or view.visible(np.asarray(lo) - m, np.asarray(hi) + m):
            return "proxy"
        return "skip"

    def fiber_fraction(self, yarn_pixels: float, fibers: int, *, lod_scale: float = 1.0,
                       min_fibers: int = 8) -> float:
        """Fraction of a yarn's fibers to expand when its diameter covers ``yarn_pixels`` pixels:
        ``fibers_per_pixel * yarn_pixels * lod_scale`` fibers, never fewer than
        ``min_fiber_fraction`` of them nor fewer than ``min_fibers``."""
        if lod_scale <= 0 or fibers <= 0:
            return 1.0
        keep = max(float(min_fibers), self.min_fiber_fraction * fibers,
                   lod_scale * self.fibers_per_pixel * yarn_pixels)
        return float(min(1.0, keep / fibers))

    def fiber_widening(self, fraction: float) -> float:
        """Factor by which the kept fibers of a yarn expanded at ``fraction`` are widened:
        ``fraction ** -widen_exponent``."""
        return float(fraction) ** -self.widen_exponent

    def far_yarn(self, yarn_pixels: float, *, lod_scale: float = 1.0) -> bool:
        """Whether a yarn whose diameter covers ``yarn_pixels`` pixels is drawn with its far field."""
        return lod_scale > 0 and yarn_pixels * lod_scale < self.far_yarn_pixels
