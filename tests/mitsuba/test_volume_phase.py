"""Volumetric cloth in Mitsuba: the fiber phase function (sampling vs evaluation, normalization,
Eq. 3's projected area), the medium's transmittance against Beer-Lambert, and a white furnace."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

import usdfiber  # noqa: F401  (registers schemas first)
from usdfiber.backend import mitsuba
from usdfiber.geometry.voxelize import VoxelGrid

from usdfiber.translators.mitsuba.fiber_bank import FiberBank, FiberSlot
from usdfiber.translators.mitsuba.volume.medium import brick_majorants, cloth_medium, cloth_shapes
from usdfiber.translators.mitsuba.volume.phase import fiber_phase

mi = mitsuba()
import drjit as dr  # noqa: E402  (after the variant is set)


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def uniform_grid(shape=(1, 1, 1), extinction=1.0, direction=(0.3, 0.8, 0.52), psi=0.9, voxel=1.0,
                 origin=(0.0, 0.0, 0.0)) -> VoxelGrid:
    """A grid of identical voxels: one slot, fibers along ``direction``, rotated by ``psi``."""
    nx, ny, nz = shape
    t = _unit(direction)
    ref = _unit(np.cross(t, [0.0, 0.0, 1.0]) if abs(t[2]) < 0.9 else np.cross(t, [1.0, 0.0, 0.0]))
    ax = math.cos(psi) * ref + math.sin(psi) * np.cross(t, ref)
    full = (nz, ny, nx)
    return VoxelGrid(origin=np.asarray(origin, float), voxel_size=float(voxel),
                     extinction=np.full(full, extinction, np.float32), length=np.full(full, 1.0, np.float32),
                     direction=np.broadcast_to(t, full + (3,)).astype(np.float32).copy(),
                     spread=np.zeros(full, np.float32), slot=np.zeros(full, np.int32),
                     axis=np.broadcast_to(ax, full + (3,)).astype(np.float32).copy(),
                     slot_length=np.ones((1,) + full, np.float32))


def _mei(n, wi, p=(0.5, 0.5, 0.5)):
    mei = dr.zeros(mi.MediumInteraction3f, n)
    mei.wi = mi.Vector3f(*[float(x) for x in _unit(wi)])
    mei.p = mi.Point3f(*[float(x) for x in p])
    return mei


# ---------------------------------------------------------------------------------------------
# Phase function
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("sigma,wi", [((0.0, 0.0, 0.0), (0.3, 0.5, 0.81)),
                                      ((1.0, 3.0, 8.0), (0.7, -0.2, 0.5)),
                                      ((0.0, 0.0, 0.0), (-0.1, 0.9, 0.3))])
def test_phase_chi2_sampling_matches_pdf(silk_render_table, sigma, wi):
    """Chi-square (Mitsuba's test, significance 1e-2 over its 1 - (1 - 0.01)^(1/ n) per test
    correction) of sampled directions against pdf, for a non-round fiber rotated by psi in a
    frame that is not the world's."""
    bank = FiberBank.build([FiberSlot(silk_render_table, sigma)])
    ph = fiber_phase(mi, bank, uniform_grid(psi=1.1))
    ctx = mi.PhaseFunctionContext(None)

    def sample(s):
        wo, _, _ = ph.sample(ctx, _mei(dr.width(s), wi), s[0], mi.Point2f(s[1], s[2]))
        return wo

    def pdf(wo):
        return ph.eval_pdf(ctx, _mei(dr.width(wo), wi), wo)[1]

    test = mi.chi2.ChiSquareTest(domain=mi.chi2.SphericalDomain(), sample_func=sample, pdf_func=pdf,
                                 sample_dim=3, sample_count=300_000, res=41, ires=16)
    # Pearson chi-square: false failure = the significance level, 1e-4 (docs/testing.md).
    assert test.run(significance_level=1e-4), test.messages


