"""What a bake will cost, before it starts: time, size on disk and peak memory.

A bake's work is known exactly from its request and settings: the incoming directions of
the table's grid (:func:`usdfiber.bake.baker.table_directions`), the photons each gets
(``batches`` launches of ``photons_per_batch``; in target-error mode as many as the error
needs, up to ``max_photons``; with a row schedule, each row's), the tracer launches (one per batch of a group of
:func:`~usdfiber.bake.settings.directions_per_group` directions). What it costs per photon
depends on the fiber and on this machine, so a quick **probe** measures it
(:func:`probe`) with the baker's own code. A launch of N photons takes ``a + N / rate``
(:func:`launch_model`; ``a`` is the cost of its phases, which grows only slowly with N),
so two launch sizes give ``a`` and the rate: a few directions
at the bake's photons per direction, and a launch shaped like the bake's but smaller
(:func:`launch_shape`: directions spread over the grid at the bake's photons per batch,
about :data:`PROBE_LAUNCH_PHOTONS` in all; the bake's launches hold up to 2M). The few
directions are also assembled into a small table and written as a table is, which gives the
assembly time and the compressed bytes per direction, and the error constant ``c`` of
``rel L2 = c / sqrt(N)`` that target-error mode needs.

A probe traces about 1.3M photons (its directions' photons per direction are the bake's,
capped at :data:`PROBE_PHOTONS`; the timed launch holds :data:`PROBE_LAUNCH_PHOTONS`, each
size traced twice) and is kept per fiber (the geometry inputs of cross-section variant 0,
which stands for the others), grid, photons and machine under the cache root
(``probes/<key>.json``); a damaged or foreign file is probed again.

Accuracy: the direction count, photons and launches of an estimate are exact for a bake of
fixed photons or a row schedule (``tests/bake/test_cost.py`` checks them against a real bake, with the size
on disk); the time is a model, measured against real bakes in ``bench/REPORT.md``
("Cost estimates"). Peak memory is
:meth:`usdfiber.bake.settings.BakeSettings.table_bytes`, an upper bound.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import platform
import tempfile
import time
import zipfile
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from usdfiber import table_format
from usdfiber.bake.settings import ASSEMBLY_THREADS, BakeSettings, directions_per_group

__all__ = ["LONG_BAKE_SECONDS", "PROBE_DIRECTIONS", "RECIPROCITY_BYTES_PER_SECOND", "PROBE_LAUNCH_PHOTONS", "PROBE_PHOTONS", "BakeEstimate", "Probe",
           "cheaper_hint", "estimate", "estimate_request", "format_seconds", "launch_model", "launch_shape", "probe",
           "total"]

#: Bytes of a table's H and G the reciprocity averaging gets through per second (a full 2 deg
#: table's 11.5 GB in 100-110 s on 2 cores with every chunk read back, bench/REPORT.md section 7;
#: about 70 s since a bake adds each group as it is traced, so a bound for resumed bakes and
#: about 45 s over for unstopped ones): not probed.
RECIPROCITY_BYTES_PER_SECOND = 100e6
#: Incoming directions a probe traces (spread over the table's grid).
PROBE_DIRECTIONS = 4
#: Most photons per direction a probe traces (the bake's own count when fewer).
PROBE_PHOTONS = 1 << 16
#: Photons of the probe's larger timed launch (fewer when the bake's own launches are
#: smaller): with the probe directions' launch, enough for the line through the two to
#: extrapolate to the bake's launches (``bench/REPORT.md``, "Cost estimates").
PROBE_LAUNCH_PHOTONS = 1 << 19
#: Photons of the launch that compiles the tracer's kernels before the timed ones.
_COMPILE_PHOTONS = 256
#: A bake estimated to take longer than this is announced with a warning before it starts.
LONG_BAKE_SECONDS = 600.0
#: Version of the probe's measurements (part of its key).
PROBE_VERSION = 5


@dataclass(frozen=True)
class Probe:
    """What a probe measured on this machine for one fiber (see the module docstring).

    A tracer launch of N photons takes ``launch_fixed_seconds + N / photons_per_second``
    (:func:`launch_model`, the rate with the binning; the larger timed launch held
    ``timed_photons``); ``launch_seconds``: what that makes one launch of
    ``launch_directions`` directions (a group,
    :func:`~usdfiber.bake.settings.directions_per_group`) at the bake's photons per batch;
    ``assembly_seconds``: assembling and writing, per direction;
    ``direction_bytes``: compressed bytes of a direction's arrays in the table file and
    ``fixed_bytes`` those of the rest (header, levels, width), both at ``photons`` per
    direction; ``error_constant``: ``c`` of ``rel L2 = c / sqrt(N)`` (rms over the probe
    directions); ``seconds``: the probe's own time."""

    key: str
    photons: int
    directions: int
    launch_seconds: float
    launch_directions: int
    photons_per_second: float
    assembly_seconds: float
    direction_bytes: float
    fixed_bytes: float
    error_constant: float
    seconds: float
    machine: dict[str, Any]
    timed_photons: int
    launch_fixed_seconds: float


