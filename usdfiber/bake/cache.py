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
format and layout versions. Two prims that differ only in dye share a key. The settings enter
with canonical types (``resolution_deg=10`` and ``10.0`` are one key; keys of tables baked
before are unchanged). A table names its key in its header and is refused under any other.
When a key's table is missing, any cached table of the same physics (:func:`physics_key`:
every input but the :data:`QUALITY_SETTINGS`) that is at least as good (:func:`serves`: as
fine a grid, as many photons per direction) is used instead: tables made by ``usdfiber bake``
serve a render's requests whatever their batches. File-system failures (a read-only or full
disk, a directory or file in the wrong place) raise :class:`TableCacheError`, one line naming
the path; tables are written atomically, so a failed write leaves no half-written table.

Concurrency: a baker holds the key's lock (``filelock``, an OS lock released when the
process dies) while it checks and bakes; a second baker of the same key waits and then
finds the finished table. Tables are written atomically (temporary file + rename) and read
with every checksum verified: a truncated or corrupt file is reported (a
:class:`TableCacheWarning` naming the file and the reason), deleted and baked again, never
used. An interrupted bake keeps its finished directions in ``partial/<key>/``
(:mod:`usdfiber.bake.chunks`); the next bake of the key resumes from them and removes the
directory when the table is written.

Compressed entries: a table may be kept in the compact layout of
:mod:`usdfiber.bake.compression` (``usdfiber bake --compress [BOUND]`` compresses each table
before it is stored, and tables it finds uncompressed in place; ``usdfiber table compress
--cache`` compresses a whole cache in place; :meth:`TableCache.compress_entry`). It is kept
under the same key, in the same file, and served exactly as the uncompressed table: the key
says what a table describes (the fiber physics, the bake's quality, the layout the bake
produced), while the compression is how that same table is stored, like the float16 rounding of
the levels layout: a lossy encoding whose error is bounded and recorded in the header
(``compression``: codec, bound, worst error), checked by the writer against the uncompressed
table at every direction. Putting the bound in the key would make a render's request (which
knows nothing of storage) miss the compressed table and bake the same photons again. A
compressed file is read through the same verified loader: its checksums, its layout and codec
frames against its header, and its ``cache_key``; a half-written or mismatched one is reported,
deleted and baked again, never used. A table that cannot be kept within the bound is stored
uncompressed, with a warning (its photons are not thrown away).

Every kind of file kept under a cache root (tables here, yarn far fields in the Mitsuba
bridge) is read through :meth:`TableCache.load_verified` and made through
:func:`load_or_make`: look without the lock, then under the key's lock look again and make
it only if it is still missing (double-checked locking), so concurrent makers of one key
make it once.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, ContextManager, TypeVar

from usdfiber import table_format
from usdfiber.bake.baker import ProgressFn, bake_request
from usdfiber.bake.requests import TableRequest
from usdfiber.bake.settings import BakeError, BakeSettings
from usdfiber.bake.storage import LAYOUT, LAYOUT_VERSION, TableLayoutError
from usdfiber.bake.table import BcsdfTable

__all__ = ["QUALITY_SETTINGS", "CacheResult", "TableCache", "TableCacheError", "TableCacheWarning", "cache_key",
           "default_cache_dir", "load_or_make", "physics_key", "serves"]

#: Bake settings that set how good a table is, not what it describes: a cached table of the
#: same physics (every other input equal) whose resolution and photons are at least as good as
#: asked serves the request (:func:`serves`).
QUALITY_SETTINGS = ("resolution_deg", "photons", "target_error", "max_photons", "batches", "seed")

T = TypeVar("T")


class TableCacheWarning(UserWarning):
    """A cached table that could not be used (it is baked again), or a table that could not be
    stored compressed (it is stored uncompressed)."""


