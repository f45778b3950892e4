"""Fiber curves of a stage -> one curve shape with the tabulated BCSDF (:func:`translate_fibers`).

Every fiber prim (BasisCurves with FiberAPI) contributes its curves to ONE Mitsuba
B-spline shape that carries ONE ``usdfiber_bcsdf`` instance: the BSDF looks up, per curve
segment, the slot (cross-section table and colour), the rotation ``psi`` and the azimuthal
reference. Prims that share a fiber description share its tables; prims that share a
colour share a slot.

Per fiber (curve), following the paper's Section 5:

* the cross-section variant is drawn uniformly among the prim's tables and ``psi`` uniformly
  in [0, 360) degrees plus ``fiber:rotation`` (or ``psi = fiber:rotation`` when
  ``fiber:rotation:random`` is false), from ``fiber:seed``, the placement's path and the
  curve index: deterministic, and different for different prims with the same seed;
* the colour is the prim's dye and depth of shade at the render's time code, applied to
  the variant's table as the effective absorption ``mu_a * D / D_baked`` (no re-baking).
"""
from __future__ import annotations

import math
import time as _time
import zlib
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, Sequence

import numpy as np
from pxr import Usd, UsdGeom

from usdfiber.bake.settings import BakeError, BakeSettings
from usdfiber.bake.cache import TableCache
from usdfiber.bake.table import BcsdfTable
from usdfiber.bcsdf import tables_for_prim
from usdfiber.geometry.curves import (CurveError, CurveGeometry, axis_scales, concatenate, curves_from_prim,
                                      evaluate, reference_normals)
from usdfiber.geometry.expanded_fibers import ExpandedFibers
from usdfiber.geometry.yarn import BYTES_PER_POINT, ExpansionEstimate, estimate_expansion, expand_yarn
from usdfiber.memory_budget import MemoryBudget, format_bytes
from usdfiber.spec.fiber import FiberParams, FiberParamsError
from usdfiber.spec.yarn import YarnError, YarnParams

from usdfiber.translators.mitsuba.errors import TranslateError
from usdfiber.translators.mitsuba.fiber_bank import FiberBank, FiberSlot
from usdfiber.translators.mitsuba.lod import CameraView, LodPolicy
from usdfiber.translators.mitsuba.profile import TranslationProfile
from usdfiber.translators.mitsuba.yarn_far_field import (YarnBakeSettings, YarnFarField, YarnFarFieldCache,
                                                         far_field_entry)

__all__ = ["FiberTranslation", "fiber_prim", "pixel_polyline", "translate_fibers", "yarn_polylines"]


def fiber_prim(prim: Usd.Prim) -> bool:
    """Whether ``prim`` is a fiber prim (BasisCurves with FiberAPI)."""
    return prim.IsA(UsdGeom.BasisCurves) and prim.HasAPI("FiberAPI")


@dataclass
class FiberTranslation:
    """The fiber curves of a stage, ready for :func:`usdfiber.translators.mitsuba.fiber_bsdf.fiber_bsdf`."""

    geometry: CurveGeometry
    bank: FiberBank
    seg_slot: np.ndarray          # (S,) slot of each segment
    seg_psi: np.ndarray           # (S,) radians
    seg_ref: np.ndarray           # (S, 3) azimuthal reference normals
    prims: list[str] = field(default_factory=list)
    tables: list[BcsdfTable] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    yarns: dict[str, int] = field(default_factory=dict)   # yarn expansion and LOD counts
    far_fields: list[dict[str, Any]] = field(default_factory=list)  # per yarn prim: traced, cached or skipped, why
    table_seconds: float = 0.0    # time spent finding, loading and baking tables

    @property
    def curve_count(self) -> int:
        return int(self.geometry.curve_count)

    @property
    def segment_count(self) -> int:
        return self.geometry.segment_count


def _scene_units_per_um(stage: Usd.Stage) -> float:
    return 1e-6 / UsdGeom.GetStageMetersPerUnit(stage)


