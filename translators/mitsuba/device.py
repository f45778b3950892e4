"""The device a render runs on: ``usdfiber render --device`` -> a Mitsuba variant (:func:`select_device`).

Mitsuba itself is imported and its LLVM found by the core (:func:`usdfiber.backend.mitsuba`),
which the baker's photon tracer shares; this module only maps the render's device names to
variants and sets the CPU thread count.
"""
from __future__ import annotations

from typing import Any

from usdfiber.backend import mitsuba
from usdfiber.translators.mitsuba.errors import RenderRefused

__all__ = ["DEVICES", "select_device"]

#: ``--device`` -> Mitsuba variant.
DEVICES = {"cpu": "llvm_ad_rgb", "gpu": "cuda_ad_rgb"}


def select_device(device: str, threads: int | None = None) -> Any:
    """Select Mitsuba's variant for ``device`` ("cpu" or "gpu") and the CPU thread count;
    returns the ``mitsuba`` module. Raises :class:`RenderRefused` saying why a device cannot be used."""
    if device not in DEVICES:
        raise RenderRefused(f"unknown device {device!r} (choose cpu or gpu)")
    try:
        mi = mitsuba(DEVICES[device])
    except (ImportError, AttributeError, RuntimeError) as exc:
        hint = " (no CUDA GPU or driver found: use --device cpu)" if device == "gpu" else ""
        raise RenderRefused(f"cannot use the {device} device: {' '.join(str(exc).split())}{hint}") from None
    if threads is not None:
        import drjit as dr

        if threads < 1:
            raise RenderRefused(f"threads must be >= 1, got {threads}")
        dr.set_thread_count(int(threads))
    return mi
