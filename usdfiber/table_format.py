"""On-disk container of a baked BCSDF table (format version 1).

A table is a NumPy ``.npz`` archive (a zip of ``.npy`` files, readable with ``numpy.load``
without pickling) holding:

* ``header``: a 1-D ``uint8`` array, the UTF-8 bytes of a JSON object::

      {
        "format": "usdfiber-bcsdf",          # identifies the container
        "version": 1,                        # this layout
        "geometry_key": "<sha256 hex>",      # FiberParams.geometry_key() of the traced fiber
        "inputs": {...},                     # FiberParams geometry inputs, with "units"
        "resolution": ...,                   # baker-defined (e.g. bin counts per axis)
        "photons": ...,                      # photons traced (per direction or total: baker-defined)
        "error_estimate": ...,               # baker-defined estimate of the table's noise
        "created": "2026-01-01T00:00:00+00:00",  # ISO 8601, UTC
        "arrays": {"<name>": {"dtype": "<f4", "shape": [..]}, ...},
        "checksums": {"<name>": "<sha256 hex of the array's C-order bytes>", ...}
      }

  Read it with ``json.loads(numpy.load(path)["header"].tobytes().decode("utf-8"))``.
  Further keys are allowed and kept.
* one entry per named array. What the arrays mean is defined by the baker, not here.

Writes are atomic: the archive is written to a temporary file in the target's directory,
flushed and fsynced, then renamed over the target with ``os.replace``; a crash leaves either
the old file or the new one at the target path, never a partial one.

Reading verifies the container and raises :class:`TableError` whose message says why:
``missing``, ``not a usdfiber table``, ``truncated or corrupt: ...``,
``checksum mismatch for array X`` or ``unsupported version N``.

The same container, under another ``format`` name (the ``container`` argument), holds the
baker's resume chunks (:mod:`usdfiber.bake.chunks`); yarn far fields are tables with their
own ``kind``. What the arrays of a BCSDF table mean: :mod:`usdfiber.bake.storage`.
"""
from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import re
import zipfile
import zlib
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from usdfiber.atomic_file import write_atomic

try:  # ISA-L's deflate: the same format, written about 9x faster than zlib's at level 1
    from isal import isal_zlib as _isal_zlib
except ImportError:  # pragma: no cover - a declared dependency; zlib writes the same format
    _isal_zlib = None

FORMAT = "usdfiber-bcsdf"
VERSION = 1
HEADER_ENTRY = "header"
REQUIRED_HEADER_KEYS = ("geometry_key", "inputs", "resolution", "photons", "error_estimate")
_ZIP_MAGIC = b"PK\x03\x04"
_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
#: zlib level of ``compress=True``. Level 1: on a baked table's float16 arrays it wrote 1.5x
#: faster than zlib's default 6 (``numpy.savez_compressed``'s) into a file 2 % larger
#: (bench/REPORT.md, section 7, "The bake's files"). Written by ISA-L's level 1
#: (:data:`FAST_DEFLATE`).
DEFAULT_LEVEL = 1
#: Whether ``compress=True`` deflates with ISA-L (python-isal) instead of zlib: the same
#: deflate stream format, any zip reader reads it; on a full 2 deg table's float16 arrays
#: 650 MB/s against zlib's 68 MB/s at level 1, the file 2 % larger (bench/REPORT.md,
#: section 7, "The table's save with ISA-L").
FAST_DEFLATE = _isal_zlib is not None


def deflate(data: Any) -> bytes:
    """``data`` (bytes-like) as :func:`write_table` deflates an array at ``compress=True``
    (a raw deflate stream): what the array adds to a table file, e.g. for cost estimates."""
    if FAST_DEFLATE:
        return _isal_zlib.compress(data, 1, -15)
    return zlib.compress(data, DEFAULT_LEVEL, -15)


class TableError(ValueError):
    """A table file that cannot be used (or written); the message says why."""

    def __init__(self, path: str | os.PathLike[str], reason: str) -> None:
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{path}: {reason}")


def array_checksum(a: np.ndarray) -> str:
    """sha256 hex digest of an array's bytes in C order."""
    c = np.ascontiguousarray(a)
    if c.dtype.itemsize == 0:
        return hashlib.sha256(b"").hexdigest()
    # Hashed in place: a 2 deg table's p is 2.9 GB, and a copy of it (tobytes) was the
    # largest allocation of writing or reading a table.
    return hashlib.sha256(c.reshape(-1).view(np.uint8)).hexdigest()


