"""Our tabulated BCSDF against Mitsuba 3's built-in ``hair`` BSDF on a smooth round fiber.

Setup: a circular fiber, eta 1.55, Beckmann roughness beta = 2.5 deg, no absorption, baked at
6 deg with 131,072 photons per incoming direction (about 1-3 % relative L2 noise per
direction, ~20-30 s on 2 cores); Mitsuba's ``hair`` (Chiang et al. 2016) with no pigment,
``scale_tilt`` 0, ``int_ior`` 1.55 and roughnesses matched to the same beta (below). Both are
evaluated at the BSDF level, in the local frame both use on Mitsuba's curves: local y is the
fiber tangent (``sin theta = w.y``), ``si.wi`` the viewer, ``wo`` the light, and ``eval``
returns the cosine-weighted value, which for both is the density ``p(light | viewer)`` per
steradian times the albedo (no cosine to the tube's normal).

Offset h. ``hair`` is a near-field model: it derives the offset h across the fiber from the
angle between ``si.wi`` and the shading normal. A renderer averages it over the fiber's width,
uniform in h in [-1, 1]. Our table is already that average (far field). So the hair side is
averaged here over h, with 32 stratified, jittered h per evaluation cell: for each h, the
directions are rotated about the tangent so that the viewer's angle to the normal (local z) is
asin(h).

Quadrature: the light direction runs over a midpoint grid, uniform in sin(theta_l)
(600 rows) and in phi_l - phi_v (360 columns), so each cell has the same solid angle. The
directional albedo is the integral of ``eval`` over the sphere. The azimuthal distribution
(theta_l integrated) is rebinned to the table's 6 deg bins, centred on multiples of 6 deg.
The longitudinal profile is taken over the back half (|phi_l - phi_v| < 90 deg).

Matching the roughness (a first-order argument, not a fit): Beckmann slopes have a standard
deviation of alpha / sqrt(2) per axis (alpha = tan beta). Reflection turns the direction by
twice the facet tilt, so the R lobe has a standard deviation of sqrt(2) alpha = 3.5 deg, in
theta and in phi. ``hair``'s longitudinal variance is v = (0.726 b_m + 0.812 b_m^2 +
3.7 b_m^20)^2 (rad^2), so b_m solves sqrt(v) = sqrt(2) alpha (b_m = 0.078). Its azimuthal
logistic scale is s = sqrt(pi / 8) (0.265 b_n + 1.194 b_n^2 + 5.372 b_n^22). A logistic has
standard deviation s pi / sqrt(3), so b_n solves s pi / sqrt(3) = sqrt(2) alpha (b_n = 0.129).

Expected differences (why the tolerances are a bin, or a few %, not noise-level):

* Longitudinal shape: ``hair`` uses d'Eon's Gaussian-like lobes, all centred at
  theta_l = -theta_v when scale_tilt = 0, with variances v (R), v/4 (TT) and 4v (TRT and
  beyond). Our lobes come from photons traced through a rough microsurface. Our table is also
  bilinear between 6 deg bin centres, which smears every lobe over about +-6 deg. Lobe peaks
  agree to within a bin; lobe widths do not (measured standard deviation about theta_l:
  ours 3.7-4.8 deg, hair 2.6-2.7 deg at theta_v <= 36 deg).
* Azimuthal shape: ``hair`` places each path p at its smooth-circle exit azimuth
  Phi(p, h) = 2p gamma_t - 2 gamma_i + p pi and blurs it with one trimmed logistic for all p.
  It lumps p >= 3 into one lobe that is uniform in phi. Averaged over h, this is the exact
  smooth-circle distribution (:func:`usdfiber.bake.exact.azimuthal_distribution`), caustics
  included, convolved with the logistic. Our table traces every path through the rough
  surface: each interface blurs by its own amount, and p >= 3 keeps its structure. Where the
  TRT caustic (the fiber's rainbow, at |phi_l - phi_v| ~ 10-20 deg here) sits next to the
  back-scattered R light, both smear it inwards. The blur shifts the 6 deg-bin peak, which
  then lies between the exact caustic and phi_l - phi_v = 0.
* Parameterization: the roughness match above is a first-order estimate. Fresnel and
  Bravais refraction are exact in both for a circle. ``hair`` evaluates one Fresnel factor at
  the h-dependent angle; our walk draws a microfacet at every interface.
* Noise: the table's photon noise (1-3 % per direction) and our h quadrature's noise (~0.5 %
  per 6 deg bin).

Measured here (printed by ``pytest -s``): L1 distance between the two azimuthal distributions
on 6 deg bins of 2.3-3.0 % at theta_v = 3-36 deg; each is 2.5-4 % from the exact
smooth-circle distribution. Directional albedos are 1 within 0.1 % (quadrature of eval).

The checks can fail. ``test_checks_detect_wrong_frames`` runs them on a hair evaluation with
the tangent on local z instead of y, on our BSDF with the tangent on x, and on a distribution
shifted by 90 deg. Each must be flagged.
"""
from __future__ import annotations

