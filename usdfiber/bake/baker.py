"""Baking BCSDF tables: photon tracing over the incoming directions a table needs.

:func:`bake_table` traces one cross-section variant (a
:class:`~usdfiber.bake.profiles.Profile`) for every incoming direction of its grid and
returns a :class:`~usdfiber.bake.table.BcsdfTable`; :func:`bake_request` does it for a
:class:`~usdfiber.bake.requests.TableRequest` (what a fiber needs, :mod:`usdfiber.bake.requests`).
How: :class:`~usdfiber.bake.settings.BakeSettings`. The statistics of one direction
(batches, absorption levels, error estimate, target-error mode, normalization):
:mod:`usdfiber.bake.statistics`; the table made of them: :mod:`usdfiber.bake.assembly`.

Directions are traced together: batch ``b`` of up to
:data:`~usdfiber.bake.settings.GROUP_DIRECTIONS` directions (about
:data:`~usdfiber.bake.settings.GROUP_PHOTONS` photons) is one tracer launch. Each direction still gets exactly
its own photons (batch ``b`` of every direction is the tracer stream :func:`batch_seed`), so
a table does not depend on the grouping; what is shared is the tracer's fixed cost per
launch (recording and launching its phases until the slowest photon is done), which
dominated small-photon bakes such as the renderer's (bench/REPORT.md, "grouping").

Photons stopped by ``max_bounces`` are lost: with the default 4096 none was, while 256 lost up
to 0.4% of a near-smooth round fiber's light in trapped, nearly grazing paths.

Symmetries: extruded fibers are traced for theta_i >= 0 only; rotationally symmetric
profiles (a round profile, smooth or rough, with or without cuticle rings,
:func:`is_rotationally_symmetric`) for one phi_i; their tables are also mirror-averaged.

Diameter: the stage's fibers are baked at a circumscribed diameter of 1 um (cuticle height
and spacing relative to the diameter, as in ``FiberParams.geometry_inputs``); a fiber of
diameter ``D`` um recolours the table with ``diameter_scale = D`` (see
:mod:`usdfiber.bake.table`). ``BakeSettings.levels`` are optical depths across the
circumscribed diameter, ``sigma_a * D``; the table stores them in 1/um of its baked size.

Estimators (``BakeSettings.estimator``): the plain one by default; "stratified" draws each
photon's first numbers from a scrambled Sobol point (:mod:`usdfiber.bake.sampling`);
"reciprocity" averages every entry of a box-filtered table with its reciprocal partner
(:mod:`usdfiber.bake.reciprocity`) when the table is assembled (its chunks hold the plain
histograms; each direction goes to the averaging's scratch files as its group is written, so
only a resumed bake's chunks are read back); "split" splits every hit of the outer surface
into ``split_walks`` microsurface walks (:func:`usdfiber.bake.tracer.trace`; a photon then
leaves several weighted exits);
"expected" histograms, in the tracer's kernel, the expected exit of every outer-surface event
where leaving is for good over up to ``expected_normals`` normals (shared among the events by
``expected_allocation``, drawn as ``expected_sampler`` says), at every absorption level
(:class:`usdfiber.bake.tracer.ExitHistogram`). All
give every direction its own random streams (:func:`stream_seed`).

Grid: :meth:`BakeSettings.grid_for` (the settings' bin size and incoming node spacing, or with
``auto_resolution=True`` those the fiber's band limit allows, :mod:`usdfiber.bake.band_limit`,
recorded in the header's ``band_limit``). Incoming directions are sampled at the centres of
their cells by default (the paper's choice, for interpolation between nodes); ``BakeSettings(incoming="box")`` spreads each node's light over
its bin instead, which makes the discrete table reciprocal bin for bin.

Resuming: with ``resume_dir``, every finished incoming direction is written there as a
verified chunk (:mod:`usdfiber.bake.chunks`), written while the next group of directions
traces (an interruption waits for those writes and loses at most the group in flight: about
``GROUP_PHOTONS`` photons per batch; a killed process, at most two groups); a
rerun with the same directory (and the same inputs and settings, recorded in ``bake.json``)
traces only the directions without a usable chunk (scratch files a killed averaging left there
are removed: :func:`usdfiber.bake.reciprocity.remove_stale_scratch`). Tables of more than
:data:`DIRECTIONS_IN_MEMORY` directions keep their finished directions in a scratch directory
even without ``resume_dir``.
"""
from __future__ import annotations

