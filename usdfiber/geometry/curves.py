"""UsdGeomBasisCurves -> uniform cubic B-spline curves, exactly; their evaluation and frames.

Renderer-independent: renderers that draw uniform cubic B-spline curves (Mitsuba's
``bsplinecurve``: ``usdfiber.translators.mitsuba.curves``) build their shapes from a
:class:`CurveGeometry`; the yarn generator (:mod:`usdfiber.geometry.yarn`) uses
:func:`reference_normals` for its rotation-minimizing frames.

Every USD curve segment is a cubic (or linear) polynomial in its segment parameter t in [0, 1].
Any cubic polynomial segment is exactly one uniform cubic B-spline segment over the same t,
so each segment is converted with a 4x4 basis-change matrix (Bezier, Catmull-Rom) or kept
(B-spline). The radius is the 4th coordinate: vertex widths go through the same matrix; linear
(varying) widths on one segment, r(t) = ra + (rb - ra) t, are the B-spline with radius controls
(2ra - rb, ra, rb, 2rb - ra), which is why segments may own their 4 control points
(``segment_start`` lets them not share).

Conventions that USD leaves open, and the choices made here:
- pinned bspline/catmullRom: phantom points P[-1] = 2 P[0] - P[1], P[n] = 2 P[n-1] - P[n-2]
  (UsdGeomBasisCurves docs). Vertex widths get phantom values by the same rule, so the radius
  at the pinned ends is the authored one. (Hydra's HdsiPinnedCurveExpandingSceneIndex repeats
  end points instead, which gives a different curve for bspline.)
- faceVarying widths are read as varying (the only per-segment-end interpolation of curves).

Measured with Mitsuba 3.9.1 (llvm, Embree): negative radius *control values* are fine as long
as the evaluated radius is >= 0 (hits exact to float precision), so the linear-width extension
needs no clamping. Where the evaluated radius itself is negative (possible only for Catmull-Rom
vertex widths overshooting below zero) Mitsuba renders no surface: that is warned about.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from pxr import Usd, UsdGeom

from usdfiber.errors import PrimError

__all__ = [
    "NORMALS_CHUNK",
    "UNIFORM_SCALE_RTOL",
    "CurveError",
    "MAX_COORDINATE",
    "TOO_LARGE_EXPECTED",
    "axis_scales",
    "WIDTH_PRECISION",
    "too_large",
    "too_large_text",
    "unresolved_widths_text",
    "world_points_near_limit",
    "world_reach",
    "negative_vertex_widths",
    "CurveGeometry",
    "curves_from_prim",
    "concatenate",
    "evaluate",
    "reference_normals",
    "POWER_BASIS",
    "TO_BSPLINE",
]


class CurveError(PrimError):
    """Malformed BasisCurves data (a :class:`~usdfiber.errors.PrimError`: file, prim, attribute
    and what was expected)."""


#: Largest |coordinate| and width (scene units, authored or in world space) a curve may have.
#: Renderers hold geometry in float32 (largest value 3.4e38); ray-curve intersection squares
#: coordinates and widths and sums a few such squares, so values of 1e18 and above (squares of
#: 1e36 and above) overflow to Inf and the curve silently disappears. Zero widths are fine.
MAX_COORDINATE = 1e18
#: What :data:`MAX_COORDINATE` asks for, in messages.
TOO_LARGE_EXPECTED = (f"expected magnitudes below {MAX_COORDINATE:g} (renderers work in float32, "
                      f"where squares of larger values overflow)")


#: Narrowest width a curve may have relative to the largest magnitude of its points' world
#: coordinates: 2^-22 of it, a radius of one float32 step there. Narrower tubes are thinner than
#: the float32 precision of their own position, which the renderer's intersection works in:
#: they render with holes or vanish (a warning, the curves are still drawn).
WIDTH_PRECISION = 2.0 ** -22


def unresolved_widths_text(world_points: np.ndarray, world_widths: np.ndarray) -> str | None:
    """'3 widths narrower than ...' when positive widths (``world_widths``, in world space) are
    narrower than :data:`WIDTH_PRECISION` of the largest coordinate magnitude of
    ``world_points``, else None. Zero widths (tapered tips) are fine."""
    if not world_points.size or not world_widths.size:
        return None
    magnitude = float(np.abs(world_points).max())
    limit = magnitude * WIDTH_PRECISION
    w = np.asarray(world_widths, dtype=np.float64).ravel()
    thin = np.flatnonzero((w > 0) & (w < limit))
    if not thin.size:
        return None
    return (f"{thin.size} width{'s' if thin.size > 1 else ''} narrower than {limit:g} (e.g. {w[thin[0]]:g} in "
            f"world space): 2^-22 of the points' largest coordinate ({magnitude:g}), a radius below one "
            f"float32 step there, where the renderer intersects them, so these curves render with holes "
            f"or vanish; "
            f"expected the asset nearer the origin, or wider curves")


def too_large(values: np.ndarray) -> np.ndarray:
    """Indices of the rows of ``values`` (one value or point each) holding a magnitude of
    :data:`MAX_COORDINATE` or more (NaN and Inf are the finiteness checks' to report)."""
    if values.size == 0 or (values.max() < MAX_COORDINATE and values.min() > -MAX_COORDINATE):
        return np.zeros(0, np.int64)
    with np.errstate(invalid="ignore"):
        big = np.isfinite(values) & (np.abs(values) >= MAX_COORDINATE)
    return np.flatnonzero(big.reshape(len(values), -1).any(axis=1))


def world_reach(points: np.ndarray, m: np.ndarray) -> float:
    """A bound of the largest coordinate magnitude of ``points`` in world space (``m``: a
    row-vector local-to-world matrix) from two passes and no copy; NaN when a point is not
    finite, 0 for no points."""
    if not points.size:
        return 0.0
    m = np.asarray(m, dtype=np.float64)
    lo, hi = float(points.min()), float(points.max())
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return math.nan
    return max(abs(lo), abs(hi)) * float(np.abs(m[:3, :3]).sum(axis=0).max()) + float(np.abs(m[3, :3]).max())


def world_points_near_limit(points: np.ndarray, m: np.ndarray) -> np.ndarray:
    """``points`` in world space (``m``: a row-vector local-to-world matrix) when their
    :func:`world_reach` reaches :data:`MAX_COORDINATE` (then :func:`too_large` says which are
    beyond), else an empty array: the common case costs two passes and no copy."""
    if points.size:
        m = np.asarray(m, dtype=np.float64)
        if world_reach(points, m) >= MAX_COORDINATE:   # False for NaN: the finiteness checks'
            with np.errstate(over="ignore", invalid="ignore"):
                world = points.astype(np.float64) @ m[:3, :3] + m[3, :3]
            # Finite points that overflow float64 there are beyond the limit too.
            big = np.finfo(np.float64).max
            return np.nan_to_num(world, nan=big, posinf=big, neginf=-big)
    return np.zeros((0, 3))


def too_large_text(values: np.ndarray, noun: str) -> str | None:
    """'2 points of magnitude 1e+18 or more (first: point 3, (1e+30, 0, 0)); expected ...' for
    the rows of ``values`` that :func:`too_large` finds ('<noun> (...) is of magnitude ...' for
    a single row), or None when there are none."""
    bad = too_large(values)
    if not bad.size:
        return None
    first = ", ".join(f"{x:g}" for x in np.atleast_1d(values[bad[0]]))
    if len(values) == 1:
        return f"{noun} ({first}) is of magnitude {MAX_COORDINATE:g} or more; {TOO_LARGE_EXPECTED}"
    return (f"{bad.size} {noun}{'s' if bad.size > 1 else ''} of magnitude {MAX_COORDINATE:g} or more "
            f"(first: {noun} {int(bad[0])}, ({first})); {TOO_LARGE_EXPECTED}")


# Power-basis matrices M of USD's cubic bases: P(t) = [t^3, t^2, t, 1] @ M @ [P0, P1, P2, P3].
POWER_BASIS: dict[str, np.ndarray] = {
    "bezier": np.array([[-1, 3, -3, 1], [3, -6, 3, 0], [-3, 3, 0, 0], [1, 0, 0, 0]], float),
    "bspline": np.array([[-1, 3, -3, 1], [3, -6, 3, 0], [-3, 0, 3, 0], [1, 4, 1, 0]], float) / 6,
    "catmullRom": np.array([[-1, 3, -3, 1], [2, -5, 4, -1], [-1, 0, 1, 0], [0, 2, 0, 0]], float) / 2,
}
# Basis change to uniform B-spline controls: M_bspline @ (T @ P) == M_basis @ P.
TO_BSPLINE: dict[str, np.ndarray] = {
    k: np.linalg.solve(POWER_BASIS["bspline"], m) for k, m in POWER_BASIS.items()
}
_VSTEP = {"bezier": 3, "bspline": 1, "catmullRom": 1}
# B-spline weights of the 4 controls at t = 0.5 (position) and their derivative.
_MID_W = np.array([1, 23, 23, 1], float) / 48
_MID_DW = np.array([-1, -5, 5, 1], float) / 8


@dataclass
class CurveGeometry:
    """Uniform cubic B-spline curves in world space (ready for Mitsuba's ``bsplinecurve``).

    Segment ``s`` is the B-spline over ``points[segment_start[s] + 0..3]`` (and the same radii),
    with parameter t in [0, 1] equal to USD's segment parameter. Segments are ordered by
    source curve, then by their order along the curve.
    """

    points: np.ndarray  # (P, 3) float64, world-space control points
    radii: np.ndarray  # (P,) float64, world-space radius control values (may be < 0, see module doc)
    segment_start: np.ndarray  # (S,) int64, first of the 4 control points of each segment
    segment_curve: np.ndarray  # (S,) int64, source curve index (curveVertexCounts order)
    curve_count: int  # number of source curves
    warnings: list[str] = field(default_factory=list)  # approximations made (empty when exact)
    segment_part: np.ndarray | None = None  # (S,) int64, index of the part (see concatenate)

    def __post_init__(self) -> None:
        if self.segment_part is None:
            self.segment_part = np.zeros(len(self.segment_start), np.int64)

    @property
    def segment_count(self) -> int:
        """Number of B-spline segments."""
        return int(len(self.segment_start))


# ---------------------------------------------------------------------------------------------
# Reading the prim
# ---------------------------------------------------------------------------------------------


def _err(prim: Usd.Prim, attr: str, msg: str) -> CurveError:
    return CurveError.at(prim, attr, msg)


def _too_large(prim: Usd.Prim, attr: str | None, values: np.ndarray, noun: str, where: str = "") -> None:
    text = too_large_text(values, noun)
    if text:
        raise _err(prim, attr, where + text)


def _token(prim: Usd.Prim, attr: Usd.Attribute, allowed: tuple[str, ...]) -> str:
    value = str(attr.Get())  # uniform attributes; Get() returns the schema fallback if unauthored
    if value not in allowed:
        raise _err(prim, attr.GetName(), f"got {value!r}, expected one of {list(allowed)}")
    return value


def _read_widths(
    prim: Usd.Prim, time: Usd.TimeCode, default_width: float | None
) -> tuple[np.ndarray, str, str, list[str]]:
    """Return (widths, interpolation, attribute name, warnings).

    One width value whose interpolation is not authored (USD's fallback is vertex) is read as
    a constant width, with a note: Pixar's own test stages author widths so and Storm draws
    them that way. Zero widths (tapered tips) are valid; negative ones are not.
    """
    warnings: list[str] = []
    pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar("widths")
    if pv and pv.HasAuthoredValue():  # primvars:widths takes precedence over widths
        name = "primvars:widths"
        if pv.GetElementSize() != 1:
            raise _err(prim, name, f"elementSize {pv.GetElementSize()} is not supported, expected 1")
        value = pv.ComputeFlattened(time)
        interp = str(pv.GetInterpolation())
        authored_interp = pv.HasAuthoredInterpolation()
    else:
        curves = UsdGeom.Curves(prim)
        attr = curves.GetWidthsAttr()
        name = "widths"
        value = attr.Get(time) if attr.HasAuthoredValue() else None
        interp = str(curves.GetWidthsInterpolation())
        authored_interp = attr.HasMetadata("interpolation")
    if value is None or len(value) == 0:
        if default_width is None:
            raise _err(prim, "widths", "no widths authored (neither primvars:widths nor widths); "
                       "expected curve widths (diameters in scene units)")
        return np.array([float(default_width)]), "constant", "widths", warnings
    w = np.asarray(value, dtype=np.float64).reshape(-1)
    if len(w) == 1 and not authored_interp and interp != "constant":
        warnings.append(f"{prim.GetPath()}: attribute '{name}': one width without interpolation "
                        "metadata; read as constant (as Storm does)")
        interp = "constant"
    if interp == "faceVarying":
        warnings.append(f"{prim.GetPath()}: attribute '{name}': faceVarying interpolation is "
                        "not defined for curves; read as varying")
        interp = "varying"
    if interp not in ("constant", "uniform", "varying", "vertex"):
        raise _err(prim, name, f"interpolation {interp!r}, expected constant, uniform, varying or vertex")
    if not np.all(np.isfinite(w)):
        raise _err(prim, name, "contains NaN or Inf")
    _too_large(prim, name, w, "width")
    if np.any(w < 0):
        raise _err(prim, name, f"contains negative widths (min {w.min():g}); widths are diameters >= 0")
    return w, interp, name, warnings


#: Relative spread of a transform's axis scales below which it scales uniformly. Point-instancer
#: orientations are often half floats (quath, 11-bit significands): their rotations are
#: orthogonal only to a few 2^-11, so rotated instances of a uniform scale show axis scales that
#: differ by ~1e-3. Below 2^-8 the tube's radius error (the geometric mean) is under 0.4 %.
UNIFORM_SCALE_RTOL = 2.0 ** -8


def axis_scales(m3: np.ndarray) -> tuple[np.ndarray, float, bool]:
    """(axis scales, their geometric mean, whether they differ beyond :data:`UNIFORM_SCALE_RTOL`)
    of the linear part ``m3`` (3x3) of a transform: the rule for a curve's radius under it."""
    sv = np.linalg.svd(np.asarray(m3, dtype=np.float64), compute_uv=False)
    with np.errstate(over="ignore"):  # scales past 1e100: Inf, which the bounds refuse
        scale = float(np.prod(sv) ** (1.0 / 3.0))
    return sv, scale, bool(sv[0] - sv[-1] > UNIFORM_SCALE_RTOL * sv[0])


def _linear_scale(prim: Usd.Prim, m3: np.ndarray, warnings: list[str]) -> float:
    """Radius scale factor of a linear map; warns when the map does not scale uniformly."""
    sv, scale, nonuniform = axis_scales(m3)
    if nonuniform:
        warnings.append(
            f"{prim.GetPath()}: attribute 'widths': non-uniform scale (axis scales "
            f"{', '.join(f'{s:.6g}' for s in sv)}) cannot be represented on round tubes; radii "
            f"scaled by their geometric mean {scale:.6g}")
    return scale


# ---------------------------------------------------------------------------------------------
# Segment topology (vectorized over curves)
# ---------------------------------------------------------------------------------------------


def _segments(counts: np.ndarray, nseg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(curve index, index within its curve) of every segment."""
    curve = np.repeat(np.arange(len(counts), dtype=np.int64), nseg)
    first = np.cumsum(nseg) - nseg
    return curve, np.arange(len(curve), dtype=np.int64) - first[curve]


def _pin(values: np.ndarray, counts: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Insert phantom values v[-1] = 2 v[0] - v[1] and v[n] = 2 v[n-1] - v[n-2] around each curve."""
    ncurves = len(counts)
    out = np.empty((len(values) + 2 * ncurves,) + values.shape[1:], values.dtype)
    curve_of = np.repeat(np.arange(ncurves), counts)
    out[np.arange(len(values)) + 2 * curve_of + 1] = values
    first, last = offsets, offsets + counts - 1
    ext_first = first + 2 * np.arange(ncurves)
    out[ext_first] = 2 * values[first] - values[first + 1]
    out[ext_first + counts + 1] = 2 * values[last] - values[last - 1]
    return out


def _check_counts(prim: Usd.Prim, counts: np.ndarray, ok: np.ndarray, rule: str) -> None:
    if not np.all(ok):
        bad = np.flatnonzero(~ok)
        raise _err(prim, "curveVertexCounts",
                   f"{len(bad)} curve(s) violate '{rule}' (first: curve {bad[0]} with "
                   f"{counts[bad[0]]} vertices)")


# ---------------------------------------------------------------------------------------------
# Conversion
# ---------------------------------------------------------------------------------------------


def curves_from_prim(
    prim: Usd.Prim,
    time: Usd.TimeCode = Usd.TimeCode.Default(),
    xform: np.ndarray | None = None,
    *,
    default_width: float | None = None,
) -> CurveGeometry:
    """Convert a UsdGeomBasisCurves prim to world-space uniform cubic B-spline segments.

    ``xform`` is a 4x4 row-vector matrix (USD convention, p' = [p, 1] @ xform); it defaults to
    the prim's local-to-world transform at ``time``. Radii are widths / 2, scaled by the
    transform's scale (geometric mean and a warning when it is not uniform). ``default_width``
    is used when no widths are authored; without it that is an error.

    Exact for every type/basis/wrap and width interpolation of the USD definition. Warnings:
    non-uniform scale, ribbons (authored normals: rendered as round tubes), faceVarying widths,
    Catmull-Rom vertex widths that evaluate below zero. Raises CurveError for malformed input.
    """
    path = prim.GetPath()
    if not prim.IsA(UsdGeom.BasisCurves):
        raise CurveError.at(prim, None, f"prim of type {prim.GetTypeName()!r} is not a BasisCurves")
    bc = UsdGeom.BasisCurves(prim)
    ctype = _token(prim, bc.GetTypeAttr(), ("linear", "cubic"))
    # USD ignores the basis of linear curves (Maya writes basis = "" for them).
    basis = ("bezier" if ctype == "linear"
             else _token(prim, bc.GetBasisAttr(), ("bezier", "bspline", "catmullRom")))
    wrap = _token(prim, bc.GetWrapAttr(), ("nonperiodic", "periodic", "pinned"))

    counts_v = bc.GetCurveVertexCountsAttr().Get(time)
    points_v = bc.GetPointsAttr().Get(time)
    counts = np.asarray(counts_v if counts_v is not None else [], dtype=np.int64).reshape(-1)
    pts = np.asarray(points_v if points_v is not None else np.zeros((0, 3)), dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise _err(prim, "points", f"values of shape {pts.shape}; expected point3f[] (3D points)")
    if np.any(counts < 0):
        raise _err(prim, "curveVertexCounts", "negative vertex count")
    if int(counts.sum()) != len(pts):
        raise _err(prim, "curveVertexCounts",
                   f"sum {int(counts.sum())} does not match len(points) = {len(pts)}")
    if not np.all(np.isfinite(pts)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(pts), axis=1))[0])
        raise _err(prim, "points", f"contains NaN or Inf (first at index {bad})")
    _too_large(prim, "points", pts, "point")

    widths, winterp, wname, warnings = _read_widths(prim, time, default_width)

    normals = prim.GetAttribute("normals")
    nrm_pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar("normals")
    if (normals and normals.HasAuthoredValue()) or (nrm_pv and nrm_pv.HasAuthoredValue()):
        warnings.append(f"{path}: attribute 'normals': oriented ribbons are not supported by "
                        "Mitsuba; rendered as round tubes of the same width")

    # --- topology: per-curve segment counts and the 2 or 4 source indices of each segment ----
    ncurves = len(counts)
    offsets = np.cumsum(counts) - counts
    if ctype == "linear":
        periodic = wrap == "periodic"  # pinned only affects cubic bspline/catmullRom
        _check_counts(prim, counts, counts >= (3 if periodic else 2),
                      f"linear {'periodic' if periodic else 'nonperiodic'}: vertex count >= "
                      f"{3 if periodic else 2}")
        nseg = counts if periodic else counts - 1
        vstep = 1
    else:
        vstep = _VSTEP[basis]
        periodic = wrap == "periodic"
        if wrap == "pinned" and basis != "bezier":
            _check_counts(prim, counts, counts >= 2, f"cubic {basis} pinned: vertex count >= 2")
        elif periodic:
            _check_counts(prim, counts, (counts >= 3) & (counts % vstep == 0),
                          f"cubic {basis} periodic: vertex count >= 3 and a multiple of {vstep}")
        else:
            _check_counts(prim, counts, (counts >= 4) & ((counts - 4) % vstep == 0),
                          f"cubic {basis} nonperiodic: vertex count >= 4 and (count - 4) % {vstep} == 0")
        nseg = counts // vstep if periodic else (counts - 4) // vstep + 1
        if wrap == "pinned" and basis != "bezier":
            nseg = counts - 1
    seg_curve, seg_k = _segments(counts, nseg)
    nsegs_total = len(seg_curve)

    # --- widths -> radius data per interpolation ---------------------------------------------
    nvary = nseg if periodic else nseg + 1
    expected = {"constant": 1, "uniform": ncurves, "vertex": len(pts), "varying": int(nvary.sum())}
    if len(widths) != expected[winterp]:
        raise _err(prim, wname, f"{len(widths)} values for {winterp} interpolation, expected "
                   f"{expected[winterp]} ({ctype}{' ' + basis if ctype == 'cubic' else ''} {wrap})")
    radius = 0.5 * widths

    # --- transform ---------------------------------------------------------------------------
    if xform is None:
        xform = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(time))
    xform = np.asarray(xform, dtype=np.float64)
    pts = pts @ xform[:3, :3] + xform[3, :3]
    if not np.all(np.isfinite(pts)):
        raise _err(prim, None, "the local-to-world transform makes points NaN or Inf; expected a "
                   "finite transform")
    world = "in world space (after the local-to-world transform) "
    _too_large(prim, None, pts, "point", world)
    radius = radius * _linear_scale(prim, xform[:3, :3], warnings)
    _too_large(prim, None, 2 * radius, "width", world)
    thin = unresolved_widths_text(pts, 2 * radius)
    if thin:
        warnings.append(f"{prim.GetPath()}: attribute '{wname}': {thin}")

    # Linear radius along each segment (ra, rb) unless widths are cubic-interpolated (vertex).
    cubic_radius = ctype == "cubic" and winterp == "vertex"
    if not cubic_radius:
        if winterp == "constant":
            ra = rb = np.full(nsegs_total, radius[0])
        elif winterp == "uniform":
            ra = rb = radius[seg_curve]
        else:  # varying, or vertex on linear curves (identical there: one value per vertex)
            nv = nvary if winterp == "varying" else counts
            voff = (np.cumsum(nv) - nv)[seg_curve]
            nxt = seg_k + 1
            if periodic:
                nxt = nxt % nv[seg_curve]
            ra, rb = radius[voff + seg_k], radius[voff + nxt]

    # --- B-spline control points ---------------------------------------------------------------
    if ctype == "linear":
        local = seg_k[:, None] + np.arange(2)
        if periodic:
            local = local % counts[seg_curve][:, None]
        idx = offsets[seg_curve][:, None] + local
        a, b = pts[idx[:, 0]], pts[idx[:, 1]]
        # (2A - B, A, B, 2B - A): the B-spline that is exactly the line A -> B over t in [0, 1]
        cp = np.stack([2 * a - b, a, b, 2 * b - a], axis=1)
        return _per_segment(cp, _linear_radius(ra, rb), seg_curve, ncurves, warnings)

    src, src_r, cnt, off = pts, radius if cubic_radius else None, counts, offsets
    if wrap == "pinned" and basis != "bezier":
        src = _pin(pts, counts, offsets)
        if cubic_radius:
            src_r = _pin(radius, counts, offsets)
        cnt = counts + 2
        off = np.cumsum(cnt) - cnt

    if basis == "bspline" and winterp != "varying":
        # Share control points: a nonperiodic B-spline curve's segments are already
        # contiguous windows; periodic curves get their first 3 vertices appended.
        ext_cnt = cnt + 3 if periodic else cnt
        ext_off = np.cumsum(ext_cnt) - ext_cnt
        curve_of = np.repeat(np.arange(ncurves), ext_cnt)
        take = off[curve_of] + (np.arange(len(curve_of)) - ext_off[curve_of]) % cnt[curve_of]
        points = src[take]
        if cubic_radius:
            radii = src_r[take]
        elif winterp == "constant":
            radii = np.full(len(take), radius[0])
        else:  # uniform: one value per curve
            radii = radius[curve_of]
        start = ext_off[seg_curve] + seg_k
        if cubic_radius:
            _warn_negative_radius(prim, wname, radii[start[:, None] + np.arange(4)], warnings)
        return CurveGeometry(points, radii, start, seg_curve, ncurves, warnings)

    local = seg_k[:, None] * vstep + np.arange(4)
    if periodic:
        local = local % cnt[seg_curve][:, None]
    idx = off[seg_curve][:, None] + local
    conv = TO_BSPLINE[basis]
    cp = np.einsum("ij,sjk->sik", conv, src[idx])
    if cubic_radius:
        r4 = src_r[idx] @ conv.T
        _warn_negative_radius(prim, wname, r4, warnings)
    else:
        r4 = _linear_radius(ra, rb)
    return _per_segment(cp, r4, seg_curve, ncurves, warnings)


