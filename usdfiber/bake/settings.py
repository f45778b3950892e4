"""How a table is baked (:class:`BakeSettings`) and the baker's error (:class:`BakeError`).

Every field of the settings changes the baked table, so all of them (with the baker's
version and the built-in profiles' resolution) enter the cache key through
:meth:`BakeSettings.result_inputs`.
"""
from __future__ import annotations

import math
import numbers
import os
from dataclasses import asdict, dataclass, replace
from typing import Any

from usdfiber.bake import band_limit
from usdfiber.bake.absorption import DEFAULT_LEVELS
from usdfiber.bake.grid import Grid

__all__ = ["BAKER_VERSION", "BUILTIN_PROFILE_VERTICES", "ESTIMATORS", "EXPECTED_ALLOCATIONS", "EXPECTED_HIST_BYTES", "EXPECTED_SAMPLERS", "EXPECTED_QUEUE_BYTES", "MAX_EXPECTED_NORMALS", "MAX_SPLIT_WALKS", "GROUP_DIRECTIONS", "GROUP_PHOTONS", "PROCESS_BYTES",
           "ASSEMBLY_THREADS", "RECIPROCITY_NODE_BYTES", "RECIPROCITY_THREADS", "RENDER_BAKE_SETTINGS", "RENDER_EXPECTED_SETTINGS", "ROUND_RENDER_RESOLUTION_DEG", "BakeError",
           "BakeSettings", "directions_per_group", "reciprocity_bytes", "render_bake_settings"]

#: Bumped when the baker's algorithm changes what it writes (part of the cache key).
BAKER_VERSION = 1
#: Vertices of the outer loop of built-in cross sections (part of the cache key).
BUILTIN_PROFILE_VERTICES = 512


#: Variance-reduction estimators a bake may combine (``BakeSettings.estimator``; none is the
#: plain estimator): "stratified", the beam offset and the first boundary event from
#: Owen-scrambled Sobol points per direction and batch (:mod:`usdfiber.bake.sampling`);
#: "reciprocity", sigma(i, o) and sigma(o, i) averaged with inverse-variance weights
#: (:mod:`usdfiber.bake.reciprocity`, box-filtered tables only); "split", every hit of the
#: outer surface split into ``BakeSettings.split_walks`` microsurface walks, those that leave
#: the fiber deposited with weight 1/K each (:func:`usdfiber.bake.tracer.trace`, fibers
#: without cuticle scales); "expected", at every event of the outer surface where leaving is
#: for good, the expected exit over ``BakeSettings.expected_normals`` microfacet normals is
#: histogrammed and the walk goes on (same function, fibers without cuticle scales; not with
#: "split"). All trace every direction with its own random streams.
ESTIMATORS = ("expected", "reciprocity", "split", "stratified")
#: Most walks per split (``BakeSettings.split_walks``).
MAX_SPLIT_WALKS = 64
#: Most normals per event of the "expected" estimator (``BakeSettings.expected_normals``).
MAX_EXPECTED_NORMALS = 64
#: How the "expected" estimator shares its normals among events
#: (``BakeSettings.expected_allocation``): "adaptive", from 1 to K in proportion to the
#: Fresnel weight of the event's exiting branch; "uniform", K each (tables baked before the
#: adaptive allocation existed).
EXPECTED_ALLOCATIONS = ("adaptive", "uniform")
#: How the "expected" estimator draws its normals (``BakeSettings.expected_sampler``): "ndf",
#: from the normal distribution, weighted by their visibility from the incoming direction (the
#: same expectation for a fraction of the arithmetic); "visible", from the visible normals
#: (tables baked before "ndf" existed).
EXPECTED_SAMPLERS = ("ndf", "visible")
#: The "expected" estimator's memory in the tracer: its in-kernel histograms of one launch at
#: most (launches are cut at direction boundaries to stay below), and its queue of events
#: (2^22 events of 84 bytes).
EXPECTED_HIST_BYTES = 256 << 20
EXPECTED_QUEUE_BYTES = (1 << 22) * 84
#: The baking process's own resident memory beside a table's: the interpreter, NumPy, Mitsuba,
#: Dr.Jit and LLVM (their code mapped from disk and their caches). Measured 0.27 GiB resident
#: once imported, file-backed pages up to 0.17 GiB during a bake.
PROCESS_BYTES = 512 << 20
#: The "reciprocity" estimator's temporaries per entry of the theta_i node being averaged
#: (partner indices, weights, the averaged H and G; 45-53 bytes measured with tracemalloc):
#: :func:`reciprocity_bytes`.
RECIPROCITY_NODE_BYTES = 64
#: Threads averaging theta_i nodes at once at most (each holds one node's temporaries:
#: :func:`reciprocity_bytes`).
RECIPROCITY_THREADS = max(1, min(4, os.cpu_count() or 1))
#: Threads doing the assembly's arithmetic per direction (:func:`usdfiber.bake.assembly.assemble`;
#: a few MB each): a full 2 deg table's assembly ran on one core while the other waited.
ASSEMBLY_THREADS = max(1, min(4, os.cpu_count() or 1))


