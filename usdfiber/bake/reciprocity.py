"""Reciprocity averaging: each entry of a box-filtered table estimated from both of its halves.

The scattering cross-section sigma(i, o) = W(phi_i) cos(theta_i) Lambda(i) p(o | i) is
symmetric (Helmholtz reciprocity; the convention: :mod:`usdfiber.bcsdf`). A box-filtered bake
(``BakeSettings(incoming="box")``) spreads each incoming node's light uniformly in solid
angle over its bin, so the histogram sum ``H[I, O]`` of node ``I`` and outgoing bin ``O``
(:mod:`usdfiber.bake.statistics`, with ``B_I`` batches) is an unbiased estimate of

    S(I, O) / |I|,   S(I, O) = integral over I and O of sigma(i, o) di do,

and S(I, O) = S(O, I) exactly: the grid's nodes are its bin centres, so the partner (O as the
incoming bin, I as the outgoing one) is another entry of the same table. Where theta_i >= 0
only is stored (extruded fibers), the partner of a bin with theta_o < 0 is found through the
z-mirror; for rotationally symmetric tables (one phi_i node) through the rotation.

The two estimates are independent when every direction has its own random streams
(:func:`usdfiber.bake.sampling.stream_seed`), and a histogram bin's variance is that of a
Poisson count: Var[|I| H / B] = c_I S with c_I = |I| <W cos>_I / N_I (N_I photons that met
the fiber, <W cos>_I the mean batch weight). The weights lambda_I = c_P / (c_I + c_P) come from
the photon counts only, never from the histograms (weights estimated from the same bins
would correlate with them: a bias); the combined estimate has variance c_I c_P / (c_I + c_P)
S, half of either side's when both have the same photons. Absorption keeps the symmetry at
every level, so the ``G`` sums (path-length moments) are combined with the same weights.
Each direction's total per level is then restored to its own estimate: the albedo is the
direction's (1 at zero absorption, the furnace) and the averaging shapes p, which the table
stores normalized per direction anyway (a ratio: its bias is O(1/N), far below the noise).

The averaging streams (:class:`ReciprocalAverage`): each direction's H and G go to scratch
files, laid out level by level, as the direction is traced (a bake adds each group while the
next one traces) or read from its chunk; then one absorption level of every
direction at a time is read back, averaged (one theta_i node's partners at a time, on as
many threads as the memory budget holds, ``ReciprocalAverage.threads``) and written over
itself; the averaged directions are read out one at a time. It holds one level of the table
in memory (:func:`usdfiber.bake.settings.reciprocity_bytes`: 1.2 GB for a 2 deg table with
one thread, 1.4 GB with two, against 11.5 GB for all 11 levels) and needs the whole table's
H and G on disk (:func:`scratch_bytes`); :func:`check_memory` refuses a bake, before
tracing, where either does not fit. An averaging holds a lock on its H file while it is open,
so a bake killed before it removed its scratch files leaves them unlocked, and the next
averaging in that directory removes them (:func:`remove_stale_scratch`).
"""
from __future__ import annotations

import math
import os
import shutil
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import IO, Any, Mapping

import numpy as np

try:
    import fcntl
except ImportError:   # no flock (Windows)
    fcntl = None  # type: ignore[assignment]

from usdfiber.bake.grid import Grid
from usdfiber.bake.settings import RECIPROCITY_THREADS, BakeError, reciprocity_bytes
from usdfiber.memory_budget import BUDGET_ENV, MemoryBudget, format_bytes

__all__ = ["SCRATCH_PREFIX", "ReciprocalAverage", "check_grid", "check_memory", "chunk_bytes", "incoming_measure", "node_partners", "node_weights", "partner_bins",
           "reciprocal_average", "remove_stale_scratch", "scratch_bytes"]


def check_grid(grid: Grid) -> None:
    """Raise BakeError when ``grid``'s incoming nodes are not its bin centres: an entry's
    reciprocal partner is then no entry of the table."""
    if grid.incoming_deg is not None:
        raise BakeError(f"reciprocity averaging needs incoming nodes at the bin centres; this grid has "
                        f"{grid.resolution_deg:g} deg bins and {grid.incoming_deg:g} deg incoming nodes: "
                        "bake it without the 'reciprocity' estimator or without incoming_deg")