def _linear_radius(ra: np.ndarray, rb: np.ndarray) -> np.ndarray:
    # B-splines reproduce linear functions: controls a + b (i - 1) give a + b t exactly.
    return np.stack([2 * ra - rb, ra, rb, 2 * rb - ra], axis=1)


def _per_segment(cp: np.ndarray, r4: np.ndarray, seg_curve: np.ndarray, ncurves: int,
                 warnings: list[str]) -> CurveGeometry:
    s = len(cp)
    return CurveGeometry(cp.reshape(4 * s, 3), r4.reshape(4 * s),
                         4 * np.arange(s, dtype=np.int64), seg_curve, ncurves, warnings)


def negative_vertex_widths(widths: np.ndarray, counts: np.ndarray, basis: str, wrap: str
                           ) -> tuple[int, float]:
    """(segments whose interpolated radius goes below zero, the lowest radius) for vertex
    widths of valid cubic curves: the test :func:`curves_from_prim` warns with, on the widths
    alone (``usdfiber check`` runs it without converting the points)."""
    radius = 0.5 * np.asarray(widths, dtype=np.float64).reshape(-1)
    counts = np.asarray(counts, dtype=np.int64).reshape(-1)
    offsets = np.cumsum(counts) - counts
    vstep, periodic = _VSTEP[basis], wrap == "periodic"
    cnt, off = counts, offsets
    if wrap == "pinned" and basis != "bezier":
        radius = _pin(radius, counts, offsets)
        cnt = counts + 2
        off = np.cumsum(cnt) - cnt
        nseg = counts - 1
    else:
        nseg = counts // vstep if periodic else (counts - 4) // vstep + 1
    seg_curve, seg_k = _segments(counts, nseg)
    local = seg_k[:, None] * vstep + np.arange(4)
    if periodic:
        local = local % cnt[seg_curve][:, None]
    r4 = radius[off[seg_curve][:, None] + local] @ TO_BSPLINE[basis].T
    rmin = _min_radius(r4)
    neg = rmin < _negative_limit(r4)
    return int(neg.sum()), float(rmin.min()) if len(rmin) else 0.0


