"""The yarn centre line: arc length, smooth tangents and rotation-minimizing frames.

A yarn centre polyline C(s) over its arc length s in [0, L], with the cross-section frame
(n(s), b(s) = t(s) x n(s)) of eq. Y1 of :mod:`usdfiber.geometry.yarn`: a rotation-minimizing
frame by double reflection (Wang et al. 2008, :func:`usdfiber.geometry.curves.reference_normals`)
on a sampling grid, right-handed and without flips.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from usdfiber.geometry.curves import CurveGeometry, reference_normals
from usdfiber.spec.yarn import YarnError

__all__ = ["CentreFrames", "CentreLine", "centre_frames"]


@dataclass
class CentreFrames:
    """The yarn centre line sampled at arc lengths ``s``: positions and right-handed
    rotation-minimizing frames (normal, binormal = tangent x normal, tangent)."""

    s: np.ndarray          # (M,)
    position: np.ndarray   # (M, 3)
    tangent: np.ndarray    # (M, 3)
    normal: np.ndarray     # (M, 3)
    binormal: np.ndarray   # (M, 3)
    scale: np.ndarray      # (M,) radius_scale


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


class CentreLine:
    """Arc-length parameterized polyline with smooth tangents and an RMF on a sample grid."""

    def __init__(self, centre: Any, radius_scale: Any) -> None:
        c = np.asarray(centre, dtype=np.float64)
        if c.ndim != 2 or c.shape[1] != 3 or len(c) < 2:
            raise YarnError(None, None, None,
                            f"centre must be an (N >= 2, 3) array of points, got shape {c.shape}")
        if not np.all(np.isfinite(c)):
            raise YarnError(None, None, None, "centre contains NaN or Inf")
        rs = np.asarray(radius_scale, dtype=np.float64)
        if rs.ndim == 0:
            rs = np.full(len(c), float(rs))
        elif rs.shape != (len(c),):
            raise YarnError(None, None, None, f"radius_scale must be a scalar or one value per "
                            f"centre point ({len(c)}), got shape {rs.shape}")
        if not np.all(np.isfinite(rs)) or np.any(rs <= 0):
            raise YarnError(None, None, None, "radius_scale must be finite and > 0")
        seg = np.linalg.norm(np.diff(c, axis=0), axis=1)
        keep = np.concatenate([[True], seg > 1e-12 * (1.0 + np.abs(c).max())])
        c, rs = c[keep], rs[keep]
        if len(c) < 2:
            raise YarnError(None, None, None, "centre line has zero length")
        d = np.diff(c, axis=0)
        seg = np.linalg.norm(d, axis=1)
        u = d / seg[:, None]
        vt = np.empty_like(c)
        vt[0], vt[-1] = u[0], u[-1]
        mid = u[:-1] + u[1:]
        ok = np.linalg.norm(mid, axis=1) > 1e-6
        vt[1:-1] = np.where(ok[:, None], mid, u[1:])
        self.points = c
        self.cum = np.concatenate([[0.0], np.cumsum(seg)])
        self.length = float(self.cum[-1])
        self.vertex_tangent = _unit(vt)
        self.scale = rs
        self.median_segment = float(np.median(seg))
        self.grid: CentreFrames | None = None

    def _interp(self, s: np.ndarray, values: np.ndarray) -> np.ndarray:
        return np.stack([np.interp(s, self.cum, values[:, k]) for k in range(values.shape[1])], -1)

    def positions(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(position, unit tangent, scale) at arc lengths s (1-D), extrapolated beyond the ends
        along the end tangents."""
        sc = np.clip(s, 0.0, self.length)
        pos = self._interp(sc, self.points)
        tan = _unit(self._interp(sc, self.vertex_tangent))
        over = s - sc
        if np.any(over != 0):
            pos = pos + over[:, None] * tan
        return pos, tan, np.interp(sc, self.cum, self.scale)

    def build_grid(self, s: np.ndarray) -> CentreFrames:
        pos, tan, scale = self.positions(s)
        # One linear B-spline "segment" per sample whose midpoint is the sample and whose
        # derivative is the tangent: reference_normals then runs the double-reflection RMF
        # (Wang et al. 2008) over exactly these points and tangents, vectorized.
        m = len(s)
        cp = pos[:, None, :] + np.array([-1.5, -0.5, 0.5, 1.5])[None, :, None] * tan[:, None, :]
        geom = CurveGeometry(cp.reshape(-1, 3), np.zeros(4 * m), 4 * np.arange(m, dtype=np.int64),
                             np.zeros(m, np.int64), 1)
        nrm = reference_normals(geom)
        binrm = np.cross(tan, nrm)
        self.grid = CentreFrames(s, pos, tan, nrm, binrm, scale)
        return self.grid

    def frames(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(position, normal, binormal, scale) at arbitrary arc lengths (1-D), the normal
        interpolated from the RMF grid and re-orthogonalized against the tangent."""
        g = self.grid
        assert g is not None
        pos, tan, scale = self.positions(s)
        sc = np.clip(s, g.s[0], g.s[-1])
        n = np.stack([np.interp(sc, g.s, g.normal[:, k]) for k in range(3)], -1)
        n = _unit(n - np.einsum("ij,ij->i", n, tan)[:, None] * tan)
        return pos, n, np.cross(tan, n), scale


def centre_frames(centre: Any, s: Any = None, *, spacing: float | None = None,
                  radius_scale: Any = 1.0) -> CentreFrames:
    """Rotation-minimizing frames along a yarn centre polyline (double reflection, Wang et al.
    2008), at arc lengths ``s`` (increasing; default: a uniform grid of ``spacing``, or of the
    median segment length). These are the frames :func:`~usdfiber.geometry.yarn.expand_yarn` uses (eq. Y1)."""
    c = CentreLine(centre, radius_scale)
    if s is None:
        h = spacing if spacing is not None else c.median_segment
        m = max(2, int(math.ceil(c.length / h)) + 1)
        s = np.linspace(0.0, c.length, m)
    s = np.asarray(s, np.float64).reshape(-1)
    if len(s) < 1 or np.any(np.diff(s) <= 0):
        raise YarnError(None, None, None, "arc lengths s must be strictly increasing")
    return c.build_grid(s)
