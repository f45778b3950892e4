"""Baking BCSDF tables: photon tracing over the incoming directions a table needs.

:func:`bake_table` traces one cross-section variant (a
:class:`~usdfiber.bake.profiles.Profile`) for every incoming direction of its grid and
returns a :class:`~usdfiber.bake.table.BcsdfTable`. :func:`tables_for_stage` lists exactly
the distinct tables a USD stage needs; :func:`requests_from_preset` and
:func:`requests_from_params` do the same for a fiber preset or a JSON parameter file.

Per incoming direction
----------------------
Photons are traced in ``batches`` independent batches (distinct random streams; batch ``b``
of every direction uses the same stream, so errors vary smoothly with omega_i). Their exit
directions are histogrammed into the theta_o x phi_o bins, weighted by ``exp(-s_k L)`` at
each absorption level (``L``: path length in the material). The variance between batches
gives the direction's error estimate: the relative L2 error of ``p`` over the sphere,
``sqrt(sum_b dOmega_b Var[p_b]) / sqrt(sum_b dOmega_b p_b^2)`` with ``Var`` the variance of
the batch mean (at ``sigma_a = 0``). In ``target_error`` mode batches are added until the
estimate reaches the target (or ``max_photons``); the error of a Monte Carlo histogram
falls as ``N^-1/2``, which sets how many more are needed.

Directions are traced together: batch ``b`` of up to :data:`GROUP_DIRECTIONS` directions
(about :data:`GROUP_PHOTONS` photons) is one tracer launch. Each direction still gets exactly
its own photons, so a table does not depend on the grouping; what is shared is the tracer's
fixed cost per launch (recording and launching its phases until the slowest photon is done),
which dominated small-photon bakes such as the renderer's (bench/REPORT.md, "grouping").

Normalization: an extruded fiber intercepts exactly the photons launched over its shadow
``W(phi_i)``; ``Lambda`` is surviving weight over photons that met the fiber (photons stopped
by ``max_bounces`` are lost: with the default 4096 none was, while 256 lost up to 0.4% of a
near-smooth round fiber's light in trapped, nearly grazing paths). A fiber with cuticle scales has an uneven surface: ``W`` is the
width of the shadow of the scales' outer envelope (the profile offset by the scale height)
and a photon crossing that envelope's shadow without touching a scale goes straight on,
which in the far field is scattering into ``omega_o = -omega_i`` (it is counted there).

Symmetries: extruded fibers are traced for theta_i >= 0 only; rotationally symmetric
profiles (a round profile, smooth or rough, with or without cuticle rings) for one phi_i;
their tables are also mirror-averaged, ``p(phi_o - phi_i) = p(phi_i - phi_o)``, which halves
the variance.

Diameter: the stage's fibers are baked at a circumscribed diameter of 1 um (cuticle height
and spacing relative to the diameter, as in ``FiberParams.geometry_inputs``); a fiber of
diameter ``D`` um recolours the table with ``diameter_scale = D`` (see
:mod:`usdfiber.bake.table`). ``BakeSettings.levels`` are optical depths across the
circumscribed diameter, ``sigma_a * D``; the table stores them in 1/um of its baked size.

Incoming directions are sampled at bin centres by default (the paper's choice, for
interpolation between nodes); ``BakeSettings(incoming="box")`` spreads each node's light over
its bin instead, which makes the discrete table reciprocal bin for bin.

Resuming: with ``resume_dir``, every finished incoming direction is written there as an
atomic chunk file (``d<theta>_<phi>.npz``) before the next group of directions starts (an
interruption loses at most the group in flight: about ``GROUP_PHOTONS`` photons per batch); a
rerun with the same directory (and the same inputs and settings, recorded in ``bake.json``)
traces only the directions without a chunk.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import platform
import tempfile
import time
import warnings
from dataclasses import asdict, dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

import numpy as np

from usdfiber.bake.table import DEFAULT_LEVELS, WIDTH_SAMPLES, BcsdfTable, Grid, assemble
from usdfiber.table_format import save_npz_atomic

__all__ = [
    "BAKER_VERSION",
    "BakeError",
    "BakeSettings",
    "BUILTIN_PROFILE_VERTICES",
    "FAMILY_KINDS",
    "ProgressFn",
    "TableRequest",
    "bake_request",
    "bake_table",
    "is_rotationally_symmetric",
    "params_from_mapping",
    "params_from_preset",
    "profile_for",
    "requests_for_params",
    "requests_from_params",
    "requests_from_preset",
    "tables_for_stage",
]

#: Bumped when the baker's algorithm changes what it writes (part of the cache key).
BAKER_VERSION = 1
#: Vertices of the outer loop of built-in cross sections.
BUILTIN_PROFILE_VERTICES = 512
#: Built-in cross-section family (fiber:profile token) -> profiles.builtin_profiles kind.
FAMILY_KINDS: dict[str, str] = {
    "round": "polyester",
    "roundedTriangle": "silk",
    "kidney": "cotton",
    "bean": "cotton",
    "swollen": "mercerizedCotton",
    "elliptical": "wool",
}

#: ``progress(done, total, info)``: called once with ``info["event"] == "start"`` (``done``
#: = directions found in the resume directory), then after every finished direction
#: (``"direction"``, with theta_i/phi_i in degrees, photons, rel_error, seconds, resumed).
ProgressFn = Callable[[int, int, dict], None]


class BakeError(ValueError):
    """A bake that cannot be done as asked (the message is one line)."""


# ---------------------------------------------------------------------------------------------
# Settings
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class BakeSettings:
    """How a table is baked. Every field changes the result (and so the cache key).

    ``resolution_deg``: bin size (divides 90; the paper uses 2). ``photons``: photons per
    incoming direction, or the first amount when ``target_error`` is set (a relative L2
    error of p; batches are then added up to ``max_photons`` per direction). ``batches``:
    independent batches per direction for the error estimate (>= 2). ``levels``: absorption
    levels as optical depths across the diameter (sigma_a * D), starting at 0.
    ``band_tail``: mass per direction that may be dropped at the theta_o extremes.
    ``storage``: "float16" or "float32" for the per-bin arrays. ``incoming``: "centre"
    traces each incoming direction at its bin centre (the paper's sampling, for
    interpolation between nodes); "box" spreads the batches over the incoming bin
    (stratified, uniform in solid angle, weighted by ``W(phi) cos(theta)``), so that each
    entry averages over both bins and the table is reciprocal bin for bin.
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

    def __post_init__(self) -> None:
        Grid(self.resolution_deg, True, False)  # validates the resolution
        if int(self.photons) < 1:
            raise BakeError(f"photons must be >= 1, got {self.photons}")
        if self.target_error is not None and not (0 < float(self.target_error) < 1):
            raise BakeError(f"target error must be in (0, 1), got {self.target_error}")
        if int(self.batches) < 2:
            raise BakeError(f"batches must be >= 2 (the error estimate needs a variance), got {self.batches}")
        if int(self.max_bounces) < 1:
            raise BakeError(f"max_bounces must be >= 1, got {self.max_bounces}")
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

    def result_inputs(self) -> dict[str, Any]:
        """Everything that changes a baked table (for cache keys and headers)."""
        d = asdict(self)
        d["levels"] = list(self.levels)
        if self.target_error is None:
            d.pop("max_photons")  # only used in target-error mode
        d["builtin_profile_vertices"] = BUILTIN_PROFILE_VERTICES
        d["baker_version"] = BAKER_VERSION
        return d


