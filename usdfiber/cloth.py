"""Procedural cloth: yarn centre lines of knitted and woven fabrics.

Each generator defines a UsdGeom.Xform at ``path`` with BasisCurves children (one prim per
yarn direction, one curve per yarn), cubic uniform B-splines, nonperiodic, with a constant
width equal to the yarn's nominal diameter. The children carry FiberYarnAPI + FiberAPI
from a Table 3 yarn preset (:func:`usdfiber.authoring.apply_yarn`; ``fiber`` overrides the
yarn's fiber preset; ``dye`` / ``depth_of_shade`` colour the fibers). Extents are authored.

Geometry is computed in millimetres and written in the stage's units: a stage without an
authored ``metersPerUnit`` is set to 0.001 (millimetres); otherwise coordinates and widths
are converted to its unit. The fabric lies in the xy plane, its face towards +z: knitted
rows (courses) run along +x and are stacked along +y; warps run along +y, wefts along +x.

Knits (:func:`stockinette`, :func:`garter`), child prim ``Rows``, one curve per row:
  the public plain-knit centre line gamma(t) = (t + a sin 2t, h cos t, d cos 2t) with
  a = 1.5, h = 4, d = 1 and a row spacing of 4.5 (MIT-licensed plain-knit example, see
  the project's field notes); one loop per 2 pi of t. The model unit is scaled so that, at
  ``loop_size`` = ``spacing_scale`` = 1, the centre lines of different rows are one yarn
  diameter apart at their closest (the yarns touch; adjacent rows interlock: each
  row's loop heads pass in front of the next row's legs and behind nothing, its legs behind
  the next row's feet). ``loop_size`` scales the loops in the fabric plane (width, height
  and row spacing), ``spacing_scale`` the row spacing alone; depth stays in yarn units.
  Only values near 1 keep the rows interlocked without collisions (measured closest
  approach in diameters, stockinette / garter: loop_size 0.8 -> 0.82 / 0.89, 1.5 -> 1.09 /
  1.15; spacing_scale 0.9 -> 0.49 / 0.78, 1.2 -> 0.90 / 1.13, 1.5 -> 0.29 / 0.36).
  Garter alternates knit and purl rows; a purl row is the knit loop mirrored in depth. So
  that the rows still interlock, a loop's head takes the depth side of the row above (it
  is pulled through from that side): z = -s d' cos 2t tanh(k cos t) / tanh(k) with s = +1
  for knit and -1 for purl rows, d' = 1.5 and k = 2 (chosen here: with the plain mirror
  z -> -z, knit and purl rows pass through each other). Rows are curves from t = 0 to
  2 pi loops through points sampled ``samples_per_loop`` times per loop and interpolated
  exactly by the B-spline (control points from a periodic solve), so each row repeats
  every loop with the same shape.

Weaves (:func:`plain_weave`, :func:`satin`), child prims ``Warp`` and ``Weft``: yarn i of
  the warp at x = i * spacing, weft j at y = j * spacing, each extending half a spacing
  past the outer crossings. At every crossing the yarn on top has z = +c and the other
  -c, c = crimp * diameter / 2: with crimp 1 the centre lines are one diameter apart in
  depth (touching round yarns). Between crossings the height follows a half cosine, so a
  plain weave is a sinusoid and a satin float stays flat. Plain weave: warp i is over weft
  j when i + j is even. Satin: each warp floats over ``floats`` wefts and under one
  (repeat R = floats + 1); warp i goes under weft j when (j - step * i) mod R == 0, with
  ``step`` (the satin's move number) coprime with R and not 1 or R - 1 (default the
  smallest such, 2 for the 5-harness satin). The default spacing is 2.5 diameters: below
  about 2.2 diameters a sinusoidal crossing bends more sharply than the other yarn's
  section and the centre lines come closer than one diameter (measured: 0.95 diameters at
  a spacing of 1.8, 0.87 at 1.5, 0.64 at 1.0).

Every generator checks, on a patch of the fabric, that centre lines of different yarns stay
at least ``min_clearance`` (default 0.8) yarn diameters apart, and raises
:class:`ClothError` naming the distance otherwise (0 disables the check). Output is
deterministic: no random numbers are used.

Memory: yarns are made one at a time (float64, one yarn long) straight into each prim's
float32 scene points, so a cloth costs about 12 bytes per control point in USD plus, while
a prim is authored, its float32 NumPy copy (:func:`memory_estimate`, checked against the
memory budget before anything is allocated): the 2,500 x 2,500-yarn shirt panel's 50 M
control points take 0.84 GiB at their peak (estimated and measured) and 3 s of CPU.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Callable, Sequence

import numpy as np
from pxr import Sdf, Usd, UsdGeom, Vt

from usdfiber import authoring
from usdfiber import presets as _presets
from usdfiber.memory_budget import MemoryBudget

__all__ = ["ClothError", "KNIT_A", "KNIT_D", "KNIT_H", "KNIT_ROW_SPACING", "POINT_BYTES",
           "WRITE_BYTES_PER_CONTROL_POINT", "garter", "memory_estimate", "min_distance_between",
           "plain_weave", "satin", "satin_step", "stockinette", "evaluate_bspline"]

# Public plain-knit centre line (field notes, "Procedural yarns").
KNIT_A = 1.5
KNIT_H = 4.0
KNIT_D = 1.0
KNIT_ROW_SPACING = 4.5
# Garter: depth amplitude and sharpness of the head/feet depth switch (chosen here).
GARTER_D = 1.5
GARTER_K = 2.0

DEFAULT_YARN = "CNe 50"
DEFAULT_WEAVE_SPACING = 2.5  # yarn diameters
DEFAULT_MIN_CLEARANCE = 0.8  # yarn diameters
_EVAL_STEPS = 8  # samples per B-spline segment for distance checks


class ClothError(ValueError):
    """Invalid cloth parameters, or geometry whose yarns would pass through each other."""


# ----------------------------------------------------------------------------- B-splines
def _periodic_controls(samples: np.ndarray) -> np.ndarray:
    """Control points of the periodic uniform cubic B-spline through periodic ``samples``.

    A uniform cubic B-spline passes through (P[i-1] + 4 P[i] + P[i+1]) / 6 at its knots:
    a circulant system, solved with the FFT (its eigenvalues (4 + 2 cos w) / 6 >= 1/3).
    """
    n = len(samples)
    kernel = np.zeros(n)
    kernel[0] = 4.0 / 6.0
    kernel[1 % n] += 1.0 / 6.0
    kernel[-1] += 1.0 / 6.0
    spec = np.fft.fft(kernel)
    out = np.fft.ifft(np.fft.fft(samples, axis=0) / spec.reshape((-1,) + (1,) * (samples.ndim - 1)),
                      axis=0)
    return np.real(out)


def evaluate_bspline(ctrl: np.ndarray, steps: int = _EVAL_STEPS) -> np.ndarray:
    """Points of a nonperiodic uniform cubic B-spline, ``steps`` per segment plus the end."""
    ctrl = np.asarray(ctrl, dtype=np.float64)
    segs = len(ctrl) - 3
    u = np.arange(steps) / steps
    basis = np.stack([(1 - u) ** 3, 3 * u ** 3 - 6 * u ** 2 + 4,
                      -3 * u ** 3 + 3 * u ** 2 + 3 * u + 1, u ** 3], axis=1) / 6.0
    idx = np.arange(segs)[:, None] + np.arange(4)[None, :]
    pts = np.einsum("sk,nkd->nsd", basis, ctrl[idx]).reshape(-1, ctrl.shape[1])
    end = (ctrl[-3] + 4 * ctrl[-2] + ctrl[-1]) / 6.0
    return np.vstack([pts, end])


def min_distance_between(curves: list[np.ndarray]) -> float:
    """Smallest distance between points of different curves (each an (N, 3) sample array)."""
    from scipy.spatial import cKDTree

    best = math.inf
    for i in range(len(curves)):
        tree = cKDTree(curves[i])
        for j in range(i + 1, len(curves)):
            d, _ = tree.query(curves[j])
            best = min(best, float(d.min()))
    return best


# ----------------------------------------------------------------------------- helpers
def _check_int(name: str, value: Any, minimum: int, maximum: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum or (
            maximum is not None and value > maximum):
        upto = "" if maximum is None else f" and <= {maximum}"
        raise ClothError(f"{name} must be an integer >= {minimum}{upto}, got {value!r}")
    return int(value)


#: Largest length factor or spacing (mm) a cloth takes: beyond it coordinates overflow float32
#: (a spacing of 1e308 mm made infinite points).
MAX_FACTOR = 1e6
#: Longest satin float: real satins float over 4 to 12 wefts; a float of a million wefts took minutes.
MAX_FLOATS = 64


def _check_pos(name: str, value: Any) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ClothError(f"{name} must be a number, got {value!r}") from None
    if not (math.isfinite(v) and 0 < v <= MAX_FACTOR):
        raise ClothError(f"{name} must be a positive number up to {MAX_FACTOR:g}, got {value!r}")
    return v


def _check_clearance(value: Any) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ClothError(f"min_clearance must be a number, got {value!r}") from None
    if not (math.isfinite(v) and v >= 0):
        raise ClothError(f"min_clearance must be >= 0, got {value!r}")
    return v


#: Bytes of one control point as USD holds it (float32 x, y, z).
POINT_BYTES = 12
#: Peak bytes per control point of writing a cloth's stage to a file, over the stage itself
#: (measured on plain weaves of 1.3 M and 5.1 M control points: usda 59.3, its text (37 bytes
#: per point in the file) is built in memory; usdc 0.5; the 50 M of the shirt panel: usda 55.8,
#: usdc 0.1), rounded up.
WRITE_BYTES_PER_CONTROL_POINT = {"usda": 64, "usdc": 1}


def memory_estimate(prim_points: Sequence[int], write_format: str | None = None) -> int:
    """Peak bytes of generating a cloth whose curve prims have ``prim_points`` control points,
    and of then writing it as ``write_format`` (``"usda"``, ``"usdc"`` or None: not written).

    USD holds every control point (:data:`POINT_BYTES`); while a prim is authored its points
    also exist once as a float32 NumPy array (made yarn by yarn: no float64 copy of more than
    one yarn); writing adds :data:`WRITE_BYTES_PER_CONTROL_POINT` over the stage. Measured peak
    over the process's memory before: 18.2 bytes per point for a weave (two equal prims: the
    estimate's 18), 24.2 for a knit (one prim: 24).
    """
    if write_format is not None and write_format not in WRITE_BYTES_PER_CONTROL_POINT:
        raise ClothError(f"write_format must be one of {', '.join(WRITE_BYTES_PER_CONTROL_POINT)} or None, "
                         f"got {write_format!r}")
    total = sum(prim_points)
    transient = POINT_BYTES * max(prim_points, default=0)
    if write_format is not None:
        transient = max(transient, WRITE_BYTES_PER_CONTROL_POINT[write_format] * total)
    return POINT_BYTES * total + transient


def _check_budget(what: str, prim_points: Sequence[int], budget: MemoryBudget | None,
                  write_format: str | None) -> None:
    """Refuse, before any allocation, a cloth whose control points do not fit the budget."""
    estimate = memory_estimate(prim_points, write_format)
    written = f", written as {write_format}" if write_format else ""
    (budget or MemoryBudget.resolve()).require(estimate, f"{what} ({sum(prim_points)} control points{written})")


def _check_presets(yarn: str, fiber: str | None) -> None:
    try:
        _presets.yarn_preset(yarn)
        if fiber is not None:
            _presets.fiber_preset(fiber)
    except KeyError as exc:
        raise ClothError(exc.args[0]) from None


def _mm_to_scene(stage: Usd.Stage) -> float:
    """Scene units per millimetre; sets metersPerUnit = 0.001 on a stage without one."""
    if not stage.HasAuthoredMetadata("metersPerUnit"):
        UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    mpu = UsdGeom.GetStageMetersPerUnit(stage)
    return 1e-3 / mpu


@dataclass
class _Yarns:
    """One BasisCurves prim's curves: ``counts[k]`` control points of curve k, made in mm by
    ``curve(k)`` (float64). Curves are made one at a time while the prim's scene points are
    written, so that no float64 copy of a whole cloth exists (:func:`memory_estimate`)."""

    name: str
    counts: list[int]
    curve: Callable[[int], np.ndarray]

    def controls(self) -> list[np.ndarray]:
        """Every curve's control points (mm); for small patches only."""
        return [self.curve(k) for k in range(len(self.counts))]