def scratch_bytes(grid: Grid, n_levels: int) -> int:
    """Disk bytes of the averaging's scratch files: H and G of every direction, float32."""
    return 2 * 4 * grid.n_theta_i * grid.n_phi_i * grid.n_theta_o * grid.n_phi_o * int(n_levels)


#: The prefix of an averaging's scratch directory inside its ``scratch`` directory.
SCRATCH_PREFIX = ".usdfiber-reciprocity-"
#: A scratch directory without its H file is left alone for this long (seconds): its owner may
#: be between making it and naming the locked file (it holds no data before).
_UNLOCKED_GRACE_S = 3600.0


def _lock(f: IO[bytes]) -> bool:
    """Take the exclusive advisory lock of open file ``f`` without waiting: True when taken (or
    where the platform has no ``flock``: then nothing is ever found stale), False when another
    open file holds it. The lock lives as long as ``f`` is open, and dies with its process."""
    if fcntl is None:
        return True
    try:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    return True


def remove_stale_scratch(scratch: str | os.PathLike[str]) -> list[Path]:
    """Remove the averaging scratch directories in ``scratch`` that no live averaging holds: a
    bake killed before :meth:`ReciprocalAverage.close` (SIGKILL, power loss) leaves its H and
    G files (11.5 GB for a 2 deg table), and every averaging holds a lock on its H file while
    it is open. Returns the directories removed; those held, or unreadable, are left."""
    removed: list[Path] = []
    base = Path(scratch)
    if fcntl is None or not base.is_dir():   # without flock nothing is judged stale
        return removed
    for d in base.glob(SCRATCH_PREFIX + "*"):
        try:
            h = d / "H.f32"
            if h.exists():
                with open(h, "rb") as f:
                    if not _lock(f):
                        continue   # a live averaging
            elif time.time() - d.stat().st_mtime < _UNLOCKED_GRACE_S:
                continue           # being made, or too recent to judge
            shutil.rmtree(d)
            removed.append(d)
        except OSError:
            continue
    return removed


def _existing(path: Path) -> Path:
    """``path`` or its nearest existing parent (a resume directory may not exist yet)."""
    path = path.absolute()
    while not path.exists() and path.parent != path:
        path = path.parent
    return path


def chunk_bytes(grid: Grid, n_levels: int) -> int:
    """Disk bytes of one direction's resume chunk at most (:mod:`usdfiber.bake.chunks`, written
    without compression): H and G in float32 over every theta_o row, and its header."""
    return 2 * 4 * grid.n_theta_o * grid.n_phi_o * int(n_levels) + 8192


def check_memory(grid: Grid, n_levels: int, scratch: str | os.PathLike[str] | None = None,
                 budget: MemoryBudget | None = None, *, chunks: bool = False) -> None:
    """Raise BakeError (before anything is traced) when averaging a table of ``grid`` with
    ``n_levels`` absorption levels cannot be done: its grid has no reciprocal partners
    (:func:`check_grid`), one level's working set (:func:`usdfiber.bake.settings.reciprocity_bytes`)
    exceeds ``budget`` (default :meth:`MemoryBudget.resolve`), or the disk of ``scratch`` (the
    directory that will hold the scratch files; None: not checked) lacks :func:`scratch_bytes`,
    and with ``chunks`` (``scratch`` is also the bake's resume directory) the chunks it does not
    hold yet (:func:`chunk_bytes` each)."""
    check_grid(grid)
    what = (f"reciprocity averaging of a {grid.resolution_deg:g} deg table with "
            f"{grid.n_theta_i * grid.n_phi_i} directions")
    budget = budget if budget is not None else MemoryBudget.resolve()
    need = reciprocity_bytes(grid)
    if not budget.fits(need):
        raise BakeError(f"{what} needs about {format_bytes(need)} of memory (one absorption level at a time), "
                        f"more than the memory budget of {budget.describe()}: bake it without the 'reciprocity' "
                        f"estimator, at a coarser resolution, or raise ${BUDGET_ENV}")
    if scratch is not None:
        where = _existing(Path(scratch))
        disk, free = scratch_bytes(grid, n_levels), shutil.disk_usage(where).free
        if chunks:
            held = len(list(Path(scratch).glob("d*_*.npz"))) if Path(scratch).is_dir() else 0
            disk += max(0, grid.n_theta_i * grid.n_phi_i - held) * chunk_bytes(grid, n_levels)
        if disk > free:
            held_there = "scratch files and chunks" if chunks else "scratch files"
            raise BakeError(f"{what} needs {disk / 1e9:.1f} GB of disk in {where} for its {held_there} "
                            f"({free / 1e9:.1f} GB free): free space there, bake with a resume directory "
                            "(or TMPDIR) on a larger disk, or without the 'reciprocity' estimator")


