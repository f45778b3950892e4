"""Figures of a baked table people can read (matplotlib, Agg backend: no display needed).

* :func:`scattering_grid`: the paper's Figure 3 layout: one panel per light longitude
  theta_i (rows) and fiber rotation psi (columns), each the scattered intensity
  ``Lambda(omega_i) p(omega_o | omega_i)`` (per steradian, luminance of the linear Rec.709
  channels) over phi_o (x, 0-360 degrees) and theta_o (y, -90 to 90 degrees) on a log10 scale
  with one shared colour bar; the specular cone ``theta_o = -theta_i`` is marked.
* :func:`longitudinal_curves`: Figure 14-style longitudinal scattering, the intensity
  integrated over phi_o, ``M(theta_o) = int Lambda p cos(theta_o) dphi_o`` (per radian of
  theta_o), one curve per theta_i, log scale, cones marked.
* :func:`error_against_photons`: a bake's estimated relative L2 error of p per incoming
  direction against its photons, with the ``c / sqrt(N)`` law fitted through them.
* :func:`fit_comparison`: Figure 12-style slices of the table's scattering against each
  fitted standard model (:mod:`usdfiber.fit`): per light longitude theta_i (rows), the
  rotation-averaged ``s = sigma / <W>`` (:class:`usdfiber.fit.FitTarget`) on the specular
  cone over ``dphi = phi_o - phi_i`` (left) and integrated over ``dphi`` against theta_o
  (right), luminance, log scale; each model's relative L2 error over the sphere in the legend.

Each returns a matplotlib Figure; :func:`save` writes it (PNG, PDF, SVG by extension).
Angles are in degrees; absorption ``sigma_a`` per channel in 1/um at the baked size
(:meth:`usdfiber.bake.table.BcsdfTable.recolour`).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Sequence

import numpy as np

__all__ = ["error_against_photons", "fit_comparison", "longitudinal_curves", "save", "scattering_grid"]

_LUMA = np.array([0.2126, 0.7152, 0.0722])


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _intensity(rec: Any, theta_i: float, phi_i: float, psi: float, theta_o: np.ndarray,
               phi_o: np.ndarray) -> np.ndarray:
    """Luminance of Lambda p at (theta_o, phi_o) for one light direction (radians)."""
    v = rec.eval_p(theta_i, phi_i, theta_o, phi_o, psi=psi, interp_o="nearest") \
        * rec.albedo_at(theta_i, phi_i, psi=psi)
    return v @ _LUMA if v.shape[-1] == 3 else v.mean(axis=-1)


def _title(table: Any, sigma_a: Sequence[float]) -> str:
    h = table.header
    dyed = any(float(s) > 0 for s in sigma_a)
    colour = f"sigma_a {', '.join(f'{float(s):.3g}' for s in sigma_a)} /um" if dyed else "undyed"
    return (f"{h.get('kind', 'fiber')} ({h.get('profile_family', '?')}, variant {table.variant}), "
            f"{table.grid.resolution_deg:g} deg table, {colour}")


def scattering_grid(table: Any, sigma_a: Sequence[float] = (0.0, 0.0, 0.0), diameter_scale: float = 1.0, *,
                    theta_i: Sequence[float] = (-60.0, -30.0, 0.0), psi: Sequence[float] = (0.0, 60.0, 120.0),
                    phi_i: float = 0.0, decades: float = 4.0, pixels_per_bin: int = 4) -> Any:
    """Figure 3's layout (module docstring); degrees."""
    plt = _plt()
    from matplotlib.colors import LogNorm

    rec = table.recolour(list(sigma_a), diameter_scale)
    g = table.grid
    h_px, w_px = g.n_theta_o * pixels_per_bin, g.n_phi_o * pixels_per_bin
    th = np.radians(90.0 - (np.arange(h_px) + 0.5) * 180.0 / h_px)
    ph = np.radians((np.arange(w_px) + 0.5) * 360.0 / w_px)
    T, P = np.meshgrid(th, ph, indexing="ij")
    panels = [[_intensity(rec, math.radians(ti), math.radians(phi_i), math.radians(ps), T, P) for ps in psi]
              for ti in theta_i]
    top = max(float(v.max()) for row in panels for v in row)
    if not top > 0:
        raise ValueError("the slices are empty (no light scattered)")
    norm = LogNorm(vmin=top * 10.0 ** -decades, vmax=top)
    fig, axes = plt.subplots(len(theta_i), len(psi), figsize=(3.2 * len(psi) + 1.2, 1.75 * len(theta_i) + 0.9),
                             squeeze=False, sharex=True, sharey=True, constrained_layout=True)
    im = None
    for r, ti in enumerate(theta_i):
        for c, ps in enumerate(psi):
            ax = axes[r][c]
            im = ax.imshow(np.maximum(panels[r][c], norm.vmin), norm=norm, cmap="inferno", aspect="auto",
                           extent=(0, 360, -90, 90), interpolation="nearest")
            ax.axhline(-ti, color="#7fd4ff", lw=0.8, ls="--")
            ax.set_xticks([0, 90, 180, 270, 360])
            ax.set_yticks([-90, -45, 0, 45, 90])
            if r == 0:
                ax.set_title(f"psi = {ps:g} deg", fontsize=9)
            if c == 0:
                ax.set_ylabel(f"theta_i = {ti:g}\ntheta_o (deg)", fontsize=8)
            if r == len(theta_i) - 1:
                ax.set_xlabel("phi_o (deg)", fontsize=8)
            ax.tick_params(labelsize=7)
    cb = fig.colorbar(im, ax=axes, shrink=0.9, pad=0.01)
    cb.set_label("Lambda p (1/sr), log scale", fontsize=8)
    cb.ax.tick_params(labelsize=7)
    fig.suptitle(f"{_title(table, sigma_a)}; light at phi_i = {phi_i:g} deg; "
                 f"dashed: specular cone theta_o = -theta_i", fontsize=9)
    return fig


