"""Khungurn et al. 2015's fabric fiber model as a Mitsuba 3 BSDF (``usdfiber_khungurn``).

The model is :mod:`usdfiber.fit.khungurn`'s (same formulas, evaluated with Dr.Jit): for the
viewer ``v = si.wi`` and the light ``l = wo`` in Mitsuba's curve frame (local y is the fiber
tangent, ``sin theta = w.y``; the azimuth is measured in the local x-z plane)::

    f(v, l) = C_R  M(theta_l | theta_v; beta_R)  cos(dphi / 2) / 4
            + C_TT M(theta_l | theta_v; beta_TT) G(dphi - pi; gamma_TT)

``eval`` returns ``f`` (the cosine-weighted value Mitsuba expects: a far-field fiber has no
cosine to the tube's normal). The normalization of ``M`` (a Gaussian in ``theta_l + theta_v``
normalized against ``cos theta_l``) is tabulated over ``theta_v`` on 257 nodes from
:func:`usdfiber.fit.khungurn.longitudinal` and interpolated linearly.

Sampling is by the lobes: a lobe is picked with probability proportional to its mean
``C``, ``theta_l`` from the Gaussian truncated to [-pi/2, pi/2] (inverse CDF with ``erfinv``),
``dphi`` from the lobe's azimuthal density exactly (``2 asin(2u - 1)`` for R, the truncated
Gaussian about pi for TT). ``pdf`` is the mixture's density per steradian (the sampled
``theta`` density over ``cos theta``); it is not proportional to ``f`` (``M``'s cosine), so
weights are ``f / pdf``.

Per fiber slot parameters: the plugin serves every fiber curve of a scene, looking up the
slot of each curve segment (``si.prim_index``), as :mod:`.fiber_bsdf` does.
"""
from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from usdfiber.backend import configure_llvm
from usdfiber.fit.khungurn import KhungurnParams, longitudinal
from usdfiber.translators.mitsuba.plugins import VariantPlugin, forwarding_bsdf

configure_llvm()
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

__all__ = ["PLUGIN_NAME", "KhungurnBsdf", "khungurn_bsdf", "register"]

PLUGIN_NAME = "usdfiber_khungurn"
NORM_NODES = 257


def _norm_table(beta_deg: float) -> np.ndarray:
    """1 / z(theta_v) on NORM_NODES theta_v nodes over [-pi/2, pi/2] (M's normalization)."""
    tv = np.linspace(-0.5 * math.pi, 0.5 * math.pi, NORM_NODES)
    return longitudinal(tv, -tv, math.radians(beta_deg))


def _rgb(c: Sequence[float]) -> list[float]:
    c = [float(x) for x in c]
    return c * 3 if len(c) == 1 else c[:3]


