"""Exact far field of a smooth circular dielectric fiber (the reference for the bake).

For a smooth (R_a -> 0) circular fiber of radius 1, the scattered far field is a 1D integral
over the impact parameter h in [-1, 1] (Marschner et al. 2003; d'Eon et al. 2011):

* Longitudinal: every path exits on the cone theta_o = -theta_i.
* Azimuthal: inside the fiber, a 3D path behaves as a 2D one with the Bravais index
  eta' = sqrt(eta^2 - sin^2 theta) / cos theta. With gamma_i = asin(h), gamma_t = asin(h / eta'),
  path p (0 = R, 1 = TT, 2 = TRT, ...) exits at Phi(p, h) = 2 p gamma_t - 2 gamma_i + p pi.
* Attenuation: A_0 = F, A_p = (1 - F)^2 F^(p-1) T^p with F = Fresnel(cos theta cos gamma_i, eta)
  and T = exp(-sigma_a 2 cos(gamma_t) / cos(theta_t)), sin theta_t = sin theta / eta; sigma_a is
  the absorption coefficient times the radius.

Conventions (shared with ``reference_tracer``): both omega_i (towards the light) and omega_o
(towards the viewer) point AWAY from the fiber; phi is the azimuth around the fiber axis.
Phi(p, h) = phi_o - phi_i: pure backscatter (R at h = 0) exits at phi_o = phi_i, light passing
straight through (TT at h = 0) at phi_o = phi_i + pi. The impact parameter h is the hit point's
coordinate along (sin phi_i, -cos phi_i), i.e. omega_i's in-plane direction turned by -90 deg;
for phi_i = 0 the photon travels along -x at height y = -h. Histograms over h are symmetric,
so this sign only matters when following single paths.
"""
from __future__ import annotations

import numpy as np

__all__ = [
    "attenuation",
    "azimuthal_distribution",
    "bravais_eta",
    "exit_azimuth",
    "exit_theta",
    "fresnel_dielectric",
    "reflection_energy",
    "total_energy",
]

_TINY = 1e-300


def bravais_eta(eta: float | np.ndarray, theta: float | np.ndarray) -> np.ndarray:
    """Bravais' index eta' = sqrt(eta^2 - sin^2 theta) / cos theta of the in-plane problem."""
    eta = np.asarray(eta, dtype=np.float64)
    theta = np.asarray(theta, dtype=np.float64)
    s = np.sin(theta)
    c = np.maximum(np.abs(np.cos(theta)), 1e-300)
    return np.sqrt(np.maximum(eta * eta - s * s, 0.0)) / c


def fresnel_dielectric(cos_i: float | np.ndarray, eta: float | np.ndarray) -> np.ndarray:
    """Unpolarized Fresnel reflectance of a smooth dielectric boundary.

    ``cos_i`` is the cosine of the incidence angle (its sign is ignored), ``eta`` the relative
    index eta_t / eta_i. Total internal reflection gives 1; ``eta == 1`` gives 0.
    """
    cos_i = np.clip(np.abs(np.asarray(cos_i, dtype=np.float64)), 0.0, 1.0)
    eta = np.asarray(eta, dtype=np.float64)
    sin_t2 = (1.0 - cos_i * cos_i) / (eta * eta)
    tir = sin_t2 >= 1.0
    cos_t = np.sqrt(np.maximum(1.0 - sin_t2, 0.0))
    den_s = cos_i + eta * cos_t
    den_p = eta * cos_i + cos_t
    ok = (den_s > _TINY) & (den_p > _TINY)
    # Both denominators vanish only at grazing incidence with eta == 1 (handled below).
    rs = np.where(ok, (cos_i - eta * cos_t) / np.where(ok, den_s, 1.0), 1.0)
    rp = np.where(ok, (eta * cos_i - cos_t) / np.where(ok, den_p, 1.0), 1.0)
    f = 0.5 * (rs * rs + rp * rp)
    f = np.where(tir, 1.0, f)
    return np.where(eta == 1.0, 0.0, np.clip(f, 0.0, 1.0))


def exit_theta(theta_i: float | np.ndarray) -> np.ndarray:
    """Longitudinal exit angle of every path of a smooth fiber: theta_o = -theta_i.

    A smooth extruded boundary has normals perpendicular to the axis, so the axial component
    of the propagation direction is preserved by reflection and, after entering and leaving
    the same medium, by refraction; omega_o = propagation direction while omega_i = -incoming.
    """
    return -np.asarray(theta_i, dtype=np.float64)


def exit_azimuth(p: int, h: np.ndarray, theta_i: float, eta: float) -> np.ndarray:
    """Phi(p, h) = phi_o - phi_i of path ``p`` (not wrapped), see the module conventions."""
    h = np.asarray(h, dtype=np.float64)
    etap = bravais_eta(eta, theta_i)
    gamma_i = np.arcsin(np.clip(h, -1.0, 1.0))
    gamma_t = np.arcsin(np.clip(h / etap, -1.0, 1.0))
    return 2.0 * p * gamma_t - 2.0 * gamma_i + p * np.pi