import hashlib
import math
import os
import platform
import tempfile
import time
import warnings
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping

import numpy as np

from usdfiber.bake import band_limit
from usdfiber.bake.assembly import assemble
from usdfiber.bake.chunks import ResumeDirectory, chunk_name
from usdfiber.bake.grid import Grid
from usdfiber.bake.reciprocity import ReciprocalAverage, check_memory, remove_stale_scratch
from usdfiber.bake.requests import TableRequest
from usdfiber.bake.sampling import stream_seed
from usdfiber.bake.settings import ASSEMBLY_THREADS, GROUP_PHOTONS, BakeError, BakeSettings, directions_per_group
from usdfiber.bake.statistics import BakeContext, DirectionStatistics
from usdfiber.bake.storage import WIDTH_SAMPLES
from usdfiber.bake.table import BcsdfTable

__all__ = [
    "DIRECTIONS_IN_MEMORY",
    "KEEP_CHUNK_BYTES",
    "ProgressFn",
    "bake_context",
    "bake_request",
    "bake_table",
    "batch_seed",
    "envelope_width",
    "is_rotationally_symmetric",
    "assemble_from_chunks",
    "profile_fingerprint",
    "resume_fingerprint",
    "table_grid",
    "table_directions",
    "trace_directions",
    "trace_to_chunks",
]

#: Tables with more incoming directions keep finished ones on disk rather than in memory.
DIRECTIONS_IN_MEMORY = 2000
#: Chunks read from a resume directory for the assembly's first pass are kept in memory for
#: its second pass up to this many bytes of histograms (beyond it they are read again).
KEEP_CHUNK_BYTES = 1 << 30

#: ``progress(done, total, info)``: called once with ``info["event"] == "start"`` (``done``
#: = directions found in the resume directory), then after every finished direction
#: (``"direction"``, with theta_i/phi_i in degrees, photons, rel_error, seconds, resumed).
ProgressFn = Callable[[int, int, dict], None]


def is_rotationally_symmetric(profile: Any, tol: float = 1e-4) -> bool:
    """True for a single smooth loop centred on the origin with radial normals (a circle)."""
    if len(profile.loops) != 1 or not getattr(profile, "smooth", False):
        return False
    pts = np.asarray(profile.loops[0], dtype=np.float64)
    nrm = np.asarray(profile.normals[0], dtype=np.float64)
    r = np.linalg.norm(pts, axis=1)
    if r.min() <= 0 or (r.max() - r.min()) > tol * r.mean():
        return False
    radial = np.einsum("ij,ij->i", pts / r[:, None], nrm / np.linalg.norm(nrm, axis=1, keepdims=True))
    return bool(radial.min() > 1.0 - tol)


def envelope_width(profile: Any, height: float, n: int = WIDTH_SAMPLES) -> np.ndarray:
    """W(phi) of the outer loop offset by ``height`` along its normals, at phi = 2 pi j / n."""
    outer = np.asarray(profile.loops[0], dtype=np.float64)
    if height > 0:
        nrm = np.asarray(profile.normals[0], dtype=np.float64)
        outer = outer + height * nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
    phi = 2.0 * math.pi * np.arange(n) / n
    out = np.empty(n)
    for s in range(0, n, 64):
        p = phi[s:s + 64, None]
        proj = -np.sin(p) * outer[None, :, 0] + np.cos(p) * outer[None, :, 1]
        out[s:s + 64] = proj.max(axis=1) - proj.min(axis=1)
    return out