@dataclass(frozen=True)
class BakeEstimate:
    """The estimated cost of baking one table: ``directions`` incoming directions of
    ``photons_per_direction`` photons (the mean with a row schedule; ``photons`` in all) in
    ``launches`` tracer launches,
    ``seconds`` of wall time on this machine, ``disk_bytes`` on disk, at most ``peak_bytes``
    of memory. ``exact``: whether the photons are known exactly (fixed photons) or predicted
    from the probe's error (target-error mode)."""

    label: str
    key: str
    directions: int
    photons_per_direction: int
    photons: int
    launches: int
    seconds: float
    disk_bytes: int
    peak_bytes: int
    exact: bool
    probe_seconds: float = 0.0

    def describe(self) -> str:
        """One line: time, size, memory and the work behind them."""
        from usdfiber.memory_budget import format_bytes

        per = f"{self.photons_per_direction:,}" + ("" if self.exact else " (predicted)")
        return (f"about {format_seconds(self.seconds)}, {format_bytes(self.disk_bytes)} on disk, "
                f"peak {format_bytes(self.peak_bytes)} ({self.directions} directions x {per} photons)")

    def to_json(self) -> dict[str, Any]:
        """The estimate as a JSON object (``render --json``, ``bake --json``)."""
        return {k: (round(v, 3) if isinstance(v, float) else v) for k, v in asdict(self).items()}


def format_seconds(s: float) -> str:
    """A duration as a short text: ``"45 s"``, ``"12 min"``, ``"3.2 h"``."""
    if s < 90:
        return f"{s:.0f} s" if s >= 10 else f"{s:.1f} s"
    if s < 5400:
        return f"{s / 60:.0f} min"
    return f"{s / 3600:.1f} h"


def _machine() -> dict[str, Any]:
    return {"platform": platform.platform(), "processor": platform.machine(), "cpus": os.cpu_count()}


