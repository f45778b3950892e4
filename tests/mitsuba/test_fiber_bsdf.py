"""The tabulated BCSDF in Mitsuba: sampling against evaluation, weights, furnace, one fiber vs table."""
from __future__ import annotations

import math

import numpy as np
import pytest

import usdfiber  # noqa: F401  (registers schemas first)
from usdfiber.backend import mitsuba
from usdfiber.bake import profiles
from usdfiber.bake.baker import bake_table
from usdfiber.bake.settings import BakeSettings

from usdfiber.translators.mitsuba.curves import CurveGeometry, make_curve_shape
from usdfiber.translators.mitsuba.fiber_bank import FiberBank, FiberSlot, bilinear_integral
from usdfiber.translators.mitsuba.fiber_bsdf import fiber_bsdf
from usdfiber.translators.mitsuba.integrator import register as register_integrator
from usdfiber.translators.mitsuba.scene import fiber_integrator

from fiber_frame import fiber_interaction, unit
from stats_util import FALSE_FAILURE, binomial_limit, z_limit

mi = mitsuba()
import drjit as dr  # noqa: E402  (after the variant is set)

ETA = 1.55


@pytest.fixture(scope="module")
def wool():
    prof = profiles.builtin_profiles("wool", 1)[0]
    return bake_table(prof, ETA, 8.0, (3.0, 0.03, 0.2), BakeSettings(resolution_deg=30, photons=1500, batches=2))


def _ctx(null: bool):
    ctx = mi.BSDFContext()
    if not null:
        ctx.type_mask = int(mi.BSDFFlags.Glossy)
    return ctx


def _bsdf(slots, psi=0.4, pass_through=True):
    bank = FiberBank.build(slots)
    return fiber_bsdf(mi, bank, [0], [psi], np.array([[1.0, 0.0, 0.0]]), pass_through=pass_through)


# ---------------------------------------------------------------------------------------------
# Layout
# ---------------------------------------------------------------------------------------------