def profile_fingerprint(profile: Any) -> str:
    """sha256 of a profile's loops, normals and smoothness (identifies the traced shape)."""
    h = hashlib.sha256()
    for loop, nrm in zip(profile.loops, profile.normals):
        h.update(np.ascontiguousarray(loop, dtype=np.float64).tobytes())
        h.update(np.ascontiguousarray(nrm, dtype=np.float64).tobytes())
    h.update(b"smooth" if getattr(profile, "smooth", False) else b"flat")
    return h.hexdigest()


def batch_seed(seed: int, batch: int) -> int:
    """The tracer seed of batch ``batch``: distinct per (seed, batch), shared by all directions.

    Batches of one direction are independent; the same batch of different directions uses
    the same random stream (common random numbers: errors vary smoothly with omega_i). A
    few distinct seeds also keep the tracer's compiled kernels reusable: every new seed
    value costs a kernel compilation.
    """
    return (int(seed) & 0xFFFFFFFF) * 65536 + int(batch)


def trace_directions(ctx: BakeContext, dirs: list[tuple[int, int]]) -> list[dict[str, Any]]:
    """Trace incoming directions together: batch ``b`` of every direction in one launch.

    Each direction gets exactly the photons it would get alone (batch ``b`` is the tracer
    stream ``batch_seed(seed, b)`` for every direction), so a table does not depend on how
    its directions were grouped; grouping only shares the tracer's fixed cost per launch.
    """
    from usdfiber.bake import tracer

    st = ctx.settings
    n_b = st.photons_per_batch          # target-error mode plans its further batches in these
    accs = [DirectionStatistics(ctx, ti, pi) for ti, pi in dirs]
    node = {id(a): d for a, d in zip(accs, dirs)}
    sampler = "sobol" if "stratified" in st.estimator else "independent"
    split = int(st.split_walks) if "split" in st.estimator else 0
    expected = int(st.expected_normals) if "expected" in st.estimator else 0
    hist = tracer.ExitHistogram.for_grid(ctx.grid, ctx.levels_um) if expected else None
    while True:
        todo = [a for a in accs if a.queue]
        if not todo:
            break
        batch = [(a, a.queue.pop(0)) for a in todo]
        subs = [a.sub_direction(b) for a, b in batch]
        spreads = [a.spread for a, _ in batch]        # box bins whose photons draw their own direction
        if st.estimator:
            # Estimators other than the plain one need independent directions.
            seeds = [stream_seed(st.seed, b, *node[id(a)]) for a, b in batch]
        else:
            seeds = [batch_seed(st.seed, b) for _, b in batch]
        # A schedule's rows share their photons among their batches (BakeSettings.batch_photons).
        photons = [st.batch_photons(node[id(a)][0], b) for a, b in batch]
        res = tracer.trace_many(ctx.fs, subs, photons, eta=ctx.eta, beta_deg=ctx.beta_deg,
                                max_bounces=int(st.max_bounces), seed=seeds,
                                cuticle=ctx.cuticle, batch=GROUP_PHOTONS, sampler=sampler, split=split,
                                expected=expected, histogram=hist,
                                expected_allocation=st.expected_allocation,
                                expected_sampler=st.expected_sampler,
                                spread=spreads if any(sp is not None for sp in spreads) else None)
        for (a, _), (th_b, ph_b), r in zip(batch, subs, res):
            a.add(r, th_b, ph_b)
            if not a.queue:
                a.plan_more(n_b)
    return [a.result() for a in accs]


def _trace_direction(ctx: BakeContext, ti: int, pi: int) -> dict[str, Any]:
    """One incoming direction on its own (see :func:`trace_directions`)."""
    return trace_directions(ctx, [(ti, pi)])[0]


