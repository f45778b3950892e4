"""Cloth prims as volumes in a Mitsuba scene: ``render --cloth volume|fibers|auto`` (:func:`split_cloth`,
:func:`translate_volumes`).

* ``fibers`` (the default): every fiber and yarn prim as curves (explicit fibers, or the
  yarn far field for small yarns: :mod:`usdfiber.translators.mitsuba.lod`).
* ``volume``: every fiber and yarn prim as a voxelized medium
  (:mod:`usdfiber.geometry.voxelize`, :mod:`.medium`): its fibers (yarns expanded at full
  detail) are voxelized with voxels the size of the pixel footprint at the prim's nearest
  point (``voxels_per_pixel`` per footprint; never thinner than a fiber), one grid per prim.
  Yarns at most :data:`ANALYTIC_YARN_VOXELS` voxels wide are voxelized from the yarn model's
  fiber density without expanding a fiber (:mod:`usdfiber.geometry.yarn_density`: the cost
  follows the yarn length over the voxel size, which makes garments possible). Yarn prims with
  ``yarn:expandFibers = false`` keep their far-field curves.
* ``auto``: per prim, yarns narrower than :data:`VOLUME_YARN_PIXELS` become a volume, larger
  ones keep the curve levels of detail (explicit fibers, or the far field below 3 pixels);
  fiber prims stay curves. The choice is reported per prim.

Volumes and curves share the scene, so they shadow and light each other; scenes with volumes
render with Mitsuba's ``volpath``, which also lets shadow rays pass non-round fibers
(``eval_null_transmission``) and does not count pass-throughs as bounces.
"""
from __future__ import annotations

import math
import time as _time
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np
from pxr import Usd, UsdGeom

from usdfiber.bake.cache import TableCache
from usdfiber.bake.settings import BakeError, BakeSettings
from usdfiber.bcsdf import tables_for_prim
from usdfiber.geometry.curves import CurveError, axis_scales, curves_from_prim
from usdfiber.geometry.voxelize import (DEFAULT_BUDGET_BYTES, VoxelGrid, VoxelizeError, polylines_from_segments,
                                        voxel_size_for_footprint, voxelize_fibers)
from usdfiber.geometry.yarn_density import YarnCurve, voxelize_yarns
from usdfiber.spec.fiber import FiberParams, FiberParamsError
from usdfiber.spec.yarn import YarnError, YarnParams

from usdfiber.translators.mitsuba.errors import TranslateError
from usdfiber.translators.mitsuba.fiber_bank import FiberBank, FiberSlot
from usdfiber.translators.mitsuba.fibers import translate_fibers, yarn_polylines
from usdfiber.translators.mitsuba.lod import CameraView
from usdfiber.translators.mitsuba.volume.medium import BRICK_VOXELS, cloth_shapes

__all__ = ["ANALYTIC_YARN_VOXELS", "CLOTH_MODES", "VOLUME_YARN_PIXELS", "VolumeTranslation", "near_plane_warning", "split_cloth",
           "translate_volumes"]

CLOTH_MODES = ("fibers", "volume", "auto")
#: ``auto``: yarns whose diameter covers fewer pixels than this are drawn as a volume.
VOLUME_YARN_PIXELS = 1.0
#: Yarns at most this many voxels wide are voxelized from their fiber density (no expansion).
ANALYTIC_YARN_VOXELS = 4.0
#: Without a camera, a volume's voxel is this many fiber diameters.
DEFAULT_VOXEL_FIBERS = 8.0


@dataclass
class VolumeTranslation:
    """The volumes of a stage: scene entries, their grids and what was chosen per prim."""

    entries: dict[str, Any] = field(default_factory=dict)
    grids: dict[str, VoxelGrid] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    counts: dict[str, int] = field(default_factory=dict)
    table_seconds: float = 0.0


def _prim_points(pl: Any, time: Usd.TimeCode) -> np.ndarray:
    pts = np.asarray(UsdGeom.BasisCurves(pl.prim).GetPointsAttr().Get(time) or [], np.float64).reshape(-1, 3)
    if not len(pts):
        return pts
    xf = np.asarray(pl.xform, np.float64)
    return pts @ xf[:3, :3] + xf[3, :3]