def _fiber_draws(params: FiberParams, path: str, n_curves: int, n_variants: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-curve cross-section variant and rotation psi (radians), deterministic."""
    rng = np.random.default_rng([params.seed & 0xFFFFFFFF, zlib.crc32(path.encode())])
    variant = rng.integers(0, n_variants, n_curves) if n_variants > 1 else np.zeros(n_curves, np.int64)
    base = math.radians(params.rotation)
    if params.rotation_random:
        psi = rng.uniform(0.0, 2.0 * math.pi, n_curves) + base
    else:
        psi = np.full(n_curves, base)
    return variant, np.mod(psi, 2.0 * math.pi)


def _curve_segments(geom: CurveGeometry) -> Iterator[np.ndarray]:
    """The segment indices of each curve of ``geom``, one curve at a time (segments are ordered
    by curve, so a curve's segments are one contiguous run); empty curves are skipped."""
    ends = np.cumsum(np.bincount(geom.segment_curve, minlength=geom.curve_count))
    for c in range(geom.curve_count):
        ss = np.arange(ends[c - 1] if c else 0, ends[c])
        if len(ss):
            yield ss


def _sample_curve(geom: CurveGeometry, ss: np.ndarray, per_segment: int) -> tuple[np.ndarray, np.ndarray]:
    """A curve (its segments ``ss``) sampled ``per_segment`` times per segment plus its end:
    (points (M, 3), radii (M,))."""
    t = np.linspace(0.0, 1.0, per_segment, endpoint=False)
    P, R, _ = evaluate(geom, np.repeat(ss, per_segment), np.tile(t, len(ss)))
    end_p, end_r, _ = evaluate(geom, ss[-1:], np.ones(1))
    return np.concatenate([P, end_p]), np.concatenate([R, end_r])


def yarn_polylines(geom: CurveGeometry, per_segment: int = 8) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Each yarn centre curve sampled densely, one curve at a time: (points (M, 3), radii (M,)),
    so that memory follows one yarn, not the whole prim."""
    for ss in _curve_segments(geom):
        yield _sample_curve(geom, ss, per_segment)


def pixel_polyline(pts: np.ndarray, spacing: float) -> np.ndarray:
    """The samples of a dense polyline about ``spacing`` apart along it (both ends kept)."""
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= spacing or not math.isfinite(spacing) or spacing <= 0:
        return pts[[0, -1]] if s[-1] <= spacing else pts
    k = np.floor(s / spacing).astype(np.int64)
    keep = np.flatnonzero(np.diff(k, prepend=-1) > 0)
    if keep[-1] != len(pts) - 1:
        keep = np.append(keep, len(pts) - 1)
    return pts[keep]


#: Bytes per fiber curve segment of a render: the expansion's peak (``BYTES_PER_POINT``), the
#: concatenated curves and per-segment arrays (slot, psi, reference normal), and Mitsuba's own
#: curve shape and BVH (about 170 B per segment, 1.7 GB at 1e7 segments; the field notes).
RENDER_BYTES_PER_SEGMENT = BYTES_PER_POINT + 250


@dataclass
class _YarnPlan:
    """What a yarn prim becomes, decided before any fiber is made: the yarns to expand
    (segment run, fraction of fibers, estimate), the far-field yarns as authored curves
    (``far_curves``, indices) or as polylines sampled about once per pixel (``far_lines``)."""

    expand: list[tuple[int, np.ndarray, float, ExpansionEstimate]]
    far_curves: np.ndarray
    far_lines: list[tuple[np.ndarray, float]]
    stats: dict[str, int]

    @property
    def far_count(self) -> int:
        return len(self.far_curves) + len(self.far_lines)

    def estimate(self, scale: float = 1.0) -> ExpansionEstimate:
        """The fibers of every expanded yarn, with their fractions multiplied by ``scale``."""
        total = ExpansionEstimate(0, 0)
        for _, _, fraction, est in self.expand:
            total = total + _scaled(est, fraction, scale)
        return total


def _scaled(est: ExpansionEstimate, fraction: float, scale: float) -> ExpansionEstimate:
    """An expansion estimate at ``fraction`` scaled to ``fraction * scale`` (the counts are
    proportional to the fraction; never below one curve)."""
    if scale >= 1.0:
        return est
    k = max(scale, 1.0 / max(1.0, est.curves))
    return ExpansionEstimate(max(1, int(math.ceil(est.curves * k))), int(math.ceil(est.points * k)))


def _plan_yarns(geom: CurveGeometry, yarn: YarnParams, view: CameraView | None, lod_scale: float,
                policy: LodPolicy, profile: TranslationProfile) -> _YarnPlan:
    """Decide the level of detail of each yarn curve of a prim (lod.py), and estimate the
    fibers of those to expand (``estimate_expansion``), without making any.

    Yarns narrower than ``policy.far_yarn_pixels`` / ``lod_scale`` pixels, yarns outside the
    view but near it (``culled``: they still cast shadows,
    :meth:`usdfiber.translators.mitsuba.lod.LodPolicy.out_of_view`), and
    every yarn when ``yarn:expandFibers`` is false are drawn with the yarn's far field instead;
    yarns far outside the view are left out (``skipped``).
    """
    expand: list[tuple[int, np.ndarray, float, ExpansionEstimate]] = []
    far_curves: list[int] = []
    far_lines: list[tuple[np.ndarray, float]] = []
    stats = {"yarns": 0, "culled": 0, "skipped": 0, "fibers": 0, "fibers_full": 0, "far": 0, "degenerate": 0}
    for k, ss in enumerate(_curve_segments(geom)):
        # Two samples per segment decide visibility and size; only a yarn that is expanded
        # needs the dense centre line (a garment's far yarns would spend minutes on it).
        pts, rad = profile.call("centre_sampling", _sample_curve, geom, ss, 2)
        stats["yarns"] += 1
        r = float(rad.max())
        # A yarn of no width or no length has no fibers to draw (`usdfiber check` warns of a
        # zero-length curve; widths of 0 are allowed): left out, as a fiber curve of width 0 is.
        length = float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())
        if not (r > 0 and length > 1e-12 * (1.0 + float(np.abs(pts).max()))):
            stats["degenerate"] += 1
            continue
        fraction = 1.0
        if view is not None:
            n_px = view.pixels(2 * r, pts)
            where = policy.out_of_view(view, pts.min(axis=0) - r, pts.max(axis=0) + r, 2 * r)
            if where == "skip":
                stats["skipped"] += 1
                continue
            if where == "proxy":
                # Out of view, a yarn near it still shadows the view and lights it indirectly: it
                # stays as a far-field proxy, sampled as if seen (leaving it out made a close-up
                # of a weave 6 % too bright: bench/REPORT.md).
                stats["culled"] += 1
                far_lines.append((pixel_polyline(pts, max(2 * r / n_px, 2 * r)), r))
                continue
            if policy.far_yarn(n_px, lod_scale=lod_scale):
                # A yarn this small needs no more than a sample per pixel along it (its crimp
                # and bends are sub-pixel): a yarn of a garment seen whole shrinks from
                # thousands of segments to its length in pixels.
                far_lines.append((pixel_polyline(pts, 2 * r / n_px), r))
                continue
            fraction = policy.fiber_fraction(n_px, yarn.fiber_count, lod_scale=lod_scale)
        if not yarn.expand:
            far_curves.append(int(geom.segment_curve[ss[0]]))
            continue
        # The expansion samples the centre line 4x as densely as these samples (8 per segment).
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        est = estimate_expansion(yarn, float(seg.sum()), float(np.median(seg)) / 4.0 if len(seg) else 0.0,
                                 fiber_fraction=fraction)
        expand.append((k, ss, fraction, est))
    stats["far"] = len(far_curves) + len(far_lines) - stats["culled"]
    return _YarnPlan(expand, np.asarray(far_curves, np.int64), far_lines, stats)


def _expand_yarns(geom: CurveGeometry, plan: _YarnPlan, yarn: YarnParams, fiber_diameter: float,
                  instance_id: int, policy: LodPolicy, profile: TranslationProfile,
                  scale: float = 1.0) -> CurveGeometry:
    """The fiber curves of the yarns ``plan`` expands (:mod:`usdfiber.geometry.yarn`), each at
    its fraction of fibers times ``scale`` (the memory budget's reduction; at least one fiber)."""
    parts = []
    for k, ss, fraction, _ in plan.expand:
        if scale < 1.0:
            fraction = max(fraction * scale, 1.0 / yarn.fiber_count)
        pts, rad = profile.call("centre_sampling", _sample_curve, geom, ss, 8)
        ex = profile.call("expand_yarn", expand_yarn, pts, rad / yarn.yarn_radius, yarn, fiber_fraction=fraction,
                          seed_offset=instance_id * 1_000_003 + k)
        plan.stats["fibers"] += ex.curve_count
        plan.stats["fibers_full"] += int(round(ex.curve_count / fraction))
        # Fewer fibers (never fewer than half) are widened to keep the yarn's coverage (lod.py).
        parts.append(ex.to_curve_geometry(fiber_diameter * policy.fiber_widening(fraction)))
    return profile.call("concatenate", concatenate, parts) if parts else _no_curves()


def _no_curves() -> CurveGeometry:
    return CurveGeometry(np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int64), 0)


def _far_yarn_curves(geom: CurveGeometry, levels: _YarnPlan, yarn: YarnParams, bound_radius: float,
                     profile: TranslationProfile) -> CurveGeometry:
    """The far-field yarn curves of a prim, widened to the far field's bounding radius
    (``bound_radius`` for the nominal yarn radius; authored widths scale it)."""
    scale = bound_radius / yarn.yarn_radius
    parts = []
    if len(levels.far_curves):
        keep = np.isin(geom.segment_curve, levels.far_curves)
        parts.append(CurveGeometry(geom.points, geom.radii * scale, geom.segment_start[keep],
                                   geom.segment_curve[keep], geom.curve_count, []))
    if levels.far_lines:
        # The samples as B-spline control points, with the yarn module's phantom end points.
        lines = [p for p, _ in levels.far_lines]
        counts = np.array([len(p) for p in lines], np.int64)
        ex = ExpandedFibers(np.concatenate(lines), counts, np.zeros(len(lines), np.int64),
                            np.zeros(len(lines), np.int64))
        g = ex.to_curve_geometry(1.0)
        g.radii = np.repeat([r * scale for _, r in levels.far_lines], counts + 2)
        parts.append(g)
    return profile.call("concatenate", concatenate, parts)


def translate_fibers(placements: Sequence[Any], stage: Usd.Stage, time: Usd.TimeCode, *,
                     settings: BakeSettings, cache: TableCache | None = None, bake_missing: bool = True,
                     progress: Callable[..., Any] | None = None, view: CameraView | None = None,
                     lod_scale: float = 1.0, yarn_settings: YarnBakeSettings | None = None,
                     lod: LodPolicy | None = None, profile: TranslationProfile | None = None,
                     memory_budget: MemoryBudget | None = None,
                     warnings_out: list[str] | None = None) -> FiberTranslation | None:
    """The fiber curves of ``placements`` (:class:`usdfiber.translators.mitsuba.stage_walk.Placement` of fiber
    prims) with their tables (baked with ``settings`` when missing); None without fibers (the
    warnings, e.g. of yarns left out, then go to ``warnings_out``).

    Yarn prims (FiberYarnAPI) are expanded into fiber curves (:mod:`usdfiber.geometry.yarn`)
    with the level of detail of ``view`` (:mod:`usdfiber.translators.mitsuba.lod`, the policy ``lod``
    scaled by ``lod_scale``; view None: every yarn at full detail); yarns too small to resolve, and those with ``yarn:expandFibers`` false, are
    drawn as one curve each with the yarn's far field (:mod:`.yarn_far_field`, traced with
    ``yarn_settings`` when missing).

    Yarn fibers are estimated before any is made and kept within ``memory_budget`` (default
    :meth:`MemoryBudget.resolve`): over it, every expanded yarn keeps the same smaller share of
    its fibers, with a warning saying how much; when even one fiber per yarn does not fit, a
    MemoryBudgetError gives the estimate.

    Raises TranslateError for prims that cannot be rendered (unresolvable fiber values,
    malformed curves, yarn curves, tables that cannot be baked). ``profile`` gets the time of
    each step (:mod:`usdfiber.translators.mitsuba.profile`).
    """
    lod = lod or LodPolicy()
    profile = profile or TranslationProfile()
    parts: list[CurveGeometry] = []
    seg_slot: list[np.ndarray] = []
    seg_psi: list[np.ndarray] = []
    slots: list[FiberSlot] = []
    slot_ids: dict[tuple, int] = {}
    tables_by_key: dict[tuple, list[BcsdfTable]] = {}
    all_tables: list[BcsdfTable] = []
    warnings: list[str] = []
    prims: list[str] = []
    table_seconds = 0.0
    yarn_stats: list[dict[str, int]] = []
    um = _scene_units_per_um(stage)
    cache = cache or TableCache()
    far_cache = YarnFarFieldCache(cache)
    yarn_settings = yarn_settings or YarnBakeSettings()

    pending: list[tuple] = []
    far_report: list[dict[str, Any]] = []

    def add_fibers(path: str, params: FiberParams, geom: CurveGeometry, slot_of_variant: np.ndarray,
                   n_variants: int) -> None:
        if geom.segment_count == 0:
            return
        variant, psi = _fiber_draws(params, path, geom.curve_count, n_variants)
        parts.append(geom)
        seg_slot.append(slot_of_variant[variant[geom.segment_curve]])
        seg_psi.append(psi[geom.segment_curve])
        prims.append(path)

    def slot_id(table: Any, sigma: tuple[float, ...]) -> int:
        sk = (id(table), sigma)
        if sk not in slot_ids:
            slot_ids[sk] = len(slots)
            slots.append(FiberSlot(table, sigma))  # type: ignore[arg-type]
        return slot_ids[sk]

    for pl in placements:
        prim = pl.prim
        try:
            params = FiberParams.from_prim(prim, time)
        except FiberParamsError as exc:
            raise TranslateError(str(exc)) from None
        yarn = None
        if prim.HasAPI("FiberYarnAPI"):
            try:
                yarn = YarnParams.from_prim(prim, time)
            except YarnError as exc:
                raise TranslateError(str(exc)) from None
        key = (params.geometry_key(), params.table)
        tables = tables_by_key.get(key)
        if tables is None:
            t0 = _time.perf_counter()
            try:
                tables = tables_for_prim(prim, settings, bake_missing, cache=cache, time=time, progress=progress)
            except (BakeError, LookupError) as exc:
                raise TranslateError(f"{pl.path}: {exc}") from None
            table_seconds += _time.perf_counter() - t0
            tables_by_key[key] = tables
            all_tables.extend(tables)
        # Without authored widths a curve is as wide as the fiber (or yarn) in the world: the
        # default width is divided by the transform's scale, which the conversion applies.
        world_width = 2 * yarn.yarn_radius if yarn else params.diameter * um
        scale = axis_scales(np.asarray(pl.xform)[:3, :3])[1]
        try:
            geom = profile.call("curves", curves_from_prim, prim, time, pl.xform,
                                default_width=world_width / scale if 0 < scale < math.inf else world_width)
        except CurveError as exc:
            raise TranslateError(str(exc)) from None
        warnings.extend(geom.warnings)
        slot_of_variant = np.array([slot_id(t, tuple(float(x) for x in t.sigma_for(params.mu_a, params.diameter)))
                                    for t in tables], np.int64)
        if yarn is not None:
            plan = profile.call("yarn_lod", _plan_yarns, geom, yarn, view, lod_scale, lod, profile)
            if plan.stats["degenerate"]:
                warnings.append(f"{pl.path}: {plan.stats['degenerate']} yarn curve(s) of zero width or length "
                                "not drawn")
            yarn_stats.append(plan.stats)
            if not plan.far_count and plan.stats["skipped"]:
                far_report.append(far_field_entry(pl.path, plan.stats, None, False, 0.0))
            if plan.far_count:
                t0 = _time.perf_counter()
                ff, traced = _far_field(far_cache, pl.path, yarn, params.diameter * um,
                                        [slots[i] for i in slot_of_variant], yarn_settings, bake_missing, progress)
                table_seconds += _time.perf_counter() - t0
                far_report.append(far_field_entry(pl.path, plan.stats, ff, traced, _time.perf_counter() - t0))
                far_geom = _far_yarn_curves(geom, plan, yarn, float(ff.header["piece"]["bound_radius"]), profile)
                parts.append(far_geom)
                # The far field is recoloured with its fibers' absorption (one trace per yarn, any dye).
                seg_slot.append(np.full(far_geom.segment_count,
                                        slot_id(ff, slots[int(slot_of_variant[0])].sigma_a), np.int64))
                seg_psi.append(np.zeros(far_geom.segment_count))
            # Expanded after every prim is planned: the memory budget covers all of them.
            pending.append((pl, params, yarn, geom, plan, slot_of_variant, len(tables)))
            continue
        add_fibers(pl.path, params, geom, slot_of_variant, len(tables))

    if pending:
        scale = _budget_scale([p[4] for p in pending], sum(g.segment_count for g in parts),
                              memory_budget or MemoryBudget.resolve(), warnings)
        for pl, params, yarn, geom, plan, slot_of_variant, n_tables in pending:
            fibers = profile.call("yarn_expansion", _expand_yarns, geom, plan, yarn, params.diameter * um,
                                  pl.instance_id, lod, profile, scale)
            if fibers.segment_count == 0:
                if plan.stats["far"]:
                    prims.append(pl.path)
                continue
            add_fibers(pl.path, params, fibers, slot_of_variant, n_tables)

    if not parts:
        if warnings_out is not None:
            warnings_out.extend(warnings)
        return None
    geometry = profile.call("concatenate", concatenate, parts)
    bank = profile.call("fiber_bank", FiberBank.build, slots)
    seg_ref = profile.call("reference_normals", reference_normals, geometry)
    return FiberTranslation(geometry=geometry, bank=bank, seg_slot=np.concatenate(seg_slot),
                            seg_psi=np.concatenate(seg_psi), seg_ref=seg_ref,
                            prims=prims, tables=all_tables, warnings=warnings,
                            table_seconds=table_seconds, far_fields=far_report,
                            yarns={k: sum(d[k] for d in yarn_stats)
                                   for k in ("yarns", "culled", "skipped", "fibers", "fibers_full", "far")})


def _budget_scale(plans: list[_YarnPlan], other_segments: int, budget: MemoryBudget, warnings: list[str]) -> float:
    """The factor on every yarn's fraction of fibers that keeps the render within ``budget``
    (1: no reduction; a warning says how much otherwise). Raises MemoryBudgetError when one
    fiber per yarn is still too much."""
    def cost(scale: float) -> float:
        pts = sum(p.estimate(scale).points for p in plans)
        return (pts + other_segments) * RENDER_BYTES_PER_SEGMENT

    full = cost(1.0)
    if budget.fits(full):
        return 1.0
    # Fractions scale the counts linearly until they reach one fiber per yarn: bisect on the
    # scale for the largest that fits.
    least = cost(0.0)
    n_yarns = sum(len(p.expand) for p in plans)
    budget.require(least, f"the yarn fibers of {n_yarns} expanded yarns (one fiber per yarn, "
                          f"{sum(p.estimate(0.0).points for p in plans)} control points)")
    lo, hi = 0.0, 1.0
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if budget.fits(cost(mid)) else (lo, mid)
    warnings.append(f"memory budget: the yarns' fibers need about {format_bytes(full)} at the view's level of "
                    f"detail, more than the budget of {budget.describe()}; keeping {lo:.3g}x of the fibers "
                    f"of each expanded yarn (widened to keep coverage), about {format_bytes(cost(lo))}; "
                    f"--memory-budget raises the budget")
    return lo


def _far_field(far_cache: YarnFarFieldCache, path: str, yarn: YarnParams, fiber_diameter: float,
               slots: list[FiberSlot], settings: YarnBakeSettings, bake_missing: bool,
               progress: Callable[..., Any] | None) -> tuple[YarnFarField, bool]:
    """The far field of a yarn prim, from the cache or traced now (with progress), and whether
    it was traced now."""
    started = False

    def prog(done: int, total: int) -> None:
        nonlocal started
        if progress is None:
            return
        if not started:
            started = True
            progress(0, total, {"event": "start", "label": f"yarn far field {path}", "unit": "photon"})
        progress(done, total, {})

    ff, traced = far_cache.get_or_bake(yarn, fiber_diameter, slots, settings, bake_missing=bake_missing,
                                       progress=prog)
    if ff is None:
        raise TranslateError(f"{path}: the yarn's far field (for yarns too small to show their fibers, or "
                             f"yarn:expandFibers = false) is not cached and baking is off")
    return ff, traced
