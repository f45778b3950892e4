"""UsdGeom.Camera -> Mitsuba sensors (usdfiber.translators.mitsuba.camera), checked against USD's own
projection (GfFrustum view and projection matrices)."""
from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

import usdfiber  # noqa: F401  (registers plugins before any stage is opened)
from pxr import Gf, Usd, UsdGeom

from usdfiber.backend import mitsuba
from usdfiber.translators.mitsuba.camera import CameraWarning, camera_sensor, conform_aperture, default_camera
from usdfiber.translators.mitsuba.errors import TranslationError

mi = mitsuba()
_STAGES: list[Usd.Stage] = []   # prims do not keep their stage alive


def _camera(projection="perspective", h_off=0.0, v_off=0.0, h_ap=20.955, v_ap=15.2908,
            focal=35.0, rotate=(10.0, -25.0, 30.0), translate=(1.0, 2.0, 10.0)):
    st = Usd.Stage.CreateInMemory()
    _STAGES.append(st)
    cam = UsdGeom.Camera.Define(st, "/cam")
    cam.CreateProjectionAttr(projection)
    cam.CreateHorizontalApertureAttr(h_ap)
    cam.CreateVerticalApertureAttr(v_ap)
    cam.CreateHorizontalApertureOffsetAttr(h_off)
    cam.CreateVerticalApertureOffsetAttr(v_off)
    cam.CreateFocalLengthAttr(focal)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.5, 500.0))
    cam.AddTranslateOp().Set(Gf.Vec3d(*translate))
    cam.AddRotateXYZOp().Set(Gf.Vec3f(*rotate))
    xf = np.array(cam.ComputeLocalToWorldTransform(Usd.TimeCode.Default()))
    return cam, xf


def _usd_view_projection(cam, xf, width, height, policy="fit"):
    """USD's world -> NDC matrix for the camera, its aperture conformed to the image by hand."""
    gf = cam.GetCamera(Usd.TimeCode.Default())
    gf.transform = Gf.Matrix4d(xf.tolist())
    h, v, a = gf.horizontalAperture, gf.verticalAperture, width / height
    if policy == "fit":
        h, v = (h, h / a) if h / v > a else (v * a, v)
    else:  # crop
        h, v = (v * a, v) if h / v > a else (h, h / a)
    gf.horizontalAperture, gf.verticalAperture = h, v
    fr = gf.frustum
    return np.array(fr.ComputeViewMatrix()) @ np.array(fr.ComputeProjectionMatrix())


def _max_ray_miss(sensor_dict, vp, n=25, seed=1) -> float:
    """Project random world points with USD, shoot Mitsuba's ray through that film position,
    return the largest distance of a point from its ray (relative to the distance)."""
    sensor = mi.load_dict(sensor_dict)
    rng = np.random.default_rng(seed)
    inv = np.linalg.inv(vp)
    worst = 0.0
    for _ in range(n):
        ndc = np.array([*rng.uniform(-0.95, 0.95, 2), rng.uniform(-0.9, 0.9), 1.0])
        p = ndc @ inv
        p = p[:3] / p[3]
        # NDC x right, y up -> Mitsuba film position x right, y down, in [0, 1]
        film = mi.Point2f(float((ndc[0] + 1) / 2), float((1 - ndc[1]) / 2))
        ray, _ = sensor.sample_ray(0.0, 0.5, film, mi.Point2f(0.5, 0.5))
        o, d = np.array(ray.o).ravel(), np.array(ray.d).ravel()
        v = p - o
        worst = max(worst, np.linalg.norm(v - (v @ d) * d) / np.linalg.norm(v))
    return worst


@pytest.mark.parametrize("size", [(64, 64), (64, 32), (24, 48)])
@pytest.mark.parametrize("offsets", [(0.0, 0.0), (3.0, -2.0)])
def test_perspective_matches_usd_projection(size, offsets):
    cam, xf = _camera(h_off=offsets[0], v_off=offsets[1])
    d = camera_sensor(cam.GetPrim(), xf, 0, *size, spp=1)
    assert d["type"] == "perspective" and d["fov_axis"] == "x"
    assert (d["near_clip"], d["far_clip"]) == (0.5, 500.0)
    assert _max_ray_miss(d, _usd_view_projection(cam, xf, *size)) < 1e-5


