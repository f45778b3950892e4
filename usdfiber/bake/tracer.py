"""Photon tracer of the baker: one fiber, one incoming direction, Dr.Jit + Mitsuba (Embree/OptiX).

Conventions (fiber frame): the fiber runs along +z; the cross-section is in the xy plane;
phi is measured from +x towards +y; sin(theta) = w.z. ``omega_i`` points towards the light,
so photons travel along ``-omega_i``. Lengths are micrometres.

Photons are launched uniformly over the beam that covers the outer loop's shadow seen from
``phi_i`` (width ``W(phi_i)``) plus a margin on each side; photons that never touch the fiber
are not counted, so ``albedo = surviving weight / photons that hit``.

Every boundary is a rough dielectric interface with Beckmann microfacets (alpha = tan(beta),
Aliaga et al. Sec. 3.1) around the smooth shading normal. A photon that reaches it performs
the microsurface random walk of Heitz et al. 2016 ("Multiple-scattering microfacet BSDFs with
the Smith model"; uncorrelated uniform heights): at each event the hit height follows the Smith
masking, the microfacet normal is drawn from the normals visible from the photon's direction,
and the exact unpolarized Fresnel factor picks reflection or refraction (total internal
reflection always reflects). The walk ends when the photon escapes the microsurface, above
(reflected) or below (transmitted). So a sample that a single microfacet would send to the wrong
side of the macro surface is neither discarded (energy loss) nor re-sampled (a biased lobe): it
is the next event of the walk, which conserves energy exactly and keeps the boundary reciprocal.
The walk is the same as in :mod:`usdfiber.bake.reference_tracer`. ``beta = 0`` is a smooth
interface: one Fresnel event about the shading normal. Absorption is not simulated: each photon
carries the path length it travelled inside the material, and any ``sigma_a`` is applied
afterwards as ``exp(-sigma_a * L)`` (see :mod:`usdfiber.bake.binning`).

Near grazing, the smooth normal may put the incoming photon behind the surface; the flat
triangle normal is the macro normal of that event. A direction that leaves a boundary on the
wrong side of the flat triangle (within the small angle between the smooth and the flat
normal) is mirrored across the triangle's plane. A hit seen from the side opposite to the photon's
medium (a sliver thinner than float32 resolves, e.g. the tip of a slit lumen) is passed
through without interaction; a photon in the material that misses everything slipped through
a crack and is nudged and traced once more. ``TraceResult.extra["leaks"]`` counts both (about
1e-6 per photon); ``extra["forced"]`` counts walks stopped after 256 microsurface events.

Splitting at the outer surface (``split=K``, extruded fibers): a photon that reaches the outer
surface (from outside or from inside; hole walls are not split) pauses; between phases, K
independent microsurface walks are run from its state, K lanes per photon, in a loop of their
own without ray casts. Each of the K results has exactly the distribution of the one walk it
replaces, so depositing each result that leaves the fiber for good (no re-entry: a ray cast,
skipped when the outer loop is convex) with weight w / K, and continuing with one of the
others, chosen uniformly, with probability (their number) / K (Russian roulette, so that paths
are as long as without splitting), estimates the same far field. A smooth surface draws the K
Fresnel choices at once, inside the kernel. The result then holds several weighted exits per
photon (:attr:`TraceResult.weight`). Its cost and gain: bench/REPORT.md, section 7.

The expected-value estimator at the outer boundary (``expected=K``, extruded fibers): at a
microfacet event of a walk on an outer face, the outcome "the branch that ends outside is taken
(reflection on the outside, refraction from the material), then the next height step leaves the
microsurface, then the fiber for good" is replaced by its expectation
w E_m[P_side(m) G_leave(h, wo(m)) 1{escapes} 1{settle(wo(m)) in bin}] over the normals m
visible from wi, estimated with K normals of a randomly shifted rank-1 lattice and histogrammed
at every absorption level (:class:`ExitHistogram`). The normals are drawn from the normal
distribution D(m) cos(theta_m) and weighted by the visible density over it,
<wi, m>+ / ((1 + Lambda(wi)) cos(theta_i) cos(theta_m)) (``expected_sampler="ndf"``, the
default: a logarithm and a sine per normal, where Beckmann's visible-normal sampler inverts
its distribution numerically, 13x the time; bench/REPORT.md s. 7), or from the visible normals
themselves (``"visible"``, weight 1). On an edge of the outline's convex hull
(:attr:`FiberMesh.outer_hull`: the whole fiber lies behind that edge's line) every exit escapes;
on the concave sides an escape ray per normal decides, as the real photon's next ray does (not
cast where the exit's direction lies in its edge's wedge of directions that leave the pocket for
good, :mod:`usdfiber.bake.pockets`: that ray would miss). The
real walk goes on; if it then takes exactly that outcome it ends unrecorded (on the concave
sides: when its next ray escapes), so deposit and kill cover the same outcomes and the estimate
is unbiased. Events are queued in the loop and their normals evaluated between phases, on just
the events (in the loop every lane would pay for them at every iteration). An event gets 1 to K
normals (``expected_allocation="adaptive"``, the default; "uniform": K each) in proportion to
the probability of its exiting branch, decided from its state before any normal is drawn, so
every normal stays uniform and the estimate unbiased (:data:`_EV_TILT`). Lumen walls, normals
seen from below the macro surface and forced walks take the plain estimator: the choice
depends on the state only. A smooth outer boundary (hull edges only) deposits its exiting Fresnel branch with
weight w P_out and continues the other with w (1 - P_out) (Russian roulette below
``_RR_WEIGHT``). Its cost and gain: bench/REPORT.md, section 7.
"""
from __future__ import annotations

import importlib
import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from usdfiber.backend import mitsuba
from usdfiber.bake import sampling
from usdfiber.bake.fiber_mesh import FiberMesh, build_fiber_mesh, profile_bounds
from usdfiber.bake.pockets import escape_wedges
from usdfiber.bake.settings import (EXPECTED_ALLOCATIONS, EXPECTED_HIST_BYTES, EXPECTED_QUEUE_BYTES, EXPECTED_SAMPLERS,
                                    MAX_EXPECTED_NORMALS, MAX_SPLIT_WALKS)

__all__ = ["ExitHistogram", "FiberScene", "TraceResult", "prepare", "trace", "trace_many"]


@dataclass
class TraceResult:
    """Exits of the photons that hit the fiber (numpy, one row per exit).

    ``directions`` are unit exit directions in the fiber frame (towards the viewer), ``path_length``
    is the distance travelled inside the material (holes excluded), in micrometres; ``cut`` marks
    photons stopped by ``max_bounces`` or ``max_steps`` (their direction is meaningless and they
    carry no weight); ``bounces`` counts boundary hits (a microsurface walk is one).
    ``weight`` is each exit's weight at zero absorption: None means one exit of weight 1 per
    photon that hit (the plain estimator); with splitting a photon leaves several exits of
    fractional weight (a photon whose path ended inside a split has no row of its own).
    With the expected-value estimator, ``histogram`` (levels, 2, bins) float64 holds the exits
    deposited as expectations, binned in the kernel into ``histogram_bins`` at its absorption
    levels (summed weight, and weight x L, per bin; not divided by ``n_hit``); the rows hold
    the other exits.
    """

    directions: np.ndarray          # (M, 3) float32
    path_length: np.ndarray         # (M,) float32, micrometres
    cut: np.ndarray                 # (M,) bool
    bounces: np.ndarray             # (M,) uint32, boundary hits before leaving
    n_launched: int
    n_hit: int
    beam_width: float               # W(phi_i) of the profile, micrometres
    launch_width: float             # width the photons were spread over (W + both margins)
    theta_i: float
    phi_i: float
    eta: float
    beta_deg: float
    seconds: float = 0.0            # wall time of the trace (mesh build excluded)
    extra: dict = field(default_factory=dict)
    weight: np.ndarray | None = None  # (M,) float32 exit weights; None: all 1
    histogram: np.ndarray | None = None      # (levels, 2, bins) float64, expected exits
    histogram_bins: "ExitHistogram | None" = None

    def histogram_level(self, sigma_a: float) -> int:
        """Index of absorption ``sigma_a`` (1/um) among the histogram's levels (ValueError if absent)."""
        lv = np.asarray(self.histogram_bins.levels, dtype=np.float64)
        k = np.flatnonzero(np.isclose(lv, float(sigma_a), rtol=1e-6, atol=0.0))
        if not k.size:
            raise ValueError(f"sigma_a {sigma_a} is not one of the expected-value histogram's levels "
                             f"{list(self.histogram_bins.levels)}")
        return int(k[0])

    def exit_weights(self) -> np.ndarray:
        """(M,) float64 weight of each exit at zero absorption (0 for cut photons)."""
        w = np.ones(len(self.path_length)) if self.weight is None else self.weight.astype(np.float64)
        return np.where(np.asarray(self.cut, dtype=bool), 0.0, w)

    @property
    def n_cut(self) -> int:
        """Photons stopped by ``max_bounces`` (or ``max_steps``)."""
        return int(np.count_nonzero(self.cut))

    @property
    def measured_width(self) -> float:
        """Beam width the fiber actually intercepted (launch width x hit fraction), micrometres.

        Equals ``beam_width`` up to noise for an extruded fiber; for a cuticle fiber it is the
        shadow width averaged along z.
        """
        return self.launch_width * self.n_hit / max(self.n_launched, 1)

    def weights(self, sigma_a: float | np.ndarray = 0.0) -> np.ndarray:
        """Per-photon surviving weight exp(-sigma_a L) (0 for cut photons); sigma_a in 1/um.

        A vector ``sigma_a`` of k channels gives an (M, k) array.
        """
        s = np.asarray(sigma_a, dtype=np.float64)
        L = self.path_length.astype(np.float64)
        w = np.exp(-np.multiply.outer(L, s))
        return w * self.exit_weights().reshape((-1,) + (1,) * s.ndim)

    def albedo(self, sigma_a: float | np.ndarray = 0.0) -> float | np.ndarray:
        """Surviving weight / photons that hit, for absorption ``sigma_a`` (1/um); with an
        expected-value histogram, ``sigma_a`` must be among its levels."""
        total = self.weights(sigma_a).sum(axis=0)
        if self.histogram is not None:
            s = np.atleast_1d(np.asarray(sigma_a, dtype=np.float64))
            extra = np.array([self.histogram[self.histogram_level(x), 0].sum() for x in s])
            total = total + (extra[0] if np.ndim(sigma_a) == 0 else extra)
        return total / max(self.n_hit, 1)


@dataclass
class FiberScene:
    """A fiber segment loaded into Mitsuba, with the Dr.Jit buffers the tracer gathers from."""

    profile: Any
    mesh: FiberMesh
    scene: Any
    faces: Any          # mi.UInt32, flat (F*3)
    normals: Any        # mi.Float, flat (V*3) shading normals
    face_normals: Any   # mi.Float, flat (F*3) geometric normals
    cuticle: tuple[float, float, float] | None
    outer: Any = None   # mi.UInt32, (F,): 1 where the face is on the outer surface
    hull: Any = None    # mi.UInt32, (F,): 1 where it is on an edge of the outline's convex hull
    #: mi.Float, flat (F*4): each face's wedge of exit directions that leave its pocket for good
    #: (:func:`usdfiber.bake.pockets.escape_wedges`; zeros: none), for extruded fibers whose
    #: outline is not convex; None otherwise.
    wedge: Any = None


#: Exits whose direction lies in their edge's wedge (:mod:`usdfiber.bake.pockets`) skip the
#: escape ray, which would miss (a switch for the tests that compare both ways).
_POCKET_WEDGES = True


def ray_offset(mesh: FiberMesh) -> float:
    """How far the tracer moves a boundary result off its face (along the face normal):
    about 100 float32 ulps of the largest coordinate."""
    scale = max(mesh.bound_radius, mesh.z_period if not mesh.z_invariant else 0.0, 1.0)
    return float(scale * 2.0**-16)


def _pocket_wedges(profile: Any, mesh: FiberMesh) -> np.ndarray | None:
    """(F, 4) wedges of the faces of an extruded, non-convex outline (zeros off the outer
    loop), from the float32 vertices the ray casts see; None where no exit needs a ray."""
    if not mesh.z_invariant or mesh.outer_convex or mesh.outer_edge is None:
        return None
    loop = np.asarray(profile.loops[0], dtype=np.float32).astype(np.float64)
    eps = ray_offset(mesh)
    # The mesh's own hull flags (an edge without faces counts as off the hull: a longer chain
    # only narrows the wedges).
    on = mesh.outer_edge >= 0
    hull = np.zeros(len(loop), bool)
    hull[mesh.outer_edge[on]] = mesh.outer_hull[on]
    # Exit points lie eps off the edge's line up to the float32 rounding of the hit point (a few
    # ulps of coordinates of order 1).
    wedges = escape_wedges(loop, hull, offset=(0.5 * eps, 2.0 * eps))
    out = np.zeros((len(mesh.faces), 4))
    out[on] = wedges[mesh.outer_edge[on]]
    return out