def bake_context(profile: Any, eta: float, beta_deg: float, cut: tuple[float, float, float] | None,
                 st: BakeSettings, scratch: str | os.PathLike[str] | None = None) -> BakeContext:
    """The traced scene, grid and absorption levels of one table (inputs already checked:
    ``cut`` is None or has a height > 0). ``scratch``: the directory where the table will be
    assembled (the reciprocity averaging's scratch files; its disk is checked), None for work
    that does not assemble it."""
    from usdfiber.bake import tracer

    diameter = float(profile.circumscribed_diameter)
    grid = st.grid_for(beta_deg, is_rotationally_symmetric(profile), cut is not None)
    st.check_rows(grid)
    levels_um = np.asarray(st.levels, dtype=np.float64) / diameter
    if "reciprocity" in st.estimator:
        # Before hours of tracing, not after; the chunks go there too when it is a resume directory.
        # Scratch files a killed bake left there hold disk that is free again.
        if scratch is not None:
            remove_stale_scratch(scratch)
        check_memory(grid, len(levels_um), scratch, chunks=scratch is not None)
    if "split" in st.estimator and cut is not None:
        raise BakeError("estimator 'split' needs a fiber without cuticle scales (the test that light "
                        "leaving through the scales never meets them again is not built)")
    if "expected" in st.estimator and cut is not None:
        raise BakeError("estimator 'expected' needs a fiber without cuticle scales (where light leaving "
                        "through the scales is for good is not known)")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # mesh remarks on cuticle shapes
        fs = tracer.prepare(profile, cut)
    width_env = envelope_width(profile, cut[1] if cut else 0.0)
    return BakeContext(fs, grid, st, float(eta), float(beta_deg), cut, levels_um, width_env, cut[1] if cut else 0.0)


def bake_table(profile: Any, eta: float, beta_deg: float,
               cuticle: tuple[float, float, float] | None = None,
               settings: BakeSettings | None = None, progress: ProgressFn | None = None,
               resume_dir: str | os.PathLike[str] | None = None, *,
               header: Mapping[str, Any] | None = None) -> BcsdfTable:
    """Bake the table of one cross section.

    ``profile``: a :class:`~usdfiber.bake.profiles.Profile` in um (its circumscribed
    diameter is the baked diameter); ``eta``: refractive index; ``beta_deg``: Beckmann
    roughness angle (alpha = tan beta); ``cuticle``: ``(tilt_deg, height_um, spacing_um)``
    at the profile's size, or None. ``header``: extra header entries (geometry key,
    inputs, variant, ...). See the module docstring for ``progress`` and ``resume_dir``.
    """
    st = settings or BakeSettings()
    if not (math.isfinite(eta) and eta >= 1.0):
        raise BakeError(f"eta must be >= 1, got {eta}")
    if not (math.isfinite(beta_deg) and 0.0 <= beta_deg < 90.0):
        raise BakeError(f"beta must be in [0, 90) degrees, got {beta_deg}")
    cut = None
    if cuticle is not None and float(cuticle[1]) > 0.0:
        cut = (float(cuticle[0]), float(cuticle[1]), float(cuticle[2]))
    # The table is assembled in the resume directory, else in a temporary one.
    ctx = bake_context(profile, eta, beta_deg, cut, st,
                       resume_dir if resume_dir is not None else tempfile.gettempdir())
    grid = ctx.grid
    directory = Path(resume_dir) if resume_dir is not None else None
    scratch = None
    if directory is None and grid.n_theta_i * grid.n_phi_i > DIRECTIONS_IN_MEMORY:
        scratch = tempfile.TemporaryDirectory(prefix="usdfiber-bake-")
        directory = Path(scratch.name)
    try:
        resume = None
        if directory is not None:
            resume = ResumeDirectory(directory, resume_fingerprint(ctx, profile), _histogram(ctx))
        return _bake_directions(ctx, profile, resume, progress, header)
    finally:
        if scratch is not None:
            scratch.cleanup()