def reciprocity_bytes(grid: Grid, threads: int = 1) -> int:
    """Peak bytes of the reciprocity averaging of a table of ``grid``
    (:class:`usdfiber.bake.reciprocity.ReciprocalAverage`), an upper bound: one absorption
    level of H and G of every direction in float32 (the rest of the table waits on disk),
    and the temporaries of the theta_i nodes averaged at once, one per thread
    (:data:`RECIPROCITY_NODE_BYTES` per entry). One thread is what a bake needs; the averaging
    takes up to :data:`RECIPROCITY_THREADS` where the memory budget holds them."""
    bins = grid.n_theta_o * grid.n_phi_o
    node = RECIPROCITY_NODE_BYTES * grid.n_phi_i * bins
    return 2 * 4 * grid.n_theta_i * grid.n_phi_i * bins + max(1, min(int(threads), grid.n_theta_i)) * node


class BakeError(ValueError):
    """A bake that cannot be done as asked (the message is one line)."""


#: Bounds of a bake's counts: beyond them a typing error would run for years or overflow the
#: tracer's 32-bit counters (a full 2 deg table at 1e12 photons per direction is ~10^6 CPU years).
MAX_PHOTONS = 10 ** 12
MAX_BATCHES = 4096
MAX_BOUNCES = 1 << 20


