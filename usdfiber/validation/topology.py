"""Topology and value checks on fiber and yarn curves (UsdGeomBasisCurves).

Applies to non-abstract BasisCurves prims with FiberAPI or FiberYarnAPI. Everything is
vectorized over the prim's arrays, so one prim with 100k curves costs a few numpy passes.
Problems are aggregated: one Problem per code and attribute per prim, naming the first few
offending curves and, for time-sampled data, how many samples are affected and the first.

Codes (E = error, W = warning):

- ``CurveTypeInvalid`` (E): type / basis / wrap is not a UsdGeomBasisCurves token.
- ``CurveVertexCountNotPositive`` (E): a curveVertexCounts entry is <= 0.
- ``CurveTooFewPoints`` (E): a curve has fewer points than its type/basis/wrap needs.
- ``CurveBezierVertexCount`` (E): a cubic bezier curve's count is not 4 + 3k (nonperiodic,
  pinned) or 3k (periodic).
- ``CurvesCountsMismatch`` (E): sum(curveVertexCounts) != number of points.
- ``PointsNotFinite`` (E): NaN or Inf in points.
- ``PointsTooLarge`` (E): a coordinate of magnitude 1e18 or more, authored or after the
  local-to-world transform (:data:`usdfiber.geometry.curves.MAX_COORDINATE`: renderers work in
  float32, where its square overflows, and the curve silently disappears).
- ``PointsWrongType`` (E): points authored with another type than point3f[].
- ``TransformNotFinite`` (E): NaN or Inf in the local-to-world transform.
- ``CurveZeroLength`` (W): all points of a curve are equal (to float32 precision): the
  fiber has no tangent, so its frame and scattering are undefined.
- ``WidthsInterpolationInvalid`` (E): widths interpolation is not constant / uniform /
  varying / vertex (faceVarying is read as varying, with ``WidthsFaceVarying`` (W)).
- ``WidthsConstantAssumed`` (W): one width value without interpolation metadata (USD's
  fallback is vertex): read as constant, as Storm does.
- ``WidthsElementSize`` (E): primvars:widths with an elementSize other than 1.
- ``WidthsCountMismatch`` (E): widths count differs from what its interpolation needs.
- ``WidthsNotFinite`` (E): NaN or Inf in widths.
- ``WidthsTooLarge`` (E): a width of 1e18 or more, authored or scaled by the transform (the
  bound of ``PointsTooLarge``).
- ``WidthBelowPrecision`` (W): widths narrower than 2^-22 of the points' largest world
  coordinate (:data:`usdfiber.geometry.curves.WIDTH_PRECISION`): a radius below one float32
  step there, the curves render with holes or vanish.
- ``WidthNegative`` (E): a width is negative. Zero widths are valid: fibers taper to their
  tips (USD's own basisCurves example does).
- ``WidthNegativeInterpolated`` (W): cubic Catmull-Rom vertex widths that overshoot below
  zero between the points: nothing is drawn there.
- ``WidthMismatch`` (W): curve widths disagree with the fiber or yarn size (unit error);
  see :func:`width_scale_problem` for the rule.
- ``NonUniformScale`` (W): the transform scales the axes differently; round tubes take
  the geometric mean (:func:`usdfiber.geometry.curves.axis_scales`).
- ``NormalsIgnored`` (W): normals authored (oriented ribbons): drawn as round tubes.
- ``AnimatedOnly`` (W): points with time samples and no default value: nothing to draw at
  the default time (a render without a frame picks one, see
  :func:`usdfiber.stage_io.default_render_time`).

Plain curves (BasisCurves without FiberAPI) are drawn by the renderer as grey tubes, and
skipped, with a warning, when they cannot be drawn. The ``plainCurves`` check runs the very
conversion the renderer runs (:func:`usdfiber.geometry.curves.curves_from_prim`) and reports
the same as warnings: ``PlainCurves`` (drawn grey), ``PlainCurvesSkipped`` (cannot be drawn:
why), ``PlainCurvesApproximated`` (drawn with an approximation: which).

The width rule under a transform (the one the translator follows): authored widths are
scaled by the transform (:func:`usdfiber.geometry.curves.axis_scales`); a fiber or yarn
curve without widths is drawn as wide as the fiber or yarn is in the world.

Minimum point counts and varying counts follow the UsdGeomBasisCurves documentation
("Segment Indexing" and its tables), see :func:`vertex_count_rule` and
:func:`varying_counts`.
"""
from __future__ import annotations

import math
import re
import weakref
from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np
from pxr import Gf, Sdf, Tf, Usd, UsdGeom

from usdfiber.errors import PrimError
from usdfiber.geometry.curves import (MAX_COORDINATE, TOO_LARGE_EXPECTED, WIDTH_PRECISION, axis_scales,
                                      curves_from_prim, negative_vertex_widths, too_large,
                                      unresolved_widths_text, world_points_near_limit, world_reach)
from usdfiber.spec.attributes import Fiber, Yarn
from usdfiber.stage_io import animated_only
from usdfiber.spec.yarn import yarn_diameter
from usdfiber.validation import current_times
from usdfiber.validation.problems import Problem, Severity, prim_check

FIBER_API = Fiber.API
YARN_API = Yarn.API

CURVE_TYPES = ("linear", "cubic")
CURVE_BASES = ("bezier", "bspline", "catmullRom")
CURVE_WRAPS = ("nonperiodic", "periodic", "pinned")
WIDTH_INTERPOLATIONS = ("constant", "uniform", "varying", "vertex")
VSTEP = {"bezier": 3, "bspline": 1, "catmullRom": 1}