def _bake_directions(ctx: BakeContext, profile: Any, resume: ResumeDirectory | None,
                     progress: ProgressFn | None, header: Mapping[str, Any] | None) -> BcsdfTable:
    """Trace every direction without a chunk, then assemble the table and its header."""
    st, grid = ctx.settings, ctx.grid
    n_ti, n_pi = grid.n_theta_i, grid.n_phi_i
    total = n_ti * n_pi
    in_memory: dict[tuple[int, int], dict[str, Any]] = {}
    # Existence is enough here: a damaged chunk is traced again when it is read.
    done_from_disk = {(ti, pi) for ti in range(n_ti) for pi in range(n_pi)
                      if resume is not None and resume.has(ti, pi)}
    t_start = time.perf_counter()
    if progress is not None:
        progress(len(done_from_disk), total, {"event": "start", "resumed": len(done_from_disk), "total": total})
    done = len(done_from_disk)
    todo = [(ti, pi) for ti in range(n_ti) for pi in range(n_pi) if (ti, pi) not in done_from_disk]
    stats = {"photons": 0, "n_hit": 0, "n_cut": 0, "leaks": 0, "seconds": 0.0}
    counted: set[tuple[int, int]] = set()

    def count(ti: int, pi: int, d: Mapping[str, Any]) -> bool:
        """Add direction (ti, pi)'s photons and seconds to ``stats``, once: True the first time."""
        if (ti, pi) in counted:
            return False
        counted.add((ti, pi))
        for k in ("photons", "n_hit", "n_cut", "leaks", "seconds"):
            stats[k] += d[k]
        return True

    # With reciprocity each direction's histograms go to the averaging's scratch files as soon
    # as they are traced (read once, while in memory), not read back from their chunks after
    # the last group: only the chunks of a resumed bake are read then.
    averager = (ReciprocalAverage(grid, len(ctx.levels_um), st.photons_per_batch,
                                  resume.path if resume is not None else None)
                if "reciprocity" in st.estimator else None)
    try:
        _trace_all(ctx, todo, resume, averager, in_memory, count, progress, done, total)
        return _assemble_table(ctx, profile, resume, averager, in_memory, stats, count, header, t_start)
    finally:
        if averager is not None:
            averager.close()


def _trace_all(ctx: BakeContext, todo: list[tuple[int, int]], resume: ResumeDirectory | None,
               averager: ReciprocalAverage | None, in_memory: dict[tuple[int, int], dict[str, Any]],
               count: Callable[[int, int, Mapping[str, Any]], bool], progress: ProgressFn | None,
               done: int, total: int) -> None:
    """Trace the directions ``todo``; each goes to its chunk (``resume``), to the averaging
    (``averager``), or else stays in ``in_memory``."""
    st = ctx.settings
    # Directions are traced in groups that share tracer launches (about GROUP_PHOTONS photons
    # per batch). A finished group's chunks are written (and its histograms added to the
    # averaging) by one thread while the next group traces (a write mostly waits on the disk:
    # checksum, fsync); at most one group waits to be written, a failed write stops the bake
    # when the next group is traced, and leaving the block (also on Ctrl-C) waits for the
    # writes in flight.
    group = directions_per_group(st)
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="usdfiber-chunks") as writer:
        pending: Future | None = None
        for g0 in range(0, len(todo), group):
            dirs = todo[g0:g0 + group]
            traced = trace_directions(ctx, dirs)
            if pending is not None:
                pending.result()
                pending = None
            if resume is not None or averager is not None:
                pending = writer.submit(_keep_group, resume, averager, count, dirs, traced)
            for (ti, pi), data in zip(dirs, traced):
                if resume is None and averager is None:
                    in_memory[(ti, pi)] = data
                done += 1
                if progress is not None:
                    progress(done, total, {"event": "direction", "theta_i_deg": math.degrees(data["theta_i"]),
                                           "phi_i_deg": math.degrees(data["phi_i"]), "photons": data["photons"],
                                           "rel_error": data["rel_error"], "seconds": data["seconds"],
                                           "resumed": False})
        if pending is not None:
            pending.result()


