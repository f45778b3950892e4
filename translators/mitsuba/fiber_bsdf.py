"""The tabulated fiber BCSDF as a Mitsuba 3 BSDF plugin (``usdfiber_bcsdf``).

After :func:`register`, ``{"type": "usdfiber_bcsdf", "table": "fiber.npz", "mu_a": [r, g, b],
"diameter_um": 12, "psi_deg": 0}`` gives any Mitsuba scene one fiber table for all its
curves. The translator instead makes one instance (:func:`fiber_bsdf`) that serves every
fiber curve of a scene: per curve segment (Mitsuba's ``si.prim_index``) it knows the slot (cross-section table and colour), the rotation ``psi``
of the cross section and an azimuthal reference direction (a rotation-minimizing normal of
the curve).

Parts: :class:`FiberBcsdf` is the BCSDF itself (its tables on the device, the fiber frame,
the scattering probability ``q``, and ``eval``, ``pdf``, ``sample`` and the null transmission
in Mitsuba's calling convention); :class:`FamilyDevice` is one family of tables on the device
with its interpolation and its sampler. Both work for any Mitsuba variant. The Mitsuba
plugin (:func:`bsdf_class`) is a thin ``mi.BSDF`` subclass, made once per variant (a
Mitsuba class derives from the variant's own ``mi.BSDF``, and ``usdfiber render --device``
picks the variant after import), that forwards to its :attr:`~FiberBcsdf` ``fiber``; the
integrator reads the frame and ``q`` from there.

Far-field convention (``usdfiber.bcsdf``; Mitsuba's ``si.wi`` is the viewer direction
``omega_v``, the direction it samples or evaluates is the light direction ``omega_l``)
--------------------------------------------------------------------------------------
Fiber frame at a hit: ``t`` the curve's unit tangent (``si.sh_frame.t`` on Mitsuba's curves),
``x`` the segment's reference normal made perpendicular to ``t``, rotated by ``psi`` about
``t``; ``theta`` with ``sin theta = w . t``, ``phi`` the azimuth from ``x`` towards
``t x x``. ``eval`` returns the cosine-weighted BSDF Mitsuba expects, which for a far-field
fiber is

    sigma(omega_l, omega_v) / (W(phi_v) cos theta_v) = Lambda(omega_v) p(omega_l | omega_v)

(reciprocity of the scattering cross section ``sigma``), with no cosine to the tube's
normal: the far field does not depend on where across the tube the ray hit. ``sample``
draws ``omega_l`` from the undyed ``p0(. | omega_v)`` (:mod:`usdfiber.translators.mitsuba.fiber_bank`): the
weight ``Lambda p / p0`` is the albedo for an undyed fiber and near or below 1 for a dyed
one; its mean is the albedo.

Curves wider than the profile: a curve of width D (the circumscribed diameter) stands
for a profile that covers only ``W(phi_v)`` of it. A ray meeting the tube interacts with
probability ``q = W(phi_v) / D`` and otherwise passes straight on (a ``Null`` component),
so the pixel sees the fiber over ``W`` as it should; ``eval`` and ``pdf`` include the
factor ``q``. Shadow rays pass too, through ``eval_null_transmission`` (0 or 1, 1 with
probability ``1 - q``), but only integrators that call it honour it: ``volpath`` and our
``usdfiber_path`` (:mod:`usdfiber.translators.mitsuba.integrator`) do, and do not count null events
towards a path's depth. ``path`` tests shadow rays against the tube as if it were opaque
(a shadow as wide as ``D``) and counts pass-throughs as bounces. So the translator
(:mod:`usdfiber.translators.mitsuba.scene`) renders with ``usdfiber_path`` whenever a BSDF has the
``Null`` component, and with ``path`` otherwise (round fibers: ``W = D``, no pass-through).

Yarn far fields (:mod:`usdfiber.translators.mitsuba.yarn_far_field`) are slots of the round family
drawn on a curve of the yarn's bounding width: there ``q`` is the far field's coverage, the
fraction of rays meeting the tube that meet a fiber, a function of ``theta_v``.

Storage: per stored node one float16 4-vector (``Lambda p`` RGB and ``p0``, scaled by a power of
two per family, :class:`~usdfiber.translators.mitsuba.fiber_bank.Family`), converted to
float32 before any arithmetic: values carry a relative rounding error of at most 2^-11.
Extruded tables store ``theta_v >= 0``; a node below reads its mirror image. Slots are
grouped into pages of fewer than 2^32 values (Dr.Jit's array limit).
The sampler's CDFs are float32 integrals of the same rounded ``p0``, so sampling draws from
the density that ``pdf`` reports.
"""
from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from usdfiber.backend import configure_llvm

from usdfiber.translators.mitsuba.fiber_bank import Family, FiberBank, FiberSlot
from usdfiber.translators.mitsuba.plugins import VariantPlugin, forwarding_bsdf

configure_llvm()   # Dr.Jit reads the path of its LLVM once, when it is first imported
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402  (types resolve to the variant active when a method runs)

__all__ = ["PLUGIN_NAME", "FamilyDevice", "FiberBcsdf", "bsdf_class", "fiber_bsdf", "register"]

PLUGIN_NAME = "usdfiber_bcsdf"


