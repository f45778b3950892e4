"""What a fit compares: a table's scattering over the sphere, and how far a model is from it.

Target
------
A fitted model is round and smooth along the fiber; a renderer draws each fiber of a prim
with a random rotation ``psi`` (and a random cross-section variant), so a model can only
match the table's average over rotations and variants. A pixel covering many fibers sees
their coverage-weighted mean, so the target is the rotation- and variant-averaged
scattering cross section per unit of mean width (:class:`FitTarget`)::

    s(theta_i, theta_o, dphi) = < W(phi_i - psi) cos(theta_i) Lambda(omega_i) p(omega_o | omega_i) >_psi,variant / <W>

on the table's grid: ``theta_i`` at the table's incoming nodes (the light), ``theta_o`` over
its outgoing bins (the viewer) and ``dphi = phi_o - phi_i`` over bins of the table's width
centred on multiples of it (a rotation moves ``phi_i`` and ``phi_o`` together, so averaging
over the table's ``phi_i`` nodes shifts whole bins). ``s`` is dimensionless per steradian;
``int s d omega_o = cos(theta_i) <Lambda>``. A round model of width ``D`` predicts
``s = cos(theta_o) f(omega_o -> omega_i)`` with ``f`` the radiance factor a renderer returns
for the viewer ``omega_o`` and the light ``omega_i`` (bcsdf-radiometry: ``sigma / (W cos
theta_o)``), averaged over the same bins.

Objective
---------
Weighted least squares on logarithms::

    r = sqrt(w) (log(s_model + eps) - log(s_table + eps)),   w = cos(theta_i) * (bin solid angle)

Why logarithms: the table spans three to four decades between the specular peaks and the
diffuse body, and both are seen (a highlight and a body colour); squared differences of
``s`` would fit the peaks and ignore the body, squared relative errors the reverse (and
amplify the table's photon noise in dim bins). Logarithms weigh a factor of two equally
everywhere. ``eps = floor * mean(s_table)`` (``FitSettings.floor``, default 2 %) keeps
empty and noisy dim bins from dominating: below it differences count absolutely. ``w``
is the measure of the sphere of outgoing directions times that of the incoming ones.

To these come energy residuals, one per incoming node ``theta_i``::

    r_E = sqrt(lambda cos(theta_i) / sum cos(theta_i)) (log A_model(theta_i) - log A_table(theta_i))

with ``A = int s d omega_o / cos(theta_i)`` the directional albedo (``lambda``:
``FitSettings.energy_weight``, default 1). The shape terms alone let a model that cannot
follow the table's lobes trade energy for shape, and a fiber's colour under diffuse light
(what a look is judged by first, and the materials' display colour) is its albedo.

Reported error
--------------
:func:`relative_l2`: ``sqrt(sum w (s_model - s_table)^2 / sum w s_table^2)`` per colour
channel, the energy-weighted distance the eye sees in highlights; also the objective's rms
log difference and the albedo ``<Lambda>`` of both.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

__all__ = ["FitTarget", "energy_residuals", "log_residuals", "model_albedo", "relative_l2", "residuals",
           "rms_log"]


@dataclass
class FitTarget:
    """The rotation- and variant-averaged scattering of tables on their grid (module docstring).

    ``values``: (n_i, n_o, n_phi, C); ``theta_i``: (n_i,) light nodes (radians);
    ``theta_o_edges``: (n_o + 1,); ``dphi_step``: the bin width (bins centred on
    ``m * dphi_step``); ``mirror``: the tables are mirror symmetric (no cuticles) and only
    ``theta_i >= 0`` is held; ``albedo``: (n_i, C) the mean Lambda at each node.
    """

    values: np.ndarray
    theta_i: np.ndarray
    theta_o_edges: np.ndarray
    dphi_step: float
    mirror: bool
    albedo: np.ndarray

    @property
    def channels(self) -> int:
        return int(self.values.shape[-1])

    @property
    def n_phi(self) -> int:
        return int(self.values.shape[2])

    def dphi_edges(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) of each dphi bin, radians."""
        c = self.dphi_step * np.arange(self.n_phi)
        return c - 0.5 * self.dphi_step, c + 0.5 * self.dphi_step

    def weights(self) -> np.ndarray:
        """w (n_i, n_o, 1): cos(theta_i) times the bin's solid angle, summing to 1."""
        e = self.theta_o_edges
        dom = self.dphi_step * (np.sin(e[1:]) - np.sin(e[:-1]))
        w = np.cos(self.theta_i)[:, None] * dom[None, :]
        w = np.broadcast_to(w[:, :, None], self.values.shape[:3])
        return w / w.sum()

    def channel(self, c: int) -> "FitTarget":
        """The target of one colour channel."""
        return FitTarget(self.values[..., c:c + 1], self.theta_i, self.theta_o_edges, self.dphi_step,
                         self.mirror, self.albedo[:, c:c + 1])

    def mean_channel(self) -> "FitTarget":
        """The channel mean (for the colour-independent part of a fit)."""
        return FitTarget(self.values.mean(axis=-1, keepdims=True), self.theta_i, self.theta_o_edges,
                         self.dphi_step, self.mirror, self.albedo.mean(axis=-1, keepdims=True))

    # ---- construction ------------------------------------------------------------------
    @classmethod
    def from_tables(cls, tables: Sequence, sigma_a: float | Sequence[float] = 0.0,
                    diameter_scale: float = 1.0) -> "FitTarget":
        """The target of a prim's tables (one per cross-section variant, equally likely),
        recoloured for ``sigma_a`` (1/um, a scalar or one per channel) at ``diameter_scale``
        (the fiber's diameter over the baked one), like ``BcsdfTable.recolour``."""
        if not tables:
            raise ValueError("no tables to fit")
        g0 = tables[0].grid
        for t in tables[1:]:
            g = t.grid
            if ((g.resolution_deg, g.incoming_spacing_deg, g.theta_symmetric)
                    != (g0.resolution_deg, g0.incoming_spacing_deg, g0.theta_symmetric)):
                raise ValueError("the tables of one fit must share their grid and symmetry")
        sig = np.atleast_1d(np.asarray(sigma_a, dtype=np.float64)).reshape(-1)
        acc = None
        alb = None
        wbar = 0.0
        for t in tables:
            s, a, w = _table_sum(t, sig, diameter_scale)
            acc = s if acc is None else acc + s
            alb = a if alb is None else alb + a
            wbar += w
        n = len(tables)
        values = acc / wbar              # (sum of sigma) / (sum of mean widths)
        return cls(values=values, theta_i=g0.theta_i_nodes(), theta_o_edges=g0.theta_o_edges(),
                   dphi_step=g0.step, mirror=bool(g0.theta_symmetric), albedo=alb / n)


