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

from usdfiber.bake.baker import BakeError, BakeSettings
from usdfiber.bake.cache import TableCache
from usdfiber.bake.table import BcsdfTable
from usdfiber.bcsdf import tables_for_prim
from usdfiber.fiber_params import FiberParams, FiberParamsError

from usdfiber.translators.curves import (CurveError, CurveGeometry, concatenate, curves_from_prim, evaluate,
                                         reference_normals)
from usdfiber.translators.fiber_bank import FiberBank, FiberSlot
from usdfiber.translators.lod import CameraView, fiber_fraction
from usdfiber.translators.yarns import YarnError, YarnParams, expand_yarn

__all__ = ["FiberTranslation", "TranslateError", "fiber_prim", "translate_fibers"]


class TranslateError(RuntimeError):
    """A prim that cannot be rendered; the message names the prim and the attribute."""


def fiber_prim(prim: Usd.Prim) -> bool:
    """Whether ``prim`` is a fiber prim (BasisCurves with FiberAPI)."""
    return prim.IsA(UsdGeom.BasisCurves) and prim.HasAPI("FiberAPI")


@dataclass
class FiberTranslation:
    """The fiber curves of a stage, ready for :func:`usdfiber.translators.fiber_bsdf.fiber_bsdf`."""

    geometry: CurveGeometry
    bank: FiberBank
    seg_slot: np.ndarray          # (S,) slot of each segment
    seg_psi: np.ndarray           # (S,) radians
    seg_ref: np.ndarray           # (S, 3) azimuthal reference normals
    prims: list[str] = field(default_factory=list)
    tables: list[BcsdfTable] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    yarns: dict[str, int] = field(default_factory=dict)   # yarn expansion and LOD counts
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


def _yarn_polylines(geom: CurveGeometry, per_segment: int = 8) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Each yarn centre curve sampled densely, one curve at a time: (points (M, 3), radii (M,)).

    Curve by curve, so that memory follows one yarn, not the whole prim; segments are ordered
    by curve (CurveGeometry), so a curve's segments are one contiguous run.
    """
    t = np.linspace(0.0, 1.0, per_segment, endpoint=False)
    ends = np.cumsum(np.bincount(geom.segment_curve, minlength=geom.curve_count))
    for c in range(geom.curve_count):
        ss = np.arange(ends[c - 1] if c else 0, ends[c])
        if len(ss) == 0:
            continue
        P, R, _ = evaluate(geom, np.repeat(ss, per_segment), np.tile(t, len(ss)))
        end_p, end_r, _ = evaluate(geom, ss[-1:], np.ones(1))
        yield np.concatenate([P, end_p]), np.concatenate([R, end_r])


def _expand_yarns(geom: CurveGeometry, yarn: YarnParams, fiber_diameter: float, view: CameraView | None,
                  lod_scale: float, instance_id: int) -> tuple[CurveGeometry, dict[str, int]]:
    """Expand every visible yarn curve of a prim into fiber curves (level of detail: lod.py)."""
    parts = []
    stats = {"yarns": 0, "culled": 0, "fibers": 0, "fibers_full": 0}
    for c, (pts, rad) in enumerate(_yarn_polylines(geom)):
        stats["yarns"] += 1
        r = float(rad.max())
        fraction = 1.0
        if view is not None:
            if not view.visible(pts.min(axis=0) - r, pts.max(axis=0) + r):
                stats["culled"] += 1
                continue
            fraction = fiber_fraction(view.pixels(2 * r, pts), yarn.fiber_count, lod_scale=lod_scale)
        ex = expand_yarn(pts, rad / yarn.yarn_radius, yarn, fiber_fraction=fraction,
                         seed_offset=instance_id * 1_000_003 + c)
        stats["fibers"] += ex.curve_count
        stats["fibers_full"] += int(round(ex.curve_count / fraction))
        # Fewer fibers are widened to keep the yarn's total fiber cross-section (lod.py).
        parts.append(ex.to_curve_geometry(fiber_diameter / math.sqrt(fraction)))
    if not parts:
        return CurveGeometry(np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int64), 0), stats
    return concatenate(parts), stats


def translate_fibers(placements: Sequence[Any], stage: Usd.Stage, time: Usd.TimeCode, *,
                     settings: BakeSettings, cache: TableCache | None = None, bake_missing: bool = True,
                     progress: Callable[..., Any] | None = None, view: CameraView | None = None,
                     lod_scale: float = 1.0) -> FiberTranslation | None:
    """The fiber curves of ``placements`` (:class:`usdfiber.translators.stage_walk.Placement` of fiber
    prims) with their tables (baked with ``settings`` when missing); None without fibers.

    Yarn prims (FiberYarnAPI) are expanded into fiber curves (:mod:`usdfiber.translators.yarns`)
    with the level of detail of ``view`` (:mod:`usdfiber.translators.lod`; None: every yarn at
    full detail).

    Raises TranslateError for prims that cannot be rendered (unresolvable fiber values,
    malformed curves, yarn curves, tables that cannot be baked).
    """
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
            if not yarn.expand:
                raise TranslateError(
                    f"{pl.path}.yarn:expandFibers: false asks for the yarn-level approximation, which "
                    f"this version does not render; set it to true to expand the yarn into fibers")
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
        try:
            geom = curves_from_prim(prim, time, pl.xform,
                                    default_width=(2 * yarn.yarn_radius if yarn else params.diameter * um))
        except CurveError as exc:
            raise TranslateError(str(exc)) from None
        warnings.extend(geom.warnings)
        if yarn is not None:
            geom, stats = _expand_yarns(geom, yarn, params.diameter * um, view, lod_scale, pl.instance_id)
            yarn_stats.append(stats)
        if geom.segment_count == 0:
            continue
        variant, psi = _fiber_draws(params, pl.path, geom.curve_count, len(tables))
        slot_of_variant = np.zeros(len(tables), np.int64)
        for v, t in enumerate(tables):
            sigma = tuple(float(x) for x in t.sigma_for(params.mu_a, params.diameter))
            sk = (id(t), sigma)
            if sk not in slot_ids:
                slot_ids[sk] = len(slots)
                slots.append(FiberSlot(t, sigma))  # type: ignore[arg-type]
            slot_of_variant[v] = slot_ids[sk]
        parts.append(geom)
        seg_slot.append(slot_of_variant[variant[geom.segment_curve]])
        seg_psi.append(psi[geom.segment_curve])
        prims.append(pl.path)

    if not parts:
        return None
    geometry = concatenate(parts)
    bank = FiberBank.build(slots)
    return FiberTranslation(geometry=geometry, bank=bank, seg_slot=np.concatenate(seg_slot),
                            seg_psi=np.concatenate(seg_psi), seg_ref=reference_normals(geometry),
                            prims=prims, tables=all_tables, warnings=warnings,
                            table_seconds=table_seconds,
                            yarns={k: sum(d[k] for d in yarn_stats) for k in ("yarns", "culled", "fibers", "fibers_full")})