def prepare(profile: Any, cuticle: tuple[float, float, float] | None = None, **mesh_kw: Any) -> FiberScene:
    """Mesh ``profile`` (see :func:`build_fiber_mesh`) and load it into a Mitsuba scene."""
    mi = mitsuba()
    mesh = build_fiber_mesh(profile, cuticle, **mesh_kw)
    wedges = _pocket_wedges(profile, mesh)
    scene = mi.load_dict({"type": "scene", "fiber": mesh.to_mitsuba(mi)})
    return FiberScene(
        profile=profile,
        mesh=mesh,
        scene=scene,
        faces=mi.UInt32(mesh.faces.astype(np.uint32).ravel()),
        normals=mi.Float(mesh.normals.astype(np.float32).ravel()),
        face_normals=mi.Float(mesh.face_normals.astype(np.float32).ravel()),
        cuticle=cuticle,
        outer=mi.UInt32(np.asarray(mesh.outer_faces, dtype=np.uint32)),
        hull=mi.UInt32(np.asarray(mesh.outer_hull if mesh.outer_hull is not None
                                  else np.zeros(len(mesh.faces), bool), dtype=np.uint32)),
        wedge=None if wedges is None else mi.Float(wedges.astype(np.float32).ravel()),
    )


def _projected_width(profile: Any, phi: float) -> float:
    if hasattr(profile, "projected_width"):
        return float(np.asarray(profile.projected_width(phi)).reshape(-1)[0])
    lo, hi = profile_bounds(profile, phi)
    return hi - lo


def _seed_mix(seed: int) -> int:
    # splitmix64 finaliser: distinct seeds give unrelated PCG streams.
    z = (int(seed) * 0x9E3779B97F4A7C15 + 0x632BE59BD9B4E019) & 0xFFFFFFFFFFFFFFFF
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & 0xFFFFFFFFFFFFFFFF
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & 0xFFFFFFFFFFFFFFFF
    return z ^ (z >> 31)


_INV_SQRT_PI = float(1.0 / np.sqrt(np.pi))
_MAX_WALK = 256          # microsurface events per boundary before a photon is forced out
_NEWTON = 48             # bracketed Newton steps of the below-horizon slope inversion (float64)
#: Splitting: outer-surface hits of a photon that are split (the first ones; later hits take
#: one walk). Each split is a pause between phases, a round of launches for the photons still
#: bouncing; splitting only the first 4 kept a quarter of the variance gain on silk, whose
#: light leaves after many hits of the outer surface (bench/REPORT.md, section 7).
_SPLIT_HITS = 64
_SPLIT_CHUNK = 1 << 21   # splitting: most walks traced together between phases
#: Expected-value estimator: the histograms of one launch (every level, weight and weight x L
#: per bin, per direction of the launch: float32 in the kernels with their copies per thread,
#: :func:`_hist_copies`, and float64 read back) take at most this many bytes, counted as float64
#: per copy; launches are cut at direction boundaries to stay below it (one direction alone may
#: exceed it, with one copy).
_HIST_BYTES = EXPECTED_HIST_BYTES
#: Expected-value estimator: most photons per launch at a rough boundary (a phase queues at most
#: one event per photon and iteration: 2^18 x 8).
_EV_LANES = 1 << 18
#: Expected-value estimator: bytes of a queued event (21 fields of 4 bytes).
_EV_EVENT_BYTES = 84
#: The expected value's queued "hull" field of an event on a hull face (else its face index).
_EV_HULL = 0xFFFFFFFF
#: Expected-value estimator: events queued before their normals are evaluated (352 MB), or one
#: phase's room if larger (at most _EV_LANES x 8, fewer events).
_EV_QUEUE = EXPECTED_QUEUE_BYTES // _EV_EVENT_BYTES
#: The tail of a launch: once at most this many photons are still in flight (rough fibers, no
#: splitting), phases last _TAIL_STEPS iterations and a microfacet normal
#: seen from below the macro surface is drawn inside the loop. Before, every phase drew those
#: normals between phases, so a photon in a long grazing walk (one such normal per event) took a
#: phase per event: hundreds of phases, each recorded and launched anew, for one photon
#: (bench/REPORT.md, "throughput"). Each photon's numbers and arithmetic are the same.
_TAIL_LANES = 256
_TAIL_STEPS = 64
#: Expected-value estimator, allocation of normals ("adaptive", the default): an event gets K
#: normals in proportion to P_side, the probability of the branch that ends outside, bounded
#: above by its value at the macro normal tilted by _EV_TILT x beta towards leaving (reflection
#: on the outside: more grazing; refraction from the material: less, out of total internal
#: reflection), all K at _EV_FULL and above, in powers of two from 1. Silk queues 3-8 events
#: per photon; 43-78 % of those from the material deposit nothing (total internal reflection)
#: and those on the outside deposit F, 0.05-0.1 away from grazing: uniform K spent most
#: normals where the variance is not (bench/REPORT.md, section 7, "allocation").
_EV_TILT = 1.5
_EV_FULL = 0.9
#: Expected-value estimator at a smooth boundary: a photon whose weight falls below this plays
#: Russian roulette (survives with probability weight / _RR_WEIGHT, at that weight).
_RR_WEIGHT = 0.25