def _scene_points(g: _Yarns, to_scene: float) -> np.ndarray:
    """The prim's control points in scene units as one float32 (N, 3) array, filled curve by
    curve: each curve's float64 points times ``to_scene``, rounded to float32."""
    pts = np.empty((sum(g.counts), 3), np.float32)
    start = 0
    for k, n in enumerate(g.counts):
        c = g.curve(k)
        if c.shape != (n, 3):
            raise AssertionError(f"curve {k} of {g.name}: {c.shape} control points, expected ({n}, 3)")
        pts[start:start + n] = c * to_scene        # float64 product, rounded on assignment
        start += n
    return pts


def _author(stage: Usd.Stage, path: str | Sdf.Path, build: Callable[[float], list[_Yarns]],
            yarn: str, fiber: str | None, dye: str | None,
            depth_of_shade: float | None, doc: str) -> Usd.Prim:
    """Define the Xform and its curve prims; ``build(diameter_mm)`` gives the curves."""
    _check_presets(yarn, fiber)
    root_path = Sdf.Path(str(path))
    if not root_path.IsAbsolutePath() or not root_path.IsPrimPath():
        raise ClothError(f"path must be an absolute prim path, got {str(path)!r}")
    existed = bool(stage.GetPrimAtPath(root_path))
    to_scene = _mm_to_scene(stage)
    overrides: dict[str, Any] = {}
    if dye is not None:
        overrides["dye"] = dye
    if depth_of_shade is not None:
        overrides["depth_of_shade"] = depth_of_shade
    try:
        root = UsdGeom.Xform.Define(stage, root_path)
        root.GetPrim().SetDocumentation(doc)
        # The yarn's diameter depends on the fiber (density): apply to a scratch prim first.
        probe = UsdGeom.BasisCurves.Define(stage, root_path.AppendChild("_probe")).GetPrim()
        authoring.apply_yarn(probe, yarn, fiber, **overrides)
        diameter = authoring.yarn_diameter_mm(probe)
        stage.RemovePrim(probe.GetPath())
        groups = build(diameter)
        for g in groups:
            curves = UsdGeom.BasisCurves.Define(stage, root_path.AppendChild(g.name))
            curves.CreateTypeAttr(UsdGeom.Tokens.cubic)
            curves.CreateBasisAttr(UsdGeom.Tokens.bspline)
            curves.CreateWrapAttr(UsdGeom.Tokens.nonperiodic)
            # One prim's float32 points, then USD's copy of them (the numpy array is freed
            # before the next prim): the peak that memory_estimate models.
            pts = _scene_points(g, to_scene)
            points = Vt.Vec3fArray.FromNumpy(pts)
            del pts
            curves.CreatePointsAttr(points)
            curves.CreateCurveVertexCountsAttr(Vt.IntArray(g.counts))
            widths = Vt.FloatArray([diameter * to_scene])
            curves.CreateWidthsAttr(widths)
            curves.SetWidthsInterpolation(UsdGeom.Tokens.constant)
            curves.CreateExtentAttr(UsdGeom.Curves.ComputeExtent(points, widths))
            del points
            authoring.apply_yarn(curves.GetPrim(), yarn, fiber, **overrides)
    except BaseException:  # an AuthoringError (a PrimError) reaches the caller as it is
        _undo(stage, root_path, existed)
        raise
    return root.GetPrim()