def test_bank_slices_normalized_and_mirrored(silk_render_table, circle_table):
    bank = FiberBank.build([FiberSlot(silk_render_table, (0.0, 0.0, 0.0)), FiberSlot(circle_table, (0.0, 0.0, 0.0))])
    for fam in bank.families.values():
        # Normalized before float16 rounding (2^-11 relative per node): the integrals within 5e-4.
        assert np.allclose(bilinear_integral(fam.pdf.astype(np.float64)), 1.0, atol=5e-4)
        # Extruded fibers: only theta_v >= 0 is stored; the slice at -theta_v is read as the
        # mirror (theta_l -> -theta_l) of +theta_v (the device lookup's own test:
        # tests/mitsuba/test_device_incoming_nodes.py).
        n = fam.pdf.shape[1]
        assert fam.mirrored and all(a.shape[0] == n // 2 for a in fam.nodes)
        assert np.allclose(fam.pdf[:, 0], fam.pdf[:, n - 1, :, ::-1], atol=1e-7)
        # phi wraps: the last column repeats the first.
        assert np.array_equal(fam.pdf[..., 0], fam.pdf[..., -1])
    assert bank.families[False].f.shape[-1] == 3


def test_bank_resamples_other_resolutions(circle_table):
    # A table of another resolution is resampled onto the family grid with its own interpolation.
    coarse = bake_table(profiles.circle(), ETA, 8.0, None, BakeSettings(resolution_deg=15, photons=8000, batches=2))
    bank = FiberBank.build([FiberSlot(circle_table, (0.0, 0.0, 0.0)), FiberSlot(coarse, (0.0, 0.0, 0.0))])
    fam = bank.families[True]
    assert fam.resolution_deg == 10.0
    assert np.allclose(bilinear_integral(fam.pdf.astype(np.float64)), 1.0, atol=5e-4)
    # Both describe the same fiber: the slices agree to the tables' noise and resolution.
    a, b = fam.pdf[0].astype(np.float64), fam.pdf[1].astype(np.float64)
    # A bound on resampling a coarser grid (the difference of 10 and 15 degree bins), not on
    # noise: at 20000 and 8000 photons per direction the tables' own noise adds a few percent.
    assert np.abs(a - b).sum() / np.abs(a).sum() < 0.35


# ---------------------------------------------------------------------------------------------
# Sampling against evaluation
# ---------------------------------------------------------------------------------------------

CHI2_CASES = [
    ("circle_table", (0.0, 0.0, 0.0), (0.3, 0.5, 0.81)),
    ("circle_table", (0.0, 0.0, 0.0), (0.9, -0.1, 0.4)),
    ("silk_render_table", (0.0, 0.0, 0.0), (0.3, 0.5, 0.81)),
    ("silk_render_table", (1.0, 3.0, 8.0), (0.7, -0.2, 0.5)),
    ("wool", (0.0, 0.0, 0.0), (0.2, -0.7, 0.6)),
    ("wool", (0.0, 0.0, 0.0), (0.6, 0.6, 0.5)),
]


@pytest.mark.parametrize("name,sigma,wi", CHI2_CASES)
def test_chi2_sampling_matches_pdf(request, name, sigma, wi):
    table = request.getfixturevalue(name)
    b = _bsdf([FiberSlot(table, sigma)])
    wi = unit(wi)

    def sample(s):
        bs, _ = b.sample(_ctx(False), fiber_interaction(dr.width(s), wi), s[0], mi.Vector2f(s[1], s[2]))
        return bs.wo

    def pdf(wo):
        return b.pdf(_ctx(False), fiber_interaction(dr.width(wo), wi), wo)

    test = mi.chi2.ChiSquareTest(domain=mi.chi2.SphericalDomain(), sample_func=sample, pdf_func=pdf,
                                 sample_dim=3, sample_count=300_000, res=41, ires=16)
    # Pearson chi-square over the sphere's cells (low-expectation cells pooled by Mitsuba):
    # false failure = the significance level (Mitsuba's default is 1e-2).
    assert test.run(significance_level=FALSE_FAILURE), test.messages


def _moved_by_ulps(b, si, wo, ctx, angle: float = 4e-7):
    """eval / pdf and pdf at ``wo`` (local, numpy-convertible) turned by ``angle`` radians
    (about 4 float32 ulps of an angle near 1) about two axes: arrays (4, 3, n) and (4, n)."""
    wo = np.array(wo, dtype=np.float64)
    ref = np.where(np.abs(wo[2:3]) < 0.9, np.array([[0.0], [0.0], [1.0]]), np.array([[1.0], [0.0], [0.0]]))
    e1 = np.cross(wo.T, ref.T).T
    e1 /= np.linalg.norm(e1, axis=0)
    e2 = np.cross(wo.T, e1.T).T
    ratios, pdfs = [], []
    for e in (e1, -e1, e2, -e2):
        d = wo + angle * e
        d /= np.linalg.norm(d, axis=0)
        dv = mi.Vector3f(*(mi.Float(c.astype(np.float32)) for c in d))
        v, p = b.eval_pdf(ctx, si, dv)
        v, p = np.array(v), np.array(p)
        ratios.append(v / np.maximum(p, 1e-30)[None, :])
        pdfs.append(p)
    return np.stack(ratios), np.stack(pdfs)


@pytest.mark.parametrize("name", ["circle_table", "silk_render_table", "wool"])
def test_sample_weight_mean_is_albedo(request, name):
    """E[weight] = Lambda(omega_v): the sampled BSDF conserves exactly the table's energy."""
    table = request.getfixturevalue(name)
    n = 200_000
    rng = np.random.default_rng(3)
    for sigma in ((0.0, 0.0, 0.0), (0.5, 2.0, 6.0)):
        b = _bsdf([FiberSlot(table, sigma)], psi=0.0, pass_through=False)
        wi = unit(rng.normal(size=3))
        si = fiber_interaction(n, wi)
        s1 = mi.Float(rng.random(n).astype(np.float32))
        s2 = mi.Vector2f(mi.Float(rng.random(n).astype(np.float32)), mi.Float(rng.random(n).astype(np.float32)))
        bs, w = b.sample(_ctx(True), si, s1, s2)
        val, pdf = b.eval_pdf(_ctx(True), si, bs.wo)
        w, val, pdf = np.array(w), np.array(val), np.array(pdf)
        assert np.all(np.isfinite(w)) and np.all(w >= 0)
        # eval / pdf at the sampled direction is the weight, and the pdf is the sampler's, up
        # to 2e-3 and to how much they change when the direction moves by a few float32 ulps:
        # the sampler weighs its own point of the table, eval the point recovered from the
        # returned direction (an angle about 1e-7 rad off). Next to a row that a dye darkens
        # to almost nothing, a channel is nearly proportional to the distance from it and a
        # sample drawn 1e-5 of a row away from it moved by 1 % (one in 2e5 at 8 lanes).
        ratio = val / pdf[None, :]
        ratio_moved, pdf_moved = _moved_by_ulps(b, si, bs.wo, _ctx(True))
        slack_r = np.abs(ratio_moved - ratio[None]).max(axis=0)
        slack_p = np.abs(pdf_moved - pdf[None]).max(axis=0)
        assert np.all(np.abs(ratio - w) <= 2e-3 * np.abs(w) + 1e-6 + slack_r)
        assert np.all(np.abs(np.array(bs.pdf) - pdf) <= 2e-3 * pdf + slack_p)
        # The slack is local: a wrong weight or pdf would not hide in it.
        assert np.quantile(slack_r.max(axis=0) / np.maximum(w.max(axis=0), 1e-12), 0.999) < 1e-3
        # Frame of _si with psi = 0: t = +y, x = +x, y = t x x = -z.
        th_v, ph_v = math.asin(wi[1]), math.atan2(-wi[2], wi[0])
        albedo = table.recolour(list(sigma)).albedo_at(th_v, ph_v)
        # 1 % for bilinear interpolation between the table's nodes, plus the noise of the
        # mean of n weights: z_limit standard errors (estimated from the 2e5 weights; three
        # channels share the 1e-4). The former 1 % alone was 3.2 standard errors for dyed
        # wool's blue channel (albedo 0.20, standard error 6.3e-4): false failure 1.4e-3.
        se = w.std(axis=1) / math.sqrt(n)
        tol = 0.01 * albedo + z_limit(FALSE_FAILURE / 3) * se
        assert np.all(np.abs(w.mean(axis=1) - albedo) <= tol), (w.mean(axis=1), albedo, se)
        if sigma == (0.0, 0.0, 0.0):
            # Undyed: grey weights equal to Lambda (between incoming nodes, the nodes'
            # Lambda weighted by their p), 1 up to photons stopped by max_bounces.
            assert np.array_equal(w, np.broadcast_to(w[:1], w.shape))
            assert np.abs(w - 1.0).max() < 2e-3
        else:
            # Dyed: the undyed density stays a good proposal (dyes only remove light; the
            # bilinear representation of each colour is normalized on its own, which lets
            # a weight exceed 1 by the interpolation error of coarse tables).
            assert w.max() < 1.5
            assert w[0].mean() > w[1].mean() > w[2].mean()


def test_hard_directions_give_finite_values(silk_render_table, circle_table):
    b = _bsdf([FiberSlot(silk_render_table, (0.0, 0.0, 0.0))])
    dirs = [(0.0, 1.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.9999999, 1e-4), (1e-7, 1e-7, 1.0), (0.0, 0.0, -1.0)]
    for wi in dirs:
        wi = unit(wi)
        si = fiber_interaction(1000, wi)
        rng = np.random.default_rng(0)
        s1 = mi.Float(rng.random(1000).astype(np.float32))
        s2 = mi.Vector2f(mi.Float(rng.random(1000).astype(np.float32)), mi.Float(rng.random(1000).astype(np.float32)))
        bs, w = b.sample(_ctx(True), si, s1, s2)
        val, pdf = b.eval_pdf(_ctx(True), si, bs.wo)
        for arr in (np.array(w), np.array(val), np.array(pdf), np.array(bs.wo)):
            assert np.all(np.isfinite(arr)), wi


def test_pass_through_probability_is_width_over_diameter(silk_render_table):
    b = _bsdf([FiberSlot(silk_render_table, (0.0, 0.0, 0.0))], psi=0.0)
    n = 200_000
    rng = np.random.default_rng(1)
    for phi in (0.1, 1.2, 2.5):
        # Viewer perpendicular to the fiber (theta_v = 0) at azimuth phi from the reference +x.
        wi = [math.cos(phi), 0.0, -math.sin(phi)]   # frame: t = +y, x = +x, y = t x x = -z
        si = fiber_interaction(n, wi)
        s1 = mi.Float(rng.random(n).astype(np.float32))
        s2 = mi.Vector2f(mi.Float(rng.random(n).astype(np.float32)), mi.Float(rng.random(n).astype(np.float32)))
        bs, w = b.sample(_ctx(True), si, s1, s2)
        null = np.array(bs.sampled_type) == int(mi.BSDFFlags.Null)
        q = float(silk_render_table.width(phi)[()] / silk_render_table.baked_diameter_um)
        # Binomial(n, q) pass-throughs: exact limit at false failure 1e-4 (the old 4 sd bound
        # was 6e-5); 1e-3 for the float32 comparison of the sample with q.
        assert abs((1.0 - null.mean()) - q) <= binomial_limit(q, n) + 1e-3
        assert np.allclose(np.array(bs.wo)[:, null], -np.array(wi)[:, None], atol=1e-6)
        assert np.allclose(np.array(w)[:, null], 1.0)


# ---------------------------------------------------------------------------------------------
# Rendering
# ---------------------------------------------------------------------------------------------

def _straight_fibers(ys, radius, x_extent=4.0):
    pts, starts, cur = [], [], []
    for k, y in enumerate(ys):
        base = len(pts)
        xs = np.linspace(-x_extent, x_extent, 6)
        pts.extend((x, y, 0.0) for x in xs)
        starts.extend(base + s for s in range(len(xs) - 3))
        cur.extend([k] * (len(xs) - 3))
    return CurveGeometry(points=np.array(pts, float), radii=np.full(len(pts), radius),
                         segment_start=np.array(starts), segment_curve=np.array(cur), curve_count=len(ys))


def _ortho(origin, target, up, half, res):
    to_world = mi.ScalarTransform4f().look_at(origin=origin, target=target, up=up) @ \
        mi.ScalarTransform4f().scale([half, half, 1.0])
    return {"type": "orthographic", "to_world": to_world,
            "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}},
            "sampler": {"type": "independent", "sample_count": 64}}


@pytest.mark.parametrize("integrator", ["path", "volpath", "usdfiber_path", "usdfiber_path/generic"])
def test_rendered_white_furnace(circle_table, silk_render_table, wool, integrator):
    """Non-absorbing fibers in a uniform white dome read 1 (all orders of scattering).

    Both integrators the translator uses (``path`` for round fibers, ``usdfiber_path`` when a
    BSDF passes rays), the latter with the fiber BSDF deciding pass-throughs in ``sample``
    (generic) or the integrator deciding with the fiber's q (the default), and volpath: the
    last two also pass shadow rays through the non-round fibers (0/1 null transmission, see
    ``eval_null_transmission``).
    """
    register_integrator(mi)
    spec = {"type": integrator.split("/")[0], "max_depth": 64}
    if integrator.endswith("/generic"):
        spec["fiber_pass"] = False
    geom = _straight_fibers((-1.0, 0.0, 1.0), 0.3)
    slots = [FiberSlot(t, (0.0, 0.0, 0.0)) for t in (circle_table, silk_render_table, wool)]
    seg_slot = np.repeat([0, 1, 2], 3)
    b = fiber_bsdf(mi, FiberBank.build(slots), seg_slot, np.linspace(0, 5, 9), np.tile([0.0, 0.0, 1.0], (9, 1)))
    scene = mi.load_dict({
        "type": "scene", "integrator": spec,
        "sensor": _ortho([0.0, 3.0, 10.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], 2.0, 48),
        "emitter": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
        "fibers": make_curve_shape(geom, b)})
    img = np.array(mi.render(scene, spp=256))
    assert np.all(np.isfinite(img))
    # Every pixel (fiber or background) reads 1; the fiber rows are where it matters.
    # Non-absorbing fibers: every path carries weight 1 (only paths cut at max_depth 64 lose
    # it), so the furnace has no Monte-Carlo noise; the bounds are for bias, not noise, and
    # noise cannot fail them.
    assert abs(img.mean() - 1.0) < 0.01
    assert np.abs(img.mean(axis=(1, 2)) - 1.0).max() < 0.03
    # The pixels whose centre sees a fiber tube (45 % of the image), together: 1 within 1 %.
    depth = np.array(mi.render(mi.load_dict({
        "type": "scene", "integrator": {"type": "depth"},
        "sensor": _ortho([0.0, 3.0, 10.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], 2.0, 48),
        "fibers": make_curve_shape(geom, b)}), spp=1))[..., 0]
    fiber = depth > 0
    assert 0.2 < fiber.mean() < 0.6
    assert abs(img[fiber].mean() - 1.0) < 0.01, img[fiber].mean()


@pytest.mark.parametrize("name", ["circle_table", "silk_render_table"])
def test_one_fiber_radiance_matches_table(request, name):
    """One fiber, one distant light: the footprint-averaged radiance is E sigma / (D cos theta_v)."""
    table = request.getfixturevalue(name)
    psi = 0.7
    geom = _straight_fibers((0.0,), 0.5, x_extent=20.0)
    b = fiber_bsdf(mi, FiberBank.build([FiberSlot(table, (0.0, 0.0, 0.0))]), [0, 0, 0], [psi] * 3,
                   np.tile([0.0, 0.0, 1.0], (3, 1)))
    shape = make_curve_shape(geom, b)
    # Fiber frame: t = +x; reference z; y = t x z = -y.
    def world(theta, phi):
        return np.array([math.sin(theta), -math.cos(theta) * math.sin(phi), math.cos(theta) * math.cos(phi)])

    E = 3.0
    res = 64
    for (th_l, ph_l, th_v, ph_v) in [(0.3, 0.2, -0.2, 1.1), (-0.5, 2.0, 0.4, 0.3), (0.1, 3.5, 0.0, 0.9)]:
        wl, wv = world(th_l, ph_l), world(th_v, ph_v)
        half = 1.5
        # The image's vertical axis is perpendicular to the projected fiber axis.
        up = np.cross(wv, [1.0, 0.0, 0.0])
        scene = mi.load_dict({
            "type": "scene", "integrator": {"type": "path", "max_depth": 4},
            "sensor": _ortho((10 * wv).tolist(), [0.0, 0.0, 0.0], up.tolist(), half, res),
            "light": {"type": "directional", "direction": (-wl).tolist(), "irradiance": {"type": "rgb", "value": E}},
            "fibers": shape})
        img = np.array(mi.render(scene, spp=512))[..., 0]
        pix = 2 * half / res
        # Radiance times image area per unit length of the projected axis = L_avg * D.
        l_avg = img.sum(axis=0).mean() * pix / 1.0
        sigma = table.cross_section(th_l, ph_l, th_v, ph_v, psi=psi)
        expect = E * float(sigma) / (table.baked_diameter_um * math.cos(th_v))
        # Tolerance: the table's noise (reciprocity is used by the renderer, 4 rms relative
        # errors of the table: a bound on bin noise averaged over the footprint) and pixel
        # noise: 64 x 64 pixels x 512 spp of one directional light put about 7e5 samples on
        # the fiber, each of relative spread of order 1: a relative standard error of l_avg
        # of order 0.15 %, so the 2 % alone is > 10 standard errors (false failure < 1e-20).
        err = float(np.sqrt(np.mean(table.rel_error ** 2)))
        assert abs(l_avg - expect) <= 4 * err * expect + 0.02 * expect, (th_l, ph_l, th_v, ph_v, l_avg, expect)


def test_registered_plugin_loads_a_table_file(tmp_path, silk_render_table):
    """`usdfiber_bcsdf` by name (any Mitsuba scene): one table, sampling matches evaluation."""
    from usdfiber.translators.mitsuba.fiber_bsdf import register

    register(mi)
    path = tmp_path / "silk.npz"
    silk_render_table.save(path)
    spec = {"type": "usdfiber_bcsdf", "table": str(path), "mu_a": [0.01, 0.03, 0.09], "diameter_um": 10.0,
            "psi_deg": 20.0}
    sample, pdf = mi.chi2.BSDFAdapter("usdfiber_bcsdf", spec, wi=unit([0.2, 0.4, 0.9]),
                                      ctx=_ctx(False))
    test = mi.chi2.ChiSquareTest(domain=mi.chi2.SphericalDomain(), sample_func=sample, pdf_func=pdf,
                                 sample_dim=3, sample_count=200_000, res=41, ires=16)
    assert test.run(significance_level=FALSE_FAILURE), test.messages   # false failure 1e-4
    # The colour is the dye's: the same as the bank built by hand for mu_a * D.
    b = mi.load_dict(spec)
    # Stand-alone reference: world +z made perpendicular to the tangent (+y here).
    sigma = tuple(silk_render_table.sigma_for([0.01, 0.03, 0.09], 10.0))
    ref = fiber_bsdf(mi, FiberBank.build([FiberSlot(silk_render_table, sigma)]),
                     [0], [math.radians(20.0)], np.array([[0.0, 0.0, 1.0]]))
    si = fiber_interaction(1, unit([0.2, 0.4, 0.9]))
    wo = mi.Vector3f(*unit([-0.3, 0.2, 0.5]))
    assert np.allclose(np.array(b.eval(_ctx(True), si, wo)), np.array(ref.eval(_ctx(True), si, wo)), rtol=1e-5)
    with pytest.raises(Exception, match="table"):
        bare = mi.load_dict({"type": "usdfiber_bcsdf"})
        bare.eval(_ctx(True), si, wo)


@pytest.mark.parametrize("integrator", ["translator", "volpath"])
def test_shadow_of_non_round_fiber_is_as_wide_as_its_profile(silk_render_table, integrator):
    """A non-round fiber's shadow on a plane integrates to W(phi_l) / cos(incidence), not D / cos.

    A straight silk fiber (a tube of diameter D = 2 r whose profile covers W(phi) <= D of it)
    hangs at height h over a white diffuse plane, lit by a distant light perpendicular to the
    fiber at incidence alpha. An orthographic camera looks straight down at the shadow only
    (its rays pass beside the fiber), with max_depth 2: the plane sees the light directly, so
    no light the fiber scatters reaches the image. The shadow's missing fraction of the
    unshadowed radiance, integrated across the shadow, is the width it blocks: W / cos alpha
    when shadow rays pass the tube with probability 1 - W / D, D / cos alpha if the tube were
    opaque. The integrator is the one ``translate_stage`` picks for such a BSDF
    (``usdfiber_path``), and ``volpath``, which also passes shadow rays through null surfaces.
    """
    r, h, alpha, psi = 0.5, 3.0, math.radians(40.0), math.radians(50.0)
    geom = _straight_fibers((0.0,), r, x_extent=30.0)              # along +x through the origin
    b = fiber_bsdf(mi, FiberBank.build([FiberSlot(silk_render_table, (0.0, 0.0, 0.0))]), [0, 0, 0], [psi] * 3,
                   np.tile([0.0, 0.0, 1.0], (3, 1)))
    assert mi.has_flag(b.flags(), mi.BSDFFlags.Null)              # pass-through is on: W < D
    if integrator == "translator":
        integrator = fiber_integrator(mi, b)                        # as translate_stage
        assert integrator == "usdfiber_path"
    d = np.array([0.0, math.sin(alpha), -math.cos(alpha)])          # the light's direction of travel
    y_shadow, half, res = h * math.tan(alpha), 1.2, 64
    assert y_shadow - half > r and r / math.cos(alpha) < half - 0.3   # camera misses the fiber, sees all the shadow
    T = mi.ScalarTransform4f()
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": integrator, "max_depth": 2},
        "sensor": _ortho([0.0, y_shadow, 10.0], [0.0, y_shadow, 0.0], [0.0, 1.0, 0.0], half, res),
        "light": {"type": "directional", "direction": d.tolist(), "irradiance": {"type": "rgb", "value": 1.0}},
        "plane": {"type": "rectangle", "to_world": T.translate([0.0, 0.0, -h]) @ T.scale(40.0),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 1.0}}},
        "fibers": make_curve_shape(geom, b)})
    img = np.array(mi.render(scene, spp=64))[..., 0]
    lit = math.cos(alpha) / math.pi                                 # E cos(alpha) rho / pi
    # Image rows run along y (across the shadow), columns along the fiber.
    blocked = ((1.0 - img / lit).sum(axis=0) * (2 * half / res)).mean()
    # phi_l of the light in the fiber frame (module docstring of fiber_bsdf): t = +x,
    # x = cos(psi) z + sin(psi) (t x z), y = t x x.
    t = np.array([1.0, 0.0, 0.0])
    fx = math.cos(psi) * np.array([0.0, 0.0, 1.0]) + math.sin(psi) * np.cross(t, [0.0, 0.0, 1.0])
    phi_l = math.atan2(d @ np.cross(t, fx), d @ fx)
    q = float(silk_render_table.width(phi_l)[()] / silk_render_table.baked_diameter_um)
    assert q < 0.8                                                 # a clearly non-round view
    expect = q * 2 * r / math.cos(alpha)
    # Shadow rays pass the fiber or not (0 or 1, see eval_null_transmission): about 140k samples
    # fall in the shadow, a relative standard deviation of 0.16 %; the 1 % bound is 6 standard
    # deviations (false failure 2e-9); an opaque tube is 35 % off.
    assert abs(blocked - expect) < 0.01 * expect, (blocked, expect, 2 * r / math.cos(alpha))