# ---------------------------------------------------------------------------------------------
# Profiles
# ---------------------------------------------------------------------------------------------

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


def _envelope_width(profile: Any, height: float, n: int = WIDTH_SAMPLES) -> np.ndarray:
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


def _profile_fingerprint(profile: Any) -> str:
    h = hashlib.sha256()
    for loop, nrm in zip(profile.loops, profile.normals):
        h.update(np.ascontiguousarray(loop, dtype=np.float64).tobytes())
        h.update(np.ascontiguousarray(nrm, dtype=np.float64).tobytes())
    h.update(b"smooth" if getattr(profile, "smooth", False) else b"flat")
    return h.hexdigest()


def profile_for(params: Any, variant: int) -> Any:
    """The cross section of ``variant`` of a fiber, centred, at circumscribed diameter 1 um."""
    from usdfiber.bake import profiles as P

    fam = params.profile_family
    if fam == "user":
        if not 0 <= variant < len(params.user_profiles):
            raise BakeError(f"{params.prim_path}: no user cross section {variant}")
        up = params.user_profiles[variant]
        try:
            prof = P.profile_from_polygons([np.asarray(l, dtype=np.float64) for l in up.loops],
                                           name=up.path, smooth=up.smooth)
        except P.ProfileError as exc:
            raise BakeError(f"{up.path}: invalid cross section: {exc}") from None
    else:
        kind = FAMILY_KINDS.get(fam)
        if kind is None:
            raise BakeError(f"{params.prim_path}: unknown cross-section family {fam!r}")
        if not 0 <= variant < max(1, params.variant_count):
            raise BakeError(f"{params.prim_path}: variant {variant} out of range")
        prof = P.builtin_profiles(kind, variant + 1, seed=params.seed if fam != "round" else 0,
                                  n=BUILTIN_PROFILE_VERTICES)[variant]
    return prof.centered().scaled_to_diameter(1.0)


# ---------------------------------------------------------------------------------------------
# One incoming direction
# ---------------------------------------------------------------------------------------------

