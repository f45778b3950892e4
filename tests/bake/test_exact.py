"""Exact far field of a smooth circular dielectric fiber."""
from __future__ import annotations

import numpy as np
import pytest

from usdfiber.bake import exact


def fresnel_polarized(theta_i: float, n1: float, n2: float) -> float:
    """Textbook Fresnel with Snell angles (an independent formulation)."""
    s = n1 / n2 * np.sin(theta_i)
    if s >= 1.0:
        return 1.0
    theta_t = np.arcsin(s)
    rs = (n1 * np.cos(theta_i) - n2 * np.cos(theta_t)) / (n1 * np.cos(theta_i) + n2 * np.cos(theta_t))
    rp = (n2 * np.cos(theta_i) - n1 * np.cos(theta_t)) / (n2 * np.cos(theta_i) + n1 * np.cos(theta_t))
    return 0.5 * (rs * rs + rp * rp)


def test_fresnel_against_textbook_and_limits():
    for ang in np.linspace(0, 1.55, 23):
        for n1, n2 in [(1.0, 1.55), (1.55, 1.0), (1.0, 1.33), (1.73, 1.0)]:
            f = exact.fresnel_dielectric(np.cos(ang), n2 / n1)
            assert f == pytest.approx(fresnel_polarized(ang, n1, n2), abs=1e-12)
    eta = 1.55
    assert exact.fresnel_dielectric(1.0, eta) == pytest.approx(((eta - 1) / (eta + 1)) ** 2, abs=1e-15)
    assert exact.fresnel_dielectric(0.0, eta) == 1.0
    assert exact.fresnel_dielectric(0.1, 1 / eta) == 1.0  # total internal reflection
    assert np.all(exact.fresnel_dielectric(np.linspace(0, 1, 11), 1.0) == 0.0)
    assert np.all(np.isfinite(exact.fresnel_dielectric(np.linspace(0, 1, 101), 1.0 / 1.55)))


def test_bravais_index():
    assert exact.bravais_eta(1.55, 0.0) == pytest.approx(1.55)
    th = 0.7
    assert exact.bravais_eta(1.55, th) == pytest.approx(np.sqrt(1.55**2 - np.sin(th) ** 2) / np.cos(th))
    assert exact.bravais_eta(1.0, 0.9) == pytest.approx(1.0)
    assert np.isfinite(exact.bravais_eta(1.55, np.pi / 2))


@pytest.mark.parametrize("theta", [0.0, 0.3, 0.8, 1.2, 1.5, np.radians(89.9)])
@pytest.mark.parametrize("eta", [1.33, 1.54, 1.55, 1.73])
def test_energy_conservation(theta, eta):
    h = np.concatenate([np.linspace(-1, 1, 201), [1 - 1e-12, -1 + 1e-9]])
    p_max = 40
    a = np.array([exact.attenuation(p, h, theta, eta) for p in range(p_max + 1)])
    f = exact.attenuation(0, h, theta, eta)
    tail = (1 - f) * f**p_max  # sum over p > p_max of (1 - F)^2 F^(p - 1)
    np.testing.assert_allclose(a.sum(axis=0) + tail, 1.0, atol=1e-10)
    assert exact.total_energy(theta, eta, 0.0) == pytest.approx(1.0, abs=1e-10)
    assert exact.total_energy(theta, eta, 0.7) < 1.0
    assert exact.total_energy(theta, eta, np.inf) == pytest.approx(exact.reflection_energy(theta, eta), abs=1e-12)


# ---------------------------------------------------------------------------------------------
# A deterministic vector trace of the unit circle (exact intersections), independent of the
# formula: refract, bounce inside, and record where each path p leaves.
# ---------------------------------------------------------------------------------------------

def _fresnel_vec(cos_i, eta_rel):
    return fresnel_polarized(np.arccos(min(cos_i, 1.0)), 1.0, eta_rel)


def _refract(d, n, eta_rel):
    """Refract unit d through unit normal n (facing against d), eta_rel = eta_t / eta_i."""
    cos_i = -d @ n
    r = 1.0 / eta_rel
    k = 1.0 - r * r * (1.0 - cos_i * cos_i)
    return r * d + (r * cos_i - np.sqrt(k)) * n


def _reflect(d, n):
    return d - 2.0 * (d @ n) * n