def _undo(stage: Usd.Stage, root_path: Sdf.Path, existed: bool) -> None:
    if existed:
        for child in ("_probe", "Rows", "Warp", "Weft"):
            p = root_path.AppendChild(child)
            if stage.GetPrimAtPath(p):
                stage.RemovePrim(p)
    elif stage.GetPrimAtPath(root_path):
        stage.RemovePrim(root_path)


def _clearance_error(what: str, dist_mm: float, diameter: float, min_clearance: float,
                     hint: str) -> ClothError:
    return ClothError(
        f"{what}: the centre lines of different yarns come within {dist_mm:.4g} mm = "
        f"{dist_mm / diameter:.2f} yarn diameters ({diameter:.4g} mm) of each other, below "
        f"min_clearance {min_clearance:g}: the yarns would pass through each other; {hint}")


# ----------------------------------------------------------------------------- knits
def _knit_depth(t: np.ndarray, pattern: str, row: int) -> np.ndarray:
    if pattern == "stockinette":
        return KNIT_D * np.cos(2 * t)
    s = 1.0 if row % 2 == 0 else -1.0  # knit rows even, purl rows odd
    return -s * GARTER_D * np.cos(2 * t) * np.tanh(GARTER_K * np.cos(t)) / math.tanh(GARTER_K)


