"""Chiang et al. 2016 hair model (d'Eon et al. 2011 longitudinal lobes) as a far-field BCSDF.

The model Mitsuba 3's ``hair`` BSDF and MaterialX's ``chiang_hair_bsdf`` implement. For a
viewer ``omega_v`` and a light ``omega_l`` (both pointing away from the fiber; ``theta``
from the plane normal to the fiber, ``dphi = phi_l - phi_v``), at the offset ``h`` across
the fiber where the viewer's ray meets it::

    f(v, l; h) = sum_{p=0}^{2} t_p M_p(theta_v^(p), theta_l) A_p(theta_v, h) N_p(dphi; h)
                 + t_2 M_3(theta_v, theta_l) A_3(theta_v, h) / (2 pi)

* ``M_p``: d'Eon's longitudinal lobe with variance ``v_p`` (``v_0 = v``, ``v_1 = v/4``,
  ``v_2 = v_3 = 4 v``, ``v = (0.726 b_m + 0.812 b_m^2 + 3.7 b_m^20)^2``)::

      M(v; a, b) = exp(-sin a sin b / v) I0(cos a cos b / v) / (2 v sinh(1/v))

  which integrates to 1 against ``cos(theta_l) d theta_l``. The cuticle tilt ``alpha``
  turns the viewer's angle per lobe: ``theta_v - 2 alpha`` (R), ``+ alpha`` (TT),
  ``+ 4 alpha`` (TRT), as Mitsuba does.
* ``A_p``: Fresnel ``F`` at ``cos(theta_v) cos(gamma_i)`` (``h = sin gamma_i``) and the
  transmittance ``T = exp(-sigma_a 2 cos(gamma_t) / cos(theta_t))`` per crossing (``sigma_a``
  per unit RADIUS, as in Mitsuba's ``sigma_a`` and MaterialX's ``absorption_coefficient``;
  Bravais index ``eta' = sqrt(eta^2 - sin^2 theta_v) / cos theta_v``, ``sin gamma_t = h /
  eta'``): ``A_0 = F``, ``A_1 = (1-F)^2 T``, ``A_2 = A_1 T F``, ``A_3 = A_2 T F / (1 - T F)``.
* ``N_p``: the logistic of scale ``s = sqrt(pi/8) (0.265 b_n + 1.194 b_n^2 + 5.372 b_n^22)``
  trimmed to [-pi, pi], centred on ``Phi(p, h) = 2 p gamma_t - 2 gamma_i + p pi``.
* ``t_p``: per-lobe tints (MaterialX's ``tint_R``, ``tint_TT``, ``tint_TRT``; the last one
  also scales p >= 3 there). Mitsuba's ``hair`` has none (all 1).

Far field: a renderer averages over ``h`` uniform in [-1, 1] (``f_bar = (1/2) int f dh``),
which is what a table holds. ``f_bar(v, l)`` is the radiance factor of the viewer ``v`` for
the light ``l`` (Mitsuba's cosine-weighted ``eval`` with ``si.wi = v``), so in the tables'
convention (``usdfiber.bcsdf``) ``sigma(omega_i, omega_o) = D cos(theta_o) f_bar(omega_o ->
omega_i)`` for a fiber of width ``D`` lit from ``omega_i`` and seen from ``omega_o``. With no
absorption and tints 1, ``int f_bar d omega_l = 1`` for every viewer (the A_p sum to 1, each
M_p and N_p is normalized): the white furnace. The model is not reciprocal (A_p and N_p see
only the viewer), so ``sigma`` is not symmetric; Mitsuba marks it non-symmetric too.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Sequence

import numpy as np
from scipy.special import i0e

from usdfiber.fit.lobes import offset_nodes, periodic_cdf, theta_bin_nodes, wrap_pi

__all__ = ["ChiangParams", "far_field", "grid_values", "logistic_scale", "longitudinal",
           "longitudinal_variance", "MODEL"]

MODEL = "chiang"
SQRT_PI_OVER_8 = math.sqrt(math.pi / 8.0)
_LOBE_VARIANCE = (1.0, 0.25, 4.0, 4.0)      # v_p / v
_TILT = (-2.0, 1.0, 4.0, 0.0)               # theta_v^(p) = theta_v + k_p alpha


def longitudinal_variance(beta_m: float) -> float:
    """d'Eon / Chiang longitudinal variance ``v`` of roughness ``b_m`` in [0, 1] (rad^2)."""
    b = float(beta_m)
    return (0.726 * b + 0.812 * b * b + 3.7 * b ** 20) ** 2


