"""Progress, failures and the end-of-run summary of a farm bake or frame sequence.

:class:`FarmProgress` draws one progress bar for the whole run (units of work done, time
left) on stderr and prints one line per failure there, naming the task, the worker and the
error. :class:`FarmSummary` collects what the run did (tables, frames, tasks, retries,
failures, times) and is printed as JSON by ``--json``.

Retries are counted from the tasks' own start events (:data:`EVENT_TOPIC`, logged on the
Dask scheduler by every task as it starts): a task that started more than once was retried,
because its worker died or it raised and was resubmitted.
"""
from __future__ import annotations

import json
import sys
import time
from collections import Counter
from dataclasses import asdict, dataclass, field
from typing import Any, Iterable, TextIO

__all__ = ["EVENT_TOPIC", "FarmFailure", "FarmProgress", "FarmSummary", "count_retries"]

#: Topic of the events tasks log on the Dask scheduler (``Worker.log_event``).
EVENT_TOPIC = "usdfiber-farm"


@dataclass
class FarmFailure:
    """A task that failed for good: what it was, where it ran, why."""

    task: str
    worker: str
    error: str

    def line(self) -> str:
        return f"task {self.task} failed on {self.worker or 'an unknown worker'}: {self.error}"


@dataclass
class FarmSummary:
    """What a farm run did; ``to_json()`` is the ``--json`` output."""

    engine: str                                   # "local", "dask" or "shard"
    scheduler: str | None = None                  # Dask scheduler address
    shard: str | None = None                      # "I/N"
    workers: int = 1
    tables: list[dict[str, Any]] = field(default_factory=list)
    frames: list[dict[str, Any]] = field(default_factory=list)
    tasks: dict[str, int] = field(default_factory=lambda: {"total": 0, "run": 0, "skipped": 0,
                                                            "failed": 0, "retries": 0})
    failures: list[FarmFailure] = field(default_factory=list)
    times: dict[str, float] = field(default_factory=dict)
    ok: bool = True

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["failures"] = [asdict(f) for f in self.failures]
        return d

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True, default=str)


def count_retries(events: Iterable[tuple[float, Any]], keys: Iterable[str], run: str | None = None) -> dict[str, int]:
    """Retries per task key: starts logged under :data:`EVENT_TOPIC` minus one (0 if it never
    started). ``run``: count only the starts of that run (a scheduler keeps the events of
    earlier bakes of the same tasks)."""
    wanted = set(keys)
    starts: Counter[str] = Counter()
    for _, msg in events:
        if (isinstance(msg, dict) and msg.get("event") == "start" and msg.get("task") in wanted
                and (run is None or msg.get("run") == run)):
            starts[msg["task"]] += 1
    return {k: max(0, starts[k] - 1) for k in wanted}


class FarmProgress:
    """One progress bar for a whole farm run, with time left; failure lines above it."""

    def __init__(self, total: int, *, initial: int = 0, unit: str = "dir", desc: str = "bake",
                 show: bool = True, file: TextIO | None = None) -> None:
        from tqdm import tqdm

        self.file = file or sys.stderr
        self.t0 = time.perf_counter()
        self.bar = tqdm(total=max(0, total), initial=initial, unit=unit, desc=desc, file=self.file,
                        dynamic_ncols=True, disable=not show)

    def advance(self, n: int, note: str | None = None) -> None:
        """``n`` more units done; ``note`` (e.g. the last error estimate) shown after the bar."""
        self.bar.update(n)
        if note:
            self.bar.set_postfix_str(note, refresh=False)

    def log(self, line: str) -> None:
        """A line above the bar (stderr), e.g. a failure or a retry."""
        self.bar.write(line, file=self.file)

    def close(self) -> float:
        """Close the bar; the seconds since it was opened."""
        self.bar.close()
        return time.perf_counter() - self.t0