import math
import os
import tempfile

import numpy as np
import pytest

import usdfiber  # noqa: F401  (registers schemas first)
from usdfiber.backend import mitsuba
from usdfiber.bake import exact, profiles
from usdfiber.bake.baker import BakeSettings, bake_table

from usdfiber.translators.fiber_bank import FiberBank, FiberSlot
from usdfiber.translators.fiber_bsdf import fiber_bsdf

mi = mitsuba()
import drjit as dr  # noqa: E402  (after the variant is set)

ETA = 1.55
BETA_DEG = 2.5
RES_DEG = 6.0
PHOTONS = 131_072
THETA_V_DEG = (3.0, 21.0, 36.0)        # two table nodes and one direction between nodes
N_U, N_PHI, N_H = 600, 360, 32        # quadrature: sin(theta_l) rows, phi columns, h per cell
BIN = math.radians(RES_DEG)
N_BINS = int(round(2 * math.pi / BIN))


def matched_hair_roughness(beta_deg: float) -> tuple[float, float]:
    """(longitudinal_roughness, azimuthal_roughness) whose R lobe std is sqrt(2) tan(beta)."""
    from scipy.optimize import brentq

    std = math.sqrt(2.0) * math.tan(math.radians(beta_deg))
    b_m = brentq(lambda b: 0.726 * b + 0.812 * b * b + 3.7 * b ** 20 - std, 0.0, 1.0)
    s = std * math.sqrt(3.0) / math.pi
    b_n = brentq(lambda b: math.sqrt(math.pi / 8) * (0.265 * b + 1.194 * b * b + 5.372 * b ** 22) - s, 0.0, 1.0)
    return b_m, b_n


@pytest.fixture(scope="module", autouse=True)
def _temp_cache():
    old = os.environ.get("USDFIBER_CACHE_DIR")
    with tempfile.TemporaryDirectory() as d:
        os.environ["USDFIBER_CACHE_DIR"] = d
        yield
    if old is None:
        os.environ.pop("USDFIBER_CACHE_DIR", None)
    else:
        os.environ["USDFIBER_CACHE_DIR"] = old


@pytest.fixture(scope="module")
def table():
    return bake_table(profiles.circle(), ETA, BETA_DEG, None,
                      BakeSettings(resolution_deg=RES_DEG, photons=PHOTONS, batches=2))


@pytest.fixture(scope="module")
def ours(table):
    return fiber_bsdf(mi, FiberBank.build([FiberSlot(table, (0.0, 0.0, 0.0))]), [0], [0.0],
                      np.array([[1.0, 0.0, 0.0]]), pass_through=False)


@pytest.fixture(scope="module")
def hair():
    b_m, b_n = matched_hair_roughness(BETA_DEG)
    return mi.load_dict({"type": "hair", "eumelanin": 0.0, "pheomelanin": 0.0,
                         "longitudinal_roughness": b_m, "azimuthal_roughness": b_n,
                         "scale_tilt": 0.0, "int_ior": ETA})


# ---------------------------------------------------------------------------------------------
# Evaluation on the quadrature grid
# ---------------------------------------------------------------------------------------------

_U = -1.0 + (np.arange(N_U) + 0.5) * 2.0 / N_U
TH_L = np.arcsin(_U)                                           # rows
DPHI = -math.pi + (np.arange(N_PHI) + 0.5) * 2.0 * math.pi / N_PHI   # columns, in [-pi, pi)
CELL = (2.0 / N_U) * (2.0 * math.pi / N_PHI)                    # solid angle of a cell