def _table_sum(table, sig: np.ndarray, diameter_scale: float) -> tuple[np.ndarray, np.ndarray, float]:
    """(rotation-mean sigma (n_i, n_o, n_phi, C), mean albedo (n_i, C), mean width) of one table."""
    g = table.grid
    rec = table.recolour(sig if len(sig) > 1 else float(sig[0]), diameter_scale)
    p = rec.p                                                    # (n_ti, n_pi, B, n_po, C)
    n_ti, n_pi, B, n_po, C = p.shape
    start = table.band_start.astype(np.int64)
    phi_i = g.phi_i_nodes()
    w_i = table.width(phi_i)                                      # (n_pi,)
    w_bar = float(np.mean(table.width(np.linspace(0.0, 2.0 * math.pi, 720, endpoint=False))))
    cos_i = np.cos(g.theta_i_nodes())
    out = np.zeros((n_ti, g.n_theta_o, n_po, C))
    # Node j sits over the centre of bin shift[j] (nodes at bin centres; a coarser incoming
    # spacing of an even number of bins puts them on bin edges, which this sum cannot shift).
    shift_f = (phi_i - 0.5 * g.step) / g.step
    shift = np.rint(shift_f).astype(np.int64)
    if not np.allclose(shift_f, shift, atol=1e-6):
        raise ValueError(f"fits need incoming nodes at bin centres; this table's phi_i spacing "
                         f"{g.incoming_spacing_deg:g} deg is an even multiple of its {g.resolution_deg:g} deg bins")
    for j in range(n_pi):
        # sigma of node j, its phi_o bins shifted so that column m is dphi = m * step
        pj = np.roll(p[:, j].astype(np.float64), -int(shift[j]), axis=2)      # (n_ti, B, n_po, C)
        scale = (w_i[j] * cos_i)[:, None] * rec.albedo[:, j].astype(np.float64)   # (n_ti, C)
        for ti in range(n_ti):
            r0 = int(start[ti, j])
            out[ti, r0:r0 + B] += pj[ti] * scale[ti][None, None, :]
    albedo = rec.albedo.astype(np.float64).mean(axis=1)
    return out / n_pi, albedo, w_bar


