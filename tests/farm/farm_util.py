"""Processes for the farm tests: a Dask scheduler and workers on 127.0.0.1, killed at the end.

Every process is started in its own session and killed (with its children) when the
:class:`Processes` context ends, also when a test fails. Every wait is bounded.
"""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on (now)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def env(cache: Path | None = None, **extra: str) -> dict[str, str]:
    """The environment of a usdfiber or dask process: this checkout first, short Dask timeouts."""
    e = dict(os.environ)
    e["PYTHONPATH"] = str(REPO) + os.pathsep + e.get("PYTHONPATH", "")
    e["DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT"] = "5s"
    if cache is not None:
        e["USDFIBER_CACHE_DIR"] = str(cache)
    e.update(extra)
    return e


def wait_until(predicate, timeout: float, what: str, poll: float = 0.1):
    """``predicate()`` once it is truthy; AssertionError naming ``what`` after ``timeout`` s."""
    t_end = time.monotonic() + timeout
    while True:
        v = predicate()
        if v:
            return v
        if time.monotonic() > t_end:
            raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(poll)


def _listening(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.5)
        return s.connect_ex(("127.0.0.1", port)) == 0


class Processes:
    """Processes started for one test; all killed on exit (SIGKILL to each process group)."""

    def __init__(self, logdir: Path) -> None:
        self.logdir = Path(logdir)
        self.logdir.mkdir(parents=True, exist_ok=True)
        self.procs: list[subprocess.Popen] = []

    def __enter__(self) -> "Processes":
        return self

    def __exit__(self, *exc) -> None:
        for p in self.procs:
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
        for p in self.procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                pass

    def start(self, args: list[str], name: str, cache: Path | None = None, cwd: Path | None = None,
              **extra_env: str) -> subprocess.Popen:
        out = open(self.logdir / f"{name}.log", "w")
        p = subprocess.Popen(args, stdout=out, stderr=subprocess.STDOUT, env=env(cache, **extra_env),
                             cwd=cwd or REPO, start_new_session=True)
        out.close()
        self.procs.append(p)
        return p

    def log(self, name: str) -> str:
        return (self.logdir / f"{name}.log").read_text(errors="replace")

    def scheduler(self, port: int) -> str:
        """Start ``dask scheduler`` on 127.0.0.1:port; its address once it listens."""
        self.start([sys.executable, "-m", "dask", "scheduler", "--host", "127.0.0.1",
                    "--port", str(port), "--no-dashboard"], f"scheduler-{port}")
        wait_until(lambda: _listening(port), 60, f"the scheduler on port {port}")
        return f"tcp://127.0.0.1:{port}"

    def worker(self, address: str, name: str, cache: Path | None = None, cwd: Path | None = None,
               wrapper: list[str] | None = None) -> subprocess.Popen:
        """Start one ``dask worker`` process (no nanny: SIGKILL ends it for good)."""
        args = [sys.executable, "-m", "dask", "worker", address, "--nthreads", "1",
                "--no-nanny", "--host", "127.0.0.1", "--no-dashboard", "--name", name]
        return self.start((wrapper or []) + args, name, cache=cache, cwd=cwd)

    def usdfiber(self, args: list[str], name: str, cache: Path | None = None) -> subprocess.Popen:
        return self.start([sys.executable, "-m", "usdfiber", *map(str, args)], name, cache=cache)


def run_usdfiber(*args, cache: Path | None = None, timeout: float = 300) -> subprocess.CompletedProcess:
    """``python -m usdfiber ARGS`` to completion (bounded)."""
    return subprocess.run([sys.executable, "-m", "usdfiber", *map(str, args)], capture_output=True, text=True,
                          env=env(cache), cwd=REPO, timeout=timeout)


# ---- small stages and tables ------------------------------------------------------------------

#: Coarse, fast bake settings for farm tests (15 degree grid, few photons: a table in seconds).
COARSE_SETTINGS = dict(resolution_deg=15.0, photons=2000, batches=2)
COARSE_ARGS = ["--resolution", "15", "--photons", "2000", "--batches", "2", "--no-progress"]


def fiber_stage(path: Path, presets: tuple[str, ...] = ("silk",)) -> Path:
    """A stage with one fiber curve per preset, each with one cross-section variant (one table)."""
    import usdfiber  # noqa: F401 - registers the schema
    from pxr import Usd, UsdGeom

    from usdfiber import authoring

    stage = Usd.Stage.CreateNew(str(path))
    for i, name in enumerate(presets):
        c = UsdGeom.BasisCurves.Define(stage, f"/World/{name.capitalize()}{i}")
        c.CreateCurveVertexCountsAttr([4])
        c.CreatePointsAttr([(0, 0, i), (1, 0, i), (2, 0, i), (3, 0, i)])
        c.CreateWidthsAttr([0.01])
        authoring.apply_fiber(c.GetPrim(), name, variant_count=1)
    stage.GetRootLayer().Save()
    return path


def same_table(a, b) -> bool:
    """Equal arrays bit for bit, and equal headers but for times, machine and dates."""
    import numpy as np

    if sorted(a.arrays) != sorted(b.arrays):
        return False
    if not all(a.arrays[k].dtype == b.arrays[k].dtype and np.array_equal(a.arrays[k], b.arrays[k])
               for k in a.arrays):
        return False

    def strip(h):
        h = {k: v for k, v in h.items() if k not in ("created", "prims", "fiber")}
        h["bake"] = {k: v for k, v in h.get("bake", {}).items() if k not in ("trace_seconds", "wall_seconds", "machine")}
        return h

    return strip(a.header) == strip(b.header)