class KhungurnBsdf:
    """The per-slot parameters on the device and the model's eval/pdf/sample (any variant)."""

    def __init__(self, params: Sequence[KhungurnParams], seg_slot: np.ndarray | None = None) -> None:
        if not params:
            raise ValueError("no Khungurn parameters")
        F, U = mi.Float, mi.UInt32
        n = len(params)
        seg = np.zeros(1, np.uint32) if seg_slot is None else np.asarray(seg_slot, np.uint32)
        if len(seg) and int(seg.max()) >= n:
            raise ValueError("segment slot index out of range")
        self.per_segment = seg_slot is not None
        self._seg_slot = U(seg)
        c_r = np.array([_rgb(p.c_r) for p in params], np.float32)
        c_tt = np.array([_rgb(p.c_tt) for p in params], np.float32)
        self._c_r = mi.Vector3f(*(F(np.ascontiguousarray(c_r[:, k])) for k in range(3)))
        self._c_tt = mi.Vector3f(*(F(np.ascontiguousarray(c_tt[:, k])) for k in range(3)))
        # Lobe choice: probability of R from the channels' mean C.
        mr, mt = c_r.mean(axis=1), c_tt.mean(axis=1)
        self._p_r = F(np.where(mr + mt > 0, mr / np.maximum(mr + mt, 1e-30), 0.5).astype(np.float32))
        self._beta = [F(np.array([math.radians(getattr(p, name)) for p in params], np.float32))
                      for name in ("beta_r_deg", "beta_tt_deg")]
        gam = np.array([math.radians(p.gamma_tt_deg) for p in params])
        self._gamma = F(gam.astype(np.float32))
        from scipy.special import erf
        self._gamma_span = F(erf(math.pi / (math.sqrt(2.0) * gam)).astype(np.float32))
        self._norm = [F(np.concatenate([_norm_table(getattr(p, name)) for p in params]).astype(np.float32))
                      for name in ("beta_r_deg", "beta_tt_deg")]

    # ---- helpers ---------------------------------------------------------------------------
    def _slot(self, si: Any, active: Any) -> Any:
        seg = si.prim_index if self.per_segment else mi.UInt32(0)
        return dr.gather(mi.UInt32, self._seg_slot, seg, active)

    @staticmethod
    def _angles(w: Any) -> tuple[Any, Any]:
        return dr.asin(dr.clip(w.y, -1.0, 1.0)), dr.atan2(w.x, w.z)

    @staticmethod
    def _wrap(x: Any) -> Any:
        return x - 2 * math.pi * dr.round(x / (2 * math.pi))

    def _m(self, lobe: int, slot: Any, th_v: Any, th_l: Any, active: Any) -> Any:
        """M(theta_l | theta_v; beta) with the tabulated normalization."""
        beta = dr.gather(mi.Float, self._beta[lobe], slot, active)
        u = dr.clip((th_v + 0.5 * math.pi) / math.pi, 0.0, 1.0) * (NORM_NODES - 1)
        j = dr.minimum(mi.UInt32(dr.floor(u)), NORM_NODES - 2)
        a = u - mi.Float(j)
        base = slot * NORM_NODES + j
        inv_z = (1.0 - a) * dr.gather(mi.Float, self._norm[lobe], base, active) \
            + a * dr.gather(mi.Float, self._norm[lobe], base + 1, active)
        x = (th_l + th_v) / beta
        return dr.exp(-0.5 * x * x) * inv_z

    def _n_tt(self, slot: Any, dphi: Any, active: Any) -> Any:
        g = dr.gather(mi.Float, self._gamma, slot, active)
        span = dr.gather(mi.Float, self._gamma_span, slot, active)
        x = self._wrap(dphi - math.pi) / g
        return dr.exp(-0.5 * x * x) / (math.sqrt(2 * math.pi) * g * span)

    def _theta_pdf(self, lobe: int, slot: Any, th_v: Any, th_l: Any, active: Any) -> Any:
        """Density per radian of the truncated Gaussian the sampler draws theta_l from."""
        beta = dr.gather(mi.Float, self._beta[lobe], slot, active)
        s = math.sqrt(2.0) * beta
        span = 0.5 * (dr.erf((0.5 * math.pi + th_v) / s) - dr.erf((-0.5 * math.pi + th_v) / s))
        x = (th_l + th_v) / beta
        return dr.exp(-0.5 * x * x) / (math.sqrt(2 * math.pi) * beta * dr.maximum(span, 1e-12))

    def _eval_pdf(self, si: Any, wo: Any, active: Any) -> tuple[Any, Any]:
        slot = self._slot(si, active)
        th_v, ph_v = self._angles(si.wi)
        th_l, ph_l = self._angles(wo)
        dphi = self._wrap(ph_l - ph_v)
        n_r = dr.cos(0.5 * dphi) / 4.0
        n_t = self._n_tt(slot, dphi, active)
        c_r = mi.Color3f(dr.gather(mi.Vector3f, self._c_r, slot, active))
        c_t = mi.Color3f(dr.gather(mi.Vector3f, self._c_tt, slot, active))
        f = c_r * (self._m(0, slot, th_v, th_l, active) * n_r) + c_t * (self._m(1, slot, th_v, th_l, active) * n_t)
        p_r = dr.gather(mi.Float, self._p_r, slot, active)
        inv_cos = 1.0 / dr.maximum(dr.cos(th_l), 1e-7)
        pdf = (p_r * self._theta_pdf(0, slot, th_v, th_l, active) * n_r
               + (1.0 - p_r) * self._theta_pdf(1, slot, th_v, th_l, active) * n_t) * inv_cos
        return dr.select(active, f, 0.0), dr.select(active, pdf, 0.0)

    # ---- Mitsuba's interface ---------------------------------------------------------------
    def eval(self, ctx: Any, si: Any, wo: Any, active: Any = True) -> Any:
        return self._eval_pdf(si, wo, active)[0]

    def pdf(self, ctx: Any, si: Any, wo: Any, active: Any = True) -> Any:
        return self._eval_pdf(si, wo, active)[1]

    def eval_pdf(self, ctx: Any, si: Any, wo: Any, active: Any = True) -> tuple[Any, Any]:
        return self._eval_pdf(si, wo, active)

    def sample(self, ctx: Any, si: Any, sample1: Any, sample2: Any, active: Any = True) -> tuple[Any, Any]:
        F = mi.Float
        slot = self._slot(si, active)
        th_v, ph_v = self._angles(si.wi)
        p_r = dr.gather(F, self._p_r, slot, active)
        is_r = sample1 < p_r
        beta = dr.select(is_r, dr.gather(F, self._beta[0], slot, active), dr.gather(F, self._beta[1], slot, active))
        s = math.sqrt(2.0) * beta
        lo, hi = dr.erf((-0.5 * math.pi + th_v) / s), dr.erf((0.5 * math.pi + th_v) / s)
        e = dr.clip(lo + sample2.x * (hi - lo), -0.99999994, 0.99999994)
        th_l = dr.clip(-th_v + s * dr.erfinv(e), -0.5 * math.pi + 1e-6, 0.5 * math.pi - 1e-6)
        g = dr.gather(F, self._gamma, slot, active)
        span = dr.gather(F, self._gamma_span, slot, active)
        u = sample2.y
        d_r = 2.0 * dr.asin(dr.clip(2.0 * u - 1.0, -1.0, 1.0))
        d_t = math.pi + math.sqrt(2.0) * g * dr.erfinv(dr.clip((2.0 * u - 1.0) * span, -0.99999994, 0.99999994))
        ph_l = ph_v + dr.select(is_r, d_r, d_t)
        ct = dr.cos(th_l)
        wo = mi.Vector3f(ct * dr.sin(ph_l), dr.sin(th_l), ct * dr.cos(ph_l))
        f, pdf = self._eval_pdf(si, wo, active)
        bs = dr.zeros(mi.BSDFSample3f)
        ok = active & (pdf > 0)
        bs.wo = wo
        bs.pdf = dr.select(ok, pdf, 0.0)
        bs.eta = 1.0
        bs.sampled_component = mi.UInt32(0)
        Flags = mi.BSDFFlags
        refl = mi.Frame3f.cos_theta(wo) * mi.Frame3f.cos_theta(si.wi) > 0
        bs.sampled_type = dr.select(refl, mi.UInt32(int(Flags.GlossyReflection)),
                                    mi.UInt32(int(Flags.GlossyTransmission)))
        return bs, dr.select(ok, f / dr.maximum(pdf, 1e-30), 0.0)


