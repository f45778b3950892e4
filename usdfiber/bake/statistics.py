"""Per-direction statistics of a bake: histograms at every absorption level and the error.

Photons of one incoming direction are traced in ``batches`` independent batches (distinct
random streams; batch ``b`` of every direction uses the same stream, so errors vary smoothly
with omega_i). Their exit directions are histogrammed into the theta_o x phi_o bins,
weighted by ``exp(-s_k L)`` at each absorption level (``L``: path length in the material).
The variance between batches gives the direction's error estimate: the relative L2 error of
``p`` over the sphere, ``sqrt(sum_b dOmega_b Var[p_b]) / sqrt(sum_b dOmega_b p_b^2)`` with
``Var`` the variance of the batch mean (at ``sigma_a = 0``). In ``target_error`` mode
batches are added until the estimate reaches the target (or ``max_photons``); the error of a
Monte Carlo histogram falls as ``N^-1/2``, which sets how many more are needed.

Normalization: an extruded fiber intercepts exactly the photons launched over its shadow
``W(phi_i)``: a batch is divided by the photons that met the fiber. A fiber with cuticle
scales has an uneven surface: ``W`` is the width of the shadow of the scales' outer envelope
and a photon crossing that envelope's shadow without touching a scale goes straight on,
which in the far field is scattering into ``omega_o = -omega_i`` (it is counted there).
A box-filtered bin (``incoming="box"``) of an extruded fiber draws every photon's light
direction in the bin in proportion to the power the fiber intercepts (the tracer's
``spread``): a batch is then divided by its photons that met the fiber and weighted by the
bin's power per unit irradiance and solid angle, ``(1/|I|) integral over I of W cos``
(:func:`usdfiber.bake.sampling.box_power`). With cuticle scales a batch is one stratified
point of the bin instead, weighted by ``W(phi) cos(theta)`` there: also unbiased, but the
variation of p over the bin then counts in the spread between batches.
Rotationally symmetric tables are mirror-averaged, ``p(phi_o - phi_i) = p(phi_i - phi_o)``
(:func:`mirror_phi`), which halves the variance.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from usdfiber.bake.binning import level_sums
from usdfiber.bake.grid import Grid
from usdfiber.bake.sampling import box_power
from usdfiber.bake.settings import BakeSettings

__all__ = ["BakeContext", "DirectionStatistics", "level_histograms", "mirror_phi"]


def mirror_phi(a: np.ndarray) -> np.ndarray:
    """Average with the mirror phi_o - phi_i -> -(phi_o - phi_i) (phi_i at half a bin)."""
    n = a.shape[-1]
    idx = (-np.arange(n)) % n
    return 0.5 * (a + a[..., idx])


def level_histograms(r: Any, grid: Grid, levels_um: Any) -> tuple[np.ndarray, np.ndarray]:
    """Summed exit weight and weight x L per outgoing bin of ``grid`` at every absorption level
    (``exp(-s_k L)``; rows and the tracer's expected-value histogram): two (levels, bins) arrays."""
    # Exit weights at zero absorption (cut photons carry none; fractional with splitting,
    # where one photon leaves several exits: its batch still is one independent sample).
    h, gl = level_sums(r.directions, r.path_length, getattr(r, "weight", None), r.cut, grid, levels_um)
    if getattr(r, "histogram", None) is not None:
        # Exits deposited as expectations, already binned in the tracer at these levels.
        hb = r.histogram_bins
        if hb.n_bins != h.shape[1] or not np.allclose(hb.levels, levels_um, rtol=1e-6, atol=0.0):
            raise ValueError("the tracer's expected-value histogram has other bins or levels than the table")
        h += r.histogram[:, 0]
        gl += r.histogram[:, 1]
    return h, gl


@dataclass
class BakeContext:
    """What every incoming direction of one table shares: the traced scene (``fs``, from
    :func:`usdfiber.bake.tracer.prepare`), the grid, the settings, the traced optics, the
    absorption levels in 1/um of the baked size and the envelope width ``W_env(phi)``."""

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


class DirectionStatistics:
    """The histograms of one incoming direction, filled batch by batch, and its error."""

    def __init__(self, ctx: BakeContext, ti: int, pi: int) -> None:
        g, st = ctx.grid, ctx.settings
        self.ctx = ctx
        self.theta = float(g.theta_i_nodes()[ti])
        self.phi = float(g.phi_i_nodes()[pi])
        self.nb = g.n_theta_o * g.n_phi_o
        K = len(ctx.levels_um)
        self.H = np.zeros((K, self.nb))
        self.G = np.zeros((K, self.nb))
        # The batches' p at sigma_a = 0 as running weighted moments (West's update), not kept
        # one by one: a direction may run to thousands of batches (target-error mode), and a
        # group of directions would hold them all.
        self.n_batches = 0
        self.weight_sum = 0.0         # sum of the batches' weights (the table's ``norm``)
        self.weight_sq_sum = 0.0
        self.p_mean = np.zeros(self.nb)
        self.p_m2 = np.zeros(self.nb)
        self._dom = np.repeat(g.solid_angles(), g.n_phi_o)
        self.rng = np.random.default_rng([int(st.seed) & 0xFFFFFFFF, ti, pi, 7])
        self.strata = (self.rng.permutation(int(st.batches)), self.rng.permutation(int(st.batches)))
        self.stats = {"n_hit": 0, "n_cut": 0, "launched": 0, "leaks": 0, "misses": 0.0}
        self.seconds = 0.0
        self.next_batch = st.row_batches(ti)
        self.queue = list(range(self.next_batch))   # batches still to trace
        self.err = math.inf

    @cached_property
    def spread(self) -> tuple[float, float, float, float] | None:
        """The bin (theta_lo, theta_hi, phi_lo, phi_hi) every photon draws its light direction
        from, for a box-filtered bin of an extruded fiber; otherwise None."""
        g, ctx = self.ctx.grid, self.ctx
        if ctx.settings.incoming != "box" or ctx.cuticle is not None:
            return None
        h = 0.5 * g.step
        lo, hi = max(self.theta - h, -0.5 * math.pi), min(self.theta + h, 0.5 * math.pi)
        if g.phi_invariant:
            return lo, hi, self.phi, self.phi
        return lo, hi, self.phi - h, self.phi + h

    @cached_property
    def box_weight(self) -> float:
        """Power per unit irradiance and solid angle of the bin of :attr:`spread`."""
        lo, hi, p0, p1 = self.spread
        phis = np.linspace(p0, p1, 33) if p1 > p0 else np.array([p0])
        # W exactly (the profile's shadow at each azimuth), not the table's samples of it.
        return box_power(lo, hi, self.ctx.fs.profile.projected_width(phis))

    def sub_direction(self, b: int) -> tuple[float, float]:
        """The batch's light direction: the node, or a stratified point of its bin ("box"
        with cuticle scales; without them each photon draws its own, :attr:`spread`)."""
        g, st = self.ctx.grid, self.ctx.settings
        if st.incoming != "box" or self.spread is not None:
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
        g = ctx.grid
        h, gl = level_histograms(r, g, ctx.levels_um)
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
        # fixed direction; W(phi) cos(theta) per unit irradiance for the points of a bin, in
        # proportion to its photons (a schedule's batches share a row's photons: they need
        # not all be photons_per_batch; a full batch weighs exactly as before).
        box = ctx.settings.incoming == "box"
        if not box:
            weight = norm
        else:
            share = r.n_launched / ctx.settings.photons_per_batch
            if self.spread is not None:
                weight = self.box_weight * share
            else:
                weight = ctx.env_width(ph_b) * math.cos(th_b) * share
        scale = weight / norm if norm > 0 else 0.0
        self._add_moments(h[0] / max(norm, 1e-300), weight)
        # Scaled in place (h and gl are this batch's own): no megabyte temporaries per batch.
        self.H += np.multiply(h, scale, out=h)
        self.G += np.multiply(gl, scale, out=gl)
        self.stats["n_hit"] += int(r.n_hit)
        self.stats["n_cut"] += int(r.n_cut)
        self.stats["launched"] += int(r.n_launched)
        self.stats["leaks"] += int(r.extra.get("leaks", 0)) if isinstance(r.extra, dict) else 0
        self.seconds += float(r.seconds)

    def _add_moments(self, h0: np.ndarray, weight: float) -> None:
        """One batch's p (``h0``: its level-0 histogram divided by its photons that met) into
        the running weighted mean and sum of squared deviations (West 1979)."""
        g = self.ctx.grid
        p = h0 / self._dom
        if g.phi_invariant:
            p = mirror_phi(p.reshape(g.n_theta_o, g.n_phi_o)).reshape(self.nb)
        self.n_batches += 1
        self.weight_sq_sum += weight * weight
        total = self.weight_sum + weight
        if total > 0:
            delta = p - self.p_mean
            self.p_mean += (weight / total) * delta
            self.p_m2 += weight * delta * (p - self.p_mean)
        self.weight_sum = total

    def error(self) -> float:
        """Relative L2 error of p from the spread between batches (see the module docstring)."""
        nB, W = self.n_batches, self.weight_sum
        if nB < 2 or not W > 0:
            return float("inf")
        # Variance of the weighted mean from the spread between batches: the weighted variance
        # of one batch, nB / (nB - 1) unbiased, times sum(w^2) for the normalized weights w.
        var = (self.p_m2 / W) * nB / (nB - 1) * (self.weight_sq_sum / (W * W))
        den = float((self._dom * self.p_mean ** 2).sum())
        # (West's update keeps the squared deviations >= 0 up to rounding: clamp that.)
        return float(math.sqrt(max(0.0, float((self._dom * var).sum())) / den)) if den > 0 else float("inf")

    def plan_more(self, n_b: int) -> None:
        """After the queued batches: queue as many more as the target error needs."""
        st = self.ctx.settings
        self.err = self.error()
        b = self.next_batch
        if st.target_error is None or not (self.err > st.target_error and b * n_b < int(st.max_photons)):
            return
        if not math.isfinite(self.err):
            return      # no light met the fiber or left it: more of the same photons cannot help
        need = b * n_b * (self.err / float(st.target_error)) ** 2 * 1.05
        extra = int(math.ceil(need / n_b)) - b
        extra = max(1, min(extra, int(st.max_photons) // n_b - b))
        self.queue = list(range(b, b + extra))
        self.next_batch = b + extra

    def result(self) -> dict[str, Any]:
        """The direction's histograms (theta_o rows with light only) and statistics: the
        mapping :func:`usdfiber.bake.assembly.assemble` reads and a chunk stores."""
        g = self.ctx.grid
        n_r, n_c = g.n_theta_o, g.n_phi_o
        K = len(self.ctx.levels_um)
        H = self.H.reshape(K, n_r, n_c)
        G = self.G.reshape(K, n_r, n_c)
        if g.phi_invariant:
            H, G = mirror_phi(H), mirror_phi(G)
        nz = np.flatnonzero(H[0].sum(axis=-1) > 0)
        r0, r1 = (int(nz[0]), int(nz[-1]) + 1) if nz.size else (0, 1)
        return {
            "rows": (r0, r1),
            "H": H[:, r0:r1].astype(np.float32),
            "G": G[:, r0:r1].astype(np.float32),
            "norm": float(self.weight_sum),
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