def _negative_limit(r4: np.ndarray) -> float:
    # A radius below zero by rounding only (a bezier taper to 0 evaluates to -1e-20) draws
    # the same as zero: what counts is below -1e-9 of the prim's largest radius.
    return -1e-9 * float(np.abs(r4).max()) if len(r4) else 0.0


def _warn_negative_radius(prim: Usd.Prim, wname: str, r4: np.ndarray, warnings: list[str]) -> None:
    """Warn where the cubic radius r(t), t in [0, 1], evaluates below zero."""
    if len(r4) == 0 or np.all(r4 >= 0):  # convex hull: non-negative controls, non-negative r
        return
    rmin = _min_radius(r4)
    neg = rmin < _negative_limit(r4)
    if np.any(neg):
        warnings.append(
            f"{prim.GetPath()}: attribute '{wname}': the interpolated width is negative on "
            f"{int(neg.sum())} segment(s) (worst radius {rmin.min():.6g}); Mitsuba renders no "
            "surface where the radius is < 0")


def _min_radius(r4: np.ndarray) -> np.ndarray:
    """The minimum over t in [0, 1] of each B-spline segment's radius (controls ``r4``)."""
    if len(r4) == 0:
        return np.zeros(0)
    out = r4.min(axis=1).copy()  # convex hull: non-negative controls, non-negative r
    some = out < 0
    if not some.any():
        return out
    r4 = r4[some]
    c = r4 @ POWER_BASIS["bspline"].T  # power coefficients a t^3 + b t^2 + c t + d
    a, b, cc, d = c.T
    cand = [np.zeros(len(c)), np.ones(len(c))]
    disc = b * b - 3 * a * cc  # roots of 3a t^2 + 2b t + c
    sq = np.sqrt(np.maximum(disc, 0))
    with np.errstate(divide="ignore", invalid="ignore"):
        for sgn in (1, -1):
            t = np.where(np.abs(a) > 1e-300, (-b + sgn * sq) / (3 * a), -cc / (2 * b))
            cand.append(np.where(np.isfinite(t) & (disc >= 0), np.clip(t, 0, 1), 0.0))
    out[some] = np.min([((a * t + b) * t + cc) * t + d for t in cand], axis=0)
    return out