def _params_from_properties(props: Any) -> KhungurnParams:
    def rgb(name: str, default: float) -> tuple[float, ...]:
        if name not in props:
            return (default,) * 3
        v = props.get(name)
        return (float(v),) * 3 if isinstance(v, (int, float)) else tuple(float(v[i]) for i in range(3))

    return KhungurnParams(c_r=rgb("c_r", 0.05), c_tt=rgb("c_tt", 0.9),
                          beta_r_deg=float(props.get("beta_r_deg", 10.0)),
                          beta_tt_deg=float(props.get("beta_tt_deg", 10.0)),
                          gamma_tt_deg=float(props.get("gamma_tt_deg", 30.0)))


def _define_plugin(mi: Any) -> type:
    class KhungurnPlugin(forwarding_bsdf(mi)):
        """``usdfiber_khungurn``: Mitsuba's view of a :class:`KhungurnBsdf`."""

        def __init__(self, props: Any) -> None:
            super().__init__(props)
            self.model = KhungurnBsdf([_params_from_properties(props)])
            Flags = mi.BSDFFlags
            flags = Flags.GlossyReflection | Flags.GlossyTransmission | Flags.FrontSide | Flags.BackSide
            self.m_components, self.m_flags = [flags], flags

        def set_fibers(self, params: Sequence[KhungurnParams], seg_slot: np.ndarray) -> None:
            """Per-slot parameters and the slot of each curve segment."""
            self.model = KhungurnBsdf(params, seg_slot)

        def to_string(self) -> str:
            return "KhungurnFiber[]"

    return KhungurnPlugin


_PLUGIN = VariantPlugin(PLUGIN_NAME, "bsdf", _define_plugin)


def bsdf_class(mi: Any) -> type:
    """The Mitsuba BSDF class for the active variant; its ``model`` is a :class:`KhungurnBsdf`.

    Stand-alone properties (one fiber for every curve): ``c_r``, ``c_tt`` (RGB or float),
    ``beta_r_deg``, ``beta_tt_deg``, ``gamma_tt_deg``.
    """
    return _PLUGIN.plugin_class(mi)


def register(mi: Any) -> type:
    """Register ``usdfiber_khungurn`` with Mitsuba's active variant (once); returns the class."""
    return _PLUGIN.register(mi)


def khungurn_bsdf(mi: Any, params: Sequence[KhungurnParams], seg_slot: np.ndarray) -> Any:
    """A ready BSDF for curves whose segments use the slots ``seg_slot`` of ``params``."""
    b = bsdf_class(mi)(mi.Properties())
    b.set_fibers(params, np.asarray(seg_slot))
    return b
