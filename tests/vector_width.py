"""Run Dr.Jit's LLVM backend at another SIMD width, as on another machine.

Dr.Jit compiles its kernels for the host CPU and vectorizes with the host's SIMD width
(16 float lanes with AVX-512, 8 with AVX2). Lane count, target instructions (reciprocal
square root approximations, FMA contraction) and the order of parallel reductions change
rounding, and rounding changes Monte-Carlo paths, so the same seed does not give the same
random estimate on every machine. Running the suite at both widths on one machine shows that
its statistical assertions hold on either kind of machine.

Dr.Jit's Python API does not expose the target; its core library exports
``jit_llvm_set_target(cpu, features, vector_width)`` (C++ linkage, drjit 1.x), which takes
effect for every kernel compiled afterwards, so it is called through ctypes once the LLVM
backend is initialized and before any test compiles a kernel.
"""
from __future__ import annotations

import ctypes
import os

#: Supported widths: the LLVM CPU and features that a machine of that SIMD width has.
TARGETS: dict[int, tuple[str, str]] = {
    16: ("skylake-avx512", "+avx512f,+avx512dq,+avx512cd,+avx512bw,+avx512vl,+avx2,+avx,+fma,+f16c,"
                           "+bmi,+bmi2,+lzcnt,+popcnt,+sse4.2,+sse4.1,+ssse3,+sse3,+sse2,+sse"),
    8: ("haswell", "+avx2,+avx,+fma,+f16c,+bmi,+bmi2,+lzcnt,+popcnt,+sse4.2,+sse4.1,+ssse3,+sse3,+sse2,+sse,"
                   "-avx512f"),
}

_SYMBOLS = {
    "set_target": "_Z19jit_llvm_set_targetPKcS0_j",
    "cpu": "_Z19jit_llvm_target_cpuv",
    "features": "_Z24jit_llvm_target_featuresv",
    "width": "_Z21jit_llvm_vector_widthv",
}


def _core() -> ctypes.CDLL:
    from usdfiber.backend import configure_llvm

    configure_llvm()
    import drjit as dr
    import drjit.llvm  # noqa: F401  (initializes the LLVM backend)

    path = os.path.join(os.path.dirname(dr.__file__), "libdrjit-core.so")
    lib = ctypes.CDLL(path)
    for name, sym in _SYMBOLS.items():
        if not hasattr(lib, sym):
            raise RuntimeError(f"{path} does not export {sym} (jit_llvm_{name}): "
                               f"this Dr.Jit ({dr.__version__}) cannot be retargeted by the test suite")
    getattr(lib, _SYMBOLS["cpu"]).restype = ctypes.c_char_p
    getattr(lib, _SYMBOLS["features"]).restype = ctypes.c_char_p
    getattr(lib, _SYMBOLS["width"]).restype = ctypes.c_uint32
    getattr(lib, _SYMBOLS["set_target"]).argtypes = [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_uint32]
    getattr(lib, _SYMBOLS["set_target"]).restype = None
    return lib


def current_target() -> tuple[str, int]:
    """(LLVM CPU name, vector width) that Dr.Jit compiles kernels for now."""
    lib = _core()
    return (getattr(lib, _SYMBOLS["cpu"])() or b"?").decode(), int(getattr(lib, _SYMBOLS["width"])())


def force_vector_width(width: int) -> tuple[str, int]:
    """Compile every later Dr.Jit LLVM kernel for a machine of ``width`` float lanes.

    Refuses a width the host cannot execute (AVX-512 code on an AVX2 host) and any width not
    in ``TARGETS``. Returns the resulting (cpu, width).
    """
    if width not in TARGETS:
        raise ValueError(f"USDFIBER_TEST_VECTOR_WIDTH={width}: expected one of {sorted(TARGETS)}")
    lib = _core()
    host = (getattr(lib, _SYMBOLS["features"])() or b"").decode().split(",")
    needed = [f for f in TARGETS[width][1].split(",") if f.startswith("+")]
    missing = [f for f in needed if f not in host and f.lstrip("+") in ("avx512f", "avx2", "fma")]
    if missing:
        raise ValueError(f"USDFIBER_TEST_VECTOR_WIDTH={width}: this CPU lacks {', '.join(missing)}")
    cpu, features = TARGETS[width]
    getattr(lib, _SYMBOLS["set_target"])(cpu.encode(), features.encode(), width)
    got = current_target()
    if got != (cpu, width):
        raise RuntimeError(f"Dr.Jit did not take the LLVM target {cpu}/{width} (now {got[0]}/{got[1]})")
    return got
