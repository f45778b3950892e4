"""Import curve files (Cem Yuksel's BCC and HAIR formats) as fiber or yarn curves.

:func:`import_curves` reads a file and writes a USD stage with BasisCurves prims carrying
FiberAPI (fiber presets) or FiberYarnAPI + FiberAPI (yarn presets), authored through
:mod:`usdfiber.authoring`. :func:`read_curves` only reads (format chosen by the file's
first bytes, not its name). Malformed files raise :class:`CurveFileError` whose message
starts with the file's name and says what is wrong.

BCC ("binary curve collection", Yuksel's yarn-level cloth models), little endian::

    offset size
    0      3    sign, "BCC"
    3      1    byte count, 0x44 = 4-byte integers and 4-byte floats (the only one here)
    4      2    curve type: "C0" uniform Catmull-Rom, "PL" polyline, "BS" uniform B-spline
    6      1    dimensions (must be 3)
    7      1    up dimension (1 = y, 2 = z; the stage's upAxis follows it, else "Y")
    8      8    curve count (uint64)
    16     8    total control point count (uint64)
    24     40   file info (text)
    64     ...  per curve: int32 n, then |n| points of 3 float32; n < 0: a closed curve

Curve types map to USD as: C0 -> cubic catmullRom, PL -> linear, BS -> cubic bspline;
closed curves -> wrap "periodic" (the closing segment is implied, no point is repeated),
open curves -> "nonperiodic". USD's wrap is per prim, so a file with both open and closed
curves becomes two prims. Open C0 / BS curves need at least 4 points (USD spans them from
the second to the second-last point, as Yuksel's loaders do), closed ones 3; polylines 2
(open) or 3 (closed).

HAIR (Yuksel's hair model files), little endian::

    0    4   "HAIR"
    4    4   strand count (uint32)
    8    4   total point count (uint32)
    12   4   flags: 1 segments array, 2 points array, 4 thickness array,
                    8 transparency array, 16 colour array (other bits: ignored, noted)
    16   4   default segment count (uint32), used without a segments array
    20   4   default thickness (float32), used without a thickness array
    24   4   default transparency (float32)
    28   12  default colour (3 float32)
    40   88  file info (text)
    128  ... arrays present, in this order: segments (uint16 per strand), points
             (3 float32 per point), thickness (float32 per point), transparency (float32
             per point), colours (3 float32 per point)

A strand of s segments has s + 1 points; strands become linear nonperiodic curves.
Thickness is taken as the strand's diameter, i.e. USD's ``widths`` (per-vertex widths
from a thickness array, a constant width from the default thickness): the format's page
says only "thickness", and the public importers that map it to a renderer width (Unreal's
groom importer sets the vertex width to it) use it as the full width, not a radius.
Colours and transparency in HAIR files are not imported: a fiber's colour comes from its
dye (``dye=`` / ``--dye``, see ``usdfiber presets``), which the scattering model
computes; the importer records this as a note.

Sources read for the layouts: cemyuksel.com "Using Binary Curve Collection (BCC) files"
(cyCodeBase solution), cemyuksel.com/research/hairmodels ("HAIR File Format
Specification"), and public loaders of both formats (header field order and sizes, the
negative count for closed curves, the "PL" / "BS" curve types).

Units: file coordinates times ``units_per_file_unit`` are scene units; the stage's
``metersPerUnit`` is ``meters_per_unit`` (default 0.001: millimetres). Widths default to
the file's thickness (HAIR) else the fiber's diameter (FiberAPI) or the nominal yarn
diameter (yarn presets).
"""
from __future__ import annotations

import math
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pxr import Sdf, Tf, Usd, UsdGeom, Vt

from usdfiber.geometry.curves import MAX_COORDINATE, TOO_LARGE_EXPECTED

from usdfiber import authoring
from usdfiber.memory_budget import MemoryBudget
from usdfiber.spec.attributes import Fiber

__all__ = ["BYTES_PER_IMPORTED_POINT", "CurveData", "CurveFileError", "DEFAULT_FIBER_PRESET", "UNSET",
           "check_file_budget", "import_curves", "read_bcc", "read_curves", "read_hair", "write_curves"]

DEFAULT_FIBER_PRESET = "polyester"

BCC_HEADER_SIZE = 64
HAIR_HEADER_SIZE = 128

