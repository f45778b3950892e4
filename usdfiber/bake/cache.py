"""Content-addressed cache of baked BCSDF tables.

Location: the ``root`` given, else ``$USDFIBER_CACHE_DIR``, else ``~/.cache/usdfiber``
(``$XDG_CACHE_HOME/usdfiber`` when XDG_CACHE_HOME is set). Layout under the root::

    tables/<key>.npz        finished tables (usdfiber table files)
    partial/<key>/          chunks of an unfinished bake (one file per incoming direction)
    locks/<key>.lock        one lock file per key

The key is the sha256 of the canonical JSON of: the fiber's geometry inputs
(``FiberParams.geometry_inputs()``: everything that changes traced photon paths, not the
dye, depth of shade or diameter, which only recolour), the cross-section variant index, the
bake settings that change the result (:meth:`BakeSettings.result_inputs`) and the table
format and layout versions. Two prims that differ only in dye share a key.

Concurrency: a baker holds the key's lock (``filelock``, an OS lock released when the
process dies) while it checks and bakes; a second baker of the same key waits and then
finds the finished table. Tables are written atomically (temporary file + rename) and read
with every checksum verified: a truncated or corrupt file is reported (a
:class:`TableCacheWarning` naming the file and the reason), deleted and baked again, never
used. An interrupted bake keeps its finished directions in ``partial/<key>/``; the next
bake of the key resumes from them and removes the directory when the table is written.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from usdfiber import table_format
from usdfiber.bake.baker import BakeSettings, ProgressFn, TableRequest, bake_request
from usdfiber.bake.table import LAYOUT, LAYOUT_VERSION, BcsdfTable, TableLayoutError

__all__ = ["CacheResult", "TableCache", "TableCacheWarning", "cache_key", "default_cache_dir"]


class TableCacheWarning(UserWarning):
    """A cached table that could not be used (it is baked again)."""


def default_cache_dir() -> Path:
    """``$USDFIBER_CACHE_DIR``, else ``$XDG_CACHE_HOME/usdfiber``, else ``~/.cache/usdfiber``."""
    env = os.environ.get("USDFIBER_CACHE_DIR")
    if env:
        return Path(env).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME")
    if xdg:
        return Path(xdg).expanduser() / "usdfiber"
    return Path("~/.cache/usdfiber").expanduser()


def cache_key(geometry_inputs: dict[str, Any], variant: int, settings: BakeSettings) -> str:
    """sha256 hex of (geometry inputs, variant, result-changing settings, format versions)."""
    blob = json.dumps({
        "inputs": geometry_inputs,
        "variant": int(variant),
        "settings": settings.result_inputs(),
        "table_format": table_format.VERSION,
        "layout": [LAYOUT, LAYOUT_VERSION],
    }, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(blob.encode("utf-8")).hexdigest()


@dataclass
class CacheResult:
    """Outcome of :meth:`TableCache.get_or_bake`."""

    key: str
    path: Path
    table: BcsdfTable
    baked: bool               # False: found in the cache
    seconds: float            # wall time of this call
    resumed: int = 0          # directions taken from an interrupted bake


class TableCache:
    """The tables under one cache root (see the module docstring)."""

    def __init__(self, root: str | os.PathLike[str] | None = None) -> None:
        self.root = Path(root).expanduser() if root is not None else default_cache_dir()

    # ---- paths -------------------------------------------------------------------------------
    def key(self, request: TableRequest, settings: BakeSettings) -> str:
        return cache_key(request.inputs, request.variant, settings)

    def table_path(self, key: str) -> Path:
        return self.root / "tables" / f"{key}.npz"

    def partial_dir(self, key: str) -> Path:
        return self.root / "partial" / key

    def lock_path(self, key: str) -> Path:
        return self.root / "locks" / f"{key}.lock"

    # ---- lookups -------------------------------------------------------------------------------
    def load(self, key: str) -> BcsdfTable | None:
        """The cached table of ``key``, verified; None when absent or unusable.

        A damaged file (truncated, corrupt, checksum mismatch, foreign layout) is reported
        with a TableCacheWarning naming it and the reason, and deleted.
        """
        return self.load_verified(self.table_path(key), BcsdfTable.load,
                                  lambda t: t.header.get("cache_key") in (None, key))

    def load_verified(self, path: Path, read: Any, written_for_key: Any, redo: str = "baking it again") -> Any:
        """``read(path)`` when the file exists, reads cleanly and ``written_for_key(result)``;
        otherwise None, and a damaged file is reported (TableCacheWarning: the file, the
        reason, ``redo``) and deleted. For every kind of file kept under this cache."""
        if not path.exists():
            return None
        try:
            obj = read(path)
            if not written_for_key(obj):
                raise TableLayoutError(f"{path}: written for another cache key")
            return obj
        except (table_format.TableError, TableLayoutError, KeyError, ValueError) as exc:
            reason = exc.reason if isinstance(exc, table_format.TableError) else str(exc)
            if reason.startswith(str(path)):
                reason = reason[len(str(path)):].lstrip(": ")
            warnings.warn(f"{path}: {reason}; {redo}", TableCacheWarning, stacklevel=3)
            try:
                path.unlink()
            except FileNotFoundError:
                pass
            return None

    def contains(self, key: str) -> bool:
        return self.table_path(key).exists()

    def lock(self, key: str, timeout: float = -1):
        """The key's inter-process lock (a ``filelock.FileLock``; use as a context manager)."""
        from filelock import FileLock

        p = self.lock_path(key)
        p.parent.mkdir(parents=True, exist_ok=True)
        return FileLock(str(p), timeout=timeout)

    # ---- baking ---------------------------------------------------------------------------------
    def get_or_bake(self, request: TableRequest, settings: BakeSettings | None = None,
                    progress: ProgressFn | None = None, *, bake_missing: bool = True) -> CacheResult | None:
        """The table of ``request`` from the cache, baking it (under the key's lock) if needed.

        Returns None only when ``bake_missing`` is False and the table is not cached.
        """
        st = settings or BakeSettings()
        key = self.key(request, st)
        t0 = time.perf_counter()
        table = self.load(key)
        if table is not None:
            return CacheResult(key, self.table_path(key), table, False, time.perf_counter() - t0)
        if not bake_missing:
            return None
        with self.lock(key):
            table = self.load(key)  # another process may have finished it while we waited
            if table is not None:
                return CacheResult(key, self.table_path(key), table, False, time.perf_counter() - t0)
            resumed = 0

            def prog(done: int, total: int, info: dict) -> None:
                nonlocal resumed
                if info.get("event") == "start":
                    resumed = int(info.get("resumed", 0))
                    info = {**info, "label": request.label}
                if progress is not None:
                    progress(done, total, info)

            pdir = self.partial_dir(key)
            table = bake_request(request, st, prog, resume_dir=pdir)
            table.header["cache_key"] = key
            path = self.table_path(key)
            path.parent.mkdir(parents=True, exist_ok=True)
            table.save(path)
            shutil.rmtree(pdir, ignore_errors=True)
            return CacheResult(key, path, table, True, time.perf_counter() - t0, resumed)

    def clear_partial(self, key: str) -> None:
        shutil.rmtree(self.partial_dir(key), ignore_errors=True)
