"""One error type for a prim value that cannot be used, from the spec readers to the CLI.

:class:`PrimError` names the file, the prim and the attribute and says what was expected, in
one line::

    cloth.usda: /Cloth/Fibers.fiber:dye:molarMass: must be > 0 g/mol with extinctionSource "molar", got 0

The file is the layer holding the strongest opinion of the attribute (else of the prim, else
the stage's root layer), shortened to a relative path under the current directory; it is
left out for in-memory stages. Readers raise it (or a subclass, where callers must tell
errors of one reader apart), and commands print ``str(error)`` and exit 1: nothing re-wraps
it on the way.
"""
from __future__ import annotations

import os
from typing import Any

__all__ = ["PrimError", "layer_path", "short_path"]


def short_path(identifier: str) -> str:
    """``identifier`` relative to the current directory when it is a file below it."""
    try:
        rel = os.path.relpath(identifier)
        return rel if not rel.startswith("..") and os.path.exists(identifier) else identifier
    except ValueError:
        return identifier


def layer_path(prim: Any, attribute: str | None = None) -> str | None:
    """The file holding the strongest opinion of ``prim``'s ``attribute`` (else of the prim,
    else the stage's root layer); None for anonymous (in-memory) layers or no prim."""
    if not prim or not prim.IsValid():
        return None
    layer = None
    prop = prim.GetProperty(attribute) if attribute else None
    if prop:
        stack = prop.GetPropertyStack()
        if stack:
            layer = stack[0].layer
    if layer is None:
        stack = prim.GetPrimStack()
        layer = stack[0].layer if stack else prim.GetStage().GetRootLayer()
    if layer.anonymous:
        return None
    return layer.realPath or layer.identifier


class PrimError(ValueError):
    """A prim's value that cannot be used: ``file``, ``prim`` and ``attribute`` say where,
    ``expected`` what was expected instead (and usually what was found).

    ``str()`` is one line: ``file: prim.attribute: expected`` (file and attribute left out
    when None).
    """

    def __init__(self, file: str | None, prim: str | None, attribute: str | None,
                 expected: str) -> None:
        self.file = file
        self.prim = prim
        self.attribute = attribute
        self.expected = expected
        where = prim or ""
        if attribute:
            where = f"{where}.{attribute}" if where else attribute
        head = ": ".join(x for x in (short_path(file) if file else None, where or None) if x)
        text = str(expected).replace("\n", " ")  # one line
        super().__init__(f"{head}: {text}" if head else text)

    def __reduce__(self) -> tuple:
        # Picklable (worker processes): rebuilt from the four fields, not from the message.
        return (type(self), (self.file, self.prim, self.attribute, self.expected))

    @classmethod
    def at(cls, prim: Any, attribute: str | None, expected: str) -> "PrimError":
        """The error for ``prim`` (a ``Usd.Prim``), its file looked up (:func:`layer_path`)."""
        path = str(prim.GetPath()) if prim else "<invalid prim>"
        return cls(layer_path(prim, attribute), path, attribute, expected)
