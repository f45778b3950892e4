"""The tabulated BCSDFs of a render, laid out for the renderer (:class:`FiberBank`).

A render needs, for every *slot* (one cross-section table recoloured for one dye, depth
of shade and diameter), the reciprocal form of the far-field scattering function

    f(omega_l | omega_v) = Lambda(omega_v) p(omega_l | omega_v)

(``omega_v`` towards the viewer, ``omega_l`` towards the light; see :mod:`usdfiber.bcsdf`),
and for every *table* the density used to sample ``omega_l``: the undyed ``p0(. | omega_v)``,
the same for every colour of that table. Dyes only remove light (each bin's photons are
weighted by ``exp(-sigma_a L) <= 1``), so ``Lambda p <= p0`` bin for bin and the sample
weight ``f / p0`` stays near or below 1 whatever the colour (each colour's interpolant is
normalized to its own albedo, exactly, so on coarse grids a weight may exceed 1 by the
interpolation error).

Both are stored on a grid of nodes at the table's bin centres and interpolated linearly in
``omega_v`` (theta_v, phi_v) and bilinearly in ``omega_l`` (theta_l, phi_l), which the
renderer samples exactly (the algorithm of Mitsuba's ``MarginalContinuous2D``, on the CDFs of
:meth:`Family.sampling_cdfs`). Coordinates of a slice:

* ``y`` in [0, 1] spans theta from the first to the last bin centre,
  ``theta = -pi/2 + s/2 + y (pi - s)`` for bin size ``s``; the polar caps beyond the outer
  centres (``1 - cos(s/2)`` of the sphere each) carry no density;
* ``x`` in [0, 1] spans phi over one turn from the first bin centre, ``phi = s/2 + 2 pi x``
  for tables of non-round profiles; for round ones (whose ``p`` depends on
  ``phi_l - phi_v`` only) ``x = (phi_l - phi_v) / (2 pi)`` modulo 1.

Node values are ``p cos(theta_l)`` (a density per unit theta and phi), normalized so that
each slice's bilinear interpolant integrates to 1 over the unit square; the density per
steradian is then ``value / (2 pi (pi - s) cos(theta_l))``. Tables of extruded fibers hold
``theta_v >= 0`` only: the bank mirrors them (``theta_l -> -theta_l``) so that the
interpolation across ``theta_v = 0`` matches :class:`~usdfiber.bake.table.BcsdfTable`.

Round and non-round tables form two *families* (different parameterizations); tables of
one family share one resolution and one incoming node spacing (the ``omega_v`` nodes may be
coarser than the bins, :mod:`usdfiber.bake.grid`; other tables are resampled with their own
interpolation).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import Sequence

import numpy as np

from usdfiber.bake.grid import Grid
from usdfiber.bake.table import BcsdfTable, Recoloured

__all__ = ["Family", "FiberBank", "FiberSlot", "bilinear_integral"]

_TWO_PI = 2.0 * math.pi
#: theta_v nodes of ``FiberBank.slot_coverage``: -90 to 90 degrees every 5 degrees.
COVERAGE_THETA = np.linspace(-0.5 * math.pi, 0.5 * math.pi, 37)


@dataclass(frozen=True)
class FiberSlot:
    """One table recoloured for one effective absorption (1/um at the baked size, RGB)."""

    table: BcsdfTable
    sigma_a: tuple[float, float, float]


@dataclass
class Family:
    """Node arrays of the tables of one parameterization (see the module docstring).

    ``pdf``: (T, n_tv, n_pv, H, W) float32, one undyed sampling density per table;
    ``f``: (S, n_tv, n_pv, H, W, 3) float32, ``Lambda p`` per slot and channel;
    ``slot_table``: (S,) the table (index into ``pdf``) of each slot.
    ``theta_v``: the theta_v nodes (radians, increasing); ``phi_v``: the phi_v nodes
    (one node for round tables; otherwise one turn plus the first node repeated), spaced
    ``incoming_deg`` (None: ``resolution_deg``, the bin size of the slices).
    """

    round: bool
    resolution_deg: float
    theta_v: np.ndarray
    phi_v: np.ndarray
    pdf: np.ndarray
    f: np.ndarray
    slot_table: np.ndarray
    incoming_deg: float | None = None

    @property
    def step(self) -> float:
        """Bin size of the slices (omega_l), radians."""
        return math.radians(self.resolution_deg)

    @property
    def incoming_step(self) -> float:
        """Spacing of the omega_v nodes, radians."""
        return math.radians(self.resolution_deg if self.incoming_deg is None else self.incoming_deg)

    @property
    def theta_span(self) -> float:
        """pi - s: the theta range the y coordinate spans."""
        return math.pi - self.step

    @cached_property
    def node_scale(self) -> float:
        """The power of two node values are multiplied by before rounding to float16.

        It puts the family's largest value in [2^14, 2^15): float16 (largest finite value
        65504) keeps a factor of 2 of headroom, and values down to 2^-29 of the largest stay
        normal numbers with float16's full precision. Peaky slices reach values of a few
        hundred on a 6 deg grid (up to ``4 (H - 1) (W - 1)`` in principle), tails go down
        to 1e-17: unscaled, the former could overflow on fine grids and the latter would
        lose their precision. A power of two is exact to apply and to undo.
        """
        top = max(float(self.f.max(initial=0.0)), float(self.pdf.max(initial=0.0)))
        if not (math.isfinite(top) and top > 0):
            return 1.0
        return math.ldexp(1.0, 15 - math.frexp(top)[1])

    def node_table(self) -> np.ndarray:
        """(S, n_tv, n_pv, H, W, 4) float16: ``node_scale * [f_r, f_g, f_b, p0]`` per slot and node.

        What the renderer stores and gathers (one 8-byte vector per node). Each value is
        rounded to nearest: a relative error of at most 2^-11 (4.9e-4) for values above
        ``2^-14 / node_scale``, an absolute one of at most ``2^-25 / node_scale`` below.
        ``p0`` (the slot's table's sampling density) rides along in the fourth channel.
        """
        s = self.node_scale
        out = np.empty(self.f.shape[:-1] + (4,), np.float16)
        out[..., :3] = self.f * s
        out[..., 3] = self.pdf[self.slot_table] * s
        return out

    def sampling_pdf(self) -> np.ndarray:
        """(T, n_tv, n_pv, H, W) float32: ``pdf`` rounded exactly as :meth:`node_table` stores it.

        The sampler is built from these values, so that it draws from the density that
        evaluation reports.
        """
        s = self.node_scale
        return (self.pdf * s).astype(np.float16).astype(np.float32) / np.float32(s)

    def sampling_cdfs(self) -> tuple[np.ndarray, np.ndarray]:
        """The sampler's tables, integrals of :meth:`sampling_pdf` (float32, not normalized).

        ``marg`` (T n_tv n_pv, H - 1): per slice, the running integral over y of the row
        integrals (its last entry is the slice's total); ``cond`` (T n_tv n_pv, H, W - 1): per
        row, the running integral over x of the row's linear interpolant. Those of Mitsuba's
        ``MarginalContinuous2D`` (continuous variant), summed in float64.
        """
        v = self.sampling_pdf().astype(np.float64)
        h, w = v.shape[-2:]
        v = v.reshape(-1, h, w)
        cond = np.cumsum((0.5 / (w - 1)) * (v[:, :, :-1] + v[:, :, 1:]), axis=-1)
        rows = cond[:, :, -1]
        marg = np.cumsum((0.5 / (h - 1)) * (rows[:, :-1] + rows[:, 1:]), axis=-1)
        return marg.astype(np.float32), cond.astype(np.float32)

    def nbytes(self) -> int:
        """Bytes the renderer keeps on the device: the float16 node table and the sampler's
        float32 tables (:meth:`sampling_cdfs`)."""
        t, n_tv, n_pv, h, w = self.pdf.shape
        table = self.f[..., 0].size * 4 * 2
        cdfs = 4 * t * n_tv * n_pv * ((h - 1) + h * (w - 1))
        return int(table + cdfs)


def bilinear_integral(values: np.ndarray) -> np.ndarray:
    """Integral over the unit square of the bilinear interpolant of node values (..., H, W)."""
    h, w = values.shape[-2:]
    wy = np.full(h, 1.0 / (h - 1))
    wy[[0, -1]] *= 0.5
    wx = np.full(w, 1.0 / (w - 1))
    wx[[0, -1]] *= 0.5
    return np.einsum("...hw,h,w->...", values, wy, wx)


def _band_to_rows(rec: Recoloured) -> np.ndarray:
    """The recoloured p on all theta_o rows: (n_ti, n_pi, n_to, n_po, C) float64."""
    t = rec.table
    g = t.grid
    n_ti, n_pi, n_b, n_po, n_c = rec.p.shape
    out = np.zeros((n_ti, n_pi, g.n_theta_o, n_po, n_c))
    rows = t.band_start[..., None].astype(np.int64) + np.arange(n_b)
    ti, pi = np.meshgrid(np.arange(n_ti), np.arange(n_pi), indexing="ij")
    out[ti[..., None], pi[..., None], rows] = rec.p
    return out


def _native_nodes(rec: Recoloured) -> tuple[np.ndarray, np.ndarray]:
    """p at the bank's nodes from a table on the same grid: (n_tv, n_pv, H, W, C), albedo.

    Mirrors theta_v for extruded tables, wraps phi_l (and phi_v for non-round tables).
    """
    g = rec.grid
    p = _band_to_rows(rec)
    alb = rec.albedo.astype(np.float64)
    if g.theta_symmetric:
        # Node k < n is the mirror of table node n - 1 - k, with theta_l negated.
        p = np.concatenate([p[::-1, :, ::-1], p], axis=0)
        alb = np.concatenate([alb[::-1], alb], axis=0)
    if not g.phi_invariant:
        p = np.concatenate([p, p[:, :1]], axis=1)
        alb = np.concatenate([alb, alb[:, :1]], axis=1)
    p = np.concatenate([p, p[:, :, :, :1]], axis=3)
    return p, alb


def _resampled_nodes(rec: Recoloured, fam_round: bool, s: float, s_in: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """p at the nodes of a grid of bin size ``s`` and omega_v node spacing ``s_in`` (radians,
    default ``s``), with the table's interpolation."""
    s_in = s if s_in is None else s_in
    n = int(round(math.pi / s))
    n_in = int(round(math.pi / s_in))
    th_v = -0.5 * math.pi + s_in * (np.arange(n_in) + 0.5)
    th_l = -0.5 * math.pi + s * (np.arange(n) + 0.5)
    if fam_round:
        ph_v = np.array([0.0])
        x = np.linspace(0.0, 1.0, 2 * n + 1)
        ph_l = x * _TWO_PI                                  # relative to phi_v = 0
    else:
        ph_v = 0.5 * s_in + s_in * np.arange(2 * n_in + 1)
        ph_l = 0.5 * s + np.linspace(0.0, _TWO_PI, 2 * n + 1)
    TV, PV, TL, PL = np.meshgrid(th_v, ph_v, th_l, ph_l, indexing="ij")
    if fam_round:
        PL = PL + PV
    p = rec.eval_p(TV, PV, TL, PL)
    alb = rec.albedo_at(th_v[:, None] + 0 * ph_v[None, :], ph_v[None, :] + 0 * th_v[:, None])
    return p, alb


@dataclass
class FiberBank:
    """Every slot of a render, grouped into round and non-round families.

    ``slots``: the slots in the order the renderer indexes them. ``resolution_deg``: the
    node spacing of each family (default: the finest resolution among its tables).
    """

    slots: Sequence[FiberSlot]
    families: dict[bool, Family] = field(default_factory=dict)
    slot_family: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    slot_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    slot_width: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.float32))
    slot_coverage: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.float32))

    @classmethod
    def build(cls, slots: Sequence[FiberSlot], resolution_deg: dict[bool, float] | None = None) -> "FiberBank":
        """Lay out ``slots`` (``resolution_deg``: {round?: degrees} to override)."""
        if not slots:
            raise ValueError("a fiber bank needs at least one slot")
        bank = cls(list(slots))
        tables: dict[bool, list[BcsdfTable]] = {True: [], False: []}
        for sl in bank.slots:
            fam = sl.table.grid.phi_invariant
            if not any(t is sl.table for t in tables[fam]):
                tables[fam].append(sl.table)
        n = len(bank.slots)
        bank.slot_family = np.zeros(n, np.int32)
        bank.slot_index = np.zeros(n, np.int32)
        for fam_round, tabs in tables.items():
            if not tabs:
                continue
            res = (resolution_deg or {}).get(fam_round) or min(t.grid.resolution_deg for t in tabs)
            members = [i for i, sl in enumerate(bank.slots) if sl.table.grid.phi_invariant == fam_round]
            bank.families[fam_round] = _build_family(fam_round, float(res), tabs,
                                                     [bank.slots[i] for i in members],
                                                     _family_incoming(float(res), tabs))
            for k, i in enumerate(members):
                bank.slot_family[i] = 0 if fam_round else 1
                bank.slot_index[i] = k
        # W(phi) / circumscribed diameter: the fraction of a curve's width the profile covers,
        # on one phi grid for all slots (a yarn far field has a constant width).
        n_w = max(len(sl.table.arrays["width"]) for sl in bank.slots)
        bank.slot_width = np.stack([_width_row(sl, n_w) for sl in bank.slots]).astype(np.float32)
        # coverage(theta_v): 1 for fibers (their profile is extruded); for a yarn far field the
        # fraction of the rays meeting its tube that meet a fiber (yarn_far_field.py).
        bank.slot_coverage = np.stack([
            np.asarray(sl.table.coverage_at(COVERAGE_THETA), np.float64) if hasattr(sl.table, "coverage_at")
            else np.ones(len(COVERAGE_THETA)) for sl in bank.slots]).clip(0.0, 1.0).astype(np.float32)
        return bank

    def nbytes(self) -> int:
        return (sum(f.nbytes() for f in self.families.values()) + int(self.slot_width.nbytes)
                + int(self.slot_coverage.nbytes))


