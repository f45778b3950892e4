"""The tabulated far-field BCSDF of one fiber cross-section variant (:class:`BcsdfTable`).

Far-field convention (see :mod:`usdfiber.bcsdf` for the renderer's side)
--------------------------------------------------------------------------
Fiber frame: t (the fiber axis) is +z, the cross section lies in the xy plane. A direction
is (theta, phi): ``theta`` is the angle from the plane normal to t (sin theta = w . t),
in [-pi/2, pi/2]; ``phi`` the azimuth in that plane from the profile's +x axis towards +y,
in [0, 2 pi). ``omega_i`` points towards the light, ``omega_o`` towards the viewer: both
point away from the fiber. All angles of this module's API are in RADIANS; the header
and the command line use degrees. A fiber rotated by ``psi`` about t sees ``phi - psi``
(every method takes ``psi``).

The table holds, for one cross section:

* ``W(phi)``: the width of the profile's shadow seen from azimuth phi (um at the baked
  size). Per unit length a beam from (theta, phi) meets the area ``W(phi) cos(theta)``.
* ``Lambda(omega_i)``: the albedo, the fraction of the photons meeting that area that
  leave the fiber (1 without absorption, up to photons stopped by ``max_bounces``).
* ``p(omega_o | omega_i)``: where they leave, per steradian; it integrates to 1 over the
  sphere. No cosine is folded into any of them.

The scattering cross section ``sigma(omega_i, omega_o) = W(phi_i) cos(theta_i)
Lambda(omega_i) p(omega_o | omega_i)`` is symmetric (reciprocity).

Grid (:mod:`usdfiber.bake.grid`)
--------------------------------
With a resolution of ``d`` degrees a bin's value is the average of ``p`` over the bin;
incoming directions are nodes at bin centres, theta_i >= 0 only for extruded fibers and one
phi_i node for rotationally symmetric profiles. The header's ``incoming`` says how a node
was traced: ``"centre"`` (the default, as in the paper): the light comes from the node's
direction, so values are point samples in omega_i and bin averages in omega_o; ``"box"``:
the photons of a node come from its whole bin (weighted by ``W(phi) cos(theta)``), so values
are averages over both bins and ``<W cos> Lambda p`` is symmetric bin for bin.

Absorption (:mod:`usdfiber.bake.absorption`)
--------------------------------------------
Photons are traced once, without absorption; at ``K`` absorption levels the table keeps
each bin's mass ``F_k`` and mean path length ``Lbar_k``; between levels ``log F`` is
interpolated by cubic Hermite polynomials. :meth:`BcsdfTable.recolour` evaluates this on all
cores in float32 (:mod:`usdfiber.bake.recolour`; it agrees with the float64 numpy reference to
about 1e-6).

Diameter: the bake traces the profile scaled to a circumscribed diameter of
``baked_diameter_um`` (1 um). All path lengths scale with the diameter, so a fiber of
diameter ``D`` with absorption ``mu_a`` (1/um) is the baked profile with
``sigma_a = mu_a * D / baked_diameter_um``: pass ``sigma_a=mu_a`` and
``diameter_scale=D / baked_diameter_um`` (or use :meth:`BcsdfTable.sigma_for`).

Storage, lookup and sampling
----------------------------
The arrays of a table file: :mod:`usdfiber.bake.storage` (the container:
:mod:`usdfiber.table_format`). Evaluation at arbitrary directions: :mod:`usdfiber.bake.lookup`.
Sampling needs no stored array: :meth:`Recoloured.cdfs` builds, per incoming node, the
marginal CDF over the band's theta_o rows and the conditional CDFs over phi_o from the
(recoloured) bin masses, and :meth:`Recoloured.sample` draws from them
(:mod:`usdfiber.bake.sampler`). Tables are made by :func:`usdfiber.bake.assembly.assemble`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from usdfiber.bake import compression
from usdfiber.bake import recolour as kernels
from usdfiber.bake.absorption import level_bracket, log_interpolate
from usdfiber.bake.grid import Grid
from usdfiber.bake.lookup import eval_directional, eval_incoming
from usdfiber.bake.sampler import outgoing_cdfs, sample_outgoing
from usdfiber.bake.storage import TableLayoutError, check_layout, read_table_file, write_table_file

__all__ = ["BcsdfTable", "Recoloured"]

_TWO_PI = 2.0 * math.pi
#: Recolourings a table keeps for reuse: at most this many, and this many bytes of p.
_RECOLOUR_CACHE_ENTRIES = 8
_RECOLOUR_CACHE_BYTES = 1 << 30


def _channels(x: np.ndarray, scalar: bool) -> np.ndarray:
    return x[..., 0] if scalar else x


@dataclass
class Recoloured:
    """A table recoloured for one absorption: p and Lambda per colour channel (float32).

    ``p``: (n_ti, n_pi, B, n_po, C) per steradian, each slice integrating to 1 over the band;
    ``albedo``: (n_ti, n_pi, C); ``sigma_a``: the effective absorption per channel (1/um at
    the baked size) they were computed for.
    """

    table: "BcsdfTable"
    sigma_a: np.ndarray
    p: np.ndarray
    albedo: np.ndarray
    _cdfs: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)

    @property
    def grid(self) -> Grid:
        return self.table.grid

    def eval_p(self, theta_i, phi_i, theta_o, phi_o, *, psi: float = 0.0, interp_i: str = "linear",
               interp_o: str = "bilinear") -> np.ndarray:
        """p(omega_o | omega_i) per steradian, shape (..., C). Radians; see BcsdfTable.eval_p."""
        return eval_directional(self.grid, self.table.band_start, self.p, theta_i, phi_i,
                                theta_o, phi_o, psi, interp_i, interp_o)

    def albedo_at(self, theta_i, phi_i, *, psi: float = 0.0, interp_i: str = "linear") -> np.ndarray:
        """Lambda(omega_i), shape (..., C)."""
        return eval_incoming(self.grid, self.albedo, theta_i, phi_i, psi, interp_i)

    # ---- sampling ------------------------------------------------------------------------
    def cdfs(self) -> tuple[np.ndarray, np.ndarray]:
        """(marginal, conditional) CDFs for sampling omega_o, computed once
        (:func:`~usdfiber.bake.sampler.outgoing_cdfs` of the channel-mean p)."""
        if self._cdfs is None:
            self._cdfs = outgoing_cdfs(self.p, self.table.domega_band())
        return self._cdfs

    def sample(self, theta_i, phi_i, u: np.ndarray, *, psi: float = 0.0,
               interp_i: str = "linear") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Draw omega_o from the channel-mean p(. | omega_i); ``u`` (..., 5) uniform numbers.

        Returns (theta_o, phi_o, pdf) with the pdf per steradian of the whole mixture, which
        equals the channel mean of ``eval_p(..., interp_o="nearest")``
        (:func:`~usdfiber.bake.sampler.sample_outgoing`).
        """
        return sample_outgoing(self, theta_i, phi_i, u, psi=psi, interp_i=interp_i)