def _knit_row(pattern: str, r: int, loops: int, n: int, loop_size: float,
              spacing_scale: float) -> np.ndarray:
    """Control points of row ``r`` in model units (before scaling to the yarn): n * loops + 3."""
    t = 2 * math.pi * np.arange(n) / n
    periodic = np.stack([loop_size * KNIT_A * np.sin(2 * t), loop_size * KNIT_H * np.cos(t),
                         _knit_depth(t, pattern, r)], axis=1)
    ctrl_p = _periodic_controls(periodic)
    idx = np.arange(-1, n * loops + 2)
    ctrl = ctrl_p[idx % n].copy()
    ctrl[:, 0] += loop_size * 2 * math.pi * idx / n
    ctrl[:, 1] += r * loop_size * KNIT_ROW_SPACING * spacing_scale
    return ctrl


def _knit_rows(pattern: str, rows: int, loops: int, n: int, loop_size: float,
               spacing_scale: float) -> list[np.ndarray]:
    """Control points of every row in model units; for small patches only."""
    return [_knit_row(pattern, r, loops, n, loop_size, spacing_scale) for r in range(rows)]


def _knit_patch_distance(pattern: str, n: int, loop_size: float, spacing_scale: float,
                         rows: int = 4, loops: int = 3) -> float:
    curves = [evaluate_bspline(c) for c in _knit_rows(pattern, rows, loops, n, loop_size,
                                                      spacing_scale)]
    return min_distance_between(curves)


