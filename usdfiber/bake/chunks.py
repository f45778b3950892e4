"""Resume chunks: the finished incoming directions of a bake, one file each.

A bake given a resume directory (the cache's ``partial/<key>/``, or a large bake's scratch
directory) writes every finished incoming direction there before the next group starts, so
an interruption loses at most the group in flight. The directory holds:

* ``bake.json``: the bake's inputs and settings (its *fingerprint*, canonical JSON). A bake
  with another fingerprint removes the chunks it finds: they cannot be reused.
* ``d<ti>_<pi>.npz``: one chunk per direction, a :mod:`usdfiber.table_format` container of
  format :data:`CHUNK_FORMAT` (written atomically and uncompressed, a checksum per array)
  whose header names the bake key (sha256 of the fingerprint) and the direction ``[ti, pi]``; arrays ``rows``
  (the theta_o rows held), ``H`` and ``G`` (the sums of ``exp(-s_k L)`` and ``L exp(-s_k L)``
  per bin and level, :mod:`usdfiber.bake.statistics`) and ``scalars`` (:data:`SCALARS`).

:meth:`ResumeDirectory.load` is the one loader, and it verifies: a chunk that is unreadable,
damaged, of another bake or of another direction, or whose sums are not finite non-negative
floats of the bake's histogram size, is reported (a RuntimeWarning naming the file and the
reason) and its direction is traced again. :meth:`ResumeDirectory.load_scalars` is the same
loader reading a chunk's scalars alone (photons, error, seconds: what reports over a whole
bake need), with the same checks of what it reads.
"""
from __future__ import annotations

import hashlib
import json
import os
import tempfile
import warnings
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from usdfiber import table_format

__all__ = ["CHUNK_COMPRESS", "CHUNK_FORMAT", "SCALARS", "ResumeDirectory", "chunk_name"]

#: The container format name of a chunk file.
CHUNK_FORMAT = "usdfiber-bake-chunk"
#: The per-direction numbers of a chunk's ``scalars`` array, in order.
SCALARS = ("norm", "photons", "n_hit", "n_cut", "leaks", "misses", "rel_error", "seconds")
_INTEGER_SCALARS = ("photons", "n_hit", "n_cut", "leaks")
#: How chunks are written (``table_format.write_table``'s ``compress``): stored. Deflate (level
#: 6 or 1 alike) shrinks a chunk's float32 sums only to 0.6-0.7 and took 2.6 s per group of 64
#: 2 deg directions against 0.36 s stored (reads 0.6 against 0.26 s), 1-4 % of the group's
#: tracing; chunks are scratch, removed once the table is cached (bench/REPORT.md, section 7).
CHUNK_COMPRESS: bool | int = False


def chunk_name(ti: int, pi: int) -> str:
    """File name of the chunk of incoming node (ti, pi)."""
    return f"d{ti:04d}_{pi:04d}.npz"


