"""Khungurn et al. 2015's fabric fiber model as a far-field BCSDF.

"Matching Real Fabrics with Micro-Appearance Models" scatters light from a fiber with two
lobes, a reflection R and a transmission TT, each a Gaussian in the longitudinal angle about
the specular cone and, for TT, a Gaussian in azimuth about the forward direction; the
parameters are those Aliaga et al. fit in their Figure 12 (``C_R``, ``C_TT``, ``beta_R``,
``beta_TT``, ``gamma_TT``). For a viewer ``v`` and a light ``l`` (both pointing away from the
fiber, ``dphi = phi_l - phi_v`` in [-pi, pi])::

    f(v, l) = C_R  M(theta_l | theta_v; beta_R)  cos(dphi / 2) / 4
            + C_TT M(theta_l | theta_v; beta_TT) G(dphi - pi; gamma_TT)

* ``M(theta_l | theta_v; beta)``: a Gaussian of standard deviation ``beta`` in
  ``theta_l + theta_v`` (the specular cone is ``theta_l = -theta_v``), normalized so that
  ``int M cos(theta_l) d theta_l = 1`` over [-pi/2, pi/2] for every viewer;
* ``cos(dphi / 2) / 4``: the azimuthal distribution of light reflected by a cylinder
  (Marschner et al. 2003 without Fresnel), integrating to 1;
* ``G(x; gamma)``: a Gaussian of standard deviation ``gamma`` about the forward direction,
  wrapped to the circle by truncation to [-pi, pi] and normalized there.

``C_R`` and ``C_TT`` are per colour channel (the model allows coloured reflection, which
Fresnel does not; Aliaga et al. Section 2), so ``int f d omega_l = C_R + C_TT``: with
``C_R + C_TT = 1`` the model passes the white furnace. ``f`` is the radiance factor of the
viewer (a renderer's cosine-weighted ``eval``), as for :mod:`usdfiber.fit.chiang`; the
per-viewer normalization of M makes it slightly non-reciprocal away from the specular cone.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
from scipy.special import erf

from usdfiber.fit.lobes import gauss_legendre, periodic_bin_mean, theta_bin_nodes, wrap_pi

__all__ = ["KhungurnParams", "MODEL", "far_field", "grid_values"]

MODEL = "khungurn"
_NORM_NODES = gauss_legendre(96, -0.5 * math.pi, 0.5 * math.pi)


@dataclass(frozen=True)
class KhungurnParams:
    """``c_r``, ``c_tt`` per channel; ``beta_r_deg``, ``beta_tt_deg``, ``gamma_tt_deg`` in degrees."""

    c_r: tuple[float, ...] = (0.05,)
    c_tt: tuple[float, ...] = (0.9,)
    beta_r_deg: float = 10.0
    beta_tt_deg: float = 10.0
    gamma_tt_deg: float = 30.0

    def __post_init__(self) -> None:
        cr = tuple(float(x) for x in self.c_r)
        ct = tuple(float(x) for x in self.c_tt)
        if len(cr) != len(ct):
            raise ValueError(f"c_r has {len(cr)} channels, c_tt {len(ct)}")
        object.__setattr__(self, "c_r", cr)
        object.__setattr__(self, "c_tt", ct)
        for name in ("beta_r_deg", "beta_tt_deg", "gamma_tt_deg"):
            if not (getattr(self, name) > 0):
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")

    @property
    def channels(self) -> int:
        return len(self.c_r)

    def to_json(self) -> dict[str, Any]:
        return {"c_r": list(self.c_r), "c_tt": list(self.c_tt), "beta_r_deg": self.beta_r_deg,
                "beta_tt_deg": self.beta_tt_deg, "gamma_tt_deg": self.gamma_tt_deg}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "KhungurnParams":
        return cls(c_r=tuple(d["c_r"]), c_tt=tuple(d["c_tt"]), beta_r_deg=float(d["beta_r_deg"]),
                   beta_tt_deg=float(d["beta_tt_deg"]), gamma_tt_deg=float(d["gamma_tt_deg"]))


def longitudinal(theta_v: np.ndarray, theta_l: np.ndarray, beta: float) -> np.ndarray:
    """M(theta_l | theta_v; beta) (module docstring), per radian against cos theta_l."""
    tv = np.asarray(theta_v, dtype=np.float64)
    tl = np.asarray(theta_l, dtype=np.float64)
    x, w = _NORM_NODES
    g = np.exp(-0.5 * ((x[:, None] + tv.ravel()[None, :]) / beta) ** 2)
    z = (w[:, None] * np.cos(x)[:, None] * g).sum(axis=0).reshape(tv.shape)
    return np.exp(-0.5 * ((tl + tv) / beta) ** 2) / z


def _reflection_cdf(x: np.ndarray) -> np.ndarray:
    return 0.5 * (np.sin(0.5 * x) + 1.0)


def _forward_cdf(gamma: float):
    lo = erf(-math.pi / (math.sqrt(2.0) * gamma))
    span = -2.0 * lo

    def cdf(x: np.ndarray) -> np.ndarray:
        return (erf(x / (math.sqrt(2.0) * gamma)) - lo) / span
    return cdf


def _forward(x: np.ndarray, gamma: float) -> np.ndarray:
    span = erf(math.pi / (math.sqrt(2.0) * gamma))
    return np.exp(-0.5 * (x / gamma) ** 2) / (math.sqrt(2.0 * math.pi) * gamma * span)


def far_field(params: KhungurnParams, theta_v, theta_l, dphi) -> np.ndarray:
    """f(v, l) per steradian at points (radians, broadcast), shape (..., C)."""
    tv, tl, dp = np.broadcast_arrays(*(np.asarray(x, dtype=np.float64) for x in (theta_v, theta_l, dphi)))
    d = wrap_pi(dp)
    mr = longitudinal(tv, tl, math.radians(params.beta_r_deg))
    mt = longitudinal(tv, tl, math.radians(params.beta_tt_deg))
    nr = np.cos(0.5 * d) / 4.0
    nt = _forward(wrap_pi(d - math.pi), math.radians(params.gamma_tt_deg))
    cr, ct = np.asarray(params.c_r), np.asarray(params.c_tt)
    return (mr * nr)[..., None] * cr + (mt * nt)[..., None] * ct


def lobe_grids(params: KhungurnParams, target, n_sub: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """The R and TT lobes with ``C = 1`` on the target's bins, each (n_i, n_o, n_phi)."""
    th, wt = theta_bin_nodes(target.theta_o_edges, n_sub)                # (n_o, n_sub)
    wt = wt * np.cos(th)              # s = cos(theta_o) f, averaged over the bin's solid angle
    ti = target.theta_i[:, None, None]
    mr = (longitudinal(th[None], ti, math.radians(params.beta_r_deg)) * wt[None]).sum(axis=-1)   # (n_i, n_o)
    mt = (longitudinal(th[None], ti, math.radians(params.beta_tt_deg)) * wt[None]).sum(axis=-1)
    lo, hi = target.dphi_edges()
    nr = periodic_bin_mean(_reflection_cdf, lo, hi)                        # (n_phi,)
    nt = periodic_bin_mean(_forward_cdf(math.radians(params.gamma_tt_deg)), lo - math.pi, hi - math.pi)
    return mr[:, :, None] * nr[None, None, :], mt[:, :, None] * nt[None, None, :]


def grid_values(params: KhungurnParams, target, n_sub: int = 3) -> np.ndarray:
    """The model's ``s = cos(theta_o) f(omega_o -> omega_i)`` averaged over the target's bins
    (:mod:`usdfiber.fit.objective`), shape (n_i, n_o, n_phi, C)."""
    r, t = lobe_grids(params, target, n_sub)
    cr, ct = np.asarray(params.c_r), np.asarray(params.c_tt)
    return r[..., None] * cr + t[..., None] * ct


def channel_params(params: KhungurnParams, c_r: Sequence[float], c_tt: Sequence[float]) -> KhungurnParams:
    return KhungurnParams(tuple(c_r), tuple(c_tt), params.beta_r_deg, params.beta_tt_deg, params.gamma_tt_deg)
