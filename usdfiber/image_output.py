"""Image output of ``usdfiber render``: scene-referred EXR and display-referred PNG.

Colour pipeline
---------------
Mitsuba's ``*_rgb`` variants render **linear Rec.709 primaries, D65 white**, scene-referred
(values above 1 are normal: specular glints on fibres). That is :data:`SOURCE_SPACE`, the
colour space named ``"Linear Rec.709 (sRGB)"`` in the ACES cg-config (aliases ``lin_rec709``,
``lin_srgb``; colour interop ID ``lin_rec709_scene``).

* :func:`write_exr` stores those values unchanged (the master image), tagged with their
  colour space: ``chromaticities`` (Rec.709/D65) and ``oiio:ColorSpace`` /
  ``colorInteropID`` = :data:`EXR_COLORSPACE` (``"lin_rec709_scene"``, OIIO 3's name).
* :func:`display_image` / :func:`write_display_png` make a preview through an OpenColorIO
  display/view transform.

OCIO config
-----------
``config=None`` (the default) means: the ``OCIO`` environment variable if it is set and
non-empty (the usual OCIO convention, so a studio config applies everywhere), else
:data:`DEFAULT_OCIO_CONFIG`, OCIO's built-in ACES cg config, which needs no files.
An explicit ``config`` wins over ``$OCIO``.

Default view
------------
:data:`DEFAULT_VIEW` is ``"ACES 2.0 - SDR 100 nits (Rec.709)"`` (also the config's own
default for ``"sRGB - Display"``). Fibre renders have highlights well above 1; the ACES 2.0
output transform rolls them off smoothly and desaturates them towards white, where a plain
sRGB encode clips each channel at 1 (flat, hue-shifted highlights). The price is a tone
curve: linear 0.18 shows as 0.349, not 0.461. To compare a preview with a reference or a
measurement, use the ``"Un-tone-mapped"`` view (a plain sRGB encode of Rec.709) or the EXR.
"""
from __future__ import annotations

import functools
import os
import tempfile
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import PyOpenColorIO as ocio

from usdfiber.atomic_file import write_atomic

__all__ = [
    "DEFAULT_DISPLAY",
    "DEFAULT_OCIO_CONFIG",
    "DEFAULT_VIEW",
    "EXR_COLORSPACE",
    "SOURCE_SPACE",
    "UNTONEMAPPED_VIEW",
    "ImageOutputError",
    "check_writable",
    "display_image",
    "list_views",
    "read_exr",
    "read_exr_channels",
    "resolve_config",
    "write_display_png",
    "write_exr",
]

DEFAULT_OCIO_CONFIG = "ocio://cg-config-latest"
DEFAULT_DISPLAY = "sRGB - Display"
DEFAULT_VIEW = "ACES 2.0 - SDR 100 nits (Rec.709)"
UNTONEMAPPED_VIEW = "Un-tone-mapped"
#: OCIO colour space of Mitsuba's rgb variants (in the ACES cg/studio configs).
SOURCE_SPACE = "Linear Rec.709 (sRGB)"
#: What the EXR's ``oiio:ColorSpace`` says: OIIO 3's colour interop ID for linear Rec.709.
EXR_COLORSPACE = "lin_rec709_scene"
#: Rec.709 / sRGB primaries and D65 white: (Rx, Ry, Gx, Gy, Bx, By, Wx, Wy).
REC709_CHROMATICITIES = (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290)

_PREFIX = "usdfiber:"
_HALF_MAX = 65504.0
_INT32 = (-(2**31), 2**31 - 1)
_LAYER_SUFFIXES = {1: ("",), 2: (".X", ".Y"), 3: (".R", ".G", ".B"), 4: (".R", ".G", ".B", ".A")}

MetaValue = str | float | int


class ImageOutputError(RuntimeError):
    """An image could not be written, read or converted; the message says which and why."""


# --------------------------------------------------------------------------------------------
# EXR
# --------------------------------------------------------------------------------------------