@pytest.mark.parametrize("size", [(64, 64), (64, 32), (24, 48)])
def test_crop_policy_matches_usd_projection(size):
    cam, xf = _camera(h_off=1.0, v_off=0.5)
    d = camera_sensor(cam.GetPrim(), xf, 0, *size, spp=1, conform_policy="cropAperture")
    assert _max_ray_miss(d, _usd_view_projection(cam, xf, *size, policy="crop")) < 1e-5


def test_fov_and_fit_by_hand():
    cam, xf = _camera(h_ap=36.0, v_ap=24.0, focal=50.0)
    # image wider (2:1) than the aperture (1.5:1): fit keeps the vertical aperture
    d = camera_sensor(cam.GetPrim(), xf, 0, 64, 32, spp=1)
    assert d["fov"] == pytest.approx(math.degrees(2 * math.atan(48.0 / 2 / 50.0)))
    # image narrower (1:1): fit keeps the horizontal aperture
    d = camera_sensor(cam.GetPrim(), xf, 0, 32, 32, spp=1)
    assert d["fov"] == pytest.approx(math.degrees(2 * math.atan(36.0 / 2 / 50.0)))
    assert conform_aperture(36, 24, 1.0, "adjustApertureWidth") == (24, 24)
    assert conform_aperture(36, 24, 1.0, "adjustApertureHeight") == (36, 36)


@pytest.mark.parametrize("size", [(64, 64), (64, 32), (24, 48)])
def test_orthographic_matches_usd_projection(size):
    cam, xf = _camera("orthographic", h_off=30.0, v_off=-12.0, h_ap=200.0, v_ap=100.0)
    d = camera_sensor(cam.GetPrim(), xf, 0, *size, spp=1)
    assert d["type"] == "orthographic"
    assert _max_ray_miss(d, _usd_view_projection(cam, xf, *size)) < 1e-5


def test_orthographic_window_size_in_tenths_of_scene_units():
    # identity transform: the window is 20 x 10 scene units (aperture 200 x 100 tenths)
    cam, xf = _camera("orthographic", h_ap=200.0, v_ap=100.0, rotate=(0, 0, 0), translate=(0, 0, 0))
    sensor = mi.load_dict(camera_sensor(cam.GetPrim(), xf, 0, 40, 20, spp=1))
    for film, expect in (((0.0, 0.5), (-10, 0)), ((1.0, 0.5), (10, 0)), ((0.5, 0.0), (0, 5))):
        ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(*film), mi.Point2f(0.5, 0.5))
        assert np.allclose(np.array(ray.o).ravel()[:2], expect, atol=1e-4)
        assert np.allclose(np.array(ray.d).ravel(), [0, 0, -1], atol=1e-6)   # looks down -Z


def test_thinlens_focus_and_aperture():
    cam, xf = _camera(focal=50.0)
    cam.CreateFStopAttr(2.0)
    cam.CreateFocusDistanceAttr(7.0)
    d = camera_sensor(cam.GetPrim(), xf, 0, 32, 32, spp=1)
    assert d["type"] == "thinlens"
    assert d["aperture_radius"] == pytest.approx(50.0 * 0.1 / (2 * 2.0))   # 1.25 scene units
    assert d["focus_distance"] == 7.0
    sensor = mi.load_dict(d)
    # All lens samples through one film point meet at the focus distance along the view axis.
    hits = []
    for lens in ((0.1, 0.1), (0.9, 0.2), (0.5, 0.9)):
        ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(0.5, 0.5), mi.Point2f(*lens))
        o, dd = np.array(ray.o).ravel(), np.array(ray.d).ravel()
        fwd = -xf[2, :3] / np.linalg.norm(xf[2, :3])                 # USD camera -Z in world
        t = (7.0 - (o - xf[3, :3]) @ fwd) / (dd @ fwd)
        hits.append(o + t * dd)
    assert np.allclose(hits, xf[3, :3] + 7.0 * fwd, atol=1e-4)
    assert camera_sensor(cam.GetPrim(), xf, 0, 32, 32, spp=1, depth_of_field=False)["type"] == "perspective"
    cam.CreateHorizontalApertureOffsetAttr(1.0)
    with pytest.warns(CameraWarning, match=r"/cam: .*thinlens"):
        camera_sensor(cam.GetPrim(), xf, 0, 32, 32, spp=1)