def _sphere_quadrature(n_z=600, n_phi=1200):
    z = -1.0 + (np.arange(n_z) + 0.5) * (2.0 / n_z)
    ph = (np.arange(n_phi) + 0.5) * (2 * math.pi / n_phi)
    Z, P = np.meshgrid(z, ph, indexing="ij")
    r = np.sqrt(1 - Z**2)
    d = np.stack([r * np.cos(P), r * np.sin(P), Z], -1).reshape(-1, 3)
    return d, 4 * math.pi / (n_z * n_phi)


@pytest.mark.parametrize("sigma", [(0.0, 0.0, 0.0), (0.5, 2.0, 6.0)])
def test_phase_normalized_to_albedo(silk_render_table, sigma):
    """The pdf integrates to 1 over the sphere and the value to the table's albedo
    Lambda(omega_v) (1 without dye): the phase is the normalized BCSDF, the albedo rides in
    its value. Deterministic quadrature (720k directions): no random failure."""
    bank = FiberBank.build([FiberSlot(silk_render_table, sigma)])
    psi = 0.7
    grid = uniform_grid(psi=psi)
    ph = fiber_phase(mi, bank, grid)
    d, w = _sphere_quadrature()
    wo = mi.Vector3f(*[mi.Float(d[:, k].astype(np.float32)) for k in range(3)])
    rec = silk_render_table.recolour(list(sigma))
    for wi in ((0.3, 0.5, 0.81), (0.9, -0.3, 0.1)):
        val, pdf = ph.eval_pdf(mi.PhaseFunctionContext(None), _mei(len(d), wi), wo)
        total = np.array(val, np.float64)
        total = (total if total.shape[-1] == 3 else total.T).sum(axis=0) * w
        assert abs(np.array(pdf, np.float64).sum() * w - 1.0) < 5e-3
        # The table's own albedo at omega_v in the fiber frame.
        t = grid.direction[0, 0, 0].astype(float)
        x = grid.axis[0, 0, 0].astype(float)
        v = _unit(wi)
        th = math.asin(float(np.clip(v @ t, -1, 1)))
        phi = math.atan2(float(v @ np.cross(t, x)), float(v @ x))
        alb = np.asarray(rec.albedo_at(np.array([th]), np.array([phi])), float).reshape(-1)[:3]
        if not any(sigma):
            assert np.allclose(total, 1.0, atol=1e-2)
        assert np.allclose(total, alb, rtol=2e-2, atol=2e-3), (total, alb)