# ---------------------------------------------------------------------------------------------
# Utilities on CurveGeometry
# ---------------------------------------------------------------------------------------------


def concatenate(parts: Sequence[CurveGeometry]) -> CurveGeometry:
    """Join several geometries into one: indices are offset, ``segment_curve`` becomes global
    (curves numbered across parts in order) and ``segment_part`` records the part index."""
    if not parts:
        return CurveGeometry(np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64),
                             np.zeros(0, np.int64), 0, [])
    pt_off = np.cumsum([0] + [len(p.points) for p in parts])
    cv_off = np.cumsum([0] + [p.curve_count for p in parts])
    return CurveGeometry(
        np.concatenate([p.points for p in parts]),
        np.concatenate([p.radii for p in parts]),
        np.concatenate([p.segment_start + pt_off[i] for i, p in enumerate(parts)]),
        np.concatenate([p.segment_curve + cv_off[i] for i, p in enumerate(parts)]),
        int(cv_off[-1]),
        [w for p in parts for w in p.warnings],
        np.concatenate([np.full(p.segment_count, i, np.int64) for i, p in enumerate(parts)]),
    )


def _bspline_weights(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    t = np.asarray(t, np.float64)[..., None]
    pw = np.concatenate([t**3, t**2, t, np.ones_like(t)], axis=-1)
    dpw = np.concatenate([3 * t**2, 2 * t, np.ones_like(t), np.zeros_like(t)], axis=-1)
    return pw @ POWER_BASIS["bspline"], dpw @ POWER_BASIS["bspline"]


def evaluate(geom: CurveGeometry, segment: np.ndarray, t: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Evaluate segments at parameters t in [0, 1] (broadcast together).

    Returns (positions (..., 3), radii (...), derivatives d position / dt (..., 3)).
    """
    segment, t = np.broadcast_arrays(np.asarray(segment, np.int64), np.asarray(t, np.float64))
    w, dw = _bspline_weights(t)
    idx = geom.segment_start[segment][..., None] + np.arange(4)
    p = geom.points[idx]
    return (np.einsum("...j,...jk->...k", w, p), np.einsum("...j,...j->...", w, geom.radii[idx]),
            np.einsum("...j,...jk->...k", dw, p))


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1)


def _reflector(v: np.ndarray) -> np.ndarray:
    """Householder matrices I - 2 v v^T / (v.v); identity where v is ~0 (no reflection needed)."""
    c = np.einsum("si,si->s", v, v)
    ok = c > 1e-24
    h = np.broadcast_to(np.eye(3), (len(v), 3, 3)).copy()
    h[ok] -= 2 * np.einsum("si,sj->sij", v[ok], v[ok]) / c[ok, None, None]
    return h


#: Segments whose reference normals are formed together: the scan holds about 600 bytes per
#: segment (3x3 products, reflectors, temporaries), so a chunk peaks near 150 MB whatever the
#: number of segments (whole, the 9M segments of a long yarn expanded at full detail took 5 GB).
NORMALS_CHUNK = 1 << 18


def reference_normals(geom: CurveGeometry) -> np.ndarray:
    """(S, 3) unit normals, perpendicular to each segment's tangent at its midpoint.

    A rotation-minimizing frame (double reflection, Wang et al. 2008) over the segment midpoints
    of each curve, starting from world +z projected onto the first segment's normal plane (+x if
    the tangent is within ~25 degrees of z). The per-step rotations are independent of the frame,
    so their products are formed with a segmented log-depth scan: vectorized even for a single
    very long curve. Curves are runs of equal (segment_part, segment_curve); they are formed in
    chunks of whole curves of about :data:`NORMALS_CHUNK` segments (the same values: each
    curve's frame depends on its own segments only).
    """
    s = geom.segment_count
    if s == 0:
        return np.zeros((0, 3))
    new = np.ones(s, bool)
    new[1:] = (geom.segment_curve[1:] != geom.segment_curve[:-1]) | (
        geom.segment_part[1:] != geom.segment_part[:-1])
    starts = np.flatnonzero(new)
    out = np.empty((s, 3))
    lo = 0
    while lo < s:
        k = np.searchsorted(starts, lo + NORMALS_CHUNK)   # the first curve start at or past the chunk's end
        hi = int(starts[k]) if k < len(starts) else s
        out[lo:hi] = _reference_normals(geom, lo, hi, new[lo:hi])
        lo = hi
    return out


def _reference_normals(geom: CurveGeometry, lo: int, hi: int, new: np.ndarray) -> np.ndarray:
    """:func:`reference_normals` of segments ``lo:hi`` (whole curves; ``new`` marks their starts)."""
    s = hi - lo
    idx = geom.segment_start[lo:hi, None] + np.arange(4)
    p = geom.points[idx]
    x = np.einsum("j,sjk->sk", _MID_W, p)
    d = np.einsum("j,sjk->sk", _MID_DW, p)
    # A zero derivative (degenerate segment) falls back on the control polygon's chord.
    tiny = np.linalg.norm(d, axis=1) <= 1e-12 * (1 + np.abs(x).max(axis=1))
    d[tiny] = p[tiny, 3] - p[tiny, 0]
    d[np.linalg.norm(d, axis=1) == 0] = (1.0, 0.0, 0.0)
    tan = _unit(d)
    del p, d

    first = np.maximum.accumulate(np.where(new, np.arange(s), 0))

    # Step i-1 -> i as a rotation (product of two reflections), identity at curve starts.
    steps = np.broadcast_to(np.eye(3), (s, 3, 3)).copy()
    cont = np.flatnonzero(~new)
    if len(cont):
        h1 = _reflector(x[cont] - x[cont - 1])
        t_l = np.einsum("sij,sj->si", h1, tan[cont - 1])
        h2 = _reflector(tan[cont] - t_l)
        steps[cont] = h2 @ h1
    # Segmented inclusive scan: acc[i] = steps[i] @ steps[i-1] @ ... @ steps[first[i]].
    acc, span, pos = steps, 1, np.arange(s)
    while True:
        m = (pos[span:] - span >= first[span:])[:, None, None]
        if not m.any():
            break
        # whole-slice products (cheaper than gathers); the right side is formed before the write
        acc[span:] = np.where(m, acc[span:] @ acc[:-span], acc[span:])
        span *= 2

    t0 = tan[first]
    guide = np.where(np.abs(t0[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    n0 = _unit(guide - np.einsum("si,si->s", guide, t0)[:, None] * t0)
    n = np.einsum("sij,sj->si", acc, n0)
    # Remove the rounding drift of the long products: exact perpendicularity and unit length.
    return _unit(n - np.einsum("si,si->s", n, tan)[:, None] * tan)