class TableCacheError(BakeError):
    """A cache that cannot be used (a read-only or full disk, a directory where a file belongs,
    a file where a directory belongs): one line naming the path and the reason."""

    @classmethod
    def of(cls, exc: OSError, root: Path) -> "TableCacheError":
        """The error for a failed file-system operation under the cache ``root``."""
        where = exc.filename if exc.filename is not None else root
        why = exc.strerror or str(exc)
        if isinstance(exc, IsADirectoryError):
            why += " (a directory where the cache keeps a file)"
        elif isinstance(exc, (NotADirectoryError, FileExistsError)):
            why += " (a file where the cache keeps a directory)"
        return cls(f"{where}: {why}; the table cache {root} must be a writable directory with free space "
                   f"(--cache-dir or $USDFIBER_CACHE_DIR chooses another)")


def default_cache_dir() -> Path:
    """``$USDFIBER_CACHE_DIR``, else ``$XDG_CACHE_HOME/usdfiber``, else ``~/.cache/usdfiber``."""
    env = os.environ.get("USDFIBER_CACHE_DIR")
    if env:
        return Path(env).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME")
    if xdg:
        return Path(xdg).expanduser() / "usdfiber"
    return Path("~/.cache/usdfiber").expanduser()


def _digest(geometry_inputs: Any, variant: int, settings: dict[str, Any]) -> str:
    blob = json.dumps({
        "inputs": geometry_inputs,
        "variant": int(variant),
        "settings": settings,
        "table_format": table_format.VERSION,
        "layout": [LAYOUT, LAYOUT_VERSION],
    }, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(blob.encode("utf-8")).hexdigest()


def cache_key(geometry_inputs: dict[str, Any], variant: int, settings: BakeSettings) -> str:
    """sha256 hex of (geometry inputs, variant, result-changing settings, format versions).

    The settings enter with canonical types (:class:`BakeSettings` normalises them), so
    ``resolution_deg=10`` and ``10.0`` give one key."""
    return _digest(geometry_inputs, variant, settings.result_inputs())


def physics_key(geometry_inputs: Any, variant: int, settings: dict[str, Any]) -> str:
    """sha256 hex of what a table describes: :func:`cache_key`'s inputs without the
    :data:`QUALITY_SETTINGS` (``settings`` as :meth:`BakeSettings.result_inputs` gives them,
    or as a table header records them)."""
    return _digest(geometry_inputs, variant, {k: v for k, v in settings.items() if k not in QUALITY_SETTINGS})


def serves(header: dict[str, Any], settings: BakeSettings) -> bool:
    """Whether a table with ``header`` (of the same physics) is at least as good as a bake
    with ``settings``: a grid as fine or finer, and as many photons per direction (with a
    target error: an error estimate at or below it, or the photon cap reached)."""
    try:
        res = float(header["bake"]["settings"]["resolution_deg"])
        least = int(header["photons"]["min_per_direction"])
        worst = float(header.get("error_estimate", {}).get("max", math.inf))
    except (KeyError, TypeError, ValueError):
        return False
    if res > settings.resolution_deg * (1 + 1e-9):
        return False
    if settings.target_error is None:
        return least >= settings.photons
    return worst <= settings.target_error or least >= settings.max_photons


def load_or_make(load: Callable[[], T | None], lock: Callable[[], ContextManager[Any]],
                 make: Callable[[], T], *, make_missing: bool = True) -> tuple[T | None, bool]:
    """``(value, made)``: ``load()`` if it finds the value, else ``make()`` under ``lock()``.

    Double-checked: the first ``load()`` runs without the lock (the common, cached case);
    after taking the lock it runs again, because another process may have made the value
    while this one waited, and only then ``make()`` runs (it also stores the value). With
    ``make_missing=False`` a missing value gives ``(None, False)`` and no lock is taken.
    """
    value = load()
    if value is not None or not make_missing:
        return value, False
    with lock():
        value = load()
        if value is not None:
            return value, False
        return make(), True


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
        """The cache key of a request baked with ``settings`` (:func:`cache_key`)."""
        return cache_key(request.inputs, request.variant, settings)

    def table_path(self, key: str) -> Path:
        """Where the finished table of ``key`` is kept."""
        return self.root / "tables" / f"{key}.npz"

    def partial_dir(self, key: str) -> Path:
        """The resume directory of an unfinished bake of ``key``."""
        return self.root / "partial" / key

    def lock_path(self, key: str) -> Path:
        """The lock file of ``key``."""
        return self.root / "locks" / f"{key}.lock"

    # ---- lookups -------------------------------------------------------------------------------
    def load(self, key: str) -> BcsdfTable | None:
        """The cached table of ``key``, verified; None when absent or unusable.

        A damaged file (truncated, corrupt, checksum mismatch, foreign layout) is reported
        with a TableCacheWarning naming it and the reason, and deleted.
        """
        # A table names its key (a file without one, or renamed, serves no key).
        return self.load_verified(self.table_path(key), BcsdfTable.load,
                                  lambda t: t.header.get("cache_key") == key)

    def find_serving(self, request: TableRequest, settings: BakeSettings) -> str | None:
        """The key of a cached table that serves ``request`` baked with ``settings``: its own
        key when that table exists, else another table of the same physics at least as good
        (:func:`serves`; the coarsest such grid, then the fewest photons). Reads the headers of
        the cached tables (about a millisecond each), not their arrays."""
        key = self.key(request, settings)
        if self.contains(key):
            return key
        want = physics_key(request.inputs, request.variant, settings.result_inputs())
        best: tuple[tuple[float, int], str] | None = None
        try:
            files = sorted((self.root / "tables").glob("*.npz"))
        except OSError:
            return None
        for path in files:
            try:
                h = table_format.read_header(path)
                other = h["bake"]["settings"]
                if (h.get("cache_key") != path.stem or h.get("variant") != request.variant
                        or physics_key(h.get("inputs"), h["variant"], other) != want
                        or _digest(h.get("inputs"), h["variant"], other) != path.stem
                        or not serves(h, settings)):
                    continue
                rank = (-float(other["resolution_deg"]), int(h["photons"]["min_per_direction"]))
            except (table_format.TableError, OSError, KeyError, TypeError, ValueError):
                continue  # damaged or foreign files are reported when their own key is loaded
            if best is None or rank < best[0]:
                best = (rank, path.stem)
        return None if best is None else best[1]

    def load_verified(self, path: Path, read: Any, written_for_key: Any, redo: str = "baking it again") -> Any:
        """``read(path)`` when the file exists, reads cleanly and ``written_for_key(result)``;
        otherwise None, and a damaged file is reported (TableCacheWarning: the file, the
        reason, ``redo``) and deleted. For every kind of file kept under this cache."""
        if not path.exists():
            return None
        if path.is_dir():
            raise TableCacheError(f"{path}: is a directory, where the cache keeps a file; remove it "
                                  f"(the table cache is {self.root})")
        try:
            obj = read(path)
            if not written_for_key(obj):
                raise TableLayoutError(f"{path}: written for another cache key")
            return obj
        except PermissionError as exc:
            raise TableCacheError.of(exc, self.root) from None
        except (table_format.TableError, TableLayoutError, KeyError, ValueError) as exc:
            reason = exc.reason if isinstance(exc, table_format.TableError) else str(exc)
            if reason.startswith(str(path)):
                reason = reason[len(str(path)):].lstrip(": ")
            warnings.warn(f"{path}: {reason}; {redo}", TableCacheWarning, stacklevel=3)
            try:
                path.unlink()
            except OSError:  # gone, or a read-only cache: it is not used either way
                pass
            return None

    def contains(self, key: str) -> bool:
        """Whether a table file exists for ``key`` (it is verified when loaded)."""
        return self.table_path(key).exists()

    def compress_entry(self, key: str, bound: float) -> BcsdfTable | None:
        """The cached table of ``key`` in the compressed layout (:mod:`usdfiber.bake.compression`,
        every direction within ``bound`` relative L2 of p), compressed in place under the key's
        lock when it is not already (one compressed at any bound is left as it is). None when
        the key has no usable table. Raises CompressionError (the file is then left as it was)."""
        if not self.contains(key):
            return None
        try:
            with self.lock(key):
                table = self.load(key)
                if table is None or table.compressed:
                    return table
                small = table.compress(bound)
                small.save(self.table_path(key))
                return small
        except OSError as exc:
            raise TableCacheError.of(exc, self.root) from None

    def lock(self, key: str, timeout: float = -1):
        """The key's inter-process lock (a ``filelock.FileLock``; use as a context manager)."""
        from filelock import FileLock

        p = self.lock_path(key)
        p.parent.mkdir(parents=True, exist_ok=True)
        return FileLock(str(p), timeout=timeout)

    # ---- baking ---------------------------------------------------------------------------------
    def get_or_bake(self, request: TableRequest, settings: BakeSettings | None = None,
                    progress: ProgressFn | None = None, *, bake_missing: bool = True,
                    compress: float | None = None) -> CacheResult | None:
        """The table of ``request`` from the cache, baking it (under the key's lock) if needed.

        ``compress``: keep the table compressed within this bound (relative L2 of p per
        direction): a baked table is compressed before it is stored, a cached uncompressed one
        is compressed in place (:meth:`compress_entry`). A table the bound cannot hold is kept
        uncompressed, with a TableCacheWarning. Returns None only when ``bake_missing`` is
        False and the table is not cached.
        """
        st = settings or BakeSettings()
        key = self.key(request, st)
        t0 = time.perf_counter()
        resumed = 0
        served = key

        def prog(done: int, total: int, info: dict) -> None:
            nonlocal resumed
            if info.get("event") == "start":
                resumed = int(info.get("resumed", 0))
                info = {**info, "label": request.label}
            if progress is not None:
                progress(done, total, info)

        def load() -> BcsdfTable | None:
            nonlocal served
            table = self.load(key)
            if table is None:
                # Another table of the same physics at least as good (e.g. made by `usdfiber
                # bake` with other batches or a finer grid) serves this request too.
                other = self.find_serving(request, st)
                if other is not None and other != key:
                    table = self.load(other)
                    served = other if table is not None else key
            return table

        def make() -> BcsdfTable:
            pdir = self.partial_dir(key)
            path = self.table_path(key)
            path.parent.mkdir(parents=True, exist_ok=True)  # a cache it cannot write fails before tracing
            table = bake_request(request, st, prog, resume_dir=pdir)
            table.header["cache_key"] = key
            if compress is not None:
                table = self._compressed_or_kept(table, compress, path)
            table.save(path)
            shutil.rmtree(pdir, ignore_errors=True)
            return table

        try:
            table, baked = load_or_make(load, lambda: self.lock(key), make, make_missing=bake_missing)
        except OSError as exc:  # read-only or full disk, a directory or file in the wrong place
            raise TableCacheError.of(exc, self.root) from None
        if table is None:
            return None
        if compress is not None and not table.compressed:
            small = self._compressed_or_kept(table, compress, self.table_path(served), in_place=served)
            table = small if small is not None else table
        return CacheResult(served, self.table_path(served), table, baked, time.perf_counter() - t0,
                           resumed if baked else 0)

    def _compressed_or_kept(self, table: BcsdfTable, bound: float, path: Path,
                            in_place: str | None = None) -> BcsdfTable | None:
        """``table`` compressed within ``bound`` (stored in place under the key ``in_place``
        when given), or, when the bound cannot hold, a TableCacheWarning and ``table`` itself
        (None for an in-place entry gone meanwhile)."""
        from usdfiber.bake.compression import CompressionError

        try:
            if in_place is not None:
                return self.compress_entry(in_place, bound)
            return table.compress(bound)
        except CompressionError as exc:
            why = str(exc).split(": ", 1)[1] if str(exc).startswith((f"{path}: ", "table: ")) else str(exc)
            warnings.warn(f"{path}: cannot be compressed within {bound:g} ({why}); kept uncompressed",
                          TableCacheWarning, stacklevel=3)
            return table

    def clear_partial(self, key: str) -> None:
        """Remove the resume directory of ``key``."""
        shutil.rmtree(self.partial_dir(key), ignore_errors=True)
