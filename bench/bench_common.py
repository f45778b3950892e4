"""Helpers shared by the benchmark scripts (run them as `python bench/<name>.py`)."""
from __future__ import annotations

import hashlib
import os
import platform
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np


def json_default(o: Any) -> Any:
    """json.dump fallback for numpy scalars and arrays and paths."""
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(type(o))


def write_results(path: str | Path, results: dict[str, Any]) -> Path:
    """Write a benchmark's results as indented JSON (numpy values converted), making folders."""
    import json

    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=1, default=json_default))
    return out


class Timer:
    """Wall and process CPU time (all threads) of a block; cores = cpu / wall."""

    def __enter__(self) -> "Timer":
        self.w0, self.c0 = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.wall = time.perf_counter() - self.w0
        self.cpu = time.process_time() - self.c0

    @property
    def cores(self) -> float:
        return self.cpu / self.wall if self.wall > 0 else 0.0


def md_table(headers: list[str], rows: list[list[Any]]) -> str:
    """A Markdown table."""
    out = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    out += ["| " + " | ".join("-" if c is None else str(c) for c in r) + " |" for r in rows]
    return "\n".join(out)


# ---------------------------------------------------------------------------------------------
# The record of where a benchmark ran
# ---------------------------------------------------------------------------------------------

def cpu_model() -> str:
    """The CPU's model name (from /proc/cpuinfo where there is one)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def meminfo_gib(key: str) -> float | None:
    """A /proc/meminfo entry (MemTotal, MemAvailable, ...) in GiB."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) / 2**20
    except OSError:
        pass
    return None


def proc_status_mib(key: str, pid: str = "self") -> float | None:
    """A /proc/<pid>/status entry (VmRSS, VmHWM, ...) in MiB."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None


class RssSampler(threading.Thread):
    """Samples a /proc/self/status entry (``key``, MiB) every ``period`` seconds until ``stop``
    is set: ``peak``, and ``peak_at`` (``time.perf_counter()`` of the peak sample)."""

    def __init__(self, key: str = "VmRSS", period: float = 0.01) -> None:
        super().__init__(daemon=True)
        self.key, self.period = key, period
        self.peak, self.peak_at, self.stop = 0.0, 0.0, False

    def run(self) -> None:
        while not self.stop:
            r = proc_status_mib(self.key) or 0.0
            if r > self.peak:
                self.peak, self.peak_at = r, time.perf_counter()
            time.sleep(self.period)


def machine(**extra: Any) -> dict[str, Any]:
    """CPU, memory, versions and the Mitsuba variant, plus ``extra`` entries."""
    from usdfiber.backend import mitsuba

    mi = mitsuba()
    import drjit as dr

    return {
        "cpu_model": cpu_model(),
        "cores": os.cpu_count(),
        "cores_usable": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "ram_gib": round(meminfo_gib("MemTotal") or 0.0, 1),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "mitsuba": mi.__version__,
        "drjit": dr.__version__,
        "variant": mi.variant(),
        "drjit_llvm": os.environ.get("DRJIT_LIBLLVM_PATH"),
        "gpu": "none" if shutil.which("nvidia-smi") is None else "nvidia-smi present (not used)",
        **extra,
    }


def sha16(path: Path) -> str | None:
    """The first 16 hex digits of a file's SHA-256, or None if it cannot be read."""
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()[:16]
    except OSError:
        return None


def git_state(root: Path, sources: Sequence[str], dirs: Sequence[str]) -> dict[str, Any]:
    """HEAD, the modified tracked files under ``dirs`` and the hashes of ``sources``."""
    def run(*args: str) -> str:
        try:
            return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, timeout=30).stdout
        except (OSError, subprocess.SubprocessError):
            return ""

    status = run("status", "--porcelain", "--untracked-files=no", "--", *dirs)
    return {
        "head": run("rev-parse", "HEAD").strip(),
        "modified_sources": [l[3:] for l in status.splitlines() if l.strip()],
        "sha256_16": {s: sha16(root / s) for s in sources},
    }


#: Import hooks of editable installs (setuptools' redirecting finder, scikit-build-core's):
#: they resolve ``usdfiber`` to the installed checkout whatever ``sys.path`` says.
_EDITABLE_HOOKS = ("editable", "skbc", "scikitbuild", "redirecting")


def use_source_tree(tree: str | os.PathLike[str], *, bench: bool = False) -> None:
    """Import ``usdfiber`` (and, with ``bench``, the benchmarks' helpers) from the source tree
    ``tree`` in this process, not from an editable install: call it before the first import."""
    sys.meta_path[:] = [f for f in sys.meta_path
                        if not any(h in f"{type(f).__module__} {type(f).__name__}".lower() for h in _EDITABLE_HOOKS)]
    root = str(Path(tree).resolve())
    sys.path[:0] = [root, os.path.join(root, "bench")] if bench else [root]