def test_projected_area_is_eq3_direction_factor(silk_render_table):
    """projected_area = (W(phi') / D) cos(theta') from the table's width, at most 1."""
    bank = FiberBank.build([FiberSlot(silk_render_table, (0.0, 0.0, 0.0))])
    grid = uniform_grid(psi=0.4)
    ph = fiber_phase(mi, bank, grid)
    rng = np.random.default_rng(1)
    d = rng.normal(size=(2000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    mei = dr.zeros(mi.MediumInteraction3f, len(d))
    mei.wi = mi.Vector3f(*[mi.Float(d[:, k].astype(np.float32)) for k in range(3)])
    mei.p = mi.Point3f(0.5, 0.5, 0.5)
    got = np.array(ph.projected_area(mei), np.float64)
    t, x = grid.direction[0, 0, 0].astype(float), grid.axis[0, 0, 0].astype(float)
    ct = np.sqrt(np.clip(1 - (d @ t) ** 2, 0, 1))
    phi = np.arctan2(d @ np.cross(t, x), d @ x)
    width = np.asarray(silk_render_table.arrays["width"], float) / silk_render_table.baked_diameter_um
    n = len(width)
    want = np.interp(np.mod(phi, 2 * math.pi), 2 * math.pi * np.arange(n + 1) / n, np.append(width, width[0])) * ct
    assert got.max() <= 1.0 + 1e-6
    assert np.allclose(got, want, atol=2e-4)
    assert width.min() < 0.8 * width.max()    # a non-round profile: the test sees phi


# ---------------------------------------------------------------------------------------------
# Medium: transmittance and furnace
# ---------------------------------------------------------------------------------------------

def _ratio_tracking(medium, o, d, n, seed):
    """Ratio-tracking estimates of the transmittance from o along d out of the medium's box:
    per ray the product of sigma_n / majorant over tentative collisions (unbiased)."""
    rng = np.random.default_rng(seed)
    o_ = [mi.Float(np.full(n, float(v), np.float32)) for v in o]
    ray = mi.Ray3f(mi.Point3f(*o_), mi.Vector3f(*[float(v) for v in d]))
    tr = mi.Float(np.ones(n, np.float32))
    active = mi.Bool(np.ones(n, bool))
    for _ in range(400):
        u = mi.Float(rng.random(n).astype(np.float32))
        mei = medium.sample_interaction(ray, u, mi.UInt32(0), active)
        hit = active & mei.is_valid()
        ratio = dr.select(hit, mei.sigma_n[0] / mei.combined_extinction[0], 1.0)
        tr = tr * ratio
        ray.o = dr.select(hit, mei.p, ray.o)
        active = hit & (tr > 0)
        dr.eval(tr, ray.o, active)
        if not dr.any(active):
            break
    return np.array(tr, np.float64)


def eq3_factor(table, grid: VoxelGrid, d: np.ndarray) -> float:
    """(W(phi') / D) cos(theta') of the grid's first voxel for rays along ``d`` (Mitsuba's wi is
    -d; W(phi + pi) = W(phi) and cos theta is even: the same factor)."""
    t, x = grid.direction[0, 0, 0].astype(float), grid.axis[0, 0, 0].astype(float)
    w = -np.asarray(d, float)
    ct = math.sqrt(max(0.0, 1 - float(w @ t) ** 2))
    phi = math.atan2(float(w @ np.cross(t, x)), float(w @ x))
    width = np.asarray(table.arrays["width"], float) / table.baked_diameter_um
    n_w = len(width)
    return ct * float(np.interp(phi % (2 * math.pi), 2 * math.pi * np.arange(n_w + 1) / n_w,
                                np.append(width, width[0])))


@pytest.mark.parametrize("direction", [(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0),
                                       (0.6, 0.0, 0.8), (0.3, -0.5, 0.81), (0.9, 0.3, -0.3)])
def test_transmittance_is_beer_lambert_with_eq3(silk_render_table, direction):
    """A uniform slab of aligned silk fibers (along x, rotated by psi): the transmittance along
    and across the fibers is exp(-E (W(phi')/D) cos(theta') s), s the path length in the slab.
    Bound: 5 standard errors of the mean of 100k independent ratio-tracking estimates (the
    standard error estimated from the same 100k values): false failure below 1e-6."""
    bank = FiberBank.build([FiberSlot(silk_render_table, (0.0, 0.0, 0.0))])
    E = 1.2
    grid = uniform_grid(shape=(4, 4, 4), extinction=E, direction=(1.0, 0.0, 0.0), psi=0.5, voxel=0.5)
    medium = cloth_medium(mi, grid, bank)
    d = _unit(direction)
    centre = np.array([1.0, 1.0, 1.0])
    # From the centre of the 2-unit cube to its boundary along d.
    s = min((1.0 / abs(c)) for c in d if abs(c) > 1e-9)
    want = math.exp(-E * eq3_factor(silk_render_table, grid, d) * s)
    est = _ratio_tracking(medium, centre, d, 100_000, seed=7)
    se = est.std(ddof=1) / math.sqrt(len(est))
    assert abs(est.mean() - want) < 5 * se + 1e-4, (est.mean(), want, se)


@pytest.mark.slow
def test_white_furnace(silk_render_table):
    """A non-absorbing fiber volume (optical thickness ~ 10) in a uniform white dome reads 1.

    Tests the phase normalization, albedo 1 and the anisotropic extinction consistent between
    free-flight sampling and shadow-ray transmittance. The image mean over 32 x 32 pixels at
    64 spp, bound 1 % and at least 5 standard errors (standard error from the pixel values,
    1023 degrees of freedom): false failure below 1e-6."""
    bank = FiberBank.build([FiberSlot(silk_render_table, (0.0, 0.0, 0.0))])
    rng = np.random.default_rng(0)
    grid = uniform_grid(shape=(6, 6, 6), extinction=8.0, direction=(0.2, 0.9, 0.3), psi=0.3, voxel=1.0 / 3.0,
                        origin=(-1.0, -1.0, -1.0))
    # Vary the voxels: different directions and rotations and densities per voxel.
    dirs = rng.normal(size=grid.direction.shape)
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    grid.direction[:] = dirs
    ax = np.cross(dirs, rng.normal(size=dirs.shape))
    grid.axis[:] = ax / np.linalg.norm(ax, axis=-1, keepdims=True)
    grid.extinction[:] = rng.uniform(2.0, 14.0, grid.extinction.shape)
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "volpath", "max_depth": -1, "rr_depth": 50},
        "dome": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
        # Bricks of 2 voxels: 27 media with their own majorants behind shared faces.
        **cloth_shapes(mi, grid, bank, brick=2),
        "sensor": {"type": "perspective", "fov": 25.0,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 32, "height": 32, "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": 64}},
    })
    img = np.array(mi.render(scene, seed=int(rng.integers(1 << 30))), np.float64)
    vals = img.mean(axis=2).reshape(-1)
    se = vals.std(ddof=1) / math.sqrt(len(vals))
    assert 5 * se < 0.01, se                  # the test resolves 1 %
    assert abs(vals.mean() - 1.0) < 0.01, (vals.mean(), se)