#: Allowed ratio between a fiber curve's width (in metres) and fiber:diameter either way.
FIBER_WIDTH_FACTOR = 1.5
#: Allowed ratio between a yarn curve's width and the nominal yarn diameter either way.
#: Loose: ply compression (up to 2x), packing and flyaways change the real diameter, but a
#: unit error (mm authored as m, um as mm) is a factor of 1000 and is always caught.
YARN_WIDTH_FACTOR = 4.0

# Points are point3f: two points closer than a few float32 ulps of their magnitude are equal.
_ZERO_LENGTH_RTOL = 8.0 * float(np.finfo(np.float32).eps)
_LIST_LIMIT = 5


# --------------------------------------------------------------------------------------
# USD's curve rules
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class VertexCountRule:
    """Valid point counts of one curve: ``n >= minimum`` and ``(n - minimum) % step == 0``."""

    minimum: int
    step: int
    text: str  # e.g. "cubic bezier nonperiodic curves need 4 + 3k points (4, 7, 10, ...)"

    def valid(self, counts: np.ndarray) -> np.ndarray:
        """Boolean mask of the counts that satisfy the rule."""
        return (counts >= self.minimum) & ((counts - self.minimum) % self.step == 0)


def curve_kind(curve_type: str, basis: str, wrap: str) -> str:
    """'linear periodic' or 'cubic bspline pinned' (basis is unused by linear curves)."""
    return f"{curve_type} {wrap}" if curve_type == "linear" else f"{curve_type} {basis} {wrap}"


def vertex_count_rule(curve_type: str, basis: str, wrap: str) -> VertexCountRule:
    """The point-count rule of one curve, from the UsdGeomBasisCurves docs.

    linear: >= 2 (nonperiodic, pinned), >= 3 (periodic; a closed polygon; the docs' own
    example uses 3). cubic bezier (vstep 3): 4 + 3k nonperiodic, 3k periodic; pinned only
    affects bspline/catmullRom, so pinned bezier is nonperiodic. cubic bspline/catmullRom
    (vstep 1): >= 4 nonperiodic, >= 3 periodic, >= 2 pinned (phantom end points).
    """
    name = curve_kind(curve_type, basis, wrap)
    if curve_type == "linear":
        minimum = 3 if wrap == "periodic" else 2
        return VertexCountRule(minimum, 1, f"{name} curves need at least {minimum} points")
    if basis == "bezier":
        if wrap == "periodic":
            return VertexCountRule(3, 3, f"{name} curves need 3k points (3, 6, 9, ...)")
        return VertexCountRule(4, 3, f"{name} curves need 4 + 3k points (4, 7, 10, ...)")
    minimum = {"nonperiodic": 4, "periodic": 3, "pinned": 2}[wrap]
    return VertexCountRule(minimum, 1, f"{name} curves need at least {minimum} points")


def segment_counts(counts: np.ndarray, curve_type: str, basis: str, wrap: str) -> np.ndarray:
    """Segments per curve (UsdGeomBasisCurves docs, "curve segment count" table).

    Only meaningful for counts that pass :func:`vertex_count_rule`.
    """
    counts = np.asarray(counts, dtype=np.int64)
    if curve_type == "linear":
        return counts if wrap == "periodic" else counts - 1
    vstep = VSTEP[basis]
    if wrap == "periodic":
        return counts // vstep
    if wrap == "pinned" and basis != "bezier":
        return counts - 1  # one phantom point at each end: (n + 2 - 4) / 1 + 1
    return (counts - 4) // vstep + 1


def varying_counts(counts: np.ndarray, curve_type: str, basis: str, wrap: str) -> np.ndarray:
    """Varying values per curve: segments + 1, or segments for periodic curves.

    This is the documented table. usd-core's ``ComputeVaryingDataSize`` disagrees with it
    for linear periodic (n + 1) and pinned bspline/catmullRom (n - 2) curves; the docs,
    whose worked example gives linear periodic [3 7] -> [3 7], are followed here.
    """
    segs = segment_counts(counts, curve_type, basis, wrap)
    return segs if wrap == "periodic" else segs + 1


def expected_widths_count(
    interpolation: str, counts: np.ndarray, curve_type: str, basis: str, wrap: str
) -> int:
    """Number of width values that ``interpolation`` needs for these curves."""
    if interpolation == "constant":
        return 1
    counts = np.asarray(counts, dtype=np.int64)
    if interpolation == "uniform":
        return int(counts.size)
    if interpolation == "varying":
        return int(varying_counts(counts, curve_type, basis, wrap).sum())
    if interpolation == "vertex":
        return int(counts.sum())
    raise ValueError(f"unknown widths interpolation {interpolation!r}")