def _width_row(slot: FiberSlot, n_w: int) -> np.ndarray:
    """W(phi) / D of a slot at phi = 2 pi j / n_w (periodic linear resampling if needed)."""
    w = np.asarray(slot.table.arrays["width"], np.float64) / slot.table.baked_diameter_um
    if len(w) != n_w:
        w = np.interp(_TWO_PI * np.arange(n_w) / n_w, _TWO_PI * np.arange(len(w)) / len(w), w, period=_TWO_PI)
    return np.clip(w, 0.0, 1.0)


def _family_incoming(res_deg: float, tables: list[BcsdfTable]) -> float:
    """The omega_v node spacing of a family of bin size ``res_deg``: the finest of its
    tables' incoming spacings when that is a valid one for the family's bins, else the bins'."""
    d = min(t.grid.incoming_spacing_deg for t in tables)
    try:
        return Grid(res_deg, True, False, d).incoming_spacing_deg
    except ValueError:
        return res_deg


def _build_family(fam_round: bool, res_deg: float, tables: list[BcsdfTable], slots: list[FiberSlot],
                  incoming_deg: float | None = None) -> Family:
    s = math.radians(res_deg)
    grid = Grid(res_deg, True, fam_round, incoming_deg)  # validates the resolution and the spacing
    s_in = grid.incoming_step

    def nodes(rec: Recoloured) -> tuple[np.ndarray, np.ndarray]:
        if (math.isclose(rec.grid.resolution_deg, res_deg)
                and math.isclose(rec.grid.incoming_spacing_deg, grid.incoming_spacing_deg)):
            return _native_nodes(rec)
        return _resampled_nodes(rec, fam_round, s, s_in)

    n_t = int(round(math.pi / s))
    th_l = -0.5 * math.pi + s * (np.arange(n_t) + 0.5)
    cos_l = np.cos(th_l)[None, None, :, None]
    th_nodes = -0.5 * math.pi + s_in * (np.arange(int(round(math.pi / s_in))) + 0.5)
    pdfs = []
    for t in tables:
        p0, _ = nodes(t.recolour(0.0))
        d = p0.mean(axis=-1) * cos_l
        tot = bilinear_integral(d)
        pdfs.append(np.where(tot[..., None, None] > 0, d / np.where(tot > 0, tot, 1.0)[..., None, None], 1.0))
    fs, slot_table = [], []
    for sl in slots:
        rec = sl.table.recolour(list(sl.sigma_a))
        p, alb = nodes(rec)
        d = p * cos_l[..., None]
        tot = bilinear_integral(np.moveaxis(d, -1, 0))               # (C, n_tv, n_pv)
        tot = np.moveaxis(tot, 0, -1)
        norm = np.where(tot > 0, alb / np.where(tot > 0, tot, 1.0), 0.0)
        fs.append((d * norm[:, :, None, None, :]).astype(np.float32))
        slot_table.append(next(i for i, t in enumerate(tables) if t is sl.table))
    n_pv = pdfs[0].shape[1]
    phi_v = np.array([0.0]) if fam_round else 0.5 * s_in + s_in * np.arange(n_pv)
    return Family(round=fam_round, resolution_deg=res_deg, theta_v=th_nodes, phi_v=phi_v,
                  pdf=np.stack(pdfs).astype(np.float32), f=np.stack(fs), slot_table=np.array(slot_table, np.int32),
                  incoming_deg=grid.incoming_deg)
