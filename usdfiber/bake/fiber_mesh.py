"""Triangle meshes of a straight fiber segment, for the photon tracer.

Fiber frame: the tangent is +z, the cross-section lies in the xy plane, the azimuth phi is
measured from +x towards +y and sin(theta) = w.z. Lengths are micrometres.

Two kinds of segment are built:

* **extruded** (no cuticle): every loop of the profile is extruded along z. The geometry is
  z-invariant, so the tracer intersects it with horizontal rays (at a random height inside the
  segment, so that a ray slipping through a crack is retried elsewhere) and converts distances
  to 3D: no wrapping at all, whatever theta is.
* **cuticle** (wool): the outer loop becomes a stack of overlapping, slightly tapered scales.
  The segment holds ``periods`` whole scale periods, ``z`` in ``[0, z_period)``; the tracer
  wraps photons that cross ``z = 0`` or ``z = z_period``, which is exact because the geometry
  repeats with that period.

Vertex normals are the profile's smooth normals (out of the material), so the interpolated
shading normal follows the smooth curve, not the facets. For a polygon inscribed in a circle
the interpolated normal at a hit is exactly the radial direction through the hit point.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["FiberMesh", "build_fiber_mesh", "hull_edges", "is_convex_loop", "profile_bounds"]


@dataclass(frozen=True)
class FiberMesh:
    """A fiber segment as plain arrays (float64, micrometres) plus what the tracer needs."""

    vertices: np.ndarray        # (V, 3)
    faces: np.ndarray           # (F, 3) uint32, counter-clockwise seen from outside the material
    normals: np.ndarray         # (V, 3) unit shading normals, out of the material
    face_normals: np.ndarray    # (F, 3) unit geometric normals, out of the material
    z_invariant: bool           # True: extruded, traced with horizontal rays
    z_period: float             # length of the periodic slab [0, z_period) (cuticle), or segment length
    bound_radius: float         # every vertex lies within this distance of the z axis
    #: (F,) bool: the face belongs to the outer surface (outer loop or cuticle scales), where
    #: light leaves the fiber; False for the walls of holes (lumen), which it crosses inside.
    outer_faces: np.ndarray | None = None
    #: The outer loop is convex and there are no scales: light leaving through the outer
    #: surface cannot meet the fiber again.
    outer_convex: bool = False
    #: (F,) bool: an outer face whose profile edge is an edge of the outer loop's convex hull
    #: (extruded fibers; all outer faces of a convex loop). The whole fiber lies on the inner
    #: side of that edge's line, so light leaving such a face outwards cannot meet it again.
    outer_hull: np.ndarray | None = None
    #: (F,) int: the edge of the outer loop (vertex i to i + 1) a face is extruded from, -1 for
    #: other faces and for cuticle segments.
    outer_edge: np.ndarray | None = None

    def to_mitsuba(self, mi: Any) -> Any:
        """Build the ``mi.Mesh`` (positions, faces, vertex normals) of this segment."""
        mesh = mi.Mesh("fiber", len(self.vertices), len(self.faces), has_vertex_normals=True)
        params = mi.traverse(mesh)
        params["vertex_positions"] = mi.Float(self.vertices.astype(np.float32).ravel())
        params["faces"] = mi.UInt32(self.faces.astype(np.uint32).ravel())
        params["vertex_normals"] = mi.Float(self.normals.astype(np.float32).ravel())
        params.update()
        return mesh


def _loops(profile: Any) -> tuple[list[np.ndarray], list[np.ndarray]]:
    loops = [np.asarray(lp, dtype=np.float64) for lp in profile.loops]
    normals = []
    for lp, nm in zip(loops, profile.normals):
        nm = np.asarray(nm, dtype=np.float64)
        nm = nm / np.linalg.norm(nm, axis=1, keepdims=True)
        if nm.shape != lp.shape:
            raise ValueError("profile normals must match its loops vertex for vertex")
        normals.append(nm)
    return loops, normals


def profile_bounds(profile: Any, phi: float) -> tuple[float, float]:
    """Shadow of the outer loop seen from 2D direction (cos phi, sin phi).

    Returns (lo, hi): the extent of the outer loop along u_perp = (-sin phi, cos phi).
    """
    outer = np.asarray(profile.loops[0], dtype=np.float64)
    s = -outer[:, 0] * np.sin(phi) + outer[:, 1] * np.cos(phi)
    return float(s.min()), float(s.max())


def _quads(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Quads between the edges of ring a and ring b, as triangles.

    A ring is (start, end): the vertex indices at the two ends of each edge. With the loop
    running so that the material is on its left and b above a (larger z), or b inside a in the
    plane of a step face that looks towards +z,
    (a_s, a_e, b_e) and (a_s, b_e, b_s) have geometric normals pointing out of the material.
    """
    (a_s, a_e), (b_s, b_e) = a, b
    return np.concatenate([np.stack([a_s, a_e, b_e], axis=1), np.stack([a_s, b_e, b_s], axis=1)])