@lru_cache(maxsize=None)
def _knit_contact_distance(pattern: str, n: int) -> float:
    """Closest approach of different rows at loop_size = spacing_scale = 1, model units."""
    return _knit_patch_distance(pattern, n, 1.0, 1.0)


def _knit(stage: Usd.Stage, path: str | Sdf.Path, pattern: str, *, rows: int, loops: int,
          yarn: str, fiber: str | None, spacing_scale: float, loop_size: float,
          dye: str | None, depth_of_shade: float | None, samples_per_loop: int,
          min_clearance: float, memory_budget: MemoryBudget | None = None,
          write_format: str | None = None) -> Usd.Prim:
    rows = _check_int("rows", rows, 1)
    loops = _check_int("loops", loops, 1)
    n = _check_int("samples_per_loop", samples_per_loop, 4)
    spacing_scale = _check_pos("spacing_scale", spacing_scale)
    loop_size = _check_pos("loop_size", loop_size)
    min_clearance = _check_clearance(min_clearance)
    _check_budget(f"cloth {pattern} of {rows} rows x {loops} loops", [rows * (n * loops + 3)], memory_budget,
                  write_format)

    def build(diameter: float) -> list[_Yarns]:
        unit = diameter / _knit_contact_distance(pattern, n)  # mm per model unit
        if min_clearance > 0 and rows > 1:
            d = _knit_patch_distance(pattern, n, loop_size, spacing_scale,
                                     rows=min(rows, 4), loops=min(loops, 3)) * unit
            if d < min_clearance * diameter:
                raise _clearance_error(
                    f"{pattern} with loop_size {loop_size:g}, spacing_scale {spacing_scale:g}",
                    d, diameter, min_clearance, "use values nearer 1 (or min_clearance=0)")
        return [_Yarns("Rows", [n * loops + 3] * rows,
                       lambda r: _knit_row(pattern, r, loops, n, loop_size, spacing_scale) * unit)]

    what = "stockinette (plain knit)" if pattern == "stockinette" else "garter (knit and purl rows)"
    doc = (f"{what}: {rows} rows of {loops} loops, yarn {yarn}, generated by usdfiber.cloth; "
           f"Rows holds one cubic B-spline centre line per row (x along the row, y up the "
           f"fabric, z towards the face)")
    return _author(stage, path, build, yarn, fiber, dye, depth_of_shade, doc)


