"""Level of detail for yarns: what the camera can see, at the detail it can resolve.

"Model only what a scene needs":

* **Culling**: a yarn curve whose bounding box (grown by its radius) misses the camera's
  view frustum produces no fibers at all.
* **Fiber count from the pixel footprint**: a yarn whose diameter covers ``n_px`` pixels
  keeps the fraction ``min(1, lod_scale * fibers_per_pixel * n_px / fibers)`` of its
  fibers (at least ``min_fibers``), a deterministic subset (:func:`expand_yarn`'s
  ``fiber_fraction``). Kept fibers are widened by ``1 / sqrt(fraction)``, which keeps the
  yarn's total fiber cross-section area but NOT its coverage or brightness: measured
  against full expansion the image is 33-54 % too bright at ``lod_scale`` 1 (bench/REPORT.md,
  "Yarns, cloth and level of detail"). Their optics (diameter, absorption, tables) are
  unchanged. Flyaways follow the same fraction.

* **Far yarns**: a yarn narrower than :data:`FAR_YARN_PIXELS` / ``lod_scale`` pixels is
  not expanded at all: it is drawn as one curve with the yarn's far field, traced once
  through its fibers (:mod:`.yarn_far_field`; measured against full expansion in
  bench/REPORT.md, "Yarns, cloth and level of detail").

``lod_scale = 0`` turns the reduction off (every fiber is expanded; culling stays).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pxr import Gf, Usd, UsdGeom

__all__ = ["CameraView", "FAR_YARN_PIXELS", "camera_view", "far_yarn", "fiber_fraction"]

#: Fibers kept per pixel of yarn diameter at lod_scale 1 (a pixel resolves about this many
#: fiber highlights across a yarn).
FIBERS_PER_PIXEL = 4.0

#: Yarns narrower than this many pixels (at lod_scale 1) are drawn with their far field. Measured
#: on a plain weave at 2.8 px per yarn: the far field's image bias is 0.25 (mean -0.1 %), that of
#: fewer, widened fibers 0.34 (+39 %) at lod_scale 1 (bench/REPORT.md).
FAR_YARN_PIXELS = 3.0


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
    gc = UsdGeom.Camera(cam_prim).GetCamera(time)
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


def fiber_fraction(yarn_pixels: float, fibers: int, *, lod_scale: float = 1.0, min_fibers: int = 8) -> float:
    """Fraction of a yarn's fibers to expand when its diameter covers ``yarn_pixels`` pixels."""
    if lod_scale <= 0 or fibers <= 0:
        return 1.0
    keep = max(float(min_fibers), lod_scale * FIBERS_PER_PIXEL * yarn_pixels)
    return float(min(1.0, keep / fibers))


def far_yarn(yarn_pixels: float, *, lod_scale: float = 1.0) -> bool:
    """Whether a yarn whose diameter covers ``yarn_pixels`` pixels is drawn with its far field."""
    return lod_scale > 0 and yarn_pixels * lod_scale < FAR_YARN_PIXELS
