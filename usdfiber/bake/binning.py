"""Binning photon exits into the (theta_o, phi_o) table grid, for a set of absorption levels.

Grid: theta_o in [-90, 90] deg (``n_theta`` bins, default 90), phi_o in [0, 360) deg (``n_phi``
bins, default 180), phi from +x towards +y in the fiber frame, sin(theta) = w.z.
Densities are per steradian and per photon that hit the fiber: a bin's value is the summed
weight of its photons divided by (n_hit x its exact solid angle (sin th1 - sin th0) dphi), so
``sum(density * solid_angle)`` is the albedo Lambda(omega_i) and density / albedo is
p(omega_o | omega_i).

Absorption is applied after tracing. A :class:`LevelTable` keeps, for every bin, the sum of
exp(-s_k L) over its photons for a few absorption levels s_k (1/um; L the path length in the
material), and :func:`recolour` interpolates between the levels to any per-channel sigma_a in
log(value) as a function of s. The chord between two levels is exact for a bin whose photons
all travel the same length; otherwise log E[exp(-sL)] is convex in s and the chord
overestimates, so the default follows the curvature with a clamped cubic spline. Measured
against exact per-photon weights (levels 0 and 12 steps from 1e-4 to 1 per um; 10-18 um
fibers, smooth and rough): L1 error below 5e-4 up to sigma_a = 0.085 /um (the paper's dyes
span 0.005 to 0.085 /um), about 2e-3 at 0.12 /um and 1e-2 at 0.3 to 0.7 /um; the chord alone
is 5 to 20 times worse. Above the last level the table extrapolates (1e-1 at 2 /um): extend
the levels there. The error grows with sigma_a times the fiber's path lengths (thick wool).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ExitGrid", "LevelTable", "bin_direct", "bin_exits", "default_levels", "recolour"]


@dataclass(frozen=True)
class ExitGrid:
    """Regular (theta, phi) grid over the sphere of exit directions."""

    n_theta: int = 90
    n_phi: int = 180

    @property
    def theta_edges(self) -> np.ndarray:
        """Bin edges in theta (radians), from -pi/2 to pi/2."""
        return np.linspace(-0.5 * np.pi, 0.5 * np.pi, self.n_theta + 1)

    @property
    def phi_edges(self) -> np.ndarray:
        """Bin edges in phi (radians), from 0 to 2 pi."""
        return np.linspace(0.0, 2.0 * np.pi, self.n_phi + 1)

    @property
    def theta_centers(self) -> np.ndarray:
        e = self.theta_edges
        return 0.5 * (e[1:] + e[:-1])

    @property
    def phi_centers(self) -> np.ndarray:
        e = self.phi_edges
        return 0.5 * (e[1:] + e[:-1])

    @property
    def solid_angle(self) -> np.ndarray:
        """(n_theta, n_phi) exact solid angle of each bin, (sin th1 - sin th0) * dphi."""
        s = np.sin(self.theta_edges)
        return np.repeat(((s[1:] - s[:-1]) * (2.0 * np.pi / self.n_phi))[:, None], self.n_phi, axis=1)

    def flat_index(self, directions: np.ndarray) -> np.ndarray:
        """Flat bin index (it * n_phi + ip) of unit directions (M, 3)."""
        d = np.asarray(directions, dtype=np.float64)
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        theta = np.arcsin(np.clip(d[:, 2], -1.0, 1.0))
        phi = np.mod(np.arctan2(d[:, 1], d[:, 0]), 2.0 * np.pi)
        it = np.floor((theta + 0.5 * np.pi) * (self.n_theta / np.pi)).astype(np.int64)
        ip = np.floor(phi * (self.n_phi / (2.0 * np.pi))).astype(np.int64)
        np.clip(it, 0, self.n_theta - 1, out=it)
        ip %= self.n_phi
        return it * self.n_phi + ip


def default_levels(n: int = 12, lo: float = 1e-4, hi: float = 1.0) -> np.ndarray:
    """Absorption levels (1/um): 0 followed by ``n`` geometric steps from ``lo`` to ``hi``."""
    return np.concatenate([[0.0], np.geomspace(lo, hi, n)])


@dataclass
class LevelTable:
    """Per-steradian exit densities of one incoming direction at several absorption levels."""

    grid: ExitGrid
    levels: np.ndarray      # (K,) 1/um, increasing, levels[0] == 0 normally
    density: np.ndarray     # (K, n_theta, n_phi) float64
    n_hit: int

    def albedo(self) -> np.ndarray:
        """(K,) albedo at each level: sum(density * solid angle)."""
        return np.einsum("kij,ij->k", self.density, self.grid.solid_angle)


def _valid(result) -> tuple[np.ndarray, np.ndarray]:
    keep = ~np.asarray(result.cut, dtype=bool)
    return np.asarray(result.directions)[keep], np.asarray(result.path_length, dtype=np.float64)[keep]


def bin_exits(result, levels: np.ndarray | None = None, grid: ExitGrid | None = None) -> LevelTable:
    """Accumulate a :class:`~usdfiber.bake.tracer.TraceResult` into a :class:`LevelTable`.

    Cut photons carry no weight. ``levels`` default to :func:`default_levels`.
    """
    grid = grid or ExitGrid()
    levels = default_levels() if levels is None else np.asarray(levels, dtype=np.float64)
    if np.any(np.diff(levels) <= 0.0) or levels[0] < 0.0:
        raise ValueError("absorption levels must be >= 0 and strictly increasing")
    dirs, L = _valid(result)
    idx = grid.flat_index(dirs) if len(dirs) else np.zeros(0, np.int64)
    nb = grid.n_theta * grid.n_phi
    norm = 1.0 / (max(int(result.n_hit), 1) * grid.solid_angle.ravel())
    out = np.empty((len(levels), grid.n_theta, grid.n_phi))
    # Sorting once makes the per-level accumulation a cheap segmented sum.
    order = np.argsort(idx, kind="stable")
    idx_s, L_s = idx[order], L[order]
    starts = np.searchsorted(idx_s, np.arange(nb))
    nonempty = np.diff(np.append(starts, len(idx_s))) > 0
    for k, s in enumerate(levels):
        w = np.exp(-s * L_s) if s > 0.0 else np.ones_like(L_s)
        sums = np.zeros(nb)
        if len(w):
            sums[nonempty] = np.add.reduceat(w, starts[nonempty])
        out[k] = (sums * norm).reshape(grid.n_theta, grid.n_phi)
    return LevelTable(grid=grid, levels=levels, density=out, n_hit=int(result.n_hit))


def bin_direct(result, sigma_a: float | np.ndarray = 0.0, grid: ExitGrid | None = None) -> np.ndarray:
    """Densities with the exact per-photon weight exp(-sigma_a L) (no interpolation).

    Returns (n_theta, n_phi) for a scalar ``sigma_a`` or (n_theta, n_phi, C) for C channels.
    """
    grid = grid or ExitGrid()
    dirs, L = _valid(result)
    idx = grid.flat_index(dirs) if len(dirs) else np.zeros(0, np.int64)
    nb = grid.n_theta * grid.n_phi
    norm = 1.0 / (max(int(result.n_hit), 1) * grid.solid_angle.ravel())
    s = np.atleast_1d(np.asarray(sigma_a, dtype=np.float64))
    out = np.stack([np.bincount(idx, weights=np.exp(-c * L), minlength=nb) * norm for c in s], axis=-1)
    out = out.reshape(grid.n_theta, grid.n_phi, len(s))
    return out[..., 0] if np.ndim(sigma_a) == 0 else out


def recolour(table: LevelTable, sigma_a: float | np.ndarray, method: str = "cubic") -> np.ndarray:
    """Densities for absorption ``sigma_a`` (1/um; scalar or per channel, e.g. RGB).

    Interpolation is in log(density) as a function of s. ``method="linear"``: the chord between
    the two neighbouring levels. ``method="cubic"`` (default): a natural cubic spline through
    all levels, clamped between the chord (an upper bound, log E[exp(-sL)] being convex in s)
    and the next level's value (a lower bound, densities fall as s grows); it follows the
    curvature that the chord misses. Above the last level, log(density) is extrapolated with
    the slope of the last two levels (the decay rate tends to that of the bin's shortest
    paths). A bin that is empty at any level used is interpolated linearly in value.
    Returns (n_theta, n_phi) or (n_theta, n_phi, C).
    """
    if method not in ("linear", "cubic"):
        raise ValueError(f"unknown recolour method {method!r}")
    lv = np.asarray(table.levels, dtype=np.float64)
    dens = table.density
    s = np.atleast_1d(np.asarray(sigma_a, dtype=np.float64))
    if np.any(s < lv[0]):
        raise ValueError(f"sigma_a below the lowest tabulated level {lv[0]}")
    spline = None
    if method == "cubic" and len(lv) >= 3:
        from scipy.interpolate import CubicSpline

        all_pos = np.all(dens > 0.0, axis=0)
        logd = np.log(np.where(all_pos, dens, 1.0))
        spline = CubicSpline(lv, logd, axis=0, bc_type="natural")
    out = np.empty(dens.shape[1:] + (len(s),))
    for c, sc in enumerate(s):
        k = int(np.clip(np.searchsorted(lv, sc, side="right") - 1, 0, len(lv) - 2))
        t = (sc - lv[k]) / (lv[k + 1] - lv[k])
        a, b = dens[k], dens[k + 1]
        pos = (a > 0.0) & (b > 0.0)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            la, lb = np.log(np.where(pos, a, 1.0)), np.log(np.where(pos, b, 1.0))
            if t > 1.0:
                # Extrapolation: never let a bin grow with more absorption.
                slope = np.minimum(lb - la, 0.0)
                val = np.exp(lb + (t - 1.0) * slope)
                lin = np.zeros_like(b)
            else:
                chord = (1.0 - t) * la + t * lb
                if spline is not None:
                    lg = np.clip(spline(sc), np.minimum(lb, chord), chord)
                    lg = np.where(all_pos, lg, chord)
                else:
                    lg = chord
                val = np.exp(lg)
                lin = (1.0 - t) * a + t * b
        out[..., c] = np.where(pos, val, lin)
    return out[..., 0] if np.ndim(sigma_a) == 0 else out