def stockinette(stage: Usd.Stage, path: str | Sdf.Path, *, rows: int = 8, loops: int = 8,
                yarn: str = DEFAULT_YARN, fiber: str | None = None, spacing_scale: float = 1.0,
                loop_size: float = 1.0, dye: str | None = None,
                depth_of_shade: float | None = None, samples_per_loop: int = 16,
                min_clearance: float = DEFAULT_MIN_CLEARANCE,
                memory_budget: MemoryBudget | None = None, write_format: str | None = None) -> Usd.Prim:
    """Plain knit (every row knit): an Xform at ``path`` with BasisCurves ``Rows``.

    ``rows`` curves of ``loops`` loops each; ``yarn`` a Table 3 preset, ``fiber`` a fiber
    preset overriding its composition; ``loop_size`` scales the loops in the fabric plane,
    ``spacing_scale`` the row spacing; ``samples_per_loop`` interpolated points per loop
    (control points per loop). ``memory_budget`` (default :meth:`MemoryBudget.resolve`):
    a cloth whose control points do not fit is refused (MemoryBudgetError) before anything
    is allocated (:func:`memory_estimate`; ``write_format`` ``"usda"`` or ``"usdc"``: the
    stage will then be written in that format, whose writer's memory is part of the
    estimate). Returns the Xform prim. See the module doc.
    """
    return _knit(stage, path, "stockinette", rows=rows, loops=loops, yarn=yarn, fiber=fiber,
                 spacing_scale=spacing_scale, loop_size=loop_size, dye=dye,
                 depth_of_shade=depth_of_shade, samples_per_loop=samples_per_loop,
                 min_clearance=min_clearance, memory_budget=memory_budget, write_format=write_format)


def garter(stage: Usd.Stage, path: str | Sdf.Path, *, rows: int = 8, loops: int = 8,
           yarn: str = DEFAULT_YARN, fiber: str | None = None, spacing_scale: float = 1.0,
           loop_size: float = 1.0, dye: str | None = None,
           depth_of_shade: float | None = None, samples_per_loop: int = 16,
           min_clearance: float = DEFAULT_MIN_CLEARANCE,
           memory_budget: MemoryBudget | None = None, write_format: str | None = None) -> Usd.Prim:
    """Garter stitch (knit and purl rows alternating, row 0 knit): Xform with ``Rows``.

    Parameters as :func:`stockinette`.
    """
    return _knit(stage, path, "garter", rows=rows, loops=loops, yarn=yarn, fiber=fiber,
                 spacing_scale=spacing_scale, loop_size=loop_size, dye=dye,
                 depth_of_shade=depth_of_shade, samples_per_loop=samples_per_loop,
                 min_clearance=min_clearance, memory_budget=memory_budget, write_format=write_format)


