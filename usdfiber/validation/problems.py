"""What a usdFiber check reports, and the registry of prim checks.

Each check is a plain function ``check(prim) -> Iterable[Problem]``, registered with
:func:`prim_check`. The UsdValidation plugin (``usdfiber.validation.plugin``) exposes every
registered check as a USD validator named ``usdFiber:<name>``; ``usdfiber check`` runs them
through USD's validation framework and prints the problems.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import Callable, Iterable

from pxr import Usd


class Severity(str, Enum):
    """Errors block a render; warnings are reported and the render goes on."""

    ERROR = "error"
    WARNING = "warning"


@dataclass(frozen=True)
class Problem:
    """One finding: which check found it, where, and what was expected instead."""

    code: str                      # stable identifier, e.g. "FiberDiameterOutOfRange"
    severity: Severity
    prim: str                      # prim path
    attribute: str | None          # attribute or relationship name, None for prim-level
    message: str                   # says what is wrong AND what was expected
    layer: str | None = None       # identifier of the layer holding the strongest opinion
    time: float | None = None      # time code when the problem is time-sampled


PrimCheckFn = Callable[[Usd.Prim], Iterable[Problem]]


@dataclass(frozen=True)
class PrimCheck:
    """A registered check: its validator name, documentation and function."""

    name: str
    doc: str
    fn: PrimCheckFn
    keywords: tuple[str, ...] = field(default=("usdFiber",))


CHECKS: dict[str, PrimCheck] = {}


def prim_check(name: str, doc: str) -> Callable[[PrimCheckFn], PrimCheckFn]:
    """Register ``fn`` as the prim check ``name`` (validator ``usdFiber:<name>``)."""

    def deco(fn: PrimCheckFn) -> PrimCheckFn:
        if name in CHECKS:
            raise ValueError(f"duplicate usdFiber check {name!r}")
        CHECKS[name] = PrimCheck(name, doc, fn)
        return fn

    return deco