@dataclass(frozen=True)
class ExitHistogram:
    """Output bins of the expected-value estimator's in-kernel histograms.

    ``step`` is the bin size in radians of a :class:`~usdfiber.bake.grid.Grid`'s outgoing bins
    (``n_theta`` rows of theta_o from -90 deg, ``n_phi`` columns of phi_o from 0), ``levels``
    the absorption coefficients sigma_a (1/um) at which exits are weighted by exp(-sigma_a L).
    """

    step: float
    n_theta: int
    n_phi: int
    levels: tuple[float, ...]

    @classmethod
    def for_grid(cls, grid: Any, levels: Sequence[float]) -> "ExitHistogram":
        return cls(float(grid.step), int(grid.n_theta_o), int(grid.n_phi_o), tuple(float(x) for x in levels))

    @property
    def n_bins(self) -> int:
        return self.n_theta * self.n_phi

    @property
    def packet(self) -> int:
        """Values per packet of a deposit: 8 (float32: one AVX2 vector), or the smallest power
        of two that holds a bin's 2 x levels values when they are fewer."""
        return min(8, 1 << max(0, 2 * len(self.levels) - 1).bit_length())

    @property
    def stride(self) -> int:
        """Values per bin in the launch's histograms: weight and weight x L of every level,
        padded to whole packets."""
        return -(-2 * len(self.levels) // self.packet) * self.packet

    @property
    def bytes_per_direction(self) -> int:
        """A direction's histograms counted as float64 (as read back; the kernels' float32
        copies take half that each), the unit of :data:`_HIST_BYTES`."""
        return self.stride * self.n_bins * 8


def _summed(parts: list[np.ndarray], shape: tuple[int, ...]) -> np.ndarray:
    """The sum of a direction's histograms from the launches that traced it (zeros if none)."""
    if not parts:
        return np.zeros(shape)
    return parts[0] if len(parts) == 1 else np.sum(parts, axis=0)


def _packet_deposits() -> bool:
    """Whether deposits are packet adds: on the CPU (LLVM) backend; the GPU's takes one atomic
    add per value, as it always has."""
    return mitsuba().variant().startswith("llvm")


def _hist_copies(histogram: ExitHistogram) -> int:
    """Copies of a launch's histograms that its deposits write: one per CPU thread (packet adds
    to a private copy, Dr.Jit's ``ReduceMode.Expand``: no atomics) where a direction's copies
    fit :data:`_HIST_BYTES`, else one shared copy with atomic adds."""
    if not _packet_deposits():
        return 1
    import drjit as dr

    threads = max(1, int(dr.thread_count()))
    return threads if threads * histogram.bytes_per_direction <= _HIST_BYTES else 1


def _lattice_generator(K: int) -> int:
    """Second coordinate's generator of the K-point rank-1 lattice (1, a) / K: the integer
    nearest K / golden ratio that is coprime to K (the Fibonacci lattice when K is a Fibonacci
    number), so that both coordinates of the points are stratified."""
    a = max(1, int(round(K * 0.6180339887498949)))
    while math.gcd(a, K) != 1:
        a -= 1
    return a


def _beckmann_lambda(dr: Any, F: Any, wz: Any, alpha: Any) -> Any:
    """Smith Lambda of an isotropic Beckmann surface for a direction of local cosine ``wz``.

    Lambda = (erf(a) - 1) / 2 + exp(-a^2) / (2 a sqrt(pi)), a = cot(theta) / alpha; the same
    expression gives Lambda(-w) = -1 - Lambda(w) for downward directions.
    """
    sin_t = dr.sqrt(dr.maximum(1.0 - wz * wz, 0.0))
    vertical = sin_t < 1e-7
    a = wz / dr.select(vertical, 1.0, sin_t) / alpha
    a = dr.select(dr.abs(a) < 1e-12, dr.copysign(1e-12, wz), a)
    lam = 0.5 * (dr.erf(a) - 1.0) + (0.5 * _INV_SQRT_PI) * dr.exp(-a * a) / a
    return F(dr.select(vertical, dr.select(wz > 0.0, 0.0, -1.0), lam))


def _height_cdf(dr: Any, hr: Any) -> tuple[Any, Any]:
    """C1(h) = (h + 1) / 2, the share of the microsurface's uniform heights below ``hr``, and
    log(max(C1, 1e-30)), which every direction leaving from that height shares."""
    c1 = dr.clip(0.5 * (hr + 1.0), 0.0, 1.0)
    return c1, dr.log(dr.maximum(c1, 1e-30))


def _leave_probability(dr: Any, F: Any, wz: Any, c1: Any, log_c1: Any, alpha: Any, lam: Any = None) -> Any:
    """:func:`_escape_probability` of a direction of local cosine ``wz`` from a height given
    by its :func:`_height_cdf` ``c1`` and ``log_c1``."""
    if lam is None:
        lam = _beckmann_lambda(dr, F, wz, alpha)
    g1 = dr.select((wz > 0.0) & (c1 > 0.0), dr.exp(lam * log_c1), 0.0)
    return F(dr.select(wz > 0.9999, 1.0, g1))


def _escape_probability(dr: Any, F: Any, wr: Any, hr: Any, alpha: Any) -> tuple[Any, Any]:
    """Probability that the next height step of a walk at height ``hr`` travelling along ``wr``
    (mirrored local frame) leaves the microsurface: G1 = C1(h)^Lambda(wr) for an upward ray
    (C1(h) = (h + 1) / 2), 1 for a vertical one (the step's shortcut), 0 downwards.
    Returns (probability, Lambda, C1), the last two for :func:`_height_step`.
    """
    lam = _beckmann_lambda(dr, F, wr.z, alpha)
    c1, log_c1 = _height_cdf(dr, hr)
    return _leave_probability(dr, F, wr.z, c1, log_c1, alpha, lam), lam, c1


def _height_step(dr: Any, F: Any, wr: Any, hr: Any, u: Any, alpha: Any) -> tuple[Any, Any]:
    """One Smith height step of a microsurface walk (Heitz et al. 2016), uniform heights.

    ``wr``: travel direction in the (mirrored) local frame, ``hr`` the height in [-1, 1]. An
    upward ray escapes with probability G1 = C1(h)^Lambda, C1(h) = (h + 1) / 2
    (:func:`_escape_probability`); otherwise (and always for a downward ray) the next hit is
    where C1(h') = C1(h) / (1 - u)^(1 / Lambda). Returns (leave, new height).
    """
    g1, lam, c1 = _escape_probability(dr, F, wr, hr, alpha)
    lam_s = dr.select(lam == 0.0, -1.0, lam)
    c1n = c1 * dr.exp(-dr.log(dr.maximum(1.0 - u, 1e-30)) / lam_s)
    c1n = dr.select(wr.z < -0.9999, u * c1, c1n)
    hn = dr.clip(2.0 * dr.minimum(c1n, 1.0) - 1.0, -1.0, 1.0)
    hn = dr.select(dr.abs(wr.z) < 1e-4, hr, hn)
    leave = (u > 1.0 - g1) | (wr.z > 0.9999)
    return leave, F(hn)


def _vndf_below(mi: Any, dr: Any, wi: Any, u1: Any, u2: Any, alpha: Any) -> Any:
    """Beckmann normal visible from ``wi`` for any ``wi`` (local frame, z = macro normal).

    Heitz & d'Eon 2014: stretch to alpha = 1, invert the CDF of the visible slope
    cot/2 (1 + erf x) + exp(-x^2) / (2 sqrt(pi)) on x < cot by bracketed Newton steps, draw the
    other slope from a Gaussian, rotate to wi's azimuth and unstretch. float64 because below
    the horizon the CDF is a far Gaussian tail.
    """
    D = mi.Float64
    a = D(alpha)
    wx, wy, wz = a * D(wi.x), a * D(wi.y), D(wi.z)
    nrm = dr.sqrt(wx * wx + wy * wy + wz * wz)
    cos_t = dr.clip(wz / nrm, -1.0, 1.0)
    sin_t = dr.sqrt(dr.maximum(1.0 - cos_t * cos_t, 0.0))
    has_phi = sin_t > 1e-12
    cos_p = dr.select(has_phi, wx / nrm / dr.select(has_phi, sin_t, 1.0), 1.0)
    sin_p = dr.select(has_phi, wy / nrm / dr.select(has_phi, sin_t, 1.0), 0.0)
    cot = dr.clip(cos_t / dr.maximum(sin_t, 1e-300), -1e12, 1e12)

    def cdf(x):
        return 0.5 * cot * (1.0 + dr.erf(x)) + (0.5 * _INV_SQRT_PI) * dr.exp(-x * x)

    hi = dr.minimum(cot, 9.0)
    lo = dr.minimum(-9.0, cot - 4.0)
    uu = D(u1)
    target = uu * cdf(hi)
    x = dr.clip(dr.erfinv(dr.clip(2.0 * uu - 1.0, -1.0 + 1e-15, 1.0 - 1e-15)), lo, hi)

    def newton(x: Any, lo: Any, hi: Any, i: Any) -> tuple[Any, Any, Any, Any]:
        gx = cdf(x) - target
        lo = dr.select(gx < 0.0, x, lo)
        hi = dr.select(gx > 0.0, x, hi)
        dg = (cot - x) * dr.exp(-x * x) * _INV_SQRT_PI
        xn = x - gx / dg
        bad = ~dr.isfinite(xn) | (xn <= lo) | (xn >= hi)
        return dr.select(bad, 0.5 * (lo + hi), xn), lo, hi, i + 1

    # A symbolic loop: its body is recorded once, not _NEWTON times (this runs between every
    # two phases of a launch, and recording the unrolled steps cost 2-4 % of a bake's wall).
    x, lo, hi, _ = dr.while_loop((x, lo, hi, mi.UInt32(0)), lambda x, lo, hi, i: i < _NEWTON, newton,
                                 mode="symbolic", label="vndf below")
    y = dr.erfinv(dr.clip(2.0 * D(u2) - 1.0, -1.0 + 1e-15, 1.0 - 1e-15))
    sx = a * (cos_p * x - sin_p * y)
    sy = a * (sin_p * x + cos_p * y)
    inv = 1.0 / dr.sqrt(sx * sx + sy * sy + 1.0)
    return mi.Vector3f(mi.Float(-sx * inv), mi.Float(-sy * inv), mi.Float(inv))


def _gather_state(mi: Any, dr: Any, s: dict, idx: Any) -> dict:
    """The lanes ``idx`` of a loop state (PCG32 included)."""
    out = {}
    for k, v in s.items():
        if isinstance(v, mi.PCG32):
            r = mi.PCG32(v)
            r.state = dr.gather(type(v.state), v.state, idx)
            r.inc = dr.gather(type(v.inc), v.inc, idx)
            out[k] = r
        else:
            out[k] = dr.gather(type(v), v, idx)
    return out


@dataclass
class _Launch:
    """The photons of one tracer launch: lane -> incoming direction and random stream.

    ``beams`` holds one row per incoming direction: the unit propagation direction
    ``-omega_i`` (3), ``u = (cos phi_i, sin phi_i)`` (2), and the launch interval along
    ``u_perp``: its start and width (2), float32 like the kernel. Lane ``l`` belongs to
    direction ``beam[l]`` and is photon ``photon[l]`` of that direction's stream ``mix[l]``.
    ``spread`` (box-filtered bins, or None) holds per direction the bin each photon draws
    its own light direction from: (theta_lo, theta_hi, phi_lo, phi_hi), float64.
    """

    beams: np.ndarray      # (n_dirs, 7) float32
    beam: np.ndarray       # (n,) uint32
    photon: np.ndarray     # (n,) uint64
    mix: np.ndarray        # (n,) uint64
    #: Owen-scramble seeds (n_dirs, 4) uint32 of the per-stream Sobol points that replace the
    #: first random numbers (``sampler="sobol"``), or None for independent PCG32 numbers only.
    scramble: np.ndarray | None = None
    spread: np.ndarray | None = None

    @property
    def size(self) -> int:
        return int(len(self.beam))


def _trace_batch(fs: FiberScene, launch: _Launch, *, eta: float, alpha: float, max_bounces: int,
                 max_steps: int, mode: str, phase_steps: int = 8, split: int = 0, expected: int = 0,
                 histogram: ExitHistogram | None = None, expected_allocation: str = "adaptive",
                 expected_sampler: str = "ndf") -> dict:
    """Trace the photons of ``launch`` (any mix of incoming directions) in one kernel.

    Returns numpy arrays ``d`` (n,3), ``L``, ``hit_any``, ``cut``, ``bounces``, ``leaks`` and
    ``forced`` per lane, and ``w``, the lane's final weight, and ``deposits`` (lane, direction,
    L, weight, bounces of every exit deposited on the way) when ``split`` (K walks per outer
    boundary hit) is on. With ``expected`` (K normals per event) the expected exits are
    histogrammed in the kernel: ``hist`` (directions b0 .. b0 + n - 1 of the launch, with
    ``hist_first`` = b0) is (n, levels, 2, bins) float64, the summed weight and weight x L, and
    ``ev_events`` / ``ev_normals`` (n,) count the events and the normals evaluated
    (``expected_allocation``: see :data:`_EV_TILT`). The loop runs in phases of ``phase_steps`` iterations; between
    phases finished photons are compacted away (a SIMD packet or GPU warp otherwise keeps
    running until its slowest photon is done), and the rare microfacet samples seen from below
    the macro surface are drawn by the exact float64 inversion on just those lanes. Once at
    most ``_TAIL_LANES`` photons are left (rough fibers, no splitting),
    phases last ``_TAIL_STEPS`` iterations and those normals are drawn in the loop instead,
    with the same inputs and arithmetic: a photon's path does not depend on the phases. Directions
    and seeds are data, not literals, so one compiled kernel serves every direction and batch,
    and many directions share each phase's fixed cost.
    """
    mi = mitsuba()
    import drjit as dr

    F, U, B, V3 = mi.Float, mi.UInt32, mi.Bool, mi.Vector3f
    mesh = fs.mesh
    z_inv = mesh.z_invariant
    rough = alpha > 0.0
    eps = ray_offset(mesh)
    rb = float(mesh.bound_radius)
    zp = float(mesh.z_period)

    # Opaque scalars: the kernel is compiled once and reused for every direction and material.
    eta_o = dr.opaque(F, float(eta))
    inv_eta_o = dr.opaque(F, 1.0 / float(eta))
    alpha_o = dr.opaque(F, float(max(alpha, 1e-4)))
    n = launch.size
    beam = U(launch.beam)
    col = [dr.gather(F, F(np.ascontiguousarray(launch.beams[:, k])), beam) for k in range(7)]
    d0, ux, uy, lo_o, w_o = col[0:3], col[3], col[4], col[5], col[6]
    rb_o, zp_o, eps_o = dr.opaque(F, rb), dr.opaque(F, zp), dr.opaque(F, eps)
    zs_o = dr.opaque(F, 0.8 * zp)             # extruded: spread of the tracing planes
    maxb, maxs = dr.opaque(U, max_bounces), dr.opaque(U, max_steps)
    maxw = dr.opaque(U, _MAX_WALK)
    scene, faces, vnorm, fnorm = fs.scene, fs.faces, fs.normals, fs.face_normals
    distr = mi.MicrofacetDistribution(mi.MicrofacetType.Beckmann, alpha_o, True) if rough else None
    split = int(split)
    if split and not z_inv:
        raise ValueError("splitting needs an extruded fiber (no cuticle scales)")
    outer, outer_convex = fs.outer, bool(mesh.outer_convex)
    inv_k = dr.opaque(F, 1.0 / max(split, 1))
    ev = int(expected)
    # The expected value's exits off the hull skip the escape ray inside their face's wedge: the
    # walk keeps the face of its boundary event (state face).
    wedges = fs.wedge if (ev and rough and not outer_convex and _POCKET_WEDGES and fs.wedge is not None) else None
    if ev and (split or not z_inv or histogram is None):
        raise ValueError("the expected-value estimator needs an extruded fiber, a histogram and no splitting")

    # Photon i of stream mix: the stream PCG32(size, mix, mix >> 1) gives its lane i.
    rng = mi.PCG32(size=n)
    rng.seed(initstate=mi.UInt64(launch.mix + launch.photon), initseq=mi.UInt64((launch.mix >> np.uint64(1)) + launch.photon))

    if launch.spread is not None:
        # A box-filtered bin: each photon its own light direction, drawn (before anything
        # else of its stream) in proportion to the power the fiber intercepts from it
        # (sampling.cos2_latitude; phi uniform, W(phi) left to the fixed launch width).
        F64 = mi.Float64
        box = [dr.gather(F64, F64(np.ascontiguousarray(launch.spread[:, k])), beam) for k in range(4)]
        u_t, u_p = F64(rng.next_float32()), F64(rng.next_float32())
        th = sampling.cos2_latitude(box[0], box[1], u_t)
        ph = box[2] + (box[3] - box[2]) * u_p
        ct, stn, cp, spn = dr.cos(th), dr.sin(th), dr.cos(ph), dr.sin(ph)
        d0 = [F(-ct * cp), F(-ct * spn), F(-stn)]
        ux, uy = F(cp), F(spn)
    qmc = launch.scramble is not None
    if qmc:
        # Scrambled Sobol point of the photon's number in its stream: h, then the first
        # boundary event's numbers (sampling.py; every point is uniform: no bias).
        sobol = sampling.sobol_unscrambled(U(launch.photon.astype(np.uint32)))
        qs = [sampling.to_unit_float(sampling.owen_scramble(
            sobol[k], dr.gather(U, U(np.ascontiguousarray(launch.scramble[:, k])), beam)))
            for k in range(sampling.QMC_DIMENSIONS)]
        h0 = lo_o + w_o * qs[0]
    else:
        # Launch: offset h along u_perp = (-sin phi, cos phi) over [lo, lo + width].
        h0 = lo_o + w_o * rng.next_float32()
    if z_inv:
        s0 = rb_o * 1.01 + eps_o
        z0 = F(0.0)
    else:
        s0 = dr.sqrt(dr.maximum(rb_o * rb_o - h0 * h0, 0.0)) + eps_o
        z0 = rng.next_float32() * zp_o
    st = {
        "idx": dr.arange(U, n),
        "p": V3(-h0 * uy + s0 * ux, h0 * ux + s0 * uy, z0),
        "d": V3(d0[0], d0[1], d0[2]),
        "L": dr.zeros(F, n), "seg": dr.zeros(F, n),
        "active": dr.full(B, True, n), "hit_any": dr.full(B, False, n), "cut": dr.full(B, False, n),
        "bounces": dr.zeros(U, n), "steps": dr.zeros(U, n),
        # Boundary state: in a microsurface walk, medium at its start, side, height, normals.
        "walking": dr.full(B, False, n), "inside": dr.full(B, False, n), "above": dr.full(B, True, n),
        "h": dr.zeros(F, n), "nm": dr.zeros(V3, n), "ngs": dr.zeros(V3, n), "wsteps": dr.zeros(U, n),
        # need_m: the next microfacet normal is seen from below the macro surface and is drawn
        # between phases (mq holds its two random numbers); has_m: mq holds that normal.
        "need_m": dr.full(B, False, n), "has_m": dr.full(B, False, n), "mq": dr.zeros(V3, n),
        "leaks": dr.zeros(U, n), "forced": dr.zeros(U, n), "retried": dr.full(B, False, n),
        "rng": rng,
    }
    if not rough:
        for k in ("h", "wsteps", "need_m", "has_m", "mq", "forced"):
            del st[k]
    if qmc:
        st["q"] = V3(qs[1], qs[2], qs[3])
    # Leaving for good without a ray cast: a boundary result that ends outside the fiber on a face
    # of the outline's convex hull (the whole fiber lies behind that face's line) has nothing left
    # to meet, so the photon escapes there instead of in one more iteration whose cast must miss.
    # Whether a walk's boundary event is on such a face: state hull (also read by the expected
    # value, which needs an extruded fiber).
    hull_esc = z_inv
    if z_inv and rough:
        st["hull"] = dr.full(B, False, n)
    if wedges is not None:
        st["face"] = dr.zeros(U, n)
    if rough:
        # A walk's leaving test comes at the end of the iteration of its microfacet event (it used to
        # open the next iteration, with the number that iteration drew first): this number stands
        # for the test of the first iteration, which had no walk, so every photon uses the same
        # numbers for the same draws as when the test opened the iteration.
        rng.next_float32()
    split_walks = bool(split) and rough
    if split:
        # Splitting at the outer surface: the photon's weight (w). Rough boundaries: need_s
        # pauses a photon that hit the outer surface until its K walks are run between phases
        # (split_walks_between_phases), from the hit (p0, d0: incoming direction, normals nm0 and ngs0,
        # medium in0) with streams seeded by two numbers of its own (sa, sb).
        st["w"] = dr.full(F, 1.0, n)
        if split_walks:
            st.update({"need_s": dr.full(B, False, n), "p0": dr.zeros(V3, n), "d0": dr.zeros(V3, n),
                       "nm0": dr.zeros(V3, n), "ngs0": dr.zeros(V3, n), "in0": dr.full(B, False, n),
                       "sa": dr.zeros(U, n), "sb": dr.zeros(U, n), "ns": dr.zeros(U, n)})
    # Deposits of the splitting estimator: buffers of the current phase (replaced between phases).
    dep: dict[str, Any] = {}
    if ev:
        # Expected-value estimator at the outer boundary: the photon's weight (w; smooth
        # boundaries split it between the two Fresnel branches), whether its boundary event is
        # on a face the estimator serves (evf: rough, any outer face, where leaving is for good
        # on a hull edge, state hull; smooth, an edge of the outline's convex hull), whether the branch its walk just took ends outside (evo: then leaving at the next
        # height step is the outcome whose expectation was deposited) and, off the hull, whether
        # the photon has just taken that outcome and its next ray decides (evp: if it escapes,
        # the expectation covered it).
        st["w"] = dr.full(F, 1.0, n)
        st["evf"] = dr.full(B, False, n)
        if rough:
            st.update({"evo": dr.full(B, False, n), "evp": dr.full(B, False, n)})
        hist_first = int(launch.beam.min()) if n else 0
        hist_n = (int(launch.beam.max()) - hist_first + 1) if n else 1
        nlev, nbin = len(histogram.levels), histogram.n_bins
        pk_n, pk_g = histogram.stride // histogram.packet, histogram.packet
        # float32 sums: a copy holds at most one batch of a direction from one thread, read back
        # into float64 after each launch; against float64 sums the histograms differ by 1e-6
        # relative, a thousand times below a bake's noise, and a bake traces 1.13-1.15x faster
        # (float64 products, conversions and packets; bench/REPORT.md s. 7, "float32").
        hist = dr.zeros(mi.Float32, hist_n * histogram.stride * nbin)
        # A deposit's 2 x levels values are adjacent (bin-major histograms) and added as packets
        # of pk_g values, to a private copy per thread where they fit (no atomics: 1.6x less
        # CPU per expected-value trace of rough silk, bench/REPORT.md s. 7), else atomically.
        hist_mode = dr.ReduceMode.Expand if _hist_copies(histogram) > 1 else dr.ReduceMode.Direct
        packets = _packet_deposits()
        ArrayXf = getattr(importlib.import_module(type(hist).__module__), "ArrayXf")
        pad = mi.Float32(0.0)
        hist_beam = U(launch.beam.astype(np.uint32) - np.uint32(hist_first))
        lev_o = [dr.opaque(F, float(x)) for x in histogram.levels]
        step_inv = dr.opaque(F, 1.0 / histogram.step)
        step_inv64 = dr.opaque(mi.Float64, 1.0 / histogram.step)
        nth_o, nph_o = dr.opaque(U, histogram.n_theta), dr.opaque(U, histogram.n_phi)
        # Normals per event: one class of K, or (adaptive) powers of two up to K, each with
        # its own lattice.
        ev_classes = (sorted({min(1 << i, ev) for i in range(ev.bit_length() + 1)})
                      if expected_allocation == "adaptive" and rough else [ev])
        tilt_o = dr.opaque(F, _EV_TILT * math.atan(max(alpha, 0.0)))
        ndf_normals = expected_sampler == "ndf"
        alpha2_o = dr.opaque(F, float(max(alpha, 1e-4)) ** 2)
        ev_events, ev_normals = dr.zeros(U, hist_n), dr.zeros(U, hist_n)

    def deposit_expected(hb: Any, mask: Any, d: Any, wt: Any, att: list, exact_rows: bool = True) -> None:
        """Histogram an exit of weight ``wt`` along ``d`` (lanes ``mask``; ``hb``: their direction
        in the launch's histograms) at every absorption level (``att``: :func:`attenuation` of
        their path length L): weight and weight x L of its bin, as
        :meth:`usdfiber.bake.grid.Grid.bin_index` bins it."""
        # theta_o in float64, as numpy bins: a smooth extruded fiber sends all its light to
        # theta_o = -theta_i, which may lie on a bin edge (float32 could pick the other row).
        # A rough exit's direction is continuous: a float32 arcsine differs from numpy's row
        # only within an ulp of an edge, a set of no measure, and costs less.
        if exact_rows:
            th = dr.asin(dr.clip(mi.Float64(d.z), -1.0, 1.0))
        else:
            th = mi.Float64(dr.asin(dr.clip(d.z, -1.0, 1.0)))
        ph = dr.atan2(d.y, d.x)
        ph = dr.select(ph < 0.0, ph + 2.0 * math.pi, ph)
        row = U(dr.clip(dr.floor((th + 0.5 * math.pi) * step_inv64), 0.0, 1e9))
        row = dr.minimum(row, nth_o - 1)
        col = U(dr.maximum(dr.floor(ph * step_inv), 0.0))
        col = dr.select(col >= nph_o, col - nph_o, col)
        # Bin-major: a deposit's 2 x levels values share a few cache lines (level-major, each
        # add was a cache miss of its own: 2.2x the deposit kernel's time at 11 levels).
        cell = hb * nbin + row * nph_o + col
        vals = [wt * a for a in att]
        if not packets:
            for i, v in enumerate(vals):
                dr.scatter_reduce(dr.ReduceOp.Add, hist, v, cell * (pk_n * pk_g) + i, mask, mode=hist_mode)
            return
        vals += [pad] * (pk_n * pk_g - len(vals))
        for q in range(pk_n):
            dr.scatter_reduce(dr.ReduceOp.Add, hist, ArrayXf(vals[q * pk_g:(q + 1) * pk_g]), cell * pk_n + q, mask,
                              mode=hist_mode)

    def attenuation(L: Any) -> list:
        """exp(-sigma_k L) and L exp(-sigma_k L) of every level, once per event: a deposit
        multiplies them by its weight."""
        out = []
        for lev in lev_o:
            a = dr.exp(-lev * L)
            out += [a, a * L]
        return out

    #: Rough outer events waiting for their expected exits (written by the loop, read between
    #: phases): fields of the state an event needs, one row per event.
    EV_FIELDS = ("hb", "into", "above", "hull", "L", "w", "h", "sg", "r1", "r2", "nx", "ny", "nz", "wx", "wy", "wz",
                 "gx", "gy", "gz", "px", "py")
    EV_UINT = ("hb", "into", "above", "hull")
    #: The "hull" field: _EV_HULL for an event on a hull face, else its face (with wedges) or 0.
    ev_hull = dr.opaque(U, _EV_HULL)
    assert 4 * len(EV_FIELDS) == _EV_EVENT_BYTES
    evq: dict[str, Any] = {}
    evq_cap = [0]

    def settle(d: Any, ngs: Any, p: Any, above: Any) -> tuple[Any, Any]:
        """Direction and offset point of a boundary result that leaves ``above`` (or below).

        Reflected light must leave on the incident side of the flat triangle, transmitted light
        on the other; a direction within the small angle between the smooth and the flat
        normal (or a grazing microsurface exit) that disagrees is mirrored across the facet.
        """
        dg = dr.dot(d, ngs)
        wrong = dr.select(above, dg <= 0.0, dg >= 0.0)
        d = dr.select(wrong, V3(dr.normalize(d - ngs * (2.0 * dg))), d)
        side = dr.select(above, 1.0, -1.0)
        return d, V3(dr.fma(ngs, side * eps_o, p))

    def finish(s: dict, fin: Any) -> None:
        """End the boundary event of lanes ``fin``: set the medium, reconcile with the facet, offset."""
        above = s["above"]
        d, p = settle(s["d"], s["ngs"], s["p"], above)
        s["d"] = dr.select(fin, d, s["d"])
        s["p"] = dr.select(fin, p, s["p"])
        s["inside"] = dr.select(fin & ~above, ~s["inside"], s["inside"])
        s["walking"] = s["walking"] & ~fin

    def escapes(p: Any, d: Any, test: Any, rng: Any) -> Any:
        """Lanes ``test`` (outside the fiber at ``p``, leaving along ``d``) that never meet it again."""
        if outer_convex:
            return test           # a convex outer surface cannot be met again
        return escapes_from(p, d, test, (rng.next_float32() - 0.5) * zs_o)

    def escapes_from(p: Any, d: Any, test: Any, zr: Any) -> Any:
        """:func:`escapes` with the ray cast in the plane ``z = zr`` (extruded fibers: any plane;
        a random one keeps a crack between two triangles from deciding)."""
        lxy = dr.sqrt(dr.fma(d.x, d.x, d.y * d.y))
        lxy_s = dr.maximum(lxy, 1e-30)
        ray = mi.Ray3f(mi.Point3f(p.x, p.y, zr), V3(d.x / lxy_s, d.y / lxy_s, 0.0))
        pi = scene.ray_intersect_preliminary(ray, coherent=False, active=test & (lxy > 1e-7))
        return test & ~(pi.is_valid() & (lxy > 1e-7))

    def deposit(s: dict, mask: Any, d: Any, w: Any) -> None:
        """Record an exit of weight ``w`` that leaves the fiber for good (lanes ``mask``)."""
        slot = dr.scatter_inc(dep["count"], U(0), mask)
        for k, v in (("dx", d.x), ("dy", d.y), ("dz", d.z), ("L", s["L"]), ("w", F(w))):
            dr.scatter(dep[k], v, slot, mask)
        dr.scatter(dep["lane"], s["idx"], slot, mask)
        dr.scatter(dep["bounces"], s["bounces"], slot, mask)


    def fresnel_branches(wi: Any, m: Any, into_mat: Any) -> tuple[Any, Any, Any]:
        """Fresnel reflectance and the reflected and refracted directions of ``wi`` about ``m``."""
        cos_i = dr.clip(dr.dot(wi, m), 0.0, 1.0)
        rel = dr.select(into_mat, eta_o, inv_eta_o)
        F_r, cos_t, _, eta_ti = mi.fresnel(cos_i, rel)
        wo_r = m * (2.0 * cos_i) - wi
        wo_t = m * dr.fma(cos_i, eta_ti, cos_t) - wi * eta_ti
        return F_r, wo_r, wo_t

    def fresnel_event(wi: Any, m: Any, into_mat: Any, u: Any) -> tuple[Any, Any]:
        """Reflect or refract ``wi`` (pointing away from the surface) about ``m``; Fresnel decides."""
        F_r, wo_r, wo_t = fresnel_branches(wi, m, into_mat)
        refl = u < F_r
        return V3(dr.normalize(dr.select(refl, wo_r, wo_t))), refl

    def local_wi(s: dict) -> tuple[Any, Any, Any]:
        """Frame of the macro normal, side sign, and wi mirrored so that the photon is above."""
        frame = mi.Frame3f(s["nm"])
        sg = dr.select(s["above"], 1.0, -1.0)
        return frame, sg, -(V3(frame.to_local(s["d"])) * sg)

    def split_smooth(s: dict, hit: Any, d: Any, nm: Any, inside: Any, u: Any, rng: Any) -> tuple[Any, Any, Any]:
        """Splitting at a smooth outer boundary (lanes ``hit``): the K walks are K Fresnel
        choices between two fixed directions, so they are drawn at once.

        Of the K, n choose the branch that ends outside (reflected from outside, transmitted
        from inside). If that branch leaves the fiber for good it is deposited with weight
        w n / K and the photon continues along the other branch with probability (K - n) / K;
        if it meets the fiber again, every result continues and one Fresnel choice picks the
        branch. Returns the continuing branch's direction, whether it is the reflected one,
        and the lanes that end.
        """
        F_r, wo_r, wo_t = fresnel_branches(-d, nm, ~inside)
        wo_r, wo_t = V3(dr.normalize(wo_r)), V3(dr.normalize(wo_t))
        p_out = dr.select(inside, 1.0 - F_r, F_r)                  # the branch that ends outside
        n_out = F(0.0)
        for _ in range(split):
            n_out += dr.select(rng.next_float32() < p_out, 1.0, 0.0)
        d_out = dr.select(inside, wo_t, wo_r)
        d_set, p_set = settle(d_out, s["ngs"], s["p"], ~inside)
        # A branch that cannot happen (total internal reflection) cannot meet the fiber either.
        esc = escapes(p_set, d_set, hit & (p_out > 0.0), rng) | (hit & (p_out <= 0.0))
        deposit(s, esc & (n_out > 0.0), d_set, s["w"] * n_out * inv_k)
        refl = dr.select(esc, inside, u < F_r)                     # esc: the branch that stays
        ended = esc & (rng.next_float32() * F(split) < n_out)
        s["w"] = dr.select(ended, 0.0, s["w"])
        return V3(dr.select(refl, wo_r, wo_t)), refl, ended

    def expected_event(s: dict, elig: Any, sg: Any, wi: Any, rng: Any) -> None:
        """Queue a rough outer event (lanes ``elig``, state before the event) for
        :func:`expected_exits`, with the two numbers that shift its lattice of normals. (Run
        between phases on just the events, K normals each cost what a few loop iterations of
        one photon cost; in the loop every lane would pay them at every iteration.)"""
        into = s["inside"] ^ s["above"]           # on the outside medium now
        above_out = dr.select(into, s["above"], ~s["above"])
        h_out = dr.select(into, s["h"], -s["h"]) * sg
        r1, r2 = rng.next_float32(), rng.next_float32()
        slot = dr.scatter_inc(evq["count"], U(0), elig)
        nm, ng, p = s["nm"], s["ngs"], s["p"]
        face = s["face"] if wedges is not None else U(0)
        vals = (dr.gather(U, hist_beam, s["idx"]), U(dr.select(into, 1, 0)), U(dr.select(above_out, 1, 0)),
                dr.select(s["hull"], ev_hull, face), s["L"], s["w"], h_out, sg, r1, r2, nm.x, nm.y, nm.z,
                wi.x, wi.y, wi.z, ng.x, ng.y, ng.z, p.x, p.y)
        for k, v in zip(EV_FIELDS, vals):
            dr.scatter(evq[k], v, slot, elig)

    def normals_per_event(into: Any, wz: Any) -> Any:
        """Adaptive allocation (:data:`_EV_TILT`): the smallest class of normals at least
        K P_side / _EV_FULL, P_side at the tilted macro normal; a function of the event's state
        only, so every normal stays uniform over the visible normals."""
        t = dr.acos(dr.clip(wz, 0.0, 1.0))
        c_out = dr.cos(dr.minimum(t + tilt_o, 0.5 * math.pi))
        c_in = dr.cos(dr.maximum(t - tilt_o, 0.0))
        q = dr.select(into, mi.fresnel(c_out, eta_o)[0], 1.0 - mi.fresnel(c_in, inv_eta_o)[0])
        need = q * (ev / _EV_FULL)
        k = dr.full(U, ev, dr.width(wz))
        for c in reversed(ev_classes[:-1]):
            k = dr.select(need <= c, c, k)
        return k

    def expected_exits(used: int) -> None:
        """Deposit the expected exits of the ``used`` queued rough outer events, each with its
        number of normals (:func:`normals_per_event`; all K with a uniform allocation)."""
        sel = dr.arange(U, used)
        if len(ev_classes) == 1:
            groups = [(ev, sel)]
        else:
            k_e = normals_per_event(dr.gather(U, evq["into"], sel) != 0, dr.gather(F, evq["wz"], sel))
            dr.eval(k_e)
            groups = [(c, dr.compress(k_e == c)) for c in ev_classes]
        for c, idx in groups:
            if dr.width(idx):
                expected_normals(idx, c)
        dr.eval(hist, ev_events, ev_normals)

    def expected_normals(sel: Any, kn: int) -> None:
        """Deposit the expected exits of queued rough outer events ``sel`` with ``kn`` normals each.

        The outcome replaced: the branch that ends outside (reflected on the outside,
        transmitted from the material; probability P_side = F or 1 - F), then leaving at the
        next height step (probability G_leave, at the same height, mirrored across the
        surface after a refraction) and then the fiber for good: always on a hull face, elsewhere
        where the exit ray meets the fiber no more (a ray cast per normal, as the real photon's
        next ray decides). Its expected contribution w E_m[P_side G_leave 1{escapes}
        1{settle(wo(m)) in bin}], m visible from wi, is estimated with K normals from a randomly
        shifted rank-1 lattice over the two numbers of the visible-normal sampler (each point
        uniform: unbiased; the lattice stratifies them), each deposited with weight
        w P_side G_leave / K.
        """
        used = dr.width(sel)
        e = {k: dr.gather(type(evq[k]), evq[k], sel) for k in EV_FIELDS}
        dr.scatter_reduce(dr.ReduceOp.Add, ev_events, U(1), e["hb"])
        dr.scatter_reduce(dr.ReduceOp.Add, ev_normals, U(kn), e["hb"])
        lat_a, inv_ev = _lattice_generator(kn), dr.opaque(F, 1.0 / kn)
        into, above_out, hull = e["into"] != 0, e["above"] != 0, e["hull"] == ev_hull
        if wedges is not None:
            # The event's face's wedge (zeros on the hull: its exits need no ray anyway).
            wdg = [dr.gather(F, wedges, e["hull"] * 4 + k, ~hull) for k in range(4)]
        frame = mi.Frame3f(V3(e["nx"], e["ny"], e["nz"]))
        wi, ngs, sg = V3(e["wx"], e["wy"], e["wz"]), V3(e["gx"], e["gy"], e["gz"]), e["sg"]
        p_ev = V3(e["px"], e["py"], 0.0)
        att = attenuation(e["L"])
        valid = dr.full(B, True, used)
        if ndf_normals:
            # The visible density over D(m) cos(theta_m), without its <wi, m>+ / cos(theta_m):
            # G1(wi) / cos(theta_i) (finite at grazing wi, where G1 falls like cos(theta_i)).
            vis_w = inv_ev / ((1.0 + _beckmann_lambda(dr, F, wi.z, alpha_o)) * dr.maximum(wi.z, 1e-12))
            # phi_m = 2 pi (r2 + c_j): one sincos per event, each normal's by the angle sum.
            s_r2, c_r2 = dr.sincos((2.0 * math.pi) * e["r2"])
        # The exits leave from the event's height: its C1 and log C1 once per event.
        c1_out, log_c1_out = _height_cdf(dr, e["h"])
        for j in range(kn):
            u1 = e["r1"] + j * (1.0 / kn)
            u1 = dr.select(u1 >= 1.0, u1 - 1.0, u1)
            c_j = ((j * lat_a) % kn) * (1.0 / kn)  # the lattice's second coordinate, before its shift
            if ndf_normals:
                # D(m) cos(theta_m) by inversion: tan^2(theta_m) = -alpha^2 ln(1 - u1), phi_m = 2 pi u2.
                cos_m = dr.rsqrt(dr.fma(-alpha2_o, dr.log(1.0 - u1), 1.0))
                sin_m = dr.sqrt(dr.maximum(dr.fma(-cos_m, cos_m, 1.0), 0.0))
                a_j = 2.0 * math.pi * c_j
                s_phi = dr.fma(s_r2, math.cos(a_j), c_r2 * math.sin(a_j))
                c_phi = dr.fma(c_r2, math.cos(a_j), -s_r2 * math.sin(a_j))
                m = V3(sin_m * c_phi, sin_m * s_phi, cos_m)
                w_m = vis_w * dr.maximum(dr.dot(wi, m), 0.0) / cos_m
            else:
                u2 = e["r2"] + c_j
                u2 = dr.select(u2 >= 1.0, u2 - 1.0, u2)
                m, _ = distr.sample(wi, mi.Point2f(u1, u2))
                w_m = inv_ev
            F_r, wo_r, wo_t = fresnel_branches(wi, V3(m), into)
            wo = V3(dr.normalize(dr.select(into, wo_r, wo_t)))
            p_side = dr.select(into, F_r, 1.0 - F_r)
            g = _leave_probability(dr, F, dr.select(into, wo, -wo).z, c1_out, log_c1_out, alpha_o)
            d_out, p_out = settle(V3(frame.to_world(wo * sg)), ngs, p_ev, above_out)
            wt = e["w"] * p_side * g * w_m
            live = valid & (wt > 0.0)
            if not outer_convex:
                # Off the hull the exit may meet the fiber again: then it is not this outcome.
                # (Planes spread over the slab, one per normal, as the real rays' random ones.)
                zr = zs_o * ((j + 0.5) / kn - 0.5)
                cast = ~hull & live
                if wedges is not None:
                    # Inside the wedge the ray would miss (pockets.py): it leaves without one.
                    clear = ((wdg[0] * d_out.y - wdg[1] * d_out.x > 0.0)
                             & (d_out.x * wdg[3] - d_out.y * wdg[2] > 0.0))
                    cast = cast & ~clear
                live = (hull | ~cast) & live | escapes_from(p_out, d_out, cast, zr)
            deposit_expected(e["hb"], live, d_out, wt, att, exact_rows=False)

    def expected_smooth(s: dict, elig: Any, d: Any, nm: Any, inside: Any, rng: Any) -> tuple[Any, Any, Any]:
        """Expected value at a smooth outer boundary (lanes ``elig``): the branch that ends
        outside (probability P_out) leaves for good and is deposited with weight w P_out; the
        photon continues along the other with weight w (1 - P_out), with Russian roulette
        below _RR_WEIGHT. Returns the continuing direction, whether it is the reflected one,
        and the lanes that end."""
        F_r, wo_r, wo_t = fresnel_branches(-d, nm, ~inside)
        wo_r, wo_t = V3(dr.normalize(wo_r)), V3(dr.normalize(wo_t))
        p_out = dr.select(inside, 1.0 - F_r, F_r)
        d_out, _ = settle(dr.select(inside, wo_t, wo_r), s["ngs"], s["p"], ~inside)
        deposit_expected(dr.gather(U, hist_beam, s["idx"]), elig & (p_out > 0.0), d_out, s["w"] * p_out,
                         attenuation(s["L"]))
        w = s["w"] * (1.0 - p_out)
        q = dr.minimum(w * (1.0 / _RR_WEIGHT), 1.0)
        ended = elig & (rng.next_float32() >= q)
        s["w"] = dr.select(elig, dr.select(ended, 0.0, w / dr.maximum(q, 1e-30)), s["w"])
        return V3(dr.select(inside, wo_r, wo_t)), inside, ended

    #: Tail phases (see _TAIL_LANES): a lane that needs a normal seen from below draws it at
    #: the start of its next iteration, where it would otherwise resume after the phase.
    tail = [False]

    def cond(s: dict) -> Any:
        c = s["active"] & (s["steps"] < s_lim)
        if split_walks:
            c = c & ~s["need_s"]
        return c & ~s["need_m"] if rough and not tail[0] else c

    def draw_below(s: dict) -> None:
        """Tail phases: the normal seen from below of the lanes that need one, as between phases
        (same inputs, same function), in a branch that SIMD packets without such a lane skip.
        (From the first phase on, the branch's code in the loop cost the others about 8 %.)"""
        def true_fn(nm: Any, d: Any, above: Any, mq: Any) -> Any:
            _, _, wi_m = local_wi({"nm": nm, "d": d, "above": above})
            return V3(_vndf_below(mi, dr, wi_m, mq.x, mq.y, alpha_o))

        below_m = s["need_m"]
        s["mq"] = dr.if_stmt(args=(s["nm"], s["d"], s["above"], s["mq"]), cond=below_m, true_fn=true_fn,
                             false_fn=lambda nm, d, above, mq: V3(mq), mode="symbolic", label="below")
        s["has_m"] = s["has_m"] | below_m
        s["need_m"] = s["need_m"] & ~below_m

    def body(s: dict) -> tuple[dict]:
        s = dict(s)
        rng = s["rng"]
        active = s["active"]

        # 1. Walks in progress scatter again below (their leaving test ended the last iteration).
        if rough:
            if tail[0]:
                draw_below(s)
            cont = s["walking"]
        p, d, inside = s["p"], s["d"], s["inside"]

        # 2. Trace the photons that are between boundaries.
        trace_m = active & ~s["walking"]
        retried = s["retried"]
        if z_inv:
            # z-invariant geometry: intersect with the horizontal direction and convert the
            # distance to 3D; no wrapping, whatever theta is.
            lxy = dr.sqrt(dr.fma(d.x, d.x, d.y * d.y))
            lxy_s = dr.maximum(lxy, 1e-30)
            fwd = V3(d.x / lxy_s, d.y / lxy_s, 0.0)
            # A random plane z per step: a ray that slips through a crack between two triangles
            # (float32 edge tests) is retried on other triangles instead of leaking.
            zr = (rng.next_float32() - 0.5) * zs_o
            pi = scene.ray_intersect_preliminary(mi.Ray3f(mi.Point3f(p.x, p.y, zr), fwd),
                                                 coherent=False, active=trace_m)
            hit = trace_m & pi.is_valid()
            t2 = dr.select(hit, pi.t, 0.0)
            p_hit = V3(dr.fma(fwd.x, t2, p.x), dr.fma(fwd.y, t2, p.y), 0.0)
            miss = trace_m & ~hit
            seg = F(s["seg"] + dr.select(hit, t2 / lxy_s, 0.0))
            leak = miss & inside & ~retried
            escape = miss & ~leak
        else:
            # Periodic slab [0, zp): stop the ray at the slab face it would cross and wrap it.
            tz = dr.select(d.z > 0, (zp_o - p.z) / d.z, dr.select(d.z < 0, -p.z / d.z, dr.inf))
            tz = dr.maximum(tz, 0.0)
            ray = mi.Ray3f(mi.Point3f(p), d)
            ray.maxt = F(tz)
            fwd = d
            pi = scene.ray_intersect_preliminary(ray, coherent=False, active=trace_m)
            hit = trace_m & pi.is_valid() & (pi.t < tz)
            t3 = dr.select(hit, pi.t, 0.0)
            p_hit = V3(dr.fma(d, t3, p))
            miss = trace_m & ~hit
            tz_s = dr.select(dr.isfinite(tz), tz, 0.0)
            p_end = dr.fma(d, tz_s, p)
            # Outside the bounding cylinder and moving away from it: nothing more can be hit.
            outside = (dr.fma(p_end.x, p_end.x, p_end.y * p_end.y) >= rb_o * rb_o) & (
                dr.fma(p_end.x, d.x, p_end.y * d.y) >= 0.0)
            gone = miss & (outside | ~dr.isfinite(tz))
            leak = gone & inside & ~retried
            escape = gone & ~leak
            wrap = miss & ~gone
            seg = F(s["seg"] + dr.select(hit, t3, dr.select(wrap, tz_s, 0.0)))
            p = dr.select(wrap, V3(p_end.x, p_end.y, dr.select(d.z > 0, 0.0, zp_o)), p)

        # A photon in the material cannot leave without crossing the boundary: it slipped
        # through a crack. Nudge it sideways by a few ulps and trace once more; if it misses
        # again, the medium flag was wrong (an offset past a thin edge) and it really escapes.
        jit = (rng.next_float32() - 0.5) * eps_o
        p = dr.select(leak, V3(p.x - d.y * jit, p.y + d.x * jit, p.z), p)
        leaks = U(s["leaks"] + dr.select(leak, 1, 0))
        s["retried"] = B(leak)

        # Normals at the hit: interpolated smooth normal and flat triangle normal.
        prim = pi.prim_index
        f0 = dr.gather(U, faces, prim * 3, hit)
        f1 = dr.gather(U, faces, prim * 3 + 1, hit)
        f2 = dr.gather(U, faces, prim * 3 + 2, hit)
        b1, b2 = pi.prim_uv.x, pi.prim_uv.y
        b0 = 1.0 - b1 - b2
        ns = V3(dr.normalize(dr.gather(V3, vnorm, f0, hit) * b0 + dr.gather(V3, vnorm, f1, hit) * b1
                             + dr.gather(V3, vnorm, f2, hit) * b2))
        ng = dr.gather(V3, fnorm, prim, hit)

        # A hit from the side opposite to the photon's medium means it crossed a feature thinner
        # than float32 can resolve (the tip of a slit lumen, where both walls fall within a few
        # ulps), or an offset carried it past such a feature. Either way it passes through
        # without interacting, which restores agreement between medium and geometry.
        mism = hit & ((dr.dot(d, ng) > 0.0) ^ inside)
        leaks = U(leaks + dr.select(mism, 1, 0))
        p = dr.select(mism, V3(dr.fma(fwd, eps_o, p_hit)), p)
        hit = hit & ~mism
        s["L"] = F(s["L"] + dr.select(hit & inside, seg, 0.0))
        s["seg"] = dr.select(hit, 0.0, seg)
        s["leaks"] = leaks
        s["hit_any"] = s["hit_any"] | hit

        if ev and rough:
            # An exit the expected value covered (evp): escaping, it ends unrecorded; meeting the
            # fiber again, it goes on (a pass-through of a sliver decides nothing yet).
            covered = escape & s["evp"]
            s["w"] = dr.select(covered, 0.0, s["w"])
            s["evp"] = s["evp"] & ~hit & ~escape

        over = hit & (s["bounces"] >= maxb)
        s["cut"] = s["cut"] | over
        hit = hit & ~over

        # 3. New boundary events: normals on the photon's side; near grazing the smooth normal can
        # face away from the photon, the flat one is used there.
        sgn = dr.select(inside, -1.0, 1.0)
        ngs = ng * sgn
        nss = ns * sgn
        nm = dr.select(dr.dot(-d, nss) > 1e-6, nss, ngs)
        s["p"] = dr.select(hit, p_hit, p)
        s["ngs"] = dr.select(hit, ngs, s["ngs"])
        s["nm"] = dr.select(hit, nm, s["nm"])
        s["above"] = s["above"] | hit
        s["bounces"] = U(s["bounces"] + dr.select(hit, 1, 0))
        if hull_esc:
            # Leaving through a face on the outline's convex hull is for good (see hull_esc).
            on_hull = dr.gather(U, fs.hull, pi.prim_index, hit) != 0
            if rough:
                s["hull"] = dr.select(hit, on_hull, s["hull"])
            if wedges is not None:
                s["face"] = dr.select(hit, pi.prim_index, s["face"])
        if ev:
            # The expected value serves hull faces and, on a rough walk, any other outer face
            # (what its exit ray shows to leave for good).
            served = on_hull | (dr.gather(U, outer, pi.prim_index, hit) != 0) if rough else on_hull
            s["evf"] = dr.select(hit, served, s["evf"])
        oh = B(False)
        if split:
            # A hit on the outer surface is split.
            oh = hit & (dr.gather(U, outer, pi.prim_index, hit) != 0)
        if split_walks:
            # Rough: pause until the K walks are run between phases (the first _SPLIT_HITS).
            oh = oh & (s["ns"] < _SPLIT_HITS)
            s["ns"] = U(s["ns"] + dr.select(oh, 1, 0))
            s["need_s"] = s["need_s"] | oh
            for k, v in (("p0", p_hit), ("d0", d), ("nm0", nm), ("ngs0", ngs), ("in0", inside)):
                s[k] = dr.select(oh, v, s[k])
            s["sa"] = dr.select(oh, rng.next_uint32(), s["sa"])
            s["sb"] = dr.select(oh, rng.next_uint32(), s["sb"])
            hit = hit & ~oh
        s["walking"] = s["walking"] | hit
        if rough:
            start = hit
            s["wsteps"] = dr.select(hit, 0, s["wsteps"])
            # The walk starts above every microfacet; the first hit height follows the masking.
            frame, sg, wi = local_wi(s)
            _, hn = _height_step(dr, F, -wi, F(1.0), rng.next_float32(), alpha_o)
            s["h"] = dr.select(start, hn, s["h"])
            # 4. One microfacet event for new and continuing walks.
            sc = start | cont
            u1, u2, u3 = rng.next_float32(), rng.next_float32(), rng.next_float32()
            if qmc:
                # The first boundary event takes its normal and Fresnel choice from the point.
                first = hit & (s["bounces"] == 1)
                u1, u2, u3 = (dr.select(first, s["q"][k], u) for k, u in enumerate((u1, u2, u3)))
            below = sc & ~s["has_m"] & (wi.z < 1e-3)
            if ev:
                # Normals seen from below the macro surface (drawn between phases) take the
                # plain estimator: the choice depends on the state only.
                elig = sc & s["evf"] & ~s["has_m"] & ~below
                expected_event(s, elig, sg, wi, rng)
            m_fast, _ = distr.sample(wi, mi.Point2f(u1, u2))
            m = dr.select(s["has_m"], s["mq"], V3(m_fast))
            wo, refl = fresnel_event(wi, m, s["inside"] ^ s["above"], u3)
            go = sc & ~below
            if ev:
                # The branch that ends outside: reflected on the outside, transmitted inside.
                s["evo"] = dr.select(go, elig & ~(refl ^ (s["inside"] ^ s["above"])), s["evo"])
            s["d"] = dr.select(go, V3(frame.to_world(wo * sg)), s["d"])
            s["above"] = dr.select(go & ~refl, ~s["above"], s["above"])
            s["wsteps"] = U(s["wsteps"] + dr.select(go, 1, 0))
            s["has_m"] = s["has_m"] & ~go
            s["need_m"] = below
            s["mq"] = dr.select(below, V3(u1, u2, 0.0), s["mq"])
        else:
            # Smooth boundary: one Fresnel event about the macro normal, in world space.
            u = rng.next_float32()
            if qmc:
                u = dr.select(hit & (s["bounces"] == 1), s["q"].x, u)
            if split:
                wo, refl, ended = split_smooth(s, oh, d, nm, inside, u, rng)
                wo_p, refl_p = fresnel_event(-d, nm, ~inside, u)
                wo, refl = dr.select(oh, wo, wo_p), dr.select(oh, refl, refl_p)
                active = active & ~ended
            elif ev:
                elig = hit & s["evf"]
                wo_e, refl_e, ended = expected_smooth(s, elig, d, nm, inside, rng)
                wo_p, refl_p = fresnel_event(-d, nm, ~inside, u)
                wo, refl = dr.select(elig, wo_e, wo_p), dr.select(elig, refl_e, refl_p)
                active = active & ~ended
            else:
                wo, refl = fresnel_event(-d, nm, ~inside, u)
            s["d"] = dr.select(hit, wo, s["d"])
            s["above"] = dr.select(hit, refl, s["above"])
            finish(s, hit)

        s["steps"] = U(s["steps"] + 1)
        stuck = active & ~escape & ~over & (s["steps"] >= maxs)
        s["cut"] = s["cut"] | stuck
        active = active & ~escape & ~over & ~stuck
        if hull_esc and not rough:
            active = active & ~(hit & on_hull & ~s["inside"])     # leaves for good (see hull_esc)
        if rough:
            # 5. Walks: does the photon leave the microsurface now? (Lanes still in flight; not a
            #    walk waiting for a normal seen from below, whose event has not happened yet.)
            test = s["walking"] & ~s["need_m"] & active
            sg = dr.select(s["above"], 1.0, -1.0)
            wi = -(V3(frame.to_local(s["d"])) * sg)     # local_wi(s), the frame of step 4
            leave, hn = _height_step(dr, F, -wi, s["h"] * sg, rng.next_float32(), alpha_o)
            s["h"] = dr.select(test, hn * sg, s["h"])
            forced = test & ~leave & (s["wsteps"] >= maxw)
            s["forced"] = U(s["forced"] + dr.select(forced, 1, 0))
            # A walk that is forced out leaves along its current direction, on the side it points to.
            s["above"] = dr.select(forced, dr.dot(s["d"], s["nm"]) > 0.0, s["above"])
            fin = test & (leave | forced)
            finish(s, fin)
            if ev:
                # Leaving now, after a branch that ends outside, is the outcome whose expectation
                # the event deposited: on a hull face the photon ends here, unrecorded; on
                # another outer face its next ray decides (evp: it ends if it escapes).
                gone = test & leave & s["evo"]
                s["evo"] = s["evo"] & ~test
                s["evp"] = s["evp"] | (gone & ~s["hull"])
                gone = gone & s["hull"]
                active = active & ~gone
                s["w"] = dr.select(gone, 0.0, s["w"])
            if hull_esc:
                active = active & ~(fin & s["hull"] & ~s["inside"])     # leaves for good (see hull_esc)
        s["active"] = active
        if not z_inv:
            # Keep offset points inside the periodic slab.
            q = s["p"]
            s["p"] = V3(q.x, q.y, dr.select(q.z < 0.0, q.z + zp_o, dr.select(q.z > zp_o, q.z - zp_o, q.z)))
        s["rng"] = rng
        return (s,)

    def split_walks_between_phases(st: dict, need: Any, deposits: dict[str, list[np.ndarray]]) -> None:
        """Run the K microsurface walks of every photon paused at the outer surface (lanes ``need``).

        The walks run in their own loop, K lanes per photon, without ray casts (the main loop
        would run its whole body, ray cast included, for every step of every walk). Each result
        that leaves the fiber for good is deposited with weight w / K; the photon continues with
        one of the others, chosen uniformly, with probability (their number) / K, else it ends.
        Photons are taken ``_SPLIT_CHUNK`` walks at a time (bounded memory).
        """
        step = max(1, _SPLIT_CHUNK // split)
        total = dr.width(need)
        for c0 in range(0, total, step):
            part = need if total <= step else dr.gather(U, need, dr.arange(U, c0, min(c0 + step, total)))
            split_chunk(st, part, deposits)
        dr.scatter(st["need_s"], False, need)
        dr.eval(st)

    def split_chunk(st: dict, need: Any, deposits: dict[str, list[np.ndarray]]) -> None:
        """The K walks of the photons in lanes ``need`` (see :func:`split_walks_between_phases`)."""
        K = split
        m = dr.width(need)
        M = m * K
        r = dr.arange(U, M)
        own = r // K                     # the photon of each walk, 0..m-1
        lane = dr.gather(U, need, own)   # its lane in the state
        g = {k: dr.gather(type(st[k]), st[k], lane) for k in ("p0", "d0", "nm0", "ngs0", "in0", "L", "bounces",
                                                             "w", "idx", "sa", "sb")}
        # One stream per walk: seeded by the photon's two numbers and the walk's number.
        key = (mi.UInt64(g["sa"]) << 32) | mi.UInt64(g["sb"])
        j = mi.UInt64(r - own * K)
        wr = mi.PCG32(size=M)
        wr.seed(initstate=key + j * 0x9E3779B97F4A7C15, initseq=key ^ (j + 1))
        frame = mi.Frame3f(g["nm0"])
        in0 = g["in0"]
        # Local travel direction v (z: the macro normal on the photon's side); the walk starts
        # above every microfacet, at a first height that follows the masking.
        v = V3(frame.to_local(g["d0"]))
        _, h = _height_step(dr, F, v, F(1.0), wr.next_float32(), alpha_o)
        ws = {"v": v, "h": F(h), "above": dr.full(B, True, M), "wsteps": dr.zeros(U, M),
              "done": dr.full(B, False, M), "need_m": dr.full(B, False, M), "has_m": dr.full(B, False, M),
              "mq": dr.zeros(V3, M), "forced": dr.zeros(U, M), "rng": wr}

        def wcond(w: dict) -> Any:
            return ~w["done"] & ~w["need_m"]

        def wbody(w: dict) -> tuple[dict]:
            w = dict(w)
            rng_w = w["rng"]
            # One microfacet event (as in the main loop's step 4), then the height test (step 1).
            sg = dr.select(w["above"], 1.0, -1.0)
            wi = -(w["v"] * sg)
            u1, u2, u3 = rng_w.next_float32(), rng_w.next_float32(), rng_w.next_float32()
            below = ~w["has_m"] & (wi.z < 1e-3)
            m_fast, _ = distr.sample(wi, mi.Point2f(u1, u2))
            mn = dr.select(w["has_m"], w["mq"], V3(m_fast))
            wo, refl = fresnel_event(wi, mn, in0 ^ w["above"], u3)
            go = ~below
            w["v"] = dr.select(go, V3(wo * sg), w["v"])
            w["above"] = dr.select(go & ~refl, ~w["above"], w["above"])
            w["wsteps"] = U(w["wsteps"] + dr.select(go, 1, 0))
            w["has_m"] = w["has_m"] & ~go
            w["need_m"] = below
            w["mq"] = dr.select(below, V3(u1, u2, 0.0), w["mq"])
            sg2 = dr.select(w["above"], 1.0, -1.0)
            leave, hn = _height_step(dr, F, V3(w["v"] * sg2), w["h"] * sg2, rng_w.next_float32(), alpha_o)
            w["h"] = dr.select(go, F(hn * sg2), w["h"])
            forced = go & ~leave & (w["wsteps"] >= maxw)
            w["forced"] = U(w["forced"] + dr.select(forced, 1, 0))
            w["above"] = dr.select(forced, w["v"].z > 0.0, w["above"])
            w["done"] = w["done"] | (go & (leave | forced))
            w["rng"] = rng_w
            return (w,)

        while True:
            (ws,) = dr.while_loop((ws,), wcond, wbody, mode="symbolic", label="split walks")
            dr.eval(ws)
            pend = dr.compress(ws["need_m"])
            if len(pend) == 0:
                break
            # Microfacet normals seen from below the macro surface: exact, on just those walks.
            sub = {k: dr.gather(type(ws[k]), ws[k], pend) for k in ("v", "above", "mq")}
            wi = -(sub["v"] * dr.select(sub["above"], 1.0, -1.0))
            dr.scatter(ws["mq"], _vndf_below(mi, dr, V3(wi), sub["mq"].x, sub["mq"].y, alpha_o), pend)
            dr.scatter(ws["has_m"], True, pend)
            dr.scatter(ws["need_m"], False, pend)
            dr.eval(ws)
        wr = ws["rng"]                   # the walks' streams, past the numbers they used
        above = ws["above"]
        d_out, p_out = settle(V3(frame.to_world(ws["v"])), g["ngs0"], g["p0"], above)
        inside = in0 ^ ~above
        esc = escapes(p_out, d_out, ~inside, wr)
        # Deposits: the walks that leave the fiber for good, w / K each.
        dsel = dr.compress(esc)
        if len(dsel) > 0:
            for k, val in (("lane", g["idx"]), ("dx", d_out.x), ("dy", d_out.y), ("dz", d_out.z), ("L", g["L"]),
                           ("w", g["w"] * inv_k), ("bounces", g["bounces"])):
                deposits[k].append(np.asarray(dr.gather(type(val), val, dsel).numpy()))
        # The continuing result: the one with the largest random key among the photon's others.
        keep = ~esc
        keyf = dr.select(keep, wr.next_float32(), -1.0)
        best = dr.full(F, -1.0, m)
        dr.scatter_reduce(dr.ReduceOp.Max, best, keyf, own)
        nc = dr.zeros(U, m)
        dr.scatter_reduce(dr.ReduceOp.Add, nc, dr.select(keep, U(1), U(0)), own)
        chosen = keep & (keyf == dr.gather(F, best, own))
        tgt = dr.gather(U, need, own)
        dr.scatter(st["p"], p_out, tgt, chosen)
        dr.scatter(st["d"], d_out, tgt, chosen)
        dr.scatter(st["inside"], inside, tgt, chosen)
        dr.scatter_reduce(dr.ReduceOp.Add, st["forced"], ws["forced"], tgt)
        # Continue with probability nc / K (Russian roulette), at the photon's weight.
        ur = mi.PCG32(size=m)
        kk = dr.gather(mi.UInt64, key, dr.arange(U, m) * K)
        ur.seed(initstate=kk ^ 0x5851F42D4C957F2D, initseq=kk + 0x14057B7EF767814F)
        alive = ur.next_float32() * float(K) < F(nc)
        dr.scatter(st["active"], alive, need, ~alive)
        dr.scatter(st["w"], F(0.0), need, ~alive)
        dr.eval(st)

    if mode not in ("symbolic", "wavefront"):
        raise ValueError(f"unknown loop mode {mode!r}")
    out_d = dr.zeros(V3, n)
    out_L = dr.zeros(F, n)
    out_hit = dr.full(B, False, n)
    out_cut = dr.full(B, False, n)
    out_b = dr.zeros(U, n)
    counters = {k: dr.zeros(U, n) for k in ("leaks", "forced")}   # "forced": rough walks only
    out_w = dr.full(F, 1.0, n)
    deposits: dict[str, list[np.ndarray]] = {k: [] for k in ("lane", "dx", "dy", "dz", "L", "w", "bounces")}
    limit = 0
    while True:
        limit += _TAIL_STEPS if tail[0] else int(phase_steps)
        s_lim = dr.opaque(U, limit)
        if ev and rough:
            # A lane queues at most one event per iteration: room for every iteration left to it.
            # The queue holds the events of several phases and is flushed when this phase's room
            # might not fit (each flush merges the per-thread histograms once).
            room = int(dr.sum(dr.select(st["active"], limit - dr.minimum(st["steps"], limit), 0))[0]) + 1
            pending = int(evq["count"][0]) if evq else 0
            if pending and pending + room > evq_cap[0]:
                expected_exits(pending)
                evq["count"] = dr.zeros(U, 1)
            if not evq or room > evq_cap[0]:
                evq_cap[0] = max(room, _EV_QUEUE)
                evq.update({k: dr.empty(U if k in EV_UINT else F, evq_cap[0]) for k in EV_FIELDS})
                evq["count"] = dr.zeros(U, 1)
        if split and not rough:
            # A lane deposits at most once per iteration: room for every iteration left to it.
            room = int(dr.sum(dr.select(st["active"], limit - dr.minimum(st["steps"], limit), 0))[0]) + 1
            dep.update({k: dr.empty(F, room) for k in ("dx", "dy", "dz", "L", "w")})
            dep.update({"lane": dr.empty(U, room), "bounces": dr.empty(U, room), "count": dr.zeros(U, 1)})
        if mode == "symbolic":
            (st,) = dr.while_loop((st,), cond, body, mode="symbolic", label="photon")
        else:
            (st,) = dr.while_loop((st,), cond, body, mode="evaluated",
                                  compress=dr.width(st["active"]) > 1, label="photon")
        dr.eval(st)                 # one launch for every output of the loop
        if ev and rough:
            used = int(evq["count"][0])
            if used > evq_cap[0]:
                raise RuntimeError(f"the expected-value estimator queued {used} events into room for {evq_cap[0]}")
        if split and not rough:
            used = int(dep["count"][0])
            if used > room:
                raise RuntimeError(f"splitting deposited {used} exits into room for {room}")
            if used:
                sel = dr.arange(U, used)
                for k, v in deposits.items():
                    v.append(np.asarray(dr.gather(type(dep[k]), dep[k], sel).numpy()))
        if rough:
            # Microfacet normals seen from below the macro surface: exact, on just those lanes.
            need = dr.compress(st["need_m"])
            if len(need) > 0:
                sub = _gather_state(mi, dr, {k: st[k] for k in ("nm", "d", "above", "mq")}, need)
                _, _, wi = local_wi(sub)
                m = _vndf_below(mi, dr, wi, sub["mq"].x, sub["mq"].y, alpha_o)
                dr.scatter(st["mq"], m, need)
                dr.scatter(st["has_m"], True, need)
                dr.scatter(st["need_m"], False, need)
                dr.eval(st)
        if split_walks:
            need = dr.compress(st["need_s"])
            if len(need) > 0:
                split_walks_between_phases(st, need, deposits)
        act = st["active"]
        n_act = int(dr.count(act)[0])
        size = dr.width(act)
        tail[0] = tail[0] or (rough and mode == "symbolic" and not split and n_act <= _TAIL_LANES)
        if n_act == 0 or n_act < size // 2:
            # Write every lane's current outcome (finished lanes are final), then keep the rest.
            dr.scatter(out_d, st["d"], st["idx"])
            dr.scatter(out_L, st["L"], st["idx"])
            dr.scatter(out_hit, st["hit_any"], st["idx"])
            dr.scatter(out_cut, st["cut"], st["idx"])
            dr.scatter(out_b, st["bounces"], st["idx"])
            if split or ev:
                dr.scatter(out_w, st["w"], st["idx"])
            for k, out in counters.items():
                if k in st:
                    dr.scatter(out, st[k], st["idx"])
            if n_act == 0:
                break
            st = _gather_state(mi, dr, st, dr.compress(act))
            dr.eval(out_d, out_L, out_hit, out_cut, out_b, counters, st)
    if ev and rough and evq:
        used = int(evq["count"][0])
        if used:
            expected_exits(used)
    dr.eval(out_d, out_L, out_hit, out_cut, out_b, counters, out_w)
    dn = np.asarray(out_d.numpy())
    extra: dict[str, Any] = {}
    if ev:
        extra["w"] = np.asarray(out_w.numpy())
        # From the kernels' bin-major layout to (direction, level, weight / weight x L, bin), by a
        # gather on every thread (numpy's strided transpose of the same took 3 % of a bake).
        i = dr.arange(U, hist_n * 2 * nlev * nbin)
        dk, b = i // nbin, i % nbin                  # dk: direction x (2 levels) + value
        src = (dk // (2 * nlev) * nbin + b) * histogram.stride + dk % (2 * nlev)
        extra["hist"] = np.asarray(dr.gather(mi.Float32, hist, src).numpy(), dtype=np.float64).reshape(
            hist_n, nlev, 2, nbin)
        extra["hist_first"] = hist_first
        if rough:
            extra["ev_events"] = np.asarray(ev_events.numpy(), dtype=np.int64)
            extra["ev_normals"] = np.asarray(ev_normals.numpy(), dtype=np.int64)
    if split:
        extra["w"] = np.asarray(out_w.numpy())
        extra["deposits"] = {k: (np.concatenate(v) if v else np.zeros(0, np.uint32 if k in ("lane", "bounces")
                                                                        else np.float32)) for k, v in deposits.items()}
    return {
        **extra,
        "d": dn.T if dn.ndim == 2 and dn.shape[0] == 3 and dn.shape[1] == n else dn,
        "L": np.asarray(out_L.numpy()),
        "hit_any": np.asarray(out_hit.numpy()).astype(bool),
        "cut": np.asarray(out_cut.numpy()).astype(bool),
        "bounces": np.asarray(out_b.numpy()),
        **{k: np.asarray(v.numpy()) for k, v in counters.items()},
    }


def trace(
    profile: Any,
    theta_i: float,
    phi_i: float,
    n_photons: int,
    *,
    eta: float,
    beta_deg: float,
    max_bounces: int = 256,
    seed: int = 0,
    cuticle: tuple[float, float, float] | None = None,
    batch: int = 1 << 21,
    mode: str = "symbolic",
    max_steps: int | None = None,
    sampler: str = "independent",
    split: int = 0,
    expected: int = 0,
    histogram: ExitHistogram | None = None,
    expected_allocation: str = "adaptive",
    expected_sampler: str = "ndf",
) -> TraceResult:
    """Trace ``n_photons`` from direction (theta_i, phi_i) (radians, towards the light).

    ``profile`` is a :class:`~usdfiber.bake.profiles.Profile` or a :class:`FiberScene` from
    :func:`prepare` (reuse it across directions to skip meshing). ``eta`` is the fiber's
    refractive index (air outside and in holes), ``beta_deg`` the roughness angle
    (Beckmann alpha = tan(beta)), ``cuticle=(tilt_deg, height_um, spacing_um)`` adds wool
    scales. Photons are traced ``batch`` at a time. ``mode="symbolic"`` (default) compiles the
    whole random walk into one kernel, run in phases of 8 iterations with finished photons
    compacted away in between; ``mode="wavefront"`` launches one kernel per iteration and
    compacts after each (1.5x slower on 2 CPU cores; may differ on a GPU). Both give identical
    photons for a given ``seed``, whatever ``batch`` is. ``max_steps`` bounds loop iterations
    including periodic wraps (cuticle fibers at grazing angles); photons stopped by it or by
    ``max_bounces`` are reported as cut. ``sampler="sobol"`` draws the beam offset and the
    first boundary event's numbers from an Owen-scrambled Sobol point per photon (one
    scramble per stream, :mod:`usdfiber.bake.sampling`): the photons of a stream are
    stratified over those dimensions; ``"independent"`` (default) uses PCG32 numbers only.
    ``split=K`` (extruded fibers) splits every hit of the outer surface into K independent
    microsurface walks from the same state: each result that leaves the fiber for good is an
    exit of weight w / K; the photon continues with one of the other results, chosen
    uniformly, with probability (their number) / K (so paths are no longer than without
    splitting). At a smooth boundary the K walks are K Fresnel choices. The result then
    has several weighted exits per photon (``TraceResult.weight``). ``expected=K`` (extruded
    fibers; needs ``histogram``, the bins and absorption levels) is the expected-value
    estimator at the outer boundary: at every microfacet event on an outer face of the outline's
    convex hull it histograms the expected exit of the branch that ends outside and leaves the
    microsurface, over K normals (see the module docstring); the result's
    ``histogram`` holds those exits, its rows the others. ``expected_allocation``:
    "adaptive" (default) gives each event from 1 to K normals in proportion to the Fresnel
    weight of its exiting branch (:data:`_EV_TILT`), "uniform" K to every event; the result's
    ``extra`` counts ``expected_events`` and ``expected_normals``. ``expected_sampler``: "ndf"
    (default) draws the normals from the normal distribution and weights them by their
    visibility, "visible" from the visible normals (see the module docstring). Many directions
    are faster together: :func:`trace_many`.
    """
    return trace_many(profile, [(theta_i, phi_i)], n_photons, eta=eta, beta_deg=beta_deg,
                      max_bounces=max_bounces, seed=seed, cuticle=cuticle, batch=batch, mode=mode,
                      max_steps=max_steps, sampler=sampler, split=split, expected=expected,
                      histogram=histogram, expected_allocation=expected_allocation,
                      expected_sampler=expected_sampler)[0]


def trace_many(
    profile: Any,
    directions: Sequence[tuple[float, float]],
    n_photons: int | Sequence[int],
    *,
    eta: float,
    beta_deg: float,
    max_bounces: int = 256,
    seed: int | Sequence[int] = 0,
    cuticle: tuple[float, float, float] | None = None,
    batch: int = 1 << 21,
    mode: str = "symbolic",
    max_steps: int | None = None,
    sampler: str = "independent",
    split: int = 0,
    expected: int = 0,
    histogram: ExitHistogram | None = None,
    expected_allocation: str = "adaptive",
    expected_sampler: str = "ndf",
    spread: Sequence[tuple[float, float, float, float] | None] | None = None,
) -> list[TraceResult]:
    """Trace several incoming directions ``(theta_i, phi_i)`` (radians) in shared launches.

    ``n_photons`` and ``seed`` are one value or one per direction. Direction ``j`` gets exactly
    the photons ``trace(profile, *directions[j], n_photons[j], seed=seed[j], ...)`` would
    trace (same random streams, same arithmetic); only the launches are shared: the
    photons of all directions are traced ``batch`` lanes at a time, so the fixed cost of a
    launch (its phases run until the slowest photon is done, each recorded and launched
    anew) is paid once per ``batch`` photons rather than once per direction. A result's
    ``seconds`` is the call's wall time shared out by photon count. ``spread`` (extruded
    fibers): per direction a bin ``(theta_lo, theta_hi, phi_lo, phi_hi)`` (radians, holding
    the direction; phi_lo = phi_hi for one azimuth) from which every photon draws its own
    light direction, theta with density cos^2(theta) and phi uniform, over one launch
    interval that covers the fiber's shadow from the whole bin, so that every photon that
    meets the fiber carries the same power (a box-filtered incoming bin; the result's
    ``theta_i``, ``phi_i`` stay the given direction, its ``beam_width`` is W at it). Other
    arguments: see :func:`trace`.
    """
    import time

    mitsuba()  # selects the JIT variant (and LLVM) before drjit is used
    import drjit as dr

    fs = profile if isinstance(profile, FiberScene) else prepare(profile, cuticle)
    if cuticle is not None and fs.cuticle != tuple(cuticle):
        raise ValueError("the prepared FiberScene was built with a different cuticle")
    dirs = [(float(t), float(p)) for t, p in directions]
    nd = len(dirs)
    if nd == 0:
        return []
    counts = np.broadcast_to(np.asarray(n_photons, dtype=np.int64), (nd,)).copy()
    seeds = np.broadcast_to(np.asarray(seed, dtype=object), (nd,))
    if not eta > 0.0:
        raise ValueError("eta must be > 0")
    if np.any(counts <= 0):
        raise ValueError("n_photons must be > 0")
    if not 0.0 <= beta_deg < 90.0:
        raise ValueError("beta_deg must be in [0, 90)")
    if sampler not in ("independent", "sobol"):
        raise ValueError(f"sampler must be 'independent' or 'sobol', got {sampler!r}")
    if not (isinstance(split, (int, np.integer)) and 0 <= int(split) <= MAX_SPLIT_WALKS):
        raise ValueError(f"split must be an integer from 0 (off) to {MAX_SPLIT_WALKS}, got {split!r}")
    if split and not fs.mesh.z_invariant:
        raise ValueError("split needs an extruded fiber: the escape test of fibers with cuticle scales is not built")
    if not (isinstance(expected, (int, np.integer)) and 0 <= int(expected) <= MAX_EXPECTED_NORMALS):
        raise ValueError(f"expected must be an integer from 0 (off) to {MAX_EXPECTED_NORMALS}, got {expected!r}")
    expected = int(expected)
    if expected and split:
        raise ValueError("expected and split cannot be combined (both replace the outer surface's exits)")
    if expected and not fs.mesh.z_invariant:
        raise ValueError("expected needs an extruded fiber: leaving through cuticle scales is not known to be for good")
    if expected and histogram is None:
        raise ValueError("expected needs a histogram (ExitHistogram: the output bins and absorption levels)")
    if expected_allocation not in EXPECTED_ALLOCATIONS:
        raise ValueError(f"expected_allocation must be one of {', '.join(EXPECTED_ALLOCATIONS)}, "
                         f"got {expected_allocation!r}")
    if expected_sampler not in EXPECTED_SAMPLERS:
        raise ValueError(f"expected_sampler must be one of {', '.join(EXPECTED_SAMPLERS)}, got {expected_sampler!r}")
    boxes = None
    if spread is not None:
        if len(spread) != nd:
            raise ValueError(f"spread needs one bin per direction ({nd}), got {len(spread)}")
        if not fs.mesh.z_invariant:
            raise ValueError("spread needs an extruded fiber (no cuticle scales)")
        boxes = np.array([(th, th, ph, ph) if sp is None else sp for (th, ph), sp in zip(dirs, spread)],
                         dtype=np.float64)
        ok = (np.isfinite(boxes).all(axis=1) & (boxes[:, 0] <= boxes[:, 1]) & (boxes[:, 2] <= boxes[:, 3])
              & (boxes[:, 0] >= -0.5 * np.pi) & (boxes[:, 1] <= 0.5 * np.pi) & (boxes[:, 3] - boxes[:, 2] < 0.5 * np.pi))
        if not ok.all():
            raise ValueError(f"spread {tuple(boxes[~ok][0])} is not a bin (theta_lo <= theta_hi within "
                             "[-pi/2, pi/2], phi_lo <= phi_hi less than pi/2 apart)")
    if sampler == "sobol" and int(counts.max()) > 1 << 32:
        raise ValueError("sampler 'sobol' numbers at most 2^32 photons per stream")
    # Per direction: -omega_i, u = (cos phi, sin phi), and the launch interval along u_perp.
    beams = np.empty((nd, 7), dtype=np.float64)
    widths = np.empty((nd, 2), dtype=np.float64)     # W(phi_i), launch width
    extra = fs.cuticle[1] if fs.cuticle is not None else 0.0
    for j, (th, ph) in enumerate(dirs):
        lo, hi = profile_bounds(fs.profile, ph)
        W = _projected_width(fs.profile, ph)
        if boxes is not None and boxes[j, 3] > boxes[j, 2]:
            # One interval along every u_perp of the bin: the union of the shadows (sampled
            # finely; the margin below covers what lies between the samples).
            b = [profile_bounds(fs.profile, q) for q in np.linspace(boxes[j, 2], boxes[j, 3], 17)]
            lo, hi = min(x[0] for x in b), max(x[1] for x in b)
        # Margin: the polygon's shadow may differ slightly from W, and scales stick out of the loop.
        margin = 0.01 * W + extra + 1e-3
        lo_l, width = lo - margin, (hi - lo) + 2.0 * margin
        cti, sti, cpi, spi = float(np.cos(th)), float(np.sin(th)), float(np.cos(ph)), float(np.sin(ph))
        beams[j] = (-cti * cpi, -cti * spi, -sti, cpi, spi, lo_l, width)
        widths[j] = (W, width)
    beams32 = beams.astype(np.float32)
    mixes = np.array([_seed_mix(int(s)) for s in seeds], dtype=np.uint64)
    scramble = sampling.scramble_seeds(mixes) if sampler == "sobol" else None
    alpha = float(np.tan(np.radians(beta_deg))) if beta_deg > 0.0 else 0.0
    if max_steps is None:
        # A safety net only: boundary hits, microsurface events (256 per hit) and z-wraps have
        # their own limits; photons in long walks cost little once the others are compacted away.
        max_steps = 1 << 17

    t0 = time.perf_counter()
    starts = np.concatenate([[0], np.cumsum(counts)])
    total = int(starts[-1])
    kept: dict[str, list[np.ndarray]] = {"beam": [], "d": [], "L": [], "cut": [], "bounces": [], "w": []}
    n_hit = np.zeros(nd, dtype=np.int64)
    n_leaks = np.zeros(nd, dtype=np.int64)
    n_forced = np.zeros(nd, dtype=np.int64)
    ev_counts = np.zeros((2, nd), dtype=np.int64)      # expected value: events, normals
    # Expected values: each direction's histograms, one per launch that traced some of its
    # photons (summed only when a launch boundary split it: usually one, kept as it came).
    hist_parts: list[list[np.ndarray]] = [[] for _ in range(nd)]
    # Expected values: a launch spans few enough directions for its histograms (with their
    # copies per thread) to stay below _HIST_BYTES (launches end at a direction's end instead).
    span = max(1, _HIST_BYTES // (histogram.bytes_per_direction * _hist_copies(histogram))) if expected else nd
    lanes = min(int(batch), _EV_LANES) if expected and alpha > 0.0 else int(batch)
    a = 0
    while a < total:
        b = min(a + lanes, total, int(starts[min(nd, int(np.searchsorted(starts, a, side="right") - 1) + span)]))
        # Lanes a .. b - 1: the photons of each direction they cover, in order.
        j0 = int(np.searchsorted(starts, a, side="right") - 1)
        j1 = int(np.searchsorted(starts, b, side="left"))
        per = np.minimum(starts[j0 + 1:j1 + 1], b) - np.maximum(starts[j0:j1], a)
        beam = np.repeat(np.arange(j0, j1, dtype=np.uint32), per)
        photon = (np.arange(a, b, dtype=np.int64) - starts[beam]).astype(np.uint64)
        launch = _Launch(beams32, beam, photon, mixes[beam], scramble, boxes)
        out = _trace_batch(fs, launch, eta=float(eta), alpha=alpha, max_bounces=int(max_bounces),
                           max_steps=int(max_steps), mode=mode, split=int(split), expected=expected,
                           histogram=histogram, expected_allocation=expected_allocation,
                           expected_sampler=expected_sampler)
        a = b
        hit = out["hit_any"]
        n_hit += np.bincount(beam[hit], minlength=nd)
        for total_k, key in ((n_leaks, "leaks"), (n_forced, "forced")):
            nz = np.flatnonzero(out[key])      # rare events: count them where they happened
            total_k += np.bincount(beam[nz], weights=out[key][nz], minlength=nd).astype(np.int64)
        if expected:
            f0 = int(out["hist_first"])
            for j, h in enumerate(out["hist"], start=f0):
                hist_parts[j].append(h)
            if "ev_events" in out:
                ev_counts[0, f0:f0 + len(out["hist"])] += out["ev_events"]
                ev_counts[1, f0:f0 + len(out["hist"])] += out["ev_normals"]
            # Photons whose last exit was deposited as an expectation (weight 0) leave no row.
            hit = hit & ((out["w"] > 0.0) | out["cut"])
        if split:
            # Photons whose path ended inside a split left all their weight in deposits.
            hit = hit & ((out["w"] > 0.0) | out["cut"])
        kept["beam"].append(beam[hit])
        kept["d"].append(out["d"][hit])
        kept["L"].append(out["L"][hit])
        kept["cut"].append(out["cut"][hit])
        kept["bounces"].append(out["bounces"][hit])
        if split or expected:
            kept["w"].append(out["w"][hit])
        if split:
            dp = out["deposits"]
            kept["beam"].append(beam[dp["lane"]])
            kept["d"].append(np.stack([dp["dx"], dp["dy"], dp["dz"]], axis=-1))
            kept["L"].append(dp["L"])
            kept["cut"].append(np.zeros(len(dp["L"]), bool))
            kept["bounces"].append(dp["bounces"])
            kept["w"].append(dp["w"])
    dr.sync_thread()
    seconds = time.perf_counter() - t0
    cat = {k: (v[0] if len(v) == 1 else np.concatenate(v)) for k, v in kept.items() if v}
    if split:
        # Deposits follow each batch's photons: bring each direction's rows together.
        order = np.argsort(cat["beam"], kind="stable")
        cat = {k: v[order] for k, v in cat.items()}
    # Lanes are in direction order, so each direction's photons are one contiguous run.
    cuts = np.searchsorted(cat["beam"], np.arange(nd + 1, dtype=cat["beam"].dtype), side="left")
    results = []
    for j, (th, ph) in enumerate(dirs):
        r = slice(cuts[j], cuts[j + 1])
        results.append(TraceResult(
            directions=np.ascontiguousarray(cat["d"][r], dtype=np.float32),
            path_length=cat["L"][r].astype(np.float32, copy=False),
            cut=cat["cut"][r].astype(bool, copy=False),
            bounces=cat["bounces"][r].astype(np.uint32, copy=False),
            n_launched=int(counts[j]),
            n_hit=int(n_hit[j]),
            beam_width=float(widths[j, 0]),
            launch_width=float(widths[j, 1]),
            theta_i=th,
            phi_i=ph,
            eta=float(eta),
            beta_deg=float(beta_deg),
            seconds=seconds * float(counts[j]) / total,
            extra={"leaks": int(n_leaks[j]), "forced": int(n_forced[j]),
                   **({"expected_events": int(ev_counts[0, j]), "expected_normals": int(ev_counts[1, j])}
                      if expected else {})},
            weight=cat["w"][r].astype(np.float32, copy=False) if (split or expected) else None,
            histogram=_summed(hist_parts[j], (len(histogram.levels), 2, histogram.n_bins)) if expected else None,
            histogram_bins=histogram if expected else None,
        ))
    return results