#: Arrays (of either layout) that hold integers; every other array holds floats.
_INTEGER_ARRAYS = frozenset({"band_start", "photons", "basis_groups", "basis_codec"})
#: Error estimates, infinite for a direction that no light leaves: reported, never rendered.
_DIAGNOSTIC_ARRAYS = frozenset({"rel_error", "compression_error"})
#: Arrays whose values cannot be negative.
_NON_NEGATIVE_ARRAYS = frozenset({"p", "p_scale", "lbar", "albedo", "width", "rel_error", "photons",
                                  "compression_error"})


def _all_finite(a: np.ndarray) -> bool:
    """Whether every value of ``a`` is finite, a slice at a time (no table-sized mask)."""
    if a.ndim < 2:
        return bool(np.all(np.isfinite(a)))
    return all(bool(np.all(np.isfinite(part))) for part in a)


# ---------------------------------------------------------------------------------------------
# The table
# ---------------------------------------------------------------------------------------------

@dataclass
class BcsdfTable:
    """The tabulated BCSDF of one cross-section variant (layout: :mod:`usdfiber.bake.storage`)."""

    header: dict[str, Any]
    arrays: dict[str, np.ndarray]
    path: str | None = None
    _recoloured: dict = field(default_factory=dict, repr=False)
    _domega_band: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        where = self.path or "table"
        if self.compressed:
            # The codec's bytes are decoded once, on load (checked against the header).
            self.grid = compression.check_layout(self.header, self.arrays, where)
            if "basis" not in self.arrays:
                self.arrays["basis"] = compression.decode_basis(self.header, self.arrays, where)
            compression.check_layout(self.header, self.arrays, where)
        else:
            self.grid = check_layout(self.header, self.arrays, where)

    # ---- I/O -------------------------------------------------------------------------------
    @classmethod
    def load(cls, path: str | Path) -> "BcsdfTable":
        """Read and verify a table file (TableError for damaged files, TableLayoutError)."""
        from usdfiber.table_format import TableError

        try:
            header, arrays = read_table_file(path)
            table = cls(header=header, arrays=arrays, path=str(path))   # checks the layout
            table._check_values()
        except (TableError, TableLayoutError):
            raise
        except (AttributeError, TypeError, KeyError, ValueError, IndexError) as exc:
            # Checksums that hold over a header or arrays that do not describe a usable table
            # (a crafted or hand-edited file): one line, never a traceback, never used.
            reason = " ".join(str(exc).split()) or type(exc).__name__
            raise TableError(str(path), f"not a usable table: {reason[:300]}") from None
        return table

    def _check_values(self) -> None:
        """Raise ValueError where the values that the layout check (array shapes, grid) does not
        cover are unusable: a NaN, infinite or negative albedo, a baked diameter, index or
        roughness that is not a finite positive number, absorption levels that are not finite,
        arrays of the wrong kind of number, floats (error estimates aside) that are NaN or
        infinite, negative p, p scales, path lengths, albedos, widths, errors or photons."""
        for name, a in self.arrays.items():
            kinds = "iu" if name in _INTEGER_ARRAYS else "f"
            if a.dtype.kind not in kinds:
                expected = "integers" if kinds == "iu" else "floats"
                raise ValueError(f"array {name} has dtype {a.dtype}, expected {expected}")
            if kinds == "f" and name not in _DIAGNOSTIC_ARRAYS and not _all_finite(a):
                raise ValueError(f"array {name} holds NaN or infinite values")
            if name in _NON_NEGATIVE_ARRAYS and a.size and a.min() < 0:
                raise ValueError(f"array {name} holds negative values")
        if self.arrays["width"].ndim != 1 or self.arrays["width"].size == 0:
            raise ValueError(f"array width has shape {self.arrays['width'].shape}, expected (n,) with n >= 1")
        if not (0 < self.baked_diameter_um < math.inf):
            raise ValueError(f"baked_diameter_um is {self.header.get('baked_diameter_um')!r}")
        for name in ("eta", "beta_deg"):
            if name in self.header and not math.isfinite(float(self.header[name])):
                raise ValueError(f"{name} is {self.header[name]!r}")
        if not np.all(np.isfinite(np.asarray(self.levels, dtype=np.float64))):
            raise ValueError("the absorption levels are not finite numbers")

    def save(self, path: str | Path) -> dict[str, Any]:
        """Write the table atomically (compressed); returns the header written."""
        if self.compressed:   # the codec's bytes, not the decoded basis; zip adds nothing to them
            arrays = {k: v for k, v in self.arrays.items() if k != "basis"}
            written = write_table_file(path, self.header, arrays, compress=False)
        else:
            written = write_table_file(path, self.header, self.arrays)
        self.header = written
        self.path = str(path)
        return written

    def compress(self, bound: float = compression.DEFAULT_BOUND, *, rank: int | None = None,
                 progress: Any = None) -> "BcsdfTable":
        """This table in the compact, recolourable layout of :mod:`usdfiber.bake.compression`,
        p within ``bound`` relative L2 per direction at every checked absorption
        (CompressionError when it cannot be)."""
        header, arrays = compression.compress_table(self, bound, rank=rank, progress=progress)
        return BcsdfTable(header=header, arrays=arrays)

    # ---- metadata --------------------------------------------------------------------------
    @property
    def compressed(self) -> bool:
        """Whether the table is in the absorption-basis layout (:mod:`usdfiber.bake.compression`)."""
        lay = self.header.get("layout", {})
        return isinstance(lay, dict) and lay.get("name") == compression.LAYOUT

    @property
    def levels(self) -> np.ndarray:
        return self.arrays["levels"]

    @property
    def band_start(self) -> np.ndarray:
        return self.arrays["band_start"]

    @property
    def n_band(self) -> int:
        return int(self.arrays["basis" if self.compressed else "p"].shape[3])

    @property
    def geometry_key(self) -> str:
        return str(self.header.get("geometry_key", ""))

    @property
    def variant(self) -> int:
        return int(self.header.get("variant", 0))

    @property
    def baked_diameter_um(self) -> float:
        return float(self.header.get("baked_diameter_um", 1.0))

    @property
    def rel_error(self) -> np.ndarray:
        """Estimated relative L2 error of p per incoming direction (at sigma_a = 0)."""
        return self.arrays["rel_error"]

    def sigma_for(self, mu_a_per_um: float | Sequence[float], diameter_um: float) -> np.ndarray:
        """Effective absorption of a fiber of ``diameter_um`` with ``mu_a`` (1/um)."""
        return np.asarray(mu_a_per_um, dtype=np.float64) * (float(diameter_um) / self.baked_diameter_um)

    def domega_band(self) -> np.ndarray:
        """Solid angle of each band row's bins, (n_ti, n_pi, B)."""
        if self._domega_band is None:
            dom = self.grid.solid_angles()
            rows = self.band_start[..., None].astype(np.int64) + np.arange(self.n_band)
            self._domega_band = dom[rows]
        return self._domega_band

    def nbytes(self) -> int:
        """Bytes of the arrays in memory (the file is compressed on top)."""
        return int(sum(a.nbytes for a in self.arrays.values()))

    def p_directions(self, sigmas: Sequence[float], directions: np.ndarray) -> np.ndarray:
        """Recoloured p of the flat incoming ``directions`` (indices into theta_i x phi_i) for
        each effective absorption: (n, B, n_po, C) float32, from the levels (the uncompressed
        reference that :mod:`usdfiber.bake.compression` is checked against)."""
        if self.compressed:
            raise ValueError(f"{self.path or 'table'}: p_directions reads the levels of an uncompressed table")
        p, lb = self.arrays["p"], self.arrays["lbar"]
        n_ti, n_pi, K, B, n_po = p.shape
        idx = np.asarray(directions, dtype=np.int64)
        flat = lambda a: a.reshape((n_ti * n_pi,) + a.shape[2:])[idx]
        scale = flat(self.arrays["p_scale"].astype(np.float64) * self.arrays["albedo"])
        dom = flat(self.domega_band())
        if kernels.available():
            return kernels.recolour_p(flat(p), flat(lb), scale, dom, self.levels, sigmas)
        out = []
        for s in sigmas:
            F = log_interpolate(self.levels, float(s),
                                lambda k: flat(p[:, :, k]).astype(np.float64) * scale[:, k, None, None],
                                lambda k: flat(lb[:, :, k]).astype(np.float64))
            tot = F.sum(axis=(-2, -1), keepdims=True)
            out.append((np.where(tot > 0, F / np.where(tot > 0, tot, 1.0), 0.0) / dom[..., None]).astype(np.float32))
        return np.stack(out, axis=-1)

    # ---- levels ----------------------------------------------------------------------------
    def level_p(self, k: int) -> np.ndarray:
        """p at level k (n_ti, n_pi, B, n_po), float32, per steradian."""
        if self.compressed:
            return self._p_channels([float(self.levels[k])], kernels.available())[..., 0]
        return self.arrays["p"][:, :, k].astype(np.float32) * self.arrays["p_scale"][:, :, k, None, None]

    def _level_mass(self, k: int) -> np.ndarray:
        """F_k: fraction of the photons meeting the fiber that leave into each bin, float64."""
        p = self.level_p(k).astype(np.float64)
        return p * self.domega_band()[..., None] * self.arrays["albedo"][:, :, k, None, None]

    def _mass_at(self, s: float) -> np.ndarray:
        """F at absorption ``s``: float64 numpy, the reference for :mod:`~usdfiber.bake.recolour`."""
        lb = self.arrays["lbar"]
        return log_interpolate(self.levels, s, self._level_mass, lambda k: lb[:, :, k].astype(np.float64))

    def _albedo_at(self, s: float) -> np.ndarray:
        a = self.arrays["albedo"].astype(np.float64)
        al = self.arrays["albedo_lbar"].astype(np.float64)
        return log_interpolate(self.levels, s, lambda k: a[:, :, k], lambda k: al[:, :, k])

    def _p_reference(self, s: float) -> np.ndarray:
        """Recoloured p for one absorption, float64 numpy (one core; slow on large tables)."""
        if self.compressed:
            return self._p_basis([s], kernel=False)[..., 0].astype(np.float64)
        F = self._mass_at(s)
        tot = F.sum(axis=(-2, -1), keepdims=True)
        return np.where(tot > 0, F / np.where(tot > 0, tot, 1.0), 0.0) / self.domega_band()[..., None]

    def _p_basis(self, sigmas: Sequence[float], kernel: bool) -> np.ndarray:
        """Recoloured p of a compressed table, (n_ti, n_pi, B, n_po, C) float32."""
        basis = self.arrays["basis"]
        n_ti, n_pi, R, B, n_po = basis.shape
        n = n_ti * n_pi
        coef = compression.coefficients(self.arrays["absorptions"], self.arrays["coef"].reshape(n, -1, R), sigmas)
        dom = self.domega_band().reshape(n, B)
        if kernel:
            out = kernels.recolour_basis(basis.reshape(n, R, B, n_po), coef, dom)
            return out.reshape(n_ti, n_pi, B, n_po, len(sigmas))
        p = compression.reconstruct_p(basis.reshape(n, R, B * n_po), coef, np.repeat(dom, n_po, axis=1))
        return np.moveaxis(p, 1, -1).reshape(n_ti, n_pi, B, n_po, len(sigmas))

    def _p_channels(self, sigmas: Sequence[float], kernel: bool) -> np.ndarray:
        """Recoloured p for each absorption, (n_ti, n_pi, B, n_po, C) float32."""
        if self.compressed:
            return self._p_basis(sigmas, kernel)
        if kernel:
            p, lb = self.arrays["p"], self.arrays["lbar"]
            n_ti, n_pi, K, B, n_po = p.shape
            n = n_ti * n_pi
            scale = self.arrays["p_scale"].astype(np.float64) * self.arrays["albedo"]
            out = kernels.recolour_p(p.reshape(n, K, B, n_po), lb.reshape(n, K, B, n_po), scale.reshape(n, K),
                                       self.domega_band().reshape(n, B), self.levels, sigmas)
            return out.reshape(n_ti, n_pi, B, n_po, len(sigmas))
        return np.stack([self._p_reference(s).astype(np.float32) for s in sigmas], axis=-1)

    # ---- recolouring -----------------------------------------------------------------------
    def forget_recolourings(self) -> None:
        """Drop the cached recolourings (:meth:`recolour` keeps up to 1 GiB of them): a caller
        that has laid out what it needs (the renderer's fiber bank) frees them for the rest
        of its run."""
        self._recoloured.clear()

    def recolour(self, sigma_a_rgb_per_um: float | Sequence[float] = 0.0,
                 diameter_scale: float = 1.0, *, kernel: bool | None = None) -> Recoloured:
        """p and Lambda for an absorption per channel (1/um), without re-tracing.

        ``sigma_a_rgb_per_um``: a scalar or one value per channel (e.g. linear Rec.709 RGB)
        in 1/um; ``diameter_scale``: the fiber's diameter over ``baked_diameter_um``. The
        effective absorption of the baked profile is their product. Results are cached.
        p is computed by the Dr.Jit kernel of :mod:`usdfiber.bake.recolour` (float32, all
        cores) where Dr.Jit has an LLVM backend, else in float64 numpy; ``kernel`` forces
        one (True / False). A grey absorption is computed once (a read-only view per channel).
        """
        sig = np.atleast_1d(np.asarray(sigma_a_rgb_per_um, dtype=np.float64)).reshape(-1)
        ds = float(diameter_scale)
        if not (math.isfinite(ds) and ds > 0):
            raise ValueError(f"diameter_scale must be > 0, got {diameter_scale}")
        eff = sig * ds
        key = tuple(float(x) for x in eff)
        for s in key:
            level_bracket(self.levels, s)               # validates s
        use_kernel = kernels.available() if kernel is None else bool(kernel)
        hit = self._recoloured.get((key, use_kernel))
        if hit is not None:
            return hit
        if len(set(key)) == 1:
            p = self._p_channels(key[:1], use_kernel)
            p = np.broadcast_to(p, p.shape[:-1] + (len(key),)) if len(key) > 1 else p
        else:
            p = self._p_channels(key, use_kernel)
        alb = np.stack([self._albedo_at(s).astype(np.float32) for s in key], axis=-1)
        rec = Recoloured(self, eff, p, alb)
        # Keep a few recent colours, but not several full tables' worth (a 2 degree RGB p is
        # 1.5 GB, larger than the whole budget: not kept): the oldest go first.
        if rec.p.nbytes <= _RECOLOUR_CACHE_BYTES:
            self._recoloured[(key, use_kernel)] = rec
        while len(self._recoloured) > _RECOLOUR_CACHE_ENTRIES or sum(
                r.p.nbytes for r in self._recoloured.values()) > _RECOLOUR_CACHE_BYTES:
            del self._recoloured[next(iter(self._recoloured))]
        return rec

    # ---- evaluation --------------------------------------------------------------------------
    def eval_p(self, theta_i, phi_i, theta_o, phi_o, sigma_a: float | Sequence[float] = 0.0, *,
               diameter_scale: float = 1.0, psi: float = 0.0, interp_i: str = "linear",
               interp_o: str = "bilinear") -> np.ndarray:
        """p(omega_o | omega_i) per steradian at arbitrary directions (radians, broadcast).

        ``sigma_a``: scalar (result shape = broadcast shape) or per channel (result (..., C)),
        1/um, times ``diameter_scale``. ``psi``: rotation of the fiber about its axis.
        Interpolation: in omega_i linear between incoming nodes (``interp_i="linear"``;
        extruded tables mirror the first theta_i node through theta_i = 0) or the nearest
        node; in omega_o bilinear between bin centres (``interp_o="bilinear"``) or the bin's
        value (``"nearest"``: exactly the histogram, which integrates to 1).
        """
        scalar = np.ndim(sigma_a) == 0
        rec = self.recolour(sigma_a, diameter_scale)
        return _channels(rec.eval_p(theta_i, phi_i, theta_o, phi_o, psi=psi, interp_i=interp_i,
                                    interp_o=interp_o), scalar)

    def albedo(self, theta_i, phi_i, sigma_a: float | Sequence[float] = 0.0, *,
               diameter_scale: float = 1.0, psi: float = 0.0, interp_i: str = "linear") -> np.ndarray:
        """Lambda(omega_i) (radians, broadcast); channels as in :meth:`eval_p`."""
        scalar = np.ndim(sigma_a) == 0
        rec = self.recolour(sigma_a, diameter_scale)
        return _channels(rec.albedo_at(theta_i, phi_i, psi=psi, interp_i=interp_i), scalar)

    def width(self, phi, *, psi: float = 0.0) -> np.ndarray:
        """W(phi - psi): the projected width (um at the baked size), linear in phi."""
        w = self.arrays["width"].astype(np.float64)
        n = len(w)
        x = np.mod(np.asarray(phi, dtype=np.float64) - psi, _TWO_PI) / _TWO_PI * n
        j0 = np.floor(x).astype(np.int64) % n
        t = x - np.floor(x)
        return (1 - t) * w[j0] + t * w[(j0 + 1) % n]

    def cross_section(self, theta_i, phi_i, theta_o, phi_o, sigma_a: float | Sequence[float] = 0.0,
                      **kw: Any) -> np.ndarray:
        """sigma = W(phi_i) cos(theta_i) Lambda(omega_i) p(omega_o | omega_i) (um per sr).

        Keywords as :meth:`eval_p` (``diameter_scale`` does not rescale W: multiply by the
        diameter scale for a fiber of another size).
        """
        psi = kw.get("psi", 0.0)
        interp_i = kw.get("interp_i", "linear")
        p = self.eval_p(theta_i, phi_i, theta_o, phi_o, sigma_a, **kw)
        a = self.albedo(theta_i, phi_i, sigma_a, diameter_scale=kw.get("diameter_scale", 1.0),
                        psi=psi, interp_i=interp_i)
        wc = self.width(phi_i, psi=psi) * np.cos(np.asarray(theta_i, dtype=np.float64))
        if np.ndim(sigma_a) != 0:
            wc = np.asarray(wc)[..., None]
        return wc * a * p

    # ---- summaries -------------------------------------------------------------------------
    def summary(self) -> dict[str, Any]:
        """Key numbers for reports: resolution, photons, error, albedo range, size."""
        alb0 = self.arrays["albedo"][:, :, 0]
        err = self.rel_error
        return {
            "resolution_deg": self.grid.resolution_deg,
            "shape": {"theta_i": self.grid.n_theta_i, "phi_i": self.grid.n_phi_i,
                      "levels": len(self.levels), "band": self.n_band,
                      "theta_o": self.grid.n_theta_o, "phi_o": self.grid.n_phi_o},
            "photons_total": int(self.arrays["photons"].sum()),
            "photons_per_direction": [int(self.arrays["photons"].min()), int(self.arrays["photons"].max())],
            "rel_error_rms": float(np.sqrt(np.mean(err.astype(np.float64) ** 2))),
            "rel_error_max": float(err.max()),
            "albedo_min": float(alb0.min()),
            "albedo_max": float(alb0.max()),
            "nbytes": self.nbytes(),
            **({"compression": {k: self.header["compression"][k] for k in ("codec", "bound", "rank", "error_max", "error_rms")}}
               if self.compressed else {}),
        }