def test_render_emissive_sphere_lands_at_usd_projection():
    """End to end: a tiny emissive sphere shows up at the pixel USD's projection predicts."""
    w, h = 48, 24
    cam, xf = _camera(h_off=2.0, v_off=1.0)
    vp = _usd_view_projection(cam, xf, w, h)
    ndc = np.array([0.35, -0.4, 0.5, 1.0])
    p = ndc @ np.linalg.inv(vp)
    p = p[:3] / p[3]
    dist = np.linalg.norm(p - xf[3, :3])
    sensor = camera_sensor(cam.GetPrim(), xf, 0, w, h, spp=16, film_extra={"rfilter": {"type": "box"}})
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 1},
                          "sensor": sensor,
                          "ball": {"type": "sphere", "center": p.tolist(), "radius": 0.004 * dist,
                                   "emitter": {"type": "area", "radiance": 1.0}}})
    img = np.array(mi.render(scene)).sum(axis=2)
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    cx, cy = (img * xs).sum() / img.sum(), (img * ys).sum() / img.sum()
    assert cx == pytest.approx((ndc[0] + 1) / 2 * w, abs=0.3)
    assert cy == pytest.approx((1 - ndc[1]) / 2 * h, abs=0.3)


def test_camera_scale_removed_and_film_options():
    cam, xf = _camera()
    scaled = np.diag([2.0, 2.0, 2.0, 1.0]) @ xf
    d = camera_sensor(cam.GetPrim(), scaled, 0, 32, 16, spp=8, seed=3,
                      film_extra={"rfilter": {"type": "box"}})
    assert _max_ray_miss(d, _usd_view_projection(cam, xf, 32, 16)) < 1e-5
    assert d["film"] == {"type": "hdrfilm", "width": 32, "height": 16, "rfilter": {"type": "box"},
                         "pixel_format": "rgb", "component_format": "float32"}
    assert d["sampler"] == {"type": "independent", "sample_count": 8, "seed": 3}
    assert camera_sensor(cam.GetPrim(), xf, 0, 8, 8, spp=1)["film"]["rfilter"] == {"type": "gaussian"}


def test_bad_cameras():
    st = Usd.Stage.CreateInMemory()
    xform = UsdGeom.Xform.Define(st, "/notcam")
    with pytest.raises(TranslationError, match="/notcam"):
        camera_sensor(xform.GetPrim(), np.eye(4), 0, 8, 8, spp=1)
    cam, xf = _camera(focal=0.0)
    with pytest.raises(TranslationError, match=r"/cam\.focalLength"):
        camera_sensor(cam.GetPrim(), xf, 0, 8, 8, spp=1)
    cam, xf = _camera()
    cam.GetClippingRangeAttr().Set(Gf.Vec2f(5.0, 1.0))
    with pytest.raises(TranslationError, match=r"/cam\.clippingRange"):
        camera_sensor(cam.GetPrim(), xf, 0, 8, 8, spp=1)
    cam, xf = _camera()
    cam.CreateExposureAttr(1.0)
    with pytest.warns(CameraWarning, match="exposure"):
        camera_sensor(cam.GetPrim(), xf, 0, 8, 8, spp=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cam2, xf2 = _camera()
        camera_sensor(cam2.GetPrim(), xf2, 0, 8, 8, spp=1)    # a plain camera warns nothing


@pytest.mark.parametrize("up", ["Y", "Z"])
def test_default_camera_frames_the_box(up):
    lo, hi = np.array([-1.0, 0.0, 2.0]), np.array([3.0, 1.0, 4.0])
    d = default_camera(lo, hi, 40, 20, spp=4, up_axis=up)
    sensor = mi.load_dict(d)
    m = np.array(sensor.world_transform().matrix)[..., 0] if np.array(
        sensor.world_transform().matrix).ndim == 3 else np.array(sensor.world_transform().matrix)
    eye, fwd, upv = m[:3, 3], m[:3, 2], m[:3, 1]
    centre = (lo + hi) / 2
    assert np.allclose(fwd, (centre - eye) / np.linalg.norm(centre - eye), atol=1e-5)
    axis = np.array([0, 1, 0]) if up == "Y" else np.array([0, 0, 1])
    front = np.array([0, 0, 1]) if up == "Y" else np.array([0, -1, 0])
    assert (eye - centre) @ axis > 0 and (eye - centre) @ front > 0   # in front, raised
    assert upv @ axis > 0.9
    # every box corner is inside the 30 degree cone (the smaller image axis)
    for corner in np.array(np.meshgrid(*zip(lo, hi))).reshape(3, -1).T:
        v = corner - eye
        assert math.degrees(math.acos(v @ fwd / np.linalg.norm(v))) <= 15.0 + 1e-6
        assert d["near_clip"] < v @ fwd < d["far_clip"]
