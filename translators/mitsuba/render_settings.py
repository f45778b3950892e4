"""Stage-level render settings (``UsdRender.Settings``) and world bounds for translation.

Also holds the small helpers the other translator modules share: time-code coercion and the
USD -> Mitsuba matrix conversion (the errors are in :mod:`usdfiber.translators.mitsuba.errors`).

How the samples per pixel are specified
---------------------------------------
``UsdRender.Settings`` has no sample-count attribute (renderers add their own, e.g.
``ri:hider:maxsamples`` or ``karma:global:pathtracedsamples``). usdfiber reads the custom
attribute ``int usdfiber:samplesPerPixel`` from the RenderProduct (first listed in
``products``) if authored there, else from the RenderSettings prim. Unauthored -> ``None``
(the caller picks its default).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdRender

from usdfiber.translators.mitsuba.errors import TranslationError

__all__ = [
    "RenderSettingsInfo",
    "SPP_ATTR",
    "as_timecode",
    "read_render_settings",
    "stage_bbox",
    "to_mi_transform",
]

#: Custom attribute (on a RenderSettings or RenderProduct prim) holding samples per pixel.
SPP_ATTR = "usdfiber:samplesPerPixel"
#: Most samples per pixel of a render (stage or command line): 2^20, far above any
#: production setting; beyond it a typing error would run for days (Mitsuba itself takes
#: up to 2^32 - 1).
MAX_SPP = 1 << 20
#: Most pixels of an image (16384 x 16384): the film, its passes and the written EXR must
#: fit in memory.
MAX_PIXELS = 1 << 28


def as_timecode(time: Usd.TimeCode | float | None) -> Usd.TimeCode:
    """``None`` -> the default time code; a number -> that time; a TimeCode unchanged."""
    if time is None:
        return Usd.TimeCode.Default()
    if isinstance(time, Usd.TimeCode):
        return time
    return Usd.TimeCode(float(time))


def to_mi_transform(xform: np.ndarray):
    """USD row-vector 4x4 (``p' = [p, 1] @ M``) -> ``mi.ScalarTransform4f`` (column vectors).

    Mitsuba applies ``M_mi @ [p, 1]^T``, so ``M_mi = M_usd^T``.
    """
    from usdfiber.backend import mitsuba

    mi = mitsuba()
    m = np.asarray(xform, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"expected a (4, 4) transform, got shape {m.shape}")
    return mi.ScalarTransform4f(m.T.tolist())


@dataclass(frozen=True)
class RenderSettingsInfo:
    """What a render needs from a ``UsdRender.Settings`` prim (values after product overrides).

    ``path`` is ``None`` when the stage has no render settings; every other field then holds
    the UsdRender schema fallback (resolution 2048x1080, pixel aspect 1, policy
    ``expandAperture``) or ``None``.
    """

    path: Sdf.Path | None
    resolution: tuple[int, int] = (2048, 1080)
    camera: Sdf.Path | None = None
    pixel_aspect_ratio: float = 1.0
    aspect_ratio_conform_policy: str = "expandAperture"
    samples_per_pixel: int | None = None
    #: ``dataWindowNDC`` (xmin, ymin, xmax, ymax); (0, 0, 1, 1) = the whole image.
    data_window_ndc: tuple[float, float, float, float] = (0.0, 0.0, 1.0, 1.0)
    disable_depth_of_field: bool = False
    included_purposes: tuple[str, ...] = ("default", "render")
    product: Sdf.Path | None = None
    warnings: list[str] = field(default_factory=list)


def _authored(attr: Usd.Attribute) -> bool:
    return bool(attr) and attr.HasAuthoredValue()


def read_render_settings(stage: Usd.Stage, path: str | Sdf.Path | None = None) -> RenderSettingsInfo:
    """Read the render settings at ``path``, or at the stage's ``renderSettingsPrimPath``.

    Per UsdRender, a RenderProduct inherits the settings' ``resolution``, ``camera``,
    ``pixelAspectRatio``, ``aspectRatioConformPolicy``, ``dataWindowNDC`` and
    ``disableDepthOfField`` and may override them: values authored on the first product of
    ``products`` win. The camera is the first target of the ``camera`` relationship.
    No ``path`` and no ``renderSettingsPrimPath`` metadata -> schema fallbacks (``path`` None).
    Raises :class:`TranslationError` when ``path`` (explicit or from metadata) is not a
    RenderSettings prim.
    """
    if path is None:
        meta = stage.GetMetadata("renderSettingsPrimPath") if stage.HasAuthoredMetadata(
            "renderSettingsPrimPath") else ""
        if not meta:
            return RenderSettingsInfo(path=None)
        path = meta
    sdf_path = Sdf.Path(str(path))
    prim = stage.GetPrimAtPath(sdf_path)
    if not prim or not prim.IsA(UsdRender.Settings):
        raise TranslationError(sdf_path, None, "is not a UsdRender.Settings prim")
    settings = UsdRender.Settings(prim)
    warnings: list[str] = []

    product: UsdRender.Product | None = None
    targets = settings.GetProductsRel().GetForwardedTargets()
    if targets:
        p = stage.GetPrimAtPath(targets[0])
        if p and p.IsA(UsdRender.Product):
            product = UsdRender.Product(p)
        else:
            warnings.append(f"{sdf_path}.products: {targets[0]} is not a RenderProduct; ignored")
        if len(targets) > 1:
            warnings.append(f"{sdf_path}.products: {len(targets)} products; only {targets[0]} is used")

    def pick(getter: str):
        """The product's value if authored there, else the settings' (or its fallback)."""
        if product is not None:
            attr = getattr(product, getter)()
            if _authored(attr):
                return attr.Get()
        return getattr(settings, getter)().Get()

    def pick_camera() -> Sdf.Path | None:
        for base in ([product] if product is not None else []) + [settings]:
            cams = base.GetCameraRel().GetForwardedTargets()
            if cams:
                return cams[0]
        return None

    res = pick("GetResolutionAttr")
    resolution = (int(res[0]), int(res[1])) if res is not None else (2048, 1080)
    if resolution[0] <= 0 or resolution[1] <= 0 or resolution[0] * resolution[1] > MAX_PIXELS:
        raise TranslationError(sdf_path, "resolution", f"must be positive with at most {MAX_PIXELS} pixels "
                               f"(16384 x 16384), got {resolution}")
    pixel_aspect = float(pick("GetPixelAspectRatioAttr") or 1.0)
    policy = str(pick("GetAspectRatioConformPolicyAttr") or "expandAperture")
    dw = pick("GetDataWindowNDCAttr")
    data_window = tuple(float(v) for v in dw) if dw is not None else (0.0, 0.0, 1.0, 1.0)
    no_dof = bool(pick("GetDisableDepthOfFieldAttr") or False)
    purposes = settings.GetIncludedPurposesAttr().Get()
    purposes_t = tuple(str(p) for p in purposes) if purposes is not None else ("default", "render")

    spp: int | None = None
    for base in ([product.GetPrim()] if product is not None else []) + [prim]:
        attr = base.GetAttribute(SPP_ATTR)
        if _authored(attr):
            value = attr.Get()
            if not isinstance(value, int) or isinstance(value, bool) or not 0 < value <= MAX_SPP:
                raise TranslationError(base.GetPath(), SPP_ATTR,
                                       f"must be an int from 1 to {MAX_SPP}, got {value!r}")
            spp = value
            break

    return RenderSettingsInfo(
        path=sdf_path,
        resolution=resolution,
        camera=pick_camera(),
        pixel_aspect_ratio=pixel_aspect,
        aspect_ratio_conform_policy=policy,
        samples_per_pixel=spp,
        data_window_ndc=data_window,  # type: ignore[arg-type]
        disable_depth_of_field=no_dof,
        included_purposes=purposes_t,
        product=product.GetPath() if product is not None else None,
        warnings=warnings,
    )


def stage_bbox(
    stage: Usd.Stage,
    time: Usd.TimeCode | float | None = None,
    purposes: Iterable[str] = ("default", "render"),
) -> tuple[np.ndarray, np.ndarray] | None:
    """World-space (min, max) of the visible geometry (UsdGeom.Gprim prims), or None if none.

    Uses ``UsdGeom.BBoxCache`` (extents, or extents computed from points when not authored),
    per gprim so that boundable lights (Rect/Sphere/Disk lights have extents) do not count.
    Invisible prims (``ComputeVisibility``) and purposes not in ``purposes`` are skipped;
    instance proxies are traversed.
    """
    tc = as_timecode(time)
    purpose_tokens = [str(p) for p in purposes]
    cache = UsdGeom.BBoxCache(tc, purpose_tokens, useExtentsHint=False)
    total = Gf.Range3d()
    it = iter(Usd.PrimRange.Stage(stage, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)))
    for prim in it:
        img = UsdGeom.Imageable(prim)
        if img and img.ComputeVisibility(tc) == UsdGeom.Tokens.invisible:
            it.PruneChildren()
            continue
        if prim.IsA(UsdGeom.Gprim):
            it.PruneChildren()
            if str(img.ComputePurpose()) not in purpose_tokens:
                continue
            rng = cache.ComputeWorldBound(prim).ComputeAlignedRange()
            if not rng.IsEmpty():
                total.UnionWith(rng)
    if total.IsEmpty():
        return None
    return np.array(total.GetMin(), dtype=np.float64), np.array(total.GetMax(), dtype=np.float64)