# ----------------------------------------------------------------------------- weaves
def satin_step(floats: int) -> int:
    """The smallest satin move number for a repeat of floats + 1 (ClothError if none)."""
    r = floats + 1
    for step in range(2, r - 1):
        if math.gcd(step, r) == 1:
            return step
    raise ClothError(
        f"no regular satin floats over {floats} wefts: a repeat of {r} has no move number "
        f"coprime with {r} other than 1 and {r - 1} (satins need floats = 4, 6, 7, ...)")


def _heights(up: np.ndarray, c: float, per: int) -> np.ndarray:
    """Periodic height samples (``per`` per crossing) from crossing heights +-c."""
    h = np.where(up, c, -c)
    nxt = np.roll(h, -1)
    u = np.arange(per) / per
    ease = (1 - np.cos(math.pi * u)) / 2
    return (h[:, None] + (nxt - h)[:, None] * ease[None, :]).reshape(-1)


def _weave_yarn(up_period: np.ndarray, c: float, spacing: float, crossings: int, along: int,
                offset: float, per: int = 4) -> np.ndarray:
    """Control points (mm) of one yarn crossing ``crossings`` yarns; ``along`` is the axis
    it runs along (0 = x, 1 = y), ``offset`` its position on the other axis."""
    z = _periodic_controls(_heights(up_period, c, per))
    half = per // 2
    idx = np.arange(-half - 1, per * (crossings - 1) + half + 2)
    ctrl = np.zeros((len(idx), 3))
    ctrl[:, along] = idx * spacing / per
    ctrl[:, 1 - along] = offset
    ctrl[:, 2] = z[idx % len(z)]
    return ctrl


def _weave_curves(warps: int, wefts: int, spacing: float, c: float, repeat: int,
                  over: Callable[[int, int], bool]) -> list[_Yarns]:
    """Warp and weft yarns, made one at a time; ``over(i, j)``: warp i is over weft j."""

    def warp(i: int) -> np.ndarray:
        up = np.array([over(i, j) for j in range(repeat)])
        return _weave_yarn(up, c, spacing, wefts, along=1, offset=i * spacing)

    def weft(j: int) -> np.ndarray:
        up = np.array([not over(i, j) for i in range(repeat)])
        return _weave_yarn(up, c, spacing, warps, along=0, offset=j * spacing)

    # A yarn crossing k others has 4 control points per crossing plus 3 (_weave_yarn).
    return [_Yarns("Warp", [4 * wefts + 3] * warps, warp), _Yarns("Weft", [4 * warps + 3] * wefts, weft)]


def _weave(stage: Usd.Stage, path: str | Sdf.Path, name: str, *, warps: int, wefts: int,
           yarn: str, fiber: str | None, spacing: float | None, crimp: float,
           dye: str | None, depth_of_shade: float | None, min_clearance: float,
           memory_budget: MemoryBudget | None, repeat: int, over: Callable[[int, int], bool], doc: str,
           write_format: str | None = None) -> Usd.Prim:
    warps = _check_int("warps", warps, 1)
    wefts = _check_int("wefts", wefts, 1)
    crimp = _check_pos("crimp", crimp)
    if spacing is not None:
        spacing = _check_pos("spacing", spacing)
    min_clearance = _check_clearance(min_clearance)
    # Control points of a yarn crossing k others: 4 per crossing plus the ends (_weave_yarn).
    _check_budget(f"cloth {name} of {warps} warps x {wefts} wefts",
                  [warps * (4 * wefts + 3), wefts * (4 * warps + 3)], memory_budget, write_format)

    def build(diameter: float) -> list[_Yarns]:
        s = DEFAULT_WEAVE_SPACING * diameter if spacing is None else spacing
        c = crimp * diameter / 2
        if min_clearance > 0:
            pw, pf = min(warps, repeat + 2), min(wefts, repeat + 2)
            patch = _weave_curves(pw, pf, s, c, repeat, over)
            d = min_distance_between([evaluate_bspline(k) for g in patch for k in g.controls()])
            if d < min_clearance * diameter:
                raise _clearance_error(
                    f"{name} with spacing {s:.4g} mm and crimp {crimp:g}", d, diameter,
                    min_clearance, f"a spacing of {2.2 * diameter:.4g} mm (2.2 diameters) or "
                    f"more keeps round yarns with crimp 1 apart (or pass min_clearance=0)")
        return _weave_curves(warps, wefts, s, c, repeat, over)

    return _author(stage, path, build, yarn, fiber, dye, depth_of_shade, doc)