def node_partners(grid: Grid, ti: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For every entry (pi, row, col) of theta_i node ``ti``, its reciprocal partner's
    (ti', pi', row', col'): four int64 arrays broadcastable to (n_phi_i, n_theta_o, n_phi_o).
    Only the node's own entries are formed (not the table's): the averaging works node by node.
    ``grid`` must have its incoming nodes at the bin centres (:func:`check_grid`)."""
    n_ti, n_pi, n_r, n_c = grid.n_theta_i, grid.n_phi_i, grid.n_theta_o, grid.n_phi_o
    pi = np.arange(n_pi, dtype=np.int64)[:, None, None]
    ro = np.arange(n_r, dtype=np.int64)[None, :, None]
    co = np.arange(n_c, dtype=np.int64)[None, None, :]
    if grid.theta_symmetric:
        # Node k is the centre of row n_ti + k; a row below the equator is mirrored (z -> -z).
        upper = ro >= n_ti
        pt = np.where(upper, ro - n_ti, n_ti - 1 - ro)
        pr = np.where(upper, n_ti + ti, n_ti - 1 - ti)
    else:
        pt, pr = ro, np.full((1, 1, 1), ti, dtype=np.int64)
    if grid.phi_invariant:
        # Rotate the partner's incoming direction onto the single node: I lands at -col.
        pp, pc = np.zeros((1, 1, 1), dtype=np.int64), (-co) % n_c
    else:
        pp, pc = co, pi
    return pt, pp, pr, pc


def partner_bins(grid: Grid) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For every entry (ti, pi, row, col), its reciprocal partner's (ti', pi', row', col').

    Four int64 arrays of shape (n_theta_i, n_phi_i, n_theta_o, n_phi_o) (:func:`node_partners`
    of every node). Applying the map twice gives the identity. BakeError for a grid with
    coarser incoming nodes (:func:`check_grid`).
    """
    check_grid(grid)
    shape = (grid.n_phi_i, grid.n_theta_o, grid.n_phi_o)
    nodes = [node_partners(grid, ti) for ti in range(grid.n_theta_i)]
    pt, pp, pr, pc = (np.stack([np.broadcast_to(p[j], shape) for p in nodes]) for j in range(4))
    return pt, pp, pr, pc


def node_weights(grid: Grid, ti: int, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The averaging of theta_i node ``ti``'s entries (n_phi_i, n_theta_o, n_phi_o): the flat
    index of each entry's partner in one level of the table laid out (theta_i, phi_i,
    theta_o, phi_o), and the weight lam of the entry's own estimate (the partner's gets
    1 - lam). ``c``: per direction (flat (theta_i, phi_i)) the Poisson constant |I| wbar / N
    of the module docstring, infinite where no photon met the fiber. lam = c_P / (c_I + c_P)
    (inverse variances); an entry that is its own partner keeps its estimate (lam = 1)."""
    n_pi, n_r, n_c = grid.n_phi_i, grid.n_theta_o, grid.n_phi_o
    pt, pp, pr, pc = node_partners(grid, ti)
    part = pt * n_pi + pp                                       # the partner's direction
    flat = np.broadcast_to((part * n_r + pr) * n_c + pc, (n_pi, n_r, n_c))
    own = ti * n_pi + np.arange(n_pi)
    self_pair = flat == (own[:, None, None] * n_r + np.arange(n_r)[:, None]) * n_c + np.arange(n_c)
    cI, cQ = c[own][:, None, None], c[part]
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = np.where(np.isfinite(cQ), cQ / (cI + cQ), 1.0)
    return flat, np.where(self_pair, 1.0, lam)


def incoming_measure(grid: Grid) -> np.ndarray:
    """|I| of each theta_i node's box (solid angle, the phi width one bin), (n_theta_i,)."""
    th = grid.theta_i_nodes()
    h = 0.5 * grid.step
    return grid.step * (np.sin(np.minimum(th + h, 0.5 * math.pi)) - np.sin(np.maximum(th - h, -0.5 * math.pi)))


def _write(f: IO[bytes], a: np.ndarray, offset: int) -> None:
    """Write ``a``'s bytes at ``offset``: positioned, so threads may write other parts at once."""
    view = memoryview(np.ascontiguousarray(a)).cast("B")
    fd, done = f.fileno(), 0
    while done < len(view):
        done += os.pwrite(fd, view[done:], offset + done)


