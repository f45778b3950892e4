"""Image output of `usdfiber render`: EXR round trip and safety, OCIO display transform, PNG."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

from usdfiber import image_output as io
from usdfiber.image_output import ImageOutputError

SRGB_018 = 1.055 * 0.18 ** (1 / 2.4) - 0.055  # 0.46135...


@pytest.fixture(autouse=True)
def _no_ocio_env(monkeypatch):
    # A developer's $OCIO must not change what these tests check.
    monkeypatch.delenv("OCIO", raising=False)


def image(h: int = 6, w: int = 8, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.0, 4.0, (h, w, 3)).astype(np.float32)


META = {"stage": "scenes/knit.usda", "camera": "/World/Cam", "spp": 256, "frame": 12,
        "render_seconds": 12.5, "variant": "scalar_rgb"}


# ---- EXR --------------------------------------------------------------------------------------

def test_exr_round_trip_half(tmp_path: Path):
    rgb = image()
    out = tmp_path / "beauty.exr"
    io.write_exr(out, rgb, META)
    back, header = io.read_exr(out)
    assert back.shape == rgb.shape and back.dtype == np.float32
    np.testing.assert_allclose(back, rgb, rtol=2**-11, atol=0)  # half: 11-bit significand
    assert np.array_equal(back, rgb.astype(np.float16).astype(np.float32))
    assert header["usdfiber:stage"] == "scenes/knit.usda"
    assert header["usdfiber:camera"] == "/World/Cam"
    assert header["usdfiber:spp"] == "256" and header["usdfiber:frame"] == "12"
    assert header["usdfiber:render_seconds"] == "12.5"
    assert header["usdfiber:variant"] == "scalar_rgb"
    assert header["oiio:ColorSpace"] == io.EXR_COLORSPACE == "lin_rec709_scene"
    chroma = [float(v) for v in header["chromaticities"].split()]
    np.testing.assert_allclose(chroma, io.REC709_CHROMATICITIES, atol=1e-6)
    assert header["compression"] == "zip"
    assert oiio.ImageInput.open(str(out)).spec().format == oiio.TypeDesc("half")


def test_exr_float32_exact_and_extra_channels(tmp_path: Path):
    rgb = image(seed=1)
    depth = np.linspace(0, 1e5, 48, dtype=np.float32).reshape(6, 8)  # beyond half range: fine in float
    albedo = image(seed=2) / 4
    out = tmp_path / "beauty.exr"
    io.write_exr(out, rgb, {"spp": 2**40}, half=False,
                 extra_channels={"depth.Z": depth, "albedo": albedo})
    back, header = io.read_exr(out)
    assert np.array_equal(back, rgb)
    assert header["usdfiber:spp"] == str(2**40)  # beyond EXR's int32: kept as a string
    inp = oiio.ImageInput.open(str(out))
    names = list(inp.spec().channelnames)
    data = inp.read_image(0, 0, 0, len(names), "float")
    inp.close()
    assert set(names) == {"R", "G", "B", "depth.Z", "albedo.R", "albedo.G", "albedo.B"}
    assert np.array_equal(data[..., names.index("depth.Z")], depth)
    assert np.array_equal(data[..., [names.index(f"albedo.{c}") for c in "RGB"]], albedo)


def test_exr_atomic_leaves_no_temp_files(tmp_path: Path):
    out = tmp_path / "beauty.exr"
    io.write_exr(out, image(), META)
    io.write_exr(out, image(seed=3), META)  # overwrite in place
    assert [p.name for p in tmp_path.iterdir()] == ["beauty.exr"]
    assert np.array_equal(io.read_exr(out)[0], image(seed=3).astype(np.float16).astype(np.float32))
    # A write that fails at the rename (target is a directory) cleans up after itself.
    blocked = tmp_path / "blocked.exr"
    blocked.mkdir()
    with pytest.raises(ImageOutputError, match="blocked.exr"):
        io.write_exr(blocked, image(), META)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["beauty.exr", "blocked.exr"]
    with pytest.raises(ImageOutputError, match="missing"):
        io.write_exr(tmp_path / "missing" / "x.exr", image(), META)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_exr_refuses_nonfinite(tmp_path: Path, bad: float):
    rgb = image()
    rgb[2, 5, 1] = bad
    rgb[4, 0, 0] = bad
    out = tmp_path / "beauty.exr"
    with pytest.raises(ImageOutputError) as err:
        io.write_exr(out, rgb, META)
    msg = str(err.value)
    assert str(out) in msg and "2 of 48 pixels" in msg and "x=5, y=2" in msg and f"G={bad:g}" in msg
    assert list(tmp_path.iterdir()) == []
    io.write_exr(out, rgb, META, half=False, allow_nonfinite=True)  # when told to
    assert np.isnan(io.read_exr(out)[0][2, 5, 1]) == np.isnan(bad)


def test_exr_refuses_half_overflow(tmp_path: Path):
    rgb = image()
    rgb[1, 3, 2] = 1e6  # finite, but Inf once stored as half
    with pytest.raises(ImageOutputError, match=r"x=3, y=1 .*half=False"):
        io.write_exr(tmp_path / "a.exr", rgb, {})
    io.write_exr(tmp_path / "a.exr", rgb, {}, half=False)
    assert io.read_exr(tmp_path / "a.exr")[0][1, 3, 2] == 1e6


def test_exr_rejects_bad_input(tmp_path: Path):
    with pytest.raises(ImageOutputError, match=r"shape \(4, 4\)"):
        io.write_exr(tmp_path / "a.exr", np.zeros((4, 4), np.float32), {})
    with pytest.raises(ImageOutputError, match="metadata 'x'"):
        io.write_exr(tmp_path / "a.exr", image(), {"x": [1, 2]})  # type: ignore[dict-item]
    with pytest.raises(ImageOutputError, match="cannot read .*nope.exr"):
        io.read_exr(tmp_path / "nope.exr")


# ---- display ----------------------------------------------------------------------------------

def test_display_black_and_grey():
    grey = np.full((2, 3, 3), 0.18, np.float32)
    for view in (io.DEFAULT_VIEW, io.UNTONEMAPPED_VIEW):
        assert np.all(io.display_image(np.zeros((2, 3, 3), np.float32), view=view) == 0)
    out = io.display_image(grey, view="Un-tone-mapped")
    assert out.dtype == np.float32 and out.shape == grey.shape
    np.testing.assert_allclose(out, SRGB_018, atol=1 / 255)
    assert abs(SRGB_018 - 0.4613) < 1e-4


def test_display_aces_ramp_monotonic_and_white_saturates():
    ramp = np.geomspace(1e-4, 1e4, 200, dtype=np.float32)
    rgb = np.repeat(ramp[None, :, None], 3, axis=2)
    out = io.display_image(rgb)[0, :, 0]
    assert np.all(np.diff(out) >= 0) and out[-1] > out[0]
    assert 0.0 <= out.min() and out.max() <= 1.0
    white = io.display_image(np.full((1, 2, 3), 1e4, np.float32))
    assert np.all(white <= 1.0) and np.all(white > 0.99)
    assert np.all(io.display_image(np.full((1, 1, 3), 4.0, np.float32), view="Un-tone-mapped") == 1.0)


def test_display_exposure_is_doubling():
    rgb = image() / 8
    for view in (io.DEFAULT_VIEW, io.UNTONEMAPPED_VIEW):
        np.testing.assert_array_equal(io.display_image(rgb, exposure_stops=1.0, view=view),
                                      io.display_image(rgb * 2, view=view))


def test_display_unknown_choices():
    rgb = image()
    with pytest.raises(ImageOutputError, match=r"unknown view 'Filmic'.*Un-tone-mapped"):
        io.display_image(rgb, view="Filmic")
    with pytest.raises(ImageOutputError, match=r"unknown display 'CRT'.*sRGB - Display"):
        io.display_image(rgb, display="CRT")
    with pytest.raises(ImageOutputError, match=r"unknown source .*Linear Rec.709 \(sRGB\)"):
        io.display_image(rgb, source="linear")
    with pytest.raises(ImageOutputError, match=r"'/no/such.ocio'.*ocio://cg-config-latest"):
        io.display_image(rgb, config="/no/such.ocio")


def test_ocio_env_var(monkeypatch):
    monkeypatch.setenv("OCIO", "/no/such/studio.ocio")
    with pytest.raises(ImageOutputError, match=r"from \$OCIO"):
        io.list_views()
    assert io.DEFAULT_VIEW in io.list_views(io.DEFAULT_OCIO_CONFIG)[io.DEFAULT_DISPLAY]  # explicit wins
    monkeypatch.setenv("OCIO", "ocio://studio-config-latest")
    assert io.resolve_config() == "ocio://studio-config-latest"


def test_list_views():
    views = io.list_views()
    assert io.DEFAULT_VIEW in views[io.DEFAULT_DISPLAY]
    assert io.UNTONEMAPPED_VIEW in views[io.DEFAULT_DISPLAY]
    assert "Display P3 - Display" in views


# ---- PNG --------------------------------------------------------------------------------------

def test_png_8bit_size_and_values(tmp_path: Path):
    rgb = np.zeros((5, 7, 3), np.float32)
    rgb[:, :3] = 0.18
    rgb[:, 3:5] = 100.0
    out = tmp_path / "preview.png"
    io.write_display_png(out, rgb, view="Un-tone-mapped", metadata={"spp": 64})
    assert [p.name for p in tmp_path.iterdir()] == ["preview.png"]
    inp = oiio.ImageInput.open(str(out))
    spec = inp.spec()
    pixels = inp.read_image(0, 0, 0, 3, "uint8")
    inp.close()
    assert (spec.width, spec.height, spec.nchannels) == (7, 5, 3)
    assert spec.format == oiio.TypeDesc("uint8")
    assert np.all(pixels[:, :3] == round(SRGB_018 * 255)) and np.all(pixels[:, 3:5] == 255)
    assert np.all(pixels[:, 5:] == 0)
    assert spec.getattribute("usdfiber:view") == "Un-tone-mapped"
    assert spec.getattribute("usdfiber:spp") == "64"
    # Same through the default ACES view: grey lands at its tone-mapped value.
    io.write_display_png(out, rgb)
    aces = oiio.ImageInput.open(str(out)).read_image(0, 0, 0, 3, "uint8")
    expected = np.round(io.display_image(rgb) * 255).astype(np.uint8)
    assert np.array_equal(aces, expected)


def test_png_refuses_nan_and_bad_view(tmp_path: Path):
    rgb = image()
    rgb[0, 1, 2] = np.nan
    with pytest.raises(ImageOutputError, match=r"preview.png.*x=1, y=0"):
        io.write_display_png(tmp_path / "preview.png", rgb)
    with pytest.raises(ImageOutputError, match=r"preview.png.*valid views"):
        io.write_display_png(tmp_path / "preview.png", image(), view="Filmic")
    assert list(tmp_path.iterdir()) == []