def lerp_nodes(v: Any, v0: float, step: float, n: int) -> tuple[Any, Any]:
    """(k, w): the lower of n nodes v0 + i step around v (clamped) and the upper's weight."""
    if n == 1:
        return mi.UInt32(0), mi.Float(0.0)
    u = dr.clip((v - v0) / step, 0.0, float(n - 1))
    k = dr.minimum(mi.UInt32(dr.floor(u)), n - 2)
    return k, u - mi.Float(k)


def device_array(kind: Any, arr: np.ndarray) -> Any:
    """A device array that kernels read as data, not as baked-in constants."""
    x = kind(np.ascontiguousarray(arr))
    dr.make_opaque(x)
    return x


#: Dr.Jit arrays hold at most 2^32 entries: float16 node values are split into pages of
#: whole slots below that (a 2 deg non-round slot is 531M values: 8 slots a page).
PAGE_ENTRIES = (1 << 32) - 4


class FamilyDevice:
    """A family's arrays on the device, its interpolation and its sampler.

    ``release``: drop the family's host nodes slot by slot as they are copied (a render of
    2 deg tables cannot hold them twice); the :class:`Family` is then spent.
    """

    def __init__(self, fam: Family, release: bool = False) -> None:
        self.round = fam.round
        self.s = fam.step                   # bin size of the omega_l slices
        self.s_in = fam.incoming_step       # spacing of the omega_v nodes (a multiple of s)
        self.span = fam.theta_span
        n_ts, n_pv, h, w = fam.slice_shape
        self.n_tv, self.n_ts, self.n_pv, self.h, self.w = len(fam.theta_v), n_ts, n_pv, h, w
        self.mirrored, self.start = fam.mirrored, fam.stored_start
        self.theta0 = float(fam.theta_v[0])
        self.slice = h * w
        # Node storage: float16, gathered as one 4-vector (8 bytes) per node. Derived from the
        # variant's own types, so this holds for every backend (llvm, cuda).
        self._v4h = dr.float16_array_t(mi.Vector4f)
        f16 = dr.float16_array_t(mi.Float)
        # Per slot and stored node: (Lambda p) RGB and the sampling density of the slot's
        # table, interleaved so that one 4-wide gather reads both; float16 times a power of
        # two (Family.node_scale), which halves the bytes the random lookups pull through the
        # caches. Slots are grouped into pages of fewer than 2^32 values.
        per_slot = n_ts * n_pv * h * w * 4
        if per_slot > PAGE_ENTRIES:
            raise ValueError(f"one slot of a {fam.resolution_deg:g} deg family has {per_slot} node values, more than "
                             f"a device array holds (2^32)")
        per_page = PAGE_ENTRIES // per_slot
        n_slots = len(fam.nodes)
        self.pages = []
        # The sampler's CDFs, integrals of the same float16-rounded p0 that eval gathers,
        # copied table by table (one table's on the host at a time).
        n_marg, n_cond = n_ts * n_pv * (h - 1), n_ts * n_pv * h * (w - 1)
        n_tables = fam.n_tables
        if n_tables * n_cond > PAGE_ENTRIES:
            raise ValueError(f"the sampling tables of {n_tables} {fam.resolution_deg:g} deg tables have "
                             f"{n_tables * n_cond} entries, more than a device array holds (2^32)")
        if n_tables == 1:
            marg, cond = fam.table_cdfs(0)
            self.marg = device_array(mi.Float, marg.reshape(-1))
            self.cond = device_array(mi.Float, cond.reshape(-1))
        else:
            self.marg = dr.empty(mi.Float, n_tables * n_marg)
            self.cond = dr.empty(mi.Float, n_tables * n_cond)
            for t in range(n_tables):
                marg, cond = fam.table_cdfs(t)
                dr.scatter(self.marg, mi.Float(marg.reshape(-1)), dr.arange(mi.UInt32, n_marg) + t * n_marg)
                dr.scatter(self.cond, mi.Float(cond.reshape(-1)), dr.arange(mi.UInt32, n_cond) + t * n_cond)
                dr.eval(self.marg, self.cond)
                dr.sync_thread()
            dr.make_opaque(self.marg, self.cond)
        del marg, cond
        for first in range(0, n_slots, per_page):
            members = range(first, min(n_slots, first + per_page))
            if len(members) == 1 or not release:
                page = device_array(f16, np.concatenate([fam.nodes[k].reshape(-1) for k in members]))
            else:
                # Filled slot by slot in place: never the whole page on the host and the device
                # (uninitialized memory is committed as it is written, while the host's shrinks).
                page = dr.empty(f16, len(members) * per_slot)
                for m, k in enumerate(members):
                    src = f16(fam.nodes[k].reshape(-1))
                    dr.scatter(page, src, dr.arange(mi.UInt32, per_slot) + m * per_slot)
                    # Kernels run asynchronously: wait for this one before the host copy goes,
                    # or every slot's host nodes stay alive until the first render.
                    dr.eval(page)
                    dr.sync_thread()
                    del src
                    fam.nodes[k] = None
                dr.make_opaque(page)
            if release:
                for k in members:
                    fam.nodes[k] = None
            self.pages.append(page)
        self.per_page = per_page
        self.inv_scale = 1.0 / fam.node_scale
        self.slot_table = device_array(mi.UInt32, fam.slot_table.astype(np.uint32))
        # Per slot and stored incoming node: the albedo Lambda RGB, the integral of the slice's
        # Lambda p interpolant (what eval integrates to), for eval_diffuse_reflectance.
        self.albedo = device_array(mi.Float, fam.albedo.reshape(-1))

    def stored(self, k: Any) -> tuple[Any, Any]:
        """(stored theta_v node, flipped) of theta_v node ``k``: below the stored half a
        node is its mirror image (rows reversed)."""
        if not self.mirrored:
            return k, mi.Bool(False)
        flip = k < self.start
        return dr.select(flip, self.n_tv - 1 - k, k) - self.start, flip

    def _page_of(self, slot: Any) -> tuple[Any, Any]:
        """(page, slot within the page) of a slot."""
        if len(self.pages) == 1:
            return mi.UInt32(0), slot
        page = slot // self.per_page
        return page, slot - page * self.per_page

    def _gather(self, page: Any, index: Any, active: Any) -> Any:
        """The node 4-vector at ``index`` (4-vector units) of each lane's page."""
        if len(self.pages) == 1:
            return mi.Vector4f(dr.gather(self._v4h, self.pages[0], index, active))
        out = mi.Vector4f(0.0)
        for p, arr in enumerate(self.pages):
            m = active & (page == p)
            out = dr.select(m, mi.Vector4f(dr.gather(self._v4h, arr, index, m)), out)
        return out

    # -- coordinates --------------------------------------------------------------------------
    def _phi_v(self, ph_v: Any) -> Any:
        ph = ph_v - dr.floor(ph_v / (2 * math.pi)) * (2 * math.pi)
        return dr.select(ph < 0.5 * self.s_in, ph + 2 * math.pi, ph)

    def to_xy(self, th_l: Any, ph_l: Any, ph_v: Any) -> tuple[Any, Any, Any]:
        """(x, y, inside) of a light direction."""
        y = (th_l - self.theta0) / self.span
        if self.round:
            d = (ph_l - ph_v) / (2 * math.pi)
        else:
            d = (ph_l - 0.5 * self.s) / (2 * math.pi)
        x = d - dr.floor(d)
        inside = (y >= 0) & (y <= 1)
        return x, dr.clip(y, 0.0, 1.0), inside

    def from_xy(self, x: Any, y: Any, ph_v: Any) -> tuple[Any, Any]:
        """(theta_l, phi_l) of the point (x, y) of a slice: the inverse of :meth:`to_xy`."""
        th = self.theta0 + y * self.span
        ph = ph_v + x * 2 * math.pi if self.round else 0.5 * self.s + x * 2 * math.pi
        return th, ph

    # -- interpolation ------------------------------------------------------------------------
    def _incoming(self, th_v: Any, ph_v: Any) -> tuple[Any, Any, Any, Any]:
        """(kt, tt, kp, tp): the lower theta_v and phi_v nodes and the upper ones' weights."""
        kt, tt = lerp_nodes(th_v, self.theta0, self.s_in, self.n_tv)
        if self.round:
            return kt, tt, mi.UInt32(0), mi.Float(0.0)
        kp, tp = lerp_nodes(self._phi_v(ph_v), 0.5 * self.s_in, self.s_in, self.n_pv)
        return kt, tt, kp, tp

    def _cell(self, slot: Any, kt: Any, kp: Any, i: Any, j: Any, active: Any) -> list[list[Any]]:
        """The corners of cell (i, j) in each incoming slice around the viewer.

        [slice][corner]: slices (kt, kp), (kt, kp + 1), (kt + 1, kp), (kt + 1, kp + 1)
        (two for round tables), corners (i, j), (i + 1, j), (i, j + 1), (i + 1, j + 1);
        each a Vector4f ``node_scale * [f_r, f_g, f_b, p0]``. A mirrored slice reads its
        stored twin's rows ``H - 1 - j`` and ``H - 2 - j``.
        """
        page, loc = self._page_of(slot)
        out = []
        for dt in (0, 1):
            ks, flip = self.stored(kt + dt)
            r0 = dr.select(flip, self.h - 1 - j, j)
            r1 = dr.select(flip, self.h - 2 - j, j + 1)
            for dp in ((0,) if self.round else (0, 1)):
                sl = ((loc * self.n_ts + ks) * self.n_pv + (kp + dp)) * self.slice
                b0 = sl + r0 * self.w + i
                b1 = sl + r1 * self.w + i
                out.append([self._gather(page, b, active) for b in (b0, b0 + 1, b1, b1 + 1)])
        return out

    def _blend(self, cell: list[list[Any]], tt: Any, tp: Any, ax: Any, ay: Any) -> tuple[Any, Any]:
        """(Lambda p per channel, p0): the cell's corners interpolated at (ax, ay) in each
        slice, the slices linearly in theta_v and phi_v."""
        if self.round:
            ws = [1.0 - tt, tt]
        else:
            ws = [(1.0 - tt) * (1.0 - tp), (1.0 - tt) * tp, tt * (1.0 - tp), tt * tp]
        acc = mi.Vector4f(0.0)
        for wgt, (v00, v10, v01, v11) in zip(ws, cell):
            acc += wgt * dr.lerp(dr.lerp(v00, v10, ax), dr.lerp(v01, v11, ax), ay)
        acc *= self.inv_scale
        return mi.Color3f(acc.x, acc.y, acc.z), acc.w

    def eval_f(self, slot: Any, th_v: Any, ph_v: Any, x: Any, y: Any, active: Any) -> tuple[Any, Any]:
        """(Lambda p per channel, p0) in (x, y) density, interpolated like the sampler."""
        kt, tt, kp, tp = self._incoming(th_v, ph_v)
        fx = x * (self.w - 1)
        fy = y * (self.h - 1)
        i = dr.minimum(mi.UInt32(dr.floor(fx)), self.w - 2)
        j = dr.minimum(mi.UInt32(dr.floor(fy)), self.h - 2)
        return self._blend(self._cell(slot, kt, kp, i, j, active), tt, tp, fx - mi.Float(i), fy - mi.Float(j))

    # -- sampling -----------------------------------------------------------------------------
    @staticmethod
    def _segment(u: Any, n: int, v0: Any, v1: Any) -> Any:
        """Where in [0, 1] the integral of a density going linearly from v0 to v1 over
        one of n patches of the unit interval reaches u (Mitsuba's ``sample_segment``)."""
        non_const = dr.abs(v0 - v1) > 1e-4 * (v0 + v1)
        div = dr.select(non_const, v0 - v1, v0 + v1)
        t = u * (2.0 * n)
        t = dr.select(non_const, v0 - dr.safe_sqrt(dr.square(v0) + t * (v1 - v0)), t)
        return dr.clip(dr.select(div != 0, t / div, t), 0.0, 1.0)

    def sample_f(self, slot: Any, table: Any, th_v: Any, ph_v: Any, u: Any, u2: Any,
                 active: Any) -> tuple[Any, Any, Any, Any]:
        """(x, y, Lambda p per channel, p0 at (x, y)) of a light direction drawn from p0.

        One incoming node is picked with its interpolation weight (``u``) and its slice is
        sampled exactly, as Mitsuba's ``MarginalContinuous2D`` samples a bilinear
        interpolant: the row from the marginal CDF, y within it, the column from the
        row-interpolated conditional CDF, x within it. The density drawn from is then
        the interpolated p0 that eval reports (up to each slice's normalization,
        1 + O(2^-11) after rounding). Sampling one exact slice costs the lookups of one
        slice; the cell's corners are gathered once for the sampler and the result.
        """
        F, U = mi.Float, mi.UInt32
        kt, tt, kp, tp = self._incoming(th_v, ph_v)
        up_t = u < tt
        pick = dr.select(up_t, U(1), U(0))
        dt = pick
        dp = U(0)
        if not self.round:
            u = dr.select(up_t, u / dr.maximum(tt, 1e-12), (u - tt) / dr.maximum(1.0 - tt, 1e-12))
            dp = dr.select(u < tp, U(1), U(0))
            pick = 2 * dt + dp
        ks, flip = self.stored(kt + dt)
        sl = (table * self.n_ts + ks) * self.n_pv + kp + dp
        h1, w1 = self.h - 1, self.w - 1
        uy = dr.clip(u2.y, dr.epsilon(F), 1.0 - dr.epsilon(F))
        ux = dr.clip(u2.x, dr.epsilon(F), 1.0 - dr.epsilon(F))
        # Row: the marginal CDF of the slice (its last entry is the slice's total).
        m0 = sl * h1
        uy *= dr.gather(F, self.marg, m0 + (h1 - 1), active)
        row = dr.binary_search(0, h1 - 1, lambda k: dr.gather(F, self.marg, m0 + k, active) < uy)
        uy -= dr.gather(F, self.marg, m0 + row - 1, active & (row > 0))
        c0 = (sl * self.h + row) * w1
        r0 = dr.gather(F, self.cond, c0 + (w1 - 1), active)
        r1 = dr.gather(F, self.cond, c0 + (2 * w1 - 1), active)
        ay = self._segment(uy, h1, r0, r1)

        # Column: the conditional CDFs of the two rows, interpolated at y.
        def cdf(k: Any, m: Any) -> Any:
            return dr.lerp(dr.gather(F, self.cond, c0 + k, m), dr.gather(F, self.cond, c0 + w1 + k, m), ay)

        ux *= dr.lerp(r0, r1, ay)
        col = dr.binary_search(0, w1 - 1, lambda k: cdf(k, active) < ux)
        ux -= cdf(col - 1, active & (col > 0))
        # A mirrored slice was sampled in its stored twin: y reversed.
        row = dr.select(flip, h1 - 1 - row, row)
        ay = dr.select(flip, 1.0 - ay, ay)
        cell = self._cell(slot, kt, kp, col, row, active)
        # The picked slice's p0 along the cell's edges x = col and x = col + 1, at y.
        ends = []
        for a, b in ((0, 2), (1, 3)):
            va, vb = cell[0][a].w, cell[0][b].w
            for n in range(1, len(cell)):
                va = dr.select(pick == n, cell[n][a].w, va)
                vb = dr.select(pick == n, cell[n][b].w, vb)
            ends.append(dr.lerp(va, vb, ay) * self.inv_scale)
        ax = self._segment(ux, w1, ends[0], ends[1])
        rgb, p = self._blend(cell, tt, tp, ax, ay)
        return (F(col) + ax) / w1, (F(row) + ay) / h1, rgb, p