def azimuthal_scale_raw(beta_n: float) -> float:
    """Chiang's ``0.265 b_n + 1.194 b_n^2 + 5.372 b_n^22`` (MaterialX's azimuthal roughness)."""
    b = float(beta_n)
    return 0.265 * b + 1.194 * b * b + 5.372 * b ** 22


def logistic_scale(beta_n: float) -> float:
    """The logistic scale ``s`` of azimuthal roughness ``b_n`` in [0, 1] (radians)."""
    return SQRT_PI_OVER_8 * azimuthal_scale_raw(beta_n)


@dataclass(frozen=True)
class ChiangParams:
    """Parameters of the model (module docstring), per colour channel where they are tuples.

    ``ior``: the fiber's index; ``beta_m``, ``beta_n``: Mitsuba's ``longitudinal_roughness``
    and ``azimuthal_roughness`` in [0, 1]; ``alpha_deg``: cuticle tilt (Mitsuba's
    ``scale_tilt``); ``sigma_a``: absorption per unit radius per channel; ``tint_r``,
    ``tint_tt``, ``tint_trt``: per channel lobe tints (1 = none).
    """

    ior: float = 1.55
    beta_m: float = 0.3
    beta_n: float = 0.3
    alpha_deg: float = 0.0
    sigma_a: tuple[float, ...] = (0.0,)
    tint_r: tuple[float, ...] = (1.0,)
    tint_tt: tuple[float, ...] = (1.0,)
    tint_trt: tuple[float, ...] = (1.0,)

    def __post_init__(self) -> None:
        n = len(self.sigma_a)
        for name in ("tint_r", "tint_tt", "tint_trt"):
            t = tuple(float(x) for x in getattr(self, name))
            if len(t) == 1 and n > 1:
                t = t * n
            if len(t) != n:
                raise ValueError(f"{name} has {len(t)} channels, sigma_a {n}")
            object.__setattr__(self, name, t)
        object.__setattr__(self, "sigma_a", tuple(float(x) for x in self.sigma_a))
        if not (self.ior > 1.0):
            raise ValueError(f"ior must be > 1, got {self.ior}")
        for name in ("beta_m", "beta_n"):
            v = getattr(self, name)
            if not (0.0 < v <= 1.0):
                raise ValueError(f"{name} must be in (0, 1], got {v}")

    @property
    def channels(self) -> int:
        return len(self.sigma_a)

    @property
    def variance(self) -> float:
        return longitudinal_variance(self.beta_m)

    @property
    def scale(self) -> float:
        return logistic_scale(self.beta_n)

    def tints(self) -> np.ndarray:
        """(4, C): the tint of each lobe p = 0..3 (p >= 3 takes TRT's, as MaterialX does)."""
        trt = np.asarray(self.tint_trt)
        return np.stack([np.asarray(self.tint_r), np.asarray(self.tint_tt), trt, trt])

    def has_tints(self) -> bool:
        return bool(np.any(np.abs(self.tints() - 1.0) > 1e-9))

    # ---- exchange ------------------------------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        return {"ior": self.ior, "beta_m": self.beta_m, "beta_n": self.beta_n, "alpha_deg": self.alpha_deg,
                "sigma_a": list(self.sigma_a), "tint_r": list(self.tint_r), "tint_tt": list(self.tint_tt),
                "tint_trt": list(self.tint_trt)}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "ChiangParams":
        return cls(ior=float(d["ior"]), beta_m=float(d["beta_m"]), beta_n=float(d["beta_n"]),
                   alpha_deg=float(d["alpha_deg"]), sigma_a=tuple(d["sigma_a"]), tint_r=tuple(d["tint_r"]),
                   tint_tt=tuple(d["tint_tt"]), tint_trt=tuple(d["tint_trt"]))

    def to_mitsuba(self) -> dict[str, Any]:
        """A ``mi.load_dict`` dictionary of Mitsuba 3's ``hair`` BSDF with these parameters.

        ``hair`` has no lobe tints: a fit with tints (``FitSettings(tints=True)``) is refused.
        ``sigma_a`` is per unit radius, as ``hair`` uses it (its path length through the
        fiber is ``2 cos gamma_t / cos theta_t``).
        """
        if self.has_tints():
            raise ValueError("Mitsuba's hair BSDF has no lobe tints; fit with FitSettings(tints=False)")
        sig = list(self.sigma_a) * (3 if self.channels == 1 else 1)
        return {"type": "hair", "int_ior": float(self.ior), "longitudinal_roughness": float(self.beta_m),
                "azimuthal_roughness": float(self.beta_n), "scale_tilt": float(self.alpha_deg),
                "sigma_a": {"type": "rgb", "value": [float(x) for x in sig[:3]]}}

    def to_materialx(self) -> dict[str, Any]:
        """The inputs of MaterialX 1.39 ``chiang_hair_bsdf`` (name -> value), three channels.

        MaterialX takes, per lobe, ``roughness_X = (longitudinal variance, azimuthal scale
        before the sqrt(pi/8) factor)``, as its ``chiang_hair_roughness`` node makes them, and
        ``cuticle_angle`` in [0, 1] mapped to ``pi c - pi/2`` radians turning the LIGHT's
        angle with the opposite sign to Mitsuba's tilt of the viewer's: ``c = 1/2 - alpha /
        pi`` puts every lobe's peak at the same place.
        """
        def rgb(t: Sequence[float]) -> tuple[float, float, float]:
            t = list(t) * (3 if len(t) == 1 else 1)
            return (float(t[0]), float(t[1]), float(t[2]))

        v = self.variance
        s = azimuthal_scale_raw(self.beta_n)
        return {
            "tint_R": rgb(self.tint_r), "tint_TT": rgb(self.tint_tt), "tint_TRT": rgb(self.tint_trt),
            "ior": float(self.ior),
            "roughness_R": (float(v), float(s)), "roughness_TT": (float(v * 0.25), float(s)),
            "roughness_TRT": (float(v * 4.0), float(s)),
            "cuticle_angle": float(0.5 - math.radians(self.alpha_deg) / math.pi),
            "absorption_coefficient": rgb(self.sigma_a),
        }

    def with_channels(self, sigma_a: Sequence[float], tints: np.ndarray | None = None) -> "ChiangParams":
        t = np.ones((3, len(sigma_a))) if tints is None else np.asarray(tints)
        return replace(self, sigma_a=tuple(float(x) for x in sigma_a), tint_r=tuple(t[0]), tint_tt=tuple(t[1]),
                       tint_trt=tuple(t[2]))


