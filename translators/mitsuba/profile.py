"""Where a translation spends its time: seconds and calls per step (:class:`TranslationProfile`).

:func:`~usdfiber.translators.mitsuba.scene.translate_stage` times its steps through the
profile of its options (``SceneOptions.profile``; a fresh one when none is given) and returns
it as ``Translation.profile``. Benchmarks read it, and may listen to each step's result
(progress of a long garment), instead of replacing the translator's functions. The steps,
each summed over its calls:

==================  ==========================================================================
``curves``          fiber and yarn prims read from USD and converted to B-splines
``yarn_lod``        the level of detail of a yarn prim's curves decided (fibers kept, far
                    field, culled); includes ``centre_sampling`` of the coarse centre lines
``yarn_expansion``  a yarn prim's planned yarns expanded into fiber curves; includes
                    ``centre_sampling`` and ``expand_yarn``
``centre_sampling`` yarn centre curves sampled into polylines
``expand_yarn``     one yarn's fibers generated (the listener gets the ``ExpandedFibers``)
``concatenate``     curve geometries joined
``reference_normals`` the fibers' azimuthal reference normals
``fiber_bank``      the tables of every fiber slot recoloured and packed
``bsdf``            the fiber BSDF built and its arrays uploaded
``curve_shape``     Mitsuba curve shapes built (fibers and other curves)
``scene``           the Mitsuba scene loaded (acceleration structure included)
==================  ==========================================================================
"""
from __future__ import annotations

import time
from typing import Any, Callable

__all__ = ["STEPS", "TranslationProfile"]

#: The steps a translation reports (module docstring).
STEPS = ("curves", "yarn_lod", "yarn_expansion", "centre_sampling", "expand_yarn", "concatenate", "reference_normals",
         "fiber_bank", "bsdf", "curve_shape", "scene")


class TranslationProfile:
    """Seconds and calls per translation step; ``listener(step, result)`` (optional) is called
    after every timed call, e.g. to report progress."""

    def __init__(self, listener: Callable[[str, Any], None] | None = None) -> None:
        self.seconds: dict[str, float] = {}
        self.calls: dict[str, int] = {}
        self.listener = listener

    def call(self, step: str, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        """``fn(*args, **kwargs)``, its time added to ``step``."""
        if step not in STEPS:
            raise ValueError(f"unknown translation step {step!r} (steps: {', '.join(STEPS)})")
        t0 = time.perf_counter()
        try:
            result = fn(*args, **kwargs)
        finally:
            self.seconds[step] = self.seconds.get(step, 0.0) + time.perf_counter() - t0
            self.calls[step] = self.calls.get(step, 0) + 1
        if self.listener is not None:
            self.listener(step, result)
        return result