def _assemble_table(ctx: BakeContext, profile: Any, resume: ResumeDirectory | None,
                    averager: ReciprocalAverage | None, in_memory: dict[tuple[int, int], dict[str, Any]],
                    stats: dict[str, Any], count: Callable[[int, int, Mapping[str, Any]], bool],
                    header: Mapping[str, Any] | None, t_start: float) -> BcsdfTable:
    """The table of the traced directions (averaged by ``averager``, when given), and its header."""
    st, grid = ctx.settings, ctx.grid
    n_ti, n_pi = grid.n_theta_i, grid.n_phi_i
    # The assembly reads every direction twice (bands, then arrays): chunks read from disk
    # are kept for the second read while they fit in KEEP_CHUNK_BYTES, and released by it.
    kept: dict[tuple[int, int], dict[str, Any]] = {}
    kept_bytes = 0

    def load_slice(ti: int, pi: int, again: bool = True, read: Any = _UNREAD) -> Mapping[str, Any]:
        """Direction (ti, pi), counted in ``stats`` once; ``again``: it will be read again;
        ``read``: its chunk as ``resume.load`` returned it, when already read."""
        nonlocal kept_bytes
        if resume is None:
            d = in_memory[(ti, pi)] if again else in_memory.pop((ti, pi))
        elif (ti, pi) in kept:
            d = kept.pop((ti, pi))
            kept_bytes -= _chunk_bytes(d)
        else:
            d = resume.load(ti, pi) if read is _UNREAD else read
            if d is None:  # unusable: trace it again
                d = _trace_direction(ctx, ti, pi)
                resume.save(ti, pi, d)
            # Kept on its first read only (count: True then).
            if count(ti, pi, d) and again and kept_bytes + _chunk_bytes(d) <= KEEP_CHUNK_BYTES:
                kept[(ti, pi)] = d
                kept_bytes += _chunk_bytes(d)
        count(ti, pi, d)
        return d

    cut = ctx.cuticle
    hdr: dict[str, Any] = {
        "geometry_key": "",
        "inputs": {},
        "variant": 0,
    }
    hdr.update(dict(header or {}))
    hdr.update({
        "baked_diameter_um": float(profile.circumscribed_diameter),
        "incoming": st.incoming,
        "eta": ctx.eta,
        "beta_deg": ctx.beta_deg,
        "cuticle": None if cut is None else {"tilt_deg": cut[0], "height_um": cut[1], "spacing_um": cut[2]},
        "profile": {"name": str(getattr(profile, "name", "")), "loops": len(profile.loops),
                    "edges": int(sum(len(l) for l in profile.loops)), "smooth": bool(getattr(profile, "smooth", False)),
                    "area_um2": float(profile.area), "fingerprint": profile_fingerprint(profile)},
        "photons": {"per_direction_setting": int(st.photons), "total": int(stats["photons"]),
                    "min_per_direction": None, "max_per_direction": None,
                    "hit": int(stats["n_hit"]), "cut": int(stats["n_cut"]), "batches": int(st.batches)},
        "units": {"angles": "deg in this header, radians in the Python API",
                  "p": "1/sr", "albedo": "1", "width": "um at the baked size",
                  "levels": "1/um at the baked size", "lbar": "um at the baked size",
                  "baked_diameter_um": "um"},
        "bake": {"settings": st.result_inputs(), "trace_seconds": float(stats["seconds"]),
                 "wall_seconds": float(time.perf_counter() - t_start),
                 "machine": {"platform": platform.platform(), "processor": platform.machine(),
                             "cpus": os.cpu_count()}},
    })
    source: Callable[[int, int], Mapping[str, Any]] = load_slice
    if averager is not None:
        # Each entry is averaged with its partner's: every direction goes in (read once; the
        # assembly reads the averaged ones), then the averaged ones come out one at a time.
        # Those traced now are in already; a resumed bake's chunks are read here.
        order = [(ti, pi) for ti in range(n_ti) for pi in range(n_pi) if not averager.has(ti, pi)]
        if resume is None:
            for ti, pi in order:
                averager.add(ti, pi, load_slice(ti, pi, again=False))
        else:
            for (ti, pi), chunk in _read_ahead(resume, order):
                averager.add(ti, pi, load_slice(ti, pi, again=False, read=chunk))
        averager.finish()
        source = averager.source
    table = assemble(grid, ctx.levels_um, (n_ti, n_pi), source, ctx.width_env, hdr,
                     band_tail=st.band_tail, storage=st.storage, threads=ASSEMBLY_THREADS)
    table.header["photons"].update({"total": int(stats["photons"]), "hit": int(stats["n_hit"]),
                                    "cut": int(stats["n_cut"])})
    table.header["bake"]["trace_seconds"] = float(stats["seconds"])
    table.header["bake"]["wall_seconds"] = float(time.perf_counter() - t_start)
    ph = table.arrays["photons"]
    err = table.rel_error.astype(np.float64)
    table.header["photons"]["min_per_direction"] = int(ph.min())
    table.header["photons"]["max_per_direction"] = int(ph.max())
    table.header["error_estimate"] = {
        "metric": "relative L2 error of p over the sphere at sigma_a = 0, from the variance "
                  "between independent photon batches, per incoming direction",
        "rms": float(np.sqrt(np.mean(err ** 2))), "max": float(err.max()), "median": float(np.median(err)),
        "target": st.target_error,
    }
    table.header["levels_optical_depth"] = [float(x) for x in st.levels]
    if st.auto_resolution:
        table.header["band_limit"] = {"rule_version": band_limit.RULE_VERSION,
                                      "resolution_deg": grid.resolution_deg,
                                      "incoming_deg": grid.incoming_spacing_deg,
                                      "rule": "usdfiber.bake.band_limit"}
    table.header["leaks"] = int(stats["leaks"])
    return table