def write_exr(path: str | os.PathLike[str], rgb: np.ndarray,
              metadata: Mapping[str, MetaValue] | None = None, *, half: bool = True,
              extra_channels: Mapping[str, np.ndarray] | None = None,
              channel_names: Mapping[str, Sequence[str]] | None = None,
              allow_nonfinite: bool = False) -> None:
    """Write a scene-referred linear Rec.709 image as an OpenEXR file, atomically.

    ``rgb`` is ``(H, W, 3)``, stored as channels R, G, B in half float (``half=True``) or
    float32, zip compressed, tagged ``chromaticities`` = Rec.709/D65 and
    ``oiio:ColorSpace`` = :data:`EXR_COLORSPACE`. Each ``metadata`` item becomes the header
    attribute ``usdfiber:<key>``: str as string, int as int (as a decimal string outside the
    32-bit range, which EXR cannot hold), float as EXR's 32-bit float.

    ``extra_channels`` maps a layer name to an ``(H, W)`` or ``(H, W, C)`` array, C <= 4,
    stored in the same precision as RGB: one channel is named after the layer, 2 as
    ``name.X/Y``, 3 as ``name.R/G/B``, 4 as ``name.R/G/B/A``, unless ``channel_names`` gives a
    layer's channel names (``{"normal": ("normal.X", "normal.Y", "normal.Z")}``, or
    ``{"A": ("A",)}`` for the image's alpha). Compositors (Nuke, OIIO) read ``layer.channel``
    names as layers.

    NaN or Inf pixels (and, in half mode, finite values beyond the half range that would be
    stored as Inf) raise :class:`ImageOutputError` with their count and the first one's
    position, unless ``allow_nonfinite``. The file is written next to ``path`` under a
    temporary name and renamed over it, so readers never see a partial image.
    """
    path = Path(path)
    rgb = _as_image(rgb, f"cannot write {path}: rgb")
    height, width = rgb.shape[:2]
    names = ["R", "G", "B"]
    planes = [rgb]
    for layer, data in (extra_channels or {}).items():
        data = np.asarray(data, dtype=np.float32)
        if data.ndim == 2:
            data = data[..., None]
        if data.ndim != 3 or data.shape[:2] != (height, width) or data.shape[2] not in _LAYER_SUFFIXES:
            raise ImageOutputError(
                f"cannot write {path}: extra channel {layer!r} has shape {data.shape}, "
                f"expected ({height}, {width}) or ({height}, {width}, C) with C <= 4")
        given = (channel_names or {}).get(layer)
        if given is not None and len(given) != data.shape[2]:
            raise ImageOutputError(f"cannot write {path}: extra channel {layer!r} has {data.shape[2]} "
                                   f"channel(s) but {len(given)} name(s)")
        layer_names = list(given) if given is not None else [layer + s for s in _LAYER_SUFFIXES[data.shape[2]]]
        if clash := set(layer_names) & set(names):
            raise ImageOutputError(f"cannot write {path}: channel name(s) {sorted(clash)} used twice")
        names += layer_names
        planes.append(data)
    pixels = np.ascontiguousarray(np.concatenate(planes, axis=2), dtype=np.float32)

    if not allow_nonfinite:
        _refuse_nonfinite(path, pixels, names, half_limit=half)

    spec = oiio.ImageSpec(width, height, len(names), "half" if half else "float")
    spec.channelnames = tuple(names)
    spec.attribute("compression", "zip")
    spec.attribute("oiio:ColorSpace", EXR_COLORSPACE)
    spec.attribute("chromaticities", oiio.TypeDesc("float[8]"), REC709_CHROMATICITIES)
    spec.attribute("Software", f"usdfiber {_version()}")
    for key, value in (metadata or {}).items():
        _set_attribute(spec, path, key, value)

    _atomic_write(path, lambda tmp: _oiio_write(tmp, "openexr", spec, pixels))


def read_exr(path: str | os.PathLike[str]) -> tuple[np.ndarray, dict[str, str]]:
    """Read an EXR: its R, G, B channels as ``(H, W, 3)`` float32 and every header attribute.

    The header dict is keyed by full attribute name (``"usdfiber:spp"``,
    ``"chromaticities"``, ``"oiio:ColorSpace"``...) with values as strings: numbers in
    shortest round-trip form (``0.1`` stays ``"0.1"`` after float32 storage), arrays as
    space-separated numbers. Extra channels are not returned (read them with OIIO).
    """
    channels, data, header = _read_float_image(Path(path), require="RGB")
    return np.ascontiguousarray(data[..., [channels.index(c) for c in "RGB"]]), header