@dataclass(frozen=True)
class BakeSettings:
    """How a table is baked. Every field changes the result (and so the cache key).

    ``resolution_deg``: bin size (divides 90; the paper uses 2). ``incoming_deg``: the
    incoming node spacing, a multiple of ``resolution_deg`` dividing 90 (None:
    ``resolution_deg``, the paper's grid, whose tables and cache keys do not mention it).
    ``auto_resolution``: the outgoing bins and incoming nodes are those the fiber's band limit
    allows against the paper's 2 degree grid (:mod:`usdfiber.bake.band_limit`, chosen per table
    from its roughness and cross section and recorded in its header; ``resolution_deg`` then
    stays 2, the finest grid the rule chooses). ``photons``: photons per
    incoming direction, or the first amount when ``target_error`` is set (a relative L2
    error of p; batches are then added up to ``max_photons`` per direction). ``batches``:
    independent batches per direction for the error estimate (>= 2). ``levels``: absorption
    levels as optical depths across the diameter (sigma_a * D), starting at 0.
    ``band_tail``: mass per direction that may be dropped at the theta_o extremes.
    ``storage``: "float16" or "float32" for the per-bin arrays. ``incoming``: "centre"
    traces each incoming direction at its bin centre (the paper's sampling, for
    interpolation between nodes); "box" spreads the light over the incoming bin (each
    photon its own direction, in proportion to the power the fiber intercepts; with cuticle
    scales one stratified point per batch), so that each entry averages over both bins and
    the table is reciprocal bin for bin. ``estimator``:
    the variance-reduction estimators used (names from :data:`ESTIMATORS`; empty: the plain
    estimator, whose tables and cache keys do not mention it). ``row_photons``: photons per
    incoming direction of each theta_i row (a schedule, e.g. each row at its own error
    target), met exactly, in :meth:`row_batches` batches of at most ``photons / batches``
    (:meth:`batch_photons`).
    """

    resolution_deg: float = 2.0
    photons: int = 1_000_000
    target_error: float | None = None
    max_photons: int = 64_000_000
    batches: int = 8
    max_bounces: int = 4096
    seed: int = 0
    levels: tuple[float, ...] = DEFAULT_LEVELS
    band_tail: float = 1e-5
    storage: str = "float16"
    incoming: str = "centre"
    estimator: tuple[str, ...] = ()
    incoming_deg: float | None = None
    auto_resolution: bool = False
    #: Walks per outer-surface hit of the "split" estimator (part of the cache key only with it).
    split_walks: int = 8
    #: Normals per outer-surface event of the "expected" estimator (in the cache key
    #: only with it; bench/REPORT.md, section 7, chose the default: 32 gains most on whole
    #: 2 degree tables, 1.2x over 16 and 1.0-1.2x over 64); the most per event with the adaptive
    #: allocation.
    expected_normals: int = 32
    #: Normals per event of the "expected" estimator: one of :data:`EXPECTED_ALLOCATIONS` (in
    #: the cache key only with it, and only when adaptive: uniform tables keep earlier keys).
    expected_allocation: str = "adaptive"
    #: How the "expected" estimator draws its normals: one of :data:`EXPECTED_SAMPLERS` (in the
    #: cache key only with it, and only when "ndf": tables of visible normals keep earlier keys).
    expected_sampler: str = "ndf"
    row_photons: tuple[int, ...] | None = None

    def __post_init__(self) -> None:
        # Canonical types (10 and 10.0, NumPy integers): equal settings have equal cache keys.
        auto = bool(self.auto_resolution)
        object.__setattr__(self, "auto_resolution", auto)
        for name, kind in (("resolution_deg", float), ("photons", int), ("max_photons", int), ("batches", int),
                           ("max_bounces", int), ("seed", int), ("band_tail", float)):
            value = getattr(self, name)
            try:
                canonical = kind(value)
            except (TypeError, ValueError, OverflowError):
                raise BakeError(f"{name} must be a number, got {value!r}") from None
            if kind is int and canonical != value:
                raise BakeError(f"{name} must be an integer, got {value!r}")
            object.__setattr__(self, name, canonical)
        if self.target_error is not None:
            object.__setattr__(self, "target_error", float(self.target_error))
        if not 0 <= self.seed < 2 ** 32:
            raise BakeError(f"seed must be an integer from 0 to 2^32 - 1, got {self.seed}")
        try:  # validates the resolution and the incoming spacing (None when equal to it)
            g = Grid(self.resolution_deg, True, False, None if self.incoming_deg is None else float(self.incoming_deg))
        except (TypeError, ValueError) as exc:
            raise BakeError(str(exc)) from None
        object.__setattr__(self, "incoming_deg", g.incoming_deg)
        if auto and (self.resolution_deg != band_limit.FINEST_DEG or self.incoming_deg is not None):
            raise BakeError("resolution 'auto' chooses the bins and incoming nodes itself: give no resolution "
                            "or incoming spacing with it")
        for name in ("photons", "max_photons"):
            if not 1 <= getattr(self, name) <= MAX_PHOTONS:
                raise BakeError(f"{name} must be from 1 to {MAX_PHOTONS:.0e} per direction, got {getattr(self, name)}")
        if self.target_error is not None and not (1e-4 <= float(self.target_error) < 1):
            raise BakeError(f"target error must be in [1e-4, 1) (0.01 % already takes 10^4 times the photons "
                            f"of 1 %), got {self.target_error}")
        if not 2 <= int(self.batches) <= MAX_BATCHES:
            raise BakeError(f"batches must be from 2 (the error estimate needs a variance) to {MAX_BATCHES}, "
                            f"got {self.batches}")
        if not 1 <= int(self.max_bounces) <= MAX_BOUNCES:
            raise BakeError(f"max_bounces must be from 1 to {MAX_BOUNCES}, got {self.max_bounces}")
        lv = tuple(float(x) for x in self.levels)
        if not lv or lv[0] != 0.0 or any(b <= a for a, b in zip(lv, lv[1:])) or not all(map(math.isfinite, lv)):
            raise BakeError(f"levels must start at 0 and increase, got {list(self.levels)}")
        object.__setattr__(self, "levels", lv)
        if not (0.0 <= float(self.band_tail) < 0.1):
            raise BakeError(f"band_tail must be in [0, 0.1), got {self.band_tail}")
        if self.storage not in ("float16", "float32"):
            raise BakeError(f"storage must be float16 or float32, got {self.storage!r}")
        if self.incoming not in ("centre", "box"):
            raise BakeError(f"incoming must be 'centre' or 'box', got {self.incoming!r}")
        raw = self.estimator if self.estimator is not None else ()
        est = (raw,) if isinstance(raw, str) else tuple(raw)
        est = tuple(sorted({str(e) for e in est if str(e) not in ("", "plain")}))
        unknown = [e for e in est if e not in ESTIMATORS]
        if unknown:
            raise BakeError(f"unknown estimator {unknown[0]!r}: expected some of {', '.join(ESTIMATORS)} or 'plain'")
        if "reciprocity" in est and self.incoming != "box":
            # Centre-sampled nodes against bin-averaged outputs are not reciprocal bin for bin:
            # averaging the two halves would mix two different quantities (a bias).
            raise BakeError("estimator 'reciprocity' needs incoming='box' (only box-filtered tables "
                            "are reciprocal bin for bin)")
        object.__setattr__(self, "estimator", est)
        sw = self.split_walks
        if isinstance(sw, bool) or not isinstance(sw, (int, float)) or int(sw) != sw or not 1 <= int(sw) <= MAX_SPLIT_WALKS:
            raise BakeError(f"split_walks must be an integer from 1 to {MAX_SPLIT_WALKS}, got {sw!r}")
        object.__setattr__(self, "split_walks", int(sw))
        en = self.expected_normals
        if (isinstance(en, bool) or not isinstance(en, (int, float)) or int(en) != en
                or not 1 <= int(en) <= MAX_EXPECTED_NORMALS):
            raise BakeError(f"expected_normals must be an integer from 1 to {MAX_EXPECTED_NORMALS}, got {en!r}")
        object.__setattr__(self, "expected_normals", int(en))
        if self.expected_allocation not in EXPECTED_ALLOCATIONS:
            raise BakeError(f"expected_allocation must be one of {', '.join(EXPECTED_ALLOCATIONS)}, "
                            f"got {self.expected_allocation!r}")
        if self.expected_sampler not in EXPECTED_SAMPLERS:
            raise BakeError(f"expected_sampler must be one of {', '.join(EXPECTED_SAMPLERS)}, "
                            f"got {self.expected_sampler!r}")
        if "expected" in est and "split" in est:
            raise BakeError("estimators 'expected' and 'split' cannot be combined (both replace the exits "
                            "through the outer surface)")
        if self.row_photons is not None:
            rows = self.row_photons
            if isinstance(rows, (str, bytes)) or not hasattr(rows, "__len__") or not 1 <= len(rows) <= 4096:
                raise BakeError(f"row_photons must be a list of photons per theta_i row, got {rows!r}")
            canon = []
            for n in rows:
                if isinstance(n, bool) or not isinstance(n, numbers.Real) or not math.isfinite(n) or int(n) != n \
                        or not 1 <= int(n) <= MAX_PHOTONS:
                    raise BakeError(f"row_photons must hold integers from 1 to {MAX_PHOTONS:.0e}, got {n!r}")
                canon.append(int(n))
            if self.target_error is not None or auto:
                # Both choose the photons or the rows themselves.
                raise BakeError("row_photons cannot be combined with a target error or resolution 'auto'")
            if min(canon) < int(self.batches):
                raise BakeError(f"row_photons must give every row at least one photon per batch "
                                f"({self.batches} batches), got {min(canon)}")
            object.__setattr__(self, "row_photons", tuple(canon))
        if self.incoming == "box" and (auto or self.incoming_deg is not None):
            # A box node spreads its light over one outgoing bin's solid angle, not a coarser cell.
            raise BakeError("incoming='box' needs incoming nodes as far apart as the bins (no "
                            "incoming_deg, no resolution 'auto')")

    def grid_for(self, beta_deg: float, round_profile: bool, cuticle: bool) -> Grid:
        """The grid of a table of a fiber with roughness ``beta_deg``, a rotationally symmetric
        profile or not and cuticle scales or not (these also set the grid's symmetries)."""
        if self.auto_resolution:
            res, inc = band_limit.band_limited_grid(beta_deg, round_profile, cuticle, photons=self.photons,
                                                    target_error=self.target_error)
        else:
            res, inc = float(self.resolution_deg), self.incoming_deg
        return Grid(res, theta_symmetric=not cuticle, phi_invariant=round_profile, incoming_deg=inc)

    @property
    def photons_per_batch(self) -> int:
        """Photons of one batch of one direction (``photons / batches``, rounded up)."""
        return max(1, int(math.ceil(int(self.photons) / int(self.batches))))

    def row_batches(self, ti: int) -> int:
        """Batches a direction of theta_i row ``ti`` is first given: ``batches``, or with
        ``row_photons`` as many as hold the row's photons at ``photons_per_batch`` at most (at
        least ``batches``)."""
        if self.row_photons is None:
            return int(self.batches)
        return max(int(self.batches), int(math.ceil(self.row_photons[ti] / self.photons_per_batch)))

    def batch_photons(self, ti: int, b: int) -> int:
        """Photons of batch ``b`` of a direction of theta_i row ``ti``: ``photons_per_batch``,
        or with ``row_photons`` the row's photons exactly, shared as evenly as whole photons
        allow among its :meth:`row_batches` (the first ``N mod B`` one more). A schedule is
        then met to the photon while each batch holds up to ``photons_per_batch``: large
        batches cost less per photon (each batch of a direction pays for its own histograms,
        bench/REPORT.md, section 7), and a row need not be rounded up to whole batches.
        Batches past the row's (more in target-error mode, which has no schedule) are full."""
        if self.row_photons is None:
            return self.photons_per_batch
        n, nb = self.row_photons[ti], self.row_batches(ti)
        if b >= nb:
            return self.photons_per_batch
        return n // nb + (1 if b < n % nb else 0)

    def whole_batch_schedule(self) -> bool:
        """Whether every row of ``row_photons`` is whole batches of ``photons_per_batch`` (at
        least ``batches`` of them): the photons such a schedule gives are the same whether rows
        are shared evenly (:meth:`batch_photons`) or rounded up to whole batches, as they were
        before batches could be shared."""
        per, nb = self.photons_per_batch, int(self.batches)
        return all(n % per == 0 and n >= nb * per for n in (self.row_photons or ()))

    def check_rows(self, grid: Grid) -> None:
        """Refuse a ``row_photons`` schedule that is not one entry per theta_i row of ``grid``."""
        if self.row_photons is not None and len(self.row_photons) != grid.n_theta_i:
            raise BakeError(f"row_photons has {len(self.row_photons)} rows; the table's grid has "
                            f"{grid.n_theta_i} theta_i rows")

    def table_bytes(self) -> int:
        """Peak bytes of baking one table with these settings, an upper bound: the assembled
        per-bin arrays ``p`` and ``lbar`` with a full theta_o band (:mod:`usdfiber.bake.storage`),
        the float64 sums of a group of directions in flight and their batches' running moments
        (:mod:`usdfiber.bake.statistics`: not one histogram per batch, so not growing with batches)
        and the tracer's photons (about 2^21 at 64 bytes); with the "reciprocity" estimator,
        also one absorption level of every direction's histograms (:func:`reciprocity_bytes`);
        with "expected", the tracer's histograms and event queue (:data:`EXPECTED_HIST_BYTES`,
        :data:`EXPECTED_QUEUE_BYTES`); and the process's own (:data:`PROCESS_BYTES`), so that it
        bounds the whole process's resident peak, file-backed pages included."""
        # (with auto_resolution, resolution_deg is the finest grid the rule chooses)
        g = Grid(self.resolution_deg, True, False, self.incoming_deg)
        K = len(self.levels)
        per_direction = K * g.n_theta_o * g.n_phi_o
        item = 2 if self.storage == "float16" else 4
        group = directions_per_group(self)
        symmetrize = reciprocity_bytes(g) if "reciprocity" in self.estimator else 0
        expected = EXPECTED_HIST_BYTES + EXPECTED_QUEUE_BYTES if "expected" in self.estimator else 0
        moments = 3 * g.n_theta_o * g.n_phi_o * 8     # mean, squared deviations, solid angles
        return (g.n_theta_i * g.n_phi_i * per_direction * 2 * item + group * (per_direction * 16 + moments)
                + (1 << 21) * 64 + symmetrize + expected + PROCESS_BYTES)

    def result_inputs(self) -> dict[str, Any]:
        """Everything that changes a baked table (for cache keys and headers)."""
        d = asdict(self)
        d["levels"] = list(self.levels)
        if self.estimator:
            d["estimator"] = list(self.estimator)
        else:
            d.pop("estimator")  # the plain estimator: keys of tables baked before it existed
        if "split" not in self.estimator:
            d.pop("split_walks")    # only used by the split estimator
        if "expected" not in self.estimator:
            d.pop("expected_normals")    # only used by the expected-value estimator
        if "expected" not in self.estimator or self.expected_allocation == "uniform":
            d.pop("expected_allocation")     # uniform: keys of tables baked before it existed
        if "expected" not in self.estimator or self.expected_sampler == "visible":
            d.pop("expected_sampler")        # visible normals: keys of tables baked before "ndf"
        if self.incoming == "box":
            # Box bins of extruded fibers draw a light direction per photon (statistics.py),
            # no longer one per batch: other photons than box tables baked before.
            d["box_sampling"] = "photon"
        if self.incoming_deg is None:
            d.pop("incoming_deg")  # the paper's grid: keys of tables baked before it existed
        if self.auto_resolution:
            d["band_limit_rule"] = band_limit.RULE_VERSION
        else:
            d.pop("auto_resolution")  # the paper's grid: keys of tables baked before it existed
        if self.target_error is None:
            d.pop("max_photons")  # only used in target-error mode
        if self.row_photons is None:
            d.pop("row_photons")  # no schedule: keys of tables baked before it existed
        else:
            d["row_photons"] = list(self.row_photons)
            if not self.whole_batch_schedule():
                # Rows met to the photon in shared batches, where they used to be rounded up to
                # whole batches: other photons than a table of the same schedule baked before.
                d["row_batches"] = "shared"
        d["builtin_profile_vertices"] = BUILTIN_PROFILE_VERTICES
        d["baker_version"] = BAKER_VERSION
        return d


