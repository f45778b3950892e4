"""Checks on user cross sections (FiberProfileAPI) and baked table assets (fiber:table).

Profile codes (E = error, W = warning), on non-abstract prims with FiberProfileAPI:

- ``ProfileMissingPoints`` (E): no points or no loop counts authored.
- ``ProfileCountsMismatch`` (E): loopVertexCounts do not sum to the number of points.
- ``ProfileTooFewPoints`` (E): a loop has fewer than 3 (distinct) points.
- ``ProfilePointsNotFinite`` (E): NaN or Inf in the points.
- ``ProfileZeroArea`` (E): a loop (or the whole profile) has no area.
- ``ProfileSelfIntersecting`` (E): a loop crosses itself.
- ``ProfileLoopsIntersect`` (E): two loops cross each other.
- ``ProfileHoleOutside`` (E): a hole is not inside the outer boundary, or lies inside
  another hole.
- ``ProfileOuterNotFirst`` (W): the first loop is not the outer boundary (the schema says
  it is; the baker takes the loop of largest area instead).
- ``ProfileInvalid`` (E): any other defect found by the profile builder.

A repeated closing point (last == first) is tolerated: loops are closed implicitly and the
builder drops the duplicate. The geometry tests are those of
:func:`usdfiber.bake.profiles.profile_from_polygons`, the function the baker uses, so the
check and the bake cannot disagree.

Table codes, on non-abstract prims with FiberAPI and an authored fiber:table:

- ``TableMissing`` (E): the asset path does not resolve to a file.
- ``TableUnreadable`` (E): the file is not a valid usdfiber table (corrupt, truncated,
  wrong format or version, an array that fails its checksum); the reason comes from
  :func:`usdfiber.table_format.read_header` with ``verify=True``.
- ``TableStale`` (W): the table was baked for other traced-geometry parameters than the
  prim's (header geometry_key != ``FiberParams.geometry_key()``); it will be re-baked.
"""
from __future__ import annotations

import os
from typing import Any, Sequence

import numpy as np
from pxr import Sdf, Usd

from usdfiber.spec.attributes import Fiber, Profile
from usdfiber.validation.problems import Problem, Severity, prim_check

PROFILE_API = "FiberProfileAPI"
FIBER_API = "FiberAPI"
POINTS = Profile.POINTS
COUNTS = Profile.LOOP_VERTEX_COUNTS
TABLE = Fiber.TABLE

# ProfileError messages of usdfiber.bake.profiles -> (code, attribute); first match wins.
# ProfileError carries no machine-readable kind, so its wording is matched (tests pin it).
_PROFILE_ERROR_CODES: tuple[tuple[str, str, str], ...] = (
    ("self-intersection", "ProfileSelfIntersecting", POINTS),
    ("intersects loop", "ProfileLoopsIntersect", POINTS),
    ("hole is not inside", "ProfileHoleOutside", POINTS),
    ("inside hole loop", "ProfileHoleOutside", POINTS),
    ("area", "ProfileZeroArea", POINTS),
    ("zero-size", "ProfileZeroArea", POINTS),
    ("at least 3", "ProfileTooFewPoints", COUNTS),
    ("non-finite", "ProfilePointsNotFinite", POINTS),
)


def _layer_of(obj: Usd.Attribute | Usd.Prim) -> str | None:
    """Identifier of the layer with the strongest opinion."""
    try:
        stack = obj.GetPropertyStack() if isinstance(obj, Usd.Attribute) else obj.GetPrimStack()
    except Exception:  # noqa: BLE001 - a missing layer must not hide the problem itself
        return None
    return stack[0].layer.identifier if stack else None


def _problem(prim: Usd.Prim, code: str, severity: Severity, attr_name: str | None,
             message: str) -> Problem:
    attr = prim.GetAttribute(attr_name) if attr_name else None
    return Problem(code, severity, str(prim.GetPath()), attr_name, message,
                   layer=_layer_of(attr if attr else prim))


# --------------------------------------------------------------------------------------
# Profiles
# --------------------------------------------------------------------------------------


def classify_profile_error(message: str) -> tuple[str, str]:
    """(code, attribute) of a ProfileError message; ``ProfileInvalid`` when unknown."""
    low = message.lower()
    for needle, code, attr in _PROFILE_ERROR_CODES:
        if needle in low:
            return code, attr
    return "ProfileInvalid", POINTS