class FiberBcsdf:
    """The tabulated far-field fiber BCSDF (see the module docstring), for any Mitsuba variant.

    Its methods take Mitsuba's arguments (a ``SurfaceInteraction3f`` on a fiber curve, a
    ``BSDFContext``, local directions) and return what Mitsuba's ``BSDF`` interface returns;
    the plugin of :func:`bsdf_class` forwards to them. Without data (:meth:`set_fibers`, or
    ``from_properties``) every method that needs a table raises.
    """

    def __init__(self) -> None:
        self.families: list[FamilyDevice | None] = [None, None]   # [round, non-round]
        self.per_segment = True
        self.pass_through = False
        self._has_data = False

    @classmethod
    def from_properties(cls, props: Any) -> "FiberBcsdf":
        """Stand-alone use in any Mitsuba scene: one table for every fiber.

        Properties: ``table`` (a baked table file), ``mu_a`` (RGB absorption, 1/um,
        default 0), ``diameter_um`` (default: the baked diameter), ``psi_deg`` (rotation,
        default 0), ``pass_through`` (default true). The azimuthal reference is world +z
        made perpendicular to the tangent (world +x for fibers along z).
        """
        from usdfiber.bake.table import BcsdfTable

        table = BcsdfTable.load(str(props.get("table")))
        mu = props.get("mu_a", 0.0)
        mu = [float(mu)] * 3 if isinstance(mu, (int, float)) else [float(mu[i]) for i in range(3)]
        diameter = float(props.get("diameter_um", table.baked_diameter_um))
        sigma = tuple(float(x) for x in table.sigma_for(mu, diameter))
        bank = FiberBank.build([FiberSlot(table, sigma)])  # type: ignore[arg-type]
        fiber = cls()
        fiber.set_fibers(bank, np.zeros(1, np.int64), np.array([math.radians(float(props.get("psi_deg", 0.0)))]),
                         np.array([[0.0, 0.0, 1.0]]), pass_through=bool(props.get("pass_through", True)))
        fiber.per_segment = False
        return fiber

    # ---- data ----------------------------------------------------------------------------------
    def set_fibers(self, bank: FiberBank, seg_slot: np.ndarray, seg_psi: np.ndarray,
                   seg_ref: np.ndarray, pass_through: bool = True, release_host: bool = False) -> None:
        """Give the BSDF its tables and per-segment data (slot, psi in radians, reference).
        ``release_host``: drop the bank's host nodes as they are copied (the bank is spent)."""
        F, U = mi.Float, mi.UInt32
        n = len(seg_slot)
        if not (len(seg_psi) == n and seg_ref.shape == (n, 3)):
            raise ValueError("per-segment arrays differ in length")
        if n and (seg_slot.min() < 0 or seg_slot.max() >= len(bank.slots)):
            raise ValueError("segment slot index out of range")
        self.families = [(FamilyDevice(bank.families[r], release=release_host) if r in bank.families else None)
                         for r in (True, False)]
        self._slot_family = device_array(U, bank.slot_family.astype(np.uint32))
        self._slot_index = device_array(U, bank.slot_index.astype(np.uint32))
        self._n_w = int(bank.slot_width.shape[1])
        self._width = device_array(F, bank.slot_width.reshape(-1))
        self._seg_slot = device_array(U, seg_slot.astype(np.uint32))
        self._seg_psi = device_array(F, seg_psi.astype(np.float32))
        self._seg_ref = mi.Vector3f(*(device_array(F, np.ascontiguousarray(seg_ref[:, k], np.float32))
                                      for k in range(3)))
        self._n_c = int(bank.slot_coverage.shape[1])
        self._coverage = device_array(F, bank.slot_coverage.reshape(-1))
        self._has_width = bool(np.any(bank.slot_width < 0.999))
        self._has_coverage = bool(np.any(bank.slot_coverage < 0.999))
        self.pass_through = bool(pass_through) and (self._has_width or self._has_coverage)
        self._has_data = True

    def flags(self) -> tuple[list[Any], Any]:
        """(components, flags) for Mitsuba: glossy reflection and transmission, plus a
        ``Null`` component when rays may pass the tube (:attr:`pass_through`)."""
        Flags = mi.BSDFFlags
        glossy = Flags.GlossyReflection | Flags.GlossyTransmission | Flags.FrontSide | Flags.BackSide
        comps = [glossy]
        if self.pass_through:
            comps.append(Flags.Null | Flags.FrontSide | Flags.BackSide)
        flags = comps[0]
        for c in comps[1:]:
            flags = flags | c
        return comps, flags

    # ---- frame ---------------------------------------------------------------------------------
    def fiber_frame(self, si: Any, active: Any) -> tuple[Any, Any, Any, Any]:
        """(t, x, y, slot): the fiber frame at the hit, x rotated by psi."""
        if not self._has_data:
            raise RuntimeError("usdfiber_bcsdf has no table: give it a 'table' property "
                               "(a baked table file) or build it with fiber_bsdf()")
        seg = si.prim_index if self.per_segment else mi.UInt32(0)
        slot = dr.gather(mi.UInt32, self._seg_slot, seg, active)
        psi = dr.gather(mi.Float, self._seg_psi, seg, active)
        ref = dr.gather(mi.Vector3f, self._seg_ref, seg, active)
        t = dr.normalize(si.sh_frame.t)
        if not self.per_segment:
            ref = dr.select(dr.abs(t.z) > 0.9, mi.Vector3f(1.0, 0.0, 0.0), ref)
        r = dr.normalize(ref - dr.dot(ref, t) * t)
        b = dr.cross(t, r)
        c, s = dr.cos(psi), dr.sin(psi)
        x = c * r + s * b
        y = dr.cross(t, x)
        return t, x, y, slot

    @staticmethod
    def hit_is_finite(si: Any) -> Any:
        """Whether Mitsuba gave the hit a finite frame. Mitsuba 3.9.1 returns NaN tangents
        for hits within about N 2^-24 of the end of a shape of N segments (see
        curves.make_curve_shape); such a rare hit absorbs, rather than make a NaN pixel."""
        t, wi = si.sh_frame.t, si.wi
        return (dr.isfinite(t.x) & dr.isfinite(t.y) & dr.isfinite(t.z)
                & dr.isfinite(wi.x) & dr.isfinite(wi.y) & dr.isfinite(wi.z))

    @staticmethod
    def angles(w: Any, t: Any, x: Any, y: Any) -> tuple[Any, Any]:
        """(theta, phi) of the world direction ``w`` in the fiber frame (t, x, y)."""
        th = dr.asin(dr.clip(dr.dot(w, t), -1.0, 1.0))
        ph = dr.atan2(dr.dot(w, y), dr.dot(w, x))
        return th, ph

    def scatter_probability(self, slot: Any, th_v: Any, ph_v: Any, active: Any) -> Any:
        """Probability ``q`` that a ray meeting the tube meets the scatterer:
        ``W(phi_v) / D`` for a fiber, ``coverage(theta_v)`` for a yarn far field; 1 without
        pass-through."""
        F, U = mi.Float, mi.UInt32
        q = F(1.0)
        if not self.pass_through:
            return q
        if self._has_width:
            u = ph_v / (2 * math.pi)
            u = (u - dr.floor(u)) * self._n_w
            j0 = dr.minimum(U(dr.floor(u)), self._n_w - 1)
            a = u - F(j0)
            j1 = dr.select(j0 + 1 == self._n_w, 0, j0 + 1)
            base = slot * self._n_w
            w0 = dr.gather(F, self._width, base + j0, active)
            w1 = dr.gather(F, self._width, base + j1, active)
            q = (1.0 - a) * w0 + a * w1
        if self._has_coverage:
            j0, a = lerp_nodes(th_v, -0.5 * math.pi, math.pi / (self._n_c - 1), self._n_c)
            base = slot * self._n_c
            c0 = dr.gather(F, self._coverage, base + j0, active)
            c1 = dr.gather(F, self._coverage, base + j0 + 1, active)
            q = q * ((1.0 - a) * c0 + a * c1)
        return q

    def scatter_probability_at(self, si: Any, active: Any) -> Any:
        """``q`` (:meth:`scatter_probability`) at the hit ``si``, seen from ``si.wi``: the
        number ``eval``, ``pdf`` and ``sample`` use there."""
        t, x, y, slot = self.fiber_frame(si, active)
        th_v, ph_v = self.angles(si.to_world(si.wi), t, x, y)
        return self.scatter_probability(slot, th_v, ph_v, active)

    def _eval_pdf_world(self, si: Any, wl: Any, active: Any) -> tuple[Any, Any, Any]:
        """(Lambda p per channel, p0 per steradian, q) of the light direction ``wl`` (world)."""
        U = mi.UInt32
        t, x, y, slot = self.fiber_frame(si, active)
        wv = si.to_world(si.wi)
        th_v, ph_v = self.angles(wv, t, x, y)
        th_l, ph_l = self.angles(wl, t, x, y)
        fam_id = dr.gather(U, self._slot_family, slot, active)
        k = dr.gather(U, self._slot_index, slot, active)
        val = mi.Color3f(0.0)
        pdf = mi.Float(0.0)
        for fid, fam in enumerate(self.families):
            if fam is None:
                continue
            m = active & (fam_id == fid)
            xx, yy, inside = fam.to_xy(th_l, ph_l, ph_v)
            m = m & inside
            rgb, p = fam.eval_f(k, th_v, ph_v, xx, yy, m)
            jac = 1.0 / (2 * math.pi * fam.span * dr.maximum(dr.cos(th_l), 1e-7))
            val = dr.select(m, rgb * jac, val)
            pdf = dr.select(m, p * jac, pdf)
        q = self.scatter_probability(slot, th_v, ph_v, active)
        return val, pdf, q

    # ---- Mitsuba's BSDF interface --------------------------------------------------------------
    def eval(self, ctx: Any, si: Any, wo: Any, active: Any = True) -> Any:
        """``q Lambda p`` towards the light direction ``wo`` (local), cosine included."""
        Flags = mi.BSDFFlags
        if not ctx.is_enabled(Flags.GlossyReflection) and not ctx.is_enabled(Flags.GlossyTransmission):
            return mi.Color3f(0.0)
        active = active & self.hit_is_finite(si)
        val, _, q = self._eval_pdf_world(si, si.to_world(wo), active)
        return dr.select(active, q * val, 0.0)

    def pdf(self, ctx: Any, si: Any, wo: Any, active: Any = True) -> Any:
        """Density of :meth:`sample` drawing ``wo`` (times ``q`` when the ``Null`` component is enabled)."""
        active = active & self.hit_is_finite(si)
        _, pdf, q = self._eval_pdf_world(si, si.to_world(wo), active)
        q_eff = q if (self.pass_through and ctx.is_enabled(mi.BSDFFlags.Null, 1)) else 1.0
        return dr.select(active, q_eff * pdf, 0.0)

    def eval_pdf(self, ctx: Any, si: Any, wo: Any, active: Any = True) -> tuple[Any, Any]:
        """(:meth:`eval`, :meth:`pdf`) with one lookup."""
        active = active & self.hit_is_finite(si)
        val, pdf, q = self._eval_pdf_world(si, si.to_world(wo), active)
        q_eff = q if (self.pass_through and ctx.is_enabled(mi.BSDFFlags.Null, 1)) else 1.0
        return dr.select(active, q * val, 0.0), dr.select(active, q_eff * pdf, 0.0)

    def sample(self, ctx: Any, si: Any, sample1: Any, sample2: Any, active: Any = True) -> tuple[Any, Any]:
        """(BSDFSample3f, weight): a pass-through with probability ``1 - q`` (when the ``Null``
        component is enabled), else a light direction drawn from the undyed ``p0``."""
        Flags = mi.BSDFFlags
        F, U = mi.Float, mi.UInt32
        bs = dr.zeros(mi.BSDFSample3f)
        active = active & self.hit_is_finite(si)
        t, x, y, slot = self.fiber_frame(si, active)
        wv = si.to_world(si.wi)
        th_v, ph_v = self.angles(wv, t, x, y)
        q = self.scatter_probability(slot, th_v, ph_v, active)
        use_null = self.pass_through and ctx.is_enabled(Flags.Null, 1)
        use_scatter = ctx.is_enabled(Flags.GlossyReflection) or ctx.is_enabled(Flags.GlossyTransmission)
        u_pick0 = sample1
        if use_null and use_scatter:
            scatter = sample1 < q
            q_eff = q
            u_pick0 = dr.minimum(sample1 / dr.maximum(q, 1e-12), 0.99999994)
        elif use_null:
            scatter = mi.Bool(False)
            q_eff = F(1.0)
        else:
            scatter = mi.Bool(use_scatter)
            q_eff = F(1.0)

        fam_id = dr.gather(U, self._slot_family, slot, active)
        k = dr.gather(U, self._slot_index, slot, active)
        wl = mi.Vector3f(0.0)
        weight = mi.Color3f(0.0)
        pdf = F(0.0)
        ok = mi.Bool(False)
        for fid, fam in enumerate(self.families):
            if fam is None:
                continue
            m = active & scatter & (fam_id == fid)
            table = dr.gather(U, fam.slot_table, k, m)
            # Pick one incoming node with its interpolation weight and sample its slice
            # exactly: interpolating CDFs between nodes (as Mitsuba's parametric
            # distributions do) would not sample the interpolated density eval reports.
            xs, ys, rgb, p = fam.sample_f(k, table, th_v, ph_v, u_pick0, sample2, m)
            th_l, ph_l = fam.from_xy(xs, ys, ph_v)
            ct = dr.cos(th_l)
            d = ct * (dr.cos(ph_l) * x + dr.sin(ph_l) * y) + dr.sin(th_l) * t
            good = m & (p > 0)
            wl = dr.select(good, d, wl)
            weight = dr.select(good, rgb / dr.maximum(p, 1e-30), weight)
            pdf = dr.select(good, p / (2 * math.pi * fam.span * dr.maximum(ct, 1e-7)), pdf)
            ok |= good
        wo = si.to_local(wl)
        bs.wo = dr.select(ok, wo, dr.select(active, -si.wi, mi.Vector3f(0.0, 0.0, 1.0)))
        bs.pdf = dr.select(ok, q_eff * pdf, 1.0 - q_eff)
        bs.eta = 1.0
        bs.sampled_component = dr.select(ok, U(0), U(1))
        refl = mi.Frame3f.cos_theta(wo) * mi.Frame3f.cos_theta(si.wi) > 0
        glossy = dr.select(refl, U(int(Flags.GlossyReflection)), U(int(Flags.GlossyTransmission)))
        bs.sampled_type = dr.select(ok, glossy, U(int(Flags.Null)))
        passed = active & ~scatter & use_null
        w = dr.select(ok, weight, dr.select(passed, mi.Color3f(1.0), mi.Color3f(0.0)))
        valid = ok | passed
        bs.pdf = dr.select(valid, bs.pdf, 0.0)
        return bs, w

    def eval_diffuse_reflectance(self, si: Any, active: Any = True) -> Any:
        """The fiber's albedo ``Lambda(omega_v)`` seen from ``si.wi``, recoloured: the
        integral of :meth:`eval` over all light directions, without the pass-through
        probability ``q`` (what Mitsuba's ``aov`` integrator writes as ``albedo``).
        Interpolated between the incoming nodes like :meth:`eval`."""
        U = mi.UInt32
        active = active & self.hit_is_finite(si)
        t, x, y, slot = self.fiber_frame(si, active)
        th_v, ph_v = self.angles(si.to_world(si.wi), t, x, y)
        fam_id = dr.gather(U, self._slot_family, slot, active)
        k = dr.gather(U, self._slot_index, slot, active)
        out = mi.Color3f(0.0)
        for fid, fam in enumerate(self.families):
            if fam is None:
                continue
            m = active & (fam_id == fid)
            kt, tt, kp, tp = fam._incoming(th_v, ph_v)
            acc = mi.Color3f(0.0)
            for dt, wt in ((0, 1.0 - tt), (1, tt)):
                for dp, wp in (((0, 1.0),) if fam.round else ((0, 1.0 - tp), (1, tp))):
                    node = (k * fam.n_ts + fam.stored(kt + dt)[0]) * fam.n_pv + kp + dp
                    acc += (wt * wp) * dr.gather(mi.Color3f, fam.albedo, node, m)
            out = dr.select(m, acc, out)
        return out

    def eval_null_transmission(self, si: Any, active: Any = True) -> Any:
        """Transmission of a shadow ray through the tube: 0 or 1, 1 with probability 1 - q.

        ``usdfiber_path`` and ``volpath`` multiply a shadow ray's weight by this at every
        surface the ray meets and trace on while the weight is non-zero. Returning the
        expectation 1 - q itself would make every shadow ray cross every fiber in its way
        ((1 - q)^n never reaches 0): in a fiber mat that costs several times the whole
        render. A 0/1 value of the
        same expectation stops the ray at the first fiber that blocks it: the choice
        ``sample`` makes for camera and scattered rays (null or scatter). This interface
        has no sampler: the uniform number is a hash of the hit point, a continuous random
        variable of the path, so distinct hits draw independent-looking numbers.
        """
        if not self.pass_through:
            return mi.Color3f(0.0)
        active = active & self.hit_is_finite(si)
        q = self.scatter_probability_at(si, active)
        bx, by, bz = (dr.reinterpret_array(mi.UInt32, c) for c in (si.p.x, si.p.y, si.p.z))
        u = mi.sample_tea_float32(bx ^ ((bz << 16) | (bz >> 16)), by, 8)
        return mi.Color3f(dr.select(active & (u >= q), 1.0, 0.0))

    def __repr__(self) -> str:
        return f"FiberBcsdf[families={[f is not None for f in self.families]}, pass_through={self.pass_through}]"