def _dirs(theta, phi, tangent_axis: int = 1):
    """Unit vectors, theta from the plane normal to the tangent (local axis), phi in that plane."""
    c = np.cos(theta)
    a, b = c * np.cos(phi), c * np.sin(phi)
    s = np.sin(theta) * np.ones_like(phi)
    if tangent_axis == 1:          # (x, y = tangent, z): Mitsuba's convention on curves
        comps = (a, s, b)
    elif tangent_axis == 2:        # tangent on z (the wrong convention for curves)
        comps = (a, b, s)
    else:                          # tangent on x
        comps = (s, a, b)
    return mi.Vector3f(*[mi.Float(np.ascontiguousarray(x, dtype=np.float32)) for x in comps])


def _si(wi, n, frame_t=(0.0, 1.0, 0.0)):
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = wi
    t = np.asarray(frame_t, float)
    z = np.array([0.0, 0.0, 1.0]) if abs(t[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    z = z - z.dot(t) * t
    z /= np.linalg.norm(z)
    s = np.cross(t, z)
    # Local coordinates equal world ones for the default frame (s = x, t = y, n = z).
    si.sh_frame = mi.Frame3f(mi.Vector3f(*s.tolist()), mi.Vector3f(*t.tolist()), mi.Vector3f(*z.tolist()))
    si.prim_index = 0
    return si


def grid_ours(bsdf, theta_v: float, frame_t=(0.0, 1.0, 0.0)) -> np.ndarray:
    """eval(viewer, light) on the grid: (N_U, N_PHI), density per steradian times albedo."""
    th, dp = np.meshgrid(TH_L, DPHI, indexing="ij")
    n = th.size
    phi_v = 0.3
    wi = _dirs(np.full(n, theta_v), np.full(n, phi_v))
    wo = _dirs(th.ravel(), phi_v + dp.ravel())
    f = np.array(bsdf.eval(mi.BSDFContext(), _si(wi, n, frame_t), wo))[0]
    return f.reshape(th.shape).astype(np.float64)


def grid_hair(bsdf, theta_v: float, tangent_axis: int = 1, seed: int = 0) -> np.ndarray:
    """``hair``'s eval averaged over the offset h (stratified, jittered), on the grid."""
    rng = np.random.default_rng(seed)
    th, dp = np.meshgrid(TH_L, DPHI, indexing="ij")
    n = th.size
    acc = np.zeros(n)
    ctx = mi.BSDFContext()
    for k in range(N_H):
        h = -1.0 + 2.0 * (k + rng.random(n)) / N_H
        # Local azimuth of the viewer (from x towards the normal z) with gamma = asin(h) from z.
        psi = 0.5 * math.pi + np.arcsin(h)
        wi = _dirs(np.full(n, theta_v), psi, tangent_axis)
        wo = _dirs(th.ravel(), psi + dp.ravel(), tangent_axis)
        acc += np.array(bsdf.eval(ctx, _si(wi, n), wo))[0]
    return (acc / N_H).reshape(th.shape)


def albedo(f: np.ndarray) -> float:
    return float(f.sum() * CELL)


def azimuthal(f: np.ndarray) -> np.ndarray:
    """Normalized density per radian over phi_l - phi_v on N_BINS bins centred on k * BIN."""
    a = f.sum(axis=0) * (2.0 / N_U)                      # per radian, columns over [-pi, pi)
    a = np.roll(a, N_PHI // 2)                           # columns over [0, 2 pi)
    per = N_PHI // N_BINS
    a = np.roll(a, per // 2).reshape(N_BINS, per).mean(axis=1)
    return a / (a.sum() * BIN)


def exact_azimuthal(theta_v: float) -> np.ndarray:
    n_fine = 6 * N_BINS
    d = exact.azimuthal_distribution(theta_v, ETA, n_bins=n_fine, n_h=1 << 20)
    d = np.roll(d, 3).reshape(N_BINS, 6).mean(axis=1)
    return d / (d.sum() * BIN)


def l1(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a - b).sum() * BIN)


def theta_profile(f: np.ndarray) -> np.ndarray:
    """Density per unit theta_l of the back half (|phi_l - phi_v| < 90 deg)."""
    back = np.abs(DPHI) < 0.5 * math.pi
    return (f[:, back].sum(axis=1) * (2.0 * math.pi / N_PHI)) * np.cos(TH_L)


def _refine(y: np.ndarray, k: int) -> float:
    """Sub-bin offset (in bins) of a parabola through y[k-1], y[k], y[k+1] (cyclic)."""
    a, b, c = y[(k - 1) % len(y)], y[k], y[(k + 1) % len(y)]
    den = a - 2.0 * b + c
    return 0.0 if den >= 0 else float(np.clip(0.5 * (a - c) / den, -0.5, 0.5))


def forward_peak_deg(dist: np.ndarray) -> float:
    """Position of the largest forward-half value (deg in [0, 360)), parabola-refined."""
    centres = np.arange(N_BINS) * RES_DEG
    fw = np.abs(centres - 180.0) < 90.0
    k = int(np.flatnonzero(fw)[np.argmax(dist[fw])])
    return (k + _refine(dist, k)) * RES_DEG


def back_peak_deg(dist: np.ndarray) -> float:
    """|phi_l - phi_v| of the largest back-half value of the folded distribution (deg)."""
    folded = 0.5 * (dist + np.roll(dist[::-1], 1))        # P(x) and P(-x) averaged
    k = int(np.argmax(folded[: N_BINS // 4 + 1]))
    return abs((k + _refine(folded, k)) * RES_DEG)


def lobe_problems(f: np.ndarray, theta_v: float) -> list[str]:
    """What is wrong with a grid of eval values for viewer theta_v (empty: plausible lobes)."""
    out = []
    a = albedo(f)
    if abs(a - 1.0) > 0.03:
        out.append(f"albedo {a:.4f} is not 1")
    prof = theta_profile(f)
    th_peak = math.degrees(TH_L[int(np.argmax(prof))])
    if abs(th_peak + math.degrees(theta_v)) > RES_DEG:
        out.append(f"longitudinal peak at {th_peak:.2f} deg, not at -theta_v = {-math.degrees(theta_v):.2f}")
    dist = azimuthal(f)
    tt = forward_peak_deg(dist)
    if abs(tt - 180.0) > 0.5 * RES_DEG:
        out.append(f"forward (TT) peak at {tt:.1f} deg, not 180")
    # Forward scattering dominates a clear smooth fiber: the TT half holds most of the light.
    centres = np.arange(N_BINS) * RES_DEG
    fwd = float(dist[np.abs(centres - 180.0) < 90.0].sum() * BIN)
    if fwd < 0.6:
        out.append(f"forward half holds {fwd:.2f} of the light")
    return out


@pytest.fixture(scope="module")
def grids(ours, hair):
    """eval grids of both BSDFs per viewer theta (degrees)."""
    return {t: (grid_ours(ours, math.radians(t)), grid_hair(hair, math.radians(t))) for t in THETA_V_DEG}


# ---------------------------------------------------------------------------------------------
# Tests
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("theta_v_deg", THETA_V_DEG)
def test_directional_albedo_is_one_for_both(grids, table, theta_v_deg):
    """Same total energy: the integral of eval over the sphere is 1 for both (no absorption)."""
    fo, fh = grids[theta_v_deg]
    a_o, a_h = albedo(fo), albedo(fh)
    print(f"\n[hair-comparison] theta_v {theta_v_deg:4.1f} deg: albedo (quadrature of eval) "
          f"ours {a_o:.4f}, hair {a_h:.4f}, table Lambda {float(table.albedo(math.radians(theta_v_deg), 0.0)):.4f}")
    assert abs(a_o - 1.0) < 0.01
    assert abs(a_h - 1.0) < 0.02
    assert abs(a_o - a_h) < 0.02


def test_sampled_weights_average_to_one(ours, hair):
    """Importance-sampled estimate of the same integral: mean weight eval / pdf (h random for hair)."""
    n = 400_000
    rng = np.random.default_rng(7)
    ctx = mi.BSDFContext()
    for t in THETA_V_DEG:
        th = math.radians(t)
        h = rng.uniform(-1.0, 1.0, n)
        psi = 0.5 * math.pi + np.arcsin(h)
        s1 = mi.Float(rng.random(n).astype(np.float32))
        s2 = mi.Vector2f(mi.Float(rng.random(n).astype(np.float32)), mi.Float(rng.random(n).astype(np.float32)))
        _, w_h = hair.sample(ctx, _si(_dirs(np.full(n, th), psi), n), s1, s2)
        _, w_o = ours.sample(ctx, _si(_dirs(np.full(n, th), np.full(n, 0.3)), n), s1, s2)
        m_h, m_o = float(np.array(w_h)[0].mean()), float(np.array(w_o)[0].mean())
        print(f"\n[hair-comparison] theta_v {t:4.1f} deg: mean sample weight ours {m_o:.4f}, hair {m_h:.4f}")
        assert abs(m_o - 1.0) < 0.01 and abs(m_h - 1.0) < 0.02


@pytest.mark.parametrize("theta_v_deg", THETA_V_DEG)
def test_longitudinal_peak_at_minus_theta(grids, theta_v_deg):
    """The back-half (R, TRT) longitudinal lobe peaks at theta_l = -theta_v for both, within a bin."""
    fo, fh = grids[theta_v_deg]
    peaks = {}
    for name, f in (("ours", fo), ("hair", fh)):
        prof = theta_profile(f)
        peaks[name] = math.degrees(TH_L[int(np.argmax(prof))])
        mean = float((prof * TH_L).sum() / prof.sum())
        sd = math.degrees(math.sqrt(float((prof * (TH_L - mean) ** 2).sum() / prof.sum())))
        print(f"\n[hair-comparison] theta_v {theta_v_deg:4.1f} deg: {name} longitudinal peak "
              f"{peaks[name]:.2f} deg (std about the mean {sd:.2f} deg)")
        assert abs(peaks[name] + theta_v_deg) <= RES_DEG
    assert abs(peaks["ours"] - peaks["hair"]) <= RES_DEG


@pytest.mark.parametrize("theta_v_deg", THETA_V_DEG)
def test_azimuthal_lobes_agree(grids, theta_v_deg):
    """Forward TT peak at pi for both; back-scattering peaks (R + TRT glint) at the same place."""
    fo, fh = grids[theta_v_deg]
    d_o, d_h = azimuthal(fo), azimuthal(fh)
    d_x = exact_azimuthal(math.radians(theta_v_deg))
    tt_o, tt_h = forward_peak_deg(d_o), forward_peak_deg(d_h)
    bk_o, bk_h, bk_x = back_peak_deg(d_o), back_peak_deg(d_h), back_peak_deg(d_x)
    print(f"\n[hair-comparison] theta_v {theta_v_deg:4.1f} deg: azimuthal L1 (6 deg bins) ours-hair "
          f"{100 * l1(d_o, d_h):.2f} %, ours-exact {100 * l1(d_o, d_x):.2f} %, hair-exact {100 * l1(d_h, d_x):.2f} %; "
          f"TT peak ours {tt_o:.1f}, hair {tt_h:.1f} deg; back peak |dphi| ours {bk_o:.1f}, hair {bk_h:.1f}, "
          f"exact smooth {bk_x:.1f} deg")
    assert abs(tt_o - 180.0) <= 0.5 * RES_DEG and abs(tt_h - 180.0) <= 0.5 * RES_DEG
    assert abs(bk_o - bk_h) <= RES_DEG
    # The whole distributions: the same shape up to the modelling differences (docstring).
    assert l1(d_o, d_h) < 0.06
    # Both against the exact smooth circle (roughness blurs the caustics a little).
    assert l1(d_o, d_x) < 0.08 and l1(d_h, d_x) < 0.08
    assert lobe_problems(fo, math.radians(theta_v_deg)) == []
    assert lobe_problems(fh, math.radians(theta_v_deg)) == []


def test_checks_detect_wrong_frames(ours, hair):
    """The lobe checks flag a wrong tangent axis and a 90 deg azimuth error."""
    th = math.radians(21.0)
    # hair fed directions whose tangent is local z (Mitsuba's hair wants local y).
    bad_hair = grid_hair(hair, th, tangent_axis=2)
    assert lobe_problems(bad_hair, th), "hair with the tangent on z passed the checks"
    # Our BSDF with the shading frame's tangent on x while the fiber runs along y.
    bad_ours = grid_ours(ours, th, frame_t=(1.0, 0.0, 0.0))
    assert lobe_problems(bad_ours, th), "our BSDF with the tangent on x passed the checks"
    # A 90 deg azimuth error: the same values, phi shifted by a quarter turn.
    good = grid_ours(ours, th)
    shifted = np.roll(good, N_PHI // 4, axis=1)
    assert lobe_problems(good, th) == []
    probs = lobe_problems(shifted, th)
    assert any("TT" in p for p in probs), probs