def split_cloth(placements: Sequence[Any], mode: str, view: CameraView | None, time: Usd.TimeCode,
                lod_scale: float = 1.0) -> tuple[list[Any], list[Any], list[str]]:
    """(volume placements, curve placements, one line per prim saying what it became)."""
    if mode not in CLOTH_MODES:
        raise TranslateError(f"--cloth {mode!r}: expected one of {', '.join(CLOTH_MODES)}")
    vols, curves, notes = [], [], []
    for pl in placements:
        if mode == "fibers":
            curves.append(pl)
            continue
        if mode == "volume":
            vols.append(pl)
            notes.append(f"{pl.path}: volume (--cloth volume)")
            continue
        if not pl.prim.HasAPI("FiberYarnAPI") or view is None:
            curves.append(pl)
            why = "explicit fiber curves" if view is None or not pl.prim.HasAPI("FiberYarnAPI") else ""
            notes.append(f"{pl.path}: curves ({why or 'no camera'})")
            continue
        try:
            yarn = YarnParams.from_prim(pl.prim, time)
        except YarnError as exc:
            raise TranslateError(str(exc)) from None
        pts = _prim_points(pl, time)
        px = view.pixels(2 * yarn.yarn_radius, pts) if len(pts) else float("inf")
        if px * max(lod_scale, 1e-9) < VOLUME_YARN_PIXELS and lod_scale > 0:
            vols.append(pl)
            notes.append(f"{pl.path}: volume (yarns {px:.2g} px wide, under {VOLUME_YARN_PIXELS:g})")
        else:
            curves.append(pl)
            level = "explicit fibers" if px * lod_scale >= 3 or lod_scale <= 0 else "yarn far field"
            notes.append(f"{pl.path}: {level} (yarns {px:.2g} px wide)")
    return vols, curves, notes


def near_plane_warning(view: CameraView | None, path: str, lo: np.ndarray, hi: np.ndarray) -> str | None:
    """A warning when the camera's near clipping plane cuts the volume box [lo, hi]: camera rays
    then start inside the box, and a medium entered without crossing its boundary is not seen
    (the cloth there renders as empty space). None when it does not."""
    if view is None:
        return None
    near = float(view.frustum.GetNearFar().min)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    depth = (corners - view.position) @ view.forward
    if not (depth.min() < near < depth.max()) or not view.visible(lo, hi):
        return None
    return (f"{path}: the camera's near clipping plane ({near:g} units) cuts the cloth's volume (depths "
            f"{depth.min():g} .. {depth.max():g}): camera rays that start inside it do not see the cloth; "
            f"expected the camera's clippingRange to start below {max(depth.min(), 0.0):g}")


def _voxel_size(pl: Any, fib_pts: np.ndarray, fiber_diameter: float, view: CameraView | None,
                voxels_per_pixel: float, voxel_size: float | None) -> float:
    if voxel_size is not None:
        return float(voxel_size)
    if view is None:
        return DEFAULT_VOXEL_FIBERS * fiber_diameter
    footprint = 1.0 / view.pixels(1.0, fib_pts)
    if not np.isfinite(footprint) or footprint <= 0:
        # The prim reaches behind the camera plane: the finest detail a fiber can carry.
        footprint = fiber_diameter
    return voxel_size_for_footprint(footprint, fiber_diameter=fiber_diameter, per_pixel=voxels_per_pixel)


def _yarn_density_grid(pl: Any, stage: Usd.Stage, time: Usd.TimeCode, yarn: YarnParams, *, settings: BakeSettings,
                       cache: TableCache | None, bake_missing: bool, progress: Callable[..., Any] | None,
                       view: CameraView | None, voxels_per_pixel: float, voxel_size: float | None,
                       budget_bytes: int, seed: int) -> tuple[VoxelGrid, FiberBank, float] | None:
    """A yarn prim voxelized from its fiber density (:mod:`usdfiber.geometry.yarn_density`), with
    its bank of slots (one per cross-section variant, the prim's dye and depth of shade) and
    the table time; None when the yarns are wide enough in voxels to be expanded instead."""
    try:
        params = FiberParams.from_prim(pl.prim, time)
    except FiberParamsError as exc:
        raise TranslateError(str(exc)) from None
    um = 1e-6 / UsdGeom.GetStageMetersPerUnit(stage)
    dia = params.diameter * um
    scale = axis_scales(np.asarray(pl.xform)[:3, :3])[1]
    width = 2 * yarn.yarn_radius
    try:
        geom = curves_from_prim(pl.prim, time, pl.xform, default_width=width / scale if 0 < scale < math.inf else width)
    except CurveError as exc:
        raise TranslateError(str(exc)) from None
    # Centre lines sampled twice per B-spline segment: the samples lie on the curve, far
    # closer together than a voxel (a garment's centre line has ~20 segments per crossing).
    curves = [YarnCurve(pts, rad / yarn.yarn_radius) for pts, rad in yarn_polylines(geom, 2)]
    if not curves:
        return None
    pts = np.concatenate([c.points for c in curves])
    size = _voxel_size(pl, pts, dia, view, voxels_per_pixel, voxel_size)
    widest = 2 * yarn.yarn_radius * max(float(np.max(c.radius_scale)) for c in curves)
    if widest > ANALYTIC_YARN_VOXELS * size:
        return None
    t0 = _time.perf_counter()
    try:
        tables = tables_for_prim(pl.prim, settings, bake_missing, cache=cache, time=time, progress=progress)
    except (BakeError, LookupError) as exc:
        raise TranslateError(f"{pl.path}: {exc}") from None
    seconds = _time.perf_counter() - t0
    bank = FiberBank.build([FiberSlot(t, tuple(float(x) for x in t.sigma_for(params.mu_a, params.diameter)))
                            for t in tables])
    try:
        grid = voxelize_yarns(curves, yarn, size, fiber_diameter=dia, slots=list(range(len(tables))),
                              n_slots=len(tables), budget_bytes=budget_bytes, seed=seed, source=pl.path)
    except VoxelizeError as exc:
        raise TranslateError(str(exc)) from None
    return grid, bank, seconds