HAIR_SEGMENTS = 1
HAIR_POINTS = 2
HAIR_THICKNESS = 4
HAIR_TRANSPARENCY = 8
HAIR_COLOURS = 16
_HAIR_KNOWN = HAIR_SEGMENTS | HAIR_POINTS | HAIR_THICKNESS | HAIR_TRANSPARENCY | HAIR_COLOURS

# BCC curve type -> (USD type, USD basis); basis None for linear curves.
_BCC_TYPES = {b"C0": ("cubic", "catmullRom"), b"PL": ("linear", None), b"BS": ("cubic", "bspline")}
_BCC_TYPE_NAMES = {b"C0": "uniform Catmull-Rom", b"PL": "polyline", b"BS": "uniform B-spline"}


class CurveFileError(ValueError):
    """A curve file that cannot be imported; the message starts with the file's name."""


@dataclass
class CurveData:
    """Curves read from a file, in file units.

    ``points`` (N, 3) float32; ``counts`` (C,) points per curve; ``closed`` (C,) bool;
    ``widths`` (N,) per-point widths (diameters) or None; ``default_width`` one width for
    all points or None; ``curve_type`` "cubic" / "linear" and ``basis`` "catmullRom",
    "bspline" or None; ``up_axis`` "Y" or "Z"; ``notes`` what was not imported or assumed.
    """

    path: str
    format: str  # "bcc" or "hair"
    curve_type: str
    basis: str | None
    points: np.ndarray
    counts: np.ndarray
    closed: np.ndarray
    widths: np.ndarray | None = None
    default_width: float | None = None
    up_axis: str = "Y"
    info: str = ""
    notes: list[str] = field(default_factory=list)

    @property
    def description(self) -> str:
        kind = self.curve_type if self.basis is None else f"{self.curve_type} {self.basis}"
        return (f"{self.format.upper()} file, {len(self.counts)} {kind} curve"
                f"{'' if len(self.counts) == 1 else 's'}, {len(self.points)} points")


# ------------------------------------------------------------------------------ reading
def _name(path: str | os.PathLike[str]) -> str:
    return os.path.basename(os.fspath(path)) or os.fspath(path)


def _read_bytes(path: str | os.PathLike[str]) -> bytes:
    name = _name(path)
    p = Path(path)
    try:
        if p.is_dir():
            raise CurveFileError(f"{name}: is a directory, not a curve file")
        return p.read_bytes()
    except FileNotFoundError:
        raise CurveFileError(f"{name}: no such file") from None
    except PermissionError:
        raise CurveFileError(f"{name}: permission denied") from None
    except OSError as exc:
        raise CurveFileError(f"{name}: cannot read: {exc.strerror or exc}") from None


def _text(raw: bytes) -> str:
    return raw.split(b"\0", 1)[0].decode("latin-1").strip()


def _plural(n: int, word: str) -> str:
    return f"{n} {word}{'' if n == 1 else 's'}"


def read_curves(path: str | os.PathLike[str]) -> CurveData:
    """Read a BCC or HAIR file (chosen by its first bytes); CurveFileError when malformed."""
    data = _read_bytes(path)
    name = _name(path)
    if data[:3] == b"BCC":
        return _noted(_parse_bcc(data, path))
    if data[:4] == b"HAIR":
        return _noted(_parse_hair(data, path))
    if not data:
        raise CurveFileError(f"{name}: empty file; expected a BCC or HAIR curve file")
    raise CurveFileError(
        f"{name}: not a BCC or HAIR file: starts with {data[:4]!r}; a BCC file starts with "
        f"b'BCC', a HAIR file with b'HAIR'")


def read_bcc(path: str | os.PathLike[str]) -> CurveData:
    """Read a BCC file; CurveFileError when it is not one or is malformed."""
    return _noted(_parse_bcc(_read_bytes(path), path))


def read_hair(path: str | os.PathLike[str]) -> CurveData:
    """Read a HAIR file; CurveFileError when it is not one or is malformed."""
    return _noted(_parse_hair(_read_bytes(path), path))