# ---- comparison ----------------------------------------------------------------------------

def _eps(target: FitTarget, floor: float) -> np.ndarray:
    w = target.weights()[..., None]
    mean = (w * target.values).sum(axis=(0, 1, 2))               # per channel
    return np.maximum(floor * mean, 1e-12)


def log_residuals(model: np.ndarray, target: FitTarget, floor: float) -> np.ndarray:
    """The objective's residuals (flat): sqrt(w) (log(model + eps) - log(table + eps))."""
    eps = _eps(target, floor)
    sw = np.sqrt(target.weights())[..., None]
    r = sw * (np.log(np.maximum(model, 0.0) + eps) - np.log(np.maximum(target.values, 0.0) + eps))
    return r.ravel()


def _node_albedo(values: np.ndarray, target: FitTarget) -> np.ndarray:
    e = target.theta_o_edges
    dom = target.dphi_step * (np.sin(e[1:]) - np.sin(e[:-1]))
    return (values * dom[None, :, None, None]).sum(axis=(1, 2)) / np.cos(target.theta_i)[:, None]


def energy_residuals(model: np.ndarray, target: FitTarget, weight: float) -> np.ndarray:
    """The energy residuals (flat) of the objective (module docstring)."""
    wi = np.cos(target.theta_i) / np.cos(target.theta_i).sum()
    am = np.maximum(_node_albedo(model, target), 1e-9)
    at = np.maximum(_node_albedo(target.values, target), 1e-9)
    return (np.sqrt(weight * wi)[:, None] * (np.log(am) - np.log(at))).ravel()


def residuals(model: np.ndarray, target: FitTarget, floor: float, energy_weight: float) -> np.ndarray:
    """All residuals of the objective: shape (:func:`log_residuals`) and energy."""
    r = log_residuals(model, target, floor)
    if energy_weight > 0:
        r = np.concatenate([r, energy_residuals(model, target, energy_weight)])
    return r


def rms_log(model: np.ndarray, target: FitTarget, floor: float) -> np.ndarray:
    """Root of the weighted mean squared log difference, per channel (the objective)."""
    eps = _eps(target, floor)
    w = target.weights()[..., None]
    d = np.log(np.maximum(model, 0.0) + eps) - np.log(np.maximum(target.values, 0.0) + eps)
    return np.sqrt((w * d * d).sum(axis=(0, 1, 2)))


def relative_l2(model: np.ndarray, target: FitTarget) -> np.ndarray:
    """sqrt(sum w (model - table)^2 / sum w table^2) per channel (module docstring)."""
    w = target.weights()[..., None]
    num = (w * (model - target.values) ** 2).sum(axis=(0, 1, 2))
    den = (w * target.values ** 2).sum(axis=(0, 1, 2))
    return np.sqrt(num / np.where(den > 0, den, 1.0))


def model_albedo(model: np.ndarray, target: FitTarget) -> np.ndarray:
    """Mean over the incoming nodes (weights cos theta_i) of int s d omega_o / cos theta_i."""
    cos_i = np.cos(target.theta_i)
    per_node = _node_albedo(model, target)                                      # (n_i, C)
    wi = cos_i / cos_i.sum()
    return (wi[:, None] * per_node).sum(axis=0)


def table_albedo(target: FitTarget) -> np.ndarray:
    """The table's <Lambda> with the same weights as :func:`model_albedo`."""
    return model_albedo(target.values, target)