def trace_circle(h, theta, eta, sigma_a, p_max):
    """Exit azimuth (relative to phi_i = 0), exit theta and power of paths p = 0..p_max."""
    omega_i = np.array([np.cos(theta), 0.0, np.sin(theta)])
    d = -omega_i
    # Impact parameter along (sin phi_i, -cos phi_i) = (0, -1): the photon travels at y = -h.
    o = np.array([2.0, -h, 0.0])

    def next_hit(o, d):
        # |o_xy + t d_xy| = 1, the far root (inside) or the near root (outside).
        a = d[0] ** 2 + d[1] ** 2
        b = 2 * (o[0] * d[0] + o[1] * d[1])
        c = o[0] ** 2 + o[1] ** 2 - 1
        disc = np.sqrt(max(b * b - 4 * a * c, 0.0))
        ts = [(-b - disc) / (2 * a), (-b + disc) / (2 * a)]
        t = min(x for x in ts if x > 1e-12)
        p = o + t * d
        return p, t

    p, _ = next_hit(o, d)
    n = np.array([p[0], p[1], 0.0])
    cos_i = -d @ n
    f0 = _fresnel_vec(cos_i, eta)
    out = []
    r = _reflect(d, n)
    out.append((np.arctan2(r[1], r[0]), np.arcsin(r[2]), f0))
    power = 1.0 - f0
    d = _refract(d, n, eta)
    o = p
    for k in range(1, p_max + 1):
        p, t = next_hit(o, d)
        power *= np.exp(-sigma_a * t)  # t is the 3D length in units of the radius
        n = np.array([p[0], p[1], 0.0])
        cos_i = d @ n
        f = _fresnel_vec(cos_i, 1.0 / eta)
        out_d = _refract(d, -n, 1.0 / eta)
        out.append((np.arctan2(out_d[1], out_d[0]), np.arcsin(np.clip(out_d[2], -1, 1)), power * (1 - f)))
        power *= f
        d = _reflect(d, -n)
        o = p
    return out


@pytest.mark.parametrize("theta, eta", [(0.0, 1.55), (0.5, 1.55), (1.1, 1.54), (-0.7, 1.73), (1.4, 1.33)])
def test_formula_matches_vector_trace(theta, eta):
    sigma_a = 0.3
    for h in [-0.95, -0.6, -0.2, 0.05, 0.4, 0.8, 0.99]:
        paths = trace_circle(h, theta, eta, sigma_a, p_max=5)
        for p, (phi, th_o, power) in enumerate(paths):
            expected = exact.exit_azimuth(p, h, theta, eta)
            diff = np.angle(np.exp(1j * (phi - expected)))
            assert abs(diff) < 1e-9, (p, h)
            assert th_o == pytest.approx(float(exact.exit_theta(theta)), abs=1e-9)
            assert power == pytest.approx(float(exact.attenuation(p, h, theta, eta, sigma_a)), abs=1e-9)


def test_conventions_backscatter_and_forward():
    # R at h = 0 goes straight back to the light (phi_o = phi_i), TT at h = 0 straight through.
    assert exact.exit_azimuth(0, 0.0, 0.3, 1.55) == pytest.approx(0.0)
    assert exact.exit_azimuth(1, 0.0, 0.3, 1.55) == pytest.approx(np.pi)
    # R maps uniform h to phi = -2 asin(h): with F replaced by 1 its density would be
    # cos(phi / 2) / 4 per radian over (-pi, pi); check the mapping through the formula.
    h = np.linspace(-0.999, 0.999, 7)
    np.testing.assert_allclose(exact.exit_azimuth(0, h, 0.4, 1.55), -2 * np.arcsin(h), atol=1e-15)


def test_distribution_normalization_and_symmetry():
    for sigma_a in [0.0, 0.5]:
        d = exact.azimuthal_distribution(0.4, 1.55, sigma_a=sigma_a, n_bins=180, n_h=1 << 20)
        assert d.shape == (180,)
        energy = d.sum() * 2 * np.pi / 180
        assert energy == pytest.approx(exact.total_energy(0.4, 1.55, sigma_a), abs=1e-6)
        # Mirror symmetry h -> -h: phi -> -phi.
        np.testing.assert_allclose(d, d[::-1], atol=2e-3 * d.max())


def test_eta_one_sends_everything_forward():
    for theta in [0.0, 0.6, 1.2]:
        d = exact.azimuthal_distribution(theta, 1.0, n_bins=180, n_h=1 << 18)
        bw = 2 * np.pi / 180
        # Straight through: phi_o - phi_i = pi, the edge between bins 89 and 90.
        assert (d[89] + d[90]) * bw == pytest.approx(1.0, abs=1e-12)
        assert exact.reflection_energy(theta, 1.0) == 0.0
    # Approaching 1, the light concentrates around the forward direction.
    d = exact.azimuthal_distribution(0.2, 1.001, n_bins=180, n_h=1 << 19)
    bw = 2 * np.pi / 180
    assert d[85:95].sum() * bw > 0.99


def test_reflection_lobe_energy_is_mean_fresnel():
    h = np.linspace(-1, 1, 200001)
    f = exact.fresnel_dielectric(np.cos(0.5) * np.sqrt(1 - h * h), 1.55)
    assert exact.reflection_energy(0.5, 1.55) == pytest.approx(np.trapezoid(f, h) / 2, abs=1e-6)
    d = exact.azimuthal_distribution(0.5, 1.55, sigma_a=np.inf, n_h=1 << 18)
    assert d.sum() * 2 * np.pi / 180 == pytest.approx(exact.reflection_energy(0.5, 1.55, n_h=1 << 18), abs=1e-12)


def test_exit_theta_is_mirror():
    np.testing.assert_array_equal(exact.exit_theta(np.array([0.3, -1.0])), [-0.3, 1.0])
