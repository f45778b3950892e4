"""Argument types shared by the sub-commands: each turns bad input into one readable line."""
from __future__ import annotations

import argparse
import math


def _number(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"not a finite number: {text!r}")
    return v


def positive_int(text: str) -> int:
    """An integer >= 1."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {v}")
    return v


def finite_float(text: str) -> float:
    """Any finite number."""
    return _number(text)


def positive_float(text: str) -> float:
    """A finite number > 0."""
    v = _number(text)
    if v <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text!r}")
    return v


def compression_bound(text: str) -> float:
    """A compression bound: the relative L2 error of p, in [MIN_BOUND, 1)."""
    from usdfiber.bake.compression import MIN_BOUND

    v = finite_float(text)
    if not MIN_BOUND <= v < 1:
        raise argparse.ArgumentTypeError(f"must be in [{MIN_BOUND:g}, 1) (relative L2 error of p, e.g. 0.01), "
                                         f"got {text}")
    return v


def percentage(text: str) -> float:
    """A finite percentage >= 0 (depth of shade)."""
    v = _number(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be a percentage >= 0, got {text!r}")
    return v


def non_negative_float(text: str) -> float:
    """A finite number >= 0."""
    v = _number(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be a number >= 0, got {text!r}")
    return v


#: Seeds are 32-bit unsigned (NumPy's and Mitsuba's samplers take them as such).
SEED_MAX = 2 ** 32 - 1


def seed(text: str) -> int:
    """A random seed, an integer in [0, 2^32 - 1]."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if not 0 <= v <= SEED_MAX:
        raise argparse.ArgumentTypeError(f"must be an integer from 0 to {SEED_MAX}, got {v}")
    return v


def memory_size(text: str) -> str:
    """A memory size (``8G``, ``512MiB``, bytes), checked here and resolved by
    :meth:`usdfiber.memory_budget.MemoryBudget.resolve`."""
    from usdfiber.memory_budget import MemoryBudgetError, parse_size

    try:
        parse_size(text)
    except MemoryBudgetError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def add_memory_budget_option(parser: argparse.ArgumentParser) -> None:
    """``--memory-budget SIZE`` (see :mod:`usdfiber.memory_budget`)."""
    from usdfiber.memory_budget import BUDGET_ENV, DEFAULT_FRACTION

    parser.add_argument("--memory-budget", type=memory_size, default=None, metavar="SIZE",
                        help=f"memory the geometry and tables may use, e.g. 8G (default ${BUDGET_ENV}, "
                             f"else {DEFAULT_FRACTION * 100:.0f}%% of the machine's memory)")  # %% : argparse formats help