#: ``load_slice``'s marker of a chunk not read yet (``resume.load`` returns None for an unusable one).
_UNREAD = object()


def _read_ahead(resume: ResumeDirectory, order: list[tuple[int, int]]) -> Iterator[tuple[tuple[int, int], Any]]:
    """``(direction, resume.load(direction))`` in ``order``, the next chunk read and verified
    by one thread while the caller uses this one (a read mostly waits on the disk and the
    checksum, which run without the interpreter lock); one chunk ahead at most."""
    if not order:
        return
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="usdfiber-chunks") as reader:
        ahead = reader.submit(resume.load, *order[0])
        for i, key in enumerate(order):
            chunk = ahead.result()
            if i + 1 < len(order):
                ahead = reader.submit(resume.load, *order[i + 1])
            yield key, chunk


def _keep_group(resume: ResumeDirectory | None, averager: ReciprocalAverage | None,
                count: Callable[[int, int, Mapping[str, Any]], bool],
                dirs: list[tuple[int, int]], traced: list[dict[str, Any]]) -> None:
    """Write a traced group's chunks, in order, and add them to the averaging (counted then)."""
    for (ti, pi), data in zip(dirs, traced):
        if resume is not None:
            resume.save(ti, pi, data)
            if averager is not None:
                # Its pages will not be read again (unless a later bake resumes from it): let
                # the page cache keep the averaging's scratch files instead.
                _drop_cached(resume.chunk_path(ti, pi))
        if averager is not None:
            averager.add(ti, pi, data)
            count(ti, pi, data)


def _drop_cached(path: Path) -> None:
    """Ask the kernel to drop ``path``'s pages from its cache (a hint; nothing where the
    platform has no ``posix_fadvise``). A chunk is written with fsync, so its pages are clean."""
    if not hasattr(os, "posix_fadvise"):
        return
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
    except OSError:
        pass
    finally:
        os.close(fd)


def _chunk_bytes(data: Mapping[str, Any]) -> int:
    """Bytes of a direction's histograms (what keeping its chunk in memory costs)."""
    return int(np.asarray(data["H"]).nbytes + np.asarray(data["G"]).nbytes)


def bake_request(request: TableRequest, settings: BakeSettings | None = None,
                 progress: ProgressFn | None = None,
                 resume_dir: str | os.PathLike[str] | None = None) -> BcsdfTable:
    """Bake the table of a request (no cache; see :mod:`usdfiber.bake.cache`)."""
    return bake_table(request.profile(), request.eta, request.beta_deg, request.cuticle,
                      settings, progress, resume_dir, header=request.header())


# ---------------------------------------------------------------------------------------------
# Parts of one bake in other processes (farm tasks: usdfiber.farm)
# ---------------------------------------------------------------------------------------------

def resume_fingerprint(ctx: BakeContext, profile: Any) -> dict[str, Any]:
    """What a resume directory's chunks were traced for (:class:`ResumeDirectory`'s fingerprint)."""
    cut = ctx.cuticle
    return {"profile": profile_fingerprint(profile), "eta": ctx.eta, "beta_deg": ctx.beta_deg,
            "cuticle": list(cut) if cut else None, "grid": ctx.grid.to_header(),
            "settings": ctx.settings.result_inputs()}