class ResumeDirectory:
    """The chunks of one bake in ``path`` (created; chunks of another bake are removed)."""

    def __init__(self, path: str | os.PathLike[str], fingerprint: Mapping[str, Any],
                 histogram: tuple[int, int, int] | None = None) -> None:
        self.path = Path(path)
        #: how chunks are written (:data:`CHUNK_COMPRESS`); any is read.
        self.compress: bool | int = CHUNK_COMPRESS
        #: (levels, theta_o rows, phi_o columns) of the bake's histograms, when known: a
        #: chunk's H and G must fit them.
        self.histogram = histogram
        text = json.dumps(fingerprint, sort_keys=True)
        #: sha256 of the fingerprint: every chunk names it.
        self.key = hashlib.sha256(text.encode("utf-8")).hexdigest()
        self._prepare(text)

    def _prepare(self, text: str) -> None:
        self.path.mkdir(parents=True, exist_ok=True)
        meta = self.path / "bake.json"
        if meta.exists():
            try:
                old = meta.read_text()
            except OSError:
                old = ""
            if old == text:
                return
            # Another bake's chunks: they cannot be reused.
            for f in self.path.glob("d*_*.npz"):
                f.unlink(missing_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".bake.", suffix=".tmp", dir=self.path)
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, meta)

    def chunk_path(self, ti: int, pi: int) -> Path:
        """Where the chunk of (ti, pi) is kept."""
        return self.path / chunk_name(ti, pi)

    def has(self, ti: int, pi: int) -> bool:
        """Whether a chunk file exists for (ti, pi) (it is verified when loaded)."""
        return self.chunk_path(ti, pi).exists()

    def save(self, ti: int, pi: int, data: Mapping[str, Any]) -> None:
        """Write the finished direction ``data`` atomically (the mapping of
        :meth:`~usdfiber.bake.statistics.DirectionStatistics.result`)."""
        arrays = {
            "rows": np.asarray(data["rows"], dtype=np.int64),
            "H": data["H"], "G": data["G"],
            "scalars": np.array([data[k] for k in SCALARS], dtype=np.float64),
        }
        header = {"bake_key": self.key, "direction": [int(ti), int(pi)], "scalars": list(SCALARS)}
        table_format.write_table(self.chunk_path(ti, pi), header, arrays, container=CHUNK_FORMAT,
                                 compress=self.compress)

    def load(self, ti: int, pi: int) -> dict[str, Any] | None:
        """The chunk of (ti, pi), verified; None (with a RuntimeWarning) when it cannot be used."""
        return self._load(ti, pi, histograms=True)

    def load_scalars(self, ti: int, pi: int) -> dict[str, Any] | None:
        """The :data:`SCALARS` of the chunk of (ti, pi) alone, verified as :meth:`load` verifies
        them (the bake, the direction, the scalars' checksum and values); None (with a
        RuntimeWarning) when the chunk cannot be used. Its histograms stay on disk: reports over
        a whole bake need not read them (10 GB for a 2 deg table)."""
        return self._load(ti, pi, histograms=False)

    def _load(self, ti: int, pi: int, histograms: bool) -> dict[str, Any] | None:
        path = self.chunk_path(ti, pi)
        try:
            header, z = table_format.read_table(path, container=CHUNK_FORMAT,
                                                names=None if histograms else ("scalars",))
            if header.get("bake_key") != self.key:
                raise ValueError("written by another bake")
            if header.get("direction") != [int(ti), int(pi)]:
                raise ValueError(f"holds direction {header.get('direction')}, not {[ti, pi]}")
            sc = z["scalars"]
            rows = tuple(int(x) for x in z["rows"]) if histograms else None
            if sc.shape != (len(SCALARS),) or (rows is not None and len(rows) != 2):
                raise ValueError("scalars or rows have the wrong length")
            if rows is not None and (z["H"].shape != z["G"].shape or z["H"].ndim != 3
                                     or z["H"].shape[1] != rows[1] - rows[0]):
                raise ValueError("rows and H disagree")
            self._check_values(rows, z)
        except (table_format.TableError, KeyError, ValueError, IndexError) as exc:
            reason = exc.reason if isinstance(exc, table_format.TableError) else str(exc)
            then = "tracing that direction again" if histograms else "not used"
            warnings.warn(f"{path}: unusable partial bake chunk ({reason}); {then}", RuntimeWarning, stacklevel=3)
            return None
        data: dict[str, Any] = {"rows": rows, "H": z["H"], "G": z["G"]} if rows is not None else {}
        for name, value in zip(SCALARS, sc):
            data[name] = int(value) if name in _INTEGER_SCALARS else float(value)
        return data

    def _check_values(self, rows: tuple[int, int] | None, z: Mapping[str, np.ndarray]) -> None:
        """ValueError where a chunk whose checksums hold cannot be a direction of this bake:
        histograms of another size, or sums or counts that are NaN, infinite or negative (the
        error estimate may be infinite: no light left that direction). ``rows`` None: the
        scalars alone were read."""
        if self.histogram is not None and rows is not None:
            levels, n_rows, n_cols = self.histogram
            if not (0 <= rows[0] < rows[1] <= n_rows) or z["H"].shape[::2] != (levels, n_cols):
                raise ValueError(f"H has shape {z['H'].shape} at rows {list(rows)}, "
                                 f"not ({levels}, rows, {n_cols}) within {n_rows} rows")
        for name in ("H", "G", "scalars") if rows is not None else ("scalars",):
            a = z[name]
            values = np.delete(a, SCALARS.index("rel_error")) if name == "scalars" else a
            if a.dtype.kind != "f" or not np.all(np.isfinite(values)) or (a.size and np.nanmin(a) < 0):
                raise ValueError(f"{name} holds values that are not finite non-negative floats")
