"""Walk a USD stage for rendering: visible gprims with world transforms, instancing expanded.

- Native instancing: traversal includes instance proxies, yielded with their proxy paths.
- UsdGeomPointInstancer: the instancer's children are pruned from the normal traversal (as
  UsdImaging and UsdGeomBBoxCache do), so are prototype roots it targets elsewhere; each
  unmasked instance (``invisibleIds``, ``inactiveIds``) yields every gprim of its prototype.
  Nested instancers recurse; a cycle raises ValueError.
- Visibility: an ``invisible`` opinion prunes its subtree. Inside a prototype only the
  prototype root and its descendants count: prototypes are often kept under an invisible
  scope so that instancer-unaware tools skip them.
- Matrices are USD's row-vector convention: p_world = [p, 1] @ xform.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator, Sequence

import numpy as np
from pxr import Sdf, Usd, UsdGeom

from usdfiber.geometry.curves import too_large_text

__all__ = ["Placement", "walk"]


@dataclass
class Placement:
    """One renderable prim placed in the world."""

    prim: Usd.Prim  # the prim (an instance proxy, or a prim of a point-instancer prototype)
    xform: np.ndarray  # (4, 4) float64 local-to-world, row-vector convention
    path: str  # unique: the (proxy) path, or "<instancer path>[<i>]<prototype prim path>"
    instance_id: int  # 0, or the point-instancer instance index (a seed offset)


_TRAVERSAL = Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)
# Prototype subtrees may sit under an `over` (the pattern the PointInstancer docs recommend to
# hide them from default traversals): do not require defined ancestors there.
_PROTO_TRAVERSAL = Usd.TraverseInstanceProxies(
    Usd.PrimIsActive & Usd.PrimIsLoaded & ~Usd.PrimIsAbstract & Usd.PrimHasDefiningSpecifier)


def _invisible(prim: Usd.Prim, time: Usd.TimeCode) -> bool:
    """The prim's own visibility opinion (ancestors are handled by pruning the traversal)."""
    attr = UsdGeom.Imageable(prim).GetVisibilityAttr() if prim.IsA(UsdGeom.Imageable) else None
    return bool(attr) and attr.Get(time) == UsdGeom.Tokens.invisible


def _np(m) -> np.ndarray:
    return np.array(m, dtype=np.float64).reshape(4, 4)