def split_loops(points: np.ndarray, counts: np.ndarray) -> list[np.ndarray]:
    """The loops of a profile: ``points`` (N, 2) cut after each of ``counts``."""
    ends = np.cumsum(counts)
    return [points[e - c:e] for c, e in zip(counts, ends)]


def check_profile_prim(prim: Usd.Prim) -> list[Problem]:
    """Loop checks on one FiberProfileAPI prim."""
    if prim.IsAbstract() or PROFILE_API not in prim.GetAppliedSchemas():
        return []
    err = Severity.ERROR
    pts_value = prim.GetAttribute(POINTS).Get() if prim.GetAttribute(POINTS) else None
    cnt_value = prim.GetAttribute(COUNTS).Get() if prim.GetAttribute(COUNTS) else None
    if not pts_value or not cnt_value:
        missing = POINTS if not pts_value else COUNTS
        return [_problem(prim, "ProfileMissingPoints", err, missing,
                         f"{missing} is empty or not authored; expected the loops of the cross "
                         f"section (points in um, at least 3 per loop)")]
    points = np.asarray(pts_value, dtype=np.float64)
    counts = np.asarray(cnt_value, dtype=np.int64).reshape(-1)
    if points.ndim != 2 or points.shape[1] != 2:
        # Authored with another type (float3[]: the fiberSchema check reports WrongValueType);
        # the loops cannot be read, so there is nothing more to say about them.
        return []

    problems: list[Problem] = []
    if int(counts.sum()) != len(points) or (counts < 0).any():
        problems.append(_problem(
            prim, "ProfileCountsMismatch", err, COUNTS,
            f"loop vertex counts {counts.tolist()} sum to {int(counts.sum())} but there are "
            f"{len(points)} points; expected the counts to sum to the point count"))
    few = np.flatnonzero(counts < 3)
    if few.size:
        problems.append(_problem(
            prim, "ProfileTooFewPoints", err, COUNTS,
            f"loop {int(few[0])} has {int(counts[few[0]])} points"
            + (f" ({few.size} loops in all)" if few.size > 1 else "")
            + "; every loop needs at least 3 points"))
    bad = np.flatnonzero(~np.isfinite(points).all(axis=1))
    if bad.size:
        problems.append(_problem(
            prim, "ProfilePointsNotFinite", err, POINTS,
            f"{bad.size} points contain NaN or Inf (first: point {int(bad[0])}); expected "
            f"finite coordinates in um"))
    if problems:
        return problems  # the loops cannot be cut or measured reliably

    from usdfiber.bake.profiles import ProfileError, profile_from_polygons

    loops = split_loops(points, counts)
    smooth_attr = prim.GetAttribute(Profile.SMOOTH)
    smooth = bool(smooth_attr.Get()) if smooth_attr else False
    try:
        profile_from_polygons(loops, name="cross section", smooth=smooth)
    except ProfileError as exc:
        code, attr = classify_profile_error(str(exc))
        return [_problem(prim, code, err, attr,
                         f"{exc}; expected closed, simple loops (the first the outer boundary, "
                         f"the others holes inside it, none crossing)")]
    # The builder takes the largest loop as the outer boundary; the schema says loop 0 is.
    areas = [abs(_shoelace(loop)) for loop in loops]
    outer = int(np.argmax(areas))
    if outer != 0:
        problems.append(_problem(
            prim, "ProfileOuterNotFirst", Severity.WARNING, POINTS,
            f"loop {outer} encloses the others but loop 0 comes first; expected the outer "
            f"boundary first (loop {outer} is used as the outer boundary)"))
    return problems