def _define_plugin(mi: Any) -> type:
    class FiberBcsdfPlugin(forwarding_bsdf(mi)):
        """``usdfiber_bcsdf``: Mitsuba's view of a :class:`FiberBcsdf`."""

        def __init__(self, props: Any) -> None:
            super().__init__(props)
            self.fiber = FiberBcsdf.from_properties(props) if "table" in props else FiberBcsdf()
            self.m_components, self.m_flags = self.fiber.flags()

        def set_fibers(self, bank: FiberBank, seg_slot: np.ndarray, seg_psi: np.ndarray,
                       seg_ref: np.ndarray, pass_through: bool = True, release_host: bool = False) -> None:
            """:meth:`FiberBcsdf.set_fibers`, then the flags that follow from it."""
            self.fiber.set_fibers(bank, seg_slot, seg_psi, seg_ref, pass_through=pass_through,
                                  release_host=release_host)
            self.m_components, self.m_flags = self.fiber.flags()

        @property
        def model(self) -> FiberBcsdf:
            return self.fiber

        def eval_null_transmission(self, si: Any, active: Any = True) -> Any:
            return self.fiber.eval_null_transmission(si, active)

        def eval_diffuse_reflectance(self, si: Any, active: Any = True) -> Any:
            return self.fiber.eval_diffuse_reflectance(si, active)

        def to_string(self) -> str:
            return repr(self.fiber)

    return FiberBcsdfPlugin