def _probe_key(request: Any, settings: BakeSettings, photons: int) -> str:
    from usdfiber.bake.cache import physics_key

    blob = json.dumps({"physics": physics_key(request.inputs, 0, settings.result_inputs()),
                       "resolution": settings.resolution_deg, "batches": settings.batches,
                       "photons": int(photons), "machine": _machine(), "version": PROBE_VERSION},
                      sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()


def launch_shape(settings: BakeSettings, n_dirs: int, photons: int = PROBE_LAUNCH_PHOTONS) -> tuple[int, int]:
    """``(directions, photons per direction)`` of the probe's timed launch for a bake of
    ``n_dirs`` directions: the bake's photons per batch (at most ``photons``) for as many
    directions as make ``photons`` in all, at most a group
    (:func:`~usdfiber.bake.settings.directions_per_group`) and the table's directions."""
    per = min(int(settings.photons_per_batch), max(1, int(photons)))
    group = max(1, min(directions_per_group(settings), int(n_dirs)))
    return max(1, min(group, int(photons) // per)), per


def launch_model(n1: int, t1: float, n2: int, t2: float) -> tuple[float, float]:
    """``(a, rate)`` of ``t(N) = a + N / rate``, the time of a tracer launch of N photons,
    from two launches (``n1`` photons in ``t1`` seconds, ``n2`` in ``t2``).

    A launch runs in phases until its slowest photon is done, each phase recorded and started
    anew: ``a``, their cost, grows with the longest path among the launch's photons, slowly
    (polyester: 72 phases at 65k photons, 100 at 250k, 107 at 2M), so the line through two
    launches of 1e5-5e5 photons extrapolates to a bake's launches of up to 2M
    (``bench/REPORT.md``, "Cost estimates"). Noise is bounded: the marginal rate is taken between the larger
    launch's mean rate (``a = 0``; also when the larger launch was not the slower) and 4
    times it."""
    if n1 > n2:
        n1, t1, n2, t2 = n2, t2, n1, t1
    mean_rate = n2 / max(t2, 1e-9)
    if n2 <= n1 or t2 <= t1:
        return 0.0, mean_rate
    rate = min(max((n2 - n1) / (t2 - t1), mean_rate), 4.0 * mean_rate)
    return max(0.0, t2 - n2 / rate), rate


def _probe_photons(settings: BakeSettings) -> int:
    """Photons per probe direction: the bake's, at most PROBE_PHOTONS, whole batches."""
    n = min(int(settings.photons), PROBE_PHOTONS)
    return max(int(settings.batches), n - n % int(settings.batches))


def probe(request: Any, settings: BakeSettings, root: str | os.PathLike[str] | None = None) -> Probe:
    """Measure the cost of baking ``request``'s fiber with ``settings`` here (module docstring),
    or read the measurement kept under the cache ``root`` (None: measure, keep nothing)."""
    from usdfiber.bake.requests import TableRequest

    # Variant 0 stands for every variant of the fiber: one probe per fiber spec. A row
    # schedule changes how many photons, not what one costs: estimate() counts it.
    req0 = TableRequest(request.params, 0, list(request.prims))
    settings = replace(settings, row_photons=None)
    n = _probe_photons(settings)
    key = _probe_key(req0, settings, n)
    path = Path(root) / "probes" / f"{key}.json" if root is not None else None
    if path is not None:
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
            if data.get("key") == key:
                return Probe(**data)
        except (OSError, ValueError, TypeError):
            pass   # absent or damaged: probe again
    result = _measure(req0, settings, n, key)
    if path is not None:
        from usdfiber.atomic_file import write_atomic

        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            write_atomic(path, lambda tmp: Path(tmp).write_text(json.dumps(asdict(result)), encoding="utf-8"))
        except OSError:
            pass   # a read-only cache: the estimate stands, it is just not kept
    return result


def _measure(request: Any, settings: BakeSettings, n: int, key: str) -> Probe:
    """Trace, assemble and write the probe directions (module docstring)."""
    import warnings as _warnings

    from usdfiber.bake.assembly import assemble
    from usdfiber.bake.baker import bake_context, profile_fingerprint, table_directions, trace_directions
    from usdfiber.bake.grid import Grid
    from usdfiber.bake.storage import write_table_file

    t_start = time.perf_counter()
    profile, cut = request.profile(), request.cuticle_scales
    eta, beta = request.eta, request.beta_deg
    ctx_big = bake_context(profile, eta, beta, cut, replace(settings, photons=n, target_error=None))
    dirs_all = table_directions(request, settings)
    D = min(PROBE_DIRECTIONS, len(dirs_all))
    dirs = [dirs_all[min(len(dirs_all) - 1, int((j + 0.5) * len(dirs_all) / D))] for j in range(D)]
    # Time: a launch of N photons takes t(N) = a + N / rate (launch_model). Two sizes give a
    # and the rate: the probe directions at the bake's photons per direction (at most
    # PROBE_PHOTONS; they also give the size and the error), in two batches, and a launch
    # shaped like the bake's but smaller (launch_shape); each size is two launches, after a
    # small run that compiles the kernels. The line is fitted to the process's CPU time,
    # which other work on the machine barely changes (a difference of wall times would carry
    # its load's swings), and scaled to the larger launch's wall time.
    nb = settings.photons_per_batch
    group = min(directions_per_group(settings), len(dirs_all))
    k, m = launch_shape(settings, len(dirs_all))
    spread = [dirs_all[min(len(dirs_all) - 1, int((j + 0.5) * len(dirs_all) / k))] for j in range(k)]

    def two_batches(photons: int) -> Any:
        return replace(ctx_big, settings=replace(settings, photons=2 * photons, batches=2, target_error=None))

    def timed(ctx: Any, directions: list[tuple[int, int]]) -> tuple[list[dict[str, Any]], float, float]:
        t0, c0 = time.perf_counter(), time.process_time()
        out = trace_directions(ctx, directions)
        return out, (time.perf_counter() - t0) / 2, (time.process_time() - c0) / 2

    timed(two_batches(min(m, _COMPILE_PHOTONS)), spread[:1])       # compiles the kernels
    size_ctx = two_batches((n + 1) // 2)
    data, _, cpu_size = timed(size_ctx, dirs)
    _, wall_launch, cpu_launch = timed(two_batches(m), spread)
    a_cpu, rate_cpu = launch_model(D * size_ctx.settings.photons_per_batch, cpu_size, k * m, cpu_launch)
    wall_per_cpu = wall_launch / max(cpu_launch, 1e-9)
    fixed_launch, rate = a_cpu * wall_per_cpu, rate_cpu / wall_per_cpu
    # The probe directions as a small table, assembled and written as the bake does: on the
    # grid of a round fiber (one phi_i, the same outgoing bins), its theta_i rows taking the
    # probe directions in turn.
    t0 = time.perf_counter()
    # A header with the entries a baked table's has (their size is part of the file's).
    hdr = dict(request.header())
    hdr.update({"baked_diameter_um": 1.0, "incoming": settings.incoming, "eta": eta, "beta_deg": beta,
                "cuticle": None if cut is None else {"tilt_deg": cut[0], "height_um": cut[1], "spacing_um": cut[2]},
                "profile": {"name": str(getattr(profile, "name", "")), "loops": len(profile.loops),
                            "edges": int(sum(len(l) for l in profile.loops)), "smooth": False, "area_um2": 0.0,
                            "fingerprint": profile_fingerprint(profile)},
                "photons": {"per_direction_setting": n, "total": 0, "min_per_direction": 0, "max_per_direction": 0,
                            "hit": 0, "cut": 0, "batches": int(settings.batches)},
                "units": {"angles": "", "p": "", "albedo": "", "width": "", "levels": "", "lbar": "",
                          "baked_diameter_um": ""},
                "bake": {"settings": settings.result_inputs(), "trace_seconds": 0.0, "wall_seconds": 0.0,
                         "machine": _machine()},
                "error_estimate": {"metric": "", "rms": 0.0, "max": 0.0, "median": 0.0, "target": None},
                "levels_optical_depth": list(settings.levels), "leaks": 0, "cache_key": "0" * 64})
    # The bins this fiber gets, and as few theta_i rows (at least the probe directions) as an
    # incoming spacing that divides 90 deg allows: assembling costs per row (what is fixed
    # per table is then counted a few times over, a small part of a bake).
    res = float(ctx_big.grid.resolution_deg)
    n_bins = int(round(90.0 / res))
    rows = min((r for r in range(D, n_bins + 1) if n_bins % r == 0), default=n_bins)
    small_grid = Grid(res, True, True, incoming_deg=res * (n_bins // rows))
    with _warnings.catch_warnings():
        _warnings.simplefilter("ignore")
        table = assemble(small_grid, ctx_big.levels_um, (rows, 1), lambda ti, pi: data[ti % D], ctx_big.width_env,
                         hdr, band_tail=settings.band_tail, storage=settings.storage, threads=ASSEMBLY_THREADS)
    with tempfile.TemporaryDirectory(prefix="usdfiber-probe-") as tmp:
        f = Path(tmp) / "probe.npz"
        write_table_file(f, table.header, table.arrays)
        fixed = _fixed_bytes(f)
    assembly = (time.perf_counter() - t0) / rows
    # Bytes per direction: the distinct probe rows of each per-direction array, deflated as
    # one stream as the file's members are (the repeated rows would deflate to nothing).
    distinct = min(D, rows)      # a grid of fewer rows than probe directions holds fewer
    per_dir = sum(len(table_format.deflate(np.ascontiguousarray(table.arrays[name][:distinct])))
                  for name in _PER_DIRECTION) / distinct
    err = np.array([float(d["rel_error"]) for d in data])
    c = float(np.sqrt(np.mean(err[np.isfinite(err)] ** 2) * n)) if np.isfinite(err).any() else math.inf
    return Probe(key=key, photons=n, directions=D, launch_seconds=float(fixed_launch + group * nb / rate),
                 launch_directions=group, photons_per_second=float(rate), assembly_seconds=float(assembly),
                 direction_bytes=float(per_dir), fixed_bytes=float(fixed), error_constant=c,
                 seconds=time.perf_counter() - t_start, machine=_machine(), timed_photons=int(k * m),
                 launch_fixed_seconds=float(fixed_launch))


#: Arrays of a table file with one entry per incoming direction (they grow with the grid).
_PER_DIRECTION = ("p", "lbar", "p_scale", "albedo", "albedo_lbar", "band_start", "rel_error", "photons")


def _fixed_bytes(path: Path) -> float:
    """Bytes of a table file that do not grow with its directions: the file less its
    per-direction members' compressed data."""
    fixed = float(os.path.getsize(path))
    with zipfile.ZipFile(path) as z:
        for info in z.infolist():
            if info.filename.removesuffix(".npy") in _PER_DIRECTION:
                fixed -= info.compress_size
    return fixed


def estimate(request: Any, settings: BakeSettings, measured: Probe, key: str = "") -> BakeEstimate:
    """The cost of baking ``request`` with ``settings``, from a probe of its fiber."""
    from usdfiber.bake.baker import table_directions, table_grid
    from usdfiber.bake.reciprocity import scratch_bytes

    n_dirs = len(table_directions(request, settings))
    n_b = settings.photons_per_batch
    B = int(settings.batches)
    if settings.target_error is None:
        batches, exact = B, True
    else:
        # rel = c / sqrt(N): the batches that reach the target, as the baker plans them.
        need = (measured.error_constant / float(settings.target_error)) ** 2 * 1.05
        batches = max(B, int(math.ceil(min(need, int(settings.max_photons)) / n_b))) if math.isfinite(need) \
            else int(settings.max_photons) // n_b
        exact = False
    group = directions_per_group(settings)
    if settings.row_photons is None:
        per_dir = batches * n_b
        full, rest = divmod(n_dirs, group)
        launches = (full + (1 if rest else 0)) * batches
        photons = n_dirs * per_dir
    else:
        # A schedule: each row's batches; a group of directions takes as many launches as its
        # direction with the most batches (the baker traces them in grid order).
        grid = table_grid(request, settings)
        settings.check_rows(grid)
        dirs = table_directions(request, settings)
        nb = [settings.row_batches(ti) for ti, _ in dirs]
        photons = sum(settings.row_photons[ti] for ti, _ in dirs)     # met exactly (batch_photons)
        per_dir = int(round(photons / max(1, n_dirs)))
        launches = sum(max(nb[g:g + group]) for g in range(0, len(nb), group))
    # Every launch costs its fixed time, every photon the probe's rate (module docstring).
    seconds = (launches * measured.launch_fixed_seconds + photons / measured.photons_per_second
               + n_dirs * measured.assembly_seconds)
    if "reciprocity" in settings.estimator:
        # The averaging passes the table's H and G through scratch files once more.
        seconds += scratch_bytes(table_grid(request, settings), len(settings.levels)) / RECIPROCITY_BYTES_PER_SECOND
    disk = measured.fixed_bytes + n_dirs * measured.direction_bytes
    return BakeEstimate(label=request.label, key=key, directions=n_dirs, photons_per_direction=per_dir,
                        photons=photons, launches=launches, seconds=float(seconds), disk_bytes=int(round(disk)),
                        peak_bytes=int(settings.table_bytes()), exact=exact, probe_seconds=measured.seconds)


def estimate_request(request: Any, settings: BakeSettings, cache: Any = None) -> BakeEstimate:
    """:func:`estimate` with the probe of ``request``'s fiber, measured now or kept in the
    table ``cache`` (a :class:`~usdfiber.bake.cache.TableCache`, None: not kept)."""
    root = getattr(cache, "root", None)
    key = cache.key(request, settings) if cache is not None else ""
    return estimate(request, settings, probe(request, settings, root), key)


def total(estimates: Iterable[BakeEstimate]) -> dict[str, float]:
    """Seconds, bytes on disk and photons of several bakes one after the other."""
    es = list(estimates)
    return {"tables": len(es), "seconds": float(sum(e.seconds for e in es)),
            "disk_bytes": int(sum(e.disk_bytes for e in es)), "photons": int(sum(e.photons for e in es))}


def cheaper_hint(settings: BakeSettings) -> str:
    """How to get a cheaper table than ``settings`` give (for the long-bake warning)."""
    tips = []
    if settings.resolution_deg < 6:
        tips.append("a coarser grid (--resolution 6: about 9x fewer directions than 2)")
    if settings.target_error is None and settings.photons > 100_000:
        tips.append("fewer photons per direction (--photons 100000: the render's tables, 2.5-7 % error)")
    elif settings.target_error is not None and settings.target_error < 0.05:
        tips.append("a larger --target-error (the photons grow as its inverse square)")
    tips.append("--scheduler or --shard to spread it over machines")
    return "; ".join(tips)
