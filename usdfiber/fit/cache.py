"""Fits cached beside their tables, keyed like the tables (``usdfiber.bake.cache``).

Location: a table at ``<root>/tables/<key>.npz`` (the table cache) has its fits in
``<root>/fits/``; any other table file ``<dir>/<name>.npz`` in ``<dir>/fits/``. One JSON
file per fit, ``<fit key>.json``.

The fit key is the sha256 of the canonical JSON of: the identities of the tables fitted (a
table's cache key, else the sha256 of its arrays' checksums), the effective absorption per
channel they were recoloured for (1/um at the baked size, 12 significant digits), the model,
the fit settings (:meth:`FitSettings.key_inputs`) and :data:`FIT_VERSION`. Anything that
changes a fit changes its key, so a stale fit is never found.

Files are written atomically and read by one verified loader (:meth:`FitCache.load`): the
format, the version, the key and a sha256 of the body must match; a damaged file is
reported (a ``TableCacheWarning`` naming it and the reason), deleted and fitted again.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any, Sequence

from usdfiber.atomic_file import write_atomic
from usdfiber.bake.cache import TableCache
from usdfiber.fit.result import FitResult, FitSettings
from usdfiber.table_format import array_checksum

__all__ = ["FIT_FORMAT", "FIT_VERSION", "FitCache", "fit_key", "table_identity"]

FIT_FORMAT = "usdfiber-fit"
#: Bumped whenever a model, the objective or the solver changes results.
FIT_VERSION = 1


def table_identity(table: Any) -> str:
    """A table's cache key, else the sha256 of its arrays' checksums (stable across copies)."""
    key = table.header.get("cache_key")
    if key:
        return str(key)
    sums = table.header.get("checksums") or {n: array_checksum(a) for n, a in sorted(table.arrays.items())}
    blob = json.dumps(sums, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(blob.encode("utf-8")).hexdigest()


def fit_key(table_ids: Sequence[str], sigma_a: Sequence[float], model: str, settings: FitSettings) -> str:
    """sha256 hex of (tables, effective absorption, model, settings, fit version)."""
    blob = json.dumps({
        "tables": list(table_ids),
        "sigma_a": [float(f"{float(s):.12g}") for s in sigma_a],
        "model": model,
        "settings": settings.key_inputs(),
        "fit_version": FIT_VERSION,
    }, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(blob.encode("utf-8")).hexdigest()


def _body_checksum(body: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":")).encode("utf-8")).hexdigest()


class FitCache:
    """The fits under one directory (module docstring)."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)

    @classmethod
    def beside(cls, table: Any) -> "FitCache | None":
        """The fit directory beside ``table``'s file; None for a table never saved."""
        if not getattr(table, "path", None):
            return None
        p = Path(table.path)
        base = p.parent.parent if p.parent.name == "tables" else p.parent
        return cls(base / "fits")

    def path(self, key: str) -> Path:
        return self.root / f"{key}.json"

    def load(self, key: str) -> FitResult | None:
        """The verified fit of ``key``; None when absent or damaged (then reported and deleted)."""
        def read(path: Path) -> FitResult:
            try:
                doc = json.loads(path.read_text(encoding="utf-8"))
            except (OSError, UnicodeDecodeError) as exc:
                raise ValueError(f"unreadable ({exc})") from None
            if not isinstance(doc, dict) or doc.get("format") != FIT_FORMAT:
                raise ValueError("not a usdfiber fit")
            if doc.get("version") != FIT_VERSION:
                raise ValueError(f"fit version {doc.get('version')} (this usdfiber writes {FIT_VERSION})")
            body = doc.get("fit")
            if not isinstance(body, dict) or doc.get("checksum") != _body_checksum(body):
                raise ValueError("checksum mismatch")
            try:
                return FitResult.from_json(body)
            except (KeyError, TypeError, ValueError) as exc:
                raise ValueError(f"malformed fit ({exc})") from None

        res = TableCache(self.root).load_verified(self.path(key), read, lambda r: r.key == key,
                                                  redo="fitting it again")
        if res is not None:
            res.cached = True
        return res

    def save(self, result: FitResult) -> Path:
        body = result.to_json()
        doc = {"format": FIT_FORMAT, "version": FIT_VERSION, "fit": body, "checksum": _body_checksum(body)}
        text = json.dumps(doc, indent=1, sort_keys=True, allow_nan=False)
        path = self.path(result.key)
        path.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(path, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))
        return path