def longitudinal_curves(table: Any, sigma_a: Sequence[float] = (0.0, 0.0, 0.0), diameter_scale: float = 1.0, *,
                        theta_i: Sequence[float] = (-60.0, -30.0, 0.0, 30.0), phi_i: float = 0.0,
                        psi: float = 0.0) -> Any:
    """Figure 14-style longitudinal scattering (module docstring); degrees."""
    plt = _plt()
    rec = table.recolour(list(sigma_a), diameter_scale)
    g = table.grid
    n_th, n_ph = g.n_theta_o * 4, g.n_phi_o * 4
    th = np.radians(-90.0 + (np.arange(n_th) + 0.5) * 180.0 / n_th)
    ph = (np.arange(n_ph) + 0.5) * (2 * math.pi / n_ph)
    T, P = np.meshgrid(th, ph, indexing="ij")
    fig, ax = plt.subplots(figsize=(6.4, 3.8), constrained_layout=True)
    colours = plt.get_cmap("viridis")(np.linspace(0.0, 0.9, len(theta_i)))
    for ti, col in zip(theta_i, colours):
        v = _intensity(rec, math.radians(ti), math.radians(phi_i), math.radians(psi), T, P)
        m = v.sum(axis=1) * (2 * math.pi / n_ph) * np.cos(th)
        ax.semilogy(np.degrees(th), np.maximum(m, 1e-12), color=col, lw=1.4, label=f"theta_i = {ti:g} deg")
        ax.axvline(-ti, color=col, lw=0.7, ls=":")
    ax.set_xlim(-90, 90)
    ax.set_xticks(range(-90, 91, 30))
    tops = [ln.get_ydata().max() for ln in ax.get_lines() if len(ln.get_ydata()) > 2]
    ax.set_ylim(max(tops) * 1e-4, max(tops) * 2)
    ax.set_xlabel("theta_o (deg)")
    ax.set_ylabel("int Lambda p cos(theta_o) dphi_o (1/rad)")
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(fontsize=8, loc="upper right")
    ax.set_title(f"Longitudinal scattering, {_title(table, sigma_a)}\nlight at phi_i = {phi_i:g} deg, "
                 f"psi = {psi:g} deg; dotted: theta_o = -theta_i", fontsize=9)
    return fig


def error_against_photons(table: Any) -> Any:
    """A bake's per-direction error estimate against its photons, with ``c / sqrt(N)``."""
    plt = _plt()
    n = table.arrays["photons"].astype(np.float64).reshape(-1)
    e = table.rel_error.astype(np.float64).reshape(-1)
    ok = (n > 0) & np.isfinite(e) & (e > 0)
    if not ok.any():
        raise ValueError("the table has no per-direction error estimates")
    c = float(np.exp(np.median(np.log(e[ok]) + 0.5 * np.log(n[ok]))))
    fig, ax = plt.subplots(figsize=(5.6, 3.8), constrained_layout=True)
    ax.loglog(n[ok], e[ok], "o", ms=3, alpha=0.6, label="incoming directions")
    xs = np.geomspace(n[ok].min() / 2, n[ok].max() * 2, 50)
    ax.loglog(xs, c / np.sqrt(xs), "k--", lw=1, label=f"{c:.3g} / sqrt(N)")
    ax.set_xlabel("photons per incoming direction N")
    ax.set_ylabel("estimated relative L2 error of p")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    s = table.summary()
    ax.set_title(f"{_title(table, [0.0])}\nrms error {s['rel_error_rms']:.3g}, "
                 f"{s['photons_total']:.3g} photons in all", fontsize=9)
    return fig