def _json_default(o: Any) -> Any:
    # Bakers naturally hand over NumPy scalars and small arrays.
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"{type(o).__name__} is not JSON serializable")


def _what(container: str) -> str:
    """How messages name a file of ``container``."""
    return "usdfiber table" if container == FORMAT else f"{container} file"


def write_table(path: str | os.PathLike[str], header: Mapping[str, Any],
                arrays: Mapping[str, np.ndarray], *, compress: bool | int = True,
                container: str = FORMAT) -> dict[str, Any]:
    """Write a table atomically and return the full header written.

    ``compress``: True deflates at :data:`DEFAULT_LEVEL`, an int at that zlib level (1
    fastest, 9 smallest), False or 0 stores the arrays as they are; readers need not know.

    ``header`` must hold :data:`REQUIRED_HEADER_KEYS` (for tables: another ``container``
    name has no required keys); ``format`` (= ``container``), ``version``, ``arrays`` and
    ``checksums`` are filled in, ``created`` when absent. Array names are identifiers other
    than ``header``; object arrays are refused.
    """
    path = Path(path)
    required = REQUIRED_HEADER_KEYS if container == FORMAT else ()
    missing = [k for k in required if k not in header]
    if missing:
        raise TableError(path, f"cannot write: header lacks {', '.join(missing)}")
    clean: dict[str, np.ndarray] = {}
    for name, a in arrays.items():
        if not isinstance(name, str) or not _NAME_RE.match(name) or name == HEADER_ENTRY:
            raise TableError(path, f"cannot write: invalid array name {name!r}")
        a = np.asarray(a)
        if a.dtype.hasobject:
            raise TableError(path, f"cannot write: array {name} has dtype object")
        clean[name] = a

    full = dict(header)
    full["format"] = container
    full["version"] = VERSION
    full.setdefault("created", _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"))
    full["arrays"] = {n: {"dtype": a.dtype.str, "shape": list(a.shape)} for n, a in clean.items()}
    full["checksums"] = {n: array_checksum(a) for n, a in clean.items()}
    try:
        text = json.dumps(full, sort_keys=True, default=_json_default, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise TableError(path, f"cannot write: header is not JSON: {exc}") from exc
    header_bytes = np.frombuffer(text.encode("utf-8"), dtype=np.uint8)

    save_npz_atomic(path, {HEADER_ENTRY: header_bytes, **clean}, compress=compress)
    return full


def save_npz_atomic(path: str | os.PathLike[str], arrays: Mapping[str, np.ndarray], *,
                    compress: bool | int = True) -> None:
    """Write ``arrays`` as an .npz at ``path`` so that readers see the old file or the new
    one, never a partial one: a temporary file in the same directory, fsync, rename, fsync
    of the directory. A failure (or Ctrl-C) leaves no temporary file behind. ``compress``:
    as :func:`write_table`."""
    if isinstance(compress, (bool, np.bool_)):
        level = DEFAULT_LEVEL if compress else 0
    elif isinstance(compress, (int, np.integer)):
        level = int(compress)
    else:
        level = -1
    if not 0 <= level <= 9:
        raise ValueError(f"compress={compress!r}: expected True, False or a zlib level 0-9")

    def write(tmp: str) -> None:
        # numpy.savez's layout (one .npy entry per array), with the zlib level ours to set.
        method = zipfile.ZIP_DEFLATED if level else zipfile.ZIP_STORED
        with open(tmp, "wb") as f, zipfile.ZipFile(f, "w", compression=method, compresslevel=level or None,
                                                   allowZip64=True) as zf:
            for name, a in arrays.items():
                with zf.open(name + ".npy", "w", force_zip64=True) as entry:
                    if level == DEFAULT_LEVEL and FAST_DEFLATE and hasattr(entry, "_compressor"):
                        # zipfile takes no compressor of ours; its entry writer calls only
                        # compress() and flush() of this object (raw deflate, as its own).
                        entry._compressor = _isal_zlib.compressobj(1, _isal_zlib.DEFLATED, -15)
                    np.lib.format.write_array(entry, np.asanyarray(a), allow_pickle=False)

    write_atomic(path, write)


def _open(path: Path, container: str):
    what = _what(container)
    if not path.exists():
        raise TableError(path, "missing")
    if not path.is_file():
        raise TableError(path, f"not a {what} (not a regular file)")
    with open(path, "rb") as f:
        magic = f.read(len(_ZIP_MAGIC))
    if not magic:
        raise TableError(path, "truncated or corrupt: empty file")
    if magic != _ZIP_MAGIC:
        if _ZIP_MAGIC.startswith(magic):
            raise TableError(path, f"truncated or corrupt: only {len(magic)} bytes")
        raise TableError(path, f"not a {what} (not an .npz archive)")
    try:
        return np.load(path, allow_pickle=False)
    except Exception as exc:  # zipfile.BadZipFile, EOFError, OSError, ValueError, ...
        raise TableError(path, f"truncated or corrupt: {exc}") from exc


def _read_entry(path: Path, z, name: str) -> np.ndarray:
    try:
        return z[name]
    except Exception as exc:  # bad CRC, zlib errors, short reads, bad .npy headers
        raise TableError(path, f"truncated or corrupt: cannot read {name}: {exc}") from exc


def _header(path: Path, z, container: str) -> dict[str, Any]:
    what = _what(container)
    if HEADER_ENTRY not in z.files:
        raise TableError(path, f"not a {what} (no header entry)")
    raw = _read_entry(path, z, HEADER_ENTRY)
    if raw.dtype != np.uint8 or raw.ndim != 1:
        raise TableError(path, f"not a {what} (header is not UTF-8 bytes)")
    try:
        header = json.loads(raw.tobytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise TableError(path, f"not a {what} (header is not UTF-8 JSON: {exc})") from exc
    if not isinstance(header, dict) or header.get("format") != container:
        raise TableError(path, f"not a {what} (format is not {container!r})")
    version = header.get("version")
    if version != VERSION or isinstance(version, bool):
        raise TableError(path, f"unsupported version {version} (this usdfiber reads version {VERSION})")
    if not isinstance(header.get("checksums"), dict) or not isinstance(header.get("arrays"), dict):
        raise TableError(path, "truncated or corrupt: header lacks checksums or arrays")
    return header


def _arrays(path: Path, z, header: dict[str, Any],
            names: Iterable[str] | None = None) -> dict[str, np.ndarray]:
    checksums: dict[str, str] = header["checksums"]
    meta: dict[str, Any] = header["arrays"]
    listed = set(checksums)
    present = set(z.files) - {HEADER_ENTRY}
    if listed - present:
        name = sorted(listed - present)[0]
        raise TableError(path, f"truncated or corrupt: array {name} listed in the header is missing")
    if present - listed:
        name = sorted(present - listed)[0]
        raise TableError(path, f"truncated or corrupt: array {name} is not listed in the header")
    wanted = listed if names is None else set(names)
    if wanted - listed:
        raise TableError(path, f"truncated or corrupt: no array {sorted(wanted - listed)[0]}")
    out: dict[str, np.ndarray] = {}
    for name in sorted(wanted):
        a = _read_entry(path, z, name)
        m = meta.get(name, {})
        if m.get("dtype") != a.dtype.str or list(m.get("shape", [])) != list(a.shape):
            raise TableError(path, f"checksum mismatch for array {name} (dtype/shape differ from the header)")
        if array_checksum(a) != checksums[name]:
            raise TableError(path, f"checksum mismatch for array {name}")
        out[name] = a
    return out


def read_header(path: str | os.PathLike[str], *, verify: bool = False,
                container: str = FORMAT) -> dict[str, Any]:
    """The header of a table, after checking the container, format and version.

    Cheap: arrays are not read. ``verify=True`` also checks every array's checksum.
    """
    p = Path(path)
    z = _open(p, container)
    with z:
        header = _header(p, z, container)
        if verify:
            _arrays(p, z, header)
    return header


def read_table(path: str | os.PathLike[str], *, container: str = FORMAT,
               names: Iterable[str] | None = None) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """``(header, arrays)`` of a table (or of a file of another ``container`` name), with
    format, version and every checksum verified. ``names``: read (and verify) only these
    arrays; the others are left on disk (the header still has to list exactly what is there)."""
    p = Path(path)
    z = _open(p, container)
    with z:
        header = _header(p, z, container)
        arrays = _arrays(p, z, header, names)
    return header, arrays


__all__ = ["DEFAULT_LEVEL", "FORMAT", "REQUIRED_HEADER_KEYS", "TableError", "VERSION", "array_checksum",
           "read_header", "read_table", "save_npz_atomic", "write_table"]
