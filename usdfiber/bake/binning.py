"""Binning photon exits into the (theta_o, phi_o) grid with exact per-photon weights.

Grid: theta_o in [-90, 90] deg (``n_theta`` bins, default 90), phi_o in [0, 360) deg (``n_phi``
bins, default 180), phi from +x towards +y in the fiber frame, sin(theta) = w.z.
Densities are per steradian and per photon that hit the fiber: a bin's value is the summed
weight of its photons divided by (n_hit x its exact solid angle (sin th1 - sin th0) dphi), so
``sum(density * solid_angle)`` is the albedo Lambda(omega_i) and density / albedo is
p(omega_o | omega_i).

Each photon is weighted by exp(-sigma_a L) with its own path length L in the material: this is
the direct answer that the baked tables' recolouring (:mod:`usdfiber.bake.table`, which keeps
a few absorption levels per bin and interpolates between them) is checked against.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ExitGrid", "bin_direct"]


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


def _valid(result) -> tuple[np.ndarray, np.ndarray]:
    keep = ~np.asarray(result.cut, dtype=bool)
    return np.asarray(result.directions)[keep], np.asarray(result.path_length, dtype=np.float64)[keep]


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