def _path_terms(h: np.ndarray, theta_i: float, eta: float, sigma_a: float):
    """Fresnel factor F, transmittance T of one internal chord, and gamma angles."""
    etap = bravais_eta(eta, theta_i)
    gamma_i = np.arcsin(np.clip(h, -1.0, 1.0))
    gamma_t = np.arcsin(np.clip(h / etap, -1.0, 1.0))
    f = fresnel_dielectric(np.cos(theta_i) * np.cos(gamma_i), eta)
    sin_t = np.sin(theta_i) / eta
    cos_t = np.sqrt(max(1.0 - sin_t * sin_t, 0.0))
    if sigma_a == 0.0:
        t = np.ones_like(h)
    else:
        # exp(-inf) = 0; the guard keeps 0 * inf out when a chord has zero length.
        length = 2.0 * np.cos(gamma_t) / max(cos_t, _TINY)
        with np.errstate(invalid="ignore", over="ignore"):
            t = np.where(length > 0.0, np.exp(-sigma_a * length), 1.0)
    return f, t, gamma_i, gamma_t


def attenuation(p: int, h: np.ndarray, theta_i: float, eta: float, sigma_a: float = 0.0) -> np.ndarray:
    """A_p(h): fraction of the power entering at offset ``h`` that leaves along path ``p``."""
    h = np.asarray(h, dtype=np.float64)
    f, t, _, _ = _path_terms(h, theta_i, eta, float(sigma_a))
    if p == 0:
        return f
    return (1.0 - f) ** 2 * f ** (p - 1) * t ** p


def _midpoints(n_h: int) -> np.ndarray:
    return -1.0 + (np.arange(n_h, dtype=np.float64) + 0.5) * (2.0 / n_h)


def total_energy(theta_i: float, eta: float, sigma_a: float = 0.0, n_h: int = 1 << 20) -> float:
    """Fraction of the intercepted power that leaves the fiber, summed over all paths.

    Uses the closed form sum_p A_p = F + (1 - F)^2 T / (1 - F T), averaged over h (midpoint
    rule). Exactly 1 at ``sigma_a = 0``; ``sigma_a = inf`` leaves the R lobe only.
    """
    h = _midpoints(n_h)
    f, t, _, _ = _path_terms(h, float(theta_i), float(eta), float(sigma_a))
    den = 1.0 - f * t
    inner = np.where(den > _TINY, (1.0 - f) ** 2 * t / np.where(den > _TINY, den, 1.0), 1.0 - f)
    return float(np.mean(f + inner))


def reflection_energy(theta_i: float, eta: float, n_h: int = 1 << 20) -> float:
    """Energy of the R lobe (p = 0): the mean over h of F(cos theta cos gamma_i)."""
    return float(np.mean(attenuation(0, _midpoints(n_h), float(theta_i), float(eta))))


def azimuthal_distribution(theta_i: float, eta: float, sigma_a: float = 0.0, n_bins: int = 180,
                           p_max: int = 256, n_h: int = 1 << 21, tol: float = 1e-12) -> np.ndarray:
    """Azimuthal distribution of the power leaving a smooth circular fiber.

    Returns ``n_bins`` densities per radian over phi_o - phi_i in [0, 2 pi); bin ``k`` covers
    [k, k + 1) * 2 pi / n_bins. Densities are per unit intercepted power: their integral
    (sum * 2 pi / n_bins) is the energy of paths p <= p_max, which equals
    :func:`total_energy` up to the truncated tail (stopped early once below ``tol``). The
    integral over h uses ``n_h`` midpoints (each carries 1 / n_h of the beam). All the light
    leaves on the cone theta_o = -theta_i (:func:`exit_theta`).
    """
    theta_i, eta, sigma_a = float(theta_i), float(eta), float(sigma_a)
    h = _midpoints(int(n_h))
    f, t, gamma_i, gamma_t = _path_terms(h, theta_i, eta, sigma_a)
    two_pi = 2.0 * np.pi
    bin_width = two_pi / n_bins
    hist = np.zeros(n_bins)
    w = 1.0 / len(h)
    total = total_energy(theta_i, eta, sigma_a, n_h=len(h))
    captured = 0.0
    a_p = f.copy()
    step = 2.0 * gamma_t + np.pi          # Phi(p + 1) - Phi(p)
    phi = -2.0 * gamma_i                  # Phi(0)
    ft = f * t
    for p in range(int(p_max) + 1):
        if p == 1:
            a_p = (1.0 - f) ** 2 * t
        elif p > 1:
            a_p = a_p * ft
        if p > 0:
            phi = phi + step
        k = np.floor(np.mod(phi, two_pi) / bin_width).astype(np.int64)
        np.clip(k, 0, n_bins - 1, out=k)
        e = np.bincount(k, weights=a_p, minlength=n_bins) * w
        hist += e
        captured += float(e.sum())
        if p >= 2 and total - captured < tol:
            break
        if p >= 1:
            # Only offsets near grazing keep bouncing; drop those whose whole remaining
            # tail (a geometric series) is below 1e-17 of their share of the beam.
            keep = a_p * ft > 1e-17 * np.maximum(1.0 - ft, 1e-300)
            if not np.all(keep):
                f, t, ft, a_p, phi, step = f[keep], t[keep], ft[keep], a_p[keep], phi[keep], step[keep]
                if len(a_p) == 0:
                    break
    return hist / bin_width