def translate_volumes(mi: Any, placements: Sequence[Any], stage: Usd.Stage, time: Usd.TimeCode, *,
                      settings: BakeSettings, cache: TableCache | None = None, bake_missing: bool = True,
                      progress: Callable[..., Any] | None = None, view: CameraView | None = None,
                      voxels_per_pixel: float = 1.0, voxel_size: float | None = None,
                      budget_bytes: int = DEFAULT_BUDGET_BYTES,
                      brick_voxels: int = BRICK_VOXELS) -> tuple[VolumeTranslation, list[Any]]:
    """One voxel grid per prim of ``placements``, as media in bricks of ``brick_voxels``
    voxels (:func:`usdfiber.translators.mitsuba.volume.medium.cloth_shapes`; 0: one medium
    per grid); returns them and the placements left as curves (yarn prims whose far field is
    authored, ``yarn:expandFibers = false``).

    Yarn prims whose yarns are at most :data:`ANALYTIC_YARN_VOXELS` voxels wide are voxelized
    from the yarn model's fiber density, without expanding a fiber; wider yarns (voxels that
    resolve fibers) are expanded and their fibers voxelized."""
    out = VolumeTranslation()
    left: list[Any] = []
    n_vox = n_faces = 0
    voxelize_s = 0.0
    for k, pl in enumerate(placements):
        yarn = None
        if pl.prim.HasAPI("FiberYarnAPI"):
            try:
                yarn = YarnParams.from_prim(pl.prim, time)
            except YarnError as exc:
                raise TranslateError(str(exc)) from None
        if yarn is not None and not yarn.expand:
            out.warnings.append(f"{pl.path}: yarn:expandFibers is false: drawn with its yarn far field, not as a volume")
            left.append(pl)
            continue
        dense = None
        t_vox = _time.perf_counter()
        if yarn is not None:
            dense = _yarn_density_grid(pl, stage, time, yarn, settings=settings, cache=cache,
                                       bake_missing=bake_missing, progress=progress, view=view,
                                       voxels_per_pixel=voxels_per_pixel, voxel_size=voxel_size,
                                       budget_bytes=budget_bytes, seed=k)
        if dense is not None:
            grid, bank, seconds = dense
            out.table_seconds += seconds
            t_vox += seconds
            out.warnings.append(f"{pl.path}: voxelized from the yarn density ({grid.voxel_size:g}-unit voxels, "
                                f"no fibers expanded)")
        else:
            ft = translate_fibers([pl], stage, time, settings=settings, cache=cache, bake_missing=bake_missing,
                                  progress=progress, view=None, lod_scale=0.0)
            if ft is None:
                out.warnings.append(f"{pl.path}: no fibers to voxelize; skipped")
                continue
            out.table_seconds += ft.table_seconds
            t_vox += ft.table_seconds
            out.warnings.extend(ft.warnings)
            bank = ft.bank
            try:
                fib = polylines_from_segments(ft.geometry, ft.seg_slot, ft.seg_psi, ft.seg_ref, source=pl.path)
                size = _voxel_size(pl, fib.points, float(np.median(fib.diameter)), view, voxels_per_pixel, voxel_size)
                grid = voxelize_fibers(fib, size, n_slots=len(ft.bank.slots), budget_bytes=budget_bytes, seed=k)
            except VoxelizeError as exc:
                raise TranslateError(str(exc)) from None
        voxelize_s += _time.perf_counter() - t_vox
        out.warnings.extend(grid.warnings)
        cut = near_plane_warning(view, pl.path, grid.origin, grid.upper)
        if cut:
            out.warnings.append(cut)
        out.grids[pl.path] = grid
        shapes = cloth_shapes(mi, grid, bank, brick=brick_voxels, prefix=f"volume_{k}")
        out.entries.update(shapes)
        n_faces += len(shapes)
        n_vox += grid.occupied
    out.counts = {"volumes": len(out.grids), "voxels_occupied": n_vox, "volume_faces": n_faces,
                  "voxel_bytes": sum(g.nbytes() for g in out.grids.values()),
                  # Fibers or yarn densities to grids, tables excluded (fiber expansion included).
                  "voxelize_ms": int(round(1000 * voxelize_s))}
    return out, left
