"""The angular grid of a BCSDF table: outgoing bins and incoming nodes.

Directions are in the fiber frame (t, the fiber axis, is +z): ``theta`` is the angle from
the plane normal to t (``sin theta = w . t``), in [-pi/2, pi/2]; ``phi`` the azimuth in that
plane from the profile's +x axis towards +y, in [0, 2 pi). Angles are radians here.

With an outgoing bin size of ``d`` degrees (``resolution_deg``, dividing 90) and an incoming
node spacing of ``D`` degrees (``incoming_deg``, a multiple of ``d`` dividing 90; by default
``D = d``, the paper's grid):

* outgoing directions: ``theta_o`` has ``180/d`` bins over [-90, 90] deg, ``phi_o`` ``360/d``
  bins over [0, 360) deg; a bin's value is the average over the bin, so photon counts are
  divided by the bin's solid angle ``d_phi (sin theta_hi - sin theta_lo)``
  (:meth:`Grid.solid_angles`);
* incoming directions are sampled at the centres of ``D``-degree cells. ``theta_i``:
  ``90/D`` nodes ``(k + 1/2) D`` over [0, 90] deg for extruded fibers (``theta_symmetric``),
  which obey ``p(theta_o, phi_o | -theta_i, phi_i) = p(-theta_o, phi_o | theta_i, phi_i)``
  (the mirror z -> -z maps the fiber onto itself); ``180/D`` nodes over [-90, 90] deg for
  fibers with cuticle scales, which break that symmetry. ``phi_i``: ``360/D`` nodes
  ``(j + 1/2) D``, or ONE node at half an OUTGOING bin (``d/2``) for rotationally symmetric
  profiles (``phi_invariant``), where p depends on ``phi_o - phi_i`` only: then
  ``p(theta_o, phi_o | theta_i, phi_i) = p_table(theta_o, phi_o - phi_i + d/2 | theta_i, d/2)``
  (the mirror ``phi_o - phi_i -> phi_i - phi_o`` then maps outgoing bins onto bins).

A coarser incoming spacing suits fibers whose lobes are wide (:mod:`usdfiber.bake.band_limit`):
fewer directions are traced, each into the same outgoing bins.

The same class bins exact photon exits for reference answers (:mod:`usdfiber.bake.binning`):
only the outgoing half is used there, so the incoming flags keep their defaults.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

__all__ = ["Grid"]

_TWO_PI = 2.0 * math.pi
_HALF_PI = 0.5 * math.pi


#: The finest bins: 0.1 deg is 1800 x 3600 outgoing bins per direction (the paper's grid is 2 deg).
MIN_RESOLUTION_DEG = 0.1


@dataclass(frozen=True)
class Grid:
    """The angular grid of a table (see the module docstring). Angles in radians.

    ``resolution_deg``: outgoing bin size. ``theta_symmetric``: theta_i >= 0 stored,
    negative theta_i by symmetry. ``phi_invariant``: one phi_i node; p depends on
    phi_o - phi_i. ``incoming_deg``: incoming node spacing (None: ``resolution_deg``; a value
    equal to it is stored as None, so equal grids compare and hash equal).
    """

    resolution_deg: float
    theta_symmetric: bool = True
    phi_invariant: bool = False
    incoming_deg: float | None = None

    def __post_init__(self) -> None:
        d = float(self.resolution_deg)
        if not (math.isfinite(d) and d > 0):
            raise ValueError(f"resolution must be a positive number of degrees, got {self.resolution_deg}")
        if d < MIN_RESOLUTION_DEG:
            raise ValueError(f"resolution must be at least {MIN_RESOLUTION_DEG:g} deg (a finer grid has more than "
                             f"a million bins per direction), got {d:g}")
        n = 90.0 / d
        if abs(n - round(n)) > 1e-9 or round(n) < 1:
            raise ValueError(f"resolution {d:g} deg must divide 90 deg (e.g. 1, 2, 3, 5, 10, 15, 30)")
        if self.incoming_deg is None:
            return
        D = float(self.incoming_deg)
        if not (math.isfinite(D) and D > 0):
            raise ValueError(f"incoming node spacing must be a positive number of degrees, got {self.incoming_deg}")
        m, n_i = D / d, 90.0 / D
        if abs(m - round(m)) > 1e-9 or abs(n_i - round(n_i)) > 1e-9 or round(n_i) < 1:
            raise ValueError(f"incoming node spacing {D:g} deg must be a multiple of the {d:g} deg outgoing "
                             f"bins that divides 90 deg")
        object.__setattr__(self, "incoming_deg", None if round(m) == 1 else D)

    @property
    def incoming_spacing_deg(self) -> float:
        """Incoming node spacing in degrees (``incoming_deg``, else ``resolution_deg``)."""
        return float(self.resolution_deg if self.incoming_deg is None else self.incoming_deg)

    @property
    def incoming_step(self) -> float:
        """Incoming node spacing in radians."""
        return math.radians(self.incoming_spacing_deg)

    @property
    def step(self) -> float:
        """Bin size in radians."""
        return math.radians(self.resolution_deg)

    @property
    def n_theta_o(self) -> int:
        """Outgoing theta bins."""
        return int(round(180.0 / self.resolution_deg))

    @property
    def n_phi_o(self) -> int:
        """Outgoing phi bins."""
        return int(round(360.0 / self.resolution_deg))

    @property
    def n_theta_i(self) -> int:
        """Incoming theta nodes."""
        n = int(round(90.0 / self.incoming_spacing_deg))
        return n if self.theta_symmetric else 2 * n

    @property
    def n_phi_i(self) -> int:
        """Incoming phi nodes."""
        return 1 if self.phi_invariant else int(round(360.0 / self.incoming_spacing_deg))

    @property
    def phi_i_origin(self) -> float:
        """phi_i of the first node: half a cell, or half an outgoing bin for one node."""
        return 0.5 * (self.step if self.phi_invariant else self.incoming_step)

    @property
    def theta_i_min(self) -> float:
        """Start of the stored theta_i range (0 with the theta symmetry, else -pi/2)."""
        return 0.0 if self.theta_symmetric else -_HALF_PI

    def theta_o_edges(self) -> np.ndarray:
        """The n_theta_o + 1 bin edges in theta_o, from -pi/2 to pi/2."""
        return -_HALF_PI + self.step * np.arange(self.n_theta_o + 1)

    def theta_o_centers(self) -> np.ndarray:
        """Outgoing theta bin centres."""
        return -_HALF_PI + self.step * (np.arange(self.n_theta_o) + 0.5)

    def phi_o_centers(self) -> np.ndarray:
        """Outgoing phi bin centres."""
        return self.step * (np.arange(self.n_phi_o) + 0.5)

    def theta_i_nodes(self) -> np.ndarray:
        """Incoming theta nodes (cell centres from :attr:`theta_i_min`)."""
        return self.theta_i_min + self.incoming_step * (np.arange(self.n_theta_i) + 0.5)

    def phi_i_nodes(self) -> np.ndarray:
        """Incoming phi nodes (cell centres; :attr:`phi_i_origin` for one node)."""
        if self.phi_invariant:
            return np.array([self.phi_i_origin])
        return self.incoming_step * (np.arange(self.n_phi_i) + 0.5)

    def solid_angles(self) -> np.ndarray:
        """Solid angle of each theta_o row's bins (n_theta_o,): d_phi (sin hi - sin lo)."""
        e = self.theta_o_edges()
        return self.step * (np.sin(e[1:]) - np.sin(e[:-1]))

    def bin_solid_angles(self) -> np.ndarray:
        """Solid angle of every outgoing bin, (n_theta_o, n_phi_o); sums to 4 pi."""
        return np.repeat(self.solid_angles()[:, None], self.n_phi_o, axis=1)

    def bin_index(self, directions: np.ndarray) -> np.ndarray:
        """Flat bin index ``row * n_phi_o + col`` of unit directions (M, 3) in the fiber frame."""
        d = np.asarray(directions, dtype=np.float64)
        theta = np.arcsin(np.clip(d[:, 2], -1.0, 1.0))
        phi = np.mod(np.arctan2(d[:, 1], d[:, 0]), _TWO_PI)
        row = np.clip(np.floor((theta + _HALF_PI) / self.step).astype(np.int64), 0, self.n_theta_o - 1)
        col = np.floor(phi / self.step).astype(np.int64) % self.n_phi_o
        return row * self.n_phi_o + col

    def to_header(self) -> dict[str, Any]:
        """The grid as recorded in a table's header (``resolution``; angles in degrees).

        ``incoming_deg`` appears only when it differs from ``deg`` (headers of the paper's
        grid are unchanged)."""
        out = {
            "deg": self.resolution_deg,
            "theta_o": self.n_theta_o,
            "phi_o": self.n_phi_o,
            "theta_i": self.n_theta_i,
            "phi_i": self.n_phi_i,
            "theta_o_range_deg": [-90.0, 90.0],
            "phi_o_range_deg": [0.0, 360.0],
            "theta_i_range_deg": [math.degrees(self.theta_i_min), 90.0],
            "theta_i_nodes": "bin centres (k + 1/2) * deg from the range start",
            "phi_i_nodes": "bin centres (j + 1/2) * deg",
            "theta_symmetric": self.theta_symmetric,
            "rotationally_symmetric": self.phi_invariant,
        }
        if self.incoming_deg is not None:
            out["incoming_deg"] = self.incoming_deg
            out["theta_i_nodes"] = "cell centres (k + 1/2) * incoming_deg from the range start"
            out["phi_i_nodes"] = ("one node at deg / 2" if self.phi_invariant
                                  else "cell centres (j + 1/2) * incoming_deg")
        return out

    @classmethod
    def from_header(cls, res: Mapping[str, Any]) -> "Grid":
        """The grid of a header's ``resolution`` entry (:meth:`to_header`).

        Raises ValueError when the entry is inconsistent: its node and bin counts are not
        those of the grid its sizes and flags describe."""
        inc = res.get("incoming_deg")
        g = cls(float(res["deg"]), bool(res["theta_symmetric"]), bool(res["rotationally_symmetric"]),
                None if inc is None else float(inc))
        counts = {"theta_o": g.n_theta_o, "phi_o": g.n_phi_o, "theta_i": g.n_theta_i, "phi_i": g.n_phi_i}
        for name, n in counts.items():
            if name in res and res[name] != n:
                raise ValueError(f"header resolution says {name} = {res[name]!r}, but a "
                                 f"{g.resolution_deg:g} deg grid with {g.incoming_spacing_deg:g} deg "
                                 f"incoming nodes has {n}")
        return g