# ---- the lobes ---------------------------------------------------------------------------------

def longitudinal(theta_v: np.ndarray, theta_l: np.ndarray, v: float) -> np.ndarray:
    """d'Eon's M(v; theta_v, theta_l) (per radian against cos theta_l), stable for small v."""
    tv = np.asarray(theta_v, dtype=np.float64)
    tl = np.asarray(theta_l, dtype=np.float64)
    cv, sv = np.abs(np.cos(tv)), np.sin(tv)
    cl, sl = np.cos(tl), np.sin(tl)
    x = cv * cl / v
    log_m = (cv * cl - sv * sl - 1.0) / v + np.log(i0e(x)) - math.log(v) - math.log1p(-math.exp(-2.0 / v))
    return np.exp(log_m)


def _fresnel(cos_i: np.ndarray, eta: float) -> np.ndarray:
    """Unpolarized Fresnel reflectance from outside a dielectric of index ``eta`` > 1."""
    c = np.clip(cos_i, 0.0, 1.0)
    ct = np.sqrt(np.maximum(1.0 - (1.0 - c * c) / (eta * eta), 0.0))
    rs = (c - eta * ct) / (c + eta * ct)
    rp = (eta * c - ct) / (eta * c + ct)
    return 0.5 * (rs * rs + rp * rp)