def brick_grid(seed: int = 4) -> VoxelGrid:
    """A 6^3 grid over [-1, 1]^3 of aligned silk fibers whose density varies per voxel and, by
    a factor 0 to 8, per 2^3 brick (a third of the bricks empty)."""
    rng = np.random.default_rng(seed)
    grid = uniform_grid(shape=(6, 6, 6), direction=(0.2, 0.9, 0.3), psi=0.3, voxel=1.0 / 3.0, origin=(-1.0, -1.0, -1.0))
    per_brick = rng.choice([0.0, 0.0, 0.0, 0.3, 1.0, 2.5, 6.0, 8.0, 8.0], size=(3, 3, 3))
    grid.extinction[:] = (rng.uniform(0.2, 1.0, (6, 6, 6)) * per_brick.repeat(2, 0).repeat(2, 1).repeat(2, 2))
    return grid


def exact_transmittance(grid: VoxelGrid, factor: float, d: np.ndarray, centre: np.ndarray, u: np.ndarray,
                        v: np.ndarray, half: float, n_rays: int = 96, n_steps: int = 1200) -> float:
    """Mean over the square ``centre + a u + b v`` (|a|, |b| <= half) of exp(-optical depth) of
    rays along ``d``: midpoint rules over the square and along the rays (nearest voxels)."""
    ab = (np.arange(n_rays) + 0.5) / n_rays * 2 * half - half
    A, B = np.meshgrid(ab, ab, indexing="ij")
    o = centre + A.reshape(-1, 1) * u + B.reshape(-1, 1) * v
    length = 2 * np.linalg.norm(centre)
    s = (np.arange(n_steps) + 0.5) / n_steps * length
    nx, ny, nz = grid.shape
    tau = np.zeros(len(o))
    for c in range(0, len(o), 2000):
        p = o[c:c + 2000, None, :] + s[None, :, None] * d
        ijk = np.floor((p - grid.origin) / grid.voxel_size).astype(int)
        inside = np.all((ijk >= 0) & (ijk < [nx, ny, nz]), axis=-1)
        ijk = np.where(inside[..., None], ijk, 0)
        e = np.where(inside, grid.extinction[ijk[..., 2], ijk[..., 1], ijk[..., 0]], 0.0)
        tau[c:c + 2000] = e.sum(axis=1) * (length / n_steps)
    return float(np.exp(-factor * tau).mean())


