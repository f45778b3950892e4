"""Standalone MaterialX documents of fiber looks, validated with MaterialX's ``validate()``.

One ``surfacematerial`` per look: ``chiang_hair_bsdf`` (the fitted inputs) -> ``surface``
-> ``surfacematerial``, named like the USD Materials. :func:`validate_document` checks a
document against the standard data libraries (``MaterialX.loadLibraries``); every document
written is validated first.
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterable

from usdfiber.atomic_file import write_atomic
from usdfiber.translators.materialx.looks import Look
from usdfiber.translators.materialx.usd_material import CHIANG_INPUT_TYPES

__all__ = ["DocumentError", "look_document", "validate_document", "write_document"]


class DocumentError(ValueError):
    """A MaterialX document that does not validate (the message says why, on one line)."""


def _mx():
    import MaterialX as mx
    return mx


def _mx_value(mx, mtype: str, v):
    if mtype == "color3":
        return mx.Color3(*[float(x) for x in v])
    if mtype == "vector2":
        return mx.Vector2(*[float(x) for x in v])
    if mtype == "vector3":
        return mx.Vector3(*[float(x) for x in v])
    return float(v)


def look_document(looks: Iterable[tuple[str, Look]]):
    """A MaterialX document with one material per (name, look)."""
    mx = _mx()
    doc = mx.createDocument()
    for name, look in looks:
        values = look.params.to_materialx()
        bsdf = doc.addNode("chiang_hair_bsdf", f"{name}_bsdf", "BSDF")
        for n, mtype in CHIANG_INPUT_TYPES.items():
            bsdf.setInputValue(n, _mx_value(mx, mtype, values[n]), mtype)
        surf = doc.addNode("surface", f"{name}_surface", "surfaceshader")
        surf.addInput("bsdf", "BSDF").setConnectedNode(bsdf)
        mat = doc.addMaterialNode(name, surf)
        mat.setDocString(f"usdfiber look ({look.kind}): Chiang et al. 2016 fitted to the fiber's tables; "
                         f"relative L2 error per channel " + ", ".join(f"{e:.3f}" for e in look.rel_l2))
    return doc


def validate_document(doc) -> None:
    """Raise DocumentError unless ``doc`` validates against the standard libraries."""
    mx = _mx()
    lib = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), lib)
    check = mx.createDocument()
    check.copyContentFrom(doc)
    check.importLibrary(lib)
    ok, message = check.validate()
    if not ok:
        raise DocumentError("MaterialX validation failed: " + " ".join(message.split()))


def write_document(doc, path: str | Path) -> Path:
    """Validate ``doc`` and write it to ``path`` atomically."""
    mx = _mx()
    validate_document(doc)
    text = mx.writeToXmlString(doc)
    path = Path(path)
    write_atomic(path, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))
    return path
