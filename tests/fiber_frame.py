"""Surface interactions on a fiber for the BSDF tests: Mitsuba's curve shading frame (s = +x,
t = +y, the fiber tangent, n = +z), one interaction per lane."""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from usdfiber.backend import mitsuba

mi = mitsuba()
import drjit as dr  # noqa: E402  (after the variant is set)


def unit(v: Sequence[float]) -> list[float]:
    """``v`` normalized, as Python floats (for ``mi.Vector3f(*...)``)."""
    v = np.asarray(v, float)
    return [float(x) for x in v / np.linalg.norm(v)]


def fiber_interaction(n: int, wi: Sequence[float], prim: Any = 0) -> Any:
    """``n`` interactions seen from local direction ``wi`` on curve segment(s) ``prim``, in the
    frame of Mitsuba's curves (the shading frame's t is the fiber tangent, here +y)."""
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = mi.Vector3f(*wi)
    si.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
    si.prim_index = prim
    return si
