"""The Dask worker plugin of ``--scheduler local:N``: Dr.Jit threads per worker process."""
from __future__ import annotations

from typing import Any

from distributed import WorkerPlugin

__all__ = ["DrjitThreads"]


class DrjitThreads(WorkerPlugin):
    """Give each worker's Dr.Jit ``threads`` threads (cores / workers on one machine), also to
    workers that restart after a crash."""

    name = "usdfiber-drjit-threads"

    def __init__(self, threads: int) -> None:
        self.threads = int(threads)

    def setup(self, worker: Any) -> None:
        try:
            from usdfiber.backend import mitsuba

            mitsuba()
            import drjit as dr

            dr.set_thread_count(self.threads)
        except Exception:  # noqa: BLE001 - the tasks report Mitsuba problems themselves
            pass