def _facet_normals_2d(loop: np.ndarray) -> np.ndarray:
    e = np.roll(loop, -1, axis=0) - loop
    n = np.stack([e[:, 1], -e[:, 0]], axis=1)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def is_convex_loop(loop: np.ndarray) -> bool:
    """True when the closed polygon ``loop`` (counter-clockwise) turns left at every vertex."""
    lp = np.asarray(loop, dtype=np.float64)
    e = np.roll(lp, -1, axis=0) - lp
    f = np.roll(e, -1, axis=0)
    cross = e[:, 0] * f[:, 1] - e[:, 1] * f[:, 0]
    scale = float(np.max(np.abs(lp))) ** 2 if len(lp) else 1.0
    return bool(np.all(cross >= -1e-12 * scale))


def hull_edges(loop: np.ndarray) -> np.ndarray:
    """(n,) bool: edge ``i`` (vertex i to i + 1) of the closed counter-clockwise polygon
    ``loop`` is an edge of its convex hull: no vertex lies outside the edge's line."""
    lp = np.asarray(loop, dtype=np.float64)
    e = np.roll(lp, -1, axis=0) - lp
    scale = float(np.max(np.abs(lp))) if len(lp) else 1.0
    out = np.empty(len(lp), dtype=bool)
    for a in range(0, len(lp), 256):          # (256, n) blocks: bounded memory
        b = min(a + 256, len(lp))
        rel = lp[None, :, :] - lp[a:b, None, :]
        cross = e[a:b, None, 0] * rel[..., 1] - e[a:b, None, 1] * rel[..., 0]
        out[a:b] = np.all(cross >= -1e-9 * scale * np.linalg.norm(e[a:b], axis=1)[:, None], axis=1)
    return out