def _histogram(ctx: BakeContext) -> tuple[int, int, int]:
    """(levels, theta_o rows, phi_o columns) of a direction's histograms in a chunk."""
    return len(ctx.levels_um), ctx.grid.n_theta_o, ctx.grid.n_phi_o


def _request_inputs(request: TableRequest) -> tuple[Any, float, float, tuple[float, float, float] | None]:
    """(profile, eta, beta_deg, cuticle or None) of a request, checked as :func:`bake_table` does."""
    eta, beta_deg = request.eta, request.beta_deg
    if not (math.isfinite(eta) and eta >= 1.0):
        raise BakeError(f"eta must be >= 1, got {eta}")
    if not (math.isfinite(beta_deg) and 0.0 <= beta_deg < 90.0):
        raise BakeError(f"beta must be in [0, 90) degrees, got {beta_deg}")
    return request.profile(), eta, beta_deg, request.cuticle_scales


def table_grid(request: TableRequest, settings: BakeSettings) -> Grid:
    """The grid of the table :func:`bake_table` bakes for ``request``."""
    profile, _, beta_deg, cut = _request_inputs(request)
    return settings.grid_for(beta_deg, is_rotationally_symmetric(profile), cut is not None)


def table_directions(request: TableRequest, settings: BakeSettings) -> list[tuple[int, int]]:
    """The incoming directions ``(ti, pi)`` :func:`bake_table` traces for ``request``, in its order."""
    grid = table_grid(request, settings)
    return [(ti, pi) for ti in range(grid.n_theta_i) for pi in range(grid.n_phi_i)]


def trace_to_chunks(request: TableRequest, settings: BakeSettings, directions: list[tuple[int, int]] | tuple,
                    chunk_dir: str | os.PathLike[str]) -> dict[str, int]:
    """Trace the ``directions`` of ``request``'s table that lack a usable chunk in ``chunk_dir``.

    The chunks are those :func:`bake_table` writes and resumes from with ``resume_dir =
    chunk_dir`` (same fingerprint, same photons per direction), so a table assembled from
    chunks traced in any number of processes equals the one-process bake. Existing chunks
    are verified (a damaged one is reported and traced again). Returns ``traced``
    (directions) and ``photons``.
    """
    profile, eta, beta_deg, cut = _request_inputs(request)
    ctx = bake_context(profile, eta, beta_deg, cut, settings, chunk_dir)   # the table is assembled there
    resume = ResumeDirectory(chunk_dir, resume_fingerprint(ctx, profile), _histogram(ctx))
    todo = [(int(ti), int(pi)) for ti, pi in directions
            if not (resume.has(ti, pi) and resume.load(ti, pi) is not None)]
    group = directions_per_group(settings)
    photons = 0
    for g0 in range(0, len(todo), group):
        dirs = todo[g0:g0 + group]
        for (ti, pi), data in zip(dirs, trace_directions(ctx, dirs)):
            resume.save(ti, pi, data)
            photons += int(data["photons"])
    return {"traced": len(todo), "photons": photons}


def assemble_from_chunks(request: TableRequest, settings: BakeSettings,
                         chunk_dir: str | os.PathLike[str]) -> BcsdfTable:
    """The table of ``request`` from the chunks in ``chunk_dir`` (one per direction, each verified).

    Raises BakeError naming the directory when a direction has no chunk; a chunk that does
    not verify (damaged, another bake's, another direction's) is reported and traced again.
    """
    directory = Path(chunk_dir)
    dirs = table_directions(request, settings)
    missing = [d for d in dirs if not (directory / chunk_name(*d)).exists()]
    if missing:
        raise BakeError(f"{directory}: {len(missing)} of {len(dirs)} directions have no chunk yet "
                        f"(first: {chunk_name(*missing[0])}); cannot assemble the table")
    return bake_request(request, settings, resume_dir=directory)