def read_exr_channels(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """Every channel of an EXR by name (``"R"``, ``"A"``, ``"albedo.R"``, ``"depth.Z"``...),
    each ``(H, W)`` float32, in the file's order."""
    channels, data, _ = _read_float_image(Path(path))
    return {name: np.ascontiguousarray(data[..., i]) for i, name in enumerate(channels)}


def _read_float_image(path: Path, require: str = "") -> tuple[list[str], np.ndarray, dict[str, str]]:
    """Channel names, every channel as ``(H, W, C)`` float32, and the header attributes as
    strings; refuses a file that lacks a channel named in ``require`` before reading pixels."""
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise ImageOutputError(f"cannot read {path}: {oiio.geterror() or 'unreadable'}")
    try:
        spec = inp.spec()
        channels = list(spec.channelnames)
        missing = [c for c in require if c not in channels]
        if missing:
            raise ImageOutputError(f"cannot read {path}: no channel(s) {missing}; has {channels}")
        data = inp.read_image(0, 0, 0, spec.nchannels, "float")
        if data is None:
            raise ImageOutputError(f"cannot read {path}: {inp.geterror() or 'read failed'}")
        data = np.asarray(data, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
        header = {a.name: _format_attribute(a.value) for a in spec.extra_attribs}
    finally:
        inp.close()
    return channels, data, header


# --------------------------------------------------------------------------------------------
# Display
# --------------------------------------------------------------------------------------------

def resolve_config(config: str | None = None) -> str:
    """The OCIO config to use: ``config`` if given, else ``$OCIO`` if set, else the default."""
    return config or os.environ.get("OCIO") or DEFAULT_OCIO_CONFIG


def list_views(config: str | None = None) -> dict[str, list[str]]:
    """Displays of an OCIO config and the views of each (for ``--list-views``)."""
    cfg = _load_config(resolve_config(config))
    return {d: list(cfg.getViews(d)) for d in cfg.getDisplays()}


def display_image(rgb: np.ndarray, *, config: str | None = None,
                  display: str = DEFAULT_DISPLAY, view: str = DEFAULT_VIEW,
                  exposure_stops: float = 0.0, source: str = SOURCE_SPACE) -> np.ndarray:
    """Convert a scene-referred image to display-referred ``(H, W, 3)`` float32 in [0, 1].

    ``rgb`` (in colour space ``source``) is scaled by ``2**exposure_stops`` (a camera
    exposure, applied before the tone curve) and sent through the OCIO
    DisplayViewTransform ``source -> (display, view)``. The result is clipped to [0, 1]
    (an un-tone-mapped view passes values > 1 through) and NaN becomes 0. Unknown config,
    display, view or source raise :class:`ImageOutputError` listing the valid choices.
    """
    rgb = _as_image(rgb, "display_image: rgb")
    processor = _display_processor(resolve_config(config), source, display, view)
    # applyRGB works in place on a C-contiguous float32 buffer: always work on a copy.
    buf = np.array(rgb, dtype=np.float32, order="C", copy=True)
    if exposure_stops:
        buf *= np.float32(2.0 ** exposure_stops)
    processor.applyRGB(buf)
    np.nan_to_num(buf, copy=False, nan=0.0, posinf=1.0, neginf=0.0)
    return np.clip(buf, 0.0, 1.0, out=buf)


def write_display_png(path: str | os.PathLike[str], rgb: np.ndarray, *,
                      metadata: Mapping[str, MetaValue] | None = None, dither: bool = False,
                      allow_nonfinite: bool = False, config: str | None = None,
                      display: str = DEFAULT_DISPLAY, view: str = DEFAULT_VIEW,
                      exposure_stops: float = 0.0, source: str = SOURCE_SPACE) -> None:
    """Write the :func:`display_image` of ``rgb`` as an 8-bit RGB PNG, atomically.

    Values are rounded to the nearest code value (deterministic); ``dither=True`` lets OIIO
    add dither noise instead, against banding in dark gradients. The PNG is tagged with the
    display's colour space where OIIO knows it (sRGB chunk / cICP) and carries the transform
    (``usdfiber:ocio_config``, ``usdfiber:display``, ``usdfiber:view``,
    ``usdfiber:exposure_stops``) and ``metadata`` as ``usdfiber:<key>`` text chunks.
    NaN/Inf input pixels are refused as in :func:`write_exr` unless ``allow_nonfinite``.
    """
    path = Path(path)
    rgb = _as_image(rgb, f"cannot write {path}: rgb")
    if not allow_nonfinite:
        _refuse_nonfinite(path, rgb, ["R", "G", "B"], half_limit=False)
    config = resolve_config(config)
    try:
        image = display_image(rgb, config=config, display=display, view=view,
                              exposure_stops=exposure_stops, source=source)
    except ImageOutputError as exc:
        raise ImageOutputError(f"cannot write {path}: {exc}") from None

    spec = oiio.ImageSpec(image.shape[1], image.shape[0], 3, "uint8")
    spec.attribute("oiio:dither", 1 if dither else 0)
    tag = _display_colorspace_tag(_load_config(config), display, view)
    if tag:
        spec.attribute("oiio:ColorSpace", tag)
    spec.attribute("Software", f"usdfiber {_version()}")
    transform = {"ocio_config": config, "display": display, "view": view,
                 "exposure_stops": float(exposure_stops)}
    for key, value in {**(metadata or {}), **transform}.items():
        spec.attribute(_PREFIX + key, str(value))  # PNG text chunks hold strings only
    _atomic_write(path, lambda tmp: _oiio_write(tmp, "png", spec, image))


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------

def _as_image(rgb: np.ndarray, what: str) -> np.ndarray:
    arr = np.asarray(rgb)
    if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[0] == 0 or arr.shape[1] == 0:
        raise ImageOutputError(f"{what} has shape {arr.shape}, expected (H, W, 3)")
    if not np.issubdtype(arr.dtype, np.floating):
        raise ImageOutputError(f"{what} has dtype {arr.dtype}, expected linear float")
    return arr.astype(np.float32, copy=False)


def _refuse_nonfinite(path: Path, pixels: np.ndarray, names: list[str], *, half_limit: bool) -> None:
    """Raise unless every value is finite (and, for half storage, within the half range)."""
    bad = ~np.isfinite(pixels)
    problem, hint = "NaN/Inf values", "fix the render, or pass allow_nonfinite=True"
    if not bad.any() and half_limit:
        # Half float tops out at 65504: a brighter firefly would silently turn into Inf.
        bad = np.abs(pixels) > _HALF_MAX
        problem = f"values beyond the half-float range (|v| > {_HALF_MAX:g}, stored as Inf)"
        hint = "write 32-bit floats (usdfiber render --float; write_exr(half=False))"
    if not bad.any():
        return
    per_pixel = bad.any(axis=2)
    y, x = (int(i) for i in np.argwhere(per_pixel)[0])
    values = ", ".join(f"{n}={v:g}" for n, v in zip(names, pixels[y, x]) if not np.isfinite(v)
                       or (half_limit and abs(v) > _HALF_MAX))
    raise ImageOutputError(
        f"refusing to write {path}: {int(per_pixel.sum())} of {per_pixel.size} pixels have "
        f"{problem}; first at x={x}, y={y} ({values}); {hint}")


def _set_attribute(spec: oiio.ImageSpec, path: Path, key: str, value: MetaValue) -> None:
    if not isinstance(key, str) or not key:
        raise ImageOutputError(f"cannot write {path}: metadata key {key!r} is not a non-empty string")
    name = _PREFIX + key
    # OIIO's EXR writer silently drops int64 and double attributes: only emit types it keeps.
    if isinstance(value, bool):
        spec.attribute(name, int(value))
    elif isinstance(value, (int, np.integer)):
        value = int(value)
        spec.attribute(name, value if _INT32[0] <= value <= _INT32[1] else str(value))
    elif isinstance(value, (float, np.floating)):
        spec.attribute(name, float(value))
    elif isinstance(value, str):
        spec.attribute(name, value)
    else:
        raise ImageOutputError(
            f"cannot write {path}: metadata {key!r} is a {type(value).__name__}, expected str, int or float")


def _format_attribute(value: object) -> str:
    if isinstance(value, float):
        return str(np.float32(value))  # attributes are float32: shortest form that round-trips
    if isinstance(value, (tuple, list)):
        return " ".join(_format_attribute(v) for v in value)
    return str(value)


def _oiio_write(filename: str, fmt: str, spec: oiio.ImageSpec, pixels: np.ndarray) -> None:
    # Name the format explicitly: the temporary file's suffix is not the target's.
    out = oiio.ImageOutput.create(fmt)
    if out is None:
        raise OSError(oiio.geterror() or f"OIIO has no {fmt} writer")
    try:
        if not out.open(filename, spec) or not out.write_image(pixels):
            raise OSError(out.geterror() or "OIIO write failed")
    finally:
        out.close()


def _atomic_write(path: Path, write: Callable[[str], None]) -> None:
    """:func:`usdfiber.atomic_file.write_atomic`, with file-system errors as ImageOutputError.

    Readers (a viewer polling the output, a comparison script) see the old image or the new
    one, never a partial one; any failure removes the temporary file.
    """
    def checked(tmp: str) -> None:
        write(tmp)
        # A writer that reports success but wrote nothing (a full disk seen late) is a failure.
        if os.path.getsize(tmp) == 0:
            raise OSError("the image writer left an empty file")

    try:
        write_atomic(path, checked)
    except OSError as exc:
        raise ImageOutputError(f"cannot write {path}: {exc.strerror or exc}") from exc


def check_writable(path: str | os.PathLike[str]) -> None:
    """Raise :class:`ImageOutputError` unless an image can be written at ``path``: its folder
    exists and takes a new file, and ``path`` is not a folder. Checked before a render, so
    that a long render does not end in a failed write."""
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if path.is_dir():
        raise ImageOutputError(f"cannot write {path}: it is a directory")
    if not folder.is_dir():
        raise ImageOutputError(f"cannot write {path}: the folder {folder} does not exist")
    try:
        fd, probe = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".probe", dir=folder)
    except OSError as exc:
        raise ImageOutputError(f"cannot write {path}: {exc.strerror or exc}") from None
    os.close(fd)
    os.unlink(probe)


@functools.lru_cache(maxsize=8)
def _load_config(config: str) -> ocio.Config:
    try:
        return ocio.Config.CreateFromFile(config)
    except Exception as exc:  # PyOpenColorIO.Exception and its subclasses
        builtin = ["ocio://default", "ocio://cg-config-latest", "ocio://studio-config-latest"]
        builtin += [f"ocio://{name}" for name in ocio.BuiltinConfigRegistry()]
        source = " (from $OCIO)" if config == os.environ.get("OCIO") else ""
        raise ImageOutputError(
            f"cannot load OCIO config {config!r}{source}: {exc}; give a .ocio file or one of "
            f"the built-in configs: {', '.join(builtin)}") from None


def _display_processor(config: str, source: str, display: str, view: str) -> ocio.CPUProcessor:
    cfg = _load_config(config)
    displays = list(cfg.getDisplays())
    if display not in displays:
        raise ImageOutputError(
            f"unknown display {display!r} in OCIO config {config!r}; valid displays: {displays}")
    views = list(cfg.getViews(display))
    if view not in views:
        raise ImageOutputError(
            f"unknown view {view!r} for display {display!r} in OCIO config {config!r}; "
            f"valid views: {views}")
    if cfg.getColorSpace(source) is None:
        raise ImageOutputError(
            f"unknown source colour space {source!r} in OCIO config {config!r}; valid colour "
            f"spaces: {list(cfg.getColorSpaceNames())}")
    transform = ocio.DisplayViewTransform(src=source, display=display, view=view)
    try:
        return cfg.getProcessor(transform).getDefaultCPUProcessor()
    except Exception as exc:
        raise ImageOutputError(
            f"OCIO cannot build {source!r} -> {display!r} / {view!r} from {config!r}: {exc}") from None


def _display_colorspace_tag(cfg: ocio.Config, display: str, view: str) -> str | None:
    """The OIIO colour space name for a display/view's output (for the PNG's colour chunks)."""
    name = cfg.getDisplayViewColorSpaceName(display, view)
    if name == "<USE_DISPLAY_NAME>":  # shared views defer to the display's colour space
        name = display
    cs = cfg.getColorSpace(name)
    if cs is None or cs.isData():  # e.g. the "Raw" view: nothing to claim
        return None
    return cs.getInteropID() or name


def _version() -> str:
    from . import __version__
    return __version__
