"""The fiber BCSDF as a Mitsuba phase function (``usdfiber_fiber_phase``), the paper's Eq. 1-3.

In the anisotropic radiative transfer of Jakob et al. 2010 that the paper's Section 5 uses,
a voxel of fibers scatters with the fibers' normalized far field, in the frame of the
voxel's mean fiber direction ``omega_f`` and rotation ``psi_f``:

* the phase function (Eq. 2) at a point ``x``, for light arriving from ``omega_l`` and leaving
  towards ``omega_v`` (Mitsuba's ``mei.wi``) is the table's ``p(omega_l | omega_v)``, and the
  directional albedo ``Lambda(omega_v)`` of Eq. 1 rides along in the value: ``eval`` returns
  ``Lambda(omega_v) p(omega_l | omega_v)`` per steradian, exactly what the curve BSDF returns
  (:mod:`usdfiber.translators.mitsuba.fiber_bsdf`, whose lookups and sampler this reuses: the
  same slots, recoloured by dye and depth of shade), so the medium's own albedo is 1;
* the extinction (Eq. 3) is ``E(x) (W(phi'_v) / D) cos(theta'_v)`` with ``E = sum L D / V``
  the voxel's extinction across round fibers (:mod:`usdfiber.geometry.voxelize`) and
  ``(theta'_v, phi'_v)`` the direction in the fiber frame (``cos theta' = sin(omega,
  omega_f)``). Mitsuba's ``heterogeneous`` medium multiplies its density by the phase
  function's ``projected_area`` when the phase has the ``Microflake`` flag, and takes
  ``scale * max(density)`` as its majorant, without that factor: ``projected_area`` here is
  ``(W / D) cos(theta')``, at most 1 (``W <= D`` by definition of the circumscribed diameter,
  the bank clips it to 1), so ``max(E)`` bounds the extinction in every direction and
  delta tracking is unbiased.

Per voxel the phase knows one slot, the mean fiber direction and the cross-section axis
(psi applied), from :class:`~usdfiber.geometry.voxelize.VoxelGrid`; it finds the voxel of
``mei.p`` as Mitsuba's ``gridvolume`` does with ``filter_type = nearest`` (floor of the
position in voxel units), so density and phase always describe the same voxel.

What the phase leaves out, measured (bench/REPORT.md, "Volumetric cloth"): the spread of the
fiber directions within a voxel (``VoxelGrid.spread``). For an axially symmetric spread s
about the mean direction, Eq. 3's sum over the fibers gives ``sin^2 = (1 - s/2) sin^2(theta)
+ s cos^2(theta)`` in place of ``sin^2(theta)``; over the Figure 7 grids (yarns from their
density, 0.071 mm voxels) the extinction-weighted mean spread is 0.015 (about 7 degrees) and
the mean extinction seen by the camera changes by -0.25 %: below the renders' noise, so the
phase uses the mean direction. The mix of tables and colours is kept across voxels (each
voxel draws one fiber in proportion to length, :mod:`usdfiber.geometry.voxelize`), not within
one; the paper's figures have one fiber type and dye per prim, where the two are the same.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from usdfiber.geometry.voxelize import VoxelGrid
from usdfiber.translators.mitsuba.fiber_bank import FiberBank
from usdfiber.translators.mitsuba.fiber_bsdf import fiber_bsdf

__all__ = ["PLUGIN_NAME", "fiber_phase", "phase_class"]

PLUGIN_NAME = "usdfiber_fiber_phase"
_CLASSES: dict[str, type] = {}


def phase_class(mi: Any) -> type:
    """The phase function class for Mitsuba's active variant (defined once per variant)."""
    variant = mi.variant()
    if variant in _CLASSES:
        return _CLASSES[variant]
    import drjit as dr

    F = mi.Float
    U = mi.UInt32

    def _dev(kind: Any, arr: np.ndarray) -> Any:
        x = kind(np.ascontiguousarray(arr))
        dr.make_opaque(x)
        return x

    class FiberPhase(mi.PhaseFunction):
        """Tabulated fiber far field as an anisotropic, microflake-style phase function."""

        def __init__(self, props: Any) -> None:
            super().__init__(props)
            self.m_flags = mi.PhaseFunctionFlags.Anisotropic | mi.PhaseFunctionFlags.Microflake
            self._ready = False

        def set_voxels(self, bank: FiberBank, grid: VoxelGrid) -> None:
            """Give the phase function its slots and the grid's per-voxel frame and slot."""
            nx, ny, nz = grid.shape
            slot = grid.slot.reshape(-1).astype(np.int64)
            if slot.max(initial=-1) >= len(bank.slots):
                raise ValueError("voxel slot index out of range of the fiber bank")
            slot = np.where(slot < 0, 0, slot)
            axis = grid.axis.reshape(-1, 3).astype(np.float64)
            # The curve BSDF serves as the table lookup: one "segment" per voxel, whose
            # reference normal is the voxel's cross-section axis (psi already applied).
            self._bsdf = fiber_bsdf(mi, bank, slot, np.zeros(len(slot)), axis, pass_through=False)
            d = grid.direction.reshape(-1, 3)
            self._dir = mi.Vector3f(*(_dev(F, d[:, k].astype(np.float32)) for k in range(3)))
            self._axis = mi.Vector3f(*(_dev(F, axis[:, k].astype(np.float32)) for k in range(3)))
            self._slot = _dev(U, slot.astype(np.uint32))
            self._n_w = int(bank.slot_width.shape[1])
            self._width = _dev(F, bank.slot_width.reshape(-1))
            self._origin = [float(v) for v in grid.origin]
            self._inv_size = 1.0 / float(grid.voxel_size)
            self._res = (nx, ny, nz)
            self._ready = True

        # ---- per-voxel frame ---------------------------------------------------------------
        def _voxel(self, p: Any) -> Any:
            idx = []
            for k in range(3):
                u = dr.floor((p[k] - self._origin[k]) * self._inv_size)
                idx.append(U(dr.clip(u, 0.0, float(self._res[k] - 1))))
            return (idx[2] * self._res[1] + idx[1]) * self._res[0] + idx[0]

        def _frame(self, mei: Any, active: Any) -> tuple[Any, Any]:
            """(si for the BSDF lookup, voxel): a surface interaction whose shading frame has
            the voxel's fiber direction as ``t`` and its cross-section axis as ``s``."""
            if not self._ready:
                raise RuntimeError("usdfiber_fiber_phase has no voxels: build it with fiber_phase()")
            v = self._voxel(mei.p)
            t = dr.gather(mi.Vector3f, self._dir, v, active)
            s = dr.gather(mi.Vector3f, self._axis, v, active)
            si = dr.zeros(mi.SurfaceInteraction3f, dr.width(v))
            si.sh_frame = mi.Frame3f(s, t, dr.cross(s, t))
            si.wi = si.sh_frame.to_local(mei.wi)
            si.prim_index = v
            si.p = mei.p
            return si, v

        def projected_area(self, mei: Any, active: Any = True) -> Any:
            """``(W(phi'_v) / D) cos(theta'_v)`` <= 1: Eq. 3's direction factor (module docstring)."""
            v = self._voxel(mei.p)
            t = dr.gather(mi.Vector3f, self._dir, v, active)
            x = dr.gather(mi.Vector3f, self._axis, v, active)
            w = mei.wi
            ct = dr.safe_sqrt(1.0 - dr.square(dr.clip(dr.dot(w, t), -1.0, 1.0)))
            ph = dr.atan2(dr.dot(w, dr.cross(t, x)), dr.dot(w, x))
            u = ph / (2 * math.pi)
            u = (u - dr.floor(u)) * self._n_w
            j0 = dr.minimum(U(dr.floor(u)), self._n_w - 1)
            a = u - F(j0)
            j1 = dr.select(j0 + 1 == self._n_w, 0, j0 + 1)
            slot = dr.gather(U, self._slot, v, active)
            w0 = dr.gather(F, self._width, slot * self._n_w + j0, active)
            w1 = dr.gather(F, self._width, slot * self._n_w + j1, active)
            return dr.select(active, ((1.0 - a) * w0 + a * w1) * ct, 0.0)

        def max_projected_area(self) -> float:
            return 1.0

        def eval_pdf(self, ctx: Any, mei: Any, wo: Any, active: Any = True) -> tuple[Any, Any]:
            si, _ = self._frame(mei, active)
            val, pdf = self._bsdf.eval_pdf(mi.BSDFContext(), si, si.sh_frame.to_local(wo), active)
            return dr.select(active, val, 0.0), dr.select(active, pdf, 0.0)

        def sample(self, ctx: Any, mei: Any, sample1: Any, sample2: Any, active: Any = True) -> tuple[Any, Any, Any]:
            si, _ = self._frame(mei, active)
            bs, weight = self._bsdf.sample(mi.BSDFContext(), si, sample1, sample2, active)
            ok = active & (bs.pdf > 0)
            wo = si.sh_frame.to_world(bs.wo)
            return (dr.select(ok, wo, mi.Vector3f(0.0, 0.0, 1.0)), dr.select(ok, weight, 0.0),
                    dr.select(ok, bs.pdf, 0.0))

        def to_string(self) -> str:
            return f"FiberPhase[voxels={self._res if self._ready else None}]"

    _CLASSES[variant] = FiberPhase
    return FiberPhase


def fiber_phase(mi: Any, bank: FiberBank, grid: VoxelGrid) -> Any:
    """A ready phase function for ``grid``, whose voxel slots index ``bank``."""
    cls = phase_class(mi)
    ph = cls(mi.Properties())
    ph.set_voxels(bank, grid)
    return ph