class _Walker:
    def __init__(self, stage: Usd.Stage, time: Usd.TimeCode, purposes: Sequence[str],
                 types: Sequence[type]) -> None:
        self.stage, self.time = stage, time
        self.purposes = {str(p) for p in purposes}
        self.types = tuple(types)
        self.xf = UsdGeom.XformCache(time)
        self._proto_cache: dict[Sdf.Path, list[tuple[Usd.Prim, np.ndarray, bool]]] = {}

    def _wanted(self, prim: Usd.Prim) -> bool:
        return (any(prim.IsA(t) for t in self.types)
                and str(UsdGeom.Imageable(prim).ComputePurpose()) in self.purposes)

    def prototype_roots(self) -> set[Sdf.Path]:
        roots: set[Sdf.Path] = set()
        for prim in Usd.PrimRange.Stage(self.stage, Usd.TraverseInstanceProxies(Usd.PrimAllPrimsPredicate)):
            if prim.IsA(UsdGeom.PointInstancer):
                roots.update(UsdGeom.PointInstancer(prim).GetPrototypesRel().GetForwardedTargets())
        return roots

    def walk(self) -> Iterator[Placement]:
        skip = self.prototype_roots()
        it = iter(Usd.PrimRange.Stage(self.stage, _TRAVERSAL))
        for prim in it:
            if prim.GetPath() in skip or _invisible(prim, self.time):
                it.PruneChildren()
                continue
            if prim.IsA(UsdGeom.PointInstancer):
                it.PruneChildren()  # its children are prototypes, drawn only through it
                if str(UsdGeom.Imageable(prim).ComputePurpose()) in self.purposes:
                    world = _np(self.xf.GetLocalToWorldTransform(prim))
                    yield from self._expand(prim, world, str(prim.GetPath()), 0, ())
                continue
            if self._wanted(prim):
                yield Placement(prim, _np(self.xf.GetLocalToWorldTransform(prim)), str(prim.GetPath()), 0)

    def _prototype_contents(self, root: Usd.Prim) -> list[tuple[Usd.Prim, np.ndarray, bool]]:
        """(prim, transform relative to the root's parent frame excluding the root's own local
        transform, is-instancer) for the wanted gprims and nested instancers under ``root``."""
        key = root.GetPath()
        if key in self._proto_cache:
            return self._proto_cache[key]
        items: list[tuple[Usd.Prim, np.ndarray, bool]] = []
        it = iter(Usd.PrimRange(root, _PROTO_TRAVERSAL))
        for prim in it:
            if _invisible(prim, self.time):
                it.PruneChildren()
                continue
            is_pi = prim.IsA(UsdGeom.PointInstancer)
            if is_pi:
                it.PruneChildren()
            if is_pi or self._wanted(prim):
                # ComputeInstanceTransformsAtTime(IncludeProtoXform) already holds the root's
                # local transform; what lies between the root and the prim comes from here.
                rel = (np.eye(4) if prim == root
                       else _np(self.xf.ComputeRelativeTransform(prim, root)[0]))
                items.append((prim, rel, is_pi))
        self._proto_cache[key] = items
        return items

    def _expand(self, prim: Usd.Prim, world: np.ndarray, label: str, id_base: int,
                stack: tuple[Sdf.Path, ...]) -> Iterator[Placement]:
        if prim.GetPath() in stack:
            raise ValueError(f"{prim.GetPath()}: PointInstancer instances itself "
                             f"(through {' -> '.join(map(str, stack))})")
        stack = stack + (prim.GetPath(),)
        pi = UsdGeom.PointInstancer(prim)
        protos = [self.stage.GetPrimAtPath(p) for p in pi.GetPrototypesRel().GetForwardedTargets()]
        indices = pi.GetProtoIndicesAttr().Get(self.time)
        if indices is None or len(indices) == 0:
            return
        indices = np.asarray(indices, dtype=np.int64)
        bad = (indices < 0) | (indices >= len(protos))
        if bad.any():
            raise ValueError(f"{prim.GetPath()}: attribute 'protoIndices': index "
                             f"{indices[bad][0]} out of range for {len(protos)} prototypes")
        for k, p in enumerate(protos):
            if not p or not p.IsValid():
                raise ValueError(f"{prim.GetPath()}: relationship 'prototypes': target {k} is not a prim")
        # Keep the mask separate so instance i stays index i (ApplyMask would compact).
        mats = pi.ComputeInstanceTransformsAtTime(
            self.time, self.time, UsdGeom.PointInstancer.IncludeProtoXform,
            UsdGeom.PointInstancer.IgnoreMask)
        if len(mats) != len(indices):
            raise ValueError(f"{prim.GetPath()}: instance transforms could not be computed "
                             f"({len(mats)} for {len(indices)} protoIndices; check positions)")
        mask = pi.ComputeMaskAtTime(self.time)
        inst_world = np.array(mats, dtype=np.float64).reshape(-1, 4, 4) @ world
        contents = [self._prototype_contents(p) for p in protos]
        n = len(indices)
        for i in range(n):
            if len(mask) and not mask[i]:
                continue
            iid = id_base * n + i  # nested instancers: unique along one nesting path
            for proto_prim, rel, is_pi in contents[indices[i]]:
                xform = rel @ inst_world[i]
                path = f"{label}[{i}]{proto_prim.GetPath()}"
                if is_pi:
                    yield from self._expand(proto_prim, xform, path, iid, stack)
                else:
                    yield Placement(proto_prim, xform, path, iid)


def _checked(pl: Placement) -> Placement:
    # A NaN or infinite transform (xformOps, or an instancer's positions, orientations or
    # scales) makes NaN geometry that fails far from its cause (an SVD, a black image).
    if not np.all(np.isfinite(pl.xform)):
        raise ValueError(f"{pl.path}: its world transform is not finite (NaN or Inf in the xformOps of the "
                         "prim or an ancestor, or in a PointInstancer's positions, orientations or scales)")
    # A world position beyond the float32 bound (xformOps, or an instancer's positions) puts
    # all of the prim's geometry there: it would disappear from the image.
    huge = too_large_text(pl.xform[3:, :3], "its world position")
    if huge:
        raise ValueError(f"{pl.path}: {huge}")
    return pl


def walk(
    stage: Usd.Stage,
    time: Usd.TimeCode = Usd.TimeCode.Default(),
    purposes: Sequence[str] = ("default", "render"),
    types: Sequence[type] = (UsdGeom.Gprim,),
) -> Iterator[Placement]:
    """Yield a Placement for every visible prim of one of ``types`` whose computed purpose is
    in ``purposes``, in traversal order, with native instances (proxy paths) and point-instancer
    instances expanded. Point-instancer transforms compose as
    prim-relative-to-prototype-root @ instance (incl. the root's local xform) @ instancer world.
    """
    return (_checked(pl) for pl in _Walker(stage, time, purposes, types).walk())
