"""The array layout of a BCSDF table file (``usdfiber-bcsdf-levels`` version 1).

A table file is a :mod:`usdfiber.table_format` container (a NumPy ``.npz`` with a JSON
header and a checksum per array); this module says which arrays a BCSDF table holds, and
checks them when a table is read (:func:`check_layout`). What the values mean: ``p``,
``Lambda`` and ``W`` in :mod:`usdfiber.bake.table`, the absorption levels in
:mod:`usdfiber.bake.absorption`, the grid in :mod:`usdfiber.bake.grid`.

``n_ti, n_pi``: incoming nodes (``incoming_deg`` apart when the header's ``resolution`` has
it, else one bin apart: :mod:`usdfiber.bake.grid`); ``K``: levels; ``n_to, n_po``: outgoing bins; ``B``: the
theta_o band (rows ``band_start .. band_start + B - 1`` of each incoming direction hold all
but ``band_tail`` of its mass at every level; the rest is dropped and ``p`` renormalized).

=================  ==============================  =========  ==================================
name               shape                           dtype      meaning
=================  ==============================  =========  ==================================
``p``              (n_ti, n_pi, K, B, n_po)        f2 or f4   p at level k / ``p_scale``
``p_scale``        (n_ti, n_pi, K)                 f4         per-slice scale of ``p`` (its max)
``lbar``           (n_ti, n_pi, K, B, n_po)        f2 or f4   Lbar_k (um), 0 in empty bins
``band_start``     (n_ti, n_pi)                    i2         first theta_o row of the band
``albedo``         (n_ti, n_pi, K)                 f4         Lambda at each level
``albedo_lbar``    (n_ti, n_pi, K)                 f4         -d log Lambda / ds at each level
``levels``         (K,)                            f8         s_k, 1/um at the baked size
``width``          (n_w,)                          f4         W(phi) at phi = 2 pi j / n_w (um)
``rel_error``      (n_ti, n_pi)                    f4         estimated relative L2 error of p
``photons``        (n_ti, n_pi)                    i8         photons traced per direction
=================  ==============================  =========  ==================================

``F_k`` (the bin mass at level k, see :mod:`usdfiber.bake.absorption`) is stored as ``p`` at
that level times ``Lambda`` at that level times the bin's solid angle. float16 rounding of
``p`` costs about 2e-4 relative L2 (measured at every bake and recorded in the header as
``quantization_error``), far below the Monte Carlo noise. The band saves little for rough
fibers at 2 degrees (multiple scattering spreads light over 60-88 of the 90 theta_o rows even
when dropping 1e-3 of the mass) and much for smooth round ones.
"""
from __future__ import annotations

import os
from typing import Any, Mapping

import numpy as np

from usdfiber import table_format
from usdfiber.bake.grid import Grid

__all__ = ["ARRAYS", "LAYOUT", "LAYOUT_VERSION", "STORAGE_DTYPES", "TableLayoutError", "WIDTH_SAMPLES",
           "check_layout", "layout_header", "read_table_file", "write_table_file"]

#: Name and version of the array layout described in the module docstring.
LAYOUT = "usdfiber-bcsdf-levels"
LAYOUT_VERSION = 1
#: Samples of W(phi) over [0, 2 pi).
WIDTH_SAMPLES = 720
#: Storage choices for the per-bin arrays ``p`` and ``lbar``.
STORAGE_DTYPES: dict[str, type] = {"float16": np.float16, "float32": np.float32}

#: The arrays of a table and what they hold (recorded in every header's ``layout``).
ARRAYS: dict[str, str] = {
    "p": "p at level k / p_scale, (theta_i, phi_i, level, band row, phi_o)",
    "p_scale": "max of p per (theta_i, phi_i, level)",
    "lbar": "exp(-s_k L)-weighted mean path length per bin, um at the baked size",
    "band_start": "first theta_o row of the band per (theta_i, phi_i)",
    "albedo": "Lambda per (theta_i, phi_i, level)",
    "albedo_lbar": "-d log Lambda / d s per (theta_i, phi_i, level), um",
    "levels": "absorption levels s_k, 1/um at the baked size",
    "width": "W(phi) at phi = 360 j / n_w deg, um at the baked size",
    "rel_error": "relative L2 error of p per incoming direction (sigma_a = 0)",
    "photons": "photons traced per incoming direction",
}


