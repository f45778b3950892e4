"""The memory a command may use: estimate geometry and tables before building them.

Commands that make geometry or tables (``render``: yarn expansion; ``cloth``; ``import``;
``bake``) estimate the bytes they will hold before allocating them and compare the estimate
with a budget. Over the budget, a command that can lower its detail does so with a warning
saying by how much (the renderer keeps fewer fibers per yarn); one that cannot refuses with
the estimate and the way to change the budget, before allocating anything.

The budget is ``--memory-budget SIZE`` on those commands, else ``$USDFIBER_MEMORY_BUDGET``,
else :data:`DEFAULT_FRACTION` of the machine's memory (physical RAM, or the cgroup limit of
a container when that is lower). A size is a number of bytes with an optional unit: ``8G``,
``512MiB``, ``1.5GB`` (units are powers of 1024; ``B`` and ``iB`` are optional).

The estimates are upper bounds of the large arrays (the per-point and per-segment costs below
were measured as the peak of the Python side, plus Mitsuba's own per-segment cost from the
project's field notes), not of the interpreter and libraries around them.
"""
from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

__all__ = ["BUDGET_ENV", "DEFAULT_FRACTION", "MemoryBudget", "MemoryBudgetError", "format_bytes",
           "machine_memory", "parse_size"]

#: Environment variable holding the default budget (a size, see :func:`parse_size`).
BUDGET_ENV = "USDFIBER_MEMORY_BUDGET"
#: Fraction of the machine's memory a command may use when no budget is given.
DEFAULT_FRACTION = 0.5
#: How to change the budget, named in every refusal.
HOW_TO_CHANGE = f"raise the budget with --memory-budget SIZE or ${BUDGET_ENV}"

_UNITS = {"": 1, "K": 1 << 10, "M": 1 << 20, "G": 1 << 30, "T": 1 << 40}
_SIZE = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)\s*([kKmMgGtT]?)(?:i?[bB])?\s*$")


class MemoryBudgetError(ValueError):
    """Work that does not fit the memory budget (one line: what, the estimate, the budget, how
    to change it), or a budget that cannot be read."""


def parse_size(text: str) -> int:
    """Bytes of a size such as ``"8G"``, ``"512MiB"``, ``"1.5GB"`` or ``"1000000"`` (> 0)."""
    m = _SIZE.match(str(text))
    if not m:
        raise MemoryBudgetError(f"not a memory size: {text!r} (expected e.g. 8G, 512MiB or a number of bytes)")
    value = float(m.group(1)) * _UNITS[m.group(2).upper()]
    if not math.isfinite(value) or value < 1:
        raise MemoryBudgetError(f"a memory size must be at least 1 byte, got {text!r}")
    return int(value)


def format_bytes(n: float) -> str:
    """``n`` bytes as a short text (``"3.2 GiB"``)."""
    n = float(n)
    for unit, size in (("TiB", 1 << 40), ("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if n >= size:
            return f"{n / size:.3g} {unit}"
    return f"{int(n)} B"


def _cgroup_limit() -> int | None:
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = Path(path).read_text().strip()
        except OSError:
            continue
        if text.isdigit() and int(text) < (1 << 60):
            return int(text)
    return None


def machine_memory() -> int:
    """The machine's memory in bytes: physical RAM, or the container's limit when lower."""
    try:
        phys = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        phys = 8 << 30
    limit = _cgroup_limit()
    return min(phys, limit) if limit else phys


@dataclass(frozen=True)
class MemoryBudget:
    """A memory budget of ``bytes``; ``source`` says where it came from (for messages)."""

    bytes: int
    source: str = "default"

    @classmethod
    def resolve(cls, option: str | None = None) -> "MemoryBudget":
        """The budget of a command: ``option`` (``--memory-budget``), else the environment
        variable, else :data:`DEFAULT_FRACTION` of :func:`machine_memory`."""
        if option is not None:
            try:
                return cls(parse_size(option), "--memory-budget")
            except MemoryBudgetError as exc:
                raise MemoryBudgetError(f"--memory-budget: {exc}") from None
        env = os.environ.get(BUDGET_ENV)
        if env:
            try:
                return cls(parse_size(env), f"${BUDGET_ENV}")
            except MemoryBudgetError as exc:
                raise MemoryBudgetError(f"${BUDGET_ENV}: {exc}") from None
        return cls(int(DEFAULT_FRACTION * machine_memory()),
                   f"{DEFAULT_FRACTION:.0%} of this machine's {format_bytes(machine_memory())}")

    def describe(self) -> str:
        """``"2 GiB (--memory-budget)"``."""
        return f"{format_bytes(self.bytes)} ({self.source})"

    def fits(self, estimate: float) -> bool:
        """Whether ``estimate`` bytes fit."""
        return float(estimate) <= self.bytes

    def require(self, estimate: float, what: str) -> None:
        """Raise :class:`MemoryBudgetError` unless ``estimate`` bytes fit: ``what`` names the
        work (with its size, e.g. "cloth stockinette of 1000000 rows x 1000000 loops")."""
        if not self.fits(estimate):
            raise MemoryBudgetError(f"{what} needs about {format_bytes(estimate)}, more than the memory budget "
                                    f"of {self.describe()}; make it smaller or {HOW_TO_CHANGE}")

    def scale_to_fit(self, estimate: float) -> float:
        """The factor in (0, 1] by which work of ``estimate`` bytes must shrink to fit."""
        return 1.0 if self.fits(estimate) else self.bytes / float(estimate)