def _geometry(theta_v: np.ndarray, h: np.ndarray, eta: float):
    """(F, path length 2 cos gamma_t / cos theta_t, gamma_i, gamma_t) at viewer angles x offsets."""
    sv = np.sin(theta_v)
    cv = np.cos(theta_v)
    cos_gi = np.sqrt(np.maximum(1.0 - h * h, 0.0))
    F = _fresnel(cv * cos_gi, eta)
    eta_p = np.sqrt(np.maximum(eta * eta - sv * sv, 0.0)) / np.maximum(cv, 1e-12)
    sgt = np.clip(h / eta_p, -1.0, 1.0)
    cos_gt = np.sqrt(1.0 - sgt * sgt)
    cos_tt = np.sqrt(np.maximum(1.0 - (sv / eta) ** 2, 0.0))
    return F, 2.0 * cos_gt / cos_tt, np.arcsin(np.clip(h, -1.0, 1.0)), np.arcsin(sgt)


def _attenuation(F: np.ndarray, length: np.ndarray, sigma_a: np.ndarray) -> np.ndarray:
    """A_p (4, ..., C) for p = 0, 1, 2 and the sum of p >= 3."""
    T = np.exp(-length[..., None] * sigma_a)
    F = F[..., None]
    a0 = np.broadcast_to(F, T.shape)
    a1 = (1.0 - F) ** 2 * T
    a2 = a1 * T * F
    a3 = a2 * T * F / np.maximum(1.0 - T * F, 1e-12)
    return np.stack([a0, a1, a2, a3])


def _logistic_cdf(s: float):
    e = math.exp(-math.pi / s)   # in (0, 1): no overflow for a very small scale s
    lo, hi = e / (1.0 + e), 1.0 / (1.0 + e)

    def cdf(x: np.ndarray) -> np.ndarray:
        return (1.0 / (1.0 + np.exp(-np.clip(x / s, -700.0, 700.0))) - lo) / (hi - lo)
    return cdf


def _logistic(x: np.ndarray, s: float) -> np.ndarray:
    """The logistic of scale s trimmed to [-pi, pi] (x already wrapped)."""
    a = np.abs(x)
    e = np.exp(-a / s)
    norm = 1.0 / (1.0 + math.exp(-math.pi / s)) - 1.0 / (1.0 + math.exp(math.pi / s))
    return e / (s * (1.0 + e) ** 2) / norm


# ---- far field -------------------------------------------------------------------------------