def build_fiber_mesh(
    profile: Any,
    cuticle: tuple[float, float, float] | None = None,
    *,
    length: float | None = None,
    periods: int | None = None,
) -> FiberMesh:
    """Mesh a straight fiber segment of ``profile`` along +z.

    ``cuticle=(tilt_deg, height_um, spacing_um)`` adds wool scales on the outer loop: each
    scale is a sleeve whose offset along the profile normals grows linearly from 0 to
    ``height`` over one ``spacing`` (free edge towards +z, the fiber tip), followed by a step
    back down whose face looks towards +z. The shading normal of a sleeve is the profile's
    smooth normal tilted by ``tilt_deg`` towards -z (the scale faces the root); the
    geometric taper is atan(height / spacing), and the two should agree (a shading normal
    that disagrees with the geometry by degrees traps light in total internal reflection).
    Holes stay straight (they are inside). ``periods`` scale periods are meshed (default:
    enough for about four diameters), so that steep photons wrap less often. Without a
    cuticle, ``length`` is the extruded length. Profiles with ``smooth=False`` get flat
    facet normals (unwelded vertices).
    """
    loops, loop_normals = _loops(profile)
    flat = not bool(getattr(profile, "smooth", True))
    verts: list[np.ndarray] = []
    norms: list[np.ndarray] = []
    faces: list[np.ndarray] = []
    outer_flags: list[np.ndarray] = []    # per block of faces: on the outer surface?
    hull_flags: list[np.ndarray] = []     # per block of faces: on an edge of the outline's hull?
    edge_ids: list[np.ndarray] = []       # per block of faces: outer-loop edge, or -1
    count = 0

    def add_faces(tri: np.ndarray, outer: bool, hull: np.ndarray | None = None,
                  edge: np.ndarray | None = None) -> None:
        faces.append(tri)
        outer_flags.append(np.full(len(tri), outer))
        hull_flags.append(np.zeros(len(tri), bool) if hull is None else np.asarray(hull, bool))
        edge_ids.append(np.full(len(tri), -1, np.int64) if edge is None else np.asarray(edge, np.int64))

    def add_ring(xy: np.ndarray, z: float, nrm3: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Add one ring of vertices at height z; returns (start, end) vertex index per edge."""
        nonlocal count
        n = len(xy)
        i = np.arange(n)
        if flat:
            # Unwelded: each edge owns its two end vertices, both with the facet normal.
            xy2 = np.stack([xy, np.roll(xy, -1, axis=0)], axis=1).reshape(-1, 2)
            nr2 = np.repeat(nrm3, 2, axis=0)
            start, end = count + 2 * i, count + 2 * i + 1
        else:
            xy2, nr2 = xy, nrm3
            start, end = count + i, count + (i + 1) % n
        verts.append(np.column_stack([xy2, np.full(len(xy2), z)]))
        norms.append(nr2)
        count += len(xy2)
        return start, end

    def shading(lp: np.ndarray, nm: np.ndarray) -> np.ndarray:
        return _facet_normals_2d(lp) if flat else nm

    radius = max(float(np.max(np.linalg.norm(lp, axis=1))) for lp in loops)

    if cuticle is None:
        seg = float(length) if length else max(2.0 * radius, 1.0)
        for j, (lp, nm) in enumerate(zip(loops, loop_normals)):
            sn = shading(lp, nm)
            n3 = np.column_stack([sn, np.zeros(len(sn))])
            a = add_ring(lp, -0.5 * seg, n3)
            b = add_ring(lp, 0.5 * seg, n3)
            # _quads gives two triangles per edge, in two blocks of one per edge.
            add_faces(_quads(a, b), j == 0, np.tile(hull_edges(lp), 2) if j == 0 else None,
                      np.tile(np.arange(len(lp)), 2) if j == 0 else None)
        z_invariant, z_period, bound = True, seg, radius
    else:
        tilt_deg, height, spacing = (float(c) for c in cuticle)
        if spacing <= 0.0 or height < 0.0:
            raise ValueError("cuticle spacing must be > 0 and height >= 0")
        taper = np.degrees(np.arctan2(height, spacing))
        if abs(taper - tilt_deg) > 1.0:
            warnings.warn(
                f"cuticle tilt {tilt_deg:.2f} deg disagrees with the scale taper atan(height/spacing)"
                f" = {taper:.2f} deg: shading and geometry differ, which can trap light in total"
                " internal reflection", stacklevel=2)
        if periods is None:
            periods = max(1, int(np.ceil(4.0 * 2.0 * radius / spacing)))
        zlen = periods * spacing
        outer, onrm = loops[0], loop_normals[0]
        ct, st = np.cos(np.radians(tilt_deg)), np.sin(np.radians(tilt_deg))
        sn = shading(outer, onrm)
        sleeve_n = np.column_stack([sn * ct, np.full(len(sn), -st)])
        step_n = np.tile([0.0, 0.0, 1.0], (len(sn), 1))

        def off(f: float) -> np.ndarray:
            # Offsetting along the smooth normals keeps every ring the same smooth shape.
            return outer + onrm * (height * f)

        # Steps sit half a period inside the slab so that none lies on a wrap plane.
        lower = add_ring(off(0.5), 0.0, sleeve_n)
        for k in range(periods):
            zs = (k + 0.5) * spacing
            top = add_ring(off(1.0), zs, sleeve_n)          # free edge of scale k
            add_faces(_quads(lower, top), True)
            if height > 0.0:
                # Step face in the plane z = zs, looking towards +z: from the free edge
                # (offset height) in to the root of the next scale (offset 0).
                add_faces(_quads(add_ring(off(1.0), zs, step_n), add_ring(off(0.0), zs, step_n)), True)
            lower = add_ring(off(0.0), zs, sleeve_n)         # root of scale k+1
        add_faces(_quads(lower, add_ring(off(0.5), zlen, sleeve_n)), True)
        for lp, nm in zip(loops[1:], loop_normals[1:]):
            hn = shading(lp, nm)
            n3 = np.column_stack([hn, np.zeros(len(hn))])
            add_faces(_quads(add_ring(lp, 0.0, n3), add_ring(lp, zlen, n3)), False)
        bound = float(np.max(np.linalg.norm(off(1.0), axis=1)))
        z_invariant, z_period = False, zlen

    V = np.concatenate(verts)
    N = np.concatenate(norms)
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    F = np.concatenate(faces).astype(np.uint32)
    outer_faces = np.concatenate(outer_flags)
    outer_hull = np.concatenate(hull_flags)
    outer_edge = np.concatenate(edge_ids)
    p0, p1, p2 = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    fn = np.cross(p1 - p0, p2 - p0)
    area2 = np.linalg.norm(fn, axis=1)
    keep = area2 > 1e-12 * max(radius, 1.0) ** 2   # drop degenerate triangles
    F, fn, area2, outer_faces, outer_hull = F[keep], fn[keep], area2[keep], outer_faces[keep], outer_hull[keep]
    outer_edge = outer_edge[keep]
    fn /= area2[:, None]
    # The winding is chosen so that geometric normals leave the material; check it against the
    # smooth normals, which is what makes the tracer's inside/outside test trustworthy.
    agree = np.einsum("ij,ij->i", fn, N[F].mean(axis=1))
    if np.any(agree <= 0.0):
        raise ValueError(
            f"{int(np.sum(agree <= 0))} faces have geometric normals opposite to the profile "
            "normals: outer loop must be CCW, holes CW, normals out of the material"
        )
    return FiberMesh(
        vertices=V,
        faces=F,
        normals=N,
        face_normals=fn,
        z_invariant=z_invariant,
        z_period=z_period,
        bound_radius=bound * (1.0 + 1e-6) + 1e-6,
        outer_faces=outer_faces,
        outer_convex=cuticle is None and is_convex_loop(loops[0]),
        outer_hull=outer_hull,
        outer_edge=outer_edge,
    )