class TableLayoutError(ValueError):
    """A table file whose arrays do not follow this layout (the message says why)."""


def layout_header() -> dict[str, Any]:
    """The header's ``layout`` entry: name, version and the arrays' descriptions."""
    return {"name": LAYOUT, "version": LAYOUT_VERSION, "arrays": dict(ARRAYS)}


def check_layout(header: Mapping[str, Any], arrays: Mapping[str, np.ndarray], where: str) -> Grid:
    """The table's grid, after checking that its arrays follow this layout.

    Raises TableLayoutError naming ``where`` (the file) and what differs.
    """
    missing = [n for n in ARRAYS if n not in arrays]
    if missing:
        raise TableLayoutError(f"{where}: missing array(s) {', '.join(missing)}")
    lay = header.get("layout", {})
    if not isinstance(lay, dict) or lay.get("name") != LAYOUT or lay.get("version") != LAYOUT_VERSION:
        raise TableLayoutError(f"{where}: unsupported array layout {lay!r} "
                               f"(this usdfiber reads {LAYOUT} version {LAYOUT_VERSION})")
    try:
        g = Grid.from_header(header["resolution"])
    except (AttributeError, KeyError, TypeError, ValueError) as exc:   # AttributeError: not a mapping
        raise TableLayoutError(f"{where}: bad resolution entry in the header: {exc}") from None
    p = arrays["p"]
    K = len(arrays["levels"])
    expect = (g.n_theta_i, g.n_phi_i, K)
    if p.ndim != 5 or p.shape[:3] != expect or p.shape[4] != g.n_phi_o or p.shape[3] > g.n_theta_o:
        raise TableLayoutError(f"{where}: array p has shape {p.shape}, expected "
                               f"{expect + ('B', g.n_phi_o)}")
    if arrays["lbar"].shape != p.shape:
        raise TableLayoutError(f"{where}: arrays p and lbar differ in shape")
    for name, shape in (("p_scale", expect), ("albedo", expect), ("albedo_lbar", expect),
                        ("band_start", expect[:2]), ("rel_error", expect[:2]), ("photons", expect[:2])):
        if arrays[name].shape != shape:
            raise TableLayoutError(f"{where}: array {name} has shape {arrays[name].shape}, "
                                   f"expected {shape}")
    lv = arrays["levels"]
    if lv[0] != 0.0 or np.any(np.diff(lv) <= 0):
        raise TableLayoutError(f"{where}: levels must start at 0 and increase")
    bs = arrays["band_start"]
    if np.any(bs < 0) or np.any(bs + p.shape[3] > g.n_theta_o):
        raise TableLayoutError(f"{where}: band_start out of range")
    return g


def read_table_file(path: str | os.PathLike[str]) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """``(header, arrays)`` of a table file, every checksum verified (TableError when damaged);
    the layout is checked by :func:`check_layout`."""
    return table_format.read_table(path)


def write_table_file(path: str | os.PathLike[str], header: Mapping[str, Any],
                     arrays: Mapping[str, np.ndarray], *, compress: bool | int = True) -> dict[str, Any]:
    """Write a table atomically (zip-deflated unless ``compress`` is False: arrays that a codec
    already compressed gain nothing; an int is the zlib level, as
    :func:`usdfiber.table_format.write_table`); returns the header written. The container's
    own entries of ``header`` (format, version, arrays, checksums) are recomputed."""
    hdr = {k: v for k, v in header.items() if k not in ("arrays", "checksums", "format", "version")}
    return table_format.write_table(path, hdr, arrays, compress=compress)