def _batch_seed(seed: int, batch: int) -> int:
    """The tracer seed of batch ``batch``: distinct per (seed, batch), shared by all directions.

    Batches of one direction are independent; the same batch of different directions uses
    the same random stream (common random numbers: errors vary smoothly with omega_i). A
    few distinct seeds also keep the tracer's compiled kernels reusable: every new seed
    value costs a kernel compilation.
    """
    return (int(seed) & 0xFFFFFFFF) * 65536 + int(batch)


def _mirror_phi(a: np.ndarray) -> np.ndarray:
    """Average with the mirror phi_o - phi_i -> -(phi_o - phi_i) (phi_i at half a bin)."""
    n = a.shape[-1]
    idx = (-np.arange(n)) % n
    return 0.5 * (a + a[..., idx])


@dataclass
class _Ctx:
    fs: Any
    grid: Grid
    settings: BakeSettings
    eta: float
    beta_deg: float
    cuticle: tuple[float, float, float] | None
    levels_um: np.ndarray
    width_env: np.ndarray      # W_env at WIDTH_SAMPLES
    env_height: float

    @cached_property
    def _width_nodes(self) -> tuple[np.ndarray, np.ndarray]:
        n = len(self.width_env)
        return 2 * math.pi * np.arange(n + 1) / n, np.append(self.width_env, self.width_env[0])

    def env_width(self, phi: float) -> float:
        """W_env at azimuth ``phi`` (radians): linear between the samples, periodic."""
        wphi, wval = self._width_nodes
        return float(np.interp(phi % (2 * math.pi), wphi, wval))