def plain_weave(stage: Usd.Stage, path: str | Sdf.Path, *, warps: int = 16, wefts: int = 16,
                yarn: str = DEFAULT_YARN, fiber: str | None = None, spacing: float | None = None,
                crimp: float = 1.0, dye: str | None = None, depth_of_shade: float | None = None,
                min_clearance: float = DEFAULT_MIN_CLEARANCE,
                memory_budget: MemoryBudget | None = None, write_format: str | None = None) -> Usd.Prim:
    """Plain weave: an Xform at ``path`` with BasisCurves ``Warp`` (along y) and ``Weft``.

    ``spacing`` between neighbouring yarns in mm (default 2.5 yarn diameters); ``crimp``:
    depth separation of warp and weft at crossings in yarn diameters; ``memory_budget`` and
    ``write_format`` as :func:`stockinette`. Returns the Xform.
    """
    return _weave(stage, path, "plain weave", warps=warps, wefts=wefts, yarn=yarn, fiber=fiber,
                  spacing=spacing, crimp=crimp, dye=dye, depth_of_shade=depth_of_shade,
                  min_clearance=min_clearance, memory_budget=memory_budget, write_format=write_format, repeat=2,
                  over=lambda i, j: (i + j) % 2 == 0,
                  doc=f"plain weave, {warps} warps x {wefts} wefts, yarn {yarn}, generated by "
                      f"usdfiber.cloth; warp i is over weft j when i + j is even")


def satin(stage: Usd.Stage, path: str | Sdf.Path, *, warps: int = 20, wefts: int = 20,
          yarn: str = DEFAULT_YARN, fiber: str | None = None, spacing: float | None = None,
          crimp: float = 1.0, floats: int = 4, step: int | None = None, dye: str | None = None,
          depth_of_shade: float | None = None,
          min_clearance: float = DEFAULT_MIN_CLEARANCE,
          memory_budget: MemoryBudget | None = None, write_format: str | None = None) -> Usd.Prim:
    """Warp-faced satin: each warp floats over ``floats`` wefts and under one.

    ``step``: the move number (default :func:`satin_step`, 2 for floats = 4: the 5-harness
    satin). Other parameters as :func:`plain_weave`.
    """
    floats = _check_int("floats", floats, 1, MAX_FLOATS)
    r = floats + 1
    if step is None:
        step = satin_step(floats)
    else:
        step = _check_int("step", step, 1)
        if not (2 <= step <= r - 2 and math.gcd(step, r) == 1):
            raise ClothError(
                f"step {step} is not a satin move number for a repeat of {r}: it must be "
                f"between 2 and {r - 2} and coprime with {r}")
    return _weave(stage, path, "satin", warps=warps, wefts=wefts, yarn=yarn, fiber=fiber,
                  spacing=spacing, crimp=crimp, dye=dye, depth_of_shade=depth_of_shade,
                  min_clearance=min_clearance, memory_budget=memory_budget, write_format=write_format, repeat=r,
                  over=lambda i, j: (j - step * i) % r != 0,
                  doc=f"{r}-harness warp-faced satin (floats {floats}, step {step}), {warps} "
                      f"warps x {wefts} wefts, yarn {yarn}, generated by usdfiber.cloth; warp "
                      f"i is under weft j when (j - {step} i) mod {r} == 0")