#: Photons per shared tracer launch when directions are traced together (the tracer's batch).
GROUP_PHOTONS = 1 << 21
#: At most this many directions are traced (and held in memory) together.
GROUP_DIRECTIONS = 64


def directions_per_group(settings: BakeSettings) -> int:
    """Directions traced together: about :data:`GROUP_PHOTONS` photons per shared batch, at
    most :data:`GROUP_DIRECTIONS`."""
    return max(1, min(GROUP_DIRECTIONS, GROUP_PHOTONS // settings.photons_per_batch))


#: Bake settings for tables baked on demand by a renderer bridge or a material writer, for
#: fibers whose cross section is not round and that have cuticle scales: a 6 degree grid
#: (renderers interpolate between bins) and 100k photons per incoming direction (2.5-7 %
#: relative L2 error per direction, rms over the table, for the presets: bench/REPORT.md,
#: "grouping"). Fibers without cuticle scales get the expected-value estimator instead
#: (:data:`RENDER_EXPECTED_SETTINGS`) and round fibers finer tables: :func:`render_bake_settings`.
#: `usdfiber bake` makes the paper's 2 degree tables.
RENDER_BAKE_SETTINGS = BakeSettings(resolution_deg=6.0, photons=100_000, batches=4)
#: The render's tables of fibers without cuticle scales: the expected-value estimator with up to
#: 16 normals per event (adaptive allocation, normals from the distribution) at 15k photons per
#: direction. Measured on whole bakes (bench/REPORT.md, section 7, "whole bakes", "allocation"
#: and "cheaper normals"): 8 visible normals reached a lower error than 100k plain photons in
#: 0.69-0.83x the time (a silk or cotton variant at 6 degrees, polyester at 2); 16 normals from
#: the distribution take 0.96-1.09x the time of those at 14-19 % less error (1.4x at equal
#: error). A silk close-up with 6 degree tables of 8 visible normals is within 6 % of a full
#: 2 degree table's highlight (section 10, "silk against a full 2 deg table").
RENDER_EXPECTED_SETTINGS = replace(RENDER_BAKE_SETTINGS, photons=15_000, estimator=("expected",),
                                   expected_normals=16)
#: Bins and incoming nodes of the tables a renderer bakes on demand for round fibers.
ROUND_RENDER_RESOLUTION_DEG = 2.0


def render_bake_settings(round_profile: bool, resolution_deg: float | None = None,
                         photons: int | None = None, cuticle_scales: bool = False) -> BakeSettings:
    """The settings of a table that a renderer or material writer bakes on demand for a fiber
    whose cross section is round (rotationally symmetric, as the baker tests it) or not,
    chosen per fiber by the error of close-up renders against finer tables (bench/REPORT.md,
    section 10; :func:`usdfiber.bcsdf.render_settings_for` applies it to a table request).

    A round fiber has one incoming azimuth, so the paper's 2 degree grid costs it 45
    directions (under a minute on 2 idle cores), and on a polyester close-up it is within the
    render's noise where 6 degree tables dim the highlight by 13 % (a 16 % error on 4 x 4 pixel
    blocks, 3.8x the noise between two render seeds): such fibers get
    :data:`usdfiber.bake.settings.ROUND_RENDER_RESOLUTION_DEG`. Other fibers trace every azimuth (900 directions at 6
    degrees, 8,100 at 2), and silk's wider lobes lose a few percent of the highlight to 5-6
    degree bins: they get :data:`usdfiber.bake.settings.RENDER_BAKE_SETTINGS`'s grid. Fibers
    without cuticle scales are baked with the expected-value estimator at fewer photons
    (:data:`usdfiber.bake.settings.RENDER_EXPECTED_SETTINGS`: a lower error in less time);
    fibers with ``cuticle_scales``, which it cannot take, with the plain estimator.
    ``resolution_deg`` and ``photons``, when given, override the choice for every fiber
    (``--bake-resolution``, ``--bake-photons``); given photons are plain photons (a bake's time
    follows them as before, and tables baked with them before keep their keys).
    """
    st = RENDER_BAKE_SETTINGS if cuticle_scales or photons is not None else RENDER_EXPECTED_SETTINGS
    if resolution_deg is not None:
        st = replace(st, resolution_deg=float(resolution_deg), incoming_deg=None)
    elif round_profile:
        st = replace(st, resolution_deg=ROUND_RENDER_RESOLUTION_DEG, incoming_deg=None)
    if photons is not None:
        st = replace(st, photons=int(photons))
    return st