def _noted(data: CurveData) -> CurveData:
    """``data`` with a note naming its curves of zero length (all points equal): they are
    imported as they are, and check and render warn about them (CurveZeroLength)."""
    counts = np.asarray(data.counts, dtype=np.int64)
    if len(counts) and counts.min() > 0:
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        pts = np.asarray(data.points)
        flat = np.all(np.maximum.reduceat(pts, starts) == np.minimum.reduceat(pts, starts), axis=1)
        if flat.any():
            data.notes.append(f"curve {int(np.argmax(flat))} has all points equal (zero length; "
                              f"{_plural(int(flat.sum()), 'such curve')}): it cannot be shaded, remove it "
                              f"from the file (check and render warn: CurveZeroLength)")
    return data


def _check_points(name: str, pts: np.ndarray, counts: np.ndarray, what: str) -> None:
    bad = ~np.isfinite(pts).all(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        curve = int(np.searchsorted(np.cumsum(counts), i, side="right"))
        first = int(np.cumsum(counts)[curve - 1]) if curve else 0
        raise CurveFileError(
            f"{name}: {what} {curve} point {i - first} has a non-finite coordinate "
            f"({', '.join(f'{c:g}' for c in pts[i])}); {int(bad.sum())} such point"
            f"{'' if bad.sum() == 1 else 's'} in all")


def _parse_bcc(data: bytes, path: str | os.PathLike[str]) -> CurveData:
    name = _name(path)
    if len(data) < BCC_HEADER_SIZE:
        if data[:3] != b"BCC" and len(data) >= 3:
            raise CurveFileError(f"{name}: not a BCC file: starts with {data[:3]!r}, expected b'BCC'")
        raise CurveFileError(
            f"{name}: truncated header: the file has {_plural(len(data), 'byte')}, a BCC header "
            f"has {BCC_HEADER_SIZE}")
    if data[:3] != b"BCC":
        raise CurveFileError(f"{name}: not a BCC file: starts with {data[:3]!r}, expected b'BCC'")
    byte_count = data[3]
    if byte_count != 0x44:
        raise CurveFileError(
            f"{name}: byte count 0x{byte_count:02x} is not supported: only 0x44 (4-byte integers "
            f"and 4-byte floats) is")
    ctype = data[4:6]
    if ctype not in _BCC_TYPES:
        raise CurveFileError(
            f"{name}: curve type {ctype!r} is not supported; supported: "
            + ", ".join(f"{k.decode()} ({v})" for k, v in _BCC_TYPE_NAMES.items()))
    dims, up = data[6], data[7]
    if dims != 3:
        raise CurveFileError(f"{name}: curves have {dims} dimensions; only 3D curves are supported")
    curve_count, total_points = struct.unpack_from("<QQ", data, 8)
    info = _text(data[24:64])
    if curve_count == 0:
        raise CurveFileError(f"{name}: header says 0 curves; nothing to import")
    curve_type, basis = _BCC_TYPES[ctype]
    if curve_type == "linear":
        min_open, min_closed = 2, 3
    else:
        min_open, min_closed = 4, 3
    what = _BCC_TYPE_NAMES[ctype]

    size = len(data)
    offset = BCC_HEADER_SIZE
    counts: list[int] = []
    closed: list[bool] = []
    starts: list[int] = []
    unpack = struct.Struct("<i").unpack_from
    for i in range(curve_count):
        if offset + 4 > size:
            extra = f" ({size - offset} stray bytes)" if offset != size else ""
            raise CurveFileError(
                f"{name}: header says {_plural(curve_count, 'curve')} but the file ends after "
                f"{len(counts)}{extra}")
        (n,) = unpack(data, offset)
        offset += 4
        m = abs(n)
        is_closed = n < 0
        need = min_closed if is_closed else min_open
        if m < need:
            kind = "a closed" if is_closed else "an open"
            raise CurveFileError(
                f"{name}: curve {i} has {_plural(m, 'control point')} (count {n}); {kind} "
                f"{what} curve needs at least {need}")
        if offset + 12 * m > size:
            have = (size - offset) // 12
            raise CurveFileError(
                f"{name}: the file ends inside curve {i}: it has {_plural(m, 'control point')} "
                f"but the file holds only {have} more")
        starts.append(offset)
        counts.append(m)
        closed.append(is_closed)
        offset += 12 * m
    if offset != size:
        raise CurveFileError(
            f"{name}: {_plural(size - offset, 'byte')} after the last of the header's "
            f"{_plural(curve_count, 'curve')}; the curve count in the header is wrong or the "
            f"file is corrupt")
    counts_a = np.asarray(counts, dtype=np.int64)
    if int(counts_a.sum()) != total_points:
        raise CurveFileError(
            f"{name}: header says {_plural(total_points, 'control point')} but the curves hold "
            f"{int(counts_a.sum())}")
    # The file's length is 64 + sum(4 + 12 |n|): a whole number of 4-byte words.
    words = np.frombuffer(data, dtype="<f4")
    idx = _ranges(np.asarray(starts, dtype=np.int64) // 4, counts_a * 3)
    pts = words[idx].astype(np.float32).reshape(-1, 3)
    _check_points(name, pts, counts_a, "curve")
    up_axis = "Z" if up == 2 else "Y"
    notes = []
    if up not in (1, 2):
        notes.append(f"up dimension {up} is neither 1 (y) nor 2 (z): the stage is Y up")
    return CurveData(path=os.fspath(path), format="bcc", curve_type=curve_type, basis=basis,
                     points=pts, counts=counts_a, closed=np.asarray(closed, dtype=bool),
                     up_axis=up_axis, info=info, notes=notes)


def _parse_hair(data: bytes, path: str | os.PathLike[str]) -> CurveData:
    name = _name(path)
    if len(data) < HAIR_HEADER_SIZE:
        if data[:4] != b"HAIR" and len(data) >= 4:
            raise CurveFileError(f"{name}: not a HAIR file: starts with {data[:4]!r}, expected b'HAIR'")
        raise CurveFileError(
            f"{name}: truncated header: the file has {_plural(len(data), 'byte')}, a HAIR header "
            f"has {HAIR_HEADER_SIZE}")
    if data[:4] != b"HAIR":
        raise CurveFileError(f"{name}: not a HAIR file: starts with {data[:4]!r}, expected b'HAIR'")
    strands, npoints, flags, dsegs = struct.unpack_from("<IIII", data, 4)
    dthick, dtransp = struct.unpack_from("<ff", data, 20)
    info = _text(data[40:128])
    for label, v in (("strand count", strands), ("point count", npoints)):
        if v >= 2 ** 31:
            raise CurveFileError(
                f"{name}: {label} {v} is negative as a signed 32-bit integer "
                f"({v - 2 ** 32}); expected a count")
    if strands == 0:
        raise CurveFileError(f"{name}: header says 0 strands; nothing to import")
    if not flags & HAIR_POINTS:
        raise CurveFileError(f"{name}: the header's flags (0x{flags:x}) say the file has no points array")
    notes: list[str] = []
    if flags & ~_HAIR_KNOWN:
        notes.append(f"unknown flag bits 0x{flags & ~_HAIR_KNOWN:x} (extensions): data after the "
                     f"known arrays is ignored")

    size = len(data)
    offset = HAIR_HEADER_SIZE

    def take(what: str, count: int, dtype: str, width: int = 1) -> np.ndarray:
        nonlocal offset
        nbytes = count * width * np.dtype(dtype).itemsize
        if offset + nbytes > size:
            raise CurveFileError(
                f"{name}: the file ends inside the {what} array: the header's counts need "
                f"{_plural(nbytes, 'byte')} for it at offset {offset}, the file has "
                f"{max(size - offset, 0)} left")
        a = np.frombuffer(data, dtype=dtype, count=count * width, offset=offset)
        offset += nbytes
        return a.reshape(-1, width) if width > 1 else a

    if flags & HAIR_SEGMENTS:
        segs = take("segments", strands, "<u2").astype(np.int64)
    else:
        if dsegs >= 2 ** 31:
            raise CurveFileError(
                f"{name}: default segment count {dsegs} is negative as a signed 32-bit "
                f"integer ({dsegs - 2 ** 32})")
        if dsegs == 0:
            raise CurveFileError(
                f"{name}: no segments array and a default segment count of 0; each strand "
                f"needs at least 1 segment")
        if strands * (dsegs + 1) != npoints:
            raise CurveFileError(
                f"{name}: header says {_plural(npoints, 'point')} but {_plural(strands, 'strand')}"
                f" of {dsegs} default segments have {strands * (dsegs + 1)} points")
        if offset + 12 * npoints > size:  # before allocating per-strand arrays
            take("points", npoints, "<f4", 3)
        segs = np.full(strands, dsegs, dtype=np.int64)
    zero = np.flatnonzero(segs == 0)
    if zero.size:
        raise CurveFileError(
            f"{name}: strand {int(zero[0])} has 0 segments (1 point; {zero.size} such strand"
            f"{'' if zero.size == 1 else 's'}); a curve needs at least 2 points")
    counts = segs + 1
    if int(counts.sum()) != npoints:
        raise CurveFileError(
            f"{name}: header says {_plural(npoints, 'point')} but the strands' segment counts "
            f"add up to {int(counts.sum())} points")
    pts = take("points", npoints, "<f4", 3).astype(np.float32)
    widths = None
    default_width = None
    if flags & HAIR_THICKNESS:
        widths = take("thickness", npoints, "<f4").astype(np.float64)
        bad = np.flatnonzero(~np.isfinite(widths) | (widths <= 0))
        if bad.size:
            raise CurveFileError(
                f"{name}: thickness of point {int(bad[0])} is {widths[bad[0]]:g}; thickness must "
                f"be positive and finite ({bad.size} bad value{'' if bad.size == 1 else 's'})")
    elif math.isfinite(dthick) and dthick > 0:
        default_width = float(dthick)
    else:
        notes.append(f"default thickness {dthick:g} is not positive: widths come from the fiber "
                     f"or yarn diameter")
    if flags & HAIR_TRANSPARENCY:
        take("transparency", npoints, "<f4")
        notes.append("the transparency array is not imported: a fiber's translucency comes "
                     "from its scattering model")
    if flags & HAIR_COLOURS:
        take("colour", npoints, "<f4", 3)
        notes.append("the colour array is not imported: a fiber's colour comes from its dye "
                     "(dye= / --dye) through the scattering model")
    if offset != size and not flags & ~_HAIR_KNOWN:
        notes.append(f"{_plural(size - offset, 'byte')} after the last array ignored")
    _check_points(name, pts, counts, "strand")
    return CurveData(path=os.fspath(path), format="hair", curve_type="linear", basis=None,
                     points=pts, counts=counts, closed=np.zeros(strands, dtype=bool),
                     widths=widths, default_width=default_width, info=info, notes=notes)


def _ranges(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Concatenated ``arange(s, s + n)`` for each start s and count n (vectorized)."""
    counts = np.asarray(counts, dtype=np.int64)
    total = int(counts.sum())
    before = np.cumsum(counts) - counts
    return np.repeat(np.asarray(starts, dtype=np.int64) - before, counts) + np.arange(total)


# ------------------------------------------------------------------------------ writing
#: ``preset`` left out: the default fiber preset, unless ``yarn`` is given.
UNSET: Any = object()


def _positive(name: str, value: Any) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return v


#: Peak bytes per imported point (the file's float32, the scaled float64 copy, USD's float32
#: arrays, widths and the written layer), rounded up.
BYTES_PER_IMPORTED_POINT = 160
#: The smallest normal float32: USD stores points and widths as float32, and smaller non-zero
#: values lose their precision there, or become 0 (a width of 0 draws nothing).
_FLOAT32_TINY = float(np.finfo(np.float32).tiny)


def _finite_in_usd(values: np.ndarray, path: Any, attribute: str, what: str, fix: str) -> None:
    """Raise ValueError when scaled ``values`` are too large to render (:data:`MAX_COORDINATE`:
    float32 squares overflow, or the value itself) or when non-zero ones fall below float32's
    normal range (they would be written as 0 or lose their precision)."""
    with np.errstate(invalid="ignore"):
        mag = np.abs(values)
        big = ~(mag < MAX_COORDINATE)
        small = (mag > 0) & (mag < _FLOAT32_TINY)
    for bad, how in ((big, TOO_LARGE_EXPECTED),
                     (small, f"expected magnitudes of at least {_FLOAT32_TINY:.3g} (float32's smallest normal "
                             f"value; smaller ones are written as 0)")):
        if bad.any():
            i = int(np.flatnonzero(bad.reshape(len(values), -1).any(axis=1))[0])
            v = np.ravel(values[i])[np.flatnonzero(np.ravel(bad[i]))[0]]
            raise ValueError(f"{_name(path)}: {attribute}: {what} {i} becomes {v:g} after scaling; {how}; {fix}")


def write_curves(data: CurveData, dst_usd: str | os.PathLike[str], *,
                 preset: str | None = UNSET, yarn: str | None = None,
                 units_per_file_unit: float = 1.0, meters_per_unit: float = 0.001,
                 width: float | str | None = None, dye: str | None = None,
                 depth_of_shade: float | None = None, root: str | None = None,
                 memory_budget: MemoryBudget | None = None) -> Path:
    """Write ``data`` to a new USD file (overwritten if it exists); see :func:`import_curves`."""
    scale = _positive("units_per_file_unit", units_per_file_unit)
    mpu = _positive("meters_per_unit", meters_per_unit)
    if isinstance(width, str) and width != "fiber":
        raise ValueError(f"width must be a number (scene units), 'fiber' or None, got {width!r}")
    if width is not None and not isinstance(width, str):
        width = _positive("width", width)
    dst = Path(dst_usd)
    if dst.suffix.lower() not in (".usd", ".usda", ".usdc"):
        raise ValueError(f"{dst.name}: the output must be a .usd, .usda or .usdc file")

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, mpu)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z if data.up_axis == "Z" else UsdGeom.Tokens.y)
    src_name = _name(data.path)
    doc = (f"Imported by usdfiber import from {src_name} ({data.description}); coordinates x "
           f"{scale:g} = scene units of {mpu:g} m.")
    if data.info:
        doc += f" File info: {data.info!r}."
    for n in data.notes:
        doc += f" Note: {n}."
    stage.GetRootLayer().documentation = doc
    root_name = root or Tf.MakeValidIdentifier(Path(src_name).stem or "Curves")
    root_path = Sdf.Path.absoluteRootPath.AppendChild(root_name)
    stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, root_path).GetPrim())

    (memory_budget or MemoryBudget.resolve()).require(
        len(data.points) * BYTES_PER_IMPORTED_POINT, f"{_name(data.path)}: importing {len(data.points)} points")
    points = data.points.astype(np.float64) * scale
    _finite_in_usd(points, data.path, "points", "coordinate", "change --units-per-file-unit")
    starts = np.concatenate([[0], np.cumsum(data.counts)[:-1]]).astype(np.int64)
    groups = [("Curves", ~data.closed, "nonperiodic"), ("ClosedCurves", data.closed, "periodic")]
    present = [(n, m, w) for n, m, w in groups if m.any()]
    split = len(present) > 1
    for child, mask, wrap in present:
        curve_ids = np.flatnonzero(mask)
        counts = data.counts[curve_ids]
        idx = _ranges(starts[curve_ids], counts) if split else np.arange(len(points))
        curves = UsdGeom.BasisCurves.Define(stage, root_path.AppendChild(child))
        curves.CreateTypeAttr(data.curve_type)
        if data.basis is not None:
            curves.CreateBasisAttr(data.basis)
        curves.CreateWrapAttr(wrap)
        pts = np.ascontiguousarray(points[idx], dtype=np.float32)
        curves.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts))
        curves.CreateCurveVertexCountsAttr(Vt.IntArray.FromNumpy(counts.astype(np.int32)))
        if split:
            pv = UsdGeom.PrimvarsAPI(curves).CreatePrimvar(
                "sourceCurveIndex", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.uniform)
            pv.Set(Vt.IntArray.FromNumpy(curve_ids.astype(np.int32)))
        prim = curves.GetPrim()
        if yarn is not None:
            authoring.apply_yarn(prim, yarn, None if preset is UNSET else preset,
                                 **_dye_args(dye, depth_of_shade))
        else:
            authoring.apply_fiber(prim, DEFAULT_FIBER_PRESET if preset is UNSET else preset,
                                  **_dye_args(dye, depth_of_shade))
        if isinstance(width, float):
            widths, interp, fix = np.array([width]), UsdGeom.Tokens.constant, "change --width"
        elif width is None and data.widths is not None:
            widths, interp = data.widths[idx] * scale, UsdGeom.Tokens.vertex
            fix = "change --units-per-file-unit or give --width"
        elif width is None and data.default_width is not None:
            widths, interp = np.array([data.default_width * scale]), UsdGeom.Tokens.constant
            fix = "change --units-per-file-unit or give --width"
        else:
            widths, interp = np.array([_nominal_width(prim, yarn is not None, mpu)]), \
                UsdGeom.Tokens.constant
            fix = "change --meters-per-unit (the fiber's diameter in scene units) or give --width"
        _finite_in_usd(widths, data.path, "widths", "width", fix)
        wv = Vt.FloatArray.FromNumpy(np.ascontiguousarray(widths, dtype=np.float32))
        curves.CreateWidthsAttr(wv)
        curves.SetWidthsInterpolation(interp)
        curves.CreateExtentAttr(UsdGeom.Curves.ComputeExtent(curves.GetPointsAttr().Get(), wv))

    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_name(f".{dst.stem}.tmp{os.getpid()}{dst.suffix}")
    try:
        try:
            ok = stage.GetRootLayer().Export(str(tmp))
        except Tf.ErrorException as exc:
            raise OSError(" ".join(str(exc).split()) or f"USD could not write {tmp}") from None
        if not ok:
            raise OSError(f"USD could not write {tmp}")
        os.replace(tmp, dst)
    finally:
        if tmp.exists():
            tmp.unlink()
    return dst


def _dye_args(dye: str | None, depth_of_shade: float | None) -> dict[str, Any]:
    out: dict[str, Any] = {}
    if dye is not None:
        out["dye"] = dye
    if depth_of_shade is not None:
        out["depth_of_shade"] = depth_of_shade
    return out


def _nominal_width(prim: Usd.Prim, is_yarn: bool, mpu: float) -> float:
    """The fiber diameter (um) or nominal yarn diameter (mm) in scene units."""
    if is_yarn:
        return authoring.yarn_diameter_mm(prim) * 1e-3 / mpu
    return float(prim.GetAttribute(Fiber.DIAMETER).Get()) * 1e-6 / mpu


def import_curves(src: str | os.PathLike[str], dst_usd: str | os.PathLike[str], *,
                  preset: str | None = UNSET, yarn: str | None = None,
                  units_per_file_unit: float = 1.0, meters_per_unit: float = 0.001,
                  width: float | str | None = None, dye: str | None = None,
                  depth_of_shade: float | None = None, root: str | None = None,
                  memory_budget: MemoryBudget | None = None) -> Path:
    """Import a BCC or HAIR file ``src`` as fiber (or yarn) curves into a new stage ``dst_usd``.

    - ``preset``: the fiber preset (default "polyester"; None authors only FiberAPI's
      fallbacks and the dye). With ``yarn`` (a Table 3 preset, e.g. "CNe 50") the curves
      are yarn centre lines (FiberYarnAPI + FiberAPI) and ``preset``, when given, overrides
      the yarn's fiber (default: the yarn's composition).
    - ``units_per_file_unit``: scene units per file unit (scales points and thickness);
      ``meters_per_unit``: the stage's metersPerUnit (default 0.001, millimetres).
    - ``width``: None -> the file's thickness (HAIR) else the fiber / yarn diameter;
      "fiber" -> always the fiber / yarn diameter; a number -> that constant width in
      scene units.
    - ``dye``, ``depth_of_shade``: a dye preset or colour (``usdfiber presets``) and its
      depth of shade in percent.
    - ``root``: name of the default prim (an Xform; default: the file's stem). Its children
      are ``Curves`` (open curves) and ``ClosedCurves`` (closed curves); when a file has
      both, each carries a uniform ``primvars:sourceCurveIndex`` with the curves' indices
      in the file.

    - ``memory_budget`` (default :meth:`MemoryBudget.resolve`): a file whose points do not
      fit is refused (MemoryBudgetError) before it is read.

    Returns the output path. Raises CurveFileError for malformed files,
    usdfiber.authoring.AuthoringError for unknown presets or dyes, ValueError for bad
    numbers (also points or widths that overflow float32 once scaled).
    """
    budget = memory_budget or MemoryBudget.resolve()
    check_file_budget(src, budget)
    data = read_curves(src)
    return write_curves(data, dst_usd, preset=preset, yarn=yarn,
                        units_per_file_unit=units_per_file_unit, meters_per_unit=meters_per_unit,
                        width=width, dye=dye, depth_of_shade=depth_of_shade, root=root,
                        memory_budget=budget)


def check_file_budget(src: str | os.PathLike[str], budget: MemoryBudget) -> None:
    """Refuse a curve file whose points (at least 12 bytes each in the file) would not fit
    ``budget`` once imported, before reading it."""
    try:
        size = os.path.getsize(src)
    except OSError:
        return  # read_curves reports the file itself
    budget.require(size / 12 * BYTES_PER_IMPORTED_POINT,
                   f"{_name(src)}: importing a curve file of {size} bytes (up to {size // 12} points)")
