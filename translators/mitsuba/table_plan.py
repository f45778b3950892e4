"""The render's fiber tables, looked up in the cache once.

Before it translates, a render lists the tables its stage needs and looks each one up in the
cache, to estimate the bakes of the missing ones (:mod:`usdfiber.bake.cost`); the translation
then asks the cache for each table again as it reaches the prims. A
:class:`PlannedTableCache` keeps the answers of the first lookups (:meth:`~PlannedTableCache.plan`)
and gives each to the translation's first lookup of that table, so the cache's table headers
are read once per render, not twice. A table found missing is still looked up again under its
lock before it is baked (:func:`usdfiber.bake.cache.load_or_make`): a table another process
baked in the meantime is found, not baked twice.
"""
from __future__ import annotations

import os
from typing import Any, Callable, Sequence

from usdfiber.bake.cache import TableCache
from usdfiber.bake.settings import BakeSettings

__all__ = ["PlannedTableCache"]


class PlannedTableCache(TableCache):
    """A :class:`~usdfiber.bake.cache.TableCache` whose first :meth:`find_serving` of each
    planned table is answered from :meth:`plan`'s lookup."""

    def __init__(self, root: str | os.PathLike[str] | None = None) -> None:
        super().__init__(root)
        self._planned: dict[str, str | None] = {}

    def plan(self, requests: Sequence[Any], settings_for: Callable[[Any], BakeSettings]) -> list[Any]:
        """Look up each of ``requests`` (baked with ``settings_for(request)``) and keep the
        answers; returns the requests no cached table serves, in order."""
        missing = []
        for req in requests:
            st = settings_for(req)
            found = super().find_serving(req, st)
            self._planned[self.key(req, st)] = found
            if found is None:
                missing.append(req)
        return missing

    def find_serving(self, request: Any, settings: BakeSettings) -> str | None:
        """The planned answer for this table the first time it is asked for (then forgotten:
        a later lookup, e.g. under the table's lock before baking, reads the cache again);
        otherwise :meth:`TableCache.find_serving`."""
        key = self.key(request, settings)
        if key in self._planned:
            return self._planned.pop(key)
        return super().find_serving(request, settings)
