"""Mitsuba shapes for uniform cubic B-spline curves (``bsplinecurve``), built from arrays.

The conversion of UsdGeomBasisCurves to B-spline segments, their evaluation and reference
frames are renderer-independent and live in :mod:`usdfiber.geometry.curves`; they are
imported here for the bridge's modules.
"""
from __future__ import annotations

import os
import tempfile
from typing import Any

import numpy as np

from usdfiber.geometry.curves import (POWER_BASIS, TO_BSPLINE, CurveError, CurveGeometry, concatenate,
                                      curves_from_prim, evaluate, reference_normals)

__all__ = [
    "CurveError",
    "CurveGeometry",
    "curves_from_prim",
    "concatenate",
    "evaluate",
    "reference_normals",
    "make_curve_shape",
    "POWER_BASIS",
    "TO_BSPLINE",
]

_SEED_CURVE = "0 0 0 1\n1 0 0 1\n2 0 0 1\n3 0 0 1\n"


def make_curve_shape(geom: CurveGeometry, bsdf: Any = None, shape_id: str = "curves") -> Any:
    """A Mitsuba ``bsplinecurve`` shape holding ``geom``, built from arrays.

    Mitsuba 3.9.1 loads curves only from a text file (slow to write at scale), so a 4-point
    seed curve is loaded and then ``control_points`` (flat x, y, z, r as float32),
    ``segment_indices`` and ``control_point_count`` are replaced through ``mi.traverse``.
    Not an official API; the tests check it against the text-file path. ``bsdf`` may be an
    ``mi.BSDF`` or a dict. Build the scene after this call (Embree reads the buffers then).
    """
    from usdfiber.backend import mitsuba

    mi = mitsuba()
    if geom.segment_count == 0:
        raise ValueError(f"shape {shape_id!r}: no curve segments to build")
    if len(geom.points) >= 2**32 - 8:
        raise ValueError(f"shape {shape_id!r}: {len(geom.points)} control points exceed uint32 indices")
    props: dict[str, Any] = {"type": "bsplinecurve", "id": shape_id}
    if bsdf is not None:
        props["bsdf"] = bsdf
    with tempfile.TemporaryDirectory(prefix="usdfiber_curve_") as tmp:
        seed = os.path.join(tmp, "seed.txt")
        with open(seed, "w") as f:
            f.write(_SEED_CURVE)
        props["filename"] = seed
        shape = mi.load_dict(props)
    # Mitsuba 3.9.1 recovers a hit's segment as floor(v * segment_count) from the float32 global
    # parameter v without clamping: a hit at the very end of the last segment rounds v to 1
    # and reads past the segment buffer (a crash; upstream mitsuba3 PR #1928). A last,
    # unreachable segment (radius 0 at the first control point) keeps that index in bounds. Such
    # hits (within about N 2^-24 of the shape's end) still get a NaN shading frame from
    # Mitsuba: the fiber BSDF treats them as absorbing (fiber_bsdf.py). A guard that continues
    # the last segment instead gave finite frames but made the demo render segfault (cause not
    # found).
    n = len(geom.points)
    cp = np.empty((n + 4, 4), np.float32)
    cp[:n, :3] = geom.points
    cp[:n, 3] = geom.radii
    cp[n:, :3] = geom.points[0]
    cp[n:, 3] = 0.0
    starts = np.append(geom.segment_start, n).astype(np.uint32)
    params = mi.traverse(shape)
    params["control_points"] = mi.Float(cp.reshape(-1))
    params["segment_indices"] = mi.UInt32(starts)
    params["control_point_count"] = int(n + 4)
    params.update()
    return shape
