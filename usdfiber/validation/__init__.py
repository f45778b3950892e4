"""usdFiber validation: prim checks exposed to USD as the ``usdFiber`` validators.

How the pieces fit:

- :mod:`.problems` holds :class:`~.problems.Problem` and the ``@prim_check`` registry.
- Check modules in this package (``values``, ``topology``, ``assets``, ...) register checks.
- ``plugInfo.json`` (next to this file) declares one UsdValidation validator per check, in
  a plugin of type ``python`` named ``usdFiber``; validator names are ``usdFiber:<check>``
  and all carry the keyword ``usdFiber``.
- When USD needs one of these validators it loads the plugin by running
  ``import usdFiber``. Importing this package installs a finder that maps that module name
  onto :mod:`usdfiber.validation.plugin`, whose import registers every check with USD.
  This works from an installed wheel and from a source checkout alike: no directory has
  to be added to ``sys.path``.
- :mod:`.runner` runs the validators through ``UsdValidation.ValidationContext``.

This module is imported by every check module, so it stays light: no check is imported
here. It also carries the time selection a validation run passes to the checks
(:func:`times_for`).
"""
from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import math
import sys
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Iterator

#: Name of the USD plugin and of the module USD imports to load it.
PLUGIN_NAME = "usdFiber"
#: Keyword every usdFiber validator carries (``ValidationContext(keywords=[KEYWORD])``).
KEYWORD = "usdFiber"
_IMPL = "usdfiber.validation.plugin"


class _PluginLoader(importlib.abc.Loader):
    """Executes the ``usdFiber`` module by importing the real plugin module."""

    def create_module(self, spec):  # default module object
        return None

    def exec_module(self, module) -> None:
        impl = importlib.import_module(_IMPL)
        module.__doc__ = impl.__doc__
        module.plugin = impl


class _PluginFinder(importlib.abc.MetaPathFinder):
    """Resolves exactly the module name ``usdFiber`` (USD's ``import usdFiber``)."""

    def find_spec(self, fullname, path=None, target=None):
        if fullname != PLUGIN_NAME:
            return None
        return importlib.util.spec_from_loader(fullname, _PluginLoader(), origin=_IMPL)


def install_plugin_module() -> None:
    """Make ``import usdFiber`` (how USD loads a python plugin) import our plugin; idempotent."""
    if not any(isinstance(f, _PluginFinder) for f in sys.meta_path):
        sys.meta_path.append(_PluginFinder())


install_plugin_module()


# --- time selection --------------------------------------------------------------------

@dataclass(frozen=True)
class TimeSelection:
    """Which values of an attribute a check looks at.

    ``everything``: the default value and every authored time sample (what ``usdfiber
    check`` does without ``--time``). Otherwise the closed interval [start, end]: a
    single time when start == end (the value resolved there), else the samples inside it
    plus the default value.
    """

    start: float = -math.inf
    end: float = math.inf
    include_default: bool = True

    @property
    def everything(self) -> bool:
        return self.start == -math.inf and self.end == math.inf and self.include_default

    @property
    def single(self) -> float | None:
        return self.start if self.start == self.end else None


EVERYTHING = TimeSelection()
#: Per-thread state of the running validation: ``times`` holds its time selection.
thread_state = threading.local()


def current_times() -> TimeSelection:
    """The time selection of the validation running on this thread."""
    sel = getattr(thread_state, "times", EVERYTHING)
    return sel if isinstance(sel, TimeSelection) else sel.get()


@contextmanager
def selected_times(sel) -> Iterator[None]:
    """Run checks on this thread with ``sel`` (set by the plugin around each check call).

    ``sel`` is a :class:`TimeSelection` or an object whose ``get()`` returns one (read
    only when a check asks).

    Thread-local because USD calls validators from its worker threads, each call holding
    the GIL for its whole duration.
    """
    old = getattr(thread_state, "times", EVERYTHING)
    thread_state.times = sel
    try:
        yield
    finally:
        thread_state.times = old


def times_for(attr) -> list[float | None]:
    """Times (None = the default value) at which a check should read ``attr``.

    Without samples the default value is what every time resolves to, so it is read
    once and reported without a time.
    """
    samples = attr.GetTimeSamples()
    if not samples:
        return [None]
    sel = current_times()
    if sel.everything:
        return [None, *samples]
    if sel.single is not None:
        return [sel.single]
    inside: list[float | None] = [t for t in samples if sel.start <= t <= sel.end]
    if not inside and math.isfinite(sel.start):
        inside = [sel.start]  # no sample inside: the value held over the interval
    return ([None] if sel.include_default else []) + inside


__all__ = [
    "EVERYTHING",
    "KEYWORD",
    "PLUGIN_NAME",
    "TimeSelection",
    "current_times",
    "install_plugin_module",
    "selected_times",
    "thread_state",
    "times_for",
]