def _read_into(f: IO[bytes], a: np.ndarray, offset: int, name: str = "") -> None:
    """Fill the contiguous ``a`` from ``offset`` (positioned, as :func:`_write`); a short read
    is a damaged scratch file (``name``: the file's, for the error; default ``f.name``)."""
    view = memoryview(a).cast("B")
    fd, done = f.fileno(), 0
    while done < len(view):
        n = os.preadv(fd, [view[done:]], offset + done)
        if n <= 0:
            raise OSError(f"{name or f.name}: scratch file shorter than written")
        done += n


class ReciprocalAverage:
    """Reciprocity averaging of a box-filtered table (module docstring), streamed.

    The directions of ``grid`` go in one at a time (:meth:`add`, each read once), are
    averaged together (:meth:`finish`) and come out one at a time (:meth:`source`, what
    :func:`usdfiber.bake.assembly.assemble` reads); ``n_levels`` absorption levels,
    ``photons_per_batch`` photons per full batch (a direction's batches are its photons over it,
    a fraction where a schedule shares a row's photons among its batches).
    Their H and G wait in two float32 files laid out (level, direction, row, column) in a
    directory made inside ``scratch`` (None: the system's temporary directory), so only one
    level of every direction is in memory at a time (2 deg: 0.5 GB per array, against 5.8 GB
    for all 11 levels). The files are read and written explicitly rather than mapped, so the
    process holds that level and not pages of the files. :meth:`close` (or leaving the
    ``with`` block, also on an error) removes the directory. BakeError at construction where
    ``budget`` or the scratch disk is too small (:func:`check_memory`).
    """

    def __init__(self, grid: Grid, n_levels: int, photons_per_batch: int,
                 scratch: str | os.PathLike[str] | None = None, budget: MemoryBudget | None = None) -> None:
        budget = budget if budget is not None else MemoryBudget.resolve()
        where = scratch if scratch is not None else tempfile.gettempdir()
        remove_stale_scratch(where)   # before the disk is checked: they hold it
        check_memory(grid, n_levels, where, budget)
        self.grid = grid
        #: Threads of :meth:`finish`: as many as the budget holds (one always does, above).
        self.threads = max(n for n in range(1, RECIPROCITY_THREADS + 1)
                           if n == 1 or budget.fits(reciprocity_bytes(grid, n)))
        self.n_levels = int(n_levels)
        self.photons_per_batch = int(photons_per_batch)
        n_dirs = grid.n_theta_i * grid.n_phi_i
        self._n_bins = grid.n_theta_o * grid.n_phi_o
        self._files: dict[str, IO[bytes]] = {}
        self._tmp = tempfile.TemporaryDirectory(prefix=SCRATCH_PREFIX, dir=scratch)
        try:
            for name in ("H", "G"):
                # H is locked before it gets its name, so a directory whose H file is not locked
                # is one whose averaging has ended (remove_stale_scratch).
                path = Path(self._tmp.name) / f"{name}.f32"
                f = open(path.with_suffix(".new"), "w+b")
                self._files[name] = f
                _lock(f)
                os.replace(path.with_suffix(".new"), path)
                f.truncate(4 * self.n_levels * n_dirs * self._n_bins)   # sparse: zeros where nothing is written
        except BaseException:
            self.close()
            raise
        self._batches = np.zeros(n_dirs)
        self._hit = np.zeros(n_dirs)
        self._wbar = np.zeros(n_dirs)
        self._meta: list[dict[str, Any] | None] = [None] * n_dirs
        self._rows = np.zeros((n_dirs, 2), dtype=np.int64)
        self._ratio = np.ones(n_dirs)
        self._finished = False

    def __enter__(self) -> "ReciprocalAverage":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def directory(self) -> Path:
        """Where the scratch files are (removed by :meth:`close`)."""
        return Path(self._tmp.name)

    def _offset(self, level: int, direction: int, row: int = 0) -> int:
        n_dirs = len(self._meta)
        return 4 * ((level * n_dirs + direction) * self._n_bins + row * self.grid.n_phi_o)

    def _direction(self, ti: int, pi: int) -> int:
        g = self.grid
        if not (0 <= ti < g.n_theta_i and 0 <= pi < g.n_phi_i):
            raise IndexError(f"no direction ({ti}, {pi}) in a grid of {g.n_theta_i} x {g.n_phi_i} nodes")
        return ti * g.n_phi_i + pi

    def _read(self, name: str, a: np.ndarray, offset: int) -> None:
        """:func:`_read_into` from scratch file ``name`` ("H" or "G"), named in its errors by
        the name it has (its file object keeps the one it was opened under)."""
        _read_into(self._files[name], a, offset, str(self.directory / f"{name}.f32"))

    def has(self, ti: int, pi: int) -> bool:
        """Whether direction (ti, pi) has been added."""
        return self._meta[self._direction(ti, pi)] is not None

    def add(self, ti: int, pi: int, data: Mapping[str, Any]) -> None:
        """Take direction (ti, pi): the mapping of
        :meth:`~usdfiber.bake.statistics.DirectionStatistics.result` (or of a chunk) of a
        box-filtered bake. Its histograms go to disk; its other entries are kept as they are."""
        if self._finished:
            raise RuntimeError("directions cannot be added after finish()")
        d = self._direction(ti, pi)
        if self._meta[d] is not None:
            raise ValueError(f"direction ({ti}, {pi}) added twice")
        K, n_r, n_c = self.n_levels, self.grid.n_theta_o, self.grid.n_phi_o
        r0, r1 = (int(x) for x in data["rows"])
        H = np.asarray(data["H"], dtype=np.float32)
        G = np.asarray(data["G"], dtype=np.float32)
        if not 0 <= r0 < r1 <= n_r or H.shape != (K, r1 - r0, n_c) or G.shape != H.shape:
            raise BakeError(f"direction ({ti}, {pi}): histograms of shape {H.shape} / {G.shape} at rows "
                            f"[{r0}, {r1}) do not fit {K} levels of {n_r} x {n_c} bins")
        for k in range(K):
            _write(self._files["H"], H[k], self._offset(k, d, r0))
            _write(self._files["G"], G[k], self._offset(k, d, r0))
        # The direction's photons in batches (a schedule's last batch may be partial: its
        # sums weigh by its photons, statistics.py), the scale of its sums.
        self._batches[d] = float(data["photons"]) / float(self.photons_per_batch)
        self._hit[d] = float(data["n_hit"]) + float(data.get("misses", 0.0))
        self._wbar[d] = float(data["norm"]) / self._batches[d]
        self._meta[d] = {key: value for key, value in data.items() if key not in ("H", "G")}

    def finish(self) -> None:
        """Average every entry with its partner, one absorption level at a time (all
        directions must have been added)."""
        if self._finished:
            return
        g = self.grid
        n_ti, n_pi = g.n_theta_i, g.n_phi_i
        missing = [d for d, m in enumerate(self._meta) if m is None]
        if missing:
            raise BakeError(f"reciprocity averaging needs every direction; {len(missing)} missing "
                            f"(first: theta_i node {missing[0] // n_pi}, phi_i node {missing[0] % n_pi})")
        meas = np.repeat(incoming_measure(g), n_pi)
        with np.errstate(divide="ignore", invalid="ignore"):
            c = np.where(self._hit > 0, meas * self._wbar / self._hit, np.inf)
        level = (n_ti, n_pi, g.n_theta_o, g.n_phi_o)
        H, G = np.empty(level, dtype=np.float32), np.empty(level, dtype=np.float32)
        # The nodes of a level are averaged by ``threads`` threads: each reads the level in
        # memory and writes only its own node's part of the files (numpy's arithmetic on these
        # arrays and the positioned writes run without the interpreter lock).
        with ThreadPoolExecutor(max_workers=self.threads, thread_name_prefix="usdfiber-reciprocity") as pool:
            for k in range(self.n_levels):
                # The whole level is read before any node is written back: partners read originals.
                self._read("H", H, self._offset(k, 0))
                self._read("G", G, self._offset(k, 0))
                for done in [pool.submit(self._average_node, k, ti, H, G, c, meas) for ti in range(n_ti)]:
                    done.result()
        self._finished = True

    def _average_node(self, k: int, ti: int, H: np.ndarray, G: np.ndarray, c: np.ndarray,
                      meas: np.ndarray) -> None:
        """Level ``k`` of theta_i node ``ti``'s directions averaged, written to the files
        (``H``, ``G``: level ``k`` of every direction, as added)."""
        g = self.grid
        flat, lam = node_weights(g, ti, c)
        part = flat // (g.n_theta_o * g.n_phi_o)                    # the partner's direction
        own = ti * g.n_phi_i + np.arange(g.n_phi_i)
        # The partner's H estimates S / |P| per batch sum: rescale it to this node's |I| / B_I.
        B = self._batches
        scale = (meas[part] * B[own][:, None, None]) / (meas[own][:, None, None] * B[part])
        a = lam.astype(np.float32)
        b = ((1.0 - lam) * scale).astype(np.float32)
        h, gs = H[ti], G[ti]
        Hn = a * h + b * H.reshape(-1)[flat]
        Gn = a * gs + b * G.reshape(-1)[flat]
        # Each direction keeps its own total per level: the albedo stays the direction's own
        # estimate (exactly 1 without absorption: the furnace), reciprocity shapes p.
        tot, tot_n = h.sum(axis=(1, 2), dtype=np.float64), Hn.sum(axis=(1, 2), dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            keep = np.where(tot_n > 0, tot / tot_n, 0.0).astype(np.float32)[:, None, None]
        Hn *= keep
        Gn *= keep
        _write(self._files["H"], Hn, self._offset(k, own[0]))
        _write(self._files["G"], Gn, self._offset(k, own[0]))
        if k == 0:
            # The variance ratio the weights give (mass-weighted over the bins), and the rows
            # that now hold light, from the level without absorption.
            for pi, d in enumerate(own):
                h0 = h[pi].astype(np.float64)
                mass = h0.sum()
                self._ratio[d] = float((lam[pi] * h0).sum() / mass) if mass > 0 else 1.0
                nz = np.flatnonzero(Hn[pi].sum(axis=-1) > 0)
                self._rows[d] = (int(nz[0]), int(nz[-1]) + 1) if nz.size else (0, 1)

    def source(self, ti: int, pi: int) -> dict[str, Any]:
        """Direction (ti, pi) averaged (after :meth:`finish`): its mapping as added, with the
        new ``rows`` (those holding light), ``H`` and ``G`` (float32, (levels, rows, n_phi_o))
        and ``rel_error`` scaled by the variance ratio the weights give."""
        if not self._finished:
            raise RuntimeError("source() needs finish() first")
        d = self._direction(ti, pi)
        r0, r1 = (int(x) for x in self._rows[d])
        out = dict(self._meta[d] or {})
        out["rows"] = (r0, r1)
        for name in ("H", "G"):
            arr = np.empty((self.n_levels, r1 - r0, self.grid.n_phi_o), dtype=np.float32)
            for k in range(self.n_levels):
                self._read(name, arr[k], self._offset(k, d, r0))
            out[name] = arr
        out["rel_error"] = float(out["rel_error"]) * math.sqrt(float(self._ratio[d]))
        return out

    def close(self) -> None:
        """Remove the scratch files (again: nothing to do)."""
        for f in self._files.values():
            f.close()
        self._files = {}
        self._tmp.cleanup()


def reciprocal_average(grid: Grid, slices: Mapping[tuple[int, int], Mapping[str, Any]],
                       photons_per_batch: int) -> dict[tuple[int, int], dict[str, Any]]:
    """Every direction's histograms averaged with their reciprocal partners.

    ``slices`` maps every incoming node (ti, pi) of ``grid`` to the mapping of
    :meth:`~usdfiber.bake.statistics.DirectionStatistics.result` of a box-filtered bake (with
    ``photons_per_batch`` photons per batch, so that ``photons / photons_per_batch`` is its
    number of batches). Returns new mappings of the same form (:meth:`ReciprocalAverage.source`),
    all of them in memory: bakes stream them with :class:`ReciprocalAverage` instead.
    """
    n_ti, n_pi = grid.n_theta_i, grid.n_phi_i
    missing = [(ti, pi) for ti in range(n_ti) for pi in range(n_pi) if (ti, pi) not in slices]
    if missing:
        raise BakeError(f"reciprocity averaging needs every direction; {len(missing)} missing "
                        f"(first: theta_i node {missing[0][0]}, phi_i node {missing[0][1]})")
    K = int(np.asarray(next(iter(slices.values()))["H"]).shape[0])
    with ReciprocalAverage(grid, K, photons_per_batch) as avg:
        for (ti, pi), d in slices.items():
            avg.add(ti, pi, d)
        avg.finish()
        return {(ti, pi): avg.source(ti, pi) for ti in range(n_ti) for pi in range(n_pi)}