def fit_comparison(tables: Sequence[Any], sigma_a: Sequence[float] = (0.0, 0.0, 0.0), diameter_scale: float = 1.0,
                   *, theta_i: Sequence[float] = (-60.0, -30.0, 0.0), models: Sequence[str] = ("chiang", "khungurn"),
                   settings: Any = None) -> Any:
    """Figure 12-style comparison of ``tables`` (one fiber's cross-section variants) with the
    standard models fitted to them (module docstring); ``theta_i`` in degrees, each shown at
    the nearest incoming node. Fits are cached beside the first table's file (``usdfiber.fit``)."""
    from usdfiber.fit import FitTarget, fit_tables, model_values

    plt = _plt()
    tables = list(tables)
    target = FitTarget.from_tables(tables, list(sigma_a), diameter_scale)
    curves = {"table": target.values}
    errors = {}
    for m in models:
        res = fit_tables(tables, m, sigma_a=list(sigma_a), diameter_scale=diameter_scale, settings=settings)
        curves[m] = model_values(m, res.params, target, res.settings)
        errors[m] = float(np.asarray(res.error["rel_l2"]) @ _LUMA) if len(res.error["rel_l2"]) == 3 \
            else float(np.mean(res.error["rel_l2"]))
    lum = {k: (v @ _LUMA if v.shape[-1] == 3 else v.mean(axis=-1)) for k, v in curves.items()}
    nodes = np.degrees(target.theta_i)
    # Mirror-symmetric tables store theta_i >= 0: s(-theta_i, -theta_o) = s(theta_i, theta_o).
    mirror = bool(target.mirror) and nodes.min() >= 0.0
    rows = [(int(np.argmin(np.abs(nodes - (abs(t) if mirror else t)))), mirror and t < 0) for t in theta_i]
    centres = np.degrees(0.5 * (target.theta_o_edges[1:] + target.theta_o_edges[:-1]))
    n_phi = target.values.shape[2]
    dphi = np.degrees(target.dphi_step * np.arange(n_phi))
    order = np.argsort(np.mod(dphi + 180.0, 360.0))
    dphi_c = np.mod(dphi + 180.0, 360.0)[order] - 180.0
    fig, axes = plt.subplots(len(rows), 2, figsize=(9.0, 2.3 * len(rows) + 0.8), squeeze=False,
                             constrained_layout=True)
    styles = {"table": dict(color="k", lw=1.8), "chiang": dict(color="#d95f02", lw=1.2, ls="--"),
              "khungurn": dict(color="#1b9e77", lw=1.2, ls="-.")}
    for r, (i, flip) in enumerate(rows):
        ti = -nodes[i] if flip else nodes[i]
        o = int(np.argmin(np.abs(centres + ti)))                  # the specular cone's bin
        ax_a, ax_l = axes[r]
        for k, v in lum.items():
            vi = v[i][::-1] if flip else v[i]                      # (theta_o, dphi) at theta_i = ti
            label = k if k == "table" else f"{k} (rel L2 {errors[k]:.2f})"
            st = styles.get(k, {})
            ax_a.semilogy(dphi_c, np.maximum(vi[o][order], 1e-9), label=label, **st)
            m_long = vi.sum(axis=1) * target.dphi_step
            ax_l.semilogy(centres, np.maximum(m_long, 1e-9), label=label, **st)
        ax_a.set_xlim(-180, 180)
        ax_a.set_xticks(range(-180, 181, 90))
        ax_a.set_ylabel(f"theta_i = {ti:.3g} deg\ns on the cone (1/sr)", fontsize=8)
        ax_l.set_xlim(-90, 90)
        ax_l.set_xticks(range(-90, 91, 30))
        ax_l.axvline(-ti, color="#7fd4ff", lw=0.8, ls=":")
        ax_l.set_ylabel("int s dphi (1/rad)", fontsize=8)
        for ax in (ax_a, ax_l):
            ax.grid(True, alpha=0.3)
            ax.tick_params(labelsize=7)
        if r == 0:
            ax_a.set_title("azimuthal slice, theta_o = -theta_i", fontsize=9)
            ax_l.set_title("longitudinal (dotted: theta_o = -theta_i)", fontsize=9)
            ax_a.legend(fontsize=7, loc="best")
        if r == len(rows) - 1:
            ax_a.set_xlabel("phi_o - phi_i (deg)", fontsize=8)
            ax_l.set_xlabel("theta_o (deg)", fontsize=8)
    fig.suptitle(f"Table against fitted models: {_title(tables[0], sigma_a)}, averaged over rotations"
                 + (f" and {len(tables)} variants" if len(tables) > 1 else ""), fontsize=9)
    return fig


def save(fig: Any, path: str | Path, dpi: int = 150) -> Path:
    """Write ``fig`` (format from the extension) and close it; OSError when it cannot."""
    plt = _plt()
    path = Path(path)
    try:
        fig.savefig(path, dpi=dpi)
    finally:
        plt.close(fig)
    return path