class _Direction:
    """The histograms of one incoming direction, filled batch by batch."""

    def __init__(self, ctx: _Ctx, ti: int, pi: int) -> None:
        g, st = ctx.grid, ctx.settings
        self.ctx = ctx
        self.theta = float(g.theta_i_nodes()[ti])
        self.phi = float(g.phi_i_nodes()[pi])
        self.nb = g.n_theta_o * g.n_phi_o
        K = len(ctx.levels_um)
        self.H = np.zeros((K, self.nb))
        self.G = np.zeros((K, self.nb))
        self.batch_hist: list[np.ndarray] = []
        self.batch_norm: list[float] = []
        self.batch_weight: list[float] = []
        self.rng = np.random.default_rng([int(st.seed) & 0xFFFFFFFF, ti, pi, 7])
        self.strata = (self.rng.permutation(int(st.batches)), self.rng.permutation(int(st.batches)))
        self.stats = {"n_hit": 0, "n_cut": 0, "launched": 0, "leaks": 0, "misses": 0.0}
        self.seconds = 0.0
        self.queue = list(range(int(st.batches)))   # batches still to trace
        self.next_batch = int(st.batches)
        self.err = math.inf

    def sub_direction(self, b: int) -> tuple[float, float]:
        """The batch's light direction: the node, or a stratified point of its bin ("box")."""
        g, st = self.ctx.grid, self.ctx.settings
        if st.incoming != "box":
            return self.theta, self.phi
        B = int(st.batches)
        if b < B:
            u, v = (self.strata[0][b] + self.rng.random()) / B, (self.strata[1][b] + self.rng.random()) / B
        else:
            u, v = self.rng.random(), self.rng.random()
        lo, hi = math.sin(self.theta - 0.5 * g.step), math.sin(self.theta + 0.5 * g.step)
        th = math.asin(min(1.0, max(-1.0, lo + u * (hi - lo))))   # uniform in solid angle
        ph = self.phi if g.phi_invariant else self.phi + (v - 0.5) * g.step
        return th, ph

    def add(self, r: Any, th_b: float, ph_b: float) -> None:
        """Bin one traced batch at every absorption level."""
        ctx = self.ctx
        g, nb, K = ctx.grid, self.nb, len(ctx.levels_um)
        idx = g.bin_index(r.directions)
        L = r.path_length.astype(np.float64)
        alive = ~np.asarray(r.cut, dtype=bool)
        h = np.zeros((K, nb))
        gl = np.zeros((K, nb))
        for k, s in enumerate(ctx.levels_um):
            w = np.exp(-s * L) if s > 0 else np.ones_like(L)
            w = np.where(alive, w, 0.0)
            h[k] = np.bincount(idx, weights=w, minlength=nb)
            gl[k] = np.bincount(idx, weights=w * L, minlength=nb)
        if ctx.cuticle is None:
            norm = float(r.n_hit)
        else:
            # Photons crossing the envelope's shadow without touching a scale go straight on.
            w_env = ctx.env_width(ph_b)
            norm = r.n_launched * w_env / float(r.launch_width)
            miss = max(0.0, norm - r.n_hit)
            fwd = int(g.bin_index(np.array([[-math.cos(th_b) * math.cos(ph_b), -math.cos(th_b) * math.sin(ph_b),
                                              -math.sin(th_b)]]))[0])
            h[:, fwd] += miss
            self.stats["misses"] += miss
        # Each batch weighs as the power its beam carries: photons that met the fiber for a
        # fixed direction; W(phi) cos(theta) per unit irradiance for the points of a bin.
        box = ctx.settings.incoming == "box"
        weight = norm if not box else ctx.env_width(ph_b) * math.cos(th_b)
        scale = weight / norm if norm > 0 else 0.0
        self.H += scale * h
        self.G += scale * gl
        self.batch_hist.append(h[0])
        self.batch_norm.append(norm)
        self.batch_weight.append(weight)
        self.stats["n_hit"] += int(r.n_hit)
        self.stats["n_cut"] += int(r.n_cut)
        self.stats["launched"] += int(r.n_launched)
        self.stats["leaks"] += int(r.extra.get("leaks", 0)) if isinstance(r.extra, dict) else 0
        self.seconds += float(r.seconds)

    def error(self) -> float:
        """Relative L2 error of p from the spread between batches (see the module docstring)."""
        g = self.ctx.grid
        dom = np.repeat(g.solid_angles(), g.n_phi_o)
        ps = np.stack([h / max(n, 1e-300) for h, n in zip(self.batch_hist, self.batch_norm)]) / dom
        if g.phi_invariant:
            ps = _mirror_phi(ps.reshape(len(ps), g.n_theta_o, g.n_phi_o)).reshape(len(ps), self.nb)
        w = np.asarray(self.batch_weight, dtype=np.float64)
        w = w / w.sum()
        mean = w @ ps
        nB = len(ps)
        # Variance of the weighted mean from the spread between batches.
        var = (w @ (ps - mean) ** 2) * nB / (nB - 1) * float((w ** 2).sum())
        den = float((dom * mean ** 2).sum())
        return float(math.sqrt((dom * var).sum() / den)) if den > 0 else float("inf")

    def plan_more(self, n_b: int) -> None:
        """After the queued batches: queue as many more as the target error needs."""
        st = self.ctx.settings
        self.err = self.error()
        b = self.next_batch
        if st.target_error is None or not (self.err > st.target_error and b * n_b < int(st.max_photons)):
            return
        need = b * n_b * (self.err / float(st.target_error)) ** 2 * 1.05
        extra = int(math.ceil(need / n_b)) - b
        extra = max(1, min(extra, int(st.max_photons) // n_b - b))
        self.queue = list(range(b, b + extra))
        self.next_batch = b + extra

    def result(self) -> dict[str, Any]:
        g = self.ctx.grid
        n_r, n_c = g.n_theta_o, g.n_phi_o
        K = len(self.ctx.levels_um)
        H = self.H.reshape(K, n_r, n_c)
        G = self.G.reshape(K, n_r, n_c)
        if g.phi_invariant:
            H, G = _mirror_phi(H), _mirror_phi(G)
        nz = np.flatnonzero(H[0].sum(axis=-1) > 0)
        r0, r1 = (int(nz[0]), int(nz[-1]) + 1) if nz.size else (0, 1)
        return {
            "rows": (r0, r1),
            "H": H[:, r0:r1].astype(np.float32),
            "G": G[:, r0:r1].astype(np.float32),
            "norm": float(sum(self.batch_weight)),
            "photons": int(self.stats["launched"]),
            "n_hit": self.stats["n_hit"],
            "n_cut": self.stats["n_cut"],
            "leaks": self.stats["leaks"],
            "misses": self.stats["misses"],
            "rel_error": self.err,
            "seconds": self.seconds,
            "theta_i": self.theta,
            "phi_i": self.phi,
        }


#: Photons per shared tracer launch when directions are traced together (the tracer's batch).
GROUP_PHOTONS = 1 << 21
#: At most this many directions are traced (and held in memory) together.
GROUP_DIRECTIONS = 64


def _photons_per_batch(st: BakeSettings) -> int:
    return max(1, int(math.ceil(int(st.photons) / int(st.batches))))


def _trace_directions(ctx: _Ctx, dirs: list[tuple[int, int]]) -> list[dict[str, Any]]:
    """Trace incoming directions together: batch ``b`` of every direction in one launch.

    Each direction gets exactly the photons it would get alone (batch ``b`` is the tracer
    stream ``_batch_seed(seed, b)`` for every direction), so a table does not depend on how
    its directions were grouped; grouping only shares the tracer's fixed cost per launch.
    """
    from usdfiber.bake import tracer

    st = ctx.settings
    n_b = _photons_per_batch(st)
    accs = [_Direction(ctx, ti, pi) for ti, pi in dirs]
    while True:
        todo = [a for a in accs if a.queue]
        if not todo:
            break
        batch = [(a, a.queue.pop(0)) for a in todo]
        subs = [a.sub_direction(b) for a, b in batch]
        res = tracer.trace_many(ctx.fs, subs, n_b, eta=ctx.eta, beta_deg=ctx.beta_deg,
                                max_bounces=int(st.max_bounces), seed=[_batch_seed(st.seed, b) for _, b in batch],
                                cuticle=ctx.cuticle, batch=GROUP_PHOTONS)
        for (a, _), (th_b, ph_b), r in zip(batch, subs, res):
            a.add(r, th_b, ph_b)
            if not a.queue:
                a.plan_more(n_b)
    return [a.result() for a in accs]


def _trace_direction(ctx: _Ctx, ti: int, pi: int) -> dict[str, Any]:
    """One incoming direction on its own (see :func:`_trace_directions`)."""
    return _trace_directions(ctx, [(ti, pi)])[0]


# ---------------------------------------------------------------------------------------------
# Chunks (resume)
# ---------------------------------------------------------------------------------------------

def _chunk_name(ti: int, pi: int) -> str:
    return f"d{ti:04d}_{pi:04d}.npz"


def _save_chunk(directory: Path, ti: int, pi: int, data: Mapping[str, Any]) -> None:
    arrays = {
        "rows": np.asarray(data["rows"], dtype=np.int64),
        "H": data["H"], "G": data["G"],
        "scalars": np.array([data["norm"], data["photons"], data["n_hit"], data["n_cut"], data["leaks"],
                             data["misses"], data["rel_error"], data["seconds"]], dtype=np.float64),
    }
    save_npz_atomic(directory / _chunk_name(ti, pi), arrays)


def _load_chunk(path: Path) -> dict[str, Any] | None:
    try:
        with np.load(path, allow_pickle=False) as z:
            sc = z["scalars"]
            rows = tuple(int(x) for x in z["rows"])
            data = {"rows": rows, "H": z["H"], "G": z["G"], "norm": float(sc[0]), "photons": int(sc[1]),
                    "n_hit": int(sc[2]), "n_cut": int(sc[3]), "leaks": int(sc[4]), "misses": float(sc[5]),
                    "rel_error": float(sc[6]), "seconds": float(sc[7])}
        if data["H"].shape[1] != rows[1] - rows[0]:
            raise ValueError("rows and H disagree")
        return data
    except Exception as exc:  # noqa: BLE001 - a damaged chunk is re-traced
        warnings.warn(f"{path}: unreadable partial bake chunk ({exc}); tracing that direction again",
                      RuntimeWarning, stacklevel=3)
        return None


def _prepare_resume_dir(resume_dir: Path, fingerprint: dict[str, Any]) -> None:
    resume_dir.mkdir(parents=True, exist_ok=True)
    meta = resume_dir / "bake.json"
    text = json.dumps(fingerprint, sort_keys=True)
    if meta.exists():
        try:
            old = meta.read_text()
        except OSError:
            old = ""
        if old == text:
            return
        # Another bake's chunks: they cannot be reused.
        for f in resume_dir.glob("d*_*.npz"):
            f.unlink(missing_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".bake.", suffix=".tmp", dir=resume_dir)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.replace(tmp, meta)


# ---------------------------------------------------------------------------------------------
# bake_table
# ---------------------------------------------------------------------------------------------

def _context(profile: Any, eta: float, beta_deg: float, cut: tuple[float, float, float] | None,
             st: BakeSettings) -> _Ctx:
    """The traced scene, grid and absorption levels of one table (inputs already checked)."""
    from usdfiber.bake import tracer

    diameter = float(profile.circumscribed_diameter)
    grid = Grid(st.resolution_deg, theta_symmetric=cut is None,
                phi_invariant=is_rotationally_symmetric(profile))
    levels_um = np.asarray(st.levels, dtype=np.float64) / diameter
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # mesh remarks on cuticle shapes
        fs = tracer.prepare(profile, cut)
    width_env = _envelope_width(profile, cut[1] if cut else 0.0)
    return _Ctx(fs, grid, st, float(eta), float(beta_deg), cut, levels_um, width_env, cut[1] if cut else 0.0)


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
    ctx = _context(profile, eta, beta_deg, cut, st)
    grid, levels_um, width_env = ctx.grid, ctx.levels_um, ctx.width_env

    n_ti, n_pi = grid.n_theta_i, grid.n_phi_i
    total = n_ti * n_pi
    chunks: dict[tuple[int, int], dict[str, Any]] = {}
    rdir = Path(resume_dir) if resume_dir is not None else None
    scratch = None
    if rdir is None and total > 2000:
        # Large tables keep their directions on disk rather than in memory.
        scratch = tempfile.TemporaryDirectory(prefix="usdfiber-bake-")
        rdir = Path(scratch.name)
    try:
        return _bake_directions(profile, eta, beta_deg, cut, st, grid, ctx, levels_um, width_env, rdir, chunks,
                                progress, header)
    finally:
        if scratch is not None:
            scratch.cleanup()


def _bake_directions(profile, eta, beta_deg, cut, st, grid, ctx, levels_um, width_env, rdir, chunks,
                     progress, header) -> BcsdfTable:
    n_ti, n_pi = grid.n_theta_i, grid.n_phi_i
    total = n_ti * n_pi
    diameter = float(profile.circumscribed_diameter)
    done_from_disk: set[tuple[int, int]] = set()
    if rdir is not None:
        fingerprint = {"profile": _profile_fingerprint(profile), "eta": float(eta), "beta_deg": float(beta_deg),
                       "cuticle": list(cut) if cut else None, "grid": grid.to_header(),
                       "settings": st.result_inputs()}
        _prepare_resume_dir(rdir, fingerprint)
        for ti in range(n_ti):
            for pi in range(n_pi):
                # Existence is enough here: a damaged chunk is traced again when it is read.
                if (rdir / _chunk_name(ti, pi)).exists():
                    done_from_disk.add((ti, pi))
    t_start = time.perf_counter()
    if progress is not None:
        progress(len(done_from_disk), total, {"event": "start", "resumed": len(done_from_disk), "total": total})
    done = len(done_from_disk)
    todo = [(ti, pi) for ti in range(n_ti) for pi in range(n_pi) if (ti, pi) not in done_from_disk]
    # Directions are traced in groups that share tracer launches (about GROUP_PHOTONS photons
    # per batch); each finished group is saved before the next starts.
    group = max(1, min(GROUP_DIRECTIONS, GROUP_PHOTONS // _photons_per_batch(st)))
    for g0 in range(0, len(todo), group):
        dirs = todo[g0:g0 + group]
        for (ti, pi), data in zip(dirs, _trace_directions(ctx, dirs)):
            if rdir is not None:
                _save_chunk(rdir, ti, pi, data)
            else:
                chunks[(ti, pi)] = data
            done += 1
            if progress is not None:
                progress(done, total, {"event": "direction", "theta_i_deg": math.degrees(data["theta_i"]),
                                       "phi_i_deg": math.degrees(data["phi_i"]), "photons": data["photons"],
                                       "rel_error": data["rel_error"], "seconds": data["seconds"],
                                       "resumed": False})

    stats = {"photons": 0, "n_hit": 0, "n_cut": 0, "leaks": 0, "seconds": 0.0}
    counted: set[tuple[int, int]] = set()

    def load_slice(ti: int, pi: int) -> Mapping[str, Any]:
        if rdir is None:
            d = chunks[(ti, pi)]
        else:
            d = _load_chunk(rdir / _chunk_name(ti, pi))
            if d is None:  # damaged: trace it again
                d = _trace_direction(ctx, ti, pi)
                _save_chunk(rdir, ti, pi, d)
        if (ti, pi) not in counted:
            counted.add((ti, pi))
            for k in ("photons", "n_hit", "n_cut", "leaks", "seconds"):
                stats[k] += d[k]
        return d

    hdr: dict[str, Any] = {
        "geometry_key": "",
        "inputs": {},
        "variant": 0,
    }
    hdr.update(dict(header or {}))
    hdr.update({
        "baked_diameter_um": diameter,
        "incoming": st.incoming,
        "eta": float(eta),
        "beta_deg": float(beta_deg),
        "cuticle": None if cut is None else {"tilt_deg": cut[0], "height_um": cut[1], "spacing_um": cut[2]},
        "profile": {"name": str(getattr(profile, "name", "")), "loops": len(profile.loops),
                    "edges": int(sum(len(l) for l in profile.loops)), "smooth": bool(getattr(profile, "smooth", False)),
                    "area_um2": float(profile.area), "fingerprint": _profile_fingerprint(profile)},
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
    table = assemble(grid, levels_um, (n_ti, n_pi), load_slice, width_env, hdr,
                     band_tail=st.band_tail, storage=st.storage)
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
    table.header["leaks"] = int(stats["leaks"])
    return table


# ---------------------------------------------------------------------------------------------
# Requests: what a stage (or a preset, or a parameter file) needs
# ---------------------------------------------------------------------------------------------

@dataclass
class TableRequest:
    """One table to bake: cross-section ``variant`` of a fiber with these parameters.

    ``prims`` lists the prims (or sources) that use it. The traced profile is at
    circumscribed diameter 1 um; cuticle height and spacing are relative to the diameter.
    """

    params: Any
    variant: int
    prims: list[str] = field(default_factory=list)

    @property
    def geometry_key(self) -> str:
        return self.params.geometry_key()

    @property
    def inputs(self) -> dict[str, Any]:
        return self.params.geometry_inputs()

    # The traced values are the canonical (rounded) geometry inputs, so that equal keys
    # always mean equal traces.
    @property
    def eta(self) -> float:
        return float(self.inputs["eta"])

    @property
    def beta_deg(self) -> float:
        return float(self.inputs["beta"])

    @property
    def cuticle(self) -> tuple[float, float, float] | None:
        c = self.inputs.get("cuticle")
        if not c:
            return None
        return (float(c["tilt"]), float(c["height_rel"]), float(c["spacing_rel"]))

    def profile(self) -> Any:
        return profile_for(self.params, self.variant)

    @property
    def label(self) -> str:
        return f"{self.params.kind}/{self.params.profile_family} variant {self.variant}"

    def header(self) -> dict[str, Any]:
        """Header entries identifying the table (and the first fiber that asked for it)."""
        p = self.params
        return {
            "geometry_key": self.geometry_key,
            "inputs": self.inputs,
            "variant": int(self.variant),
            "variant_count": int(p.variant_count),
            "kind": p.kind,
            "profile_family": p.profile_family,
            "fiber": {"prim": self.prims[0] if self.prims else p.prim_path, "diameter_um": p.diameter, "density_g_cm3": p.density,
                      "mu_a_per_um": list(p.mu_a), "extinction": list(p.extinction),
                      "depth_of_shade": p.depth_of_shade, "dye_class": p.dye_class},
            "prims": list(self.prims[:16]),
        }


def _collect(params_list: Iterable[tuple[Any, str]]) -> list[TableRequest]:
    seen: dict[tuple[str, int], TableRequest] = {}
    for params, source in params_list:
        gk = params.geometry_key()
        for v in range(max(1, int(params.variant_count))):
            req = seen.get((gk, v))
            if req is None:
                req = seen[(gk, v)] = TableRequest(params, v, [])
            if source not in req.prims:
                req.prims.append(source)
    return list(seen.values())


def requests_for_params(params: Any, source: str | None = None) -> list[TableRequest]:
    """The tables of one fiber (one per cross-section variant)."""
    return _collect([(params, source or params.prim_path)])


def _explicit_table_ok(prim: Any, params: Any) -> bool:
    """Whether ``fiber:table`` names a readable table baked for these parameters."""
    path = resolve_table_asset(prim)
    if not path:
        return False
    from usdfiber.table_format import TableError, read_header

    try:
        hdr = read_header(path)
    except TableError as exc:
        warnings.warn(f"{prim.GetPath()}: fiber:table {exc}; baking from the fiber's parameters",
                      RuntimeWarning, stacklevel=3)
        return False
    if hdr.get("geometry_key") != params.geometry_key():
        warnings.warn(f"{prim.GetPath()}: fiber:table {path} was baked for other parameters; "
                      f"baking from the fiber's parameters", RuntimeWarning, stacklevel=3)
        return False
    return True


def resolve_table_asset(prim: Any) -> str | None:
    """The file named by a prim's ``fiber:table`` (resolved), or None when empty."""
    from pxr import Sdf

    attr = prim.GetAttribute("fiber:table")
    if not attr:
        return None
    v = attr.Get()
    if v is None:
        return None
    raw = v.path if isinstance(v, Sdf.AssetPath) else str(v)
    if not raw:
        return None
    resolved = v.resolvedPath if isinstance(v, Sdf.AssetPath) else ""
    if resolved:
        return resolved
    if os.path.isabs(raw):
        return raw
    stack = attr.GetPropertyStack()
    layer = stack[0].layer if stack else prim.GetStage().GetRootLayer()
    base = layer.realPath or ""
    return os.path.normpath(os.path.join(os.path.dirname(base), raw)) if base else raw


def fiber_prims(stage: Any) -> list[Any]:
    """Concrete prims with FiberAPI (instance proxies included; class prims are not rendered)."""
    from pxr import Usd

    out = []
    for prim in Usd.PrimRange.Stage(stage, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)):
        if prim.HasAPI("FiberAPI"):
            out.append(prim)
    return out


def tables_for_stage(stage: Any, time: Any = None, *, include_explicit: bool = False) -> list[TableRequest]:
    """EXACTLY the distinct tables a stage needs: one per (geometry key, variant).

    Every concrete prim with FiberAPI (fiber curves and yarn curves alike: a yarn's fibers
    take its FiberAPI values) contributes its variants; prims sharing a definition (a class,
    a reference, equal values) share requests. Abstract class prims are not rendered and
    need nothing themselves. A prim whose ``fiber:table`` names a valid table for its
    parameters needs no bake (unless ``include_explicit``); a missing, damaged or stale one
    is warned about and its tables are requested. Raises BakeError naming the prim when
    its values cannot be resolved.
    """
    from pxr import Usd

    from usdfiber.fiber_params import FiberParams, FiberParamsError

    t = Usd.TimeCode.Default() if time is None else time
    items = []
    for prim in fiber_prims(stage):
        try:
            params = FiberParams.from_prim(prim, t)
        except FiberParamsError as exc:
            raise BakeError(str(exc)) from None
        if params.table and not include_explicit and _explicit_table_ok(prim, params):
            continue
        items.append((params, str(prim.GetPath())))
    return _collect(items)


# ---------------------------------------------------------------------------------------------
# Presets and parameter files
# ---------------------------------------------------------------------------------------------

def params_from_mapping(values: Mapping[str, Any], name: str = "params") -> Any:
    """FiberParams from a mapping (the JSON parameter file format).

    Keys: ``"preset"`` (optional fiber preset to start from, see ``usdfiber presets``); any
    FiberAPI value by its Python name (``usdfiber.authoring.FIBER_NAMES``, e.g.
    ``"diameter"``, ``"beta"``, ``"dye"``) or attribute name (``"fiber:diameter"``); and
    ``"profiles"``: user cross sections, a list of ``{"loops": [[[x, y], ...], ...],
    "smooth": false}`` in um (outer loop first, then holes). Raises BakeError.
    """
    import usdfiber  # noqa: F401 - registers the schema before the stage is made
    from pxr import Usd, UsdGeom

    from usdfiber import authoring
    from usdfiber.fiber_params import FiberParams, FiberParamsError

    if not isinstance(values, Mapping):
        raise BakeError(f"{name}: expected a JSON object of fiber values")
    values = dict(values)
    preset = values.pop("preset", None)
    profiles = values.pop("profiles", None)
    by_attr = {v: k for k, v in authoring.FIBER_NAMES.items()}
    kw: dict[str, Any] = {}
    for k, v in values.items():
        key = by_attr.get(k, k)
        if key not in authoring.FIBER_NAMES and key not in authoring.FIBER_SPECIAL:
            valid = sorted(authoring.FIBER_NAMES) + list(authoring.FIBER_SPECIAL) + ["preset", "profiles"]
            raise BakeError(f"{name}: unknown fiber value {k!r}; valid: {', '.join(valid)}")
        kw[key] = v
    stage = Usd.Stage.CreateInMemory()
    prim = UsdGeom.BasisCurves.Define(stage, "/Fiber").GetPrim()
    try:
        if profiles is not None:
            if not isinstance(profiles, list) or not profiles:
                raise BakeError(f"{name}: 'profiles' must be a non-empty list of cross sections")
            paths = []
            for i, pr in enumerate(profiles):
                if not isinstance(pr, Mapping) or "loops" not in pr:
                    raise BakeError(f"{name}: profiles[{i}] must be an object with 'loops'")
                path = f"/Profiles/P{i}"
                authoring.define_profile(stage, path, pr["loops"], smooth=bool(pr.get("smooth", False)))
                paths.append(path)
            kw["profile_sources"] = paths
        authoring.apply_fiber(prim, preset, **kw)
        return FiberParams.from_prim(prim)
    except (authoring.AuthoringError, FiberParamsError) as exc:
        msg = str(exc).replace("/Fiber", name, 1)
        raise BakeError(msg) from None
    except (TypeError, ValueError) as exc:
        raise BakeError(f"{name}: {exc}") from None


def params_from_preset(name: str) -> Any:
    """FiberParams of a fiber preset (``usdfiber presets``)."""
    from usdfiber import presets

    if name not in presets.FIBER_PRESETS:
        raise BakeError(f"unknown fiber preset {name!r}; valid: {', '.join(presets.FIBER_PRESETS)}")
    return params_from_mapping({"preset": name}, name=f"preset {name}")


def requests_from_preset(name: str) -> list[TableRequest]:
    """The tables of a fiber preset."""
    return requests_for_params(params_from_preset(name), source=f"preset:{name}")


def requests_from_params(path: str | os.PathLike[str]) -> list[TableRequest]:
    """The tables of the fiber described by a JSON parameter file (see params_from_mapping)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise BakeError(f"{p}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise BakeError(f"{p}: cannot read: {exc}") from None
    try:
        values = json.loads(text)
    except json.JSONDecodeError as exc:
        raise BakeError(f"{p}: not JSON: {exc.msg} (line {exc.lineno}, column {exc.colno})") from None
    return requests_for_params(params_from_mapping(values, name=str(p)), source=str(p))


def bake_request(request: TableRequest, settings: BakeSettings | None = None,
                 progress: ProgressFn | None = None,
                 resume_dir: str | os.PathLike[str] | None = None) -> BcsdfTable:
    """Bake the table of a request (no cache; see :mod:`usdfiber.bake.cache`)."""
    return bake_table(request.profile(), request.eta, request.beta_deg, request.cuticle,
                      settings, progress, resume_dir, header=request.header())


def replace_settings(settings: BakeSettings, **changes: Any) -> BakeSettings:
    """``dataclasses.replace`` for settings, with BakeError on bad values."""
    return replace(settings, **changes)