def zero_length_curves(points: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Indices of the curves whose points are all equal, to float32 precision.

    ``counts`` must be positive and sum to ``len(points)``. A curve is zero-length when
    its bounding box is no larger than a few float32 ulps of its coordinates' magnitude.
    Curves with NaN/Inf points are not returned (they are reported as non-finite).
    """
    if counts.size == 1:  # common for many small prims: skip the segmented reductions
        pmax, pmin = points.max(axis=0, keepdims=True), points.min(axis=0, keepdims=True)
    else:
        starts = np.zeros(counts.size, dtype=np.int64)
        np.cumsum(counts[:-1], out=starts[1:])
        pmax = np.maximum.reduceat(points, starts, axis=0)
        pmin = np.minimum.reduceat(points, starts, axis=0)
    extent = (pmax - pmin).max(axis=1)
    mag = np.maximum(np.abs(pmax), np.abs(pmin)).max(axis=1)
    return np.flatnonzero((extent <= _ZERO_LENGTH_RTOL * mag) & np.isfinite(mag))


# --------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------


def _list(indices: np.ndarray, noun: str = "curve") -> str:
    """'curve 3 has' / '42 curves (3, 17, 21, 30, 33, ...) have': the offenders of a problem."""
    n = int(indices.size)
    if n == 1:
        return f"{noun} {int(indices[0])} has"
    head = ", ".join(str(int(i)) for i in indices[:_LIST_LIMIT])
    return f"{n} {noun}s ({head}{', ...' if n > _LIST_LIMIT else ''}) have"


def _eg(indices: np.ndarray, counts: np.ndarray) -> str:
    """' (5 points)' for one offender, ' (curve 3: 5 points)' for the first of several."""
    i = int(indices[0])
    if indices.size == 1:
        return f" ({int(counts[i])} points)"
    return f" (curve {i}: {int(counts[i])} points)"


def _layer_of(obj: Usd.Attribute | Usd.Prim | None, time: Usd.TimeCode) -> str | None:
    """Identifier of the layer with the strongest opinion (only computed for problems)."""
    if obj is None:
        return None
    try:
        stack = obj.GetPropertyStack(time) if isinstance(obj, Usd.Attribute) else obj.GetPrimStack()
    except Exception:  # noqa: BLE001 - a missing layer must not hide the problem itself
        return None
    return stack[0].layer.identifier if stack else None


def _fmt_time(t: Usd.TimeCode) -> str:
    return "default" if t.IsDefault() else f"{t.GetValue():g}"


class _Collector:
    """Keeps the first occurrence of each (code, attribute) and counts affected samples."""

    def __init__(self, prim: Usd.Prim) -> None:
        self.prim = prim
        self._first: dict[tuple[str, str | None], tuple] = {}
        self._hits: dict[tuple[str, str | None], int] = {}

    def add(self, code: str, severity: Severity, attr: Usd.Attribute | str | None,
            message: str, time: Usd.TimeCode, sampled: bool) -> None:
        """Record a problem at ``time``; ``sampled`` says whether the data it comes from is
        time-sampled (otherwise the problem is reported without a time)."""
        name = attr if isinstance(attr, str) or attr is None else attr.GetName()
        key = (code, name)
        self._hits[key] = self._hits.get(key, 0) + 1
        if key not in self._first:
            self._first[key] = (severity, attr, message, time if sampled else None)

    def problems(self) -> list[Problem]:
        out = []
        path = str(self.prim.GetPath())
        for key, (severity, attr, message, time) in self._first.items():
            code, name = key
            if time is not None and time.IsDefault():
                message += " (in the default value)"
            elif time is not None:
                hits = self._hits[key]
                message += (f" (at {hits} time samples, first at time {_fmt_time(time)})"
                            if hits > 1 else f" (at time {_fmt_time(time)})")
            layer_obj = attr if isinstance(attr, Usd.Attribute) else self.prim
            out.append(Problem(
                code=code, severity=severity, prim=path, attribute=name, message=message,
                layer=_layer_of(layer_obj, Usd.TimeCode.Default() if time is None else time),
                time=None if time is None or time.IsDefault() else time.GetValue(),
            ))
        return out


def _samples(attr: Usd.Attribute | None) -> list[float]:
    return attr.GetTimeSamples() if attr is not None else []


def _has_default(attr: Usd.Attribute) -> bool:
    return attr.GetResolveInfo(Usd.TimeCode.Default()).GetSource() == Usd.ResolveInfoSourceDefault


def check_times(samples: Iterable[float], sampled_attrs: Sequence[Usd.Attribute] = ()
                ) -> list[Usd.TimeCode]:
    """Times to evaluate data whose authored samples are ``samples``, per the running
    validation's time selection (``usdfiber check --time``; everything by default).

    No samples: the default value, once. Otherwise every selected sample, plus the default
    value when the selection includes it and every time-sampled attribute also has an
    authored default (an attribute with samples only has no value at the default time).
    """
    samples = sorted(set(samples))
    if not samples:
        return [Usd.TimeCode.Default()]
    sel = current_times()
    if sel.single is not None:
        return [Usd.TimeCode(sel.single)]
    if sel.everything:
        chosen = samples
    else:
        chosen = [t for t in samples if sel.start <= t <= sel.end]
        if not chosen and math.isfinite(sel.start):
            chosen = [sel.start]  # no sample inside: the value held over the interval
    out = [Usd.TimeCode(t) for t in chosen]
    if sel.include_default and sampled_attrs and all(_has_default(a) for a in sampled_attrs):
        out.insert(0, Usd.TimeCode.Default())
    return out


def _array(attr: Usd.Attribute, time: Usd.TimeCode, dtype, width: int = 0) -> np.ndarray:
    """The attribute's value as a numpy array (empty when unauthored)."""
    value = attr.Get(time)
    if value is None:
        return np.zeros((0, width) if width else 0, dtype=dtype)
    arr = np.asarray(value)
    return arr if arr.dtype == dtype else arr.astype(dtype)


def _widths_source(prim: Usd.Prim
                   ) -> tuple[Usd.Attribute | None, UsdGeom.Primvar | None, str, bool]:
    """The widths in effect: primvars:widths when authored (it takes precedence over widths
    in Hydra), else the widths attribute. Returns (attribute, primvar, interpolation,
    whether the interpolation is authored)."""
    attr = prim.GetAttribute("primvars:widths")
    if attr and attr.HasAuthoredValue():
        pv = UsdGeom.Primvar(attr)
        return attr, pv, str(pv.GetInterpolation()), pv.HasAuthoredInterpolation()
    attr = prim.GetAttribute("widths")
    if attr and attr.HasAuthoredValue():
        return (attr, None, str(UsdGeom.Curves(prim).GetWidthsInterpolation()),
                attr.HasMetadata("interpolation"))
    return None, None, "vertex", False


def _finite_matrix(m: Gf.Matrix4d) -> bool:
    """True when every entry of ``m`` is finite.

    Fast path: the determinant's expansion multiplies every entry, so a NaN or Inf entry
    makes it non-finite; only then are the entries themselves looked at (a huge but finite
    matrix can overflow the determinant).
    """
    return math.isfinite(m.GetDeterminant()) or bool(np.isfinite(np.asarray(m)).all())


class _StageXforms:
    """Per-stage cache of xform sample times (a prim's own and its ancestors') and of
    UsdGeom.XformCache per time, so that 100k sibling prims share their ancestors' work.

    Dropped on any change of the stage (Usd.Notice.ObjectsChanged), so edits between or
    during runs are always seen.
    """

    def __init__(self, stage: Usd.Stage) -> None:
        self.times: dict[Sdf.Path, tuple[float, ...]] = {}
        self.caches: dict[float | None, UsdGeom.XformCache] = {}
        self._listener = Tf.Notice.Register(Usd.Notice.ObjectsChanged, self._changed, stage)

    def _changed(self, notice, sender) -> None:
        self.times.clear()
        self.caches.clear()

    def sample_times(self, prim: Usd.Prim) -> tuple[float, ...]:
        """Authored xform op samples of ``prim`` and all its ancestors, sorted."""
        path = prim.GetPath()
        got = self.times.get(path)
        if got is None:
            parent = prim.GetParent()
            inherited = self.sample_times(parent) if parent and not parent.IsPseudoRoot() else ()
            own = UsdGeom.Xformable(prim).GetTimeSamples() if prim.IsA(UsdGeom.Xformable) else []
            got = tuple(sorted(set(own).union(inherited))) if own else inherited
            self.times[path] = got
        return got

    def local_to_world(self, prim: Usd.Prim, time: Usd.TimeCode) -> Gf.Matrix4d:
        key = None if time.IsDefault() else time.GetValue()
        cache = self.caches.get(key)
        if cache is None:
            cache = self.caches[key] = UsdGeom.XformCache(time)
        return cache.GetLocalToWorldTransform(prim)


# Stage wrappers are unique per stage and weak-referenceable: entries go with their stage.
_STAGE_XFORMS: "weakref.WeakKeyDictionary[Usd.Stage, _StageXforms]" = weakref.WeakKeyDictionary()


def _stage_xforms(stage: Usd.Stage) -> _StageXforms:
    entry = _STAGE_XFORMS.get(stage)
    if entry is None:
        entry = _STAGE_XFORMS[stage] = _StageXforms(stage)
    return entry


# --------------------------------------------------------------------------------------
# The checks
# --------------------------------------------------------------------------------------


def transform_problems(prim: Usd.Prim) -> tuple[list[Problem], float]:
    """NaN/Inf in the local-to-world transform, at every authored sample of the prim's and
    its ancestors' xform ops (or once, when nothing is animated).

    Also returns the transform's uniform scale at the first time checked (cube root of
    |det| of its 3x3 part; NaN when degenerate or not finite), which scales the widths.
    """
    xforms = _stage_xforms(prim.GetStage())
    times = xforms.sample_times(prim)
    col = _Collector(prim)
    scale = float("nan")
    for i, t in enumerate(check_times(times)):
        m = xforms.local_to_world(prim, t)
        if _finite_matrix(m):
            if i == 0:
                det = abs(m.GetDeterminant3())
                scale = det ** (1.0 / 3.0) if det > 0 else float("nan")
            if not _is_uniform_fast(m):
                sv, mean, nonuniform = axis_scales(np.asarray(m)[:3, :3])
                if nonuniform:
                    col.add("NonUniformScale", Severity.WARNING, None,
                            f"the local-to-world transform scales the axes by "
                            f"{', '.join(f'{x:.6g}' for x in sv)}; round tubes cannot show that, "
                            f"so widths are scaled by the geometric mean {mean:.6g}; expected a "
                            f"uniform scale", t, sampled=bool(times))
            continue
        # Name the (outermost) prim whose own xform ops produce the non-finite matrix.
        chain = []
        q = prim
        while q and not q.IsPseudoRoot():
            chain.append(q)
            q = q.GetParent()
        culprit = next((q for q in reversed(chain) if q.IsA(UsdGeom.Xformable) and not
                        _finite_matrix(UsdGeom.Xformable(q).GetLocalTransformation(t))), prim)
        col.add("TransformNotFinite", Severity.ERROR, None,
                f"local-to-world transform contains NaN or Inf (from the xform ops of "
                f"{culprit.GetPath()}); expected a finite matrix", t, sampled=bool(times))
    return col.problems(), scale


def _is_uniform_fast(m: Gf.Matrix4d) -> bool:
    """True for the common case of a transform without scale or with one uniform scale
    (rows of the 3x3 part orthogonal and of equal length), without an SVD."""
    a = np.asarray(m)[:3, :3]
    with np.errstate(over="ignore", invalid="ignore"):  # scales past 1e154: not uniform here, the SVD decides
        g = a @ a.T
        d = float(g[0, 0])
        return d > 0 and bool(np.all(np.abs(g - d * np.eye(3)) <= 1e-9 * d))


def _is_number(v: object) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


@dataclass(frozen=True)
class WidthScale:
    """The width a fiber or yarn curve should have, in metres, and the allowed factor."""

    expected_m: float
    factor: float
    what: str  # describes the source of expected_m, for messages


def expected_width(prim: Usd.Prim, time: Usd.TimeCode,
                   applied: Sequence[str] | None = None) -> WidthScale | None:
    """Expected curve width of a fiber or yarn prim (None when its size values are invalid,
    which the value checks report).

    Fiber curves (FiberAPI without FiberYarnAPI): fiber:diameter * 1e-6 m, factor
    FIBER_WIDTH_FACTOR (1.5). Yarn curves: :func:`usdfiber.spec.yarn.yarn_diameter` of yarn:plies and
    yarn:ply:radius * 1e-3 m, factor YARN_WIDTH_FACTOR (4).
    """
    if YARN_API in (prim.GetAppliedSchemas() if applied is None else applied):
        plies_attr = prim.GetAttribute(Yarn.PLIES)
        radius_attr = prim.GetAttribute(Yarn.PLY_RADIUS)
        plies = plies_attr.Get(time) if plies_attr else None
        radius_mm = radius_attr.Get(time) if radius_attr else None
        # Wrong types and ranges are the value check's to report; here they just opt out.
        if not (_is_number(plies) and _is_number(radius_mm)) or plies < 1 or not (
                0 < radius_mm < math.inf):
            return None
        d = yarn_diameter(int(plies), float(radius_mm) * 1e-3)
        return WidthScale(d, YARN_WIDTH_FACTOR,
                          f"the nominal yarn diameter {d * 1e3:.4g} mm ({plies} plies of radius "
                          f"{radius_mm:g} mm: 2r(1 + 1/sin(pi/plies)))")
    diam_attr = prim.GetAttribute(Fiber.DIAMETER)
    diam_um = diam_attr.Get(time) if diam_attr else None
    if not _is_number(diam_um) or not (0 < diam_um < math.inf):
        return None
    return WidthScale(float(diam_um) * 1e-6, FIBER_WIDTH_FACTOR, f"fiber:diameter {diam_um:g} um")


def width_scale_problem(
    prim: Usd.Prim, widths: np.ndarray, time: Usd.TimeCode, scale: float, mpu: float,
    applied: Sequence[str] | None = None,
) -> str | None:
    """Message when the curves' widths disagree with the fiber or yarn size, else None.

    Rule: w = median of the positive finite widths * local-to-world scale * metersPerUnit
    (metres) must lie within a factor ``expected_width().factor`` of
    ``expected_width().expected_m`` either way. The median keeps tapered tips and a few
    stray curves from triggering it; a unit error moves all widths.
    """
    ref = expected_width(prim, time, applied)
    if ref is None or not (scale > 0) or not (mpu > 0):
        return None
    to_m = scale * mpu
    lo, hi = ref.expected_m / ref.factor / to_m, ref.expected_m * ref.factor / to_m
    wmin, wmax = float(widths.min()), float(widths.max())
    good = widths if wmin > 0 and wmax < math.inf else widths[(widths > 0) & (widths < math.inf)]
    if good.size == 0:
        return None
    if lo <= float(good.min()) and float(good.max()) <= hi:
        return None  # fast path: every width is in range, so is the median
    median = float(np.median(good))
    if lo <= median <= hi:
        return None
    stage = prim.GetStage()
    mpu_note = f"metersPerUnit {mpu:g}" + (
        "" if UsdGeom.StageHasAuthoredMetersPerUnit(stage) else ", not authored: USD's fallback")
    scale_note = "" if abs(scale - 1.0) < 1e-9 else f" x transform scale {scale:g}"
    world_m = median * to_m
    return (f"median curve width {median:.4g} scene units{scale_note} ({mpu_note}) is "
            f"{world_m:.4g} m, {world_m / ref.expected_m:.3g}x {ref.what}; expected widths "
            f"of about {ref.expected_m / to_m:.4g} scene units (within a factor "
            f"{ref.factor:g} either way); check the units of the widths and the stage's "
            f"metersPerUnit")


def check_curves_prim(prim: Usd.Prim) -> list[Problem]:
    """All topology and value checks on one fiber or yarn curves prim."""
    if prim.IsAbstract() or not prim.IsA(UsdGeom.BasisCurves):
        return []
    applied = prim.GetAppliedSchemas()
    if FIBER_API not in applied and YARN_API not in applied:
        return []
    curves = UsdGeom.BasisCurves(prim)
    path = str(prim.GetPath())
    problems: list[Problem] = []
    err, warn = Severity.ERROR, Severity.WARNING

    type_attr, basis_attr = curves.GetTypeAttr(), curves.GetBasisAttr()
    wrap_attr = curves.GetWrapAttr()
    curve_type, basis, wrap = str(type_attr.Get()), str(basis_attr.Get()), str(wrap_attr.Get())
    for attr, value, allowed in ((type_attr, curve_type, CURVE_TYPES),
                                 (basis_attr, basis, CURVE_BASES),
                                 (wrap_attr, wrap, CURVE_WRAPS)):
        if value not in allowed and not (attr is basis_attr and curve_type == "linear"):
            problems.append(Problem(
                "CurveTypeInvalid", err, path, attr.GetName(),
                f"{attr.GetName()} is {value!r}; expected one of {', '.join(allowed)}",
                layer=_layer_of(attr, Usd.TimeCode.Default())))
    xform_problems, scale = transform_problems(prim)
    if problems:
        return problems + xform_problems
    rule = vertex_count_rule(curve_type, basis, wrap)
    kind = curve_kind(curve_type, basis, wrap)

    counts_attr, points_attr = curves.GetCurveVertexCountsAttr(), curves.GetPointsAttr()
    widths_attr, widths_pv, interp, interp_authored = _widths_source(prim)
    counts_t, points_t = _samples(counts_attr), _samples(points_attr)
    widths_t = _samples(widths_attr) + (_samples(widths_pv.GetIndicesAttr()) if widths_pv else [])
    sampled_attrs = [a for a, ts in ((counts_attr, counts_t), (points_attr, points_t)) if ts]
    if widths_t:
        indices_attr = widths_pv.GetIndicesAttr() if widths_pv else None
        sampled_attrs += [a for a in (widths_attr, indices_attr)
                          if a is not None and a.GetNumTimeSamples()]
    times = check_times([*counts_t, *points_t, *widths_t], sampled_attrs)
    problems.extend(_animated_only_problems(prim, points_attr))
    # A problem carries a time only when the data it comes from is time-sampled.
    counts_s = bool(counts_t)
    points_s = counts_s or bool(points_t)
    widths_s = bool(widths_t)
    mpu = UsdGeom.GetStageMetersPerUnit(prim.GetStage())
    xforms = _stage_xforms(prim.GetStage())
    col = _Collector(prim)

    if widths_attr is None:
        # Renderers then fall back to a width of their own (1 scene unit in Hydra), which has
        # nothing to do with the fiber: say what the widths should be.
        ref = expected_width(prim, Usd.TimeCode.Default(), applied)
        scale_m = scale * mpu if scale > 0 and mpu > 0 else float("nan")
        about = (f"; expected widths of about {ref.expected_m / scale_m:.4g} scene units "
                 f"({ref.what})" if ref is not None and math.isfinite(scale_m) else "")
        problems.append(Problem(
            "WidthsMissing", warn, path, "widths",
            f"no widths authored, so the curves have no defined thickness{about}",
            layer=_layer_of(prim, Usd.TimeCode.Default())))
    elif interp == "faceVarying":
        problems.append(Problem(
            "WidthsFaceVarying", warn, path, widths_attr.GetName(),
            "widths interpolation is 'faceVarying', which curves do not define; read as "
            "'varying' (one value per segment end); expected 'varying'",
            layer=_layer_of(widths_attr, times[0])))
        interp = "varying"
    elif interp not in WIDTH_INTERPOLATIONS:
        problems.append(Problem(
            "WidthsInterpolationInvalid", err, path, widths_attr.GetName(),
            f"widths interpolation is {interp!r}; expected one of "
            f"{', '.join(WIDTH_INTERPOLATIONS)}", layer=_layer_of(widths_attr, times[0])))
    if widths_pv is not None and widths_pv.GetElementSize() != 1:
        problems.append(Problem(
            "WidthsElementSize", err, path, widths_attr.GetName(),
            f"primvars:widths has elementSize {widths_pv.GetElementSize()}; expected 1 (one "
            f"width per interpolated element)", layer=_layer_of(widths_attr, times[0])))
    normals = [prim.GetAttribute(n) for n in ("normals", "primvars:normals")]
    authored_normals = [a for a in normals if a and a.HasAuthoredValue()]
    if authored_normals:
        problems.append(Problem(
            "NormalsIgnored", warn, path, authored_normals[0].GetName(),
            "normals are authored (oriented ribbons), which the renderer cannot draw: the "
            "curves are drawn as round tubes of the same width; expected no normals on fiber "
            "curves", layer=_layer_of(authored_normals[0], times[0])))

    for t in times:
        counts = _array(counts_attr, t, np.int64).reshape(-1)
        points = _array(points_attr, t, np.float32, 3)
        if points.ndim != 2 or points.shape[1] != 3:
            col.add("PointsWrongType", err, points_attr,
                    f"points has values of shape {points.shape}; expected point3f[] (3D "
                    f"points)", t, points_s)
            continue
        n_points = int(points.shape[0])
        total = int(counts.sum())

        # Curve counts: one cheap test each, the detail only when something is wrong.
        topo_ok = total == n_points
        if counts.size and (int(counts.min()) < rule.minimum or (
                rule.step > 1 and ((counts - rule.minimum) % rule.step).any())):
            topo_ok = False
            bad = np.flatnonzero(counts <= 0)
            if bad.size:
                col.add("CurveVertexCountNotPositive", err, counts_attr,
                        f"{_list(bad)} a vertex count <= 0{_eg(bad, counts)}; every count "
                        f"must be positive ({rule.text})", t, counts_s)
            few = np.flatnonzero((counts > 0) & (counts < rule.minimum))
            if few.size:
                col.add("CurveTooFewPoints", err, counts_attr,
                        f"{_list(few)} too few points{_eg(few, counts)}; {rule.text}",
                        t, counts_s)
            off = np.flatnonzero((counts >= rule.minimum) & ~rule.valid(counts))
            if off.size:
                col.add("CurveBezierVertexCount", err, counts_attr,
                        f"{_list(off)} a point count off the bezier step{_eg(off, counts)}; "
                        f"{rule.text}", t, counts_s)
        if total != n_points:
            col.add("CurvesCountsMismatch", err, counts_attr,
                    f"curveVertexCounts sum to {total} but points has {n_points} entries; "
                    f"expected them to be equal", t, points_s)

        # float64 sum: finite exactly when every coordinate is (no float32 overflow).
        if n_points and not math.isfinite(float(points.sum(dtype=np.float64))):
            badp = np.flatnonzero(~np.isfinite(points).all(axis=1))
            col.add("PointsNotFinite", err, points_attr,
                    f"{_list(badp, 'point')} NaN or Inf coordinates; expected finite "
                    f"coordinates", t, points_s)

        world = xforms.local_to_world(prim, t)
        world = np.asarray(world) if _finite_matrix(world) else None
        big, placed, where = too_large(points), points, ""
        if not big.size and world is not None:
            placed = world_points_near_limit(points, world)
            big, where = too_large(placed), "in world space (after the local-to-world transform) "
        if big.size:
            col.add("PointsTooLarge", err, points_attr,
                    f"{where}{_list(big, 'point')} a coordinate of magnitude {MAX_COORDINATE:g} or more "
                    f"(e.g. {_vec(placed[big[0]])}); {TOO_LARGE_EXPECTED}", t, points_s)

        if topo_ok and counts.size:
            zero = zero_length_curves(points, counts)
            if zero.size:
                col.add("CurveZeroLength", warn, points_attr,
                        f"{_list(zero)} all points equal (zero length), so the fiber has "
                        f"no tangent and cannot be shaded; expected distinct points "
                        f"(remove the curve)", t, points_s)

        if widths_attr is None:
            continue
        if widths_pv is not None:
            wv = widths_pv.ComputeFlattened(t)
            widths = np.asarray(wv, dtype=np.float64) if wv is not None else np.zeros(0)
        else:
            widths = _array(widths_attr, t, np.float64)
        widths = widths.reshape(-1)
        if widths.size == 0:
            # The renderer treats empty widths as none: the fiber's own width.
            col.add("WidthsMissing", warn, widths_attr,
                    "widths is authored empty, so the curves have no defined thickness; the "
                    "renderer draws them as wide as the fiber", t, widths_s)
            continue
        w_interp = interp
        if widths.size == 1 and not interp_authored and interp != "constant":
            col.add("WidthsConstantAssumed", warn, widths_attr,
                    f"one width value without interpolation metadata (USD's fallback is "
                    f"{interp!r}); read as constant, as Storm does; expected "
                    f"interpolation = \"constant\"", t, widths_s)
            w_interp = "constant"

        # Varying and vertex counts need valid curves; constant and uniform do not.
        if w_interp in WIDTH_INTERPOLATIONS and (topo_ok or w_interp in ("constant", "uniform")):
            expected = expected_widths_count(w_interp, counts, curve_type, basis, wrap)
            if widths.size != expected:
                how = {
                    "constant": "one value",
                    "uniform": "one per curve",
                    "varying": ("segments per curve, summed" if wrap == "periodic"
                                else "segments + 1 per curve, summed"),
                    "vertex": "one per point",
                }[w_interp]
                topo_ok = False
                col.add("WidthsCountMismatch", err, widths_attr,
                        f"widths has {widths.size} values with {w_interp!r} interpolation; "
                        f"expected {expected} ({how}, for {kind} curves)",
                        t, counts_s or widths_s)

        if widths.size:
            wmin, wmax = float(widths.min()), float(widths.max())  # NaN propagates
            if not (math.isfinite(wmin) and math.isfinite(wmax)):
                badw = np.flatnonzero(~np.isfinite(widths))
                col.add("WidthsNotFinite", err, widths_attr,
                        f"{_list(badw, 'width')} a NaN or Inf value; expected finite "
                        f"positive widths", t, widths_s)
            scaled, where = widths, ""
            big = too_large(widths)
            if not big.size and world is not None and wmax > 0:
                # Widths scale by the geometric mean of the axis scales (as the renderer does).
                with np.errstate(over="ignore"):  # a determinant past float64: beyond the bound too
                    scaled = widths * abs(float(np.linalg.det(world[:3, :3]))) ** (1.0 / 3.0)
                big, where = too_large(scaled), "in world space (scaled by the local-to-world transform) "
            if big.size:
                col.add("WidthsTooLarge", err, widths_attr,
                        f"{where}{_list(big, 'width')} a value of {MAX_COORDINATE:g} or more (e.g. "
                        f"{scaled[big[0]]:g}); {TOO_LARGE_EXPECTED}", t, widths_s)
            elif world is not None and n_points and math.isfinite(wmax) and wmax > 0:
                # The points in world space only where the bound of their reach allows a width
                # below the precision there (most prims: two passes over the points, no copy).
                positive = scaled[scaled > 0]
                if positive.size and not world_reach(points, world) * WIDTH_PRECISION <= float(positive.min()):
                    with np.errstate(over="ignore", invalid="ignore"):
                        world_pts = np.asarray(points, dtype=np.float64) @ world[:3, :3] + world[3, :3]
                    thin = unresolved_widths_text(world_pts, scaled) if np.isfinite(world_pts).all() else None
                    if thin:
                        col.add("WidthBelowPrecision", warn, widths_attr, thin, t, widths_s)
            if not wmin >= 0:
                neg = np.flatnonzero(widths < 0)
                if neg.size:
                    topo_ok = False
                    col.add("WidthNegative", err, widths_attr,
                            f"{_list(neg, 'width')} a negative value (e.g. "
                            f"{widths[neg[0]]:g}); expected widths >= 0", t, widths_s)
            elif (topo_ok and w_interp == "vertex" and curve_type == "cubic"
                  and basis == "catmullRom" and math.isfinite(wmax)):
                # Catmull-Rom widths can overshoot below zero next to a tapered tip: the
                # renderer's conversion says where (and draws nothing there).
                _negative_interpolation(col, widths, counts, wrap, widths_attr, t,
                                        widths_s or counts_s)
            msg = width_scale_problem(prim, widths, t, scale, mpu, applied)
            if msg:
                col.add("WidthMismatch", warn, widths_attr, msg, t, widths_s)

    return problems + col.problems() + xform_problems


def _vec(p: np.ndarray) -> str:
    return "(" + ", ".join(f"{float(x):g}" for x in p) + ")"


def _animated_only_problems(prim: Usd.Prim, points_attr: Usd.Attribute) -> list[Problem]:
    if not animated_only(points_attr):
        return []
    return [Problem(
        "AnimatedOnly", Severity.WARNING, str(prim.GetPath()), points_attr.GetName(),
        "points has time samples and no default value, so nothing is drawn at the default "
        "time; a render without a frame renders the stage's startTimeCode (when authored) or "
        "the first time sample, with a warning; expected a frame to be chosen (render --frame)",
        layer=_layer_of(points_attr, Usd.TimeCode(points_attr.GetTimeSamples()[0])))]


def _negative_interpolation(col: "_Collector", widths: np.ndarray, counts: np.ndarray, wrap: str,
                            widths_attr: Usd.Attribute, t: Usd.TimeCode, sampled: bool) -> None:
    n, worst = negative_vertex_widths(widths, counts, "catmullRom", wrap)
    if n:
        col.add("WidthNegativeInterpolated", Severity.WARNING, widths_attr,
                f"the interpolated width is negative on {n} segment(s) (worst radius "
                f"{worst:.6g}): nothing is drawn there; expected widths that stay >= 0 "
                f"(taper over more points, or use bspline)", t, sampled)


@prim_check(
    "fiberCurves",
    "Topology and values of fiber and yarn curves: curveVertexCounts against points and "
    "the type/basis/wrap point-count rules, widths count against their interpolation, "
    "finite points, widths and transforms, zero-length curves, non-positive widths, and "
    "widths against fiber:diameter (or the yarn's plies) and metersPerUnit; at every "
    "authored time sample.",
)
def _check_fiber_curves(prim: Usd.Prim) -> Sequence[Problem]:
    return check_curves_prim(prim)


# --------------------------------------------------------------------------------------
# Plain curves: what the renderer draws grey, approximates or skips
# --------------------------------------------------------------------------------------

_ATTRIBUTE_IN_WARNING = re.compile(r"attribute '([^']+)'")


def check_plain_curves_prim(prim: Usd.Prim) -> list[Problem]:
    """Warnings for a BasisCurves prim without FiberAPI or FiberYarnAPI.

    The renderer draws such curves as grey tubes through
    :func:`usdfiber.geometry.curves.curves_from_prim` and skips, with a warning, those it
    cannot draw: this check runs that same function at every time checked, so that it warns
    exactly where the renderer skips or approximates.
    """
    if prim.IsAbstract() or not prim.IsA(UsdGeom.BasisCurves):
        return []
    applied = prim.GetAppliedSchemas()
    if FIBER_API in applied or YARN_API in applied:
        return []
    warn = Severity.WARNING
    path = str(prim.GetPath())
    curves = UsdGeom.BasisCurves(prim)
    attrs = [curves.GetCurveVertexCountsAttr(), curves.GetPointsAttr(), curves.GetWidthsAttr(),
             prim.GetAttribute("primvars:widths"), prim.GetAttribute("primvars:widths:indices")]
    attrs = [a for a in attrs if a]
    data_times = [t for a in attrs for t in a.GetTimeSamples()]
    xforms = _stage_xforms(prim.GetStage())
    all_times = [*data_times, *xforms.sample_times(prim)]
    sampled = [a for a in attrs if a.GetNumTimeSamples()]
    col = _Collector(prim)
    for t in check_times(all_times, sampled):
        xform = np.asarray(xforms.local_to_world(prim, t))
        try:
            geom = curves_from_prim(prim, t, xform)
        except (PrimError, ValueError) as exc:
            attribute = getattr(exc, "attribute", None)
            reason = exc.expected if isinstance(exc, PrimError) else str(exc)
            col.add("PlainCurvesSkipped", warn, attribute,
                    f"{reason}; BasisCurves without FiberAPI are drawn as grey tubes, and the "
                    f"renderer skips these", t, bool(all_times))
            continue
        for text in geom.warnings:
            m = _ATTRIBUTE_IN_WARNING.search(text)
            col.add("PlainCurvesApproximated", warn, m.group(1) if m else None,
                    text.split(": ", 1)[-1].split(": ", 1)[-1] if m else text.split(": ", 1)[-1],
                    t, bool(all_times))
    col_problems = col.problems() + _animated_only_problems(prim, curves.GetPointsAttr())
    note = Problem(
        "PlainCurves", warn, path, None,
        "BasisCurves without FiberAPI: the renderer draws them as grey diffuse tubes; "
        "expected FiberAPI (or a fiber class inherited) to render them as fibers",
        layer=_layer_of(prim, Usd.TimeCode.Default()))
    return [note, *col_problems]


@prim_check(
    "plainCurves",
    "BasisCurves without FiberAPI, as the renderer draws them (grey tubes): warnings for "
    "curves it skips (topology, widths, non-finite values) or approximates (non-uniform "
    "scale, ribbons, faceVarying or single widths), from the renderer's own conversion.",
)
def _check_plain_curves(prim: Usd.Prim) -> Sequence[Problem]:
    return check_plain_curves_prim(prim)
