"""``--shard I/N``: the I-th of N disjoint parts of a piece of work, for farm managers.

Farm managers (Deadline, Tractor, OpenCue) run command lines, not Python clusters: a job of
N tasks runs ``usdfiber bake STAGE --shard I/N`` for I = 1..N, on any machines, in any
order, possibly more than once. Every process plans the same work list (a deterministic
order that does not depend on what is already done) and takes the items ``j`` with
``j mod N == I - 1``: the parts are disjoint and together are all of the work.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Sequence, TypeVar

__all__ = ["MAX_SHARDS", "Shard", "ShardSpecError", "parse_shard"]

#: Upper bound on N (a typo must not plan millions of empty processes' worth of parts).
MAX_SHARDS = 100_000

T = TypeVar("T")
_SPEC = re.compile(r"^\s*(-?\d+)\s*/\s*(-?\d+)\s*$")


class ShardSpecError(ValueError):
    """A shard spec that is not I/N with 1 <= I <= N (the message is one line)."""


@dataclass(frozen=True)
class Shard:
    """Part ``index`` (1-based) of ``count``."""

    index: int
    count: int

    def __post_init__(self) -> None:
        if not 1 <= self.count <= MAX_SHARDS:
            raise ShardSpecError(f"shard {self.index}/{self.count}: N must be between 1 and {MAX_SHARDS}")
        if not 1 <= self.index <= self.count:
            raise ShardSpecError(f"shard {self.index}/{self.count}: I must be between 1 and N={self.count} "
                                 f"(shards are numbered from 1)")

    def select(self, items: Sequence[T]) -> list[T]:
        """This shard's items of a deterministically ordered work list."""
        return list(items[self.index - 1::self.count])

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"


def parse_shard(text: str) -> Shard:
    """``"2/3"`` -> ``Shard(2, 3)``; ShardSpecError for anything else (``0/3``, ``4/3``, ``a/b``)."""
    m = _SPEC.match(str(text))
    if m is None:
        raise ShardSpecError(f"bad shard {text!r}: expected I/N with 1 <= I <= N, e.g. 2/3")
    return Shard(int(m.group(1)), int(m.group(2)))
