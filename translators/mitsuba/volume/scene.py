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
* ``auto``: per yarn prim, the volume only where it is not biased: its yarns narrower than
  :data:`VOLUME_YARN_PIXELS` (a curve would not resolve them) *and* voxels of the footprint
  that keep the weave's gaps. A voxel wider than the gaps between yarns spreads their optical
  depth over them and loses the gaps' transmission (Jensen's inequality;
  :func:`usdfiber.geometry.yarn_density.coverage_map` measures it on a window of the cloth):
  the volume is chosen when it makes the cloth at most :data:`VOLUME_OPACITY_BOUND` more
  opaque than its yarns, else the yarns keep their curve levels of detail (the far field
  below 3 pixels, explicit fibers above), with the predicted excess and the voxel that would
  resolve the gaps in the report. Fiber prims stay curves. Every choice is reported per prim
  (``cloth: PATH: MODE (why)``, also in ``render --json``'s warnings).

``--cloth volume`` on yarns whose voxels exceed the bound warns with the prim, the expected
excess opacity and the voxel size (and grid memory) that would resolve the gaps
(:func:`homogenization_warning`); it does not refine the voxels itself: keeping a sheer
Skala 360 weave within the bound takes voxels of 0.6 yarn diameters (0.065 mm, 8x the voxels
of a 0.13 mm footprint), within 5 % a third of one (64x), at a render cost that grows with
them (bench/REPORT.md, "Where the voxels meet the weave").

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
from usdfiber.geometry.curves import CurveError, CurveGeometry, axis_scales, curves_from_prim
from usdfiber.geometry.voxelize import (DEFAULT_BUDGET_BYTES, VoxelGrid, VoxelizeError, grid_bytes,
                                        polylines_from_segments, voxel_size_for_footprint, voxelize_fibers)
from usdfiber.geometry.yarn_density import CoverageMap, YarnCurve, YarnLines, coverage_map, voxelize_yarns
from usdfiber.memory_budget import format_bytes
from usdfiber.spec.fiber import FiberParams, FiberParamsError
from usdfiber.spec.yarn import YarnError, YarnParams

from usdfiber.translators.mitsuba.errors import TranslateError
from usdfiber.translators.mitsuba.fiber_bank import FiberBank, FiberSlot
from usdfiber.translators.mitsuba.fibers import translate_fibers, yarn_polylines
from usdfiber.translators.mitsuba.lod import CameraView
from usdfiber.translators.mitsuba.volume.medium import BRICK_VOXELS, cloth_shapes

__all__ = ["ANALYTIC_YARN_VOXELS", "CLOTH_MODES", "ClothChoice", "VOLUME_OPACITY_BOUND", "VOLUME_YARN_PIXELS",
           "VolumeTranslation", "homogenization_warning", "near_plane_warning", "split_cloth", "translate_volumes",
           "yarn_coverage"]

CLOTH_MODES = ("fibers", "volume", "auto")
#: ``auto``: yarns whose diameter covers fewer pixels than this are drawn as a volume.
VOLUME_YARN_PIXELS = 1.0
#: ``auto``: the volume only where its voxels make the cloth at most this much more opaque than
#: its yarns (relative excess of 1 - transmittance along the normal, predicted by
#: :func:`yarn_coverage`). Measured (bench/REPORT.md, "Where the voxels meet the weave"): the
#: Figure 7 knits at +10 % predicted rendered -6.3 % in the image mean against explicit fibers
#: (+7 %: -4.4 %), the sheer Skala 360 weave at +30 % rendered +37 to +42 % on the cloth.
VOLUME_OPACITY_BOUND = 0.15
#: Side of the window the coverage is measured on: this many voxels, at least this many yarn
#: diameters (several repeats of a weave or knit either way).
COVERAGE_WINDOW_VOXELS = 6.0
COVERAGE_WINDOW_YARNS = 16.0
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


def _yarn_pixels(pl: Any, time: Usd.TimeCode, view: CameraView, size: float) -> float:
    """``view.pixels(size, points)`` over the prim's world-space control points, reading the
    points array once: the depth's minimum is found from boxes of runs of points, then
    computed exactly on the few runs that may hold it (the same number as over every point)."""
    pts = np.asarray(UsdGeom.BasisCurves(pl.prim).GetPointsAttr().Get(time) or [], np.float32).reshape(-1, 3)
    if not len(pts):
        return math.inf
    if view.pixel_size > 0:
        return view.pixels(size, pts[:1])
    nearest = YarnLines.from_points(pts).nearest_along(view.position, view.forward, np.asarray(pl.xform, np.float64))
    return view.pixels(size, nearest[None])


@dataclass(frozen=True)
class ClothChoice:
    """What ``--cloth`` made of one prim, and why: ``mode`` is ``"volume"``, ``"yarn far
    field"``, ``"explicit fibers"`` or ``"curves"``; the numbers are those the choice was made
    by (None where not needed). ``str()`` is the report line ``PATH: MODE (why)``."""

    path: str
    mode: str
    reason: str
    yarn_pixels: float | None = None
    voxel_size: float | None = None
    opacity_excess: float | None = None
    coverage: float | None = None

    def __str__(self) -> str:
        return f"{self.path}: {self.mode} ({self.reason})"

    def to_json(self) -> dict[str, Any]:
        """The choice as a JSON object."""
        return {k: getattr(self, k) for k in ("path", "mode", "reason", "yarn_pixels", "voxel_size",
                                              "opacity_excess", "coverage")}


def _yarn_geometry(pl: Any, time: Usd.TimeCode, yarn: YarnParams) -> CurveGeometry:
    """The yarn centre curves of a prim in world space (without widths: as wide as the yarn)."""
    scale = axis_scales(np.asarray(pl.xform)[:3, :3])[1]
    width = 2 * yarn.yarn_radius
    try:
        return curves_from_prim(pl.prim, time, pl.xform, default_width=width / scale if 0 < scale < math.inf else width)
    except CurveError as exc:
        raise TranslateError(str(exc)) from None


def _yarn_curves(pl: Any, time: Usd.TimeCode, yarn: YarnParams) -> list[YarnCurve]:
    """The yarn centre lines of a prim in world space, sampled twice per B-spline segment."""
    # The samples lie on the curve, far closer together than a voxel (a garment's centre line
    # has ~20 segments per crossing).
    return [YarnCurve(pts, rad / yarn.yarn_radius) for pts, rad in yarn_polylines(_yarn_geometry(pl, time, yarn), 2)]


def _yarn_lines(pl: Any, time: Usd.TimeCode, yarn: YarnParams) -> YarnLines:
    """The samples of :func:`_yarn_curves` as :class:`YarnLines`: evaluated where a query reads
    them; the curves' control points are read once, for the run boxes."""
    return YarnLines.from_geometry(_yarn_geometry(pl, time, yarn), 2)


def _fiber_diameter(pl: Any, stage: Usd.Stage, time: Usd.TimeCode) -> tuple[FiberParams, float]:
    try:
        params = FiberParams.from_prim(pl.prim, time)
    except FiberParamsError as exc:
        raise TranslateError(str(exc)) from None
    return params, params.diameter * 1e-6 / UsdGeom.GetStageMetersPerUnit(stage)


def yarn_coverage(curves: Sequence[YarnCurve] | YarnLines, yarn: YarnParams, fiber_diameter: float, voxel: float,
                  source: str = "yarns",
                  others: Sequence[tuple[Sequence[YarnCurve] | YarnLines, YarnParams, float]] = ()) -> CoverageMap:
    """The yarns' optical depth map (:func:`usdfiber.geometry.yarn_density.coverage_map`) on a
    window of :data:`COVERAGE_WINDOW_VOXELS` voxels (at least :data:`COVERAGE_WINDOW_YARNS`
    yarn diameters) a side, with the ``others`` yarn prims of the cloth (a weave's wefts for its
    warps: the voxels smear the cloth's gaps, not one prim's): its ``opacity_bias(voxel)`` is
    the volume's predicted excess. Curves as polylines or as
    :class:`~usdfiber.geometry.yarn_density.YarnLines` (read where the window needs them)."""
    window = max(COVERAGE_WINDOW_VOXELS * voxel, COVERAGE_WINDOW_YARNS * 2.0 * yarn.yarn_radius)
    try:
        return coverage_map(curves, yarn, fiber_diameter=fiber_diameter, window=window, others=others,
                            source=source)
    except VoxelizeError as exc:
        raise TranslateError(str(exc)) from None


def _excess(cov: CoverageMap, voxel: float) -> float:
    """The predicted excess opacity; a cloth narrower than two voxels counts as unbounded."""
    b = cov.opacity_bias(voxel)
    return math.inf if not math.isfinite(b) else b


def homogenization_warning(path: str, cov: CoverageMap, voxel: float, yarn_diameter: float, *,
                           box: tuple[np.ndarray, np.ndarray] | None = None, n_slots: int = 1,
                           budget_bytes: int = DEFAULT_BUDGET_BYTES,
                           bound: float = VOLUME_OPACITY_BOUND) -> str | None:
    """One line when voxels of ``voxel`` units make the cloth of ``cov`` more than ``bound``
    more opaque than its yarns: the prim, the expected excess, and the voxel size that keeps
    within the bound (with the memory of a dense grid over ``box`` at that size, and whether
    it fits ``budget_bytes``); None when within the bound."""
    excess = _excess(cov, voxel)
    if excess <= bound:
        return None
    need = cov.voxel_for_bias(voxel, bound)
    mem = ""
    if box is not None:
        ext = np.asarray(box[1], np.float64) - np.asarray(box[0], np.float64)
        shape = tuple(int(max(1, math.ceil(e / need))) for e in ext)
        nbytes = grid_bytes(shape, n_slots)          # type: ignore[arg-type]
        mem = (f", a grid of {format_bytes(nbytes)}, " + ("within" if nbytes <= budget_bytes else "over")
               + f" the budget of {format_bytes(budget_bytes)}")
    what = "more than" if math.isinf(excess) else "about"
    pct = f"{100 * bound:.0f} %" if math.isinf(excess) else f"{100 * excess:.0f} %"
    return (f"{path}: {voxel:.3g}-unit voxels spread the yarns ({yarn_diameter:.3g} units wide, coverage "
            f"{cov.coverage:.2f}) over the gaps between them: the volume is {what} {pct} more opaque than the "
            f"cloth (bound {100 * bound:.0f} %): expect the cloth's pixels off by as much or more (measured +42 % "
            f"at +30 %); voxels "
            f"of {need:.3g} units resolve the gaps{mem}")


def split_cloth(placements: Sequence[Any], mode: str, view: CameraView | None, time: Usd.TimeCode,
                lod_scale: float = 1.0, *, voxels_per_pixel: float = 1.0,
                voxel_size: float | None = None) -> tuple[list[Any], list[Any], list[ClothChoice]]:
    """(volume placements, curve placements, per prim a :class:`ClothChoice` saying what it
    became and why; its ``str()`` is the report line). ``voxels_per_pixel`` and
    ``voxel_size``: as :func:`translate_volumes` will voxelize, for ``auto``'s prediction.

    ``auto``'s cost follows the window, not the cloth: a prim's points are read once for its
    yarns' width in pixels (the nearest point found from boxes of runs of points), and only
    prims of yarns under :data:`VOLUME_YARN_PIXELS` have their curves read, once per prim
    (:class:`~usdfiber.geometry.yarn_density.YarnLines`: boxes over runs of the centre lines'
    samples, the samples evaluated where a query reads them); the footprint at the nearest
    sample and the coverage map (:func:`yarn_coverage`) read the runs that may matter only.
    The 2,500 x 2,500-yarn shirt panel's choice: 24-33 CPU s, most of it reading the curves
    (it was 128-148 s over every sample; bench/REPORT.md, "`--cloth auto`'s prediction,
    bounded by its window")."""
    if mode not in CLOTH_MODES:
        raise TranslateError(f"--cloth {mode!r}: expected one of {', '.join(CLOTH_MODES)}")
    vols, curves, notes = [], [], []
    yarns: dict[str, tuple[YarnLines, YarnParams, float]] = {}

    def yarn_of(pl: Any) -> tuple[YarnLines, YarnParams, float]:
        """A yarn prim's centre lines, parameters and fiber diameter (once per prim)."""
        if pl.path not in yarns:
            try:
                yp = YarnParams.from_prim(pl.prim, time)
            except YarnError as exc:
                raise TranslateError(str(exc)) from None
            yarns[pl.path] = (_yarn_lines(pl, time, yp), yp, _fiber_diameter(pl, pl.prim.GetStage(), time)[1])
        return yarns[pl.path]

    for pl in placements:
        if mode == "fibers":
            curves.append(pl)
            continue
        if mode == "volume":
            vols.append(pl)
            notes.append(ClothChoice(pl.path, "volume", "--cloth volume"))
            continue
        if not pl.prim.HasAPI("FiberYarnAPI") or view is None:
            curves.append(pl)
            why = "explicit fiber curves" if view is None or not pl.prim.HasAPI("FiberYarnAPI") else ""
            notes.append(ClothChoice(pl.path, "curves", why or "no camera"))
            continue
        try:
            yarn = YarnParams.from_prim(pl.prim, time)
        except YarnError as exc:
            raise TranslateError(str(exc)) from None
        px = _yarn_pixels(pl, time, view, 2 * yarn.yarn_radius)
        curve_level = "explicit fibers" if px * lod_scale >= 3 or lod_scale <= 0 else "yarn far field"
        if not (px * max(lod_scale, 1e-9) < VOLUME_YARN_PIXELS and lod_scale > 0):
            curves.append(pl)
            notes.append(ClothChoice(pl.path, curve_level, f"yarns {px:.2g} px wide", yarn_pixels=px))
            continue
        lines, _, dia = yarn_of(pl)
        if lines.curve_count == 0:
            curves.append(pl)
            notes.append(ClothChoice(pl.path, curve_level, "no yarn curves to voxelize", yarn_pixels=px))
            continue
        # The footprint at the nearest sample is the footprint over all of them.
        nearest = lines.nearest_along(view.position, view.forward)[None]
        size = _voxel_size(pl, nearest, dia, view, voxels_per_pixel, voxel_size)
        others = [yarn_of(o) for o in placements if o is not pl and o.prim.HasAPI("FiberYarnAPI")]
        cov = yarn_coverage(lines, yarn, dia, size, source=pl.path, others=others)
        excess = _excess(cov, size)
        if excess <= VOLUME_OPACITY_BOUND:
            vols.append(pl)
            notes.append(ClothChoice(pl.path, "volume", f"yarns {px:.2g} px wide, under {VOLUME_YARN_PIXELS:g}; "
                                     f"{size:.3g}-unit voxels make the cloth {100 * excess:.0f} % more opaque, "
                                     f"within {100 * VOLUME_OPACITY_BOUND:.0f} % (coverage {cov.coverage:.2f})",
                                     px, size, excess, cov.coverage))
        else:
            curves.append(pl)
            pred = (f"over half the cloth's width ({cov.tau.shape[0] * cov.texel:.3g} units): a blur of a few voxels"
                    if math.isinf(excess) else f"{100 * excess:.0f} % more opaque")
            notes.append(ClothChoice(pl.path, curve_level, f"yarns {px:.2g} px wide; not a volume: its "
                                     f"{size:.3g}-unit voxels would spread the yarns over the gaps (coverage "
                                     f"{cov.coverage:.2f}): {pred}, over the bound of "
                                     f"{100 * VOLUME_OPACITY_BOUND:.0f} %; "
                                     f"voxels of {cov.voxel_for_bias(size, VOLUME_OPACITY_BOUND):.3g} units "
                                     f"resolve them",
                                     px, size, excess, cov.coverage))
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


def _yarn_density_grid(pl: Any, stage: Usd.Stage, time: Usd.TimeCode, yarn: YarnParams, curves: list[YarnCurve], *,
                       settings: BakeSettings, cache: TableCache | None, bake_missing: bool,
                       progress: Callable[..., Any] | None, view: CameraView | None, voxels_per_pixel: float,
                       voxel_size: float | None, budget_bytes: int,
                       seed: int) -> tuple[VoxelGrid, FiberBank, float] | None:
    """A yarn prim (its centre lines ``curves``, :func:`_yarn_curves`) voxelized from its fiber
    density (:mod:`usdfiber.geometry.yarn_density`), with its bank of slots (one per
    cross-section variant, the prim's dye and depth of shade) and the table time; None when
    the yarns are wide enough in voxels to be expanded instead."""
    params, dia = _fiber_diameter(pl, stage, time)
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
    # Every yarn prim's centre lines first: each prim's homogenization is measured with the rest
    # of the cloth.
    cloth_yarns: dict[str, tuple[list[YarnCurve], YarnParams, float]] = {}
    for pl in placements:
        if pl.prim.HasAPI("FiberYarnAPI"):
            try:
                yp = YarnParams.from_prim(pl.prim, time)
            except YarnError as exc:
                raise TranslateError(str(exc)) from None
            if yp.expand:
                cloth_yarns[pl.path] = (_yarn_curves(pl, time, yp), yp, _fiber_diameter(pl, stage, time)[1])
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
        yarn_curves: list[YarnCurve] = []
        if yarn is not None:
            yarn_curves = cloth_yarns[pl.path][0]
            dense = _yarn_density_grid(pl, stage, time, yarn, yarn_curves, settings=settings, cache=cache,
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
        if yarn_curves:
            # The weave's gaps against the voxel (module docstring): never a silent bias. The
            # other yarn prims voxelized with it are the rest of the cloth.
            others = [cloth_yarns[o.path] for o in placements if o is not pl and o.path in cloth_yarns]
            cov = yarn_coverage(yarn_curves, yarn, _fiber_diameter(pl, stage, time)[1], grid.voxel_size,
                                source=pl.path, others=others)
            msg = homogenization_warning(pl.path, cov, grid.voxel_size, 2 * yarn.yarn_radius,
                                         box=(grid.origin, grid.upper), n_slots=len(bank.slots),
                                         budget_bytes=budget_bytes)
            if msg:
                out.warnings.append(msg)
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