_PLUGIN = VariantPlugin(PLUGIN_NAME, "bsdf", _define_plugin)


def bsdf_class(mi: Any) -> type:
    """The Mitsuba BSDF class for Mitsuba's active variant (defined once per variant): an
    ``mi.BSDF`` whose public attribute ``fiber`` is the :class:`FiberBcsdf` it forwards to."""
    return _PLUGIN.plugin_class(mi)


def register(mi: Any) -> type:
    """Register ``usdfiber_bcsdf`` with Mitsuba's active variant (once); returns the class."""
    return _PLUGIN.register(mi)


def fiber_bsdf(mi: Any, bank: FiberBank, seg_slot: Sequence[int] | np.ndarray, seg_psi: Sequence[float] | np.ndarray,
               seg_ref: np.ndarray, *, pass_through: bool = True, release_host: bool = False) -> Any:
    """A ready BSDF for curves whose segments use ``bank``'s slots (one per segment);
    ``release_host``: the bank's host nodes are dropped as they are copied (the bank is spent)."""
    cls = bsdf_class(mi)
    b = cls(mi.Properties())
    b.set_fibers(bank, np.asarray(seg_slot), np.asarray(seg_psi, dtype=np.float64), np.asarray(seg_ref, np.float64),
                 pass_through=pass_through, release_host=release_host)
    return b
