"""UsdGeom.Mesh (+ a UsdPreviewSurface subset) -> Mitsuba 3 meshes built from arrays.

Geometry (UsdGeomMesh docs):

* Polygons are fan-triangulated (corners 0, k, k+1). Faces listed in ``holeIndices`` and
  faces with fewer than 3 vertices are skipped (the latter with a warning).
* Winding: USD faces are counter-clockwise around the outward normal for
  ``orientation = rightHanded``. A ``leftHanded`` mesh, or a world transform with negative
  determinant (as Hydra does), gets its triangles reversed, so Mitsuba's geometric normal
  (``cross(p1 - p0, p2 - p0)``) is the outward one.
* Positions are transformed to world space (``[p, 1] @ M``); normals with the inverse
  transpose and renormalized. Scene units are kept.
* Normals: ``primvars:normals`` (wins, per the docs) or ``normals``, any interpolation
  (constant, uniform, vertex/varying, faceVarying; indexed primvars flattened).
  Without authored normals a ``subdivisionScheme = none`` mesh is flat shaded; a
  subdivision mesh (USD's fallback scheme is ``catmullClark``) is rendered as its control
  cage (with a warning) with area-weighted smooth vertex normals, to approximate the limit
  surface's shading.
* Texture coordinates (only when a texture needs them): the primvar the material's
  ``UsdPrimvarReader_float2`` names (``st`` by default), vertex or faceVarying (uniform and
  constant also accepted). Mitsuba's bitmap v runs from the image top, USD's t from the
  bottom: ``uv = (s, 1 - t)``.
* Primvars that are not per point (faceVarying, uniform) split vertices: a Mitsuba vertex is
  one unique (point, normal, uv, colour) combination.

Materials: ``UsdShade.MaterialBindingAPI.ComputeBoundMaterial("full")`` (falls back to the
all-purpose binding), then the material's universal surface (``ComputeSurfaceSource()``).
A ``UsdPreviewSurface`` maps to Mitsuba's ``principled`` BSDF:

===============================  =============================================================
UsdPreviewSurface                Mitsuba
===============================  =============================================================
diffuseColor                     ``base_color`` (value, UsdUVTexture, or a primvar reader)
roughness, metallic              ``roughness``, ``metallic`` (value or one texture channel)
ior (metallic workflow)          ``eta`` (F0 = ((ior-1)/(ior+1))^2 in both)
useSpecularWorkflow=1            ``metallic = 0``, ``specular = lum(specularColor) / 0.08``;
                                 approximate (the colour of F0 is lost): warns
clearcoat, clearcoatRoughness    ``clearcoat``, ``clearcoat_gloss = 1 - clearcoatRoughness``
opacity < 1 / texture            ``mask`` (opacity as coverage); ``opacityThreshold > 0``
                                 binarizes it (cut-out), as the spec says
emissiveColor != 0 / texture     an ``area`` emitter of that radiance on the mesh
doubleSided                      ``twosided`` wrapper (else Mitsuba's one-sided BSDF: the back
                                 faces render black)
normal, displacement             ignored with a warning when connected / non-default
===============================  =============================================================

UsdUVTexture files are read with OpenImageIO (any format it reads) and passed to Mitsuba as a
``bitmap`` texture from memory: ``sourceColorSpace`` (auto: sRGB for 8-bit RGB/RGBA files),
``scale``/``bias``, the r/g/b/a/rgb output, ``wrapS``/``wrapT`` (repeat/mirror/clamp;
``black`` -> clamp with a warning) are applied. A missing file -> warning naming the
shader input; the texture's ``fallback`` value is used.

Other surface shaders (MaterialX, renderer-specific), or a material with no universal
surface -> 0.18 grey ``diffuse`` with a warning naming the material. No bound material:
``primvars:displayColor`` (any interpolation; non-constant ones become a Mitsuba mesh
attribute) as a diffuse albedo, else 0.18 grey.

Per-face materials (GeomSubsets of family ``materialBind``) need one Mitsuba mesh each:
:func:`mesh_shapes` returns them; :func:`mesh_shape` uses the prim's own binding for the
whole mesh and warns when such subsets exist.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pxr import Sdf, Usd, UsdGeom, UsdShade

from usdfiber.geometry.curves import too_large_text
from usdfiber.translators.mitsuba.errors import TranslationError
from usdfiber.translators.mitsuba.images import load_image
from usdfiber.translators.mitsuba.render_settings import as_timecode

__all__ = ["MaterialInfo", "material_bsdf", "mesh_shape", "mesh_shapes"]

_GREY = 0.18
_PREVIEW_DEFAULTS: dict[str, Any] = {
    "diffuseColor": (0.18, 0.18, 0.18), "emissiveColor": (0.0, 0.0, 0.0),
    "useSpecularWorkflow": 0, "specularColor": (0.0, 0.0, 0.0), "metallic": 0.0,
    "roughness": 0.5, "clearcoat": 0.0, "clearcoatRoughness": 0.01, "opacity": 1.0,
    "opacityThreshold": 0.0, "ior": 1.5, "normal": (0.0, 0.0, 1.0), "displacement": 0.0,
    "occlusion": 1.0,
}
_LUMA = np.array([0.2126, 0.7152, 0.0722])


def _mi():
    from usdfiber.backend import mitsuba

    return mitsuba()


def _rgb(v: Any) -> dict:
    return {"type": "rgb", "value": [float(c) for c in v]}


@dataclass
class MaterialInfo:
    """A translated material: the Mitsuba BSDF / emitter dicts and what they need of the mesh.

    ``uv_primvar``: primvar to load as texture coordinates (None: no texture).
    ``color_primvar``: primvar to attach as the mesh attribute ``vertex_color`` (or
    ``face_color`` for uniform interpolation) read by a ``mesh_attribute`` texture.
    """

    bsdf: dict
    emitter: dict | None = None
    uv_primvar: str | None = None
    color_primvar: str | None = None
    warnings: list[str] = field(default_factory=list)
    #: The loaded ``mi.BSDF`` once built, shared by every mesh using a cached material.
    bsdf_object: Any = None


# ----------------------------------------------------------------------------- shading


class _Shading:
    """Resolution of UsdPreviewSurface inputs for one material at one time."""

    def __init__(self, material_path: str, tc: Usd.TimeCode, warns: list[str]) -> None:
        self.where = material_path
        self.tc = tc
        self.warns = warns
        self.uv_primvar: str | None = None
        self.color_primvar: str | None = None

    def source(self, shader: UsdShade.Shader, name: str):
        """('value', v) | ('output', (shader, output_name)) | ('default', None)."""
        inp = shader.GetInput(name)
        if not inp:
            return "default", None
        attrs = inp.GetValueProducingAttributes(shaderOutputsOnly=False)
        if not attrs:
            value = inp.Get(self.tc)
            return ("default", None) if value is None else ("value", self._finite(shader, name, value))
        attr = attrs[0]
        base, kind = UsdShade.Utils.GetBaseNameAndType(attr.GetName())
        if kind == UsdShade.AttributeType.Output:
            return "output", (UsdShade.Shader(attr.GetPrim()), str(base))
        value = attr.Get(self.tc)
        return ("default", None) if value is None else ("value", self._finite(shader, name, value))

    @staticmethod
    def _finite(shader: UsdShade.Shader, name: str, value: Any) -> Any:
        # A NaN or Inf colour, emission or roughness renders NaN pixels, refused only after the
        # whole render: refused here, naming the input.
        if isinstance(value, (str, bytes, bool, Sdf.AssetPath)):
            return value
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            return value
        if not np.all(np.isfinite(arr)):
            raise TranslationError(shader.GetPath(), f"inputs:{name}", f"must be finite, got {value}")
        return value

    def value(self, shader: UsdShade.Shader, name: str, default: Any) -> Any:
        kind, v = self.source(shader, name)
        return v if kind == "value" else default

    def texture(self, shader: UsdShade.Shader, name: str, *, color: bool,
                threshold: float | None = None) -> tuple[str, Any]:
        """An input as ('const', value) or ('tex', mitsuba texture dict).

        ``color`` asks for 3 channels (else 1). ``threshold`` binarizes (opacityThreshold).
        """
        default = _PREVIEW_DEFAULTS[name]
        kind, v = self.source(shader, name)
        if kind == "default":
            return "const", default
        if kind == "value":
            return "const", v
        src, out = v
        sid = src.GetShaderId() or ""
        where = f"{shader.GetPath()}.inputs:{name}"
        if sid == "UsdUVTexture":
            return self._uv_texture(src, out, where, color=color, default=default, threshold=threshold)
        if sid.startswith("UsdPrimvarReader_") and color:
            varname = self.value(src, "varname", None)
            if varname:
                self.color_primvar = str(varname)
                return "tex", {"type": "mesh_attribute", "name": "vertex_color"}  # renamed later
        self.warns.append(f"{where}: connected to {sid or src.GetPath()!s}:{out}, which is not "
                          f"supported; using {default}")
        return "const", default

    def _uv_texture(self, tex: UsdShade.Shader, out: str, where: str, *, color: bool,
                    default: Any, threshold: float | None) -> tuple[str, Any]:
        tpath = tex.GetPath()
        fallback = np.array(self.value(tex, "fallback", (0.0, 0.0, 0.0, 1.0)), dtype=np.float64)
        channel = {"r": 0, "g": 1, "b": 2, "a": 3}.get(out)
        if out != "rgb" and channel is None:
            self.warns.append(f"{tpath}.outputs:{out}: unknown UsdUVTexture output; using {default}")
            return "const", default

        def fallback_value() -> Any:
            v = fallback[:3] if out == "rgb" else fallback[channel]
            if color and out != "rgb":
                return (float(v),) * 3
            if not color and out == "rgb":
                return float(v[0])
            return tuple(float(c) for c in v) if out == "rgb" else float(v)

        asset = self.value(tex, "file", None)
        if asset is None or not asset.path:
            self.warns.append(f"{tpath}.inputs:file: no texture file; using the fallback")
            return "const", fallback_value()
        if "<UDIM>" in asset.path:
            self.warns.append(f"{tpath}.inputs:file: UDIM textures are not supported; using the fallback")
            return "const", fallback_value()
        path = asset.resolvedPath
        if not path or not os.path.isfile(path):
            self.warns.append(f"{tpath}.inputs:file: texture {asset.path!r} not found; using the fallback")
            return "const", fallback_value()
        cs = str(self.value(tex, "sourceColorSpace", "auto"))
        try:
            data = load_image(path, cs, where=f"{tpath}.inputs:file")
        except TranslationError as exc:
            self.warns.append(f"{exc}; using the fallback")
            return "const", fallback_value()
        # Expand to RGBA per the UsdUVTexture spec: 1 ch -> (v, v, v, 1), 2 ch -> (v, v, v, a).
        h, w, n = data.shape
        rgba = np.ones((h, w, 4), dtype=np.float32)
        if n <= 2:
            rgba[..., :3] = data[..., :1]
            if n == 2:
                rgba[..., 3] = data[..., 1]
        else:
            rgba[..., :min(n, 4)] = data[..., :4]
        scale = np.array(self.value(tex, "scale", (1.0, 1.0, 1.0, 1.0)), dtype=np.float32)
        bias = np.array(self.value(tex, "bias", (0.0, 0.0, 0.0, 0.0)), dtype=np.float32)
        rgba = rgba * scale + bias
        arr = rgba[..., :3] if out == "rgb" else rgba[..., channel:channel + 1]
        if color and arr.shape[2] == 1:
            arr = np.repeat(arr, 3, axis=2)
        elif not color and arr.shape[2] == 3:
            arr = arr @ _LUMA.astype(np.float32)[:, None]
        if threshold is not None and threshold > 0:
            arr = (arr >= threshold).astype(np.float32)

        wraps = []
        for axis in ("wrapS", "wrapT"):
            wmode = str(self.value(tex, axis, "useMetadata"))
            if wmode == "black":
                self.warns.append(f"{tpath}.inputs:{axis}: 'black' wrapping is not supported; clamped")
                wmode = "clamp"
            wraps.append({"useMetadata": "repeat"}.get(wmode, wmode))
        if wraps[0] != wraps[1]:
            self.warns.append(f"{tpath}: wrapS {wraps[0]!r} != wrapT {wraps[1]!r}; Mitsuba has one "
                              f"wrap mode: {wraps[0]!r} used")

        st_kind, st = self.source(tex, "st")
        varname = "st"
        if st_kind == "output":
            reader, _ = st
            if (reader.GetShaderId() or "").startswith("UsdPrimvarReader_"):
                varname = str(self.value(reader, "varname", "st") or "st")
            else:
                self.warns.append(f"{tpath}.inputs:st: connected to {reader.GetPath()} "
                                  f"({reader.GetShaderId()}), not a primvar reader; using 'st'")
        if self.uv_primvar not in (None, varname):
            self.warns.append(f"{tpath}.inputs:st: textures read different primvars "
                              f"({self.uv_primvar!r}, {varname!r}); Mitsuba meshes have one uv set: "
                              f"{self.uv_primvar!r} used")
        else:
            self.uv_primvar = varname
        mi = _mi()
        return "tex", {
            "type": "bitmap",
            "bitmap": mi.Bitmap(np.ascontiguousarray(arr, dtype=np.float32)),
            "raw": not color,
            "filter_type": "bilinear",
            "wrap_mode": wraps[0],
        }


def _as_param(kind: str, v: Any, color: bool) -> Any:
    if kind == "tex":
        return v
    if color:
        return _rgb(np.maximum(np.array(v, dtype=np.float64)[:3], 0.0))
    return float(v)


def _grey(double_sided: bool) -> dict:
    bsdf = {"type": "diffuse", "reflectance": _rgb((_GREY,) * 3)}
    return {"type": "twosided", "bsdf": bsdf} if double_sided else bsdf


def material_bsdf(material: UsdShade.Material | None, time: Usd.TimeCode | float | None = None,
                  *, double_sided: bool = False) -> MaterialInfo:
    """Translate a bound material (see the module docstring). ``None`` -> grey diffuse."""
    tc = as_timecode(time)
    if material is None or not material.GetPrim():
        return MaterialInfo(bsdf=_grey(double_sided))
    where = str(material.GetPath())
    warns: list[str] = []
    shader, _, _ = material.ComputeSurfaceSource()
    sid = (shader.GetShaderId() or "") if shader else ""
    if sid != "UsdPreviewSurface":
        outs = [o.GetFullName() for o in material.GetSurfaceOutputs()]
        what = f"surface shader {sid!r}" if shader else f"no universal surface (outputs: {outs})"
        warns.append(f"{where}: {what} is not UsdPreviewSurface; rendered as {_GREY} grey diffuse")
        return MaterialInfo(bsdf=_grey(double_sided), warnings=warns)

    sh = _Shading(where, tc, warns)
    spath = shader.GetPath()
    params: dict[str, Any] = {"type": "principled"}
    k, v = sh.texture(shader, "diffuseColor", color=True)
    params["base_color"] = _as_param(k, v, True)
    for name in ("roughness", "metallic"):
        k, v = sh.texture(shader, name, color=False)
        params[name] = _as_param(k, v, False)

    if int(sh.value(shader, "useSpecularWorkflow", 0)):
        k, spec = sh.texture(shader, "specularColor", color=True)
        if k == "tex":
            warns.append(f"{spath}.inputs:specularColor: textured specular colour is not supported; "
                         "its mean is not known here, 0.04 used")
            f0 = 0.04
        else:
            f0 = float(np.clip(np.array(spec, dtype=np.float64)[:3] @ _LUMA, 0.0, 0.99))
        params["metallic"] = 0.0
        params["specular"] = f0 / 0.08
        warns.append(f"{spath}.inputs:useSpecularWorkflow: approximated by principled's specular "
                     f"(F0 = luminance of specularColor = {f0:.4g}; tint lost)")
    else:
        ior = float(sh.value(shader, "ior", 1.5))
        eta = max(ior, 1.0 / ior) if ior > 0 else 1.5
        if ior < 1:
            warns.append(f"{spath}.inputs:ior: {ior:g} < 1 treated as {eta:g} (same F0)")
        params["eta"] = max(eta, 1.0001)  # principled needs eta > 1

    k, v = sh.texture(shader, "clearcoat", color=False)
    if k == "tex" or float(v) > 0:
        params["clearcoat"] = _as_param(k, v, False)
        kr, vr = sh.texture(shader, "clearcoatRoughness", color=False)
        if kr == "tex":
            warns.append(f"{spath}.inputs:clearcoatRoughness: texture not supported; 0.01 used")
            vr = 0.01
        params["clearcoat_gloss"] = float(np.clip(1.0 - float(vr), 0.0, 1.0))

    for name in ("normal", "displacement"):
        kind, val = sh.source(shader, name)
        if kind == "output" or (kind == "value" and tuple(np.atleast_1d(val)) !=
                                tuple(np.atleast_1d(_PREVIEW_DEFAULTS[name]))):
            warns.append(f"{spath}.inputs:{name}: not supported by the Mitsuba translator; ignored")

    bsdf: dict = {"type": "twosided", "bsdf": params} if double_sided else params
    threshold = float(sh.value(shader, "opacityThreshold", 0.0))
    k, v = sh.texture(shader, "opacity", color=False, threshold=threshold)
    if k == "tex":
        bsdf = {"type": "mask", "opacity": v, "bsdf": bsdf}
    else:
        op = float(v)
        if threshold > 0:
            op = 1.0 if op >= threshold else 0.0
        if op < 1.0:
            bsdf = {"type": "mask", "opacity": max(op, 0.0), "bsdf": bsdf}

    emitter = None
    k, v = sh.texture(shader, "emissiveColor", color=True)
    if k == "tex" or float(np.max(v)) > 0:
        emitter = {"type": "area", "radiance": _as_param(k, v, True)}
    return MaterialInfo(bsdf=bsdf, emitter=emitter, uv_primvar=sh.uv_primvar,
                        color_primvar=sh.color_primvar, warnings=warns)


# ----------------------------------------------------------------------------- geometry


@dataclass
class _Topology:
    points: np.ndarray        # (P, 3) world space
    point_of_corner: np.ndarray  # (C,) faceVertexIndices
    face_of_corner: np.ndarray   # (C,)
    tris: np.ndarray          # (T, 3) corner indices, winding already fixed
    face_of_tri: np.ndarray   # (T,)
    n_faces: int
    normal_matrix: np.ndarray  # (3, 3): n_world = n @ normal_matrix


def _topology(prim: Usd.Prim, xform: np.ndarray, tc: Usd.TimeCode, warns: list[str]) -> _Topology:
    mesh = UsdGeom.Mesh(prim)
    where = str(prim.GetPath())
    pts = mesh.GetPointsAttr().Get(tc)
    if pts is None or len(pts) == 0:
        raise TranslationError(where, "points", "no points")
    points = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    if not np.isfinite(points).all():
        raise TranslationError(where, "points", "contains NaN or infinite values")
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(tc) or [], dtype=np.int64)
    indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(tc) or [], dtype=np.int64)
    if (counts < 0).any():
        raise TranslationError(where, "faceVertexCounts", "negative face vertex count")
    if counts.sum() != len(indices):
        raise TranslationError(where, "faceVertexCounts",
                               f"sum {int(counts.sum())} != len(faceVertexIndices) {len(indices)}")
    bad = np.flatnonzero((indices < 0) | (indices >= len(points)))
    if len(bad):
        raise TranslationError(where, "faceVertexIndices",
                               f"{len(bad)} indices out of range [0, {len(points)}), first "
                               f"faceVertexIndices[{bad[0]}] = {indices[bad[0]]}")
    n_faces = len(counts)
    offsets = np.concatenate([[0], np.cumsum(counts)[:-1]]) if n_faces else np.zeros(0, np.int64)
    face_of_corner = np.repeat(np.arange(n_faces), counts)

    keep = counts >= 3
    if not keep.all():
        warns.append(f"{where}.faceVertexCounts: {int((~keep).sum())} faces with fewer than 3 "
                     "vertices skipped")
    holes = np.asarray(mesh.GetHoleIndicesAttr().Get(tc) or [], dtype=np.int64)
    if len(holes):
        valid = (holes >= 0) & (holes < n_faces)
        if not valid.all():
            warns.append(f"{where}.holeIndices: {int((~valid).sum())} indices out of range ignored")
        keep[holes[valid]] = False

    # Fan triangulation, vectorized: face f with n corners -> (o, o+k, o+k+1), k = 1..n-2.
    ntri = np.where(keep, counts - 2, 0)
    face_of_tri = np.repeat(np.arange(n_faces), ntri)
    first = np.repeat(offsets, ntri)
    k = np.arange(int(ntri.sum())) - np.repeat(np.cumsum(ntri) - ntri, ntri) + 1
    tris = np.stack([first, first + k, first + k + 1], axis=1)

    m = np.asarray(xform, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"{where}: expected a (4, 4) transform, got shape {m.shape}")
    lin = m[:3, :3]
    det = float(np.linalg.det(lin))
    if abs(det) < 1e-300:
        raise TranslationError(where, "xformOpOrder", "singular world transform")
    left = str(mesh.GetOrientationAttr().Get(tc) or "rightHanded") == UsdGeom.Tokens.leftHanded
    if left != (det < 0):
        tris = tris[:, [0, 2, 1]]
    world = points @ lin + m[3, :3]
    huge = too_large_text(world, "point")
    if huge:
        raise TranslationError(where, "points", f"in world space (after the local-to-world transform) {huge}")
    return _Topology(world, indices, face_of_corner, tris, face_of_tri, n_faces,
                     np.linalg.inv(lin).T)


def _corner_values(prim: Usd.Prim, topo: _Topology, values: np.ndarray | None, interp: str,
                   attr: str, warns: list[str]) -> np.ndarray | None:
    """Per-corner values (C, k) of a primvar, or None (with a warning) if it does not fit."""
    if values is None or len(values) == 0:
        return None
    v = np.asarray(values, dtype=np.float64)
    v = v.reshape(len(v), -1)
    need = {"constant": 1, "uniform": topo.n_faces, "vertex": len(topo.points),
            "varying": len(topo.points), "faceVarying": len(topo.point_of_corner)}.get(interp)
    if need is None or len(v) < need:
        warns.append(f"{prim.GetPath()}.{attr}: {len(v)} values do not fit interpolation "
                     f"{interp!r} (need {need}); ignored")
        return None
    if interp == "constant":
        return np.repeat(v[:1], len(topo.point_of_corner), axis=0)
    if interp == "uniform":
        return v[topo.face_of_corner]
    if interp in ("vertex", "varying"):
        return v[topo.point_of_corner]
    return v[: len(topo.point_of_corner)]


def _primvar(prim: Usd.Prim, name: str, tc: Usd.TimeCode) -> tuple[np.ndarray | None, str]:
    pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar(name)
    if not pv or not pv.HasValue():
        return None, ""
    value = pv.ComputeFlattened(tc)
    if value is None:
        return None, ""
    return np.asarray(value, dtype=np.float64), str(pv.GetInterpolation())


def _normals(prim: Usd.Prim, topo: _Topology, tc: Usd.TimeCode,
             warns: list[str]) -> np.ndarray | None:
    """Authored per-corner normals in world space, or None."""
    values, interp = _primvar(prim, "normals", tc)
    attr = "primvars:normals"
    if values is None:
        mesh = UsdGeom.Mesh(prim)
        raw = mesh.GetNormalsAttr().Get(tc)
        if raw is None or len(raw) == 0:
            return None
        values, interp, attr = np.asarray(raw, dtype=np.float64), str(mesh.GetNormalsInterpolation()), "normals"
    per_corner = _corner_values(prim, topo, values, interp, attr, warns)
    if per_corner is None:
        return None
    n = per_corner[:, :3] @ topo.normal_matrix
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(length > 0, length, 1.0)


def _smooth_normals(topo: _Topology) -> np.ndarray:
    """Area-weighted vertex normals (each polygon's normal added to its points), per corner.

    Polygon normals (the sum of their fan triangles' cross products), not triangle normals,
    so that the arbitrary fan split does not bias the average.
    """
    p = topo.points[topo.point_of_corner[topo.tris]]  # (T, 3, 3)
    tri_n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    face_n = np.zeros((topo.n_faces, 3))
    np.add.at(face_n, topo.face_of_tri, tri_n)
    acc = np.zeros_like(topo.points)
    used = np.zeros(topo.n_faces, dtype=bool)
    used[topo.face_of_tri] = True  # holes and degenerate faces do not contribute
    corner_used = used[topo.face_of_corner]
    np.add.at(acc, topo.point_of_corner[corner_used], face_n[topo.face_of_corner[corner_used]])
    length = np.linalg.norm(acc, axis=1, keepdims=True)
    acc = acc / np.where(length > 0, length, 1.0)
    return acc[topo.point_of_corner]


def _build(prim: Usd.Prim, name: str, topo: _Topology, tri_mask: np.ndarray | None,
           info: MaterialInfo, normals: np.ndarray | None, tc: Usd.TimeCode, warns: list[str]):
    where = str(prim.GetPath())
    tris = topo.tris if tri_mask is None else topo.tris[tri_mask]
    face_of_tri = topo.face_of_tri if tri_mask is None else topo.face_of_tri[tri_mask]
    if len(tris) == 0:
        raise TranslationError(where, "faceVertexCounts", "no renderable faces")

    columns: list[np.ndarray] = []  # per-corner attribute columns that may split vertices
    uv = None
    if info.uv_primvar:
        values, interp = _primvar(prim, info.uv_primvar, tc)
        if values is None:
            warns.append(f"{where}.primvars:{info.uv_primvar}: texture coordinates missing; "
                         "textures sample uv (0, 0)")
        else:
            uv = _corner_values(prim, topo, values, interp, f"primvars:{info.uv_primvar}", warns)
            if uv is not None:
                uv = np.stack([uv[:, 0], 1.0 - uv[:, 1]], axis=1)  # Mitsuba v from the image top
    color = None
    color_mode = None
    if info.color_primvar:
        values, interp = _primvar(prim, info.color_primvar, tc)
        attr = f"primvars:{info.color_primvar}"
        if interp == "uniform":  # the BSDF reads the "face_color" attribute
            color_mode = "face"
            if len(values) >= topo.n_faces:
                color = values.reshape(len(values), -1)[:, :3][face_of_tri]
            else:
                warns.append(f"{where}.{attr}: {len(values)} uniform values for {topo.n_faces} "
                             f"faces; colour {_GREY} used")
                color = np.full((len(face_of_tri), 3), _GREY)
        else:
            color_mode = "vertex"
            if values is None:
                warns.append(f"{where}.{attr}: missing; colour {_GREY} used")
            else:
                color = _corner_values(prim, topo, values, interp, attr, warns)
            color = np.full((len(topo.point_of_corner), 3), _GREY) if color is None else color[:, :3]
    for arr in (normals, uv, color if color_mode == "vertex" else None):
        if arr is not None:
            columns.append(arr)

    corners = tris.reshape(-1)
    if columns:
        key = np.concatenate([topo.point_of_corner[corners, None].astype(np.float64)]
                             + [c[corners] for c in columns], axis=1)
    else:
        key = topo.point_of_corner[corners]
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    rep = corners[first]  # one corner per Mitsuba vertex
    faces = inverse.reshape(-1, 3).astype(np.uint32)

    mi = _mi()
    props = mi.Properties()
    if info.bsdf_object is None:
        info.bsdf_object = mi.load_dict(info.bsdf)
    props["bsdf"] = info.bsdf_object
    if info.emitter is not None:
        props["emitter"] = mi.load_dict(info.emitter)
    shape = mi.Mesh(name, len(rep), len(faces), props,
                    has_vertex_normals=normals is not None, has_vertex_texcoords=uv is not None)
    params = mi.traverse(shape)
    params["vertex_positions"] = mi.Float(topo.points[topo.point_of_corner[rep]].astype(np.float32).ravel())
    params["faces"] = mi.UInt32(faces.ravel())
    if normals is not None:
        params["vertex_normals"] = mi.Float(normals[rep].astype(np.float32).ravel())
    if uv is not None:
        params["vertex_texcoords"] = mi.Float(uv[rep].astype(np.float32).ravel())
    params.update()
    if color_mode == "vertex":
        shape.add_attribute("vertex_color", 3, mi.Float(color[rep].astype(np.float32).ravel()))
    elif color_mode == "face":
        shape.add_attribute("face_color", 3, mi.Float(np.asarray(color, np.float32).ravel()))
    return shape


def _bound_material(prim: Usd.Prim) -> UsdShade.Material | None:
    mat, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial(UsdShade.Tokens.full)
    return mat if mat and mat.GetPrim() else None


def _info_for(prim: Usd.Prim, material: UsdShade.Material | None, tc: Usd.TimeCode,
              double_sided: bool, cache: dict | None = None) -> MaterialInfo:
    key = None
    if material is not None and cache is not None:
        key = (str(material.GetPath()), double_sided, None if tc.IsDefault() else tc.GetValue())
        hit = cache.get(key)
        if hit is not None:  # its warnings were reported with the first mesh
            return MaterialInfo(bsdf=hit.bsdf, emitter=hit.emitter, uv_primvar=hit.uv_primvar,
                                bsdf_object=hit.bsdf_object)
    if material is not None:
        info = material_bsdf(material, tc, double_sided=double_sided)
        if key is not None and info.color_primvar is None:  # mesh-independent: shareable
            cache[key] = info
    else:
        values, interp = _primvar(prim, "displayColor", tc)
        if values is not None and interp == "constant":
            bsdf = {"type": "diffuse", "reflectance": _rgb(np.clip(values.reshape(-1, 3)[0], 0, 1))}
            info = MaterialInfo(bsdf={"type": "twosided", "bsdf": bsdf} if double_sided else bsdf)
        elif values is not None:
            tex = {"type": "mesh_attribute",
                   "name": "face_color" if interp == "uniform" else "vertex_color"}
            bsdf = {"type": "diffuse", "reflectance": tex}
            info = MaterialInfo(bsdf={"type": "twosided", "bsdf": bsdf} if double_sided else bsdf,
                                color_primvar="displayColor")
        else:
            info = MaterialInfo(bsdf=_grey(double_sided))
    if info.color_primvar and material is not None:
        # A primvar reader feeding diffuseColor: point the attribute texture at the right buffer.
        _, interp = _primvar(prim, info.color_primvar, tc)
        if interp == "uniform":
            _rename_attribute(info.bsdf)
    return info


def _rename_attribute(d: Any) -> None:
    if isinstance(d, dict):
        if d.get("type") == "mesh_attribute" and d.get("name") == "vertex_color":
            d["name"] = "face_color"
        for v in d.values():
            _rename_attribute(v)


def _prepare(prim: Usd.Prim, xform: np.ndarray, time: Usd.TimeCode | float | None):
    if not prim or not prim.IsA(UsdGeom.Mesh):
        raise TranslationError(prim.GetPath() if prim else "<invalid prim>", None, "is not a UsdGeom.Mesh")
    tc = as_timecode(time)
    warns: list[str] = []
    mesh = UsdGeom.Mesh(prim)
    topo = _topology(prim, xform, tc, warns)
    scheme = str(mesh.GetSubdivisionSchemeAttr().Get(tc) or "catmullClark")
    normals = _normals(prim, topo, tc, warns)
    if scheme != "none":
        warns.append(f"{prim.GetPath()}.subdivisionScheme: {scheme!r} is not subdivided; the control "
                     "cage is rendered" + ("" if normals is not None else " with smooth normals"))
        if normals is None:
            normals = _smooth_normals(topo)
    double_sided = bool(mesh.GetDoubleSidedAttr().Get(tc))
    return tc, warns, topo, normals, double_sided


def mesh_shape(prim: Usd.Prim, xform: np.ndarray, time: Usd.TimeCode | float | None = None,
               *, material_cache: dict | None = None) -> tuple[Any, list[str]]:
    """One ``mi.Mesh`` (world space, material attached) for a UsdGeom.Mesh, and warnings.

    ``xform`` is the prim's local-to-world (row-vector) transform computed by the caller.
    Raises :class:`TranslationError` (naming prim and attribute) for invalid topology:
    ``faceVertexCounts`` not summing to the index count, ``faceVertexIndices`` out of range,
    no points or no renderable face.

    ``material_cache``: pass the same (initially empty) dict for every mesh of a scene to
    translate each material once and share its Mitsuba BSDF (and its texture memory) between
    meshes and instances; material warnings are then reported once.
    """
    tc, warns, topo, normals, double_sided = _prepare(prim, xform, time)
    subsets = UsdShade.MaterialBindingAPI(prim).GetMaterialBindSubsets()
    if subsets:
        warns.append(f"{prim.GetPath()}: {len(subsets)} materialBind GeomSubsets ignored by "
                     "mesh_shape (use mesh_shapes for per-face materials)")
    info = _info_for(prim, _bound_material(prim), tc, double_sided, material_cache)
    warns.extend(info.warnings)
    shape = _build(prim, str(prim.GetPath()), topo, None, info, normals, tc, warns)
    return shape, warns


def mesh_shapes(prim: Usd.Prim, xform: np.ndarray, time: Usd.TimeCode | float | None = None,
                *, material_cache: dict | None = None) -> tuple[list[Any], list[str]]:
    """Like :func:`mesh_shape`, but one ``mi.Mesh`` per ``materialBind`` GeomSubset (each with
    its subset's bound material) plus one for the faces no subset claims (the prim's material).
    """
    tc, warns, topo, normals, double_sided = _prepare(prim, xform, time)
    subsets = UsdShade.MaterialBindingAPI(prim).GetMaterialBindSubsets()
    if not subsets:
        info = _info_for(prim, _bound_material(prim), tc, double_sided, material_cache)
        warns.extend(info.warnings)
        return [_build(prim, str(prim.GetPath()), topo, None, info, normals, tc, warns)], warns
    claimed = np.zeros(topo.n_faces, dtype=bool)
    shapes = []
    for subset in subsets:
        idx = np.asarray(subset.GetIndicesAttr().Get(tc) or [], dtype=np.int64)
        idx = idx[(idx >= 0) & (idx < topo.n_faces)]
        faces = np.zeros(topo.n_faces, dtype=bool)
        faces[idx] = True
        faces &= ~claimed  # a face belongs to its first subset
        claimed |= faces
        mask = faces[topo.face_of_tri]
        if not mask.any():
            continue
        info = _info_for(prim, _bound_material(subset.GetPrim()), tc, double_sided, material_cache)
        warns.extend(info.warnings)
        shapes.append(_build(prim, str(subset.GetPath()), topo, mask, info, normals, tc, warns))
    rest = ~claimed[topo.face_of_tri]
    if rest.any():
        info = _info_for(prim, _bound_material(prim), tc, double_sided, material_cache)
        warns.extend(info.warnings)
        shapes.append(_build(prim, str(prim.GetPath()), topo, rest, info, normals, tc, warns))
    return shapes, warns