@pytest.mark.parametrize("brick,direction", [(2, (0.0, 0.0, 1.0)), (2, (0.45, -0.5, 0.74)), (0, (0.45, -0.5, 0.74))])
def test_transmittance_through_bricks_is_exact(silk_render_table, brick, direction):
    """Camera rays through bricks of different majorants (and empty bricks), rendered with
    volpath to the first real collision (max_depth 1: a pixel sample is 1 if the ray escapes
    to the white dome, else 0), average the exact transmittance over the view: brick faces
    lose or double no medium. ``brick = 0``: one medium, one majorant. Bound: 5 standard
    errors of the image mean (the standard error from the 4,096 pixel values, which also
    holds the image's own variation: conservative) plus 3e-3 for the quadrature of the exact
    value (96^2 rays x 1,200 steps; 4e-5 from 160^2 x 2,400): false failure below 1e-6."""
    bank = FiberBank.build([FiberSlot(silk_render_table, (0.0, 0.0, 0.0))])
    grid = brick_grid()
    if brick:
        maj = brick_majorants(grid, brick)
        assert (maj == 0).any() and maj.max() > 4 * maj[maj > 0].min()    # the test sees bricks
    d = _unit(direction)
    centre = -4.0 * d
    up = _unit(np.cross(d, [0.3, 1.0, 0.1]))
    right = np.cross(up, d)
    half = 1.2
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "volpath", "max_depth": 1},
        "dome": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
        **cloth_shapes(mi, grid, bank, brick=brick),
        "sensor": {"type": "orthographic",
                   "to_world": mi.ScalarTransform4f().look_at(origin=[float(x) for x in centre], target=[0, 0, 0],
                                                              up=[float(x) for x in up]).scale([half, half, 1.0]),
                   "film": {"type": "hdrfilm", "width": 64, "height": 64, "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": 64}},
    })
    img = np.array(mi.render(scene, seed=int(np.random.default_rng().integers(1 << 30))), np.float64)
    vals = img.mean(axis=2).reshape(-1)
    se = vals.std(ddof=1) / math.sqrt(len(vals))
    want = exact_transmittance(grid, eq3_factor(silk_render_table, grid, d), d, centre, right, up, half)
    assert 0.2 < want < 0.8                                     # rays cross the cloth
    assert abs(vals.mean() - want) < 5 * se + 3e-3, (vals.mean(), want, se)


def test_bricks_cover_the_occupied_voxels_and_stay_few(silk_render_table):
    """Bricks: every occupied voxel lies in a brick with a medium, whose majorant bounds it;
    empty bricks get none; a grid past MAX_BRICKS gets larger bricks; a grid without extinction
    gives no entries (the documented fallback)."""
    from usdfiber.translators.mitsuba.volume.medium import MAX_BRICKS, brick_size

    bank = FiberBank.build([FiberSlot(silk_render_table, (0.0, 0.0, 0.0))])
    grid = brick_grid()
    maj = brick_majorants(grid, 2)
    per_voxel = maj.repeat(2, 0).repeat(2, 1).repeat(2, 2)
    assert np.all(per_voxel >= grid.extinction) and np.all((per_voxel > 0) | (grid.extinction == 0))
    shapes = cloth_shapes(mi, grid, bank, brick=2)
    n_media = int((maj > 0).sum())
    # Faces: every occupied brick has 6, shared ones counted once.
    occ = np.pad(maj > 0, 1)
    shared = sum(int((np.take(occ, range(1, occ.shape[a]), a) & np.take(occ, range(occ.shape[a] - 1), a)).sum())
                 for a in range(3))
    assert len(shapes) == 6 * n_media - shared
    assert brick_size(grid, 2) == 2
    big = SimpleNamespace(shape=(512, 512, 16))          # brick_size reads the shape only
    assert math.prod(math.ceil(n / 8) for n in big.shape) > MAX_BRICKS and brick_size(big, 8) == 16
    empty = uniform_grid(shape=(2, 2, 2), extinction=0.0)
    assert cloth_shapes(mi, empty, bank, brick=2) == {} and cloth_shapes(mi, empty, bank, brick=0) == {}
