"""Traced fiber scenes shared by the estimator tests (built once per process)."""
from __future__ import annotations

from typing import Any

from usdfiber.bake import profiles
from usdfiber.bake.tracer import prepare

_SCENES: dict[tuple[str, float | None], Any] = {}


def star_profile() -> profiles.Profile:
    """Three deep lobes: much of the light leaving a concave side meets the fiber again."""
    pts, nrm = profiles.fourier_loop(512, cos=(0.0, 0.0, 0.3), radius=5.0)
    return profiles.Profile("star", loops=(pts,), normals=(nrm,))


def scene(name: str, diameter_um: float | None = None) -> Any:
    """The traced scene of "circle" (radius 5 um), "star", or a built-in profile ("silk",
    "cotton"; at ``diameter_um``, else the built-in size)."""
    key = (name, diameter_um)
    if key not in _SCENES:
        if name == "circle":
            prof = profiles.circle(512, radius=5.0)
        elif name == "star":
            prof = star_profile()
        else:
            kw = {} if diameter_um is None else {"diameter_um": diameter_um}
            prof = profiles.builtin_profiles_um(name, 1, **kw)[0]
        _SCENES[key] = prepare(prof)
    return _SCENES[key]
