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
``theta_v >= 0`` only, and so does the bank: the renderer reads a node ``theta_v < 0`` as
the mirror (``theta_l -> -theta_l``) of its stored twin, so that the interpolation across
``theta_v = 0`` matches :class:`~usdfiber.bake.table.BcsdfTable` at half the memory.

Memory: a render keeps one float16 4-vector per stored node and slot (``Lambda p`` RGB and
p0), built a chunk of theta_v nodes at a time; at 2 deg a non-round slot is 45 x 181 x 90 x
181 nodes (1.06 GB), so four silk variants in three colours are 12.7 GB.

Round and non-round tables form two *families* (different parameterizations); tables of
one family share one resolution and one incoming node spacing (the ``omega_v`` nodes may be
coarser than the bins, :mod:`usdfiber.bake.grid`; other tables are resampled with their own
interpolation).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
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

    ``nodes``: per slot, (n_ts, n_pv, H, W, 4) float16, ``node_scale * [f_r, f_g, f_b, p0]``:
    ``f = Lambda p`` of the slot and ``p0`` the sampling density of its table (one 8-byte
    vector per node, what the renderer gathers); None once released (:meth:`release`).
    ``albedo``: (S, n_ts, n_pv, 3) float32, the integral of each stored slice of ``f`` over
    the unit square (the albedo it was normalized to; the float16 nodes integrate to it
    within their rounding, 2^-11). ``slot_table``: (S,) the table of each slot.
    ``theta_v``: all theta_v nodes (radians, increasing); when ``mirrored`` (every table of
    the family extruded, ``theta_symmetric``) only the nodes from :attr:`stored_start` on are
    stored, and node ``k < stored_start`` is node ``n - 1 - k`` with ``theta_l`` negated
    (its rows reversed): half the memory, the same interpolation. ``phi_v``: the phi_v nodes
    (one node for round tables; otherwise one turn plus the first node repeated), spaced
    ``incoming_deg`` (None: ``resolution_deg``, the bin size of the slices).
    """

    round: bool
    resolution_deg: float
    theta_v: np.ndarray
    phi_v: np.ndarray
    nodes: list[np.ndarray | None]
    albedo: np.ndarray
    slot_table: np.ndarray
    node_scale: float
    mirrored: bool = False
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

    @property
    def stored_start(self) -> int:
        """The first stored theta_v node (0 unless :attr:`mirrored`)."""
        return len(self.theta_v) // 2 if self.mirrored else 0

    @property
    def slice_shape(self) -> tuple[int, int, int, int]:
        """(n_ts, n_pv, H, W): the stored slices of one slot."""
        return (len(self.theta_v) - self.stored_start, len(self.phi_v), *self.slice_nodes)

    @property
    def slice_nodes(self) -> tuple[int, int]:
        """(H, W): the nodes of one slice."""
        h = int(round(math.pi / self.step))
        w = 2 * h + 1
        return h, w

    @property
    def n_tables(self) -> int:
        return int(self.slot_table.max()) + 1

    def table_slot(self, t: int) -> int:
        """The first slot of table ``t`` (whose fourth channel holds the table's p0)."""
        return int(np.flatnonzero(self.slot_table == t)[0])

    def stored(self, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(stored index, flipped) of theta_v nodes ``k`` (indices into :attr:`theta_v`)."""
        k = np.asarray(k, np.int64)
        if not self.mirrored:
            return k, np.zeros(k.shape, bool)
        n, s = len(self.theta_v), self.stored_start
        flip = k < s
        return np.where(flip, n - 1 - k, k) - s, flip

    def full(self, channel: slice | int) -> np.ndarray:
        """(S, n_tv, n_pv, H, W[, C]) float32: stored node values / node_scale on every theta_v
        node (mirrors filled in). For tests and small tables: it is the size the storage saves."""
        ks, flip = self.stored(np.arange(len(self.theta_v)))
        out = []
        for arr in self.nodes:
            if arr is None:
                raise ValueError("the family's host nodes were released")
            a = arr[ks][..., channel].astype(np.float32) / np.float32(self.node_scale)
            a[flip] = a[flip][:, :, ::-1]
            out.append(a)
        return np.stack(out)

    @property
    def f(self) -> np.ndarray:
        """(S, n_tv, n_pv, H, W, 3) float32 ``Lambda p`` on every node (:meth:`full`)."""
        return self.full(slice(0, 3))

    @property
    def pdf(self) -> np.ndarray:
        """(T, n_tv, n_pv, H, W) float32 p0 of each table on every node (:meth:`full`)."""
        every = self.full(3)
        return every[[self.table_slot(t) for t in range(self.n_tables)]]

    def sampling_pdf(self, t: int) -> np.ndarray:
        """(n_ts, n_pv, H, W) float32: table ``t``'s p0 on the stored nodes, rounded exactly as
        the nodes store it, so that the sampler draws from the density evaluation reports."""
        arr = self.nodes[self.table_slot(t)]
        if arr is None:
            raise ValueError("the family's host nodes were released")
        return arr[..., 3].astype(np.float32) / np.float32(self.node_scale)

    def table_cdfs(self, t: int) -> tuple[np.ndarray, np.ndarray]:
        """The sampler's tables of table ``t`` over its stored slices, integrals of
        :meth:`sampling_pdf` (float32, not normalized; a mirrored slice is sampled in its
        stored twin, y reversed).

        ``marg`` (n_ts n_pv, H - 1): per slice, the running integral over y of the row
        integrals (its last entry is the slice's total); ``cond`` (n_ts n_pv, H, W - 1): per
        row, the running integral over x of the row's linear interpolant. Those of Mitsuba's
        ``MarginalContinuous2D`` (continuous variant), summed in float64 one stored theta_v
        node at a time (no full-size float64 copy).
        """
        n_ts, n_pv, h, w = self.slice_shape
        marg = np.empty((n_ts, n_pv, h - 1), np.float32)
        cond = np.empty((n_ts, n_pv, h, w - 1), np.float32)
        v_all = self.sampling_pdf(t)
        for k in range(n_ts):
            v = v_all[k].astype(np.float64)
            c = np.cumsum((0.5 / (w - 1)) * (v[..., :-1] + v[..., 1:]), axis=-1)
            rows = c[..., -1]
            marg[k] = np.cumsum((0.5 / (h - 1)) * (rows[..., :-1] + rows[..., 1:]), axis=-1)
            cond[k] = c
        return marg.reshape(-1, h - 1), cond.reshape(-1, h, w - 1)

    def sampling_cdfs(self) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`table_cdfs` of every table, in table order: (T n_ts n_pv, H - 1) and
        (T n_ts n_pv, H, W - 1)."""
        parts = [self.table_cdfs(t) for t in range(self.n_tables)]
        return np.concatenate([m for m, _ in parts]), np.concatenate([c for _, c in parts])

    def release(self) -> None:
        """Drop the host node arrays (once the renderer has its copy): a render of 2 degree
        tables would otherwise hold them twice."""
        self.nodes = [None] * len(self.nodes)

    def nbytes(self) -> int:
        """Bytes the renderer keeps on the device: the float16 nodes, the sampler's float32
        tables (:meth:`sampling_cdfs`) and the per-node albedo."""
        n_ts, n_pv, h, w = self.slice_shape
        per = n_ts * n_pv
        table = len(self.nodes) * per * h * w * 4 * 2
        cdfs = 4 * self.n_tables * per * ((h - 1) + h * (w - 1))
        return int(table + cdfs + self.albedo.nbytes)


def bilinear_integral(values: np.ndarray) -> np.ndarray:
    """Integral over the unit square of the bilinear interpolant of node values (..., H, W)."""
    h, w = values.shape[-2:]
    wy = np.full(h, 1.0 / (h - 1))
    wy[[0, -1]] *= 0.5
    wx = np.full(w, 1.0 / (w - 1))
    wx[[0, -1]] *= 0.5
    return np.einsum("...hw,h,w->...", values, wy, wx)


def _native_nodes(rec: Recoloured, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """p at theta_v nodes ``k`` (indices into the family's theta_v, all nodes of a table on
    the same grid, mirrored for extruded tables) and their albedo: (len(k), n_pv, H, W, C)
    float32, (len(k), n_pv, C) float64. Wraps phi_l (and phi_v for non-round tables)."""
    g = rec.grid
    if g.theta_symmetric:
        # Node k < n is the mirror of table node n - 1 - k, with theta_l negated.
        n = g.n_theta_i
        flip = k < n
        ti = np.where(flip, n - 1 - k, k - n)
    else:
        flip = np.zeros(k.shape, bool)
        ti = k
    _, n_pi, n_b, n_po, n_c = rec.p.shape
    n_pv = n_pi if g.phi_invariant else n_pi + 1
    out = np.zeros((len(ti), n_pv, g.n_theta_o, n_po + 1, n_c), np.float32)
    rows = rec.table.band_start[ti][..., None].astype(np.int64) + np.arange(n_b)
    a, pi = np.meshgrid(np.arange(len(ti)), np.arange(n_pi), indexing="ij")
    out[a[..., None], pi[..., None], rows, :n_po] = rec.p[ti]
    if flip.any():
        out[flip] = out[flip][:, :, ::-1]
    alb = rec.albedo[ti].astype(np.float64)
    if not g.phi_invariant:
        out[:, n_pi] = out[:, 0]
        alb = np.concatenate([alb, alb[:, :1]], axis=1)
    out[:, :, :, n_po] = out[:, :, :, 0]
    return out, alb


def _resampled_nodes(rec: Recoloured, fam_round: bool, s: float, th_v: np.ndarray,
                     s_in: float) -> tuple[np.ndarray, np.ndarray]:
    """p (float32) at theta_v nodes ``th_v`` (radians) of a grid of bin size ``s`` and omega_v
    node spacing ``s_in`` (radians), with the table's interpolation."""
    n = int(round(math.pi / s))
    n_in = int(round(math.pi / s_in))
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
    p = rec.eval_p(TV, PV, TL, PL).astype(np.float32)
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


#: Host bytes of float32 node values built at once (a chunk of theta_v nodes): bounds the
#: transient memory of laying out a 2 degree table (35 MB per theta_v node at 2 deg, RGB).
CHUNK_BYTES = 256 << 20


def _scale_for(top: float) -> float:
    """The power of two that puts ``top`` in [2^14, 2^15) (1 when ``top`` is not positive):
    float16 (largest finite value 65504) keeps a factor of 2 of headroom, and values down to
    2^-29 of the largest stay normal numbers with float16's full precision. Peaky slices
    reach values of a few hundred on a 6 deg grid, tails go down to 1e-17: unscaled, the
    former could overflow on fine grids and the latter would lose their precision. A power
    of two is exact to apply and to undo."""
    if not (math.isfinite(top) and top > 0):
        return 1.0
    return math.ldexp(1.0, 15 - math.frexp(top)[1])


def _build_family(fam_round: bool, res_deg: float, tables: list[BcsdfTable], slots: list[FiberSlot],
                  incoming_deg: float | None = None) -> Family:
    """Lay out the slots of one family node by node (see :class:`Family`): the undyed p0 of
    each table, then each slot's recolouring, a chunk of theta_v nodes at a time, written
    straight into the float16 nodes (no float32 copy of every slot is kept)."""
    s = math.radians(res_deg)
    grid = Grid(res_deg, True, fam_round, incoming_deg)  # validates the resolution and the spacing
    s_in = grid.incoming_step
    mirrored = all(t.grid.theta_symmetric for t in tables)
    n_full = int(round(math.pi / s_in))
    th_nodes = -0.5 * math.pi + s_in * (np.arange(n_full) + 0.5)
    start = n_full // 2 if mirrored else 0
    stored = np.arange(start, n_full)
    n_t = int(round(math.pi / s))
    h, w = n_t, 2 * n_t + 1
    n_pv = 1 if fam_round else 2 * n_full + 1
    th_l = -0.5 * math.pi + s * (np.arange(n_t) + 0.5)
    cos_l = np.cos(th_l).astype(np.float32)[None, None, :, None]
    # The bilinear integral's weights (bilinear_integral), float32: node arrays stay float32.
    wy = np.full(h, 1.0 / (h - 1), np.float32)
    wy[[0, -1]] *= 0.5
    wx = np.full(w, 1.0 / (w - 1), np.float32)
    wx[[0, -1]] *= 0.5
    per_node = n_pv * h * w * 3 * 4
    chunk = max(1, CHUNK_BYTES // per_node)
    chunks = [stored[a:a + chunk] for a in range(0, len(stored), chunk)]

    def nodes(rec: Recoloured, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if (math.isclose(rec.grid.resolution_deg, res_deg)
                and math.isclose(rec.grid.incoming_spacing_deg, grid.incoming_spacing_deg)):
            return _native_nodes(rec, k)
        return _resampled_nodes(rec, fam_round, s, th_nodes[k], s_in)

    def table_pdf(t: BcsdfTable) -> np.ndarray:
        """p0 of table ``t`` on the stored nodes, each slice normalized (float32)."""
        rec0 = t.recolour(0.0)
        pdf = np.empty((len(stored), n_pv, h, w), np.float32)
        for k in chunks:
            p0, _ = nodes(rec0, k)
            d = p0.mean(axis=-1) * cos_l
            tot = np.einsum("abhw,h,w->ab", d, wy, wx, optimize=True)
            pdf[k - start] = np.where(tot[..., None, None] > 0, d / np.where(tot > 0, tot, 1.0)[..., None, None], 1.0)
        return pdf

    # Dyes only remove light: Lambda p <= p0 bin for bin, so p0's largest value sets the scale
    # (f's normalization to its own albedo can exceed it by the interpolation error: the
    # headroom of 2 covers that, and a rescale below covers anything more). One table's p0 is
    # held at a time (computed twice: a 2 deg table's is 0.5 GB).
    scale = _scale_for(max(float(table_pdf(t).max(initial=0.0)) for t in tables))
    slot_table = np.array([next(i for i, t in enumerate(tables) if t is sl.table) for sl in slots], np.int32)
    out: list[np.ndarray | None] = [None] * len(slots)
    albedo = np.empty((len(slots), len(stored), n_pv, 3), np.float32)
    for ti, t in enumerate(tables):
        pdf = table_pdf(t)
        for si in np.flatnonzero(slot_table == ti):
            rec = t.recolour(list(slots[si].sigma_a))
            arr = np.empty((len(stored), n_pv, h, w, 4), np.float16)
            for k in chunks:
                f, alb = nodes(rec, k)                      # p, float32, changed in place below
                f *= cos_l[..., None]
                tot = np.einsum("abhwc,h,w->abc", f, wy, wx, optimize=True).astype(np.float64)     # (n, n_pv, C)
                ok = tot > 0
                f *= np.where(ok, alb / np.where(ok, tot, 1.0), 0.0).astype(np.float32)[:, :, None, None, :]
                top = max(float(f.max(initial=0.0)), float(pdf[k - start].max(initial=0.0)))
                if top * scale >= 65504.0:
                    # Rare: rescale what is written so far (exact: a power of two).
                    new = _scale_for(top)
                    with np.errstate(all="ignore"):          # arr's unwritten chunks
                        for a in [*out, arr]:
                            if a is not None:
                                a *= np.float16(new / scale)
                    scale = new
                f *= np.float32(scale)
                arr[k - start, ..., :3] = f
                arr[k - start, ..., 3] = pdf[k - start] * np.float32(scale)
                # Each slice integrates to the albedo it was normalized to (within the float16
                # rounding of its nodes, 2^-11).
                albedo[si, k - start] = np.where(ok, alb, 0.0)
            out[si] = arr
            del rec
        del pdf
        # The bank now holds what the renderer reads; the table's cached recolourings (the
        # undyed one of a 2 deg table is 0.5 GB) would sit beside it for the whole render.
        t.forget_recolourings()
    phi_v = np.array([0.0]) if fam_round else 0.5 * s_in + s_in * np.arange(n_pv)
    return Family(round=fam_round, resolution_deg=res_deg, theta_v=th_nodes, phi_v=phi_v, nodes=out,
                  albedo=albedo, slot_table=slot_table, node_scale=scale, mirrored=mirrored,
                  incoming_deg=grid.incoming_deg)