def far_field(params: ChiangParams, theta_v, theta_l, dphi, *, n_h: int = 96,
              h_nodes: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """f_bar(v, l) per steradian at points (radians, broadcast), shape (..., C).

    ``h_nodes``: (h, weight) for the average over offsets (default: :func:`offset_nodes`).
    """
    tv, tl, dp = np.broadcast_arrays(*(np.asarray(x, dtype=np.float64) for x in (theta_v, theta_l, dphi)))
    h, wh = offset_nodes(n_h) if h_nodes is None else (np.asarray(h_nodes[0]), np.asarray(h_nodes[1]))
    sig = np.asarray(params.sigma_a)
    shape = tv.shape
    tv, tl, dp = tv.ravel(), tl.ravel(), dp.ravel()
    chunk = max(1, 2_000_000 // (h.size * len(sig)))              # bounded memory for large grids
    if tv.size > chunk:
        parts = [_far_field_flat(params, tv[i:i + chunk], tl[i:i + chunk], dp[i:i + chunk], h, wh)
                 for i in range(0, tv.size, chunk)]
        return np.concatenate(parts).reshape(shape + (len(sig),))
    return _far_field_flat(params, tv, tl, dp, h, wh).reshape(shape + (len(sig),))


def _far_field_flat(params: ChiangParams, tv: np.ndarray, tl: np.ndarray, dp: np.ndarray, h: np.ndarray,
                    wh: np.ndarray) -> np.ndarray:
    sig = np.asarray(params.sigma_a)
    tints = params.tints()
    v = params.variance
    s = params.scale
    alpha = math.radians(params.alpha_deg)
    F, length, gi, gt = _geometry(tv[:, None], h[None, :], params.ior)          # (n, n_h)
    A = _attenuation(F, length, sig)                                          # (4, n, n_h, C)
    out = np.zeros((tv.size, len(sig)))
    for p in range(4):
        m = longitudinal(tv + _TILT[p] * alpha, tl, v * _LOBE_VARIANCE[p])       # (n,)
        if p < 3:
            phi = 2.0 * p * gt - 2.0 * gi + p * math.pi
            n_p = _logistic(wrap_pi(dp[:, None] - phi), s)                      # (n, n_h)
        else:
            n_p = np.full((1, 1), 1.0 / (2.0 * math.pi))
        az = np.einsum("nh,nhc->nc", n_p * wh[None, :], A[p]) if p < 3 else \
            (A[p] * wh[None, :, None]).sum(axis=1) / (2.0 * math.pi)
        out += (m[:, None] * az) * tints[p][None, :]
    return out


@dataclass
class ChiangGrid:
    """Precomputed pieces of :func:`grid_values` for one target and one geometry."""

    theta_sub: np.ndarray        # (n_o, n_sub) viewer nodes inside each theta_o bin
    w_sub: np.ndarray            # (n_o, n_sub) their weights (solid-angle mean over the bin)
    h: np.ndarray
    wh: np.ndarray
    key: tuple = ()
    nbin: np.ndarray | None = None     # (3, n_o * n_sub, n_h, n_phi) bin-mean N_p
    F: np.ndarray | None = None
    length: np.ndarray | None = None
    mlong: np.ndarray | None = None    # (4, n_i, n_o * n_sub)
    extra: dict = field(default_factory=dict)


def make_grid(target, n_h: int, n_sub: int) -> ChiangGrid:
    th, wt = theta_bin_nodes(target.theta_o_edges, n_sub)
    h, wh = offset_nodes(n_h)
    return ChiangGrid(th, wt, h, wh)


def _prepare(params: ChiangParams, target, grid: ChiangGrid) -> None:
    key = (params.ior, params.beta_m, params.beta_n, params.alpha_deg)
    if grid.key == key:
        return
    tv = grid.theta_sub.ravel()                                              # (V,)
    F, length, gi, gt = _geometry(tv[:, None], grid.h[None, :], params.ior)   # (V, n_h)
    lo, hi = target.dphi_edges()
    edges = np.append(lo, hi[-1])                       # contiguous bins: n_phi + 1 edges
    cdf = _logistic_cdf(params.scale)
    nb = np.empty((3, tv.size, grid.h.size, lo.size))
    for p in range(3):
        phi = (2.0 * p * gt - 2.0 * gi + p * math.pi)[..., None]             # (V, n_h, 1)
        nb[p] = np.diff(periodic_cdf(cdf, edges[None, None, :] - phi), axis=-1) / target.dphi_step
    alpha = math.radians(params.alpha_deg)
    v = params.variance
    ml = np.stack([longitudinal(tv[None, :] + _TILT[p] * alpha, target.theta_i[:, None], v * _LOBE_VARIANCE[p])
                   for p in range(4)])                                          # (4, n_i, V)
    grid.nbin, grid.F, grid.length, grid.mlong, grid.key = nb, F, length, ml, key


def grid_values(params: ChiangParams, target, grid: ChiangGrid) -> np.ndarray:
    """The model's ``s = cos(theta_o) f_bar(omega_o -> omega_i)`` averaged over the target's
    bins (see :mod:`usdfiber.fit.objective`), shape (n_i, n_o, n_phi, C)."""
    _prepare(params, target, grid)
    sig = np.asarray(params.sigma_a)
    A = _attenuation(grid.F, grid.length, sig) * grid.wh[None, None, :, None]   # (4, V, n_h, C)
    az = np.einsum("pvhm,pvhc->pvmc", grid.nbin, A[:3])                       # (3, V, n_phi, C)
    a3 = A[3].sum(axis=1) / (2.0 * math.pi)                                    # (V, C)
    n_o, n_sub = grid.theta_sub.shape
    # s = cos(theta_o) f_bar, averaged over the bin's solid angle (the weights hold the other cos)
    wv = grid.w_sub.ravel() * np.cos(grid.theta_sub.ravel())
    tints = params.tints()
    ml = grid.mlong * wv[None, None, :]                                         # (4, n_i, V)
    out = np.einsum("piv,pvmc,pc->ivmc", ml[:3], az, tints[:3])
    out += (np.einsum("iv,vc->ivc", ml[3], a3) * tints[3][None, None, :])[:, :, None, :]
    n_i = out.shape[0]
    return out.reshape(n_i, n_o, n_sub, out.shape[2], out.shape[3]).sum(axis=2)