def _shoelace(loop: np.ndarray) -> float:
    x, y = loop[:, 0], loop[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


# --------------------------------------------------------------------------------------
# Tables
# --------------------------------------------------------------------------------------

# Headers by (path, mtime_ns, size): many prims share a table; a rewritten file re-reads.
_HEADER_CACHE: dict[tuple[str, int, int, int], dict[str, Any] | Exception] = {}
_HEADER_CACHE_MAX = 256


def read_table_header(path: str) -> dict[str, Any]:
    """``table_format.read_header(path, verify=True)`` (every array's checksum checked), cached
    by file identity; raises TableError."""
    from usdfiber.table_format import TableError, read_header

    try:
        st = os.stat(path)
    except OSError:
        return read_header(path)  # raises TableError("missing") with the usual wording
    key = (path, st.st_ino, st.st_mtime_ns, st.st_size)  # writes replace the file (new inode)
    hit = _HEADER_CACHE.get(key)
    if hit is None:
        try:
            # Every checksum too: a table whose arrays are damaged cannot be rendered (the
            # renderer verifies them), so check must say so; read once per file version.
            hit = read_header(path, verify=True)
        except TableError as exc:
            hit = exc
        if len(_HEADER_CACHE) >= _HEADER_CACHE_MAX:
            _HEADER_CACHE.clear()
        _HEADER_CACHE[key] = hit
    if isinstance(hit, Exception):
        raise hit
    return hit


def _differing_inputs(baked: Any, current: dict[str, Any]) -> list[str]:
    if not isinstance(baked, dict):
        return []
    keys = sorted((set(baked) | set(current)) - {"units"})
    return [k for k in keys if baked.get(k) != current.get(k)]


def check_table_prim(prim: Usd.Prim) -> list[Problem]:
    """fiber:table checks on one FiberAPI prim (nothing when no table is authored)."""
    if prim.IsAbstract() or FIBER_API not in prim.GetAppliedSchemas():
        return []
    attr = prim.GetAttribute(TABLE)
    value = attr.Get() if attr else None
    if not isinstance(value, Sdf.AssetPath) or not value.path:
        return []  # empty: looked up in the cache by parameters
    path = str(prim.GetPath())
    resolved = value.resolvedPath
    if not resolved or not os.path.isfile(resolved):
        return [Problem("TableMissing", Severity.ERROR, path, TABLE,
                        f"fiber:table @{value.path}@ does not resolve to a file; expected an "
                        f"existing table written by `usdfiber bake` (or clear the attribute to "
                        f"use the cache)", layer=_layer_of(attr))]

    from usdfiber.table_format import TableError

    try:
        header = read_table_header(resolved)
    except TableError as exc:
        return [Problem("TableUnreadable", Severity.ERROR, path, TABLE,
                        f"fiber:table {resolved} cannot be used: {exc.reason}; expected a "
                        f"table written by `usdfiber bake` (`usdfiber bake` on this stage bakes "
                        f"the prim's tables into the table cache; then clear fiber:table or "
                        f"point it at a good table)", layer=_layer_of(attr))]

    from usdfiber.spec.fiber import FiberParams, FiberParamsError

    try:
        params = FiberParams.from_prim(prim, Usd.TimeCode.EarliestTime())
    except FiberParamsError:
        return []  # the value checks report why the parameters cannot be resolved
    key = params.geometry_key()
    baked_key = header.get("geometry_key")
    if baked_key == key:
        return []
    differ = _differing_inputs(header.get("inputs"), params.geometry_inputs())
    detail = f" (differs in: {', '.join(differ)})" if differ else ""
    baked = (f"geometry_key {baked_key[:12]}..." if isinstance(baked_key, str)
             else "no geometry_key")
    return [Problem("TableStale", Severity.WARNING, path, TABLE,
                    f"fiber:table {resolved} was baked for other fiber parameters{detail}: "
                    f"it records {baked} but this prim's is {key[:12]}...; expected matching "
                    f"keys, so the table will be re-baked for this prim",
                    layer=_layer_of(attr))]


@prim_check(
    "fiberProfile",
    "User cross sections (FiberProfileAPI): loop counts against points, at least 3 points "
    "per loop, finite points, no zero-area or self-intersecting loops, holes inside the "
    "outer boundary and not crossing it, outer boundary first.",
)
def _check_fiber_profile(prim: Usd.Prim) -> Sequence[Problem]:
    return check_profile_prim(prim)


@prim_check(
    "fiberTable",
    "Baked table assets (fiber:table): the path resolves, the file is a readable usdfiber "
    "table, and it was baked for the prim's traced-geometry parameters.",
)
def _check_fiber_table(prim: Usd.Prim) -> Sequence[Problem]:
    return check_table_prim(prim)
