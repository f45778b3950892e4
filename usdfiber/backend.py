"""Dr.Jit / Mitsuba backend selection.

Mitsuba's LLVM variants need an LLVM shared library that Dr.Jit can load. Debian's
``libllvm19`` works; older LLVMs (14/15) abort inside the JIT. Dr.Jit reads
``DRJIT_LIBLLVM_PATH`` once, when it is first imported, so it must be set before that.
"""
from __future__ import annotations

import glob
import os

_LLVM_CANDIDATES = (
    "/usr/lib/x86_64-linux-gnu/libLLVM-19.so",
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1",
    "/usr/lib/aarch64-linux-gnu/libLLVM-19.so",
    "/usr/lib/llvm-19/lib/libLLVM.so",
)


def find_llvm() -> str | None:
    """Return the path of a usable LLVM (>= 16) shared library, or None."""
    env = os.environ.get("DRJIT_LIBLLVM_PATH")
    if env and os.path.exists(env):
        return env
    for cand in _LLVM_CANDIDATES:
        if os.path.exists(cand):
            return cand
    for cand in sorted(glob.glob("/usr/lib/*/libLLVM-1[6-9]*.so*"), reverse=True):
        return cand
    return None


def configure_llvm() -> None:
    """Point Dr.Jit at a working LLVM before drjit is imported (no-op if already set)."""
    if "DRJIT_LIBLLVM_PATH" not in os.environ:
        path = find_llvm()
        if path:
            os.environ["DRJIT_LIBLLVM_PATH"] = path


def mitsuba(variant: str | None = None):
    """Import Mitsuba with a JIT variant selected and return the module.

    ``variant`` defaults to ``$USDFIBER_VARIANT``, else the JIT variant already selected,
    else ``llvm_ad_rgb``. Raises RuntimeError
    with a readable message when no LLVM library is installed.
    """
    configure_llvm()
    import mitsuba as mi

    # Without an explicit request keep a JIT variant already chosen (e.g. `render --device gpu`).
    current = mi.variant()
    keep = current if current and not current.startswith("scalar") else None
    wanted = variant or os.environ.get("USDFIBER_VARIANT") or keep or "llvm_ad_rgb"
    if mi.variant() != wanted:
        if wanted.startswith("llvm") and not os.environ.get("DRJIT_LIBLLVM_PATH"):
            raise RuntimeError(
                "Mitsuba's LLVM variant needs libLLVM >= 16 (Debian: apt-get install libllvm19); "
                "none was found. Set DRJIT_LIBLLVM_PATH to its path."
            )
        mi.set_variant(wanted)
    return mi
